"""Feature bags: the topics VINS-Mono's ``feature_tracker_node`` publishes, written to and read from
ROS 1 (``.bag``) and ROS 2 (a folder with ``metadata.yaml``) bags through ``rosbags`` (no ROS needed).

Convention (spec §3.1, §3.11, §3.12; ``docs/ros.md``):
    * ``/feature_tracker/feature``: ``sensor_msgs/PointCloud``, one message per frame the node
      *sends* (``FeatureFrame.sent``). ``header.stamp`` = the image stamp (ns exact),
      ``header.frame_id = "world"``, ``header.seq`` (ROS 1) = messages written before on the topic;
      ``points[j] = (x, y, 1)`` float32 normalised undistorted; five ``ChannelFloat32`` channels in
      VINS's order: id value, u, v, vx, vy (pixels; normalised units / s). The channels have
      **empty names**, as VINS's node leaves them (the spec gives them by position only, and the
      estimator reads them by index). The id value is ``id * num_cameras + camera`` (spec §3.11:
      ``id * NUM_OF_CAM + cam``), float32; the estimator decodes ``v = int(value + 0.5)``,
      ``id = v // num_cameras``, ``camera = v % num_cameras``. Mono: ``num_cameras = 1`` (the value
      is the id). VINS-Fusion stereo (the spec is silent on a feature topic: its estimator takes
      the feature map in-process, §6.1): the same message with ``num_cameras = 2``, one point per
      observation, ordered by id, camera 0 before camera 1 (``FeatureFrame.to_vins_fusion``'s order).
    * ``/feature_tracker/restart``: ``std_msgs/Bool`` ``data = True`` at the stamp of the image that
      restarted the clock (spec §3.2 step 2).
    * ``/feature_tracker/feature_img``: ``sensor_msgs/Image`` ``bgr8`` on published frames (optional).
    * The IMU topic of the input, copied through (a bag: the messages as recorded, converted between
      ROS 1 and ROS 2 serialisation when the formats differ; a EuRoC ``imu0/data.csv``:
      ``sensor_msgs/Imu``, orientation covariance ``[-1, 0, ...]`` = no orientation).
    Bag receive times are the header stamps (the IMU keeps its recorded receive times).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterator, List, Optional, Tuple, Union

import numpy as np

from .frames import DataError

PathLike = Union[str, Path]

FEATURE_TOPIC = "/feature_tracker/feature"
RESTART_TOPIC = "/feature_tracker/restart"
IMAGE_TOPIC = "/feature_tracker/feature_img"
FRAME_ID = "world"
#: the channel names of VINS's node: none (empty strings), in the order id, u, v, vx, vy
CHANNEL_NAMES = ("", "", "", "", "")
BAG_FORMATS = ("ros1", "ros2")

POINT_CLOUD = "sensor_msgs/msg/PointCloud"
BOOL = "std_msgs/msg/Bool"
IMAGE = "sensor_msgs/msg/Image"
IMU = "sensor_msgs/msg/Imu"


def bag_format_of(path: PathLike, fmt: Optional[str] = None) -> str:
    """``fmt`` if given, else ``"ros1"`` for a name ending in ``.bag``, ``"ros2"`` otherwise."""
    if fmt is not None:
        if fmt not in BAG_FORMATS:
            raise ValueError(f"bag format: expected ros1 or ros2, got {fmt!r}")
        return fmt
    return "ros1" if str(path).endswith(".bag") else "ros2"


@dataclasses.dataclass
class FeatureMessage:
    """One ``/feature_tracker/feature`` message as arrays (one stream, one frame).

    Attributes:
        stamp_ns: int, the header stamp (ns).
        ids: (M,) int64 feature ids.
        camera: (M,) int64 camera of each observation (0; 1 = the right camera of a stereo frame).
        xy: (M, 2) float normalised undistorted (x/z, y/z).
        uv: (M, 2) float distorted pixels.
        velocity: (M, 2) float normalised units per second.
        seq: ROS 1 header seq (0 where the bag has none).
        frame_id: the header's frame id.
        track_count: (M,) int64, on read: how many messages of the bag the (id, camera) was in so
            far, this one included (not VINS's ``track_cnt``, which the message does not carry).
    """

    stamp_ns: int
    ids: np.ndarray
    camera: np.ndarray
    xy: np.ndarray
    uv: np.ndarray
    velocity: np.ndarray
    seq: int = 0
    frame_id: str = FRAME_ID
    track_count: Optional[np.ndarray] = None

    @property
    def timestamp(self) -> float:
        return self.stamp_ns / 1e9

    def to_point_cloud(self) -> dict:
        """The ``FeatureFrame.to_point_cloud`` dict (camera 0 only): ``stamp``, ``points``, ``id``,
        ``u``, ``v``, ``vx``, ``vy`` as float32."""
        m = self.camera == 0
        return {"stamp": self.timestamp,
                "points": np.concatenate([self.xy[m], np.ones((int(m.sum()), 1))], axis=1).astype(np.float32),
                "id": self.ids[m].astype(np.float32), "u": self.uv[m, 0].astype(np.float32),
                "v": self.uv[m, 1].astype(np.float32), "vx": self.velocity[m, 0].astype(np.float32),
                "vy": self.velocity[m, 1].astype(np.float32)}


@dataclasses.dataclass
class FeatureBag:
    """What :func:`read_feature_bag` returns: ``frames`` in bag order, the ``restarts`` (stamps, ns)."""

    frames: List[FeatureMessage]
    restarts: List[int]
    path: Path


def _typestore(fmt: str):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)


def point_cloud_values(m: FeatureMessage, num_cameras: int = 1) -> Tuple[np.ndarray, List[np.ndarray]]:
    """The values of a ``/feature_tracker/feature`` ``sensor_msgs/PointCloud`` (module docstring):
    ``(xy, channels)``, ``xy`` ``(M, 2)`` float32 (the points are ``(x, y, 1)``) and the five
    channels' values in VINS's order (id value ``id * num_cameras + camera``, u, v, vx, vy), each
    ``(M,)`` float32 contiguous. The bag writer and the live node (``io.ros_messages``) both build
    their messages from it, so the two are equal by construction.

    Raises:
        ValueError: a camera index ``>= num_cameras``.
    """
    xy = np.ascontiguousarray(np.asarray(m.xy, dtype=np.float32).reshape(-1, 2))
    uv = np.asarray(m.uv, dtype=np.float32).reshape(-1, 2)
    vel = np.asarray(m.velocity, dtype=np.float32).reshape(-1, 2)
    ids = np.asarray(m.ids, dtype=np.int64).reshape(-1)
    cam = np.asarray(m.camera, dtype=np.int64).reshape(-1)
    if cam.size and int(cam.max()) >= num_cameras:
        raise ValueError(f"camera {int(cam.max())} in a message of {num_cameras} camera(s)")
    idv = (ids * num_cameras + cam).astype(np.float32)
    return xy, [np.ascontiguousarray(v, dtype=np.float32) for v in (idv, uv[:, 0], uv[:, 1], vel[:, 0], vel[:, 1])]


class FeatureBagWriter:
    """Write the feature tracker's topics into a new bag (module docstring).

    Args:
        path: the bag to create (ROS 1: a ``.bag`` file; ROS 2: a folder); must not exist.
        fmt: ``"ros1"`` or ``"ros2"`` (default: by the name, :func:`bag_format_of`).
        num_cameras: 1 (mono) or 2 (stereo: the id channel is ``id * 2 + camera``).
        images: add the ``feature_img`` topic.

    Use as a context manager (closed on success, removed on failure) or call ``close``/``abort``.
    """

    def __init__(self, path: PathLike, fmt: Optional[str] = None, num_cameras: int = 1, images: bool = False):
        self.path = Path(path)
        self.fmt = bag_format_of(self.path, fmt)
        if num_cameras not in (1, 2):
            raise ValueError(f"num_cameras: expected 1 or 2, got {num_cameras}")
        self.num_cameras = int(num_cameras)
        self.ts = _typestore(self.fmt)
        if self.fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self._w = Writer(self.path)
            self._ser = self.ts.serialize_ros1
        else:
            from rosbags.rosbag2 import Writer

            self._w = Writer(self.path, version=9)
            self._ser = self.ts.serialize_cdr
        self._w.open()
        self._conns = {FEATURE_TOPIC: self._w.add_connection(FEATURE_TOPIC, POINT_CLOUD, typestore=self.ts),
                       RESTART_TOPIC: self._w.add_connection(RESTART_TOPIC, BOOL, typestore=self.ts)}
        if images:
            self._conns[IMAGE_TOPIC] = self._w.add_connection(IMAGE_TOPIC, IMAGE, typestore=self.ts)
        self._seq = {}
        self.counts = {}
        #: a list: every message written (``(topic, stamp_ns, raw bytes)``) is appended to it too,
        #: so that a checkpointed run can write the same bag again (:meth:`replay`); None: not kept
        self.journal: Optional[list] = None
        self._open = True

    # -- messages
    def _header(self, topic: str, stamp_ns: int, frame_id: str):
        T = self.ts.types
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        kw = {"seq": seq} if self.fmt == "ros1" else {}
        stamp = T["builtin_interfaces/msg/Time"](sec=int(stamp_ns) // 10**9, nanosec=int(stamp_ns) % 10**9)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id, **kw)

    def _write(self, topic: str, stamp_ns: int, msg, msgtype: str) -> None:
        raw = self._ser(msg, msgtype)
        self._w.write(self._conns[topic], int(stamp_ns), raw)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        if self.journal is not None:
            self.journal.append((topic, int(stamp_ns), bytes(raw)))

    def header_state(self) -> dict:
        """The per-topic header ``seq`` and message counts (plain dicts), for a checkpoint."""
        return {"seq": dict(self._seq), "counts": dict(self.counts)}

    def replay(self, journal, state: dict) -> None:
        """Write again the messages of an earlier writer's ``journal`` (in order, the same bytes)
        and take its :meth:`header_state`: a new bag continues where that writer stood."""
        for topic, stamp_ns, raw in journal:
            self._w.write(self._conns[topic], int(stamp_ns), raw)
        self._seq = dict(state["seq"])
        self.counts = dict(state["counts"])

    def write_features(self, m: FeatureMessage) -> None:
        """One ``/feature_tracker/feature`` message (points in the order given)."""
        T = self.ts.types
        P, C = T["geometry_msgs/msg/Point32"], T["sensor_msgs/msg/ChannelFloat32"]
        try:
            xy, values = point_cloud_values(m, self.num_cameras)
        except ValueError as exc:
            raise ValueError(f"{self.path}: {exc}") from None
        points = [P(x=float(x), y=float(y), z=1.0) for x, y in xy]
        chans = [C(name=n, values=v) for n, v in zip(CHANNEL_NAMES, values)]
        msg = T[POINT_CLOUD](header=self._header(FEATURE_TOPIC, m.stamp_ns, m.frame_id), points=points,
                             channels=chans)
        self._write(FEATURE_TOPIC, m.stamp_ns, msg, POINT_CLOUD)

    def write_restart(self, stamp_ns: int) -> None:
        """``/feature_tracker/restart`` ``data = True``."""
        self._write(RESTART_TOPIC, stamp_ns, self.ts.types[BOOL](data=True), BOOL)

    def write_image(self, stamp_ns: int, bgr: np.ndarray) -> None:
        """``/feature_tracker/feature_img``: an ``(H, W, 3)`` uint8 BGR image."""
        img = np.ascontiguousarray(bgr, dtype=np.uint8)
        h, w = img.shape[:2]
        msg = self.ts.types[IMAGE](header=self._header(IMAGE_TOPIC, stamp_ns, FRAME_ID), height=h, width=w,
                                   encoding="bgr8", is_bigendian=0, step=w * 3, data=img.reshape(-1))
        self._write(IMAGE_TOPIC, stamp_ns, msg, IMAGE)

    def copy_topic(self, bag: PathLike, topic: str) -> int:
        """Copy every message of ``topic`` from the bag ``bag`` (receive times kept); returns how many."""
        from .rosbag import _open

        reader = _open(Path(bag))
        n = 0
        try:
            conns = [c for c in reader.connections if c.topic == topic]
            if not conns:
                return 0
            msgtype = conns[0].msgtype
            src_fmt = "ros1" if Path(bag).is_file() else "ros2"
            if topic not in self._conns:
                if src_fmt == self.fmt and self.fmt == "ros1":
                    c0 = conns[0]
                    self._conns[topic] = self._w.add_connection(topic, msgtype, msgdef=c0.msgdef.data,
                                                                md5sum=c0.digest)
                else:
                    self._conns[topic] = self._w.add_connection(topic, msgtype, typestore=self.ts)
            for conn, t, raw in reader.messages(connections=conns):
                if src_fmt != self.fmt:  # same values, the other serialisation (ROS 1 headers' seq: 0)
                    raw = self._ser(self._convert(reader.deserialize(raw, conn.msgtype), msgtype), msgtype)
                self._w.write(self._conns[topic], int(t), raw)
                n += 1
        finally:
            reader.close()
        self.counts[topic] = self.counts.get(topic, 0) + n
        return n

    def _convert(self, obj, typename: str):
        """A message object of the other ROS version as one of this bag's typestore, field by field
        (a field only one side has: the default, ``seq = 0``)."""
        cls = self.ts.types[typename]
        kw = {}
        for f in dataclasses.fields(cls):
            if not hasattr(obj, f.name):
                kw[f.name] = 0
                continue
            v = getattr(obj, f.name)
            sub = getattr(v, "__msgtype__", None)
            if sub is not None and sub in self.ts.types:
                v = self._convert(v, sub)
            elif isinstance(v, list):
                v = [self._convert(x, x.__msgtype__) if getattr(x, "__msgtype__", None) else x for x in v]
            kw[f.name] = v
        return cls(**kw)

    def write_euroc_imu(self, csv: PathLike, topic: str = "/imu0", frame_id: str = "imu4") -> int:
        """``sensor_msgs/Imu`` messages from a EuRoC ``imu0/data.csv`` (``timestamp [ns], w_x, w_y, w_z
        [rad/s], a_x, a_y, a_z [m/s^2]``); returns how many."""
        stamps, rows = [], []
        try:
            lines = Path(csv).read_text(encoding="utf-8").splitlines()
        except OSError as exc:
            raise DataError(f"{csv}: cannot read the IMU file: {exc.strerror or exc}") from None
        for k, line in enumerate(lines, 1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            f = line.split(",")
            try:
                if len(f) < 7:
                    raise ValueError(f"{len(f)} columns")
                stamps.append(int(f[0]))  # ns exact (a float64 would round them)
                rows.append([float(v) for v in f[1:7]])
            except ValueError as exc:
                raise DataError(f"{csv}:{k}: expected timestamp [ns], w_x, w_y, w_z, a_x, a_y, a_z: {exc}") from None
        T = self.ts.types
        V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        if topic not in self._conns:
            self._conns[topic] = self._w.add_connection(topic, IMU, typestore=self.ts)
        cov0 = np.zeros(9)
        cov_none = np.array([-1.0] + [0.0] * 8)
        for s, row in zip(stamps, rows):
            msg = T[IMU](header=self._header(topic, s, frame_id), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                         orientation_covariance=cov_none, angular_velocity=V(x=row[0], y=row[1], z=row[2]),
                         angular_velocity_covariance=cov0, linear_acceleration=V(x=row[3], y=row[4], z=row[5]),
                         linear_acceleration_covariance=cov0)
            self._write(topic, s, msg, IMU)
        return len(rows)

    # -- closing
    def close(self) -> None:
        if self._open:
            self._open = False
            self._w.close()

    def abort(self) -> None:
        """Stop writing and remove the bag."""
        import shutil

        if self._open:
            self._open = False
            try:
                self._w.close()
            except Exception:  # a half-written bag is removed anyway
                pass
        if self.path.is_dir():
            shutil.rmtree(self.path, ignore_errors=True)
        else:
            self.path.unlink(missing_ok=True)

    def __enter__(self) -> FeatureBagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def _iter_features(reader, topic: str, num_cameras: int, path: Path) -> Iterator[FeatureMessage]:
    conns = [c for c in reader.connections if c.topic == topic]
    for conn, _t, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        ch = msg.channels
        if len(ch) < 5:
            raise DataError(f"{path}: {topic}: expected 5 channels (id, u, v, vx, vy), got {len(ch)}")
        n = len(msg.points)
        vals = [np.asarray(c.values, dtype=np.float32).reshape(-1) for c in ch[:5]]
        if any(v.size != n for v in vals):
            raise DataError(f"{path}: {topic}: channel lengths {[v.size for v in vals]} differ from the "
                            f"{n} points")
        code = (vals[0].astype(np.float64) + 0.5).astype(np.int64)  # the estimator's decoding (spec §3.11)
        xy = np.array([(p.x, p.y) for p in msg.points], dtype=np.float32).reshape(-1, 2)
        st = msg.header.stamp
        yield FeatureMessage(stamp_ns=int(st.sec) * 10**9 + int(st.nanosec), ids=code // num_cameras,
                             camera=code % num_cameras, xy=xy.astype(np.float64),
                             uv=np.stack([vals[1], vals[2]], axis=1).astype(np.float64),
                             velocity=np.stack([vals[3], vals[4]], axis=1).astype(np.float64),
                             seq=int(getattr(msg.header, "seq", 0)), frame_id=str(msg.header.frame_id))


def read_feature_bag(path: PathLike, topic: str = FEATURE_TOPIC, num_cameras: int = 1,
                     restart_topic: str = RESTART_TOPIC) -> FeatureBag:
    """Read the feature messages of a bag (ours, or one recorded from VINS's ``feature_tracker_node``).

    Args:
        path: ROS 1 ``.bag`` or ROS 2 bag folder.
        topic: the ``sensor_msgs/PointCloud`` topic.
        num_cameras: how the id channel is decoded (1: mono; 2: stereo, module docstring).

    Returns:
        :class:`FeatureBag`: one :class:`FeatureMessage` per message in bag order (values float32
        as stored, widened to float64), ``track_count`` counted over the bag, and the restart stamps.

    Raises:
        DataError: missing or unreadable bag, no such topic or not a PointCloud, malformed messages.
    """
    from .rosbag import _open

    path = Path(path)
    reader = _open(path)
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            have = sorted({c.topic for c in reader.connections})
            raise DataError(f"{path}: no topic {topic!r} (topics: {', '.join(have) or 'none'})")
        if conns[0].msgtype != POINT_CLOUD:
            raise DataError(f"{path}: topic {topic!r} has type {conns[0].msgtype}, expected sensor_msgs/PointCloud")
        frames = list(_iter_features(reader, topic, num_cameras, path))
        rconns = [c for c in reader.connections if c.topic == restart_topic]
        restarts = [int(t) for _c, t, _raw in reader.messages(connections=rconns)] if rconns else []
    finally:
        reader.close()
    seen: dict = {}
    for f in frames:
        cnt = np.empty(len(f.ids), dtype=np.int64)
        for j, key in enumerate(zip(f.ids.tolist(), f.camera.tolist())):
            seen[key] = seen.get(key, 0) + 1
            cnt[j] = seen[key]
        f.track_count = cnt
    return FeatureBag(frames=frames, restarts=restarts, path=path)


__all__ = ["FEATURE_TOPIC", "RESTART_TOPIC", "IMAGE_TOPIC", "FRAME_ID", "CHANNEL_NAMES", "BAG_FORMATS",
           "FeatureMessage", "FeatureBag", "FeatureBagWriter", "read_feature_bag", "bag_format_of",
           "point_cloud_values"]
