"""Rig files (``--rig rig.yaml``): the inputs of a run, each with its own config.

Format (YAML): a list of inputs, one per stream, in stream order. Each entry is a mapping with
exactly one of ``euroc: DIR`` (EuRoC / TUM-VI ASL folder), ``images: DIR`` (image folder) or
``bag: PATH`` (ROS 1/2 bag), and optionally:

* ``config: FILE``: its VINS config (without one: the run's CONFIG if given, else an ``euroc``
  input's own ``sensor.yaml``);
* ``camera: CAM``: the camera folder of an ``euroc`` input (``cam0``, ``cam1``; default: the
  run's ``--camera``), so one ASL folder gives several streams;
* ``topic: T``: the image topic of a ``bag`` input (default: ``--topic``, else its config's
  ``image_topic``), so one bag gives several streams;
* ``fps: F``: the frame rate of an ``images`` input (default: ``--fps``).

Relative paths are relative to the rig file's folder. Example (a stereo EuRoC sequence as two
streams, each camera with its own calibration, plus a TUM-VI sequence)::

    - {euroc: MH_01_easy, config: cam0.yaml, camera: cam0}
    - {euroc: MH_01_easy, config: cam1.yaml, camera: cam1}
    - {euroc: dataset-room1_512_16}          # its own mav0/cam0/sensor.yaml

Errors (``ConfigError``; the CLI exits 2) name the rig file, the entry (0-based, ``[i]``) and the
key: an unknown key (with the closest known one), no or two input kinds, a value of the wrong type,
a missing input or config file.
"""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any, List, Optional, Tuple, Union

from ..errors import ConfigError

__all__ = ["RIG_KEYS", "RIG_KINDS", "read_rig"]

#: the input kinds of an entry (one per entry) and the other keys it may hold
RIG_KINDS = ("euroc", "images", "bag", "kitti")
RIG_KEYS = (*RIG_KINDS, "config", "camera", "topic", "fps")
#: the kind each per-input reader option belongs to
_OPTION_KIND = {"camera": "euroc", "topic": "bag", "fps": "images"}

PathLike = Union[str, Path]


def _path(rig: Path, value: Any, key: str, i: int) -> Path:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"expected a path, got {value!r}", rig, f"[{i}].{key}")
    p = Path(value).expanduser()
    return p if p.is_absolute() else rig.parent / p


def read_rig(path: PathLike) -> Tuple[List[Tuple[str, str, dict]], List[Optional[Path]]]:
    """The inputs of a rig file (module docstring): ``(sources, configs)``, per entry the source
    ``(kind, path, options)`` (``pipelines.inputs``; ``options`` the entry's ``camera`` / ``topic``
    / ``fps``) and its config file (None: the entry gives none).

    Raises:
        ConfigError: an unreadable rig file or a bad entry (module docstring).
    """
    import yaml

    rig = Path(path)
    if not rig.is_file():
        raise ConfigError("rig file not found" if not rig.exists() else "not a file", rig)
    try:
        data = yaml.safe_load(rig.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read: {getattr(exc, 'strerror', None) or exc}", rig) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise ConfigError(f"not valid YAML{where}: {getattr(exc, 'problem', None) or exc}", rig) from None
    if not isinstance(data, list) or not data:
        got = "an empty file" if data is None or data == [] else f"a {type(data).__name__}"
        raise ConfigError(f"expected a list of inputs (e.g. '- {{euroc: DIR, config: FILE}}'), got {got}", rig)
    sources: List[Tuple[str, str, dict]] = []
    configs: List[Optional[Path]] = []
    for i, entry in enumerate(data):
        if not isinstance(entry, dict):
            raise ConfigError(f"expected a mapping such as {{euroc: DIR, config: FILE}}, got {entry!r}", rig, f"[{i}]")
        for key in entry:
            if key not in RIG_KEYS:
                near = difflib.get_close_matches(str(key), RIG_KEYS, n=1)
                hint = f"; did you mean '{near[0]}'?" if near else ""
                raise ConfigError(f"unknown key (expected {', '.join(RIG_KEYS)}){hint}", rig, f"[{i}].{key}")
        kinds = [k for k in RIG_KINDS if k in entry]
        if len(kinds) != 1:
            raise ConfigError(f"expected exactly one input kind ({' / '.join(RIG_KINDS)}), got "
                              f"{', '.join(kinds) or 'none'}", rig, f"[{i}]")
        kind = kinds[0]
        src = _path(rig, entry[kind], kind, i)
        if not src.exists():
            raise ConfigError(f"input not found: {src}", rig, f"[{i}].{kind}")
        options: dict = {}
        for key, owner in _OPTION_KIND.items():
            if key not in entry:
                continue
            if kind != owner:
                raise ConfigError(f"'{key}' goes with {owner} inputs, not {kind}", rig, f"[{i}].{key}")
            value = entry[key]
            if key == "fps":
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
                    raise ConfigError(f"expected a finite frame rate > 0 (Hz), got {value!r}", rig, f"[{i}].fps")
                value = float(value)
            elif not isinstance(value, str) or not value.strip():
                raise ConfigError(f"expected a name, got {value!r}", rig, f"[{i}].{key}")
            options[key] = value
        cfg = None
        if entry.get("config") is not None:
            cfg = _path(rig, entry["config"], "config", i)
            if not cfg.is_file():
                raise ConfigError(f"config file not found: {cfg}", rig, f"[{i}].config")
        elif "config" in entry:
            raise ConfigError("expected a config file, got nothing (leave the key out for the default)", rig,
                              f"[{i}].config")
        sources.append((kind, str(src), options))
        configs.append(cfg)
    return sources, configs
