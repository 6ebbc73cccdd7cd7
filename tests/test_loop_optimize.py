"""Pose-graph optimiser (VINS optimize4DoF / loop_fusion optimize6DoF) against an independent
numpy solver written here (numerical Jacobians, IRLS Gauss-Newton with backtracking), on synthetic
drifting loops; convergence on a 1,000-keyframe loop vs fixed multiplicative damping; the yaw
single-wrap; analytic Jacobians vs autograd; implicit-function gradients (gradcheck); input checks;
each linear solver against a dense solve of its normal equations.
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import torch

from torch_frontend.errors import DataError
from torch_frontend.geometry import R_to_quat, R_to_ypr, quat_to_R, ypr_to_R
from torch_frontend.loop import linear_solvers as ls
from torch_frontend.loop import optimize as opt

HAS_SCIPY = importlib.util.find_spec("scipy") is not None
F64 = torch.float64


# ------------------------------------------------------------------------------------------------
# synthetic data: a closed loop flown `laps` times; vio = integrated noisy relative motion with a
# yaw drift (4-DoF) or a full rotation drift (6-DoF); loop edges = true relative poses between the
# same place on different laps
# ------------------------------------------------------------------------------------------------

def drifting_loop(N, laps=2, n_loops=20, radius=20.0, yaw_drift=0.02, rp_drift=0.0, t_noise=0.01, seed=0,
                  outliers=0):
    rng = np.random.default_rng(seed)
    th = 2 * math.pi * laps * np.arange(N) / N
    P = np.stack([radius * np.cos(th), radius * np.sin(th), 1.0 * np.sin(3 * th)], -1)
    ypr = np.stack([np.degrees(th) + 90.0, 3 * np.sin(5 * th), 2 * np.cos(4 * th)], -1)
    R = ypr_to_R(torch.from_numpy(ypr)).numpy()
    Pv, Rv = np.zeros_like(P), np.zeros_like(R)
    Pv[0], Rv[0] = P[0], R[0]
    for k in range(1, N):
        dR = R[k - 1].T @ R[k]
        dt = R[k - 1].T @ (P[k] - P[k - 1]) + rng.normal(0, t_noise, 3)
        d = np.array([yaw_drift + rng.normal(0, 0.01), rp_drift * rng.normal(), rp_drift * rng.normal()])
        Rd = ypr_to_R(torch.from_numpy(d)).numpy()
        Rv[k] = Rd @ Rv[k - 1] @ dR
        Pv[k] = Pv[k - 1] + Rv[k - 1] @ dt
    per = N // laps
    b = np.linspace(per + per // 10, N - 1, n_loops).astype(np.int64)
    a = b - per
    tm = np.einsum("eji,ej->ei", R[a], P[b] - P[a])
    if outliers:
        tm[:outliers] += np.array([0.6, -0.4, 0.3])  # a wrong loop: stays in Huber's linear part
    qa, qb = R_to_quat(torch.from_numpy(R[a])), R_to_quat(torch.from_numpy(R[b]))
    return dict(P=torch.from_numpy(P), R=torch.from_numpy(R), Pv=torch.from_numpy(Pv), Rv=torch.from_numpy(Rv),
                li=torch.from_numpy(a), lj=torch.from_numpy(b), lt=torch.from_numpy(tm),
                ly=torch.from_numpy(ypr[b, 0] - ypr[a, 0]), lq=opt._qmul(opt._qconj(qa), qb))


def _edges(d):
    N = d["Pv"].shape[0]
    si, sj = opt.sequential_edges(torch.zeros(N, dtype=torch.int64), 4)
    i, j = torch.cat([si, d["li"]]), torch.cat([sj, d["lj"]])
    loop = torch.cat([torch.zeros(len(si), dtype=torch.bool), torch.ones(len(d["li"]), dtype=torch.bool)])
    fixed = torch.zeros(N, dtype=torch.bool)
    fixed[0] = True
    return si, sj, i, j, loop, fixed


def problem4(d, dtype=F64, device="cpu"):
    si, sj, i, j, loop, fixed = _edges(d)
    tms, yms = opt.measurements_4dof(d["Pv"], d["Rv"], si, sj)
    ypr = R_to_ypr(d["Rv"])
    f = [d["Pv"], ypr[:, 0], ypr[:, 1], ypr[:, 2]]
    m = [torch.cat([tms, d["lt"]]), torch.cat([yms, d["ly"]])]
    f, m = [a.to(device, dtype) for a in f], [a.to(device, dtype) for a in m]
    return (*f, i.to(device), j.to(device), *m, loop.to(device), fixed.to(device))


def problem6(d, dtype=F64, device="cpu"):
    si, sj, i, j, loop, fixed = _edges(d)
    q = R_to_quat(d["Rv"])
    tms, qms = opt.measurements_6dof(d["Pv"], q, si, sj)
    f = [d["Pv"], q]
    m = [torch.cat([tms, d["lt"]]), torch.cat([qms, d["lq"]])]
    f, m = [a.to(device, dtype) for a in f], [a.to(device, dtype) for a in m]
    return (*f, i.to(device), j.to(device), *m, loop.to(device), fixed.to(device))


# ------------------------------------------------------------------------------------------------
# independent reference: numpy residuals, central-difference Jacobians, IRLS Gauss-Newton
# (weights ρ'(s) of Ceres's Huber per block) with Levenberg damping and backtracking
# ------------------------------------------------------------------------------------------------

def _np_ypr2R(y, p, r):
    y, p, r = np.radians(y), np.radians(p), np.radians(r)
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1)], -2)


def _np_qmul(a, b):
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - (av * bv).sum(-1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1)


def _np_qR(q):
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


class _Ref4:
    dim = 4

    def __init__(self, args):
        t, yaw, pitch, roll, i, j, tm, ym, loop, fixed = [a.detach().double().numpy() if a.is_floating_point()
                                                          else a.numpy() for a in args]
        self.x0 = np.concatenate([t, yaw[:, None]], -1)
        self.pitch, self.roll, self.i, self.j, self.tm, self.ym, self.loop, self.fixed = \
            pitch, roll, i, j, tm, ym, loop, fixed

    def residual(self, x):
        i, j = self.i, self.j
        R = _np_ypr2R(x[i, 3], self.pitch[i], self.roll[i])
        rt = np.einsum("eji,ej->ei", R, x[j, :3] - x[i, :3]) - self.tm
        a = x[j, 3] - x[i, 3] - self.ym
        a = np.where(a > 180, a - 360, np.where(a < -180, a + 360, a))
        return np.concatenate([rt, (np.where(self.loop, 0.1, 1.0) * a)[:, None]], -1)

    @staticmethod
    def plus(x, dx):
        return x + dx

    @staticmethod
    def out(x):
        return x


class _Ref6:
    dim = 6

    def __init__(self, args):
        t, q, i, j, tm, qm, loop, fixed = [a.detach().double().numpy() for a in args]
        self.x0 = np.concatenate([t, q], -1)
        self.i, self.j, self.tm, self.qm = i.astype(np.int64), j.astype(np.int64), tm, qm
        self.loop, self.fixed = loop.astype(bool), fixed.astype(bool)

    def residual(self, x):
        i, j = self.i, self.j
        rt = (np.einsum("eji,ej->ei", _np_qR(x[i, 3:]), x[j, :3] - x[i, :3]) - self.tm) / 0.1
        conj = np.array([1.0, -1, -1, -1])
        e = _np_qmul(_np_qmul(self.qm * conj, x[i, 3:] * conj), x[j, 3:])
        return np.concatenate([rt, 2 * e[:, 1:] / 0.01], -1)

    @staticmethod
    def plus(x, dx):  # rotation-vector perturbation on the left, renormalised
        th = np.linalg.norm(dx[:, 3:], axis=-1, keepdims=True)
        ax = dx[:, 3:] / np.maximum(th, 1e-300)
        dq = np.concatenate([np.cos(th / 2), np.sin(th / 2) * ax], -1)
        q = _np_qmul(dq, x[:, 3:])
        return np.concatenate([x[:, :3] + dx[:, :3], q / np.linalg.norm(q, axis=-1, keepdims=True)], -1)

    @staticmethod
    def out(x):
        return x


def _ref_cost_parts(ref, x):
    r = ref.residual(x)
    s = (r * r).sum(-1)
    out = ref.loop & (s > 0.01)
    rho = np.where(out, 0.2 * np.sqrt(np.maximum(s, 1e-300)) - 0.01, s)
    rho1 = np.where(out, 0.1 / np.sqrt(np.maximum(s, 1e-300)), 1.0)
    return r, 0.5 * rho.sum(), rho1


def reference_solve(ref, iters=200, h=1e-6):
    x = ref.x0.copy()
    N, dim = x.shape[0], ref.dim
    free = np.nonzero(~ref.fixed)[0]
    idx = [(n, k) for n in free for k in range(dim)]
    mu = 1e-6
    r, cost, w = _ref_cost_parts(ref, x)
    for _ in range(iters):
        J = np.zeros((r.size, len(idx)))
        for c, (n, k) in enumerate(idx):
            d = np.zeros((N, dim))
            d[n, k] = h
            J[:, c] = (ref.residual(ref.plus(x, d)) - ref.residual(ref.plus(x, -d))).ravel() / (2 * h)
        W = np.repeat(w, r.shape[1])
        H = J.T @ (W[:, None] * J)
        g = J.T @ (W * r.ravel())
        improved = False
        for _ in range(30):
            step = np.linalg.solve(H + mu * np.diag(np.diag(H)), -g)
            d = np.zeros((N, dim))
            d[free] = step.reshape(-1, dim)
            xn = ref.plus(x, d)
            rn, cn, wn = _ref_cost_parts(ref, xn)
            if cn <= cost:
                improved = cost - cn > 1e-15 * cost
                x, r, cost, w = xn, rn, cn, wn
                mu = max(mu / 3, 1e-12)
                break
            mu *= 4
        if not improved:
            break
    return x, cost


# ------------------------------------------------------------------------------------------------
# tests
# ------------------------------------------------------------------------------------------------

def test_sequential_edges_vins_pattern():
    seq = torch.tensor([0, 0, 0, 1, 1, 1, 1, 1, 1, 2])
    i, j = opt.sequential_edges(seq, 4)
    want = [(b - d, b) for b in range(len(seq)) for d in range(1, 5) if b - d >= 0 and seq[b - d] == seq[b]]
    assert list(zip(i.tolist(), j.tolist())) == want
    assert i.dtype == torch.int64 and opt.sequential_edges(seq, 0)[0].numel() == 0


def test_measurements_are_zero_residual_at_vio():
    """Sequential measurements reproduce the vio poses exactly: nothing moves, cost 0."""
    d = drifting_loop(40, n_loops=0)
    t, yaw, pitch, roll, i, j, tm, ym, loop, fixed = problem4(d)
    t2, y2, info = opt.optimize_4dof(t, yaw, pitch, roll, i, j, tm, ym, loop, fixed, return_info=True)
    assert info["cost_initial"] < 1e-20 and torch.allclose(t2, t) and torch.allclose(y2, yaw)
    t, q, i, j, tm, qm, loop, fixed = problem6(d)
    t2, q2, info = opt.optimize_6dof(t, q, i, j, tm, qm, loop, fixed, return_info=True)
    assert info["cost_initial"] < 1e-20 and torch.allclose(t2, t) and torch.allclose(q2, q)


@pytest.mark.parametrize("solver", ["dense", "banded", "lapack_banded", "splu"])
def test_4dof_small_graph_reaches_reference_optimum(solver):
    if solver in ("lapack_banded", "splu") and not HAS_SCIPY:
        pytest.skip("scipy is not installed: the scipy linear-solver options cannot run")
    d = drifting_loop(30, n_loops=6, yaw_drift=0.02, outliers=1)
    args = problem4(d)
    t, yaw, info = opt.optimize_4dof(*args, iters=100, return_info=True, solver=solver, function_tolerance=1e-14)
    ref = _Ref4(args)
    x_ref, cost_ref = reference_solve(ref)
    assert info["converged"] and info["solver"] == solver
    assert abs(info["cost_final"] - cost_ref) <= 1e-6 * cost_ref, (info["cost_final"], cost_ref)
    # the returned poses give that cost, and agree with the reference optimum
    x = torch.cat([t, yaw[:, None]], -1).numpy()
    assert abs(_ref_cost_parts(ref, x)[1] - cost_ref) <= 1e-6 * cost_ref
    assert np.abs(x - x_ref).max() < 1e-3
    # Huber is active at the optimum on the wrong loop edge, and the fixed node did not move
    s = (ref.residual(x) ** 2).sum(-1)
    assert s[ref.loop][0] > 0.01 and (s[ref.loop][1:] < 0.01).any()
    assert torch.equal(t[0], args[0][0]) and yaw[0] == args[1][0]


def test_4dof_default_five_iterations_and_dtypes(device, dtype):
    d = drifting_loop(60, n_loops=8, yaw_drift=0.02)
    args64 = problem4(d)
    t64, y64, info = opt.optimize_4dof(*args64, return_info=True)
    assert info["iterations"] <= 5 and info["cost_final"] < 0.9 * info["cost_initial"]
    t, y = opt.optimize_4dof(*problem4(d, dtype, device))
    assert t.dtype == dtype and t.device.type == device.type and y.shape == (60,)
    tol = 1e-8 if dtype == F64 else 2e-3
    assert torch.allclose(t.cpu().double(), t64, atol=tol * 50) and torch.allclose(y.cpu().double(), y64, atol=tol * 50)


def test_4dof_1000_keyframes_converges_and_fixed_damping_stalls():
    """Ceres-like gain-ratio damping converges within 10 iterations on a 1,000-keyframe drifting
    loop (20 loop edges); the fixed multiplicative damping diag(JᵀJ)·1e-4 stalls."""
    d = drifting_loop(1000, n_loops=20)
    args = problem4(d)
    _, _, full = opt.optimize_4dof(*args, iters=40, return_info=True, function_tolerance=1e-12)
    _, _, ada = opt.optimize_4dof(*args, iters=10, return_info=True)
    _, _, fix = opt.optimize_4dof(*args, iters=10, return_info=True, adaptive=False)
    c0, cstar = full["cost_initial"], full["cost_final"]
    gap_ada = (ada["cost_final"] - cstar) / (c0 - cstar)
    gap_fix = (fix["cost_final"] - cstar) / (c0 - cstar)
    print(f"cost0 {c0:.4f} optimum {cstar:.6f}; after 10 its: adaptive {ada['cost_final']:.6f} "
          f"({ada['termination']}, gap {gap_ada:.1e}), fixed 1e-4 {fix['cost_final']:.6f} (gap {gap_fix:.1e})")
    assert ada["converged"] or gap_ada < 1e-3
    assert gap_ada < 1e-3 and ada["iterations"] <= 10
    assert gap_fix > 10 * gap_ada and gap_fix > 1e-2


def test_6dof_small_graph_reaches_reference_optimum():
    d = drifting_loop(24, n_loops=5, yaw_drift=0.3, rp_drift=0.05, outliers=1)
    args = problem6(d)
    t, q, info = opt.optimize_6dof(*args, iters=100, return_info=True, function_tolerance=1e-14)
    ref = _Ref6(args)
    _, cost_ref = reference_solve(ref)
    assert info["converged"]
    assert abs(info["cost_final"] - cost_ref) <= 1e-6 * cost_ref, (info["cost_final"], cost_ref)
    assert torch.allclose(q.norm(dim=-1), torch.ones(24, dtype=F64), atol=1e-12)
    x = torch.cat([t, q], -1).numpy()
    s = (ref.residual(x) ** 2).sum(-1)
    assert s[ref.loop][0] > 0.01  # Huber active on the wrong loop
    assert torch.equal(t[0], args[0][0]) and torch.equal(q[0], args[1][0])


def test_6dof_loop_converges_and_keeps_unit_quaternions():
    d = drifting_loop(300, n_loops=10, yaw_drift=0.05, rp_drift=0.02)
    args = problem6(d)
    t, q, info = opt.optimize_6dof(*args, iters=10, return_info=True)
    _, _, full = opt.optimize_6dof(*args, iters=40, return_info=True, function_tolerance=1e-12)
    gap = (info["cost_final"] - full["cost_final"]) / (full["cost_initial"] - full["cost_final"])
    assert gap < 1e-3
    assert torch.allclose(q.norm(dim=-1), torch.ones(300, dtype=F64), atol=1e-12)
    # the loop pulls the drifted second lap back towards the truth
    err_vio = (args[0] - d["P"]).norm(dim=-1).max()
    assert (t - d["P"]).norm(dim=-1).max() < 0.7 * err_vio


def test_yaw_single_wrap_near_180():
    z = torch.zeros(2, dtype=F64)
    t = torch.zeros(2, 3, dtype=F64)  # coincident nodes: only the yaw residual is non-zero
    i, j = torch.tensor([0]), torch.tensor([1])
    tm = torch.zeros(1, 3, dtype=F64)
    loop, fixed = torch.tensor([False]), torch.tensor([True, False])

    def cost(yaw, ym, iters=0):
        out = opt.optimize_4dof(t, torch.tensor(yaw, dtype=F64), z, z, i, j, tm, torch.tensor([ym], dtype=F64),
                                loop, fixed, iters=iters, return_info=True)
        return out[2]["cost_initial"], out

    # across ±180: 179 -> -179 is +2 degrees, the residual wraps to 0
    assert cost([179.0, -179.0], 2.0)[0] < 1e-20
    # single wrap (Ceres NormalizeAngle), not a full normalisation: 600 -> 240, not -120
    assert cost([0.0, 600.0], 0.0)[0] == pytest.approx(0.5 * 240.0 ** 2)
    assert cost([0.0, -600.0], 0.0)[0] == pytest.approx(0.5 * 240.0 ** 2)
    # the yaw update is single-wrapped: 179.5 pulled by +1 degree lands on -179.5
    _, (_, yaw, info) = cost([0.0, 179.5], 180.5, iters=20)
    assert yaw[1] == pytest.approx(-179.5, abs=1e-6) and info["cost_final"] < 1e-12


def test_analytic_jacobians_match_autograd():
    d = drifting_loop(20, n_loops=3, yaw_drift=0.5, rp_drift=0.1)
    t, yaw, pitch, roll, i, j, tm, ym, loop, fixed = problem4(d)
    prob = opt._FourDof(pitch, roll, i, j, tm, ym, loop)
    x = torch.cat([t, yaw[:, None]], -1) + 0.3
    _, Ji, Jj = prob.linearize(x)
    J = torch.autograd.functional.jacobian(prob.residual, x)  # (E, 4, N, 4)
    e = torch.arange(len(i))
    assert torch.allclose(J[e, :, i], Ji, atol=1e-10) and torch.allclose(J[e, :, j], Jj, atol=1e-10)
    t, q, i, j, tm, qm, loop, fixed = problem6(d)
    prob = opt._SixDof(i, j, tm, qm, loop)
    x = torch.cat([t, q], -1)
    _, Ji, Jj = prob.linearize(x)
    J = torch.autograd.functional.jacobian(lambda dx: prob.residual(prob.plus(x, dx)), torch.zeros(20, 6, dtype=F64))
    assert torch.allclose(J[e, :, i], Ji, atol=1e-8) and torch.allclose(J[e, :, j], Jj, atol=1e-8)


_TIGHT = dict(iters=200, function_tolerance=0.0, gradient_tolerance=1e-13, parameter_tolerance=1e-15)
# The optimum is found to ~1e-10 (gradient ~1e-13 over a Hessian whose smallest eigenvalue is
# ~1e-3), so the finite differences use eps = 1e-3 (truncation ~1e-6, solver noise ~1e-6).
_GC = dict(eps=1e-3, atol=1e-5, rtol=1e-3)


def test_gradcheck_4dof_implicit_function():
    d = drifting_loop(8, n_loops=2, yaw_drift=0.5, outliers=1)
    t, yaw, pitch, roll, i, j, tm, ym, loop, fixed = problem4(d)
    L = int(loop.sum())

    def f(tm_loop, ym_loop, pitch_2):
        tm_ = torch.cat([tm[:-L], tm_loop])
        ym_ = torch.cat([ym[:-L], ym_loop])
        pitch_ = torch.cat([pitch[:3], pitch_2, pitch[5:]])
        return opt.optimize_4dof(t, yaw, pitch_, roll, i, j, tm_, ym_, loop, fixed, **_TIGHT)

    inputs = (tm[-L:].clone().requires_grad_(), ym[-L:].clone().requires_grad_(), pitch[3:5].clone().requires_grad_())
    assert torch.autograd.gradcheck(f, inputs, **_GC)


def test_gradcheck_6dof_implicit_function():
    d = drifting_loop(8, n_loops=2, yaw_drift=0.5, rp_drift=0.1, outliers=1)
    t, q, i, j, tm, qm, loop, fixed = problem6(d)
    L = int(loop.sum())

    def f(tm_loop, qm_loop):
        return opt.optimize_6dof(t, q, i, j, torch.cat([tm[:-L], tm_loop]), torch.cat([qm[:-L], qm_loop]), loop,
                                 fixed, **_TIGHT)

    inputs = (tm[-L:].clone().requires_grad_(), qm[-L:].clone().requires_grad_())
    # the 6-DoF optimum is found more precisely and its rotations curve more: eps = 1e-4
    assert torch.autograd.gradcheck(f, inputs, **{**_GC, "eps": 1e-4})


def test_gradient_flows_to_fixed_node_and_learns_a_measurement():
    """A loop measurement can be learnt through the optimum (gradient descent on a pose loss)."""
    d = drifting_loop(16, n_loops=3, yaw_drift=0.5)
    t, yaw, pitch, roll, i, j, tm, ym, loop, fixed = problem4(d)
    tm_l = tm.clone().requires_grad_()
    to, _ = opt.optimize_4dof(t, yaw, pitch, roll, i, j, tm_l, ym, loop, fixed, iters=50)
    loss = (to - d["P"]).pow(2).sum()
    loss.backward()
    assert torch.isfinite(tm_l.grad).all() and tm_l.grad[loop].abs().sum() > 0
    t_l = t.clone().requires_grad_()
    to, _ = opt.optimize_4dof(t_l, yaw, pitch, roll, i, j, tm, ym, loop, fixed, iters=50)
    to.sum().backward()
    # the fixed node carries the whole graph (a translation gauge): d(sum t)/d t_0 = N per axis
    assert torch.allclose(t_l.grad[0], torch.full((3,), 16.0, dtype=F64), atol=1e-4)
    assert t_l.grad[1:].abs().max() < 1e-6


def test_input_checks():
    d = drifting_loop(10, n_loops=1)
    args = list(problem4(d))
    with pytest.raises(ValueError, match=r"yaw: expected shape \(10,\)"):
        opt.optimize_4dof(*[args[0], args[1][:5]] + args[2:])
    bad = args[6].clone()
    bad[3, 1] = float("nan")
    with pytest.raises(DataError, match="t_meas"):
        opt.optimize_4dof(*args[:6], bad, *args[7:])
    bad = args[0].clone()
    bad[2, 0] = float("nan")
    with pytest.raises(DataError, match=r"t: .*row 2"):
        opt.optimize_4dof(bad, *args[1:])
    jj = args[5].clone()
    jj[0] = 10
    with pytest.raises(ValueError, match="out of range"):
        opt.optimize_4dof(*args[:5], jj, *args[6:])
    jj[0] = args[4][0]
    with pytest.raises(ValueError, match="itself"):
        opt.optimize_4dof(*args[:5], jj, *args[6:])
    with pytest.raises(ValueError, match="solver"):
        opt.optimize_4dof(*args, solver="cholmod")
    with pytest.raises(ValueError, match="band: expected a positive integer, got 0"):
        opt.optimize_4dof(*args, band=0)
    with pytest.raises(ValueError, match="iters: expected a non-negative integer, got 2.5"):
        opt.optimize_4dof(*args, iters=2.5)
    with pytest.raises(ValueError, match=r"t: expected shape \(N, 3\), got \(10, 2\)"):
        opt.optimize_4dof(args[0][:, :2], *args[1:])
    args6 = list(problem6(d))
    qm = args6[5].clone()
    qm[0] = 0.0
    with pytest.raises(DataError, match="q_meas"):
        opt.optimize_6dof(*args6[:5], qm, *args6[6:])
    with pytest.raises(ValueError, match=r"q: expected shape \(10, 4\)"):
        opt.optimize_6dof(args6[0], args6[1][:, :3], *args6[2:])


def _block_system(N=12, p=4, rd=4, band=2, seed=0):
    """A random SPD block system as the LM step builds it: near edges (at most ``band`` nodes
    apart) in the matrix part, two long edges as the low-rank part; and its full dense matrix."""
    g = torch.Generator().manual_seed(seed)
    si, sj = opt.sequential_edges(torch.zeros(N, dtype=torch.int64), band)
    fi, fj = torch.tensor([0, 3]), torch.tensor([9, 11])
    Je = torch.randn(si.numel(), rd, 2 * p, generator=g, dtype=F64)
    Jf = torch.randn(rd, 2 * p, fi.numel(), generator=g, dtype=F64)
    Hd = torch.eye(p, dtype=F64).repeat(N, 1, 1)
    Hd.index_add_(0, si, Je[..., :p].mT @ Je[..., :p]).index_add_(0, sj, Je[..., p:].mT @ Je[..., p:])
    Hij = Je[..., :p].mT @ Je[..., p:]
    Jff = Jf.permute(2, 0, 1)  # (F, rd, 2p)
    # the same long edges as matrix blocks (the dense and SuperLU methods take every edge there)
    Hd_all = Hd.clone().index_add_(0, fi, Jff[..., :p].mT @ Jff[..., :p])
    Hd_all.index_add_(0, fj, Jff[..., p:].mT @ Jff[..., p:])
    every = ls.BlockSystem(Hd_all, torch.cat([si, fi]), torch.cat([sj, fj]),
                           torch.cat([Hij, Jff[..., :p].mT @ Jff[..., p:]]), None)
    full = ls.dense_matrix(every.Hd, every.ei, every.ej, every.Hij)
    rhs = torch.randn(N, p, generator=g, dtype=F64)
    return ls.BlockSystem(Hd, si, sj, Hij, Jf), every, (si, sj, fi, fj), full, rhs


@pytest.mark.parametrize("method", ["dense", "banded", "lapack_banded", "splu"])
def test_linear_solvers_match_a_dense_solve(method):
    """Each method solves ``(B + U Uᵀ) x = rhs`` (Woodbury for the long edges' ``U`` in the banded
    ones) as ``torch.linalg.solve`` of the full matrix does."""
    if method in ("lapack_banded", "splu") and not HAS_SCIPY:
        pytest.skip("scipy is not installed: the scipy linear-solver options cannot run")
    N, p, rd, band = 12, 4, 4, 2
    banded, every, (si, sj, fi, fj), full, rhs = _block_system(N, p, rd, band)
    ref = torch.linalg.solve(full, rhs.reshape(-1)).reshape(N, p)
    if method in ("dense", "splu"):
        sys = every
        cr = ls.prepare_solver(method, N, p, band, every.ei, every.ej, fi[:0], fj[:0], rd, F64, rhs.device)
    else:
        sys, cr = banded, ls.prepare_solver(method, N, p, band, si, sj, fi, fj, rd, F64, rhs.device)
    x, ok = ls.solve(sys, rhs, method, cr)
    assert ok and x.shape == (N, p) and x.dtype == F64
    assert torch.allclose(x, ref, rtol=0, atol=1e-10 * ref.abs().max())
    assert ls.choose_solver("auto", rhs.device, 2, N, p, rd) == "dense"  # tiny: N p <= 128
    with pytest.raises(ValueError, match="band: expected a positive integer, got 1.5"):
        ls.check_solver_options(method, 1.5)


def test_all_fixed_or_no_edges_returns_inputs():
    d = drifting_loop(10, n_loops=1)
    t, yaw, pitch, roll, i, j, tm, ym, loop, fixed = problem4(d)
    allf = torch.ones_like(fixed)
    t2, y2, info = opt.optimize_4dof(t + 1, yaw, pitch, roll, i, j, tm, ym, loop, allf, return_info=True)
    assert torch.equal(t2, t + 1) and info["termination"] == "no_free_parameters"
    e = torch.zeros(0, dtype=torch.int64)
    t2, y2 = opt.optimize_4dof(t, yaw, pitch, roll, e, e, tm[:0], ym[:0], loop[:0], fixed)
    assert torch.equal(t2, t) and torch.equal(y2, yaw)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_dense_path_matches_cpu():
    d = drifting_loop(200, n_loops=6)
    a, b = problem4(d), problem4(d, device="cuda")
    t_c, y_c, info = opt.optimize_4dof(*b, return_info=True)
    t, y = opt.optimize_4dof(*a)
    assert info["solver"] == "dense" and torch.allclose(t_c.cpu(), t, atol=1e-8)
    q = quat_to_R(R_to_quat(d["Rv"][:2]))
    assert torch.allclose(q, d["Rv"][:2], atol=1e-12)
