"""Live ROS 1 messages of the feature tracker node (``torch-frontend ros``, ``pipelines.ros_node``):
camera images in, ``feature`` / ``restart`` / ``feature_img`` out, as rospy message objects.

Convention (``docs/ros.md``):
    * In: ``sensor_msgs/Image`` -> ``(H, W)`` uint8 grey, as VINS-Mono's node takes it
      (``cv_bridge::toCvCopy(msg, "mono8")``, an ``8UC1`` image read as ``mono8``): ``mono8`` /
      ``8UC1`` as they are; ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8`` through ``cv2.cvtColor``
      (``*2GRAY``, what ``cv_bridge`` calls); any other encoding is an :class:`ImageEncodingError`
      naming the encoding and the topic.
    * Out: ``sensor_msgs/PointCloud`` built from ``io.feature_bag.point_cloud_values`` (the values
      the offline bag writer stores: ``header.stamp`` the image's stamp, ``frame_id "world"``,
      points ``(x, y, 1)`` float32, five unnamed channels id, u, v, vx, vy), so a live message and
      the bag's message for the same frame are equal field for field except ``header.seq``
      (rospy numbers it per publisher); ``std_msgs/Bool`` ``data = True`` for ``restart``;
      ``sensor_msgs/Image`` ``bgr8`` for ``feature_img``.

The functions take the message classes from their arguments' modules, so importing this module
needs no ROS; only the builders (``point_cloud_msg``, ...) import ``sensor_msgs`` / ``std_msgs``.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .feature_bag import CHANNEL_NAMES, FRAME_ID, FeatureMessage, point_cloud_values
from .frames import DataError

__all__ = ["GREY_ENCODINGS", "ImageEncodingError", "image_to_grey", "point_cloud_msg", "restart_msg",
           "feature_image_msg", "stamp_ns_of"]

#: encoding -> (channels, cv2 conversion name or None)
GREY_ENCODINGS = {"mono8": (1, None), "8uc1": (1, None), "bgr8": (3, "COLOR_BGR2GRAY"),
                  "rgb8": (3, "COLOR_RGB2GRAY"), "bgra8": (4, "COLOR_BGRA2GRAY"), "rgba8": (4, "COLOR_RGBA2GRAY")}


class ImageEncodingError(DataError):
    """An image the node cannot take (an unsupported encoding, a truncated buffer)."""


def stamp_ns_of(header) -> int:
    """A ROS 1 header's stamp in integer nanoseconds (``secs``, ``nsecs``: exact)."""
    st = header.stamp
    return int(st.secs) * 1_000_000_000 + int(st.nsecs)


def image_to_grey(msg, topic: str) -> np.ndarray:
    """A ``sensor_msgs/Image`` (rospy) as ``(H, W)`` uint8 grey (module docstring).

    Raises:
        ImageEncodingError: another encoding (naming it and ``topic``) or a buffer smaller than
            ``step * height``.
    """
    enc = str(msg.encoding)
    if enc.lower() not in GREY_ENCODINGS:
        raise ImageEncodingError(
            f"{topic}: image encoding {enc!r} is not supported (expected mono8, 8UC1, bgr8, rgb8, bgra8 or rgba8, "
            f"as VINS-Mono's feature_tracker_node takes through cv_bridge)")
    c, code = GREY_ENCODINGS[enc.lower()]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(msg.data, dtype=np.uint8) if isinstance(msg.data, (bytes, bytearray)) \
        else np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < w * c or data.size < step * h:
        raise ImageEncodingError(f"{topic}: truncated image message ({data.size} bytes for {w}x{h} {enc}, step {step})")
    rows = data[: step * h].reshape(h, step)[:, : w * c]
    if code is None:
        return np.ascontiguousarray(rows)
    import cv2

    return cv2.cvtColor(np.ascontiguousarray(rows.reshape(h, w, c)), getattr(cv2, code))


def point_cloud_msg(m: FeatureMessage, header_stamp, num_cameras: int = 1):
    """The ``sensor_msgs/PointCloud`` of one feature message (values: ``point_cloud_values``);
    ``header_stamp`` a ``rospy.Time`` (the image's own stamp object: exact)."""
    from geometry_msgs.msg import Point32
    from sensor_msgs.msg import ChannelFloat32, PointCloud
    from std_msgs.msg import Header

    xy, values = point_cloud_values(m, num_cameras)
    msg = PointCloud(header=Header(stamp=header_stamp, frame_id=m.frame_id or FRAME_ID))
    msg.points = [Point32(x, y, 1.0) for x, y in xy.tolist()]
    msg.channels = [ChannelFloat32(name=n, values=v.tolist()) for n, v in zip(CHANNEL_NAMES, values)]
    return msg


def restart_msg():
    """``std_msgs/Bool`` ``data = True``."""
    from std_msgs.msg import Bool

    return Bool(data=True)


def feature_image_msg(bgr: np.ndarray, header_stamp, frame_id: Optional[str] = None):
    """``sensor_msgs/Image`` ``bgr8`` of an ``(H, W, 3)`` uint8 image (``viz.draw_tracks``)."""
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    img = np.ascontiguousarray(bgr, dtype=np.uint8)
    h, w = img.shape[:2]
    return Image(header=Header(stamp=header_stamp, frame_id=frame_id or FRAME_ID), height=h, width=w,
                 encoding="bgr8", is_bigendian=0, step=w * 3, data=img.tobytes())
