"""EuRoC / TUM-VI "ASL" folders: ``mav0/cam0/data.csv`` + ``mav0/cam0/data/*.png`` + ``sensor.yaml``.

Convention:
    ``data.csv`` rows are ``timestamp [ns], filename`` (``#`` lines are comments); timestamps are
    integer nanoseconds and are kept exact (``Frame.stamp_ns``). The folder given may be the
    sequence root (holding ``mav0/``), ``mav0/`` itself, or the camera folder (holding
    ``data.csv``). Rows are kept in file order (VINS sees them in that order; the tracker
    handles time going backwards as a restart).

    The camera folder's ``sensor.yaml`` (Kalibr/ASL format) gives the camera for runs without a
    VINS config file: ``euroc_config`` reads it with ``torch_frontend.config.config_from_sensor_yaml``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, List, Tuple, Union

from ..config import TrackerConfig, config_from_sensor_yaml
from .frames import DataError, Sequence, _Item, read_image

PathLike = Union[str, Path]


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


def euroc_config(root: PathLike, camera: str = "cam0", **overrides) -> TrackerConfig:
    """``config_from_sensor_yaml`` of the ``sensor.yaml`` of an ASL folder's camera (``root`` as
    for ``EurocSequence``; ``overrides``: ``TrackerConfig`` fields)."""
    d = find_camera_dir(root, camera)
    y = d / "sensor.yaml"
    if not y.is_file():
        raise DataError(f"{d}: no sensor.yaml (give a VINS config file instead)")
    return config_from_sensor_yaml(y, **overrides)


__all__ = [
    "EurocSequence",
    "euroc_config",
    "find_camera_dir",
]
