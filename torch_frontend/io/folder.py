"""A plain folder of images (``*.png``, ``*.jpg``, ...), one camera.

Convention:
    Timestamps, in this order of precedence:

    * ``fps`` given: frame ``i`` (in name order) is at ``i / fps`` seconds;
    * every file name (without suffix) is a number: integers with 16 or more digits are
      nanoseconds (EuRoC-style names such as ``1403715273262142976.png``), names with a decimal
      point are seconds (TUM RGB-D style ``1305031102.175304.png``); frames are ordered by that
      time. Short integer names (``000001.png``) are frame numbers, not times: give ``fps``.
    * otherwise: ``DataError`` asking for ``fps``.

    Without numeric times, files are ordered by name (plain string sort, so zero-pad numbers).
"""

from __future__ import annotations

import re
from decimal import Decimal
from pathlib import Path
from typing import Iterator, List, Tuple, Union

from .frames import IMAGE_SUFFIXES, DataError, Sequence, _Item, read_image

PathLike = Union[str, Path]
_NS_NAME = re.compile(r"^\d{16,}$")
_SECONDS_NAME = re.compile(r"^\d+\.\d+$")


def _stamps_from_names(files: List[Path]) -> List[int] | None:
    stems = [f.stem for f in files]
    if all(_NS_NAME.match(s) for s in stems):
        return [int(s) for s in stems]
    if all(_SECONDS_NAME.match(s) for s in stems):
        return [int(Decimal(s) * 1_000_000_000) for s in stems]
    return None


class ImageFolderSequence(Sequence):
    """Images of one folder, in time (or name) order.

    Args:
        folder: the folder.
        fps: frame rate; sets timestamps ``i / fps`` (required unless names are times).
        skip_bad: skip unreadable images instead of raising.

    Raises:
        DataError: missing folder, no images, names that are not times and no ``fps``, ``fps <= 0``.
    """

    kind = "images"

    def __init__(self, folder: PathLike, fps: float | None = None, skip_bad: bool = False):
        d = Path(folder)
        if not d.exists():
            raise DataError(f"{d}: folder not found")
        if not d.is_dir():
            raise DataError(f"{d}: not a folder (expected a folder of images)")
        super().__init__(d.resolve().name, skip_bad)
        self.folder = d
        files = sorted(f for f in d.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith("."))
        if not files:
            raise DataError(f"{d}: empty sequence (no {'/'.join(s[1:] for s in IMAGE_SUFFIXES)} images)")
        if fps is not None:
            if not fps > 0:
                raise DataError(f"fps: expected a frame rate > 0 (Hz), got {fps}")
            stamps = [round(i * 1e9 / fps) for i in range(len(files))]
        else:
            stamps = _stamps_from_names(files)
            if stamps is None:
                raise DataError(
                    f"{d}: cannot take timestamps from names like {files[0].name!r} (need nanoseconds, "
                    f"e.g. 1403715273262142976.png, or seconds, e.g. 1305031102.175304.png); give a frame rate (fps)"
                )
            order = sorted(range(len(files)), key=lambda i: (stamps[i], files[i].name))
            files = [files[i] for i in order]
            stamps = [stamps[i] for i in order]
        self.entries: List[Tuple[int, Path]] = list(zip(stamps, files))

    def __len__(self) -> int:
        return len(self.entries)

    def _items(self) -> Iterator[_Item]:
        for i, (stamp, path) in enumerate(self.entries):
            yield _Item(i, stamp, str(path), lambda p=path: read_image(p))


__all__ = ["ImageFolderSequence"]
