"""ROS 1 helpers of the live node's tests and benchmark: a private ``roscore``, the node as a
subprocess, and a driver (``python -m tests._ros drive SPEC RESULT``, its own process: rospy may be
initialised once per process) that publishes frames and collects the node's messages.

Nothing here imports rospy into the calling process: the master, the node and the driver are
child processes with ``ROS_MASTER_URI`` on a free port, ``ROS_HOSTNAME=127.0.0.1`` and a
temporary ``ROS_HOME``.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
ROS_PYTHON = "/usr/lib/python3/dist-packages"
ROS_PACKAGES = "ros-base python3-rospy python3-sensor-msgs python3-std-msgs python3-rosbag"


def ros_missing() -> str | None:
    """Why ROS 1 cannot be used here (None: it can): ``roscore`` on PATH, rospy importable (from
    the environment or the system's dist-packages)."""
    if shutil.which("roscore") is None:
        return f"roscore not on PATH (ROS 1: apt-get install -y {ROS_PACKAGES})"
    code = f"import sys; sys.path.append({ROS_PYTHON!r}); import rospy, sensor_msgs.msg, std_msgs.msg"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or ["?"])[-1]
        return f"rospy not importable ({last}; ROS 1: apt-get install -y {ROS_PACKAGES})"
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def master_online(uri: str) -> bool:
    import xmlrpc.client

    try:
        return xmlrpc.client.ServerProxy(uri).getPid("/probe")[0] == 1
    except OSError:
        return False


@contextlib.contextmanager
def roscore(timeout: float = 30.0):
    """A ``roscore`` on a free port; yields the environment (``os.environ`` plus the ROS
    variables) for the node and the driver. Stopped (SIGINT, then killed) on exit."""
    home = Path(tempfile.mkdtemp(prefix="tf_ros_home_"))
    port = free_port()
    env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}", ROS_HOSTNAME="127.0.0.1",
               ROS_HOME=str(home), ROS_LOG_DIR=str(home / "log"), PYTHONPATH=str(REPO))
    env.pop("ROS_IP", None)
    env.pop("ROS_NAMESPACE", None)
    proc = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        t0 = time.monotonic()
        while not master_online(env["ROS_MASTER_URI"]):
            if proc.poll() is not None:
                raise RuntimeError(f"roscore exited ({proc.returncode}): {proc.stderr.read().decode()[-500:]}")
            if time.monotonic() - t0 > timeout:
                raise RuntimeError(f"roscore not up after {timeout} s")
            time.sleep(0.1)
        yield env
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stderr.close()
        shutil.rmtree(home, ignore_errors=True)


def start_node(env, args, python=sys.executable) -> subprocess.Popen:
    """``torch-frontend ros ARGS`` as a child process (stdout, stderr piped)."""
    return subprocess.Popen([python, "-m", "torch_frontend", "ros", *map(str, args)], env=env, cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop_node(proc: subprocess.Popen, sig=signal.SIGTERM, timeout: float = 60.0):
    """Send ``sig``; returns ``(returncode, stdout, stderr)``."""
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, out, err


def drive(env, spec: dict, timeout: float = 300.0) -> dict:
    """Run the driver (:func:`_drive`) with ``spec`` in its own process; returns its result."""
    with tempfile.TemporaryDirectory(prefix="tf_ros_drive_") as d:
        sp, rp = Path(d) / "spec.pkl", Path(d) / "result.pkl"
        sp.write_bytes(pickle.dumps(spec))
        r = subprocess.run([sys.executable, "-m", "tests._ros", "drive", str(sp), str(rp)], env=env, cwd=REPO,
                           capture_output=True, text=True, timeout=timeout)
        if r.returncode != 0:
            raise RuntimeError(f"driver failed ({r.returncode}):\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}")
        return pickle.loads(rp.read_bytes())


def image_msg_fields(grey: np.ndarray, encoding: str) -> dict:
    """The fields of a ``sensor_msgs/Image`` carrying the grey image in ``encoding`` (a colour
    encoding: a colour image whose ``cvtColor`` to grey is ``grey`` exactly; an encoding the node
    refuses, e.g. ``16UC1``: the grey bytes under that name)."""
    g = np.ascontiguousarray(grey, dtype=np.uint8)
    h, w = g.shape
    if encoding in ("mono8", "8UC1") or not encoding.endswith("8"):  # other names: the grey bytes
        return dict(height=h, width=w, encoding=encoding, is_bigendian=0, step=w, data=g.tobytes())
    c = 4 if encoding.endswith("a8") else 3
    img = np.repeat(g[:, :, None], c, axis=2)
    return dict(height=h, width=w, encoding=encoding, is_bigendian=0, step=w * c, data=img.tobytes())


# ----------------------------------------------------------------------------------------------
# the driver (its own process)


def _drive(spec: dict) -> dict:
    """Publish ``spec["frames"]`` and collect the node's outputs.

    spec: ``cameras``: ``[{"topic", "outputs" (prefix of the node's topics, e.g.
    "/feature_tracker/")}]``; ``frames``: ``[round: [(camera, stamp_ns, grey (H, W) uint8, encoding)]]``;
    ``wait``: ``"round"`` (after each round, wait for one ``latency`` message per frame of it: the
    node runs with ``--latency``) or ``"none"`` (publish without waiting: at once, or at ``rate``
    rounds per second when given); ``latency``: subscribe
    to the ``latency`` topics (default True); ``settle``: seconds to wait for trailing messages at
    the end.
    Returns ``{"feature": [per camera: [(stamp_ns, seq, points (M, 3) f32, [5 x (M,) f32],
    frame_id, channel names)]], "restart": [per camera: [stamp_ns of its receipt order]],
    "latency": [per camera: [values]], "feature_img": [per camera: count]}``.
    """
    sys.path.append(ROS_PYTHON)
    import threading

    import rospy
    from sensor_msgs.msg import Image, PointCloud
    from std_msgs.msg import Bool, Float64MultiArray, Header

    rospy.init_node("tf_test_driver", anonymous=True, disable_signals=True)
    cams = spec["cameras"]
    lock = threading.Condition()
    res = {"feature": [[] for _ in cams], "restart": [[] for _ in cams], "latency": [[] for _ in cams],
           "feature_img": [0 for _ in cams]}

    def on_feature(msg, b):
        pts = np.array([(p.x, p.y, p.z) for p in msg.points], dtype=np.float32).reshape(-1, 3)
        ch = [np.asarray(c.values, dtype=np.float32) for c in msg.channels]
        st = msg.header.stamp
        with lock:
            res["feature"][b].append((int(st.secs) * 10**9 + int(st.nsecs), int(msg.header.seq), pts, ch,
                                      msg.header.frame_id, [c.name for c in msg.channels]))

    def on_restart(msg, b):
        with lock:
            res["restart"][b].append(bool(msg.data))

    def on_latency(msg, b):
        with lock:
            res["latency"][b].append(list(msg.data))
            lock.notify_all()

    def on_img(msg, b):
        with lock:
            res["feature_img"][b] += 1

    subs = []
    for b, c in enumerate(cams):
        o = c["outputs"]
        subs += [rospy.Subscriber(o + "feature", PointCloud, on_feature, callback_args=b),
                 rospy.Subscriber(o + "restart", Bool, on_restart, callback_args=b)]
        if spec.get("latency", True):
            subs.append(rospy.Subscriber(o + "latency", Float64MultiArray, on_latency, callback_args=b))
        if spec.get("images"):
            subs.append(rospy.Subscriber(o + "feature_img", Image, on_img, callback_args=b))
    pubs = [rospy.Publisher(c["topic"], Image, queue_size=1000) for c in cams]
    t0 = time.monotonic()
    wait_for = spec.get("connect_timeout", 240.0)
    while not all(p.get_num_connections() > 0 for p in pubs) or not all(s.get_num_connections() > 0 for s in subs):
        if time.monotonic() - t0 > wait_for:
            raise RuntimeError("the node did not connect to the driver's topics in time")
        time.sleep(0.05)
    time.sleep(0.3)  # the connections' headers exchanged both ways
    sent_per_cam = [0] * len(cams)
    rate, t_start = spec.get("rate"), time.perf_counter()
    for k, rnd in enumerate(spec["frames"]):
        if rate:  # a camera rate: round k at t_start + k / rate (wall clock), whatever the node does
            time.sleep(max(0.0, t_start + k / rate - time.perf_counter()))
        for b, stamp_ns, grey, enc in rnd:
            from tests._ros import image_msg_fields

            if isinstance(grey, int):  # an index into spec["pool"] (a benchmark's many rounds)
                grey = spec["pool"][grey]
            stamp = rospy.Time(int(stamp_ns) // 10**9, int(stamp_ns) % 10**9)
            pubs[b].publish(Image(header=Header(stamp=stamp, frame_id="cam"), **image_msg_fields(grey, enc)))
            sent_per_cam[b] += 1
        if spec.get("wait", "round") == "round":
            deadline = time.monotonic() + spec.get("frame_timeout", 120.0)
            with lock:
                while any(len(res["latency"][b]) < sent_per_cam[b] for b in range(len(cams))):
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise RuntimeError(f"no latency message for a frame in time: {sent_per_cam} sent, "
                                           f"{[len(x) for x in res['latency']]} answered")
                    lock.wait(min(left, 0.5))
    time.sleep(spec.get("settle", 1.0))
    with lock:
        return json.loads(json.dumps({k: v for k, v in res.items() if k != "feature"})) | {"feature": res["feature"]}


def main(argv) -> int:
    if len(argv) == 3 and argv[0] == "drive":
        spec = pickle.loads(Path(argv[1]).read_bytes())
        result = _drive(spec)
        Path(argv[2]).write_bytes(pickle.dumps(result))
        os._exit(0)  # rospy's threads: no clean-up wait
    print("usage: python -m tests._ros drive SPEC RESULT", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
