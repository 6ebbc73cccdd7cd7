"""The pose graph end to end on a rendered sequence.

A camera flies a closed loop twice inside a room textured with real photos
(``testing.synthetic.render_loop_sequence``); the VIO poses drift (yaw + xyz random walk), the
keyframes carry exact 3-D points in their drifted VIO world (as VINS's estimator would give them).
The pose graph must accept loops at the revisits and nowhere else, and halve the ATE.
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from torch_frontend.errors import DataError
from torch_frontend.geometry import R_to_quat, yaw_to_R
from torch_frontend.loop.pose_graph import PoseGraph, _brief_to_text, _text_to_brief
from torch_frontend.loop.vocabulary import Vocabulary
from torch_frontend.testing.synthetic import make_keyframes, render_loop_sequence
from torch_frontend.trajectory import Trajectory, ate_rmse

KF_PER_LAP = 56  # > 50: VINS only queries keyframes more than 50 indices older


def _vocabulary(kfs):
    desc = torch.nn.utils.rnn.pad_sequence([k.brief for k in kfs], batch_first=True)
    valid = torch.nn.utils.rnn.pad_sequence([torch.ones(k.brief.shape[0], dtype=torch.bool) for k in kfs],
                                            batch_first=True)
    return Vocabulary.train(desc, valid, k=10, L=3, generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def scene():
    seq = render_loop_sequence(laps=2, keyframes_per_lap=KF_PER_LAP, seed=0)
    kfs = make_keyframes(seq)
    voc = _vocabulary(kfs[:KF_PER_LAP:2])  # trained on half of the first lap only
    return seq, kfs, voc


def _gt(seq, idx=None):
    f = seq.keyframe_frames if idx is None else seq.keyframe_frames[idx]
    return Trajectory(seq.times[f], seq.T_gt[f], R_to_quat(seq.R_gt[f]))


def _run(seq, voc, kfs, **kw):
    pg = PoseGraph(seq.camera, voc, R_ic=seq.R_ic, t_ic=seq.t_ic, **kw)
    for k in kfs:
        pg.add_keyframe(copy.deepcopy(k))
    return pg


@pytest.fixture(scope="module")
def run4(scene):
    seq, kfs, voc = scene
    return _run(seq, voc, kfs)


def test_loops_at_revisits_only_and_ate_halved(scene, run4):
    seq, kfs, voc = scene
    pg = run4
    O = seq.overlap_matrix()
    accepted = [r for r in pg.loops if r.accepted]
    rejected = [r for r in pg.loops if not r.accepted]
    # every accepted loop is a true revisit: the two views share content both ways
    shared = [min(float(O[r.index, r.old_index]), float(O[r.old_index, r.index])) for r in accepted]
    assert min(shared) > 0.2, shared
    # (the loop is closed, so the end of the first lap already revisits its start)
    # most second-lap keyframes close a loop
    assert len(accepted) >= 0.6 * KF_PER_LAP, (len(accepted), [(r.index, r.reason) for r in rejected])
    ate_vio = ate_rmse(pg.trajectory("vio"), _gt(seq))
    ate_loop = ate_rmse(pg.trajectory(), _gt(seq))
    print(f"accepted {len(accepted)}, rejected {len(rejected)} "
          f"({sorted({r.reason for r in rejected})}); ATE {ate_vio:.4f} -> {ate_loop:.4f} m; "
          f"{pg.num_optimizations} optimisations in {pg.optimize_seconds:.2f} s")
    assert ate_loop <= 0.5 * ate_vio
    # loop_info as VINS stores it: [t, q (w, x, y, z), yaw]
    kf = next(k for k in pg.keyframes if k.has_loop)
    assert kf.loop_info.shape == (8,) and abs(float(kf.loop_info[3:7].norm()) - 1) < 1e-9
    assert abs(float(kf.loop_info[7])) < 30 and float(kf.loop_info[:3].norm()) < 20


def test_opencv_backend_agrees(scene, run4):
    seq, kfs, voc = scene
    pg = _run(seq, voc, kfs[: KF_PER_LAP + 24], pnp_backend="opencv")
    torch_acc = {(r.index, r.old_index) for r in run4.loops if r.accepted and r.index < KF_PER_LAP + 24}
    cv_acc = {(r.index, r.old_index) for r in pg.loops if r.accepted}
    agree = len(torch_acc & cv_acc) / max(len(torch_acc | cv_acc), 1)
    assert agree >= 0.8, (sorted(torch_acc ^ cv_acc))


def test_odometry_correction_matches_latest_keyframe(run4):
    pg = run4
    kf = pg.keyframes[-1]
    T, R = pg.correct(kf.origin_vio_T, kf.origin_vio_R)
    assert torch.allclose(T, kf.T_w_i, atol=1e-9) and torch.allclose(R, kf.R_w_i, atol=1e-9)


def _shift_sequence(kfs, yaw_deg, t, sequence):
    """The same keyframes in another VIO world (a new VINS sequence starts at its own origin)."""
    G = yaw_to_R(torch.tensor(yaw_deg, dtype=torch.float64))
    t = torch.tensor(t, dtype=torch.float64)
    out = []
    for k in kfs:
        k = copy.deepcopy(k)
        k.origin_vio_T = G @ k.origin_vio_T + t
        k.origin_vio_R = G @ k.origin_vio_R
        k.point_3d = k.point_3d @ G.T + t
        k.update_vio_pose(k.origin_vio_T, k.origin_vio_R)
        k.sequence = sequence
        out.append(k)
    return out


def test_two_sequences_merge_through_their_first_loop(scene):
    seq, kfs, voc = scene
    lap2 = _shift_sequence(kfs[KF_PER_LAP:], 40.0, (3.0, -2.0, 0.5), sequence=2)
    pg = _run(seq, voc, kfs[:KF_PER_LAP] + lap2)
    # the first loop from sequence 2 to sequence 1 merges them
    assert any(r.accepted and r.index >= KF_PER_LAP and r.old_index < KF_PER_LAP for r in pg.loops)
    gt = _gt(seq)
    raw = Trajectory(gt.time, pg.poses("origin")[1], R_to_quat(pg.poses("origin")[2]))
    ate_raw = ate_rmse(raw, gt)
    ate_merged = ate_rmse(pg.trajectory(), gt)
    print(f"two sequences: ATE unmerged {ate_raw:.3f} m, merged + optimised {ate_merged:.4f} m")
    assert ate_raw > 1.0  # 40 degrees and 3.6 m apart before the merge
    assert ate_merged < 0.1
    # merged once: the shift is fixed after the first loop
    assert pg._state(2).merged


def test_save_load_continue(scene, tmp_path):
    seq, kfs, voc = scene
    a = _run(seq, voc, kfs[:KF_PER_LAP])
    a.save(tmp_path / "g1")
    b = PoseGraph(seq.camera, voc, R_ic=seq.R_ic, t_ic=seq.t_ic)
    assert b.load(tmp_path / "g1") == KF_PER_LAP
    ta, Ta, Ra = a.poses()
    tb, Tb, Rb = b.poses()
    assert np.allclose(ta, tb, atol=1e-6) and np.allclose(Ta, Tb, atol=1e-6) and np.allclose(Ra, Rb, atol=1e-5)
    assert all(torch.equal(x.brief, y.brief) for x, y in zip(a.keyframes, b.keyframes))
    assert all(k.sequence == 0 for k in b.keyframes)
    # a loaded graph saves back the same keypoints, descriptors and optimised poses (its VIO
    # poses are the saved optimised ones, as VINS loads them); a second round trip is exact
    b.save(tmp_path / "g2")
    for f in sorted((tmp_path / "g1").iterdir()):
        if f.name != "pose_graph.txt":
            assert (tmp_path / "g2" / f.name).read_bytes() == f.read_bytes(), f.name
    rows1 = [r.split() for r in (tmp_path / "g1" / "pose_graph.txt").read_text().splitlines()]
    rows2 = [r.split() for r in (tmp_path / "g2" / "pose_graph.txt").read_text().splitlines()]
    pg_cols = [0, 1, 5, 6, 7, 12, 13, 14, 15, *range(16, 26)]
    # (the quaternion is renormalised on load: last printed digit may move)
    assert np.allclose(np.array(rows1, dtype=float)[:, pg_cols], np.array(rows2, dtype=float)[:, pg_cols], atol=2e-6)
    c = PoseGraph(seq.camera, voc)
    c.load(tmp_path / "g2")
    c.save(tmp_path / "g3")
    for f in sorted((tmp_path / "g2").iterdir()):
        assert (tmp_path / "g3" / f.name).read_bytes() == f.read_bytes(), f.name
    # continue both with the second lap: the reloaded map is fixed (VINS), the live one is not,
    # so the second lap lands on nearly the same poses
    for k in kfs[KF_PER_LAP:]:
        a.add_keyframe(copy.deepcopy(k))
        b.add_keyframe(copy.deepcopy(k))
    assert sum(r.accepted for r in b.loops) >= 0.6 * KF_PER_LAP
    assert b._state(1).merged
    ta, Ta, _ = a.poses()
    tb, Tb, _ = b.poses()
    diff = (Ta[KF_PER_LAP:] - Tb[KF_PER_LAP:]).norm(dim=1)
    gt = _gt(seq)
    ate_a, ate_b = ate_rmse(a.trajectory(), gt), ate_rmse(b.trajectory(), gt)
    print(f"continue: live ATE {ate_a:.4f} m, reloaded ATE {ate_b:.4f} m, lap-2 pose difference "
          f"median {diff.median():.4f} max {diff.max():.4f} m")
    assert ate_b <= 0.5 * ate_rmse(b.trajectory("vio"), gt) + 0.02


def test_vins_file_formats(run4, tmp_path):
    pg = run4
    pg.save(tmp_path / "g")
    lines = (tmp_path / "g" / "pose_graph.txt").read_text().splitlines()
    assert len(lines) == len(pg)
    f = lines[-1]
    assert f.startswith(" ") and len(f.split()) == 26
    fields = f.split()
    assert fields[0] == str(pg.keyframes[-1].index) and "." in fields[1] and len(fields[1].split(".")[1]) == 6
    assert int(fields[-1]) == pg.keyframes[-1].keypoints.shape[0]
    kp = (tmp_path / "g" / f"{pg.keyframes[-1].index}_keypoints.txt").read_text().splitlines()
    assert len(kp) == pg.keyframes[-1].keypoints.shape[0] and len(kp[0].split()) == 4
    # boost dynamic_bitset text: most-significant bit first
    d = torch.zeros(2, 4, dtype=torch.int64)
    d[0, 3] = torch.iinfo(torch.int64).min  # bit 255
    d[1, 0] = 1  # bit 0
    txt = _brief_to_text(d).splitlines()
    assert txt[0] == "1" + "0" * 255 and txt[1] == "0" * 255 + "1"
    assert torch.equal(_text_to_brief("\n".join(txt) + "\n", tmp_path, 2), d)
    # vins_result_loop.csv: time*1e9 without decimals, 7 values with 5 decimals, trailing commas
    pg.write_csv(tmp_path / "vins_result_loop.csv")
    row = (tmp_path / "vins_result_loop.csv").read_text().splitlines()[0]
    parts = row.split(",")
    assert parts[-1] == "" and len(parts) == 9 and "." not in parts[0]
    assert all(len(p.split(".")[1]) == 5 for p in parts[1:8])


def test_bad_input(scene, tmp_path):
    seq, kfs, voc = scene
    pg = PoseGraph(seq.camera, voc, R_ic=seq.R_ic, t_ic=seq.t_ic)
    pg.add_keyframe(copy.deepcopy(kfs[0]))
    bad = copy.deepcopy(kfs[1])
    bad.origin_vio_T[0] = float("nan")
    with pytest.raises(DataError, match="origin_vio_T is not finite"):
        pg.add_keyframe(bad)
    assert len(pg) == 1 and pg.global_index == 1
    # unreadable saved graphs: clear error naming the file, nothing added
    pg.save(tmp_path / "g")
    (tmp_path / "g" / "pose_graph.txt").write_text(" 0 1.0 garbage\n")
    with pytest.raises(DataError, match=r"pose_graph.txt:1: expected 26 fields"):
        pg.load(tmp_path / "g")
    with pytest.raises(DataError, match="pose_graph.txt missing"):
        pg.load(tmp_path / "nothing")
    pg.save(tmp_path / "h")
    (tmp_path / "h" / "0_briefdes.dat").unlink()
    with pytest.raises(DataError, match="0_briefdes.dat: missing"):
        pg.load(tmp_path / "h")
    assert len(pg) == 1
    # saving into a missing folder: error, nothing written
    with pytest.raises(DataError, match="does not exist"):
        pg.save(tmp_path / "no" / "such")
    assert not (tmp_path / "no").exists()
    with pytest.raises(ValueError, match="mode"):
        PoseGraph(seq.camera, voc, mode="3dof")


def _listing(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_save_never_deletes_what_it_did_not_write(scene, tmp_path):
    """``save`` refuses a folder holding a user's file, naming it, and never moves a
    file at the target away; nothing is touched and no temporary is left then."""
    seq, kfs, voc = scene
    pg = _run(seq, voc, kfs[:3])
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    (mine / "0_keypoints.txt").write_text("a pose-graph name, but the folder is the user's")
    before = _listing(mine)
    with pytest.raises(DataError, match=r"mine: not replaced: .*did not write: notes\.txt \(no "):
        pg.save(mine)
    assert _listing(mine) == before
    f = tmp_path / "graph_file"
    f.write_text("x")
    with pytest.raises(DataError, match=r"graph_file: .*is a file"):
        pg.save(f)
    assert f.read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["graph_file", "mine"]  # no hidden .old / .tmp


def test_save_replaces_its_own_folders_and_legacy_ones(scene, tmp_path):
    """``save`` replaces, as a whole, a folder an earlier save wrote (its marker lists every file)
    and one saved before the marker existed when it holds only pose-graph files (VINS's names);
    a user's file added to a saved folder makes it refuse. ``load`` reads folders without the
    marker."""
    from torch_frontend._atomic import MARKER

    seq, kfs, voc = scene
    small, big = _run(seq, voc, kfs[:3]), _run(seq, voc, kfs[:5])
    g = tmp_path / "g"
    big.save(g)
    small.save(g)  # an earlier save: replaced, the extra keyframes' files are gone
    assert sorted(p.name for p in g.iterdir()) == sorted(
        [MARKER, "pose_graph.txt", *(f"{i}_{n}" for i in range(3) for n in ("keypoints.txt", "briefdes.dat"))])
    assert sorted(json.loads((g / MARKER).read_text())["files"]) == sorted(p.name for p in g.iterdir() if p.name != MARKER)
    (g / MARKER).unlink()  # as saved before the marker existed (or by VINS)
    assert PoseGraph(seq.camera, voc).load(g) == 3
    big.save(g)
    assert len((g / "pose_graph.txt").read_text().splitlines()) == 5 and (g / MARKER).is_file()
    (g / "my_notes.txt").write_text("keep me")
    before = _listing(g)
    with pytest.raises(DataError, match=rf"did not write: my_notes\.txt \(not listed in its {MARKER}\)"):
        small.save(g)
    assert _listing(g) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g"]


@pytest.mark.slow  # slow, and CI (make test-all) runs it: keeps make test within ~5 min
def test_six_dof_mode(scene):
    seq = render_loop_sequence(laps=2, keyframes_per_lap=KF_PER_LAP, seed=1, drift="6dof", width=256, height=192)
    kfs = make_keyframes(seq)
    voc = _vocabulary(kfs[:KF_PER_LAP:2])
    pg = _run(seq, voc, kfs, mode="6dof")
    acc = [r for r in pg.loops if r.accepted]
    ate_vio, ate_loop = ate_rmse(pg.trajectory("vio"), _gt(seq)), ate_rmse(pg.trajectory(), _gt(seq))
    print(f"6-DoF: accepted {len(acc)}, ATE {ate_vio:.4f} -> {ate_loop:.4f} m")
    assert len(acc) >= 0.5 * KF_PER_LAP
    assert ate_loop <= 0.5 * ate_vio
