"""Dataset readers (EuRoC/ASL folders, image folders, ROS 1/2 bags), MultiStream and output writers.

Fixtures are built in ``tmp_path`` from a few of the repo's sample EuRoC frames; the bags are
written in the test with the ``rosbags`` writers and typestore serialisation.
"""

from __future__ import annotations

import json
import shutil
import warnings

import cv2
import numpy as np
import pytest
import torch

from tests.conftest import SAMPLE, load_gray, sample_frames, shared_data_or_skip
from torch_frontend.errors import BadFrameError, DataWarning
from torch_frontend.io import (
    DataError,
    EurocSequence,
    ImageFolderSequence,
    MultiStream,
    RosbagSequence,
    camera_from_sensor_yaml,
    config_from_sensor_yaml,
    euroc_config,
    list_image_topics,
    open_sequence,
    read_image,
)
from torch_frontend.io.multistream import ns_to_seconds

from ._helpers import TOPIC, make_asl, small_frames, truncate, write_bag

# ----------------------------------------------------------------------------------------------
# images


def test_read_image_matches_cv2():
    f = sample_frames("cam0")[0]
    img = read_image(f)
    assert img.dtype == np.uint8 and img.shape == (480, 752)
    np.testing.assert_array_equal(img, load_gray(f))


def test_bad_png_files(tmp_path):
    f = sample_frames("cam0")[0]
    t = tmp_path / "t.png"
    shutil.copy(f, t)
    truncate(t)
    with pytest.raises(DataError, match=r"t\.png: truncated PNG"):
        read_image(t)
    c = tmp_path / "c.png"
    data = bytearray(f.read_bytes())
    data[5000] ^= 0xFF
    c.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"c\.png: corrupt PNG \(CRC mismatch"):
        read_image(c)
    e = tmp_path / "e.png"
    e.write_bytes(b"")
    with pytest.raises(DataError, match="empty image file"):
        read_image(e)
    with pytest.raises(DataError, match="image file not found"):
        read_image(tmp_path / "missing.png")
    j = tmp_path / "j.jpg"
    j.write_bytes(b"not a jpeg at all")
    with pytest.raises(DataError, match="cannot decode image"):
        read_image(j)


def test_colour_and_16bit_images_become_gray(tmp_path):
    g = load_gray(sample_frames("cam0")[0])[:50, :60]
    cv2.imwrite(str(tmp_path / "c.png"), np.repeat(g[:, :, None], 3, axis=2))
    np.testing.assert_array_equal(read_image(tmp_path / "c.png"), g)
    cv2.imwrite(str(tmp_path / "w.png"), g.astype(np.uint16) * 256 + 77)
    np.testing.assert_array_equal(read_image(tmp_path / "w.png"), g)


# ----------------------------------------------------------------------------------------------
# EuRoC / ASL


def test_euroc_reader(tmp_path):
    root = make_asl(tmp_path / "seq", n=4)
    frames_src = sample_frames("cam0")[:4]
    for arg in (root, root / "mav0", root / "mav0" / "cam0"):
        seq = EurocSequence(arg)
        assert len(seq) == 4
    frames = list(seq)
    assert [f.stamp_ns for f in frames] == [int(p.stem) for p in frames_src]
    assert frames[0].stamp_ns == 1403715273262142976  # exact ns, no float rounding
    for f, p in zip(frames, frames_src):
        np.testing.assert_array_equal(f.image, load_gray(p))
    assert abs(frames[1].timestamp - frames[0].timestamp - 0.05) < 1e-6


def test_io_reexports_the_foundation_names():
    """The documented ``torch_frontend.io`` names of the readers below it are those objects."""
    import torch_frontend.config as config
    import torch_frontend.io as io_pkg
    import torch_frontend.opencv_yaml as opencv_yaml
    import torch_frontend.trajectory as trajectory

    assert io_pkg.read_opencv_yaml is opencv_yaml.read_opencv_yaml
    assert camera_from_sensor_yaml is config.camera_from_sensor_yaml
    assert config_from_sensor_yaml is config.config_from_sensor_yaml
    for name in ("Trajectory", "read_trajectory", "write_tum", "write_vins_csv", "interpolate", "covered",
                 "associate", "align_se3", "ate_rmse", "add_drift"):
        assert getattr(io_pkg, name) is getattr(trajectory, name), name
        assert name in dir(io_pkg)
    for name in io_pkg.__all__:
        assert getattr(io_pkg, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        io_pkg.nope  # noqa: B018


def test_euroc_config_from_folder():
    cfg = euroc_config(SAMPLE)
    assert (cfg.image_width, cfg.image_height, cfg.max_cnt, cfg.min_dist, cfg.freq) == (752, 480, 150, 30, 10)
    assert cfg.equalize and cfg.path.endswith("sensor.yaml")


def test_euroc_errors(tmp_path):
    with pytest.raises(DataError, match="folder not found"):
        EurocSequence(tmp_path / "nope")
    (tmp_path / "plain").mkdir()
    with pytest.raises(DataError, match="not an EuRoC/ASL folder"):
        EurocSequence(tmp_path / "plain")
    root = make_asl(tmp_path / "empty", frames=[])
    with pytest.raises(DataError, match="empty sequence"):
        EurocSequence(root)
    root = make_asl(tmp_path / "bad", n=2)
    csv = root / "mav0" / "cam0" / "data.csv"
    csv.write_text(csv.read_text() + "12x4,foo.png\n")
    with pytest.raises(DataError, match=r"data\.csv:4: timestamp is not an integer"):
        EurocSequence(root)


def test_euroc_skip_bad_frames(tmp_path):
    root = make_asl(tmp_path / "seq", n=4)
    bad = sorted((root / "mav0" / "cam0" / "data").glob("*.png"))[1]
    truncate(bad)
    with pytest.raises(BadFrameError, match=bad.name) as e:  # a DataError that names the option going on
        list(EurocSequence(root))
    assert isinstance(e.value, DataError) and "`skip_bad`" in str(e.value)
    seq = EurocSequence(root, skip_bad=True)
    frames = list(seq)
    assert [f.index for f in frames] == [0, 2, 3]
    assert len(seq.skipped) == 1 and bad.name in seq.skipped[0][0] and "truncated" in seq.skipped[0][1]


# ----------------------------------------------------------------------------------------------
# image folders


def test_image_folder_timestamps(tmp_path):
    src = sample_frames("cam0")[:3]
    ns = tmp_path / "ns"
    ns.mkdir()
    for f in reversed(src):
        shutil.copy(f, ns / f.name)
    seq = ImageFolderSequence(ns)
    assert [f.stamp_ns for f in seq] == [int(f.stem) for f in src]

    secs = tmp_path / "secs"
    secs.mkdir()
    for name in ("10.5.png", "9.25.png", "11.0.png"):
        shutil.copy(src[0], secs / name)
    assert [f.stamp_ns for f in ImageFolderSequence(secs)] == [9_250_000_000, 10_500_000_000, 11_000_000_000]

    num = tmp_path / "num"
    num.mkdir()
    for i, f in enumerate(src):
        shutil.copy(f, num / f"{i:06d}.png")
    (num / "notes.txt").write_text("ignored")
    with pytest.raises(DataError, match=r"give a frame rate \(`fps`\)"):
        ImageFolderSequence(num)
    seq = ImageFolderSequence(num, fps=20)
    frames = list(seq)
    assert [f.stamp_ns for f in frames] == [0, 50_000_000, 100_000_000]
    np.testing.assert_array_equal(frames[2].image, load_gray(src[2]))


def test_image_folder_errors(tmp_path):
    with pytest.raises(DataError, match="folder not found"):
        ImageFolderSequence(tmp_path / "nope")
    (tmp_path / "e").mkdir()
    with pytest.raises(DataError, match="empty sequence"):
        ImageFolderSequence(tmp_path / "e")
    (tmp_path / "f.png").write_bytes(b"")
    with pytest.raises(DataError, match="not a folder"):
        ImageFolderSequence(tmp_path / "f.png")
    (tmp_path / "g").mkdir()
    shutil.copy(sample_frames()[0], tmp_path / "g" / "000001.png")
    with pytest.raises(DataError, match=r"fps: expected a frame rate > 0 \(Hz\), got 0"):
        ImageFolderSequence(tmp_path / "g", fps=0)


# ----------------------------------------------------------------------------------------------
# ROS bags


@pytest.mark.parametrize("version", [1, 2], ids=["ros1", "ros2"])
@pytest.mark.parametrize("kind", ["mono8", "bgr8", "rgb8", "compressed"])
def test_rosbag_reader(tmp_path, version, kind):
    frames = small_frames(3)
    path = tmp_path / ("b.bag" if version == 1 else "b2")
    write_bag(path, frames, version=version, encoding="mono8" if kind == "compressed" else kind,
              compressed=kind == "compressed")
    assert list_image_topics(path) == [TOPIC]
    seq = RosbagSequence(path, TOPIC)
    assert len(seq) == 3
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = list(seq)
    notes = [str(w.message) for w in caught if issubclass(w.category, DataWarning)]
    if kind in ("bgr8", "rgb8"):  # one note for the sequence, naming its colour order
        assert len(notes) == 1 and "colour frames" in notes[0] and kind[:3].upper() in notes[0], notes
    else:
        assert notes == []
    assert [f.stamp_ns for f in got] == [s for s, _ in frames]  # header stamps, not bag times
    for f, (_, img) in zip(got, frames):
        assert f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, img)


def test_rosbag_errors(tmp_path):
    path = write_bag(tmp_path / "b.bag", small_frames(2))
    with pytest.raises(DataError, match=r"no topic '/cam1/image_raw' \(image topics in the bag: /cam0/image_raw\)"):
        RosbagSequence(path, "/cam1/image_raw")
    with pytest.raises(DataError, match="has type std_msgs/msg/String"):
        RosbagSequence(path, "/imu0")
    with pytest.raises(DataError, match="bag not found"):
        RosbagSequence(tmp_path / "missing.bag", TOPIC)
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"definitely not a bag")
    with pytest.raises(DataError, match="cannot open ROS bag"):
        RosbagSequence(junk, TOPIC)
    (tmp_path / "dir").mkdir()
    with pytest.raises(DataError, match="no metadata.yaml"):
        RosbagSequence(tmp_path / "dir", TOPIC)
    with pytest.raises(DataError, match="no image topic given"):
        open_sequence("bag", path, topic="")


# ----------------------------------------------------------------------------------------------
# MultiStream


def test_multistream_streams_end_independently(tmp_path):
    a = make_asl(tmp_path / "a", n=5)
    b = make_asl(tmp_path / "b", n=2)
    ms = MultiStream([EurocSequence(a), EurocSequence(b)], size=(480, 752))
    assert len(ms) == 5 and ms.num_streams == 2
    batches = list(ms)
    assert len(batches) == 5
    alive = torch.stack([x.alive for x in batches])
    assert alive[:, 0].all() and alive[:2, 1].all() and not alive[2:, 1].any()
    for x in batches:
        assert x.images.shape == (2, 1, 480, 752) and x.images.dtype == torch.uint8
        assert x.timestamps.dtype == torch.float64
        np.testing.assert_allclose(x.timestamps.numpy(), ns_to_seconds(x.stamps_ns), rtol=0, atol=0)
    # dead stream: its last image and last timestamp again
    assert batches[4].stamps_ns[1] == batches[1].stamps_ns[1]
    assert torch.equal(batches[4].images[1], batches[1].images[1])
    assert batches[4].stamps_ns[0] == int(sample_frames("cam0")[4].stem)
    assert len(list(MultiStream([EurocSequence(a)], max_steps=3))) == 3


def test_shared_euroc_excerpt_cam0_and_cam1():
    """The larger real excerpt: cam0 (95 frames) and cam1 (30) as two streams; cam1 ends first."""
    root = shared_data_or_skip("sequences", "euroc_v1_01_easy_micro")
    cam0, cam1 = EurocSequence(root, "cam0"), EurocSequence(root, "cam1")
    assert (len(cam0), len(cam1)) == (95, 30)
    ms = MultiStream([cam0, cam1], size=(480, 752), max_steps=32)
    alive = [bool(b.alive[1]) for b in ms]
    assert len(alive) == 32 and all(alive[:30]) and not any(alive[30:])
    cam = camera_from_sensor_yaml(cam1.sensor_yaml)
    assert (cam.width, cam.height) == (752, 480) and float(cam.params_dict()["fx"]) != 458.654


def test_multistream_errors(tmp_path):
    a = make_asl(tmp_path / "a", n=2)
    with pytest.raises(DataError, match=r"image size 752x480 differs from the expected 640x480"):
        list(MultiStream([EurocSequence(a)], size=(480, 640)))
    for p in (a / "mav0" / "cam0" / "data").glob("*.png"):
        truncate(p)
    with pytest.raises(DataError, match="no readable frame"):
        list(MultiStream([EurocSequence(a, skip_bad=True)]))
    with pytest.raises(DataError, match="no input sequence"):
        MultiStream([])


def test_ns_to_seconds_is_accurate():
    s = np.array([1403715273262142976, 5], dtype=np.int64)
    t = ns_to_seconds(s)
    assert abs(t[0] - 1403715273.262142976) < 3e-7 and t[1] == 5e-9


# ----------------------------------------------------------------------------------------------
# outputs: atomic writes


def test_atomic_writes_leave_no_partial_file(tmp_path):
    from torch_frontend.outputs import RunRecorder, atomic_path, write_text_atomic

    p = tmp_path / "summary.json"
    write_text_atomic(p, json.dumps({"a": 1}))
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text('{"a": 2, "half')
            raise RuntimeError("interrupted")
    assert json.loads(p.read_text()) == {"a": 1}  # old content intact
    assert sorted(x.name for x in tmp_path.iterdir()) == ["summary.json"]  # no temporary left
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        with RunRecorder(out, ["s0"], write_tracks=True):
            raise KeyboardInterrupt
    assert not out.exists()  # nor the folder the recorder made


@pytest.mark.parametrize("stop", ["interrupt", "job_aborted", "error"])
def test_run_recorder_written_set_waits_for_commit_and_a_checkpointed_stop_keeps_it(tmp_path, stop):
    """``write(commit=False)`` fills the staging folder only and ``commit()`` swaps it in; a
    checkpointed recorder (``keep_on_interrupt``) stopped by an interrupt or by
    ``distributed.JobAborted`` (another rank failed) leaves its staging folder for the resume,
    with the track images in it; any other error removes it."""
    from torch_frontend.distributed import JobAborted
    from torch_frontend.outputs import RunRecorder

    out = tmp_path / "out"
    with RunRecorder(out, ["s0"], write_tracks=False) as rec:
        staged = rec.stage_path
        paths = rec.write({"frames": 0}, plots=False, commit=False)
        assert not (out / "features.csv").exists() and (staged / "features.csv").is_file()
        assert rec.commit() == paths
    assert (out / "features.csv").is_file() and not staged.exists()
    with pytest.raises(RuntimeError, match="nothing written to commit"):
        rec.commit()

    out2 = tmp_path / "out2"
    exc = {"interrupt": KeyboardInterrupt(), "job_aborted": JobAborted(), "error": RuntimeError("boom")}[stop]
    with pytest.raises(type(exc)):
        with RunRecorder(out2, ["s0"], write_tracks=True) as rec:
            staged = rec.stage_path
            (staged / "tracks" / "stream0").mkdir()
            (staged / "tracks" / "stream0" / "0000000000000000001.png").write_bytes(b"png")
            rec.keep_on_interrupt = True  # a checkpoint covers it
            raise exc
    assert staged.is_dir() == (stop != "error")
    # the folder the recorder made: kept empty beside a kept staging folder, else removed with it
    assert list(out2.iterdir()) == [] if stop != "error" else not out2.exists()


def test_replace_dir_swaps_folders(tmp_path):
    from torch_frontend.outputs import replace_dir

    final = tmp_path / "tracks"
    final.mkdir()
    (final / "old.png").write_bytes(b"old")
    new = tmp_path / ".tracks.tmp"
    (new / "stream0").mkdir(parents=True)
    (new / "stream0" / "1.png").write_bytes(b"new")
    replace_dir(new, final)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tracks"]
    assert [p.name for p in final.iterdir()] == ["stream0"] and (final / "stream0" / "1.png").read_bytes() == b"new"
