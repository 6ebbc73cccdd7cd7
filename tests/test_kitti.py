"""KITTI sequences (``io.kitti``, ``--kitti``): the odometry and raw layouts built here from a few
of the package's sample frames, the camera from ``P0`` (``P1``..``P3``), VINS-Mono's front-end
defaults that a ``--config`` replaces, stream names from the folders, KITTI poses in ``loop``
(6-DoF graph and ``-y`` up by default), and the CLI's errors naming flags."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tests.conftest import SAMPLE
from torch_frontend.cli import main
from torch_frontend.errors import DataError
from torch_frontend.io.kitti import KittiSequence, kitti_config
from torch_frontend.trajectory import read_trajectory

FRAMES = sorted((SAMPLE / "mav0" / "cam0" / "data").glob("*.png"))
FX, FY, CX, CY, BASELINE = 458.654, 457.296, 367.215, 248.375, 0.54


def _p(fx, fy, cx, cy, tx=0.0):
    return [fx, 0.0, cx, tx, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]


def _line(key, vals):
    return key + ": " + " ".join(f"{v:.12e}" for v in vals) + "\n"


def make_odometry(root, n=6, dt=0.1036):
    """``root`` as KITTI's ``sequences/NN``: image_0/ and image_1/ (the sample frames), calib.txt,
    times.txt; returns the times (s)."""
    for cam in ("image_0", "image_1"):
        (root / cam).mkdir(parents=True)
        for i, f in enumerate(FRAMES[:n]):
            shutil.copy(f, root / cam / f"{i:06d}.png")
    calib = (_line("P0", _p(FX, FY, CX, CY)) + _line("P1", _p(FX, FY, CX, CY, -FX * BASELINE))
             + _line("P2", _p(FX, FY, CX, CY, 44.8)) + _line("P3", _p(FX, FY, CX, CY, -330.0))
             + _line("Tr", [0, -1, 0, 0, 0, 0, -1, 0, 1, 0, 0, 0]))
    (root / "calib.txt").write_text(calib)
    times = np.round(np.arange(n) * dt, 6)
    (root / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    return times


def write_kitti_poses(path, n, step=0.3):
    """KITTI poses of a camera driving forward along z (12 values per line, no times)."""
    lines = []
    for k in range(n):
        m = np.concatenate([np.eye(3), [[0.0], [0.0], [k * step]]], axis=1)
        lines.append(" ".join(f"{v:.6e}" for v in m.reshape(-1)) + "\n")
    path.write_text("".join(lines))


@pytest.fixture
def seq(tmp_path):
    root = tmp_path / "dataset" / "sequences" / "00"
    make_odometry(root)
    return root


def test_odometry_reader_and_config(seq):
    s = KittiSequence(seq)
    assert len(s) == 6 and s.name == "00" and s.kind == "kitti"
    stamps = [f.stamp_ns for f in s]
    assert stamps == [0, 103_600_000, 207_200_000, 310_800_000, 414_400_000, 518_000_000]
    cfg = kitti_config(seq)
    cam = cfg.camera
    assert cam.model_type == "PINHOLE" and (cfg.image_width, cfg.image_height) == (752, 480)
    p = {k: float(v) for k, v in cam.params_dict().items()}
    assert (p["fx"], p["fy"], p["cx"], p["cy"]) == (FX, FY, CX, CY)
    assert p["k1"] == p["k2"] == p["p1"] == p["p2"] == 0.0
    assert (cfg.max_cnt, cfg.min_dist, cfg.freq, cfg.F_threshold, cfg.equalize) == (150, 30, 10, 1.0, True)
    assert np.array_equal(cfg.body_T_cam0, np.eye(4))  # the body is camera 0 (KITTI's poses are its)
    assert "(KITTI calib.txt P0; VINS-Mono front-end defaults): PINHOLE 752x480" in cfg.settings_line()
    # camera 1: the same K, its centre one baseline to the right of camera 0's
    c1 = kitti_config(seq, "cam1")
    assert np.allclose(c1.body_T_cam0[:3, 3], [BASELINE, 0, 0], atol=1e-12)
    assert KittiSequence(seq, "cam1").name == "00/cam1"


def test_config_replaces_the_front_end_keys(seq, tmp_path):
    from torch_frontend.config import load_config
    from torch_frontend.pipelines.inputs import resolve_configs

    y = tmp_path / "front.yaml"
    y.write_text("%YAML:1.0\n---\nmax_cnt: 80\nmin_dist: 12\n")
    cfg = resolve_configs(y, [("kitti", str(seq))])[0]
    assert (cfg.max_cnt, cfg.min_dist, cfg.freq, cfg.equalize) == (80, 12, 10, True)  # the rest: defaults
    assert float(cfg.camera.params_dict()["fx"]) == FX  # the camera stays calib.txt's
    assert "front end of" in cfg.settings_line() and "front.yaml" in cfg.settings_line()
    full = resolve_configs(load_config(y), [("kitti", str(seq))])[0]
    assert full.max_cnt == 80


def test_raw_layout(tmp_path):
    day = tmp_path / "2011_09_26"
    drive = day / "2011_09_26_drive_0001_sync"
    (drive / "image_00" / "data").mkdir(parents=True)
    for i, f in enumerate(FRAMES[:3]):
        shutil.copy(f, drive / "image_00" / "data" / f"{i:010d}.png")
    (drive / "image_00" / "timestamps.txt").write_text(
        "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.068959045\n2011-09-26 13:02:26.173529006\n")
    (day / "calib_cam_to_cam.txt").write_text("calib_time: 09-Jan-2012 13:57:47\nS_rect_00: 7.520000e+02 4.800000e+02\n"
                                              + _line("P_rect_00", _p(FX, FY, CX, CY)))
    s = KittiSequence(drive)
    assert s.name == "2011_09_26_drive_0001_sync" and len(s) == 3
    assert [f.stamp_ns for f in s][0] == 1317042145_964389445  # UTC, every digit kept
    cfg = kitti_config(drive)
    assert (cfg.image_width, cfg.image_height) == (752, 480) and "P_rect_00" in cfg.origin


@pytest.mark.parametrize("broken, match", [
    ("no_times", "without times.txt"),
    ("short_times", "5 times for 6 images"),
    ("no_p0", "P0: expected 12 numbers"),
    ("camera", "expected one of cam0, cam1, cam2, cam3"),
])
def test_errors_name_the_file(seq, broken, match):
    camera = "cam0"
    if broken == "no_times":
        (seq / "times.txt").unlink()
    elif broken == "short_times":
        (seq / "times.txt").write_text("".join(f"{t}\n" for t in range(5)))
    elif broken == "no_p0":
        (seq / "calib.txt").write_text("P1: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    else:
        camera = "left"
    with pytest.raises(DataError, match=match):
        KittiSequence(seq, camera)
        kitti_config(seq, camera)


def test_kitti_poses_pair_with_times(seq, tmp_path):
    p = tmp_path / "00.txt"
    write_kitti_poses(p, 6)
    times = KittiSequence(seq).times
    tr = read_trajectory(p, times=times)
    assert np.array_equal(tr.time.numpy(), times) and tr.t[5, 2].item() == pytest.approx(1.5)
    with pytest.raises(DataError, match="KITTI poses .* have no times"):
        read_trajectory(p)
    with pytest.raises(DataError, match="6 KITTI poses but only 4 times"):
        read_trajectory(p, times=times[:4])


def test_cli_track_two_sequences(tmp_path, capsys):
    a, b = tmp_path / "sequences" / "00", tmp_path / "sequences" / "05"
    make_odometry(a, n=4)
    make_odometry(b, n=4)
    out = tmp_path / "out"
    rc = main(["track", "--kitti", str(a), "--kitti", str(b), "--out", str(out), "--no-progress", "--no-tracks"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "KITTI calib.txt P0; VINS-Mono front-end defaults" in printed
    s = json.loads((out / "summary.json").read_text())
    names = [p["name"] for p in s["per_stream"]]
    assert names == ["kitti:00", "kitti:05"], names


def test_cli_loop_kitti_defaults(seq, tmp_path, capsys):
    poses = tmp_path / "00.txt"
    write_kitti_poses(poses, 6)
    out = tmp_path / "loop"
    rc = main(["loop", "--kitti", str(seq), "--poses", str(poses), "--train-vocabulary", "--train-L", "2",
               "--out", str(out), "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    cap = capsys.readouterr()
    assert "pose graph    6dof, up -y (--kitti: no IMU, 6dof; --kitti: camera-0 world, y down)" in cap.out
    assert "warning" not in cap.err  # an extrinsic (identity, the body is camera 0) and horizontal motion
    s = json.loads((out / "summary.json").read_text())
    assert (s["mode"], s["up"], s["per_stream"][0]["name"]) == ("6dof", "-y", "kitti:00")
    vio = read_trajectory(out / "trajectory_vio.tum")
    assert vio.t[:, 2].max().item() > 0.5 and vio.t[:, :2].abs().max().item() < 1e-9  # KITTI's world, as given


def test_cli_names_flags(tmp_path, capsys):
    """A reader's error names the flag (``--fps``), not the option (``fps``)."""
    d = tmp_path / "frames"
    d.mkdir()
    for i, f in enumerate(FRAMES[:2]):
        shutil.copy(f, d / f"{i:06d}.png")
    from tests.conftest import REPO

    rc = main(["track", str(REPO / "configs" / "euroc.yaml"), "--images", str(d), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and "give a frame rate (--fps)" in err, err
    make_odometry(tmp_path / "sequences" / "03", n=2)
    rc = main(["track", "--kitti", str(tmp_path / "sequences" / "03"), "--camera", "left", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and "error: --camera: expected one of cam0, cam1, cam2, cam3" in err, err
    rc = main(["track", "--kitti", str(tmp_path / "sequences"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and "not a KITTI sequence" in err and "give one of them" in err and "sequences/03" in err, err


def test_cli_loop_warns_about_the_up_axis(seq, tmp_path, capsys):
    """KITTI poses (driving along z) taken as z-up for the 4-DoF graph: one warning line."""
    poses = tmp_path / "00.txt"
    write_kitti_poses(poses, 6)
    rc = main(["loop", "--kitti", str(seq), "--poses", str(poses), "--train-vocabulary", "--train-L", "2",
               "--pose-graph", "4dof", "--up", "+z", "--out", str(tmp_path / "loop"), "--no-progress"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "pose graph    4dof, up +z\n" in cap.out
    assert "torch-frontend: warning: " in cap.err and "runs mostly along +z" in cap.err, cap.err
