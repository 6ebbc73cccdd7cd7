"""The live ROS 1 node (``torch-frontend ros``): VINS-Mono's ``feature_tracker_node`` for one or
more cameras, all tracked by one batched ``FeatureTracker`` (``docs/ros.md``).

Convention:
    * **Cameras**: one per config entry (:class:`RosCamera`), subscribed to its image topic (the
      config's ``image_topic`` or the entry's own) with rospy's queue of 100 (as VINS). Stream b of
      the tracker is camera b, with its own config (mixed cameras as ``docs/rigs.md``).
    * **Outputs** (the namespace rule, :func:`output_prefixes`): one camera: the node's private
      names ``~feature``, ``~feature_img``, ``~restart`` (``/feature_tracker/feature`` ... with the
      default node name, exactly VINS's); several: ``<camera>/<node>/feature`` ... relative to
      the node's namespace, ``<camera>`` the image topic without its last name
      (``/cam0/image_raw`` -> ``/cam0/feature_tracker/feature``).
    * **Messages** (``io.ros_messages``): ``restart`` on the image that restarted the clock,
      ``feature`` on every frame the tracker *sends* (``FeatureFrame.sent``: FREQ, the first
      published frame not sent), ``feature_img`` on published frames with the config's
      ``show_track`` (drawn only while someone subscribes):
      what ``track --write-bag`` writes for the same images, field for field but ``header.seq``.
    * **Steps**: a step takes the oldest queued frame of every camera that has one (the others
      are inactive, ``active=``: left exactly as they were); with ``sync_wait`` > 0 it first waits
      up to that long, counted from the arrival of the oldest waiting frame, for every camera to
      have a frame.
    * **Queues**: each camera's queue holds at most ``queue_size`` frames; a frame arriving at a
      full queue drops the oldest queued one (the newest frames are kept: the backlog is bounded
      by ``queue_size`` frames), counted per camera and logged at most every 5 s.
    * **Latency**: per frame, image received (the subscriber's callback) -> its step's messages
      published; summarised on exit over the frames whose feature message was sent (median, p95,
      max) and over all tracked frames; optionally published per frame (``latency``).
    Times are seconds (``time.perf_counter``), figures in the summary milliseconds.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from ..errors import DataError
from .common import OptionError, resolve_device

__all__ = ["ROS_APT_PACKAGES", "RosCamera", "RosError", "RosOptions", "check_master", "import_rospy",
           "output_prefixes", "run_ros_node", "LATENCY_FIELDS"]

ROS_APT_PACKAGES = "ros-base python3-rospy python3-sensor-msgs python3-std-msgs"
#: where the operating system's ROS 1 Python packages live (appended to ``sys.path`` when rospy is
#: not importable as it is); ``TORCH_FRONTEND_ROS_PYTHON`` (os.pathsep-separated) replaces it
ROS_PYTHON = ("/usr/lib/python3/dist-packages",)
#: the values of a ``latency`` message (``std_msgs/Float64MultiArray``), in this order
LATENCY_FIELDS = ("stamp_sec", "stamp_nsec", "latency_ms", "median_ms", "p95_ms", "max_ms", "dropped", "sent",
                  "restarted")
LATENCY_WINDOW = 100  # frames of the median / p95 / max of a latency message
WARN_EVERY = 5.0  # seconds between two drop warnings


class RosError(DataError):
    """ROS 1 is not usable here: rospy cannot be imported, or no master answers."""


def import_rospy():
    """``rospy``, importing it from the operating system's ROS 1 packages (``ROS_PYTHON``, appended
    to ``sys.path``) when the environment has none; :class:`RosError` saying what to install."""
    try:
        import rospy

        return rospy
    except ImportError:
        pass
    env = os.environ.get("TORCH_FRONTEND_ROS_PYTHON")
    for p in (env.split(os.pathsep) if env is not None else ROS_PYTHON):
        if p and os.path.isdir(p) and p not in sys.path:
            sys.path.append(p)
    try:
        import rospy

        return rospy
    except ImportError as exc:
        raise RosError(f"cannot import rospy, ROS 1's Python client ({exc}): install ROS 1 (Debian/Ubuntu: "
                       f"apt-get install -y {ROS_APT_PACKAGES}) or source its setup.bash") from None


def check_master(timeout: float = 3.0) -> str:
    """The master's URI (``ROS_MASTER_URI``, default ``http://localhost:11311``) if it answers, else
    :class:`RosError` naming it."""
    import socket
    import xmlrpc.client

    import rosgraph

    uri = rosgraph.get_master_uri()
    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(timeout)
    try:
        code, _msg, _pid = xmlrpc.client.ServerProxy(uri).getPid("/torch_frontend")
        ok = code == 1
    except Exception:  # refused, unreachable, not a master
        ok = False
    finally:
        socket.setdefaulttimeout(old)
    if not ok:
        src = "ROS_MASTER_URI" if os.environ.get("ROS_MASTER_URI") else "ROS_MASTER_URI unset: the default"
        raise RosError(f"no ROS master answers at {uri} ({src}): start roscore, or set ROS_MASTER_URI to the "
                       f"master's address")
    return uri


@dataclasses.dataclass
class RosCamera:
    """One camera of the node: its config (path or ``TrackerConfig``) and image topic (None: the
    config's ``image_topic``; a VINS-Fusion config's ``image0_topic``)."""

    config: Any
    topic: Optional[str] = None


@dataclasses.dataclass
class RosOptions:
    """Options of :func:`run_ros_node`.

    Attributes:
        device: the tracker's device (None: cpu).
        lk_backend: the tracker's pyramid and LK kernels (as ``TrackOptions``).
        queue_size: frames queued per camera at most (>= 1); module docstring's drop policy.
        sync_wait: seconds a step waits for every camera to have a frame (0: none).
        latency: publish per camera ``<prefix>latency`` (``std_msgs/Float64MultiArray``,
            ``LATENCY_FIELDS``) for every tracked frame.
        summary: write the exit summary as JSON into this file too.
        node_name: the node's name (rospy's ``__name:=`` overrides it).
        remap: ROS remapping arguments (``name:=value``, ``__ns:=NS``) for rospy.
        max_frames: stop after this many tracked frames in all (None: until stopped).
    """

    device: Optional[str] = None
    lk_backend: Optional[str] = None
    queue_size: int = 4
    sync_wait: float = 0.0
    latency: bool = False
    summary: Optional[str] = None
    node_name: str = "feature_tracker"
    remap: Sequence[str] = ()
    max_frames: Optional[int] = None

    def check(self) -> None:
        if isinstance(self.queue_size, bool) or not isinstance(self.queue_size, int) or self.queue_size < 1:
            raise OptionError("queue_size", f"queue_size: expected an integer >= 1 (frames), got {self.queue_size!r}")
        if not (isinstance(self.sync_wait, (int, float)) and 0 <= self.sync_wait < float("inf")):
            raise OptionError("sync_wait", f"sync_wait: expected seconds >= 0, got {self.sync_wait!r}")
        from ..fused import BACKENDS

        if self.lk_backend is not None and self.lk_backend not in BACKENDS:
            raise OptionError("lk_backend", f"lk_backend: expected one of {', '.join(BACKENDS)}, got {self.lk_backend!r}")
        for r in self.remap:
            if ":=" not in str(r):
                raise OptionError("remap", f"remap: expected name:=value, got {r!r}")


def output_prefixes(topics: Sequence[str], node: str = "feature_tracker") -> List[str]:
    """The name prefix of each camera's outputs (the namespace rule, module docstring): one
    camera ``"~"``; several ``"<camera>/<node>/"``, ``<camera>`` the image topic without its last
    name and leading slash (``"camera<b>"`` for a one-name topic). Two cameras with the same
    prefix are an ``OptionError`` naming both topics."""
    if len(topics) == 1:
        return ["~"]
    out, seen = [], {}
    base = node.strip("/").split("/")[-1] or "feature_tracker"
    for b, t in enumerate(topics):
        parts = [p for p in str(t).split("/") if p]
        cam = "/".join(parts[:-1]) or f"camera{b}"
        if cam in seen:
            raise OptionError("cameras", f"cameras: the image topics {topics[seen[cam]]} and {t} give the same "
                                         f"output namespace /{cam}/ (the topic without its last name): give the "
                                         f"cameras topics in different namespaces")
        seen[cam] = b
        out.append(f"{cam}/{base}/")
    return out


def _stats(ms: List[float]) -> Dict[str, Any]:
    if not ms:
        return {"n": 0, "median": None, "p95": None, "max": None}
    a = np.asarray(ms, dtype=np.float64)
    return {"n": int(a.size), "median": round(float(np.median(a)), 3), "p95": round(float(np.percentile(a, 95)), 3),
            "max": round(float(a.max()), 3)}


@dataclasses.dataclass
class _Queued:
    stamp_ns: int
    stamp: Any  # the header's rospy.Time (exact)
    image: np.ndarray
    received: float  # perf_counter at the callback


class _Node:
    """The running node's state (module docstring); :func:`run_ros_node` drives it."""

    def __init__(self, rospy, cfgs, topics: List[str], opt: RosOptions, tracker, device, stop: threading.Event):
        from ..io.ros_messages import image_to_grey

        self.rospy, self.cfgs, self.topics, self.opt = rospy, cfgs, topics, opt
        self.tracker, self.device = tracker, device
        self.B = len(topics)
        self.cond = threading.Condition()
        self.queues = [collections.deque() for _ in range(self.B)]
        self.received = [0] * self.B
        self.dropped = [0] * self.B
        self._dropped_warned = [0] * self.B
        self._warned_at = time.perf_counter()
        self.tracked = [0] * self.B
        self.sent = [0] * self.B
        self.restarts = [0] * self.B
        self.latency_sent: List[List[float]] = [[] for _ in range(self.B)]
        self.latency_all: List[List[float]] = [[] for _ in range(self.B)]
        self.steps = 0
        self.fatal: Optional[BaseException] = None
        self.stop = stop
        self._last_ns = np.zeros(self.B, dtype=np.int64)
        self._blank = [np.zeros((c.image_height, c.image_width), dtype=np.uint8) for c in cfgs]
        self._to_grey = image_to_grey
        from sensor_msgs.msg import Image, PointCloud
        from std_msgs.msg import Bool, Float64MultiArray

        self.prefixes = output_prefixes(topics, opt.node_name)
        self.pub_feature = [rospy.Publisher(p + "feature", PointCloud, queue_size=1000) for p in self.prefixes]
        self.pub_img = [rospy.Publisher(p + "feature_img", Image, queue_size=1000) for p in self.prefixes]
        self.pub_restart = [rospy.Publisher(p + "restart", Bool, queue_size=1000) for p in self.prefixes]
        self.pub_latency = ([rospy.Publisher(p + "latency", Float64MultiArray, queue_size=1000) for p in self.prefixes]
                            if opt.latency else None)
        self.subs = [rospy.Subscriber(t, Image, self._callback, callback_args=b, queue_size=100, buff_size=2 ** 24)
                     for b, t in enumerate(topics)]

    # -- the subscribers' threads
    def _callback(self, msg, b: int) -> None:
        t = time.perf_counter()
        if self.fatal is not None:
            return
        try:
            img = self._to_grey(msg, self.topics[b])
            H, W = self.cfgs[b].image_height, self.cfgs[b].image_width
            if img.shape != (H, W):
                raise DataError(f"{self.topics[b]}: image size {img.shape[1]}x{img.shape[0]} differs from the "
                                f"expected {W}x{H} (image_width x image_height of {self.cfgs[b].path})")
        except DataError as exc:
            with self.cond:
                self.fatal = exc
                self.cond.notify_all()
            return
        from ..io.ros_messages import stamp_ns_of

        item = _Queued(stamp_ns_of(msg.header), msg.header.stamp, img, t)
        with self.cond:
            q = self.queues[b]
            self.received[b] += 1
            while len(q) >= self.opt.queue_size:  # the tracker is behind: drop the oldest, keep the newest
                q.popleft()
                self.dropped[b] += 1
            q.append(item)
            self.cond.notify_all()

    # -- the tracking thread (the main thread)
    def _running(self) -> bool:
        return not self.stop.is_set() and not self.rospy.is_shutdown()

    def next_step(self) -> Optional[List[Optional[_Queued]]]:
        """The frames of the next step (module docstring), None when stopping."""
        with self.cond:
            while self._running() and self.fatal is None and not any(self.queues):
                self.cond.wait(0.1)
            if self.fatal is not None:
                raise self.fatal
            if not self._running():
                return None
            if self.opt.sync_wait > 0 and self.B > 1:
                deadline = min(q[0].received for q in self.queues if q) + self.opt.sync_wait
                while self._running() and not all(self.queues) and self.fatal is None:
                    left = deadline - time.perf_counter()
                    if left <= 0:
                        break
                    self.cond.wait(min(left, 0.1))
            return [q.popleft() if q else None for q in self.queues]

    def track(self, items: List[Optional[_Queued]]) -> None:
        import torch

        from ..io.multistream import ns_to_seconds, stack_images
        from ..outputs import feature_message
        from .track import _on_cpu

        active = [it is not None for it in items]
        for b, it in enumerate(items):
            if it is not None:
                self._last_ns[b] = it.stamp_ns
        stacked, sizes = stack_images([it.image if it is not None else self._blank[b] for b, it in enumerate(items)])
        images = torch.from_numpy(stacked[:, None]).to(self.device, non_blocking=self.device.type == "cuda")
        kw = {} if sizes is None else {"sizes": sizes}
        frame = self.tracker.track(images, torch.from_numpy(ns_to_seconds(self._last_ns)),
                                   active=torch.tensor(active), **kw)
        if self.device.type != "cpu":
            frame = _on_cpu(frame)
        self.steps += 1
        restarted = frame.restarted.numpy().astype(bool)
        sent = frame.sent.numpy().astype(bool)
        published = frame.published.numpy().astype(bool)
        from ..io.ros_messages import feature_image_msg, point_cloud_msg, restart_msg

        for b, it in enumerate(items):
            if it is None:
                continue
            self.tracked[b] += 1
            if restarted[b]:
                self.pub_restart[b].publish(restart_msg())
                self.restarts[b] += 1
            if sent[b]:
                self.pub_feature[b].publish(point_cloud_msg(feature_message(frame, b, it.stamp_ns), it.stamp))
                self.sent[b] += 1
            if published[b] and self.cfgs[b].show_track and self.pub_img[b].get_num_connections() > 0:
                from ..viz import draw_tracks

                self.pub_img[b].publish(feature_image_msg(draw_tracks(it.image, frame, b), it.stamp))
            ms = (time.perf_counter() - it.received) * 1e3
            self.latency_all[b].append(ms)
            if sent[b]:
                self.latency_sent[b].append(ms)
            if self.pub_latency is not None:
                self._publish_latency(b, it, ms, bool(sent[b]), bool(restarted[b]))

    def _publish_latency(self, b: int, it: _Queued, ms: float, sent: bool, restarted: bool) -> None:
        from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout

        w = np.asarray(self.latency_all[b][-LATENCY_WINDOW:])
        vals = [float(it.stamp.secs), float(it.stamp.nsecs), ms, float(np.median(w)), float(np.percentile(w, 95)),
                float(w.max()), float(self.dropped[b]), float(sent), float(restarted)]
        dim = MultiArrayDimension(label=",".join(LATENCY_FIELDS), size=len(vals), stride=len(vals))
        self.pub_latency[b].publish(Float64MultiArray(layout=MultiArrayLayout(dim=[dim], data_offset=0), data=vals))

    def warn_drops(self, force: bool = False) -> None:
        """Log the frames dropped since the last warning (at most every ``WARN_EVERY`` s)."""
        now = time.perf_counter()
        if not force and now - self._warned_at < WARN_EVERY:
            return
        with self.cond:
            dropped = list(self.dropped)
        for b in range(self.B):
            k = dropped[b] - self._dropped_warned[b]
            if k:
                self.rospy.logwarn(f"torch-frontend: {self.topics[b]}: dropped {k} frames in the last "
                                   f"{now - self._warned_at:.1f} s ({dropped[b]} in all): the tracker is slower than "
                                   f"the camera; a queue of {self.opt.queue_size} frames keeps the newest")
        self._dropped_warned = dropped
        self._warned_at = now

    def summary(self, seconds: float) -> Dict[str, Any]:
        cams = []
        for b in range(self.B):
            cams.append({"topic": self.topics[b], "config": str(self.cfgs[b].path),
                         "outputs": self.rospy.names.resolve_name(self.prefixes[b] + "feature"),
                         "received": self.received[b], "tracked": self.tracked[b], "dropped": self.dropped[b],
                         "queued_at_exit": len(self.queues[b]), "feature_messages": self.sent[b],
                         "restarts": self.restarts[b], "latency_ms": _stats(self.latency_sent[b]),
                         "latency_all_ms": _stats(self.latency_all[b])})
        tracked = sum(self.tracked)
        return {"cameras": cams, "steps": self.steps, "tracked": tracked, "received": sum(self.received),
                "dropped": sum(self.dropped), "feature_messages": sum(self.sent),
                "cameras_per_step": round(tracked / self.steps, 3) if self.steps else None,
                "latency_ms": _stats([x for v in self.latency_sent for x in v]),
                "latency_all_ms": _stats([x for v in self.latency_all for x in v]),
                "queue_size": self.opt.queue_size, "sync_wait_ms": round(self.opt.sync_wait * 1e3, 3),
                "seconds": round(seconds, 3), "device": str(self.device), "lk_backend": self.tracker.lk_backend}


def _write_json(path, data) -> None:
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, p)


def _warm_up(cfgs, device, lk_backend) -> None:
    """A few steps of a throwaway tracker on a synthetic texture: the kernels' first-use costs
    (JIT caches, allocations) are paid before the first camera frame, not by its latency."""
    import torch

    from ..io.multistream import stack_images
    from .track import make_tracker

    rng = np.random.default_rng(0)
    warm = make_tracker(cfgs, device, "mono", lk_backend)
    raw = [np.ascontiguousarray(np.repeat(np.repeat(rng.integers(0, 256, ((c.image_height + 7) // 8,
                                                                          (c.image_width + 7) // 8), dtype=np.uint8),
                                                    8, 0), 8, 1)[: c.image_height, : c.image_width]) for c in cfgs]
    stacked, sizes = stack_images(raw)
    images = torch.from_numpy(stacked[:, None]).to(device)
    for k in range(3):  # first image, then published frames (FREQ: steps 0.5 s apart)
        t = torch.full((len(cfgs),), 0.5 * k, dtype=torch.float64)
        warm.track(images, t, **({} if sizes is None else {"sizes": sizes}))


def run_ros_node(cameras: Sequence[RosCamera], options: Optional[RosOptions] = None, ready=None) -> Dict[str, Any]:
    """Run the node (module docstring) until SIGINT / SIGTERM, rospy's shutdown or
    ``options.max_frames``; returns the summary (also written to ``options.summary``).

    ``ready`` (a callable or None) is called with the node's outputs once it subscribes (the CLI
    prints them). SIGINT and SIGTERM stop the node between two steps (handlers installed while it
    runs in the main thread, the previous ones restored after).

    Raises:
        OptionError: bad options; ConfigError: a bad config; RosError: no rospy, no master;
        DataError: an image the node cannot take (encoding, size) stops it, naming the topic.
    """
    from ..config import TrackerConfig, load_config
    from .track import make_tracker

    opt = RosOptions() if options is None else options
    opt.check()
    cameras = list(cameras)
    if not cameras:
        raise OptionError("cameras", "cameras: no camera given (expected at least one config)")
    loaded: Dict[str, TrackerConfig] = {}
    cfgs = []
    for c in cameras:  # the same file: the same config object (one tracker group)
        if isinstance(c.config, TrackerConfig):
            cfgs.append(c.config)
        else:
            key = str(Path(c.config).resolve())
            if key not in loaded:
                loaded[key] = load_config(c.config)
            cfgs.append(loaded[key])
    topics = []
    for b, (c, cfg) in enumerate(zip(cameras, cfgs)):
        t = c.topic or cfg.image_topic or cfg.image0_topic  # a VINS-Fusion config: its left camera
        if not t:
            raise OptionError("cameras", f"cameras: camera {b} ({cfg.path}) has no image topic: its config has no "
                                         f"image_topic (nor image0_topic); give CONFIG@TOPIC")
        topics.append(str(t))
    output_prefixes(topics, opt.node_name)  # a clash is an error before anything starts
    dev = resolve_device(opt.device or "cpu")
    rospy = import_rospy()
    remap = [str(r) for r in opt.remap]
    ns = [r.split(":=", 1)[1] for r in remap if r.startswith("__ns:=")]
    if ns:  # rospy reads its namespace from sys.argv when imported: the remap list's wins
        import rosgraph

        rospy.names._set_caller_id(rosgraph.names.make_global_ns(ns[-1]) + "unnamed")
    check_master()
    stopping = threading.Event()  # SIGINT / SIGTERM from here on: stop between two steps, exit 0
    saved = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            saved[sig] = signal.signal(sig, lambda signum, frame: stopping.set())
    try:
        _warm_up(cfgs, dev, opt.lk_backend)
        tracker = make_tracker(cfgs, dev, "mono", opt.lk_backend)
        rospy.init_node(opt.node_name, argv=[sys.argv[0], *remap], disable_signals=True)
        node = _Node(rospy, cfgs, topics, opt, tracker, dev, stopping)
        if ready is not None:
            ready(node)
        t0 = time.perf_counter()
        try:
            while True:
                items = node.next_step()
                if items is None:
                    break
                node.track(items)
                node.warn_drops()
                if opt.max_frames is not None and sum(node.tracked) >= opt.max_frames:
                    break
        finally:
            node.warn_drops(force=True)
            for s in node.subs:
                s.unregister()
            summary = node.summary(time.perf_counter() - t0)
            rospy.signal_shutdown("torch-frontend ros: stopped")
            if opt.summary:
                _write_json(opt.summary, summary)
    finally:
        for sig, prev in saved.items():
            signal.signal(sig, prev)
    return summary
