"""The live ROS 1 node (``torch-frontend ros``, ``pipelines.ros_node``) against a real ``roscore``:
its messages equal the offline ``track --write-bag`` bag's, one camera and four cameras in one
node; image encodings; errors; clean exit; the drop policy.

The equality tests are lossless by construction: the driver (``tests._ros``) publishes a round
of frames and waits for the node's per-frame ``latency`` message of each before the next round
(no timing assertions). They skip where ROS 1 is missing, unless ``TORCH_FRONTEND_REQUIRE_ROS=1``
(``make test-all``, CI), which makes that a failure.
"""

from __future__ import annotations

import json
import signal
import types

import numpy as np
import pytest

from . import _ros
from .conftest import REPO, load_gray, ros_skip, sample_frames

EUROC = REPO / "configs" / "euroc.yaml"


# ----------------------------------------------------------------------------------------------
# no ROS needed: image conversion, messages' values, errors


def _msg(grey, enc):
    return types.SimpleNamespace(**_ros.image_msg_fields(grey, enc))


def test_image_encodings_convert_as_cv_bridge():
    import cv2

    from torch_frontend.io.ros_messages import image_to_grey

    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    m = types.SimpleNamespace(height=6, width=5, encoding="bgr8", is_bigendian=0, step=16,
                              data=np.pad(bgr.reshape(6, 15), ((0, 0), (0, 1))).tobytes())  # padded rows
    assert np.array_equal(image_to_grey(m, "/cam"), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    m.encoding = "rgb8"
    assert np.array_equal(image_to_grey(m, "/cam"), cv2.cvtColor(bgr, cv2.COLOR_RGB2GRAY))
    g = bgr[:, :, 0]
    for enc in ("mono8", "8UC1", "bgra8", "rgba8"):
        assert np.array_equal(image_to_grey(_msg(g, enc), "/cam"), g), enc


def test_bad_encoding_names_it_and_the_topic():
    from torch_frontend.io.ros_messages import ImageEncodingError, image_to_grey

    m = _msg(np.zeros((4, 4), np.uint8), "mono8")
    m.encoding = "16UC1"
    with pytest.raises(ImageEncodingError, match=r"/cam0/image_raw: image encoding '16UC1' is not supported"):
        image_to_grey(m, "/cam0/image_raw")
    m.encoding, m.data = "mono8", b"\0" * 3
    with pytest.raises(ImageEncodingError, match="truncated"):
        image_to_grey(m, "/cam0/image_raw")


def test_namespace_rule():
    from torch_frontend.pipelines.common import OptionError
    from torch_frontend.pipelines.ros_node import output_prefixes

    assert output_prefixes(["/cam0/image_raw"]) == ["~"]
    assert output_prefixes(["/cam0/image_raw", "/r2/cam1/image", "/image"]) == [
        "cam0/feature_tracker/", "r2/cam1/feature_tracker/", "camera2/feature_tracker/"]
    with pytest.raises(OptionError, match="/cam0/a and /cam0/b give the same output namespace"):
        output_prefixes(["/cam0/a", "/cam0/b"])


def test_missing_rospy_is_one_line_naming_the_packages(monkeypatch, capsys):
    import sys

    from torch_frontend.cli import main

    monkeypatch.setitem(sys.modules, "rospy", None)  # import rospy raises ImportError
    monkeypatch.setenv("TORCH_FRONTEND_ROS_PYTHON", "")
    assert main(["ros", str(EUROC)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "cannot import rospy" in err and "apt-get install -y ros-base python3-rospy" in err


def test_no_master_names_ros_master_uri(monkeypatch, capsys):
    if (why := _ros.ros_missing()) is not None:
        ros_skip(why)
    import sys

    from torch_frontend.cli import main

    monkeypatch.setattr(sys, "path", list(sys.path))  # the node appends the system's ROS packages: undone
    uri = f"http://127.0.0.1:{_ros.free_port()}"
    monkeypatch.setenv("ROS_MASTER_URI", uri)
    assert main(["ros", str(EUROC)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"no ROS master answers at {uri} (ROS_MASTER_URI)" in err


def test_remapping_arguments_are_not_configs(capsys):
    from torch_frontend.cli import main

    assert main(["ros", "__ns:=/r1", "x:=y"]) == 2
    assert "no CONFIG given" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# against a real roscore


def _frames(camera: str, n: int, crop=None):
    paths = sample_frames(camera)[:n]
    imgs = [load_gray(p) for p in paths]
    if crop is not None:
        imgs = [im[: crop[0], : crop[1]].copy() for im in imgs]
    return imgs, np.array([int(p.stem) for p in paths], dtype=np.int64)


def _offline(cfg, imgs, stamps_ns, out):
    """``track --write-bag`` of these frames as one stream (the reference): ``(stamps_ns,
    {stamp: (points, channels, frame_id, names)}, feature stamps in order, restart stamps)``."""
    from torch_frontend.io.rosbag import _open
    from torch_frontend.pipelines import ArraySequence, TrackOptions, run_track

    seq = ArraySequence(imgs, np.asarray(stamps_ns) / 1e9, name="ref")
    run_track(cfg, [seq], out, TrackOptions(bag="features.bag", write_tracks=False, bag_imu=False, progress=False))
    reader = _open(out / "features.bag")
    feats, order, restarts = {}, [], []
    try:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/feature_tracker/feature":
                st = msg.header.stamp
                s = int(st.sec) * 10**9 + int(st.nanosec)
                pts = np.array([(p.x, p.y, p.z) for p in msg.points], dtype=np.float32).reshape(-1, 3)
                feats[s] = (pts, [np.asarray(c.values, dtype=np.float32) for c in msg.channels], msg.header.frame_id,
                            [c.name for c in msg.channels])
                order.append(s)
            elif conn.topic == "/feature_tracker/restart":
                restarts.append(int(t))
    finally:
        reader.close()
    return seq.stamps_ns, feats, order, restarts


def _assert_equal_to_offline(live_feature, live_latency, ref):
    stamps, feats, order, restarts = ref
    got = [f[0] for f in live_feature]  # in publication order (the bag's: by stamp)
    assert got == [int(s) for s in stamps if int(s) in feats] and sorted(got) == sorted(order), \
        "the published-frame pattern differs"
    seqs = [f[1] for f in live_feature]  # rospy numbers them itself
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) if seqs else True
    for s, _seq, pts, ch, frame_id, names in live_feature:
        rp, rch, rfid, rnames = feats[s]
        assert (frame_id, names) == (rfid, rnames)
        assert pts.shape == rp.shape and np.array_equal(pts, rp), s
        assert len(ch) == 5 and all(np.array_equal(a, b) for a, b in zip(ch, rch)), s
    # per frame: its stamp, whether it was sent, whether it restarted (the latency messages)
    lat = np.array(live_latency)
    assert [int(a) * 10**9 + int(b) for a, b in lat[:, :2]] == [int(s) for s in stamps]
    assert [int(s) for s, flag in zip(stamps, lat[:, 7]) if flag] == got
    assert sorted(int(s) for s, flag in zip(stamps, lat[:, 8]) if flag) == sorted(restarts)


def test_one_camera_equals_the_offline_bag(ros_master, tmp_path):
    """Exactly VINS's topics; FREQ, first published frame not sent, a restart on a gap > 1 s and
    on time going back; every message equal to the offline bag's; SIGTERM: exit 0, summary."""
    from torch_frontend.config import load_config

    imgs, stamps = _frames("cam0", 12)
    stamps = stamps.copy()
    stamps[6:] += 2_000_000_000  # a gap: restart
    stamps[10:] -= 3_000_000_000  # time going back: restart
    ref = _offline(load_config(EUROC), imgs, stamps, tmp_path / "ref")
    assert len(ref[3]) == 2 and len(ref[2]) >= 2
    summary = tmp_path / "summary.json"
    node = _ros.start_node(ros_master, [EUROC, "--latency", "--summary", summary])
    try:
        spec = {"cameras": [{"topic": "/cam0/image_raw", "outputs": "/feature_tracker/"}],
                "frames": [[(0, int(s), im, "mono8")] for s, im in zip(ref[0], imgs)], "images": True}
        res = _ros.drive(ros_master, spec)
    finally:
        rc, out, err = _ros.stop_node(node, signal.SIGTERM)
    assert rc == 0, err
    _assert_equal_to_offline(res["feature"][0], res["latency"][0], ref)
    assert res["restart"][0] == [True, True]
    assert res["feature_img"][0] >= len(ref[2])  # every published frame, the first one too
    s = json.loads(summary.read_text())
    assert (s["received"], s["tracked"], s["dropped"]) == (12, 12, 0)
    assert s["cameras"][0]["outputs"] == "/feature_tracker/feature"
    assert "latency       image received -> feature published: median" in out


def _config_b(tmp_path):
    """Another camera: EuRoC's intrinsics on a 376x240 crop, 60 features, min_dist 20."""
    text = EUROC.read_text()
    for a, b in (("image_width: 752", "image_width: 376"), ("image_height: 480", "image_height: 240"),
                 ("max_cnt: 150", "max_cnt: 60"), ("min_dist: 30", "min_dist: 20")):
        assert a in text, a
        text = text.replace(a, b)
    p = tmp_path / "small.yaml"
    p.write_text(text)
    return p


def test_four_cameras_each_equal_its_own_offline_run(ros_master, tmp_path):
    """Four topics, two configs (two sizes: a padded mixed batch), mono8/bgr8/rgb8/8UC1, the
    second config's cameras starting two rounds later; each camera's messages equal its own
    one-camera offline run. Stopped with SIGINT: exit 0."""
    from torch_frontend.config import load_config

    small = _config_b(tmp_path)
    n = 6
    a0, s0 = _frames("cam0", n)
    a1, s1 = _frames("cam1", n)
    b0, t0 = _frames("cam0", n, crop=(240, 376))
    b1, t1 = _frames("cam1", n, crop=(240, 376))
    t0 = t0 + 50_000_000  # other stamps than the first config's cameras
    cams = [("a", "/camA0/image_raw", a0, s0, "mono8"), ("a", "/camA1/image_raw", a1, s1, "bgr8"),
            ("b", "/camB0/image_raw", b0, t0, "rgb8"), ("b", "/camB1/image_raw", b1, t1, "8UC1")]
    cfgs = {"a": (EUROC, load_config(EUROC)), "b": (small, load_config(small))}
    refs = [_offline(cfgs[k][1], im, st, tmp_path / f"ref{i}") for i, (k, _t, im, st, _e) in enumerate(cams)]
    rounds = []
    for r in range(n + 2):
        rnd = []
        for i, (k, _t, im, _st, enc) in enumerate(cams):
            j = r if k == "a" else r - 2
            if 0 <= j < n:
                rnd.append((i, int(refs[i][0][j]), im[j], enc))
        rounds.append(rnd)
    summary = tmp_path / "summary.json"
    node = _ros.start_node(ros_master, [f"{cfgs[k][0]}@{t}" for k, t, *_ in cams]
                           + ["--latency", "--sync-wait", "200", "--summary", summary])
    try:
        spec = {"cameras": [{"topic": t, "outputs": f"{t.rsplit('/', 1)[0]}/feature_tracker/"} for _k, t, *_ in cams],
                "frames": rounds}
        res = _ros.drive(ros_master, spec)
    finally:
        rc, out, err = _ros.stop_node(node, signal.SIGINT)
    assert rc == 0, err
    for i in range(4):
        _assert_equal_to_offline(res["feature"][i], res["latency"][i], refs[i])
        assert len(refs[i][2]) >= 1
    s = json.loads(summary.read_text())
    assert (s["tracked"], s["dropped"]) == (4 * n, 0)
    assert [c["outputs"] for c in s["cameras"]] == [f"/cam{x}/feature_tracker/feature" for x in ("A0", "A1", "B0", "B1")]


@pytest.mark.slow
def test_bad_encoding_stops_the_node_naming_it(ros_master):
    node = _ros.start_node(ros_master, [EUROC])
    try:
        spec = {"cameras": [{"topic": "/cam0/image_raw", "outputs": "/feature_tracker/"}], "wait": "none",
                "latency": False, "settle": 0.0,
                "frames": [[(0, 1_000_000_000, np.zeros((480, 752), np.uint8), "16UC1")]]}
        _ros.drive(ros_master, spec)
        out, err = node.communicate(timeout=120)
    finally:
        if node.poll() is None:
            _ros.stop_node(node, signal.SIGKILL)
    assert node.returncode == 1, err
    assert "torch-frontend: error: /cam0/image_raw: image encoding '16UC1' is not supported" in err


@pytest.mark.slow
def test_drop_policy_keeps_the_newest_and_counts(ros_master, tmp_path):
    """A burst of 16 frames at a queue of 1: the tracker is slower than the burst, frames are
    dropped (counted and logged), received = tracked + dropped, the last frame is tracked."""
    imgs, stamps = _frames("cam0", 16)
    summary = tmp_path / "summary.json"
    node = _ros.start_node(ros_master, [EUROC, "--latency", "--queue-size", "1", "--summary", summary])
    try:
        spec = {"cameras": [{"topic": "/cam0/image_raw", "outputs": "/feature_tracker/"}], "wait": "none",
                "frames": [[(0, int(s), im, "mono8") for s, im in zip(stamps, imgs)]], "settle": 20.0}
        res = _ros.drive(ros_master, spec)
    finally:
        rc, out, err = _ros.stop_node(node, signal.SIGTERM)
    assert rc == 0, err
    s = json.loads(summary.read_text())["cameras"][0]
    assert s["received"] == 16 and s["dropped"] > 0 and s["tracked"] + s["dropped"] == 16
    tracked = [int(a) * 10**9 + int(b) for a, b, *_ in res["latency"][0]]
    assert tracked == sorted(tracked) and tracked[-1] == int(stamps[-1])
    assert f"dropped {s['dropped']} frames in the last" in err or "dropped" in err


@pytest.mark.slow
def test_remapping_namespace_and_node_name(ros_master, tmp_path):
    """``__ns:=`` and ``__name:=`` go to rospy: the outputs move with them; a topic remap moves the
    subscription."""
    imgs, stamps = _frames("cam0", 5)
    summary = tmp_path / "summary.json"
    node = _ros.start_node(ros_master, [EUROC, "__ns:=/uav1", "__name:=front", "/cam0/image_raw:=/uav1/image",
                                        "--latency", "--summary", summary])
    try:
        spec = {"cameras": [{"topic": "/uav1/image", "outputs": "/uav1/front/"}],
                "frames": [[(0, int(s), im, "mono8")] for s, im in zip(stamps, imgs)]}
        res = _ros.drive(ros_master, spec)
    finally:
        rc, out, err = _ros.stop_node(node, signal.SIGTERM)
    assert rc == 0, err
    assert len(res["latency"][0]) == 5 and len(res["feature"][0]) == 1  # frames 2 and 4 published, 4 sent
    assert json.loads(summary.read_text())["cameras"][0]["outputs"] == "/uav1/front/feature"
