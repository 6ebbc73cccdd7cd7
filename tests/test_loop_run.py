"""``pipelines.loop.run_loop``: several sequences sharing one map vs separate graphs, the
keyframe rule, pose coverage, the extrinsic from configs and vocabulary files of every format.
The single-sequence demo end to end is in ``test_cli_loop.py``."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from tests.conftest import REPO, SAMPLE
from torch_frontend.errors import DataError
from torch_frontend.geometry import R_to_quat, ypr_to_R
from torch_frontend.loop.report import STREAM_FILES
from torch_frontend.loop.vocabulary import Vocabulary
from torch_frontend.pipelines import loop as loop_run
from torch_frontend.pipelines.inputs import ArraySequence
from torch_frontend.pipelines.loop_stages import KeyframeLog, covered_mask
from torch_frontend.pipelines.vocabulary import load_vocabulary
from torch_frontend.trajectory import Trajectory, read_trajectory

# two laps of 56 rendered keyframes, no frame in between (fast); each lap is one sequence
TWO_SEQ = dict(keyframes_per_lap=56, frames_per_keyframe=1)


@pytest.fixture(scope="module")
def two_laps():
    return loop_run.demo_sequence(**TWO_SEQ)


@pytest.mark.slow
def test_shared_map_merges_two_sequences(two_laps, tmp_path):
    """Lap 1 and lap 2 as two streams in one pose graph: lap 2's keyframes close loops with lap 1
    (VINS's multi-sequence merge), the map's ATE with one alignment for both drops."""
    out = tmp_path / "shared"
    run = loop_run.demo_loop(out, loop_run.demo_options(progress=False), sequence=two_laps, two_sequences=True)
    s = run.summary
    assert s["streams"] == 2 and s["graphs"] == 1 and s["shared_map"]
    assert [p["sequence"] for p in s["per_stream"]] == [1, 2]
    cross = [r for r in run.loops if r.result.accepted and r.stream == 1 and r.old_stream == 0]
    assert len(cross) >= 5
    assert all(r.result.accepted is False for r in run.loops if r.stream == r.old_stream == 0)
    assert s["ate_joint_after"] <= 0.5 * s["ate_joint_before"], (s["ate_joint_before"], s["ate_joint_after"])
    # the merge moved sequence 2 into sequence 1's world: its vio poses are no longer the input's
    g = run.graphs[0]
    seq2 = [k for k in g.keyframes if k.sequence == 2]
    assert seq2 and all(not torch.allclose(k.vio_T, k.origin_vio_T) for k in seq2)
    assert all(torch.allclose(k.vio_T, k.origin_vio_T) for k in g.keyframes if k.sequence == 1)
    # per-stream files in stream<b>/, one graph at the top
    for b in (0, 1):
        for name in STREAM_FILES:
            assert (out / f"stream{b}" / name).is_file(), (b, name)
        tum = read_trajectory(out / f"stream{b}" / "trajectory_loop.tum", format="tum")
        assert tum.time.shape[0] == s["per_stream"][b]["keyframes"]
    assert (out / "pose_graph" / "pose_graph.txt").is_file()
    lines = (out / "pose_graph" / "pose_graph.txt").read_text().splitlines()
    assert len(lines) == s["keyframes"]
    with open(out / "loops.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sum(r["current_stream"] == "1" and r["old_stream"] == "0" and r["accepted"] == "1" for r in rows) == len(cross)
    assert json.loads((out / "summary.json").read_text())["ate_joint_after"] == pytest.approx(s["ate_joint_after"])


def test_separate_graphs_keep_sequences_apart(two_laps, tmp_path):
    """The same two streams with one graph each (the start of each lap, to stay quick): no loop
    across streams, each stream alone in its graph, one saved graph per stream."""
    out = tmp_path / "separate"
    run = loop_run.demo_loop(out, loop_run.demo_options(separate_graphs=True, progress=False, max_frames=16),
                             sequence=two_laps, two_sequences=True)
    s = run.summary
    assert s["graphs"] == 2 and not s["shared_map"] and "ate_joint_before" not in s
    assert [len(g) for g in run.graphs] == [p["keyframes"] for p in s["per_stream"]]
    assert all(r.old_stream == r.stream for r in run.loops)
    assert all(k.sequence == 1 for g in run.graphs for k in g.keyframes)
    for b in (0, 1):
        assert (out / f"stream{b}" / "pose_graph" / "pose_graph.txt").is_file()
        assert (out / f"stream{b}" / "trajectory_loop.tum").is_file()
    assert not (out / "pose_graph").exists()


# ---------------------------------------------------------------------------------- pieces


def _line_trajectory(n=50, dt=0.1, speed=1.0, yaw_rate=0.0):
    t = torch.arange(n, dtype=torch.float64) * dt + 5.0
    T = torch.zeros(n, 3, dtype=torch.float64)
    T[:, 0] = speed * (t - 5.0)
    ypr = torch.zeros(n, 3, dtype=torch.float64)
    ypr[:, 0] = yaw_rate * (t - 5.0)
    return Trajectory(t, T, R_to_quat(ypr_to_R(ypr)))


def _feed(log, traj, times):
    img = np.zeros((4, 4), np.uint8)
    for t in times:
        log.add(float(t), np.array([1, 2]), np.zeros((2, 2)), np.zeros((2, 2)), img)


def test_keyframe_rule():
    traj = _line_trajectory()  # 1 m/s, frames at 10 Hz
    log = KeyframeLog("s", traj, "p", 0.5, 0.25, 90.0, None)
    _feed(log, traj, traj.time.tolist())
    # first frame, then each frame more than 0.25 m from the last keyframe: every 3rd (0.3 m)
    assert log.kf_frames == list(range(0, 50, 3))
    spin = _line_trajectory(speed=0.0, yaw_rate=40.0)  # turning in place, 4 deg per frame
    log = KeyframeLog("s", spin, "p", 0.5, 0.25, 10.0, None)
    _feed(log, spin, spin.time.tolist())
    assert log.kf_frames == list(range(0, 50, 3))  # > 10 deg: every 3rd frame (12 deg)
    log = KeyframeLog("s", traj, "p", 0.5, 0.25, 10.0, 7)
    _feed(log, traj, traj.time.tolist())
    assert log.kf_frames == list(range(0, 50, 7))
    # frames outside the poses' span (or without features) are tracked but never keyframes
    log = KeyframeLog("s", traj, "p", 0.5, 0.25, 90.0, 1)
    _feed(log, traj, [4.0, 4.5, 5.0, 5.05, 99.0])
    assert log.kf_frames == [2, 3] and log.covered == [False, False, True, True, False]


def test_pose_coverage_rule():
    traj = _line_trajectory(n=5, dt=0.1)  # 5.0 .. 5.4 s
    cov = covered_mask(traj, np.array([4.99, 5.0, 5.05, 5.4, 5.41]), max_gap=0.5)
    assert cov.tolist() == [False, True, True, True, False]
    gap = Trajectory(torch.tensor([1.0, 2.0, 2.1]), torch.zeros(3, 3, dtype=torch.float64),
                     torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64))
    assert covered_mask(gap, np.array([1.0, 1.5, 2.05]), max_gap=0.5).tolist() == [True, False, True]


def test_extrinsic_from_configs():
    from torch_frontend.config import load_config
    from torch_frontend.io.euroc import euroc_config

    R, t = loop_run.extrinsic_from_config(load_config(REPO / "configs" / "euroc.yaml"))
    assert R[0, 1].item() == pytest.approx(-0.999880929698) and t[0].item() == pytest.approx(-0.0216401454975)
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)
    R2, t2 = loop_run.extrinsic_from_config(euroc_config(SAMPLE))  # sensor.yaml T_BS: same numbers
    torch.testing.assert_close(R2, R)
    torch.testing.assert_close(t2, t)
    from torch_frontend.config import TrackerConfig
    from torch_frontend.errors import ConfigWarning

    with pytest.warns(ConfigWarning, match="no camera-to-body extrinsic .* identity is used"):
        R3, t3 = loop_run.extrinsic_from_config(TrackerConfig(path="bare.yaml"))
    assert torch.equal(R3, torch.eye(3, dtype=torch.float64)) and torch.equal(t3, torch.zeros(3, dtype=torch.float64))


def test_load_vocabulary_formats(tmp_path):
    g = torch.Generator().manual_seed(0)
    desc = torch.randint(-(2**62), 2**62, (3, 40, 4), generator=g, dtype=torch.int64)
    voc = Vocabulary.train(desc, k=3, L=2, generator=g)
    voc.save(tmp_path / "v.npz")
    voc.save_vins_bin(tmp_path / "v.bin")
    for name in ("v.npz", "v.bin"):
        v = load_vocabulary(tmp_path / name)
        assert v.num_words == voc.num_words and v.k == 3 and v.L == 2
    with pytest.raises(DataError, match="not found"):
        load_vocabulary(tmp_path / "missing.bin")
    (tmp_path / "bad.bin").write_bytes(b"\x00" * 100)
    with pytest.raises(DataError, match="not a vocabulary"):
        load_vocabulary(tmp_path / "bad.bin")


def test_array_sequence_and_argument_checks(tmp_path):
    seq = ArraySequence(np.zeros((3, 8, 8), np.uint8), [1.0, 1.5, 2.0], name="a")
    frames = list(seq)
    assert len(seq) == 3 and [f.stamp_ns for f in frames] == [1_000_000_000, 1_500_000_000, 2_000_000_000]
    traj = _line_trajectory()
    train = loop_run.LoopOptions(train_vocabulary=True)
    with pytest.raises(ValueError, match="one poses file per input"):
        loop_run.run_loop(None, [seq], [], tmp_path, train)
    with pytest.raises(ValueError, match="train_vocabulary"):
        loop_run.run_loop(None, [seq], [traj], tmp_path)
    with pytest.raises(ValueError, match="ground_truth"):
        loop_run.run_loop(None, [seq], [traj], tmp_path, train, ground_truth=[traj, traj])
