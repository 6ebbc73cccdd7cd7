"""A plain folder of images (``*.png``, ``*.jpg``, ...), one camera.

Convention:
    Timestamps, in this order of precedence:

    * ``fps`` given (a finite rate > 0): frame ``i`` (in name order) is at ``i / fps`` seconds;
    * every file name (without suffix) is a number: integers with 16 or more digits are
      nanoseconds (EuRoC-style names such as ``1403715273262142976.png``), names with a decimal
      point are seconds (TUM RGB-D style ``1305031102.175304.png``); frames are ordered by that
      time. Shorter integer names are nanoseconds too when that is the one plausible reading: at
      least two distinct names whose median spacing, in nanoseconds, is a camera's frame rate
      (``PLAUSIBLE_FPS``; ``1000000000.png, 1050000000.png, ...`` are 20 Hz from 1 s). Frame
      numbers (``000001.png``: 1 ns apart would be 1 GHz) are not times: give ``fps``.
    * otherwise: ``DataError`` asking for ``fps``; it names the file that is not a time when the
      other names are (a stray ``mask.png`` among the frames).

    Without numeric times, files are ordered by name (plain string sort, so zero-pad numbers).
"""

from __future__ import annotations

import math
import numbers
import re
import statistics
from decimal import Decimal
from pathlib import Path
from typing import Iterator, List, Optional, Tuple, Union

from .frames import IMAGE_SUFFIXES, DataError, Sequence, _Item, read_image

PathLike = Union[str, Path]
_NS_NAME = re.compile(r"^\d{16,}$")
_INT_NAME = re.compile(r"^\d+$")
_SECONDS_NAME = re.compile(r"^\d+\.\d+$")
#: frame rates (Hz) that make integer names shorter than 16 digits nanoseconds (see the module
#: docstring): wide on purpose, frame numbers would need a spacing of 10^5 to reach it
PLAUSIBLE_FPS = (0.01, 10_000.0)
_NAME_HELP = "need nanoseconds, e.g. 1403715273262142976.png, or seconds, e.g. 1305031102.175304.png"


def _kind(stem: str) -> str:
    return "integer" if _INT_NAME.match(stem) else ("seconds" if _SECONDS_NAME.match(stem) else "other")


def _stamps_from_names(folder: Path, files: List[Path]) -> Tuple[Optional[List[int]], str]:
    """Integer nanoseconds from the names, or ``(None, why not)``."""
    stems = [f.stem for f in files]
    kinds = [_kind(s) for s in stems]
    if len(set(kinds)) > 1:
        # one kind of time name for most files: blame the first file that is not one
        major = max(("integer", "seconds"), key=kinds.count)
        if kinds.count(major) * 2 > len(kinds):
            i = next(i for i, k in enumerate(kinds) if k != major)
            j = kinds.index(major)
            return None, (f"{folder}: {files[i].name!r} is not a time like the other names (e.g. {files[j].name!r}): "
                          f"move it out of the folder, or give a frame rate (`fps`)")
    if kinds[0] == "seconds" and all(k == "seconds" for k in kinds):
        return [int(Decimal(s) * 1_000_000_000) for s in stems], ""
    if kinds[0] == "integer" and all(k == "integer" for k in kinds):
        stamps = [int(s) for s in stems]
        long_names = [bool(_NS_NAME.match(s)) for s in stems]
        if all(long_names):
            return stamps, ""
        if sum(long_names) * 2 > len(stems):  # a stray short number among nanosecond names
            i, j = long_names.index(False), long_names.index(True)
            return None, (f"{folder}: {files[i].name!r} is not a time like the other names (e.g. {files[j].name!r}, "
                          f"nanoseconds): move it out of the folder, or give a frame rate (`fps`)")
        distinct = sorted(set(stamps))
        if len(distinct) < 2:
            return None, (f"{folder}: cannot tell whether the integer name {files[0].name!r} is a time or a frame "
                          f"number; give a frame rate (`fps`)")
        spacing = statistics.median(b - a for a, b in zip(distinct, distinct[1:]))
        rate = 1e9 / spacing
        if PLAUSIBLE_FPS[0] <= rate <= PLAUSIBLE_FPS[1]:
            return stamps, ""
        return None, (f"{folder}: integer names like {files[0].name!r}, spaced by {spacing:g}, do not look like "
                      f"times (as nanoseconds: {rate:.3g} Hz; frame numbers?); give a frame rate (`fps`)")
    return None, f"{folder}: cannot take timestamps from names like {files[0].name!r} ({_NAME_HELP}); give a frame rate (`fps`)"


class ImageFolderSequence(Sequence):
    """Images of one folder, in time (or name) order.

    Args:
        folder: the folder.
        fps: frame rate; sets timestamps ``i / fps`` (required unless names are times).
        skip_bad: skip unreadable images instead of raising.

    Raises:
        DataError: missing or unreadable folder, no images, names that are not times and no
            ``fps``, an ``fps`` that is not a finite number > 0.
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
        try:
            names = list(d.iterdir())
        except OSError as exc:  # e.g. no read permission: a reading problem, not the output's
            raise DataError(f"{d}: cannot read folder: {exc.strerror or exc}") from None
        files = sorted(f for f in names if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith("."))
        if not files:
            raise DataError(f"{d}: empty sequence (no {'/'.join(s[1:] for s in IMAGE_SUFFIXES)} images)")
        if fps is not None:
            if isinstance(fps, bool) or not isinstance(fps, numbers.Real):
                raise DataError(f"fps: expected a frame rate > 0 (Hz), got {type(fps).__name__} {fps!r}")
            if not fps > 0 or not math.isfinite(fps):
                # inf would put every frame at 0 s (and the tracker would publish nothing)
                raise DataError(f"fps: expected a frame rate > 0 (Hz), got {fps}"
                                + (" (not a finite number)" if fps > 0 else ""))
            stamps = [round(i * 1e9 / fps) for i in range(len(files))]
        else:
            stamps, why = _stamps_from_names(d, files)
            if stamps is None:
                raise DataError(why)
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
