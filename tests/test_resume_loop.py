"""The loop-closure back end stopped, saved and restored: every state (``PoseGraph``,
``PlaceDatabase``, ``KeyFrame`` lists, ``LoopResult`` lists, ``KeyframeLog``, the pipeline's
pose-graph stage) goes through ``torch.save`` / ``torch.load(weights_only=True)`` into fresh
objects, and the run goes on to the same bits as a run that never stopped.

The pose graph runs on the rendered revisit (2 laps of 16 keyframes, exact points,
``min_loop_gap=8`` so that the short laps close loops: 4 accepted, 4 optimisations).
"""

from __future__ import annotations

import copy
import io

import numpy as np
import pytest
import torch

from torch_frontend.loop.pose_graph import PoseGraph
from torch_frontend.loop.state import StateError
from torch_frontend.loop.vocabulary import Vocabulary
from torch_frontend.testing.synthetic import make_keyframes, render_loop_sequence

KF_PER_LAP = 16
MIN_GAP = 8  # the laps are shorter than VINS's 50 keyframes


def round_trip(state):
    """``state`` through ``torch.save`` and a safe ``torch.load`` (as a checkpoint file)."""
    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=True)


@pytest.fixture(scope="module")
def scene():
    seq = render_loop_sequence(laps=2, keyframes_per_lap=KF_PER_LAP, seed=0, width=240, height=180)
    kfs = make_keyframes(seq)
    first = kfs[:KF_PER_LAP:2]
    desc = torch.nn.utils.rnn.pad_sequence([k.brief for k in first], batch_first=True)
    valid = torch.nn.utils.rnn.pad_sequence([torch.ones(k.brief.shape[0], dtype=torch.bool) for k in first],
                                            batch_first=True)
    voc = Vocabulary.train(desc, valid, k=10, L=3, generator=torch.Generator().manual_seed(0))
    return seq, kfs, voc


def _graph(seq, voc, **kw):
    return PoseGraph(seq.camera, voc, R_ic=seq.R_ic, t_ic=seq.t_ic, min_loop_gap=MIN_GAP, **kw)


def _fingerprint(pg: PoseGraph):
    """Everything the graph's outputs are made of, exactly."""
    loops = [(r.index, r.old_index, r.score, r.accepted, r.reason, r.num_matches, r.num_inliers,
              r.relative_t.tobytes(), r.relative_q.tobytes(), r.relative_yaw,
              None if r.cur_uv is None else r.cur_uv.tobytes(), None if r.old_uv is None else r.old_uv.tobytes())
             for r in pg.loops]
    kfs = [(k.index, k.time, k.sequence, k.has_loop, k.loop_index,
            *(getattr(k, f).cpu().numpy().tobytes() for f in ("vio_T", "vio_R", "T_w_i", "R_w_i", "loop_info",
                                                              "point_3d", "keypoints", "brief", "window_brief")))
           for k in pg.keyframes]
    return (pg.csv_text(), loops, kfs, list(pg.scores), pg.num_optimizations, pg.global_index,
            pg.earliest_loop_index, pg.yaw_drift, pg.generator.get_state().numpy().tobytes())


@pytest.fixture(scope="module")
def reference(scene):
    seq, kfs, voc = scene
    pg = _graph(seq, voc)
    for k in kfs:
        pg.add_keyframe(copy.deepcopy(k))
    assert sum(r.accepted for r in pg.loops) >= 2 and pg.num_optimizations >= 2  # the state has loops to keep
    return _fingerprint(pg)


@pytest.mark.parametrize("stop", [pytest.param(1, marks=pytest.mark.slow), 12, 21])  # before any candidate, before
# the first loop, after loops
def test_pose_graph_stopped_saved_restored_goes_on_bit_identically(scene, reference, stop):
    seq, kfs, voc = scene
    a = _graph(seq, voc)
    for k in kfs[:stop]:
        a.add_keyframe(copy.deepcopy(k))
    state = round_trip(a.state_dict())
    del a
    b = _graph(seq, voc)  # a fresh graph: only the state carries over
    b.load_state_dict(state)
    for k in kfs[stop:]:
        b.add_keyframe(copy.deepcopy(k))
    assert _fingerprint(b) == reference


def test_pose_graph_append_only_chunks(scene, reference):
    """Checkpoints every 5 keyframes, each writing the new keyframes' points and descriptors only:
    the chunks in order restore the graph; a missing chunk is refused."""
    seq, kfs, voc = scene
    a = _graph(seq, voc)
    chunks, saved = [], 0
    for n, k in enumerate(kfs[:23], 1):
        a.add_keyframe(copy.deepcopy(k))
        if n % 5 == 0 or n == 23:
            chunks.append(round_trip(a.state_dict(since=saved)))
            saved = len(a.keyframes)
    assert [c["keyframes"]["time"].shape[0] for c in chunks] == [5, 5, 5, 5, 3]
    b = _graph(seq, voc)
    b.load_state_dict(chunks)
    for k in kfs[23:]:
        b.add_keyframe(copy.deepcopy(k))
    assert _fingerprint(b) == reference
    with pytest.raises(StateError, match="a chunk starting at keyframe 10 does not follow the 5 keyframes"):
        _graph(seq, voc).load_state_dict([chunks[0], chunks[2]])


def test_pose_graph_state_refused_when_settings_or_version_differ(scene):
    seq, kfs, voc = scene
    a = _graph(seq, voc)
    for k in kfs[:3]:
        a.add_keyframe(copy.deepcopy(k))
    state = round_trip(a.state_dict())
    with pytest.raises(StateError, match="PoseGraph state: mode is '4dof' in the state but '6dof' here"):
        _graph(seq, voc, mode="6dof").load_state_dict(state)
    with pytest.raises(StateError, match="min_loop_gap is 8 in the state but 50 here"):
        PoseGraph(seq.camera, voc, R_ic=seq.R_ic, t_ic=seq.t_ic).load_state_dict(state)
    with pytest.raises(StateError, match="PoseGraph state: version 99, this torch-frontend reads version 1"):
        _graph(seq, voc).load_state_dict({**state, "version": 99})
    fresh = _graph(seq, voc)
    with pytest.raises(StateError):
        fresh.load_state_dict({**state, "settings": {**state["settings"], "R_ic": torch.eye(3, dtype=torch.float64)}})
    assert len(fresh) == 0  # nothing changed


def test_place_database_state(scene):
    from torch_frontend.loop.database import PlaceDatabase

    _, kfs, voc = scene
    bows = [voc.transform(k.brief[None], torch.ones(1, k.brief.shape[0], dtype=torch.bool)) for k in kfs]
    db = PlaceDatabase(voc)
    db.tail_min = 64  # tail merges into main during the run: both runs are in the state
    for bow in bows[:20]:
        db.add(bow)
    db2 = PlaceDatabase(voc)
    db2.tail_min = 64
    db2.load_state_dict(round_trip(db.state_dict()))
    assert db._main[0].numel() and db._tail[0].numel()
    for bow in bows[20:]:
        ra, rb = db.query(bow, max_id=-1), db2.query(bow, max_id=-1)
        assert torch.equal(ra[0], rb[0]) and torch.equal(ra[1], rb[1])
        db.add(bow)
        db2.add(bow)
    with pytest.raises(StateError, match="num_words is"):
        PlaceDatabase(voc.num_words + 1).load_state_dict(db.state_dict())


def test_vocabulary_state(scene):
    _, kfs, voc = scene
    v2 = Vocabulary.from_state_dict(round_trip(voc.state_dict()))
    desc = kfs[5].brief[None]
    valid = torch.ones(1, desc.shape[1], dtype=torch.bool)
    a, b = voc.transform(desc, valid), v2.transform(desc, valid)
    assert torch.equal(a.words, b.words) and torch.equal(a.weights, b.weights)


def test_keyframe_log_chunks():
    """A ``KeyframeLog`` fed published frames, checkpointed in append-only chunks, restored into a
    fresh log and fed the rest: the same lists, keyframes and images as a log that never stopped."""
    from torch_frontend.pipelines.loop_stages import KeyframeLog
    from torch_frontend.trajectory import Trajectory

    rng = np.random.default_rng(0)
    F = 30
    t = np.arange(F) * 0.1
    traj = Trajectory(torch.from_numpy(t), torch.from_numpy(np.cumsum(rng.normal(0, 0.1, (F, 3)), 0)),
                      torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(F, 4).clone())
    frames = []
    for f in range(F + 5):  # the last 5 frames lie after the poses: uncovered
        n = int(rng.integers(0, 6))
        frames.append((float(f * 0.1), rng.integers(0, 100, n), rng.normal(size=(n, 2)), rng.normal(size=(n, 2)) * 100,
                       rng.integers(0, 255, (6, 8), dtype=np.uint8)))

    def log():
        return KeyframeLog("s", traj, "poses.csv", 0.5, 0.15, 10.0, None)

    ref = log()
    for fr in frames:
        ref.add(*fr)
    a, chunks, mark = log(), [], None
    for i, fr in enumerate(frames[:22]):
        a.add(*fr)
        if i % 7 == 6:
            chunks.append(round_trip(a.state_dict(since=mark)))
            mark = a.mark()
    b = log()
    b.load_state_dict(chunks)
    for fr in frames[21:]:  # from the last checkpoint (after frame 20) on
        b.add(*fr)
    for x, y in ((ref, b),):
        assert x.times == y.times and x.covered == y.covered and x.kf_frames == y.kf_frames
        assert x._candidates == y._candidates and x.frames == y.frames
        assert len(x.obs) == len(y.obs) and all(
            o[0] == p[0] and all(np.array_equal(u, v) and u.dtype == v.dtype for u, v in zip(o[1:], p[1:]))
            for o, p in zip(x.obs, y.obs))
        assert all(np.array_equal(u, v) for u, v in zip(x.kf_images, y.kf_images))
    assert len(ref.kf_frames) >= 3
    with pytest.raises(StateError, match="does not follow the log"):
        log().load_state_dict(chunks[1:])
    with pytest.raises(StateError, match="keyframe_distance is 0.15 in the state but 0.3 here"):
        KeyframeLog("s", traj, "poses.csv", 0.5, 0.3, 10.0, None).load_state_dict(chunks)


# ----------------------------------------------------------------------------------------------
# `torch-frontend loop` SIGKILLed (the test hook), then --resume: the outputs of a run that never stopped

#: the loop inputs' run: 16 steps (2 streams), 14 keyframes; with --checkpoint-every 3: tracking
#: checkpoints 1-5 (steps 3 .. 15), the prepared one 6, pose-graph ones 7, 8, ... (every 3 keyframes)
EVERY = 3
LOOP_TIMING_KEYS = {"seconds", "times", "keyframes_per_second", "decode_seconds", "input_wait_seconds", "out"}
DEADLINE = 120  # s: far above a run's time, so only a hang reaches it


@pytest.fixture(scope="module")
def loop_cli(tmp_path_factory):
    """The small revisit render's ``loop`` arguments and an uninterrupted run's outputs."""
    from tests._helpers import make_loop_inputs
    from torch_frontend.cli import main

    root = tmp_path_factory.mktemp("resume_loop")
    args = [str(a) for a in make_loop_inputs(root)]
    ref = root / "ref"
    assert main(args + ["--out", str(ref)]) == 0
    return args, ref


def _files(d):
    return sorted(p.relative_to(d) for p in d.rglob("*") if p.is_file())


def assert_same_loop_outputs(ref, got) -> None:
    """Every file byte-identical, ``summary.json`` up to its timing fields."""
    import json

    assert _files(ref) == _files(got)
    for rel in _files(ref):
        if rel.name == "summary.json":
            a, b = (json.loads((d / rel).read_text()) for d in (ref, got))
            assert {k: v for k, v in a.items() if k not in LOOP_TIMING_KEYS} == \
                   {k: v for k, v in b.items() if k not in LOOP_TIMING_KEYS}, rel
        else:
            assert (ref / rel).read_bytes() == (got / rel).read_bytes(), rel


def run_killed(args, out, kill_at: str, *extra) -> str:
    """``torch-frontend loop args --out out --checkpoint-every 3`` in a subprocess that the test
    hook SIGKILLs at ``kill_at``; returns the phase of the checkpoint it left."""
    import os
    import signal
    import subprocess
    import sys

    from tests.conftest import REPO
    from torch_frontend._atomic import stale_staging
    from torch_frontend.pipelines.checkpoint import KILL_ENV, load_checkpoint

    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO), **{KILL_ENV: kill_at})
    p = subprocess.run([sys.executable, "-m", "torch_frontend", *args, "--out", str(out), "--checkpoint-every",
                        str(EVERY), *extra], env=env, capture_output=True, text=True, timeout=DEADLINE)
    assert p.returncode == -signal.SIGKILL, p.stderr
    stages = stale_staging(out)
    assert len(stages) == 1 and not out.exists()  # the outputs were never swapped in
    return load_checkpoint(stages[0]).payload["phase"]


def resume(args, out, *extra) -> int:
    from torch_frontend.cli import main

    return main(args + ["--out", str(out), "--checkpoint-every", str(EVERY), "--resume", *extra])


@pytest.mark.parametrize("kill_at, phase", [
    ("frame:7", "tracking"),  # while tracking, after the checkpoint at step 6
    pytest.param("checkpoint:8", "graphs", marks=pytest.mark.slow),  # mid pose-graph checkpoint: the one before it is used
    pytest.param("checkpoint:2", "tracking", marks=pytest.mark.slow),  # in the middle of a tracking one
    pytest.param("checkpoint:6", "tracking", marks=pytest.mark.slow),  # in the middle of the prepared one
    pytest.param("keyframe:5", "graphs", marks=pytest.mark.slow),  # while building the pose graph
    pytest.param("keyframe:14", "graphs", marks=pytest.mark.slow),  # after the last keyframe: the outputs next
])
def test_loop_killed_then_resumed_equals_uninterrupted(loop_cli, tmp_path, kill_at, phase):
    args, ref = loop_cli
    out = tmp_path / "out"
    assert run_killed(args, out, kill_at) == phase
    assert resume(args, out) == 0
    assert_same_loop_outputs(ref, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folder left


@pytest.mark.slow
def test_loop_killed_twice(loop_cli, tmp_path):
    """Killed while tracking, resumed and killed again in the pose-graph stage, resumed: the
    chunks of both runs add up."""
    args, ref = loop_cli
    out = tmp_path / "out"
    assert run_killed(args, out, "frame:4") == "tracking"
    assert run_killed(args, out, "keyframe:10", "--resume") == "graphs"
    assert resume(args, out) == 0
    assert_same_loop_outputs(ref, out)


@pytest.mark.slow  # covered by the track refusals (test_resume.py) (make test-all and CI run it)
def test_loop_resume_refused_for_another_run_and_start_over_without_it(loop_cli, tmp_path, capsys):
    """A resume with other options or other poses is refused with one line naming what differs
    (nothing touched); without --resume the run starts over and removes the checkpoint."""
    from tests._helpers import assert_one_error_line
    from torch_frontend.cli import main

    args, ref = loop_cli
    out = tmp_path / "out"
    assert run_killed(args, out, "frame:7") == "tracking"
    capsys.readouterr()
    i = args.index("--keyframe-every")
    other = args[:i + 1] + ["3"] + args[i + 2:]
    assert resume(other, out) == 2
    assert_one_error_line(capsys.readouterr().err, "keyframe_every differs", "(checkpoint: 2; this run: 3)")
    poses = args[args.index("--poses") + 1]
    moved = tmp_path / "vio0.csv"
    moved.write_text(open(poses).read().replace("\n", "\n\n", 1))  # the same poses, another file
    j = args.index(poses)
    assert resume(args[:j] + [str(moved)] + args[j + 1:], out) == 2
    assert_one_error_line(capsys.readouterr().err, "poses 1 differs")
    assert main(args + ["--out", str(out)]) == 0  # no --resume: from the first frame
    assert_same_loop_outputs(ref, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "vio0.csv"]


@pytest.mark.slow
def test_loop_killed_in_its_first_checkpoint_starts_over(loop_cli, tmp_path, capsys):
    """No checkpoint complete (killed inside the first): --resume says so and runs from the first
    frame; the half-written checkpoint's folder is removed."""
    import warnings

    args, ref = loop_cli
    out = tmp_path / "out"
    with pytest.raises(FileNotFoundError):
        run_killed(args, out, "checkpoint:1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the note is a DataWarning: the CLI prints it as one line
        with pytest.raises(Warning, match="no checkpoint of an interrupted run"):
            resume(args, out)
    capsys.readouterr()
    assert resume(args, out) == 0
    assert_same_loop_outputs(ref, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.slow
def test_loop_sigterm_keeps_the_checkpoint(loop_cli, tmp_path):
    """SIGTERM (a preemption's first signal) after a checkpoint: exit 143, the message says to
    rerun with --resume, the checkpoint stays; --resume finishes the run."""
    import os
    import subprocess
    import sys

    from tests.conftest import REPO
    from torch_frontend._atomic import stale_staging
    from torch_frontend.pipelines.checkpoint import KILL_ENV

    args, ref = loop_cli
    out = tmp_path / "out"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO), **{KILL_ENV: "term:7"})
    p = subprocess.run([sys.executable, "-m", "torch_frontend", *args, "--out", str(out), "--checkpoint-every",
                        str(EVERY)], env=env, capture_output=True, text=True, timeout=DEADLINE)
    assert p.returncode == 143, p.stderr
    assert "--resume" in p.stderr and len(stale_staging(out)) == 1
    assert resume(args, out) == 0
    assert_same_loop_outputs(ref, out)
