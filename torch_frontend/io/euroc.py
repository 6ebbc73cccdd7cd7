"""EuRoC / TUM-VI "ASL" folders: ``mav0/cam0/data.csv`` + ``mav0/cam0/data/*.png`` + ``sensor.yaml``.

Convention:
    ``data.csv`` rows are ``timestamp [ns], filename`` (``#`` lines are comments); timestamps are
    integer nanoseconds and are kept exact (``Frame.stamp_ns``). The folder given may be the
    sequence root (holding ``mav0/``), ``mav0/`` itself, or the camera folder (holding
    ``data.csv``). Rows are kept in file order (VINS sees them in that order; the tracker
    handles time going backwards as a restart).

    ``sensor.yaml`` (Kalibr/ASL format) gives ``resolution: [W, H]``, ``intrinsics: [fu, fv, cu,
    cv]`` and ``distortion_model`` + ``distortion_coefficients``: ``radial-tangential`` ``[k1, k2,
    p1, p2]`` → ``PinholeCamera``; ``equidistant`` ``[k1..k4]`` (TUM-VI) → ``KannalaBrandtCamera``
    with camodocal ``k2..k5 = k1..k4``. ``config_from_sensor_yaml`` wraps it in a ``TrackerConfig``
    with VINS's EuRoC front-end settings, for runs without a VINS config file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, List, Tuple, Union

from ..errors import ConfigError
from .frames import DataError, Sequence, _Item, read_image
from .fsyaml import read_opencv_yaml

PathLike = Union[str, Path]

# VINS-Mono's euroc_config.yaml front-end values, used when only sensor.yaml is given.
DEFAULT_FRONTEND = dict(max_cnt=150, min_dist=30, freq=10, F_threshold=1.0, equalize=True, fisheye=False)


def find_camera_dir(root: PathLike, camera: str = "cam0") -> Path:
    """The camera folder (holding ``data.csv``) of an ASL sequence, or ``DataError``."""
    r = Path(root)
    if not r.exists():
        raise DataError(f"{r}: folder not found")
    if not r.is_dir():
        raise DataError(f"{r}: not a folder (expected an EuRoC/ASL sequence folder)")
    for cand in (r / "mav0" / camera, r / camera, r):
        if (cand / "data.csv").is_file():
            return cand
    raise DataError(f"{r}: not an EuRoC/ASL folder (no mav0/{camera}/data.csv, {camera}/data.csv or data.csv)")


def _read_csv(path: Path) -> List[Tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DataError(f"{path}: cannot read: {exc.strerror or exc}") from None
    rows: List[Tuple[int, str]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) < 2 or not parts[1]:
            raise DataError(f"{path}:{lineno}: expected 'timestamp [ns],filename', got {s!r}")
        try:
            stamp = int(parts[0])
        except ValueError:
            raise DataError(f"{path}:{lineno}: timestamp is not an integer number of ns: {parts[0]!r}") from None
        rows.append((stamp, parts[1]))
    return rows


class EurocSequence(Sequence):
    """Frames of one camera of an EuRoC / TUM-VI ASL folder.

    Args:
        root: sequence root, ``mav0`` or the camera folder.
        camera: ``"cam0"`` (default) or ``"cam1"``.
        skip_bad: skip unreadable frames instead of raising (recorded in ``skipped``).

    Raises:
        DataError: missing folder, no ``data.csv``, malformed row, or no frames at all.
    """

    kind = "euroc"

    def __init__(self, root: PathLike, camera: str = "cam0", skip_bad: bool = False):
        self.root = Path(root)
        self.camera_dir = find_camera_dir(root, camera)
        super().__init__(f"{self.root.resolve().name}/{camera}", skip_bad)
        self.rows = _read_csv(self.camera_dir / "data.csv")
        if not self.rows:
            raise DataError(f"{self.camera_dir / 'data.csv'}: empty sequence (no frames listed)")
        self.data_dir = self.camera_dir / "data"

    def __len__(self) -> int:
        return len(self.rows)

    def _items(self) -> Iterator[_Item]:
        for i, (stamp, fname) in enumerate(self.rows):
            path = self.data_dir / fname
            yield _Item(i, stamp, str(path), lambda p=path: read_image(p))

    @property
    def sensor_yaml(self) -> Path:
        return self.camera_dir / "sensor.yaml"


def _numbers(raw: dict, key: str, n: int, path: Path) -> List[float]:
    v = raw.get(key)
    try:
        vals = [float(x) for x in v]
    except TypeError:
        raise ConfigError(f"expected a list of {n} numbers, got {v!r}", path, key) from None
    except ValueError:
        raise ConfigError(f"expected numbers, got {v!r}", path, key) from None
    if len(vals) != n:
        raise ConfigError(f"expected {n} numbers, got {len(vals)}", path, key)
    return vals


def camera_from_sensor_yaml(path: PathLike):
    """Camera model of an ASL ``sensor.yaml`` (see the module docstring).

    Raises:
        ConfigError: missing file or key, wrong list length, unsupported camera or distortion model.
    """
    from ..camera import KannalaBrandtCamera, PinholeCamera

    p = Path(path)
    raw = read_opencv_yaml(p)
    model = str(raw.get("camera_model", "pinhole")).lower()
    if model != "pinhole":
        raise ConfigError(f"unsupported camera_model {model!r} (expected 'pinhole')", p, "camera_model")
    w, h = (int(x) for x in _numbers(raw, "resolution", 2, p))
    fu, fv, cu, cv = _numbers(raw, "intrinsics", 4, p)
    dist = str(raw.get("distortion_model", "radial-tangential")).lower()
    name = str(raw.get("comment", p.parent.name))
    if dist in ("radial-tangential", "radtan", "plumb_bob"):
        k1, k2, p1, p2 = _numbers(raw, "distortion_coefficients", 4, p)
        return PinholeCamera(k1, k2, p1, p2, fu, fv, cu, cv, width=w, height=h, camera_name=name)
    if dist in ("equidistant", "fisheye"):
        k1, k2, k3, k4 = _numbers(raw, "distortion_coefficients", 4, p)
        return KannalaBrandtCamera(k1, k2, k3, k4, fu, fv, cu, cv, width=w, height=h, camera_name=name)
    raise ConfigError(
        f"unsupported distortion_model {dist!r} (expected 'radial-tangential' or 'equidistant')", p, "distortion_model"
    )


def config_from_sensor_yaml(path: PathLike, **overrides):
    """A ``TrackerConfig`` from an ASL ``sensor.yaml``: its camera and size, and VINS-Mono's EuRoC
    front-end settings (``max_cnt 150, min_dist 30, freq 10, F_threshold 1, equalize 1``) unless
    overridden by keyword."""
    from ..config import TrackerConfig

    cam = camera_from_sensor_yaml(path)
    settings = dict(DEFAULT_FRONTEND)
    settings.update(overrides)
    return TrackerConfig(
        path=str(path),
        flavour="mono",
        image_width=int(cam.width),
        image_height=int(cam.height),
        camera=cam,
        **settings,
    )


def euroc_config(root: PathLike, camera: str = "cam0", **overrides):
    """``config_from_sensor_yaml`` of the ``sensor.yaml`` of an ASL folder's camera."""
    d = find_camera_dir(root, camera)
    y = d / "sensor.yaml"
    if not y.is_file():
        raise DataError(f"{d}: no sensor.yaml (give a VINS config file instead)")
    return config_from_sensor_yaml(y, **overrides)


def euroc_camera(root: PathLike, camera: str = "cam0"):
    """The camera model of an ASL folder's ``sensor.yaml``."""
    return euroc_config(root, camera).camera


__all__ = [
    "EurocSequence",
    "camera_from_sensor_yaml",
    "config_from_sensor_yaml",
    "euroc_camera",
    "euroc_config",
    "find_camera_dir",
]
