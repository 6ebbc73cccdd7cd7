"""Frames, sequences and image decoding shared by the dataset readers.

Convention:
    A ``Sequence`` is an ordered, lazily decoded list of grey frames of one camera. Iterating it
    yields ``Frame`` objects: ``image (H, W)`` uint8 numpy, ``stamp_ns`` int (nanoseconds, exact)
    and ``timestamp`` float64 seconds (``stamp_ns * 1e-9``, what the tracker takes). A frame that
    cannot be read (missing, truncated or corrupt file, undecodable message) raises ``DataError``
    naming the file or message (iterating a ``Sequence``: ``BadFrameError``, a ``DataError`` that
    names ``skip_bad``); with ``skip_bad=True`` it is skipped instead and recorded in
    ``Sequence.skipped`` as ``(source, reason)``.

    Colour images become grey with OpenCV's BGR→grey weights, with one ``DataWarning`` per pass
    over a sequence that has them (a note: the tracker works on grey images); 16-bit images are
    reduced to 8 bits by dropping the low byte (``>> 8``), the usual mono16→mono8 rule.
"""

from __future__ import annotations

import contextvars
import dataclasses
import struct
import warnings
import zlib
from pathlib import Path
from typing import Callable, Iterator, List, Tuple

import numpy as np

from ..errors import (
    BadFrameError,
    DataError,  # noqa: F401  (re-exported)
    DataWarning,
)

# set by ``to_gray_u8`` when it converts a colour frame (what it had), read by ``Sequence.__iter__``
# around each frame's decoding to note the conversion once (a context variable: safe in threads)
_COLOUR: contextvars.ContextVar = contextvars.ContextVar("torch_frontend_colour_frame", default=None)

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")



@dataclasses.dataclass
class Frame:
    """One decoded image of a sequence.

    Attributes:
        index: position in the sequence (0-based, counting skipped frames too).
        stamp_ns: timestamp in integer nanoseconds.
        image: ``(H, W)`` uint8 grey image.
        source: where it came from (file path, or ``bag:topic#n``).
    """

    index: int
    stamp_ns: int
    image: np.ndarray
    source: str

    @property
    def timestamp(self) -> float:
        """Seconds (float64)."""
        return self.stamp_ns * 1e-9


@dataclasses.dataclass
class _Item:
    index: int
    stamp_ns: int
    source: str
    load: Callable[[], np.ndarray]


class Sequence:
    """Base of the readers: ``len(seq)`` frames, iterated lazily as ``Frame`` objects.

    Subclasses implement ``_items()`` (one ``_Item`` per frame, cheap: the decoding happens in the
    item's ``load``) and set ``name`` (for messages and outputs) and ``kind``.
    """

    kind = "sequence"

    def __init__(self, name: str, skip_bad: bool = False):
        self.name = name
        self.skip_bad = bool(skip_bad)
        self.skipped: List[Tuple[str, str]] = []

    def __len__(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def _items(self) -> Iterator[_Item]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        self.skipped = []
        for item in self._items():
            try:
                img = self._load(item)
            except DataError as exc:
                if not self.skip_bad:
                    raise BadFrameError.naming(str(exc), "skip_bad") from exc
                self.skipped.append((item.source, str(exc)))
                continue
            yield Frame(item.index, item.stamp_ns, img, item.source)

    def _load(self, item: _Item) -> np.ndarray:
        """``item.load()``, noting once per sequence (a ``DataWarning``) that colour frames are
        converted to grey. Every reader of the frames decodes through here (``pipelines.prefetch``
        too)."""
        token = _COLOUR.set(None)
        try:
            img = item.load()
            colour = _COLOUR.get()
        finally:
            _COLOUR.reset(token)
        if colour is not None and not getattr(self, "_colour_noted", False):
            self._colour_noted = True
            warnings.warn(f"{self.kind} {self.name}: colour frames ({colour}; the first: {item.source}) are "
                          f"converted to grey (cv2.cvtColor, as VINS's cv_bridge mono8); the tracker works on "
                          f"grey images", DataWarning, stacklevel=3)
        return img

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {len(self)} frames)"


def check_png(data: bytes, source: str) -> None:
    """Walk the PNG chunks and check their CRCs and the final IEND chunk.

    OpenCV's decoder (libpng) prints its own errors on stderr for a broken file; checking the
    chunk structure first lets us reject truncated or corrupt files with one clean message.
    """
    if not data.startswith(_PNG_SIG):
        raise DataError(f"{source}: not a PNG file (bad signature)")
    pos, n = len(_PNG_SIG), len(data)
    while True:
        if pos + 8 > n:
            raise DataError(f"{source}: truncated PNG ({n} bytes, ends inside a chunk header)")
        length, ctype = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 8 + length + 4
        if end > n:
            raise DataError(f"{source}: truncated PNG ({n} bytes, chunk {ctype!r} needs {end})")
        (crc,) = struct.unpack(">I", data[end - 4:end])
        if zlib.crc32(data[pos + 4:end - 4]) & 0xFFFFFFFF != crc:
            raise DataError(f"{source}: corrupt PNG (CRC mismatch in chunk {ctype.decode('latin-1')!r} at byte {pos})")
        if ctype == b"IEND":
            return
        pos = end


def to_gray_u8(img: np.ndarray, source: str, bgr: bool = True) -> np.ndarray:
    """``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` (BGR, or RGB with ``bgr=False``) or ``(H, W, 4)``,
    8 or 16 bit → ``(H, W)`` uint8 (contiguous)."""
    import cv2

    a = np.asarray(img)
    if a.dtype == np.uint16:
        a = (a >> 8).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise DataError(f"{source}: unsupported pixel type {a.dtype} (expected 8 or 16 bit)")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 3 and a.shape[2] in (3, 4):
        _COLOUR.set(f"{a.shape[2]} channels, {'BGR' if bgr else 'RGB'}{'A' if a.shape[2] == 4 else ''}")
        code = {
            (3, True): cv2.COLOR_BGR2GRAY,
            (3, False): cv2.COLOR_RGB2GRAY,
            (4, True): cv2.COLOR_BGRA2GRAY,
            (4, False): cv2.COLOR_RGBA2GRAY,
        }[(a.shape[2], bool(bgr))]
        a = cv2.cvtColor(np.ascontiguousarray(a), code)
    if a.ndim != 2 or a.shape[0] == 0 or a.shape[1] == 0:
        raise DataError(f"{source}: unsupported image shape {a.shape}")
    return np.ascontiguousarray(a)


def decode_image(data: bytes, source: str) -> np.ndarray:
    """Decode encoded image bytes (PNG, JPEG, ...) to ``(H, W)`` uint8, or raise ``DataError``."""
    import cv2

    if len(data) == 0:
        raise DataError(f"{source}: empty image file (0 bytes)")
    if data.startswith(_PNG_SIG):
        check_png(data, source)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{source}: cannot decode image ({len(data)} bytes; unreadable or corrupt)")
    return to_gray_u8(img, source)


def read_image(path, source: str | None = None) -> np.ndarray:
    """Read an image file as ``(H, W)`` uint8 grey, or raise ``DataError`` naming the file."""
    p = Path(path)
    src = source or str(p)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise DataError(f"{src}: image file not found") from None
    except OSError as exc:
        raise DataError(f"{src}: cannot read image: {exc.strerror or exc}") from None
    return decode_image(data, src)


__all__ = ["DataError", "Frame", "Sequence", "read_image", "decode_image", "to_gray_u8", "check_png", "IMAGE_SUFFIXES"]
