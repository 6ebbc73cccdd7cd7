"""ROS 1 (``.bag``) and ROS 2 (folder with ``metadata.yaml``) bags, through the ``rosbags`` package.

Convention:
    One image topic per sequence: ``sensor_msgs/Image`` (``mono8``, ``8UC1``, ``bgr8``, ``rgb8``,
    ``bgra8``, ``rgba8``, ``mono16``/``16UC1`` reduced by ``>> 8``) or ``sensor_msgs/CompressedImage``
    (any format OpenCV decodes). The timestamp is the message's ``header.stamp`` (what VINS uses);
    a zero header stamp falls back to the bag's receive time. Messages are in bag (receive-time)
    order.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, List, Union

import numpy as np

from .frames import DataError, Sequence, _Item, decode_image, to_gray_u8

PathLike = Union[str, Path]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


def _reader(path: Path):
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:  # pragma: no cover - rosbags is a dependency
        raise DataError("reading ROS bags needs the 'rosbags' package (pip install rosbags)") from None
    # ROS 2 bags written without message definitions need a default typestore.
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _open(path: Path):
    """Open a bag or raise DataError (missing path, not a bag)."""
    if not path.exists():
        raise DataError(f"{path}: bag not found")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise DataError(f"{path}: not a ROS 2 bag folder (no metadata.yaml)")
    if path.is_file() and path.suffix != ".bag":
        raise DataError(f"{path}: not a ROS bag (expected a ROS 1 '.bag' file or a ROS 2 bag folder)")
    try:
        reader = _reader(path)
        reader.open()
    except DataError:
        raise
    except Exception as exc:  # rosbags raises several reader/typesys error types
        raise DataError(f"{path}: cannot open ROS bag: {exc}") from None
    return reader


def _image_from_msg(msg, msgtype: str, source: str) -> np.ndarray:
    if msgtype.endswith("CompressedImage"):
        return decode_image(bytes(np.asarray(msg.data, dtype=np.uint8)), source)
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    channels = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3, "bgra8": 4, "rgba8": 4, "8uc4": 4,
                "mono16": 1, "16uc1": 1}
    if enc not in channels:
        raise DataError(f"{source}: unsupported image encoding {msg.encoding!r} "
                        f"(expected mono8, bgr8, rgb8, bgra8, rgba8 or mono16)")
    c = channels[enc]
    bpp = 2 if "16" in enc else 1
    if h <= 0 or w <= 0 or step < w * c * bpp or data.size < step * h:
        raise DataError(f"{source}: truncated image message ({data.size} bytes for {w}x{h} {enc}, step {step})")
    rows = data[: step * h].reshape(h, step)[:, : w * c * bpp]
    if bpp == 2:
        dt = np.dtype(">u2" if msg.is_bigendian else "<u2")
        img = rows.copy().view(dt).reshape(h, w).astype(np.uint16)
    else:
        img = rows.reshape(h, w, c) if c > 1 else rows
    return to_gray_u8(img, source, bgr=not enc.startswith("rgb"))


class RosbagSequence(Sequence):
    """Images of one topic of a ROS 1 or ROS 2 bag.

    Args:
        path: ``.bag`` file (ROS 1) or bag folder (ROS 2).
        topic: image topic (e.g. the config's ``image_topic``).
        skip_bad: skip undecodable messages instead of raising.

    Raises:
        DataError: missing or unreadable bag, topic absent or not an image type, no messages.
    """

    kind = "bag"

    def __init__(self, path: PathLike, topic: str, skip_bad: bool = False):
        self.path = Path(path)
        self.topic = topic
        super().__init__(f"{self.path.name}:{topic}", skip_bad)
        reader = _open(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == topic]
            if not conns:
                images = sorted({c.topic for c in reader.connections if c.msgtype in IMAGE_TYPES})
                hint = f"image topics in the bag: {', '.join(images)}" if images else "the bag has no image topics"
                raise DataError(f"{self.path}: no topic {topic!r} ({hint})")
            bad = [c.msgtype for c in conns if c.msgtype not in IMAGE_TYPES]
            if bad:
                raise DataError(f"{self.path}: topic {topic!r} has type {bad[0]}, expected sensor_msgs/Image "
                                f"or sensor_msgs/CompressedImage")
            self.count = int(sum(c.msgcount for c in conns))
        finally:
            reader.close()
        if self.count == 0:
            raise DataError(f"{self.path}: empty sequence (topic {topic!r} has no messages)")

    def __len__(self) -> int:
        return self.count

    def _items(self) -> Iterator[_Item]:
        reader = _open(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for i, (conn, t_bag, raw) in enumerate(reader.messages(connections=conns)):
                source = f"{self.path}:{self.topic}#{i}"
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:
                    err = DataError(f"{source}: cannot deserialize message: {exc}")

                    def _fail(e=err):
                        raise e

                    yield _Item(i, int(t_bag), source, _fail)
                    continue
                st = msg.header.stamp
                stamp = int(st.sec) * 1_000_000_000 + int(st.nanosec)
                if stamp == 0:
                    stamp = int(t_bag)
                yield _Item(i, stamp, source, lambda m=msg, t=conn.msgtype, s=source: _image_from_msg(m, t, s))
        finally:
            reader.close()


def list_image_topics(path: PathLike) -> List[str]:
    """Image topics of a bag (for messages and notebooks)."""
    reader = _open(Path(path))
    try:
        return sorted({c.topic for c in reader.connections if c.msgtype in IMAGE_TYPES})
    finally:
        reader.close()


__all__ = ["RosbagSequence", "list_image_topics"]
