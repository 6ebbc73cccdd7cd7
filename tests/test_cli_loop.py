"""``torch-frontend loop`` and ``torch-frontend demo --loop``: the demo end to end (loops
only at true revisits, ATE at least halved, every output present, TUM/VINS files parse back), the
``loop`` command on an image folder with poses / ground truth / vocabulary files, and one clear
stderr line + non-zero exit for each bad input.

The demo runs on a smaller render than the shipped one (56 keyframes per lap instead of 64) to keep
the suite fast; everything else is the shipped demo.
"""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest
import torch

from torch_frontend.cli import main
from torch_frontend.geometry import R_to_quat
from torch_frontend.loop.report import LOOP_COLUMNS, OUTPUT_FILES, STREAM_FILES
from torch_frontend.pipelines import loop as loop_run
from torch_frontend.trajectory import Trajectory, read_trajectory, write_tum, write_vins_csv

from ._helpers import assert_one_error_line, run_cli, truncate

SMALL_DEMO = dict(keyframes_per_lap=56)


def _frame_of(seq, t: float) -> int:
    return int(np.argmin(np.abs(seq.times.numpy() - t)))


# ---------------------------------------------------------------------------------------- demo


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """``torch-frontend demo --loop`` once (module scope: the run is the expensive part)."""
    out = tmp_path_factory.mktemp("demo_loop") / "out"
    mp = pytest.MonkeyPatch()
    for k, v in SMALL_DEMO.items():
        mp.setitem(loop_run.DEMO_RENDER, k, v)
    try:
        rc = main(["demo", "--loop", "--out", str(out), "--no-progress"])
        seq = loop_run.demo_sequence()
    finally:
        mp.undo()
    return rc, out, seq


@pytest.mark.slow
def test_demo_loop_cli_end_to_end(demo_run, capsys):
    rc, out, seq = demo_run
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    # every output present, no temporaries left
    for name in (*STREAM_FILES, *OUTPUT_FILES):
        assert (out / name).is_file(), name
    assert (out / "pose_graph" / "pose_graph.txt").is_file()
    assert not [p for p in out.rglob(".*")], "temporary files left"
    # summary: counts, ATE at the top level, times per stage
    assert s["keyframes"] > 2 * 50 and s["streams"] == 1 and s["graphs"] == 1
    assert s["loops_accepted"] >= 10
    assert s["loops_accepted"] + s["loops_rejected"] == s["loop_candidates"]
    assert sum(s["rejected_by_reason"].values()) == s["loops_rejected"]
    assert s["ate_after"] <= 0.5 * s["ate_before"], (s["ate_before"], s["ate_after"])
    assert s["ate_before"] > 0.05  # the demo's drift is visible
    assert s["skipped_bad_frames"] == 0
    for stage in ("tracking", "triangulation", "description", "vocabulary", "recognition_verification",
                  "optimisation", "outputs"):
        assert s["times"][stage] >= 0, stage
    assert s["vocabulary"]["source"] == "trained on this run"


@pytest.mark.slow
def test_demo_loops_only_at_revisits(demo_run):
    """Every accepted loop joins two keyframes whose views overlap (exact render geometry), the
    first lap's revisit is found early in lap 2, and lap 2 is mostly covered by loops."""
    rc, out, seq = demo_run
    with open(out / "loops.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(LOOP_COLUMNS)
    acc = [r for r in rows if r["accepted"] == "1"]
    assert acc and all(r["reason"] == "accepted" for r in acc)
    assert all(r["reason"] != "accepted" for r in rows if r["accepted"] == "0")
    lap_t = float(seq.times[seq.num_frames // 2])  # start of lap 2
    for r in acc:
        i, j = _frame_of(seq, float(r["current_time"])), _frame_of(seq, float(r["old_time"]))
        overlap = min(seq.overlaps(i, j), seq.overlaps(j, i))
        assert overlap >= 0.3, (r["current"], r["old"], overlap)
        assert int(r["current"]) - int(r["old"]) > 50  # VINS searches keyframes > 50 older only
        assert int(r["inliers"]) > 25 and int(r["matches"]) > 25 and abs(float(r["yaw_deg"])) < 30
        q = np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")])
        assert abs(np.linalg.norm(q) - 1) < 1e-6
    cur_t = sorted(float(r["current_time"]) for r in acc)
    lap_len = float(seq.times[-1]) - lap_t
    assert cur_t[0] < lap_t + 0.25 * lap_len  # the first revisit is caught early
    assert cur_t[-1] > lap_t + 0.75 * lap_len


@pytest.mark.slow
def test_demo_trajectory_files_parse(demo_run):
    """The TUM files read back (TUM parser, as evo reads them) and agree with the VINS csv."""
    rc, out, seq = demo_run
    loop = read_trajectory(out / "trajectory_loop.tum", format="tum")
    vio = read_trajectory(out / "trajectory_vio.tum", format="tum")
    csvt = read_trajectory(out / "vins_result_loop.csv", format="vins")
    s = json.loads((out / "summary.json").read_text())
    assert loop.time.shape[0] == vio.time.shape[0] == csvt.time.shape[0] == s["keyframes"]
    torch.testing.assert_close(loop.time, csvt.time, atol=1e-6, rtol=0)
    torch.testing.assert_close(loop.t, csvt.t, atol=1e-5, rtol=0)
    # the VIO file holds the input poses: the render's drifted VIO at those times
    f = [_frame_of(seq, float(t)) for t in vio.time]
    torch.testing.assert_close(vio.t, seq.T_vio[f].double(), atol=1e-6, rtol=0)
    for line in (out / "trajectory_loop.tum").read_text().splitlines()[1:3]:
        assert len(line.split()) == 8
    assert (out / "vins_result_loop.csv").read_text().splitlines()[0].endswith(",")
    for name in ("trajectory_top.png", "place_recognition_scores.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] > 300 and img.shape[1] > 600


# ------------------------------------------------------------------------------ loop on files


@pytest.fixture(scope="module")
def short_inputs(tmp_path_factory):
    """One short lap (no revisit) as files: images named by their time, a VINS-Mono config for the render's
    camera and extrinsic, VIO poses (VINS csv), ground truth (TUM), a vocabulary (.npz)."""
    root = tmp_path_factory.mktemp("loop_inputs")
    seq = loop_run.demo_sequence(laps=1, keyframes_per_lap=20)
    imgs = root / "images"
    imgs.mkdir()
    for t, im in zip(seq.times.tolist(), seq.images.numpy()):
        assert cv2.imwrite(str(imgs / f"{t:.6f}.png"), im)  # names in seconds (TUM RGB-D style)
    R_ic, t_ic = seq.R_ic.numpy(), seq.t_ic.numpy()
    cam = seq.camera
    cfg = root / "synthetic.yaml"
    cfg.write_text(f"""%YAML:1.0
model_type: PINHOLE
camera_name: synthetic
image_width: {seq.images.shape[2]}
image_height: {seq.images.shape[1]}
distortion_parameters:
   k1: 0.0
   k2: 0.0
   p1: 0.0
   p2: 0.0
projection_parameters:
   fx: {float(cam.fx)}
   fy: {float(cam.fy)}
   cx: {float(cam.cx)}
   cy: {float(cam.cy)}
extrinsicRotation: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [{", ".join(str(float(v)) for v in R_ic.reshape(-1))}]
extrinsicTranslation: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [{", ".join(str(float(v)) for v in t_ic)}]
max_cnt: 100
min_dist: 20
freq: 100
F_threshold: 1.0
equalize: 0
fisheye: 0
""")
    t = seq.times.double()
    poses = root / "vins_result_no_loop.csv"
    write_vins_csv(poses, Trajectory(t, seq.T_vio.double(), R_to_quat(seq.R_vio.double())))
    gt = root / "gt.tum"
    write_tum(gt, Trajectory(t, seq.T_gt.double(), R_to_quat(seq.R_gt.double())))
    from torch_frontend.loop.vocabulary import Vocabulary

    g = torch.Generator().manual_seed(0)
    desc = torch.randint(-(2**62), 2**62, (4, 50, 4), generator=g, dtype=torch.int64)
    voc = root / "voc.npz"
    Vocabulary.train(desc, k=4, L=2, generator=g).save(voc)
    return dict(root=root, images=imgs, config=cfg, poses=poses, gt=gt, voc=voc, seq=seq)


def test_loop_cli_image_folder(short_inputs, tmp_path, capsys):
    d = short_inputs
    out = tmp_path / "run"
    rc, stdout, err = run_cli(capsys, "loop", d["config"], "--images", d["images"], "--poses", d["poses"],
                              "--ground-truth", d["gt"], "--vocabulary", d["voc"], "--out", out, "--no-progress",
                              "--keyframe-distance", 0.1, "--keyframe-angle", 5)
    assert rc == 0, err
    assert "keyframes" in stdout and "ATE" in stdout and "loops" in stdout
    settings = [ln for ln in stdout.splitlines() if ln.startswith("config ")]  # the settings, one line
    assert len(settings) == 1 and str(d["config"]) in settings[0] and "max_cnt" in settings[0], stdout
    s = json.loads((out / "summary.json").read_text())
    for name in (*STREAM_FILES, *OUTPUT_FILES):
        assert (out / name).is_file(), name
    assert s["keyframes"] >= 15 and s["loops_accepted"] == 0  # one short lap: nothing to close
    assert s["ate_before"] == pytest.approx(s["ate_after"])  # no loop: corrected = VIO
    assert s["extrinsic"]["t_ic"] == pytest.approx(d["seq"].t_ic.tolist())  # from the config
    assert s["vocabulary"]["source"].endswith("voc.npz")
    assert s["per_stream"][0]["mean_points"] > 25
    # a second run starts from the saved graph and trains its vocabulary
    out2 = tmp_path / "run2"
    rc, stdout, err = run_cli(capsys, "loop", d["config"], "--images", d["images"], "--poses", d["poses"],
                              "--train-vocabulary", "--load-graph", out / "pose_graph", "--out", out2,
                              "--no-progress", "--keyframe-every", 4, "--max-frames", 20)
    assert rc == 0, err
    s2 = json.loads((out2 / "summary.json").read_text())
    assert s2["keyframes_loaded"] == s["keyframes"] and s2["keyframes"] == 5
    assert "ate_before" not in s2  # no ground truth given
    assert len(read_trajectory(out2 / "trajectory_loop.tum").time) == 5


def test_loop_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["loop", "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for opt in ("--poses", "--vocabulary", "--train-vocabulary", "--load-graph", "--ground-truth",
                "--separate-graphs", "--device"):
        assert opt in text


# ---------------------------------------------------------------------------------- bad input


def _loop_args(d, out, **over):
    args = {"--images": d["images"], "--poses": d["poses"], "--vocabulary": d["voc"], "--out": out}
    args.update(over)
    argv = ["loop", d["config"]]
    for k, v in args.items():
        if v is not None:
            argv += [k, v]
    return argv + ["--no-progress"]


def test_bad_poses_missing(short_inputs, tmp_path, capsys):
    missing = tmp_path / "nope.csv"
    rc, _, err = run_cli(capsys, *_loop_args(short_inputs, tmp_path / "o", **{"--poses": missing}))
    assert rc == 1
    assert_one_error_line(err, str(missing), "not found")
    assert not (tmp_path / "o" / "summary.json").exists()


def test_bad_poses_do_not_cover_images(short_inputs, tmp_path, capsys):
    d = short_inputs
    traj = read_trajectory(d["poses"])
    shifted = tmp_path / "later.tum"
    write_tum(shifted, Trajectory(traj.time + 1000.0, traj.t, traj.q))
    rc, _, err = run_cli(capsys, *_loop_args(d, tmp_path / "o", **{"--poses": shifted}))
    assert rc == 1
    assert_one_error_line(err, str(shifted), "do not cover", str(d["images"].name))


def test_bad_vocabulary_format(short_inputs, tmp_path, capsys):
    for name, data in (("voc.bin", b"this is not a vocabulary\n"), ("voc.npz", None)):
        p = tmp_path / name
        if data is None:
            np.savez(p, something=np.arange(3))  # a real .npz, but no vocabulary in it
        else:
            p.write_bytes(data)
        rc, _, err = run_cli(capsys, *_loop_args(short_inputs, tmp_path / "o", **{"--vocabulary": p}))
        assert rc == 1
        assert_one_error_line(err, str(p), "not a vocabulary")


def test_bad_empty_image_folder(short_inputs, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    rc, _, err = run_cli(capsys, *_loop_args(short_inputs, tmp_path / "o", **{"--images": empty}))
    assert rc == 1
    assert_one_error_line(err, str(empty), "empty")


def test_bad_frame_names_the_flag_and_leaves_no_folder(short_inputs, tmp_path, capsys):
    """A corrupt image stops ``loop`` with the flag that goes on (``--skip-bad-frames``), and the
    folders the run made for ``--out`` (here ``new/``) are gone with it; a folder the user made stays."""
    import shutil

    imgs = tmp_path / "imgs"
    shutil.copytree(short_inputs["images"], imgs)
    bad = sorted(imgs.iterdir())[3]
    truncate(bad)
    rc, _, err = run_cli(capsys, *_loop_args(short_inputs, tmp_path / "new" / "o", **{"--images": imgs}))
    assert rc == 1
    assert_one_error_line(err, bad.name, "--skip-bad-frames")
    assert not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()
    rc, _, err = run_cli(capsys, *_loop_args(short_inputs, tmp_path / "mine" / "o", **{"--images": imgs}))
    assert rc == 1 and (tmp_path / "mine").is_dir()


def test_bad_usage(short_inputs, tmp_path, capsys):
    d = short_inputs
    rc, _, err = run_cli(capsys, *_loop_args(d, tmp_path / "o", **{"--vocabulary": None}))
    assert rc == 2
    assert_one_error_line(err, "--vocabulary", "--train-vocabulary")
    rc, _, err = run_cli(capsys, *_loop_args(d, tmp_path / "o", **{"--poses": None}))
    assert rc == 2
    assert_one_error_line(err, "--poses", "one poses file per input")
    rc, _, err = run_cli(capsys, *_loop_args(d, tmp_path / "o"), "--ground-truth", d["gt"], "--ground-truth", d["gt"])
    assert rc == 2
    assert_one_error_line(err, "--ground-truth")
    rc, _, err = run_cli(capsys, "demo", "--two-sequences", "--out", tmp_path / "o", "--no-progress")
    assert rc == 2
    assert_one_error_line(err, "--loop")


def test_demo_announcement_says_what_is_rendered():
    """``demo --loop``'s first line counts the frames the render has (the keyframes are the
    pipeline's own choice, reported in the summary), and states the keyframe rule."""
    small = dict(width=64, height=48, keyframes_per_lap=8)
    seq = loop_run.demo_sequence(**small)
    text = loop_run.demo_announcement(**small)
    assert f"2 laps, {seq.num_frames} frames 64x48" in text, text
    assert "x 8 keyframes" not in text and "every 0.1 m or 5 deg" in text
    assert "the first 10 used" in loop_run.demo_announcement(loop_run.demo_options(max_frames=10), **small)
