"""Trajectory files (TUM / VINS CSV / EuRoC / KITTI, detected from the content), interpolation, Umeyama alignment, ATE and drift."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.conftest import shared_data_or_skip
from torch_frontend.errors import DataError
from torch_frontend.geometry import R_to_quat, R_to_ypr, quat_to_R, ypr_to_R
from torch_frontend.trajectory import (
    FORMAT_HELP,
    Trajectory,
    add_drift,
    align_se3,
    associate,
    ate_rmse,
    covered,
    interpolate,
    read_trajectory,
    write_tum,
    write_vins_csv,
)

T0 = 1403715273.262142976  # a EuRoC time: float64 seconds of this size keep ~0.24 us


def make_traj(n=50, seed=0, t0=T0, dt=0.05) -> Trajectory:
    g = torch.Generator().manual_seed(seed)
    time = t0 + dt * torch.arange(n, dtype=torch.float64)
    # a smooth 3D curve with yaw turning and some pitch/roll wobble
    s = torch.linspace(0, 2, n, dtype=torch.float64)
    t = torch.stack([3 * torch.cos(s), 2 * torch.sin(1.3 * s), 0.5 * s], -1) + 0.01 * torch.randn(
        n, 3, generator=g, dtype=torch.float64)
    ypr = torch.stack([90 * s - 40, 10 * torch.sin(3 * s), 5 * torch.cos(2 * s)], -1)
    return Trajectory(time, t, R_to_quat(ypr_to_R(ypr)))


def rot_dist_deg(qa, qb):
    d = (qa * qb).sum(-1).abs().clamp(max=1.0)
    return 2 * torch.rad2deg(torch.acos(d))


# ---------------------------------------------------------------------------------------------
# file formats


def test_round_trips(tmp_path):
    tr = make_traj()
    write_tum(tmp_path / "a.txt", tr)
    write_vins_csv(tmp_path / "a.csv", tr)
    for p, fmt, tol_t, tol_p in ((tmp_path / "a.txt", "tum", 1e-6, 1e-9),
                                 (tmp_path / "a.csv", "vins", 1e-6, 5e-6)):
        for f in (fmt, "auto"):
            r = read_trajectory(p, f)
            assert r.time.dtype == r.t.dtype == r.q.dtype == torch.float64
            assert r.time.shape == (50,) and r.t.shape == (50, 3) and r.q.shape == (50, 4)
            assert (r.time - tr.time).abs().max() < tol_t, p
            assert (r.t - tr.t).abs().max() <= tol_p, p
            assert rot_dist_deg(r.q, tr.q).max() < 1e-3
            assert torch.allclose(r.q.norm(dim=-1), torch.ones(50, dtype=torch.float64), atol=1e-12)
    assert not [x for x in tmp_path.iterdir() if x.name.startswith(".")]  # no temporaries left


def test_vins_csv_exact_format(tmp_path):
    """§7.11: time·1e9 with 0 decimals, then 7 values with 5 decimals, each followed by a comma."""
    # 1403715273.25 is exact in float64 (float64 seconds near 1.4e9 s resolve only ~0.24 us)
    tr = Trajectory(torch.tensor([1403715273.25, 1403715273.5], dtype=torch.float64),
                    torch.tensor([[0.878896, 2.1834, -0.948427], [1, 2, 3]], dtype=torch.float64),
                    torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0]], dtype=torch.float64))
    write_vins_csv(tmp_path / "v.csv", tr)
    lines = (tmp_path / "v.csv").read_text().splitlines()
    assert lines[0] == "1403715273250000000,0.87890,2.18340,-0.94843,1.00000,0.00000,0.00000,0.00000,"
    assert lines[1] == "1403715273500000000,1.00000,2.00000,3.00000,0.00000,1.00000,0.00000,0.00000,"


def test_tum_column_order(tmp_path):
    """TUM is ``t tx ty tz qx qy qz qw`` (x, y, z, w): write and parse check the exact order."""
    q = torch.tensor([[0.5, 0.5, -0.5, 0.5]], dtype=torch.float64)  # w, x, y, z
    tr = Trajectory(torch.tensor([12.5], dtype=torch.float64), torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64), q)
    write_tum(tmp_path / "t.txt", tr)
    rows = [ln.split() for ln in (tmp_path / "t.txt").read_text().splitlines() if not ln.startswith("#")]
    assert [float(v) for v in rows[0]] == [12.5, 1.0, 2.0, 3.0, 0.5, -0.5, 0.5, 0.5]
    (tmp_path / "h.txt").write_text("# timestamp tx ty tz qx qy qz qw\n1.0 1 2 3 0 0 0.6 0.8\n")
    r = read_trajectory(tmp_path / "h.txt")
    assert r.q[0].tolist() == pytest.approx([0.8, 0.0, 0.0, 0.6])
    assert r.t[0].tolist() == [1.0, 2.0, 3.0] and r.time.tolist() == [1.0]


def test_evo_loads_tum(tmp_path):
    """evo (dev extra, optional) reads our TUM output with the same poses."""
    file_interface = pytest.importorskip(
        "evo.tools.file_interface",
        reason="evo is not installed (optional: pip install evo); test_tum_column_order checks the format")
    tr = make_traj(20)
    write_tum(tmp_path / "e.txt", tr)
    ev = file_interface.read_tum_trajectory_file(str(tmp_path / "e.txt"))
    np.testing.assert_allclose(ev.timestamps, tr.time.numpy(), atol=1e-6)
    np.testing.assert_allclose(ev.positions_xyz, tr.t.numpy(), atol=1e-8)
    np.testing.assert_allclose(np.abs((ev.orientations_quat_wxyz * tr.q.numpy()).sum(1)), 1.0, atol=1e-8)


def test_euroc_and_openvins_ground_truth():
    gt = shared_data_or_skip("sequences", "euroc_v1_01_easy_micro", "mav0", "state_groundtruth_estimate0")
    ov = read_trajectory(gt / "openvins_V1_01_easy.csv")  # '#time(ns),px,...,qw,qx,qy,qz,vx,...'
    tum = read_trajectory(gt / "euroc_original_V1_01_easy_tum.txt")
    assert len(ov.time) == 101 and len(tum.time) == 793
    assert ov.time[0].item() == pytest.approx(1403715273.262142976, abs=1e-6)
    assert ov.t[0].tolist() == pytest.approx([0.878895, 2.1834, 0.948427])
    assert ov.q[0].tolist() == pytest.approx([0.069433, -0.824237, -0.106942, -0.551702], abs=1e-5)
    assert tum.q[0].tolist() == pytest.approx([0.060514, -0.828459, -0.058956, -0.553641], abs=1e-5)
    # the two ground truths of the same (nearly static) flight agree to < 5 mm after SE(3) alignment
    assert ate_rmse(ov, tum, align="se3") < 5e-3


def test_euroc_header_csv(tmp_path):
    p = tmp_path / "data.csv"
    p.write_text("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],"
                 "q_RS_z [],v_RS_R_x [m s^-1],v_RS_R_y [m s^-1],v_RS_R_z [m s^-1]\n"
                 "1403715273262142976,1,2,3,1,0,0,0,0.1,0.2,0.3\n"
                 "1403715273267142976,1.5,2,3,0,1,0,0,0.1,0.2,0.3\n")
    for fmt in ("euroc", "auto", "vins"):
        r = read_trajectory(p, fmt)
        assert r.time[1] - r.time[0] == pytest.approx(0.005, abs=1e-6)
        assert r.t[1].tolist() == [1.5, 2.0, 3.0] and r.q[1].tolist() == [0.0, 1.0, 0.0, 0.0]


def test_header_without_hash_is_skipped(tmp_path):
    p = tmp_path / "h.csv"
    p.write_text("timestamp,x,y,z,qw,qx,qy,qz\n1000000000,1,2,3,1,0,0,0\n")
    r = read_trajectory(p)
    assert r.time.tolist() == [1.0] and r.t[0].tolist() == [1.0, 2.0, 3.0]
    p.write_text("1000000000,1,2,3,1,0,0,0\ntimestamp,x,y,z,qw,qx,qy,qz\n")  # only a first line
    with pytest.raises(DataError, match=r"h\.csv:2: not a number: 'timestamp'"):
        read_trajectory(p)


def test_ns_with_decimals_and_small_quat_error_normalised(tmp_path):
    p = tmp_path / "v.csv"
    p.write_text("1403715273262142976.000000,0,0,0,1.001,0,0,0,\n1403715273312142976.500000,0,0,0,0.99999,0,0,0,"
                 "0.1,0.2,0.3,\n")
    r = read_trajectory(p)
    assert r.time[1] - r.time[0] == pytest.approx(0.05, abs=1e-6)
    assert torch.equal(r.q, torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64))


def test_sort_option(tmp_path):
    p = tmp_path / "s.txt"
    p.write_text("2 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"s\.txt:2: time goes backwards"):
        read_trajectory(p)
    r = read_trajectory(p, sort=True)
    assert r.time.tolist() == [1.0, 2.0] and r.t[0, 0] == 1.0


BAD = {
    "empty": ("", r"empty trajectory file"),
    "comments only": ("# timestamp tx ty tz qx qy qz qw\n\n", r"empty trajectory file"),
    "short tum line": ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", r":2: expected 8 space-separated"),
    "long tum line": ("1 0 0 0 0 0 0 1 9\n", r":1: expected 8 space-separated"),
    "text": ("1 0 0 0 0 0 0 1\n2 0 zero 0 0 0 0 1\n", r":2: not a number: 'zero'"),
    "nan": ("1 0 0 0 0 0 0 1\n2 0 nan 0 0 0 0 1\n", r":2: NaN or infinite"),
    "inf": ("1 0 0 0 0 0 0 1\n2 0 0 -inf 0 0 0 1\n", r":2: NaN or infinite"),
    "overflow": ("1 0 0 0 0 0 0 1\n2 0 0 1e999 0 0 0 1\n", r":2: NaN or infinite"),
    "quat": ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 0.5\n", r":2: quaternion norm 0.5"),
    "zero quat": ("1 0 0 0 0 0 0 0\n", r":1: quaternion norm 0"),
    "duplicate": ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n", r":3: duplicate time"),
    "decreasing": ("1 0 0 0 0 0 0 1\n3 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n", r":3: time goes backwards"),
    "csv short": ("1403715273262142976,0,0,0,1,0,0,\n", r":1: expected at least 8 comma-separated"),
    "csv text": ("1,0,0,0,1,0,0,0,\nabc,0,0,0,1,0,0,0,\n", r":2: not a number: 'abc'"),
    "csv nan": ("1,0,0,0,1,0,0,0,\n2,0,0,0,nan,0,0,0,\n", r":2: NaN or infinite"),
    "csv duplicate": ("5,0,0,0,1,0,0,0,\n5,0,0,0,1,0,0,0,\n", r":2: duplicate time"),
    "mixed": ("1,0,0,0,1,0,0,0,\n2 0 0 0 1 0 0 0\n", r":2: expected at least 8 comma-separated"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_inputs_name_file_and_line(tmp_path, case):
    text, pattern = BAD[case]
    p = tmp_path / "bad_traj.txt"
    p.write_text(text)
    with pytest.raises(DataError, match=pattern) as e:
        read_trajectory(p)
    assert str(p) in str(e.value)


def _kitti_lines(tr: Trajectory) -> str:
    R = quat_to_R(tr.q).numpy()
    return "".join(" ".join(f"{v:.9e}" for v in np.concatenate([R[k], tr.t[k, :, None].numpy()], 1).reshape(-1))
                   + "\n" for k in range(tr.time.shape[0]))


def test_four_formats_detected_from_the_content(tmp_path):
    """TUM, VINS CSV, EuRoC ground truth and KITTI (its times given) of one trajectory read back
    as that trajectory, each detected from its lines."""
    tr = make_traj(20)
    write_tum(tmp_path / "a.tum", tr)
    write_vins_csv(tmp_path / "a.csv", tr)
    rows = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z [],v [m s^-1]\n"]
    for k in range(20):
        ns = round(float(tr.time[k]) * 1e9)
        rows.append(",".join([str(ns), *(f"{v:.9f}" for v in (*tr.t[k].tolist(), *tr.q[k].tolist())), "0.1"]) + "\n")
    (tmp_path / "gt.csv").write_text("".join(rows))
    (tmp_path / "00.txt").write_text(_kitti_lines(tr))
    for name in ("a.tum", "a.csv", "gt.csv", "00.txt"):
        r = read_trajectory(tmp_path / name, times=tr.time.numpy())
        assert (r.time - tr.time).abs().max() < 1e-6, name
        assert (r.t - tr.t).abs().max() < 5e-6, name
        assert rot_dist_deg(r.q, tr.q).max() < 1e-3, name
    assert torch.equal(read_trajectory(tmp_path / "00.txt", "kitti", times=tr.time).time, tr.time)


def test_kitti_rotation_checked(tmp_path):
    p = tmp_path / "00.txt"
    p.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DataError, match=r"00\.txt:2: the 3x3 part is not a rotation"):
        read_trajectory(p, times=[0.0, 0.1])


@pytest.mark.parametrize("text", ["1 2 3 4 5 6\n", "1,2,3\n", "1 2 3 4 5 6 7 8 9 10 11 12 13\n"])
def test_unknown_format_names_the_formats(tmp_path, text):
    p = tmp_path / "poses.txt"
    p.write_text("# a comment\n" + text)
    with pytest.raises(DataError, match=r"poses\.txt:2: expected") as e:
        read_trajectory(p)
    assert FORMAT_HELP in str(e.value)
    for name in ("TUM", "VINS CSV", "EuRoC ground-truth CSV", "KITTI"):
        assert name in FORMAT_HELP


def test_missing_file_and_wrong_format(tmp_path):
    with pytest.raises(DataError, match="trajectory file not found") as e:
        read_trajectory(tmp_path / "nope.csv")
    assert "nope.csv" in str(e.value)
    with pytest.raises(DataError, match="is a folder"):
        read_trajectory(tmp_path)
    p = tmp_path / "v.csv"
    p.write_text("1,0,0,0,1,0,0,0,\n")
    with pytest.raises(DataError, match=r"v\.csv:1: expected 8 space-separated"):
        read_trajectory(p, "tum")
    with pytest.raises(ValueError, match="format"):
        read_trajectory(p, "g2o")


# ---------------------------------------------------------------------------------------------
# interpolation


def test_interpolate_exact_at_samples_and_between():
    tr = make_traj(30)
    r = interpolate(tr, tr.time, max_gap=0.06)
    assert torch.equal(r.t, tr.t)
    assert rot_dist_deg(r.q, tr.q).max() < 1e-6
    # midpoints: linear position, slerp rotation = geodesic midpoint
    mid = (tr.time[:-1] + tr.time[1:]) / 2
    r = interpolate(tr, mid, max_gap=0.06)
    assert torch.allclose(r.t, (tr.t[:-1] + tr.t[1:]) / 2, atol=1e-6)
    Ra, Rb, Rm = quat_to_R(tr.q[:-1]), quat_to_R(tr.q[1:]), quat_to_R(r.q)
    half_a = rot_dist_deg(R_to_quat(Ra.transpose(-1, -2) @ Rm), torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))
    half_b = rot_dist_deg(R_to_quat(Rm.transpose(-1, -2) @ Rb), torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))
    assert torch.allclose(half_a, half_b, atol=1e-5) and half_a.max() > 0.1


def test_interpolate_slerp_short_way_and_constant_rate():
    # q and -q mixed: interpolation must take the short arc (yaw 10 -> 30 degrees)
    q0 = R_to_quat(ypr_to_R(torch.tensor([10.0, 0, 0], dtype=torch.float64)))
    q1 = -R_to_quat(ypr_to_R(torch.tensor([30.0, 0, 0], dtype=torch.float64)))
    tr = Trajectory(torch.tensor([0.0, 1.0], dtype=torch.float64), torch.zeros(2, 3, dtype=torch.float64),
                    torch.stack([q0, q1]))
    r = interpolate(tr, torch.tensor([0.25, 0.5], dtype=torch.float64), max_gap=2)
    assert R_to_ypr(quat_to_R(r.q))[:, 0].tolist() == pytest.approx([15.0, 20.0], abs=1e-9)
    assert (r.q[:, 0] >= 0).all()


def test_interpolate_coverage_errors():
    tr = make_traj(10, t0=100.0, dt=0.05)  # 100.00 .. 100.45
    gappy = Trajectory(torch.cat([tr.time[:5], tr.time[5:] + 1.0]), tr.t, tr.q)  # gap 100.2 -> 101.25
    with pytest.raises(DataError, match=r"gt\.csv: 1 of 3 query times not covered.*1 before the first pose"):
        interpolate(tr, [99.9, 100.1, 100.2], name="gt.csv")
    with pytest.raises(DataError, match=r"2 after the last pose"):
        interpolate(tr, [100.5, 100.6, 100.3])
    with pytest.raises(DataError, match=r"poses: .*1 in gaps longer than max_gap=0.1 s.*100.500000 s between poses "
                                        r"at 100.200000 and 101.250000"):
        interpolate(gappy, [100.1, 100.5])
    # sample times at either end of a long gap are still covered (exact samples)
    r = interpolate(gappy, [float(gappy.time[4]), float(gappy.time[5])])
    assert torch.equal(r.t, gappy.t[4:6])
    q = [99.9, 100.0, 100.1, 100.2, 100.5, 101.25, 101.3, 101.45, 101.5, float("nan")]
    assert covered(gappy, q).tolist() == [False, True, True, True, False, True, True, True, False, False]
    with pytest.raises(DataError, match="1 not finite"):
        interpolate(gappy, [100.1, float("nan")])
    one = Trajectory(tr.time[:1], tr.t[:1], tr.q[:1])
    assert covered(one, [100.0, 100.01]).tolist() == [True, False]
    assert torch.equal(interpolate(one, tr.time[:1]).t, tr.t[:1])
    with pytest.raises(DataError, match="only one pose"):
        interpolate(one, [100.01])


# ---------------------------------------------------------------------------------------------
# alignment and ATE


def _random_rigid(seed):
    g = torch.Generator().manual_seed(seed)
    R = ypr_to_R(torch.rand(3, generator=g, dtype=torch.float64) * torch.tensor([360.0, 120, 120]) - 60)
    t = torch.randn(3, generator=g, dtype=torch.float64) * 5
    return R, t


@pytest.mark.parametrize("with_scale", [False, True])
def test_align_recovers_known_transform(with_scale):
    tr = make_traj(40)
    R, t = _random_rigid(1)
    s = 2.5 if with_scale else 1.0
    ref = s * tr.t @ R.T + t
    R2, t2, s2 = align_se3(tr.t, ref, with_scale=with_scale)
    assert torch.allclose(R2, R, atol=1e-10) and torch.allclose(t2, t, atol=1e-9)
    assert float(s2) == pytest.approx(s, rel=1e-10)
    assert torch.linalg.det(R2).item() == pytest.approx(1.0)


def test_ate_zero_after_rigid_transform_and_known_noise():
    ref = make_traj(400, dt=0.01)
    R, t = _random_rigid(2)
    # the estimate lives in another frame: q' = R q, p' = R p + t
    est = Trajectory(ref.time, ref.t @ R.T + t, R_to_quat(R @ quat_to_R(ref.q)))
    assert ate_rmse(est, ref) < 1e-9
    assert ate_rmse(est, ref, align="none") > 1.0
    # isotropic Gaussian noise sigma per axis: RMSE -> sigma * sqrt(3) (3 of 3N dof absorbed by fit)
    g = torch.Generator().manual_seed(3)
    sigma = 0.02
    noisy = Trajectory(ref.time, ref.t + sigma * torch.randn(400, 3, generator=g, dtype=torch.float64), ref.q)
    e = ate_rmse(noisy, ref, align="none")
    assert e == pytest.approx(sigma * math.sqrt(3), rel=0.1)
    assert ate_rmse(noisy, ref, align="se3") <= e
    # sim3 removes a scale error that se3 cannot
    scaled = Trajectory(ref.time, 1.2 * ref.t, ref.q)
    assert ate_rmse(scaled, ref, align="sim3") < 1e-9 < ate_rmse(scaled, ref, align="se3")


def test_associate_nearest_within_max_dt():
    est = torch.tensor([0.0, 1.0, 1.004, 2.05, 3.0], dtype=torch.float64)
    ref = torch.tensor([0.01, 1.003, 2.0, 3.0], dtype=torch.float64)
    ie, ir = associate(est, ref, max_dt=0.02)
    # 1.004 is closer to 1.003 than 1.0 is: one-to-one keeps it; 2.05 is too far
    assert ie.tolist() == [0, 2, 4] and ir.tolist() == [0, 1, 3]


def test_ate_needs_overlap():
    a = make_traj(10, t0=0.0)
    b = make_traj(10, t0=1000.0)
    with pytest.raises(DataError, match=r"only 0 of 10 .* within max_dt=0.02"):
        ate_rmse(a, b)
    with pytest.raises(ValueError, match="align"):
        ate_rmse(a, a, align="scale")


# ---------------------------------------------------------------------------------------------
# drift


def test_add_drift_is_4dof_and_grows_with_distance():
    tr = make_traj(200, dt=0.02)
    d = add_drift(tr, yaw_deg_per_m=0.5, trans_frac=0.02, seed=4)
    assert torch.equal(d.time, tr.time) and torch.allclose(d.t[0], tr.t[0])
    ypr_a, ypr_b = R_to_ypr(quat_to_R(tr.q)), R_to_ypr(quat_to_R(d.q))
    assert torch.allclose(ypr_a[:, 1:], ypr_b[:, 1:], atol=1e-9)  # pitch, roll unchanged
    dist = torch.cat([torch.zeros(1, dtype=torch.float64), torch.diff(tr.t, dim=0).norm(dim=-1).cumsum(0)])
    dyaw = torch.remainder(ypr_b[:, 0] - ypr_a[:, 0] + 180, 360) - 180
    assert torch.allclose(dyaw, 0.5 * dist, atol=1e-8)
    err = (d.t - tr.t).norm(dim=-1)
    assert err[-1] > err[len(err) // 2] > err[1] > 0
    # translation-only drift: error = trans_frac * distance exactly, in a seed-given direction
    d2 = add_drift(tr, yaw_deg_per_m=0.0, trans_frac=0.02, seed=4)
    assert torch.allclose((d2.t - tr.t).norm(dim=-1), 0.02 * dist, atol=1e-12)
    assert not torch.allclose(add_drift(tr, 0.0, 0.02, seed=5).t, d2.t)
    assert torch.equal(add_drift(tr, 0.5, 0.02, seed=4).t, d.t)  # deterministic per seed
    # a drifted trajectory has ATE > 0 even after SE(3) alignment
    assert ate_rmse(d, tr) > 1e-3
