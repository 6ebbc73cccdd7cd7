"""``open_sequence``: one entry point for the readers (what the CLI's ``--euroc/--bag/--images/--kitti`` use)."""

from __future__ import annotations

from pathlib import Path
from typing import Union

from .frames import DataError, Sequence

PathLike = Union[str, Path]
KINDS = ("euroc", "bag", "images", "kitti")


def open_sequence(kind: str, path: PathLike, *, camera: str = "cam0", fps: float | None = None,
                  topic: str | None = None, skip_bad: bool = False) -> Sequence:
    """Open a sequence of kind ``"euroc"`` (ASL folder), ``"bag"`` (ROS 1/2 bag, needs ``topic``) or
    ``"images"`` (image folder, ``fps`` optional) or ``"kitti"`` (KITTI odometry sequence or raw
    drive, ``camera`` ``cam0`` .. ``cam3``).

    Raises:
        DataError: unknown kind, missing or unreadable input, empty sequence, missing topic.
    """
    if kind == "euroc":
        from .euroc import EurocSequence

        return EurocSequence(path, camera=camera, skip_bad=skip_bad)
    if kind == "images":
        from .folder import ImageFolderSequence

        return ImageFolderSequence(path, fps=fps, skip_bad=skip_bad)
    if kind == "kitti":
        from .kitti import KittiSequence

        return KittiSequence(path, camera=camera, skip_bad=skip_bad)
    if kind == "bag":
        from .rosbag import RosbagSequence

        if not topic:
            raise DataError(f"{path}: no image topic given (and the config has no image_topic)")
        return RosbagSequence(path, topic, skip_bad=skip_bad)
    raise DataError(f"unknown input kind {kind!r} (expected one of {', '.join(KINDS)})")


__all__ = ["open_sequence", "KINDS"]
