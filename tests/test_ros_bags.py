"""Feature bags (issue 32): ``track --write-bag`` writes VINS-Mono's ``feature_tracker_node`` topics
into ROS 1 / ROS 2 bags inside the run's output set, ``io.read_feature_bag`` reads them back, and
``compare`` measures the agreement of two front ends. The written bags are checked with ``rosbags``
itself, not with our reader. Inputs: a tiny bag of cropped sample frames plus an IMU topic, built here."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ._helpers import bag_writer, crop, run_cli, small_config
from .conftest import load_gray, sample_frames

pytest.importorskip("rosbags")

N_FRAMES = 10
GAP_AT = 8  # frames from here on come 2 s later: the clock restarts (spec §3.2 step 2)
IMU_TOPIC = "/imu0"  # configs/euroc.yaml's imu_topic


def _stamps():
    s = np.array([int(f.stem) for f in sample_frames("cam0")[:N_FRAMES]], dtype=np.int64)
    s[GAP_AT:] += 2_000_000_000
    return s


def _input_bag(path, version=1):
    """Cropped sample frames on /cam0/image_raw and 5 sensor_msgs/Imu messages per frame on /imu0."""
    ts, w, ser = bag_writer(path, version)
    T = ts.types
    seq = {"seq": 0} if version == 1 else {}

    def header(ns, fid):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(ns) // 10**9,
                                        nanosec=int(ns) % 10**9), frame_id=fid, **seq)

    rng = np.random.default_rng(0)
    V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    with w:
        cam = w.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        imu = w.add_connection(IMU_TOPIC, "sensor_msgs/msg/Imu", typestore=ts)
        for f, ns in zip(sample_frames("cam0")[:N_FRAMES], _stamps()):
            img = crop(load_gray(f))
            msg = T["sensor_msgs/msg/Image"](header=header(ns, "cam0"), height=img.shape[0], width=img.shape[1],
                                             encoding="mono8", is_bigendian=0, step=img.shape[1], data=img.ravel())
            w.write(cam, int(ns) + 1000, ser(msg, "sensor_msgs/msg/Image"))
            for k in range(5):
                t = int(ns) + k * 10_000_000
                a = rng.normal(size=6)
                m = T["sensor_msgs/msg/Imu"](
                    header=header(t, "imu4"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.array([-1.0] + [0.0] * 8), angular_velocity=V(x=a[0], y=a[1], z=a[2]),
                    angular_velocity_covariance=np.zeros(9), linear_acceleration=V(x=a[3], y=a[4], z=a[5]),
                    linear_acceleration_covariance=np.zeros(9))
                w.write(imu, t + 500, ser(m, "sensor_msgs/msg/Imu"))
    return path


def _messages(path, topic):
    """``[(msgtype, bag time, raw, message)]`` of ``topic``, read with rosbags' AnyReader."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        conns = [c for c in r.connections if c.topic == topic]
        if not conns:  # messages(connections=[]) would read every topic
            return []
        return [(c.msgtype, t, bytes(raw), r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages(connections=conns)]


def _track(tmp_path, name, inputs, **bag):
    from torch_frontend.pipelines.track import TrackOptions, run_track

    out = tmp_path / name
    opt = TrackOptions(progress=False, write_tracks=False, **bag)
    run_track(small_config(tmp_path), [("bag", str(p)) for p in inputs], out, opt)
    return out


@pytest.fixture(scope="module")
def in_bag(tmp_path_factory):
    return _input_bag(tmp_path_factory.mktemp("input") / "in.bag")


@pytest.mark.parametrize("name,fmt", [("features.bag", "ros1"), ("features_db3", "ros2")])
def test_written_bag_is_vins_layout(tmp_path, in_bag, name, fmt):
    out = _track(tmp_path, "run", [in_bag], bag=name)
    bag = out / name
    assert bag.is_file() if fmt == "ros1" else (bag / "metadata.yaml").is_file()
    marker = json.loads((out / "written-by-torch-frontend.json").read_text())
    assert (name in marker["files"]) if fmt == "ros1" else (name in marker["folders"])
    z = np.load(out / "features.npz")
    csv = np.loadtxt(out / "features.csv", delimiter=",", skiprows=1)
    msgs = _messages(bag, "/feature_tracker/feature")
    assert msgs and all(m[0] == "sensor_msgs/msg/PointCloud" for m in msgs)
    stamps = sorted(set(z["stamp_ns"].tolist()))
    with_points = [m for m in msgs if len(m[3].points)]
    assert [int(m[3].header.stamp.sec) * 10**9 + int(m[3].header.stamp.nanosec) for m in with_points] == stamps
    rows = 0
    for k, (_, t, _, msg) in enumerate(msgs):
        ns = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
        assert t == ns and msg.header.frame_id == "world"
        if fmt == "ros1":
            assert msg.header.seq == k
        assert [c.name for c in msg.channels] == ["", "", "", "", ""]
        sel = z["stamp_ns"] == ns
        n = int(sel.sum())
        assert len(msg.points) == n and all(len(c.values) == n for c in msg.channels)
        if not n:
            continue
        rows += n
        pts = np.array([(p.x, p.y, p.z) for p in msg.points])
        ch = [np.asarray(c.values) for c in msg.channels]
        assert all(c.dtype == np.float32 for c in ch)
        # the exact float32 of the run's values, in features.csv's row order
        for got, key in zip([pts[:, 0], pts[:, 1], *ch], ("x", "y", "id", "u", "v", "vx", "vy")):
            np.testing.assert_array_equal(got, z[key][sel].astype(np.float32), err_msg=key)
        np.testing.assert_array_equal(pts[:, 2], 1.0)
        c = csv[np.round(csv[:, 1] * 1e9).astype(np.int64) // 1000 == ns // 1000]
        np.testing.assert_allclose(np.stack([pts[:, 0], pts[:, 1], *ch], 1), c[:, [3, 4, 2, 5, 6, 7, 8]],
                                   rtol=1e-6, atol=1e-6)
    assert rows == len(z["id"]) > 0
    restarts = _messages(bag, "/feature_tracker/restart")
    assert [(m[0], m[1], m[3].data) for m in restarts] == [("std_msgs/msg/Bool", int(_stamps()[GAP_AT]), True)]


@pytest.mark.parametrize("name", ["features.bag", "features_db3"])
def test_imu_copied_unchanged(tmp_path, in_bag, name):
    out = _track(tmp_path, "run", [in_bag], bag=name)
    src, dst = _messages(in_bag, IMU_TOPIC), _messages(out / name, IMU_TOPIC)
    assert len(dst) == len(src) == 5 * N_FRAMES
    assert [m[1] for m in dst] == [m[1] for m in src] and all(m[0] == "sensor_msgs/msg/Imu" for m in dst)
    if name.endswith(".bag"):  # same serialisation: the bytes as recorded
        assert [m[2] for m in dst] == [m[2] for m in src]
    for a, b in zip(src, dst):
        for f in ("angular_velocity", "linear_acceleration"):
            va, vb = getattr(a[3], f), getattr(b[3], f)
            assert (va.x, va.y, va.z) == (vb.x, vb.y, vb.z)
        assert a[3].header.stamp == b[3].header.stamp and a[3].header.frame_id == b[3].header.frame_id
    out2 = _track(tmp_path, "noimu", [in_bag], bag=name, bag_imu=False)
    assert _messages(out2 / name, IMU_TOPIC) == []


def test_ros2_input_and_images(tmp_path):
    inp = _input_bag(tmp_path / "in_db3", version=2)
    out = _track(tmp_path, "run", [inp], bag="f.bag", bag_images=True)
    imgs = _messages(out / "f.bag", "/feature_tracker/feature_img")
    summary = json.loads((out / "summary.json").read_text())
    assert len(imgs) == summary["published"] > 0
    assert imgs[0][3].encoding == "bgr8" and (imgs[0][3].height, imgs[0][3].width) == (192, 256)
    src, dst = _messages(inp, IMU_TOPIC), _messages(out / "f.bag", IMU_TOPIC)  # CDR -> ROS 1
    assert [m[3].linear_acceleration.x for m in dst] == [m[3].linear_acceleration.x for m in src]


def test_reader_round_trip_and_streams(tmp_path, in_bag):
    from torch_frontend.io import read_feature_bag

    out = _track(tmp_path, "run", [in_bag, in_bag], bag="features_db3", bag_format="ros1")
    names = sorted(p.name for p in out.iterdir() if "features_db3" in p.name)
    # ROS 1 by --bag-format: the readers need the .bag suffix
    assert names == ["features_db3_stream0.bag", "features_db3_stream1.bag"] and (out / names[0]).is_file()
    z = np.load(out / "features.npz")
    for b, name in enumerate(names):
        fb = read_feature_bag(out / name)
        assert fb.restarts == [int(_stamps()[GAP_AT])]
        got = [f for f in fb.frames if len(f.ids)]
        sel = z["stream"] == b
        assert np.concatenate([f.ids for f in got]).tolist() == z["id"][sel].tolist()
        np.testing.assert_array_equal(np.concatenate([f.uv for f in got]),
                                      np.stack([z["u"][sel], z["v"][sel]], 1).astype(np.float32))
        np.testing.assert_array_equal(np.concatenate([f.xy for f in got]),
                                      np.stack([z["x"][sel], z["y"][sel]], 1).astype(np.float32))
        assert np.repeat([f.stamp_ns for f in got], [len(f.ids) for f in got]).tolist() == z["stamp_ns"][sel].tolist()
        assert all(f.frame_id == "world" and (f.camera == 0).all() for f in got)
        assert got[0].track_count.tolist() == [1] * len(got[0].ids)


def test_stereo_id_encoding(tmp_path):
    """VINS-Fusion stereo: one point per observation, id channel = id * 2 + camera."""
    from torch_frontend.io import FeatureBagWriter, FeatureMessage, read_feature_bag

    m = FeatureMessage(stamp_ns=1_000_000_001, ids=np.array([3, 3, 7]), camera=np.array([0, 1, 0]),
                       xy=np.array([[0.1, 0.2], [0.05, 0.2], [-0.3, 0.4]]),
                       uv=np.array([[10.5, 20.25], [5.5, 20.25], [30.0, 40.0]]), velocity=np.zeros((3, 2)))
    with FeatureBagWriter(tmp_path / "s.bag", num_cameras=2) as w:
        w.write_features(m)
    (_, _, _, msg), = _messages(tmp_path / "s.bag", "/feature_tracker/feature")
    assert np.asarray(msg.channels[0].values).tolist() == [6.0, 7.0, 14.0]
    f, = read_feature_bag(tmp_path / "s.bag", num_cameras=2).frames
    assert f.ids.tolist() == [3, 3, 7] and f.camera.tolist() == [0, 1, 0]


def test_compare(tmp_path, in_bag, capsys):
    a = _track(tmp_path, "a", [in_bag], bag="features.bag")
    b = _track(tmp_path, "b", [in_bag])  # no bag: compared through features.npz
    rc, out, err = run_cli(capsys, "compare", a / "features.bag", b, "--out", tmp_path / "cmp")
    assert rc == 0, err
    assert "agreement     100.00 %" in out
    r = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert r["agreement"] == 1.0 and r["agreeing"] == r["reference_features"] > 0
    assert (tmp_path / "cmp" / "compare.png").stat().st_size > 1000
    # perturbed: fewer corners (max_cnt 30) -> other tracks, less agreement
    from torch_frontend.pipelines.compare import run_compare
    from torch_frontend.pipelines.track import TrackOptions, run_track

    run_track(small_config(tmp_path, max_cnt=30), [("bag", str(in_bag))], tmp_path / "c",
              TrackOptions(progress=False, write_tracks=False, bag="features.bag"))
    r2 = run_compare(a / "features.bag", tmp_path / "c", tmp_path / "cmp2")
    assert 0 < r2["agreement"] < 1.0
    assert r2["tracks_matched"] < r2["tracks_reference"]


def test_euroc_imu_and_cli_flags(tmp_path, capsys):
    from ._helpers import make_asl

    root = make_asl(tmp_path / "seq", n=6, small=True)
    imu = root / "mav0" / "imu0"
    imu.mkdir()
    rows = [(1403715273262142976 + k * 5_000_000, 0.1 * k, -0.2, 0.3, 9.8, 0.01 * k, -0.5) for k in range(7)]
    (imu / "data.csv").write_text("#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n"
                                  + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    out = tmp_path / "out"
    rc, _, err = run_cli(capsys, "track", small_config(tmp_path), "--euroc", root, "--out", out, "--no-progress",
                         "--no-tracks", "--write-bag", "f_db3")
    assert rc == 0, err
    msgs = _messages(out / "f_db3", IMU_TOPIC)
    assert [m[0] for m in msgs] == ["sensor_msgs/msg/Imu"] * 7
    got = [(m[1], m[3].angular_velocity.x, m[3].linear_acceleration.y, m[3].orientation_covariance[0]) for m in msgs]
    assert got == [(r[0], r[1], r[5], -1.0) for r in rows]
    rc, _, err = run_cli(capsys, "track", small_config(tmp_path), "--euroc", root, "--out", tmp_path / "o2",
                         "--write-bag", "sub/f.bag")
    assert rc == 2 and "--write-bag" in err and "sub/f.bag" in err and not (tmp_path / "o2").exists()


def test_failed_run_leaves_no_bag(tmp_path):
    """The bags are part of the atomic output set: a run that fails leaves ``out`` as it was."""
    from torch_frontend.outputs import RunRecorder

    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="boom"):
        with RunRecorder(out, ["a", "b"], write_tracks=False, bag="features.bag") as rec:
            assert sorted(p.name for p in rec._stage.path.iterdir()) == ["features_stream0.bag",
                                                                          "features_stream1.bag"]
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []  # not even the folder the recorder made
