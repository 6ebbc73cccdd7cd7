"""Helpers shared by several test modules: input folders, bags and configs built in ``tmp_path``
from the repo's sample frames, and the CLI runner. (No test module imports another test module.)"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from .conftest import REPO, SAMPLE, load_gray, sample_frames

# ----------------------------------------------------------------------------------------------
# input folders, bags and configs

TOPIC = "/cam0/image_raw"


CROP = (192, 256)  # (H, W) of the small test frames: rows 144.., cols 248.. of the sample


def crop(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(img[144:144 + CROP[0], 248:248 + CROP[1]])


def make_asl(root: Path, n: int = 4, camera: str = "cam0", frames=None, small: bool = False) -> Path:
    """An ASL folder ``root/mav0/<camera>`` with the first ``n`` sample frames (``small``: cropped
    to ``CROP``, use ``small_config``), data.csv and sensor.yaml."""
    src = SAMPLE / "mav0" / "cam0"
    cam = root / "mav0" / camera
    (cam / "data").mkdir(parents=True)
    frames = list(frames if frames is not None else sample_frames("cam0")[:n])
    lines = ["#timestamp [ns],filename"]
    for f in frames:
        if small:
            assert cv2.imwrite(str(cam / "data" / f.name), crop(load_gray(f)))
        else:
            shutil.copy(f, cam / "data" / f.name)
        lines.append(f"{f.stem},{f.name}")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    yaml = (src / "sensor.yaml").read_text()
    if small:  # the crop's size and principal point
        yaml = yaml.replace("resolution: [752, 480]", f"resolution: [{CROP[1]}, {CROP[0]}]").replace(
            "367.215, 248.375", f"{367.215 - 248}, {248.375 - 144}")
    (cam / "sensor.yaml").write_text(yaml)
    return root


def make_loop_inputs(root: Path, keyframes_per_lap: int = 8) -> list:
    """The demo's revisit render, small (160 x 120, 2 laps of ``keyframes_per_lap`` keyframes), as
    two image folders (lap 1, lap 2) under ``root`` with their VIO poses and ground truth, and a
    config for its camera. Returns the ``loop`` command's arguments (without ``--out``): both laps,
    a keyframe every 2 published frames, a trained vocabulary, no progress bar."""
    from torch_frontend.geometry import R_to_quat
    from torch_frontend.pipelines import loop as loop_run
    from torch_frontend.trajectory import Trajectory, write_tum, write_vins_csv

    W, H = 160, 120
    seq = loop_run.demo_sequence(laps=2, keyframes_per_lap=keyframes_per_lap, width=W, height=H)
    cam = seq.camera
    (root / "cfg.yaml").write_text(
        "%YAML:1.0\nmodel_type: PINHOLE\ncamera_name: synthetic\n"
        f"image_width: {W}\nimage_height: {H}\n"
        "distortion_parameters:\n   k1: 0.0\n   k2: 0.0\n   p1: 0.0\n   p2: 0.0\n"
        f"projection_parameters:\n   fx: {float(cam.fx)}\n   fy: {float(cam.fy)}\n   cx: {float(cam.cx)}\n"
        f"   cy: {float(cam.cy)}\n"
        "extrinsicRotation: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: [{', '.join(str(float(v)) for v in seq.R_ic.reshape(-1).tolist())}]\n"
        "extrinsicTranslation: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n"
        f"   data: [{', '.join(str(float(v)) for v in seq.t_ic.tolist())}]\n"
        "max_cnt: 100\nmin_dist: 10\nfreq: 100\nF_threshold: 1.0\nequalize: 0\nfisheye: 0\n")
    n = len(seq.times) // 2
    args: list = []
    for i, sl in enumerate([slice(0, n), slice(n, None)]):
        d = root / f"lap{i}"
        d.mkdir()
        for t, im in zip(seq.times[sl].tolist(), seq.images[sl].numpy()):
            assert cv2.imwrite(str(d / f"{t:.6f}.png"), im)
        tt = seq.times[sl].double()
        write_vins_csv(root / f"vio{i}.csv", Trajectory(tt, seq.T_vio[sl].double(), R_to_quat(seq.R_vio[sl].double())))
        write_tum(root / f"gt{i}.tum", Trajectory(tt, seq.T_gt[sl].double(), R_to_quat(seq.R_gt[sl].double())))
        args += ["--images", d, "--poses", root / f"vio{i}.csv", "--ground-truth", root / f"gt{i}.tum"]
    return ["loop", root / "cfg.yaml", *args, "--keyframe-every", 2, "--train-vocabulary", "--no-progress"]


def small_config(tmp_path: Path, max_cnt: int = 60) -> Path:
    """``configs/euroc.yaml`` for ``CROP``-sized frames (principal point moved with the crop)."""
    text = (REPO / "configs" / "euroc.yaml").read_text()
    text = text.replace("image_width: 752", f"image_width: {CROP[1]}").replace(
        "image_height: 480", f"image_height: {CROP[0]}")
    text = text.replace("cx: 3.630e+02", "cx: 115.0").replace("cy: 2.481e+02", "cy: 104.1")
    text = text.replace("max_cnt: 150", f"max_cnt: {max_cnt}")
    p = tmp_path / "small.yaml"
    p.write_text(text)
    return p


def bag_writer(path: Path, version: int = 1):
    """``(typestore, writer, serialize)`` of a new ROS 1 (``version=1``, ``path`` ending in .bag) or
    ROS 2 bag, with rosbags' own writer (the tests' inputs are not written by the package)."""
    from rosbags.typesys import Stores, get_typestore

    if version == 1:
        from rosbags.rosbag1 import Writer

        ts = get_typestore(Stores.ROS1_NOETIC)
        return ts, Writer(path), ts.serialize_ros1
    from rosbags.rosbag2 import Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    return ts, Writer(path, version=9), ts.serialize_cdr


def write_bag(path: Path, frames, version: int = 1, topic: str = TOPIC, encoding: str = "mono8",
              compressed: bool = False) -> Path:
    """A ROS 1 (``version=1``, ``path`` ending in .bag) or ROS 2 bag of ``[(stamp_ns, gray image)]``."""
    ts, writer, ser = bag_writer(path, version)
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    msgtype = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    Msg = ts.types[msgtype]
    seq = {"seq": 0} if "seq" in Header.__dataclass_fields__ else {}
    with writer as w:
        conn = w.add_connection(topic, msgtype, typestore=ts)
        other = w.add_connection("/imu0", "std_msgs/msg/String", typestore=ts)
        for i, (stamp, img) in enumerate(frames):
            header = Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="cam0", **seq)
            if compressed:
                ok, buf = cv2.imencode(".png", img)
                assert ok
                msg = Msg(header=header, format="mono8; png compressed", data=buf.ravel())
            else:
                if encoding == "mono8":
                    data = img
                elif encoding == "bgr8":
                    data = np.repeat(img[:, :, None], 3, axis=2)
                elif encoding == "rgb8":
                    data = np.repeat(img[:, :, None], 3, axis=2)
                else:
                    raise ValueError(encoding)
                c = 1 if data.ndim == 2 else 3
                msg = Msg(header=header, height=img.shape[0], width=img.shape[1], encoding=encoding,
                          is_bigendian=0, step=img.shape[1] * c, data=np.ascontiguousarray(data).ravel())
            w.write(conn, stamp + 1000, ser(msg, msgtype))
            if i == 0:
                S = ts.types["std_msgs/msg/String"]
                w.write(other, stamp, ser(S(data="x"), "std_msgs/msg/String"))
    return path


def small_frames(n: int = 3, crop=(96, 128)):
    """``[(stamp_ns, crop of a sample frame)]`` for quick bags."""
    out = []
    for f in sample_frames("cam0")[:n]:
        out.append((int(f.stem), np.ascontiguousarray(load_gray(f)[100:100 + crop[0], 200:200 + crop[1]])))
    return out


def truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


# ----------------------------------------------------------------------------------------------
# the command line

CONFIG = str(REPO / "configs" / "euroc.yaml")
OUTPUTS = ("features.csv", "features.npz", "summary.json", "features_per_frame.png", "track_length_hist.png",
           "track_paths.png")


def run_cli(capsys, *argv):
    """``torch-frontend *argv`` in this process: ``(exit code, stdout, stderr)``."""
    from torch_frontend.cli import main

    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def assert_one_error_line(err: str, *needles: str) -> None:
    """``err`` is one ``torch-frontend: error: ...`` line (no traceback) containing every needle."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one stderr line, got: {err!r}"
    assert lines[0].startswith("torch-frontend: error: ")
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], f"{n!r} not in {lines[0]!r}"
