"""Reader for OpenCV ``FileStorage`` YAML as VINS and camodocal ship it.

OpenCV's dialect is not plain YAML (see the spec §1.1): the first line is ``%YAML:1.0`` (PyYAML
rejects it), matrices are tagged ``!!opencv-matrix`` with ``rows``/``cols``/``dt``/``data``, and
OpenCV reads ``1e-3`` as a number where PyYAML's YAML 1.1 resolver reads a string. This module
strips the header, turns matrices into numpy arrays of the right shape and dtype, and coerces
number-like strings. A key given twice in one map is a ``ConfigError`` naming the key and both
lines: PyYAML would keep the last value and ``cv2.FileStorage`` keeps the first (measured with
OpenCV 4.x), so the file means different things to different readers.

:func:`format_opencv_yaml` writes the dialect back (``calibration``: configs from calibration
files): the header, ``!!opencv-matrix`` blocks, nested maps indented by 3 spaces, floats as the
shortest text that reads back to the same double.

A foundation module (numpy and PyYAML only): ``config`` and ``camera`` read their files with it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Dict, Union

import numpy as np
import yaml

from .errors import ConfigError

_DT = {"d": np.float64, "f": np.float32, "i": np.int32, "u": np.uint8, "s": np.int16, "w": np.uint16, "c": np.int8}
_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


class _DuplicateKey(Exception):
    """A key given twice in one mapping (turned into a ``ConfigError`` naming the file)."""

    def __init__(self, key: str, first_line: int, second_line: int):
        super().__init__(key)
        self.key, self.first_line, self.second_line = key, first_line, second_line


class _Loader(yaml.SafeLoader):
    def construct_mapping(self, node, deep=False):
        # PyYAML silently keeps the last of two equal keys: refuse them (0-based lines of the body)
        if isinstance(node, yaml.MappingNode):
            seen: Dict[Any, int] = {}
            for key_node, _ in node.value:
                if not isinstance(key_node, yaml.ScalarNode):
                    continue
                key = key_node.value
                if key in seen:
                    raise _DuplicateKey(str(key), seen[key], key_node.start_mark.line)
                seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def _construct_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> Dict[str, Any]:
    mapping = loader.construct_mapping(node, deep=True)
    return {"__opencv_matrix__": True, **mapping}


_Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", _construct_matrix)
_Loader.add_constructor("!opencv-matrix", _construct_matrix)


def _coerce(value: Any, path: str, key: str) -> Any:
    if isinstance(value, dict):
        if value.get("__opencv_matrix__"):
            return _matrix(value, path, key)
        return {k: _coerce(v, path, f"{key}.{k}" if key else str(k)) for k, v in value.items()}
    if isinstance(value, list):
        return [_coerce(v, path, key) for v in value]
    if isinstance(value, str) and _NUMBER.match(value.strip()):
        s = value.strip()
        return int(s) if re.fullmatch(r"[+-]?\d+", s) else float(s)
    return value


def _matrix(node: Dict[str, Any], path: str, key: str) -> np.ndarray:
    try:
        rows, cols = int(node["rows"]), int(node["cols"])
        data = [float(_coerce(v, path, key)) for v in node["data"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"malformed !!opencv-matrix (need rows, cols, data): {exc}", path, key) from None
    dtype = _DT.get(str(node.get("dt", "d"))[:1], np.float64)
    if len(data) != rows * cols:
        raise ConfigError(f"!!opencv-matrix has {len(data)} values, expected rows*cols = {rows * cols}", path, key)
    return np.asarray(data, dtype=np.float64).astype(dtype).reshape(rows, cols)


def read_opencv_yaml(path: Union[str, Path]) -> Dict[str, Any]:
    """Read an OpenCV FileStorage YAML file into a dict.

    Matrices become ``numpy.ndarray`` of shape ``(rows, cols)`` and their ``dt`` dtype; number-like
    strings such as ``1e-3`` become floats. Raises ``ConfigError`` naming the file when it is
    missing or not parseable.
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError("file not found" if not p.exists() else "not a file", p)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc}", p) from None
    lines = text.splitlines()
    # OpenCV's own header: '%YAML:1.0' (or '%YAML 1.0'); PyYAML rejects the colon form.
    skipped = 0
    if lines and lines[0].lstrip().startswith("%YAML"):
        lines, skipped = lines[1:], 1
    body = "\n".join(lines)
    try:
        docs = [d for d in yaml.load_all(body, Loader=_Loader) if d is not None]
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid OpenCV YAML: {exc}", p) from None
    except _DuplicateKey as dup:
        a, b = dup.first_line + 1 + skipped, dup.second_line + 1 + skipped  # 1-based lines of the file
        raise ConfigError(f"given twice, on line {a} and line {b} (cv2.FileStorage would keep the first value, "
                          f"PyYAML the last); keep one", p, dup.key) from None
    if not docs:
        return {}
    data = docs[0]
    if not isinstance(data, dict):
        raise ConfigError(f"expected a mapping at the top level, got {type(data).__name__}", p)
    return _coerce(data, str(p), "")


# ----------------------------------------------------------------------------------------------
# writing


def _scalar(value: Any, key: str) -> str:
    """One value as FileStorage writes it: ints, floats (the shortest text that reads back to the
    same double), double-quoted strings; bools as 0/1 (VINS's flags)."""
    if isinstance(value, (bool, np.bool_)):
        return str(int(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if not np.isfinite(v):
            raise ValueError(f"{key}: expected a finite number, got {v!r}")
        return repr(v)
    if isinstance(value, str):
        if any(c in value for c in '"\\\n'):
            raise ValueError(f"{key}: a string with a quote, backslash or newline cannot be written, got {value!r}")
        # an upper-case identifier (model_type: PINHOLE) bare, as VINS's files write it; others quoted
        return value if re.fullmatch(r"[A-Z][A-Z0-9_]*", value) else f'"{value}"'
    raise ValueError(f"{key}: cannot write a {type(value).__name__} ({value!r})")


def _matrix_lines(m: np.ndarray, key: str) -> list:
    a = np.asarray(m, dtype=np.float64)
    if a.ndim == 1:
        a = a.reshape(-1, 1)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"{key}: expected a non-empty 2-D matrix, got shape {np.shape(m)}")
    rows = [", ".join(_scalar(float(v), key) for v in row) for row in a]
    data = ("data: [" + (",\n       ".join(rows)) + "]").splitlines()
    return [f"   rows: {a.shape[0]}", f"   cols: {a.shape[1]}", "   dt: d"] + [("   " + ln) for ln in data]


def format_opencv_yaml(entries, header=()) -> str:
    """The text of an OpenCV FileStorage YAML file (what ``cv2.FileStorage`` and
    :func:`read_opencv_yaml` read back to the same values).

    Args:
        entries: in order, each ``(key, value)`` or ``(key, value, comment)``, or a string: a
            comment line (``""``: a blank line). A value is an int, float (written as the
            shortest text that reads back to the same double), bool (0/1), str (double-quoted),
            a ``numpy`` 2-D array (``!!opencv-matrix``, ``dt: d``, one row per line) or a dict of
            such scalars (a nested map, indented by 3 spaces as VINS's files are).
        header: comment lines after ``%YAML:1.0``.

    Raises:
        ValueError: a value that cannot be written (not finite, an unknown type), naming its key.
    """
    lines = ["%YAML:1.0"] + [f"# {h}" if h else "#" for h in header] + ([""] if header else [])
    for e in entries:
        if isinstance(e, str):
            lines.append(f"# {e}" if e else "")
            continue
        key, value = e[0], e[1]
        comment = f"   # {e[2]}" if len(e) > 2 and e[2] else ""
        if isinstance(value, np.ndarray):
            lines.append(f"{key}: !!opencv-matrix{comment}")
            lines += _matrix_lines(value, key)
        elif isinstance(value, dict):
            lines.append(f"{key}:{comment}")
            lines += [f"   {k}: {_scalar(v, f'{key}.{k}')}" for k, v in value.items()]
        else:
            lines.append(f"{key}: {_scalar(value, key)}{comment}")
    return "\n".join(lines) + "\n"
