"""``torch-frontend config``: a VINS config written from calibration files
(:func:`run_make_config`; the conversion is ``torch_frontend.calibration``).

Convention:
    ``out`` is the main file; a two-camera (VINS-Fusion) config adds ``<stem>_cam0.yaml`` and
    ``<stem>_cam1.yaml`` beside it. The files are first written into a temporary folder and loaded
    there with ``config.load_config`` (the project's camera factory), then each is written
    atomically (``_atomic.write_text_atomic``) under its name. A file that exists is replaced only
    when ``torch-frontend config`` wrote it (its header says so, ``calibration.WRITTEN_BY``);
    anything else is an ``OptionError`` naming it, and nothing is written. Folders made for
    ``out`` are removed again, while empty, when the run fails.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

from .common import OptionError

PathLike = Union[str, Path]

__all__ = ["run_make_config"]


def _ours(path: Path) -> bool:
    """Whether ``path`` is a file ``torch-frontend config`` wrote (its first lines say so)."""
    from ..calibration import WRITTEN_BY

    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            head = [fh.readline() for _ in range(3)]
    except OSError:
        return False
    return any(WRITTEN_BY in line for line in head)


def run_make_config(out: PathLike, *, kalibr: Optional[PathLike] = None, camera_info: Optional[PathLike] = None,
                    imu: Optional[PathLike] = None) -> Dict[str, Any]:
    """Write the VINS config of a calibration into ``out`` (module docstring).

    Args:
        out: the main config file (``.yaml``).
        kalibr: Kalibr's ``camchain.yaml`` or ``camchain-imucam.yaml`` (one or two cameras).
        camera_info: instead, a ROS ``camera_info`` YAML (one camera, no extrinsic).
        imu: Kalibr's ``imu.yaml``: VINS's IMU noise keys and ``imu_topic``.

    Returns:
        A summary: ``files`` (the paths written, the main file first), ``flavour`` (``"mono"`` /
        ``"fusion"``), ``cameras`` (``[{name, model_type, width, height}]``), ``extrinsic`` (where
        it came from, or None), ``imu`` (the imu.yaml, or None), ``settings`` (the loaded config's
        ``settings_line``).

    Raises:
        OptionError: not exactly one of ``kalibr`` / ``camera_info``; ``out`` (or a camera file
            beside it) exists and was not written by ``torch-frontend config``, or is a folder.
        ConfigError: a calibration file is missing or malformed, or names a model camodocal lacks
            (``calibration``).
    """
    from .. import calibration as cal
    from .._atomic import make_folders, remove_empty_folders, write_text_atomic
    from ..config import load_config

    if (kalibr is None) == (camera_info is None):
        raise OptionError("kalibr", "kalibr: give one calibration: a Kalibr camchain (`kalibr`) or a ROS camera_info "
                                    "YAML (`camera_info`)")
    out = Path(out)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise OptionError("out", f"out: expected a .yaml file name for the VINS config, got {str(out)!r}")
    if kalibr is not None:
        cams = cal.read_kalibr_camchain(kalibr)
        sources = [Path(kalibr).name]
    else:
        cams = [cal.read_camera_info(camera_info)]
        sources = [Path(camera_info).name]
    noise = None
    if imu is not None:
        noise = cal.read_kalibr_imu(imu)
        sources.append(Path(imu).name)
    files = cal.vins_config_files(cams, out.name, noise, sources)
    targets = [out.parent / name for name in files]
    for t in targets:
        if t.is_dir() or (t.exists() and not _ours(t)):
            raise OptionError("out", f"out: {t} exists and was not written by torch-frontend config: nothing written "
                                     f"(give another `out`, or remove it)")
    # load the files where nothing else is, with the project's loader (its camera factory): a
    # config it refuses is never written
    with tempfile.TemporaryDirectory(prefix="tf-config-") as tmp:
        for name, text in files.items():
            (Path(tmp) / name).write_text(text, encoding="utf-8")
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a key the loader does not know would be a bug here
            load_config(Path(tmp) / out.name)
    created = make_folders(out.parent)
    try:
        for t, text in zip(targets, files.values()):
            write_text_atomic(t, text)
    except BaseException:
        remove_empty_folders(created)
        raise
    cfg = load_config(out)
    extrinsic = None
    if cams[0].T_imu_cam is not None:
        extrinsic = "T_cam_imu (inverted: body <- camera)"
    elif len(cams) == 2:
        extrinsic = "T_cn_cnm1 (inverted: cam0 <- cam1; body = cam0)"
    return {
        "files": [str(t) for t in targets],
        "flavour": cfg.flavour,
        "cameras": [dict(name=c.name, model_type=c.model_type, width=c.width, height=c.height) for c in cams],
        "extrinsic": extrinsic,
        "imu": None if imu is None else str(imu),
        "settings": cfg.settings_line(),
    }


def format_make_config(s: Dict[str, Any]) -> str:
    """The lines ``torch-frontend config`` prints (``s``: :func:`run_make_config`'s summary)."""
    cams = ", ".join(f"{c['name']} {c['model_type']} {c['width']}x{c['height']}" for c in s["cameras"])
    lines: List[str] = [
        f"written       {', '.join(s['files'])}",
        f"VINS          {'VINS-Mono' if s['flavour'] == 'mono' else 'VINS-Fusion'}: {cams}",
        f"extrinsic     {s['extrinsic'] or 'none in the calibration (estimate_extrinsic 2: VINS calibrates it)'}",
        f"IMU noise     {s['imu'] or 'none given (--imu imu.yaml): VINS EuRoC values'}",
        s["settings"],
    ]
    return "\n".join(lines)
