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


@pytest.mark.parametrize("stop", [1, 12, 21])  # before any candidate, before the first loop, after loops
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
