"""Pose-graph optimisation of VINS's loop closure: ``optimize4DoF`` (§7.8) and loop_fusion's
``optimize6DoF`` (§7.12), as batched torch Levenberg-Marquardt with differentiable optima.

Convention:
    * Nodes are keyframes of the optimisation window in list order; poses are body-to-world
      ``(R_w_i, T_w_i)``, float64 by default (float32 allowed), translations in metres.
    * 4-DoF: per node ``t (N, 3)`` and ``yaw (N,)`` are optimised; ``pitch, roll (N,)`` are
      constants. Angles are in **degrees** (VINS ``ypr2R``: ``Rz(yaw) Ry(pitch) Rx(roll)``).
    * 6-DoF: per node ``t (N, 3)`` and the unit quaternion ``q (N, 4)`` **w-first** ``(w, x, y, z)``.
    * Edge ``e`` constrains node ``j[e]`` relative to node ``i[e]`` (``i`` is the older node ``a``
      of the spec). ``is_loop (E,)`` marks loop edges (Huber 0.1 loss, 4-DoF yaw residual / 10);
      ``fixed (N,)`` marks constant nodes (the earliest loop target, loaded keyframes).

The solver is Ceres's default trust region as VINS runs it (``max_num_iterations = 5``):
Levenberg-Marquardt with the damping ``diag(JᵀJ) / radius`` (initial radius 1e4), the radius
updated by the gain ratio (×1/max(1/3, 1 − (2ρ − 1)³) on success, ÷2, ÷4, ... on failure), the
robust loss through Ceres's corrector (Huber's ρ'' < 0 ⇒ plain ``sqrt(ρ')`` weighting) and Ceres's
function / gradient / parameter tolerances. Residuals and Jacobians are analytic and batched over
edges; the normal equations are assembled per node block with ``index_add``/``index_put``.

Linear solvers (``solver=``, module :mod:`.linear_solvers`): ``"dense"`` (torch Cholesky of the
full ``pN × pN`` matrix; the CUDA default), ``"banded"`` (torch block cyclic reduction of the
block-tridiagonal matrix formed by the edges between nodes at most ``band`` slots apart, plus a
Woodbury correction for the other edges, i.e. the few long loop edges; the CPU default without
scipy), ``"lapack_banded"`` (scipy's LAPACK band Cholesky ``dpbtrf`` / ``dtbtrs`` + the same
Woodbury correction; the CPU default with scipy) and ``"splu"`` (scipy.sparse SuperLU). ``"auto"``
picks dense on CUDA and for tiny graphs, on CPU lapack_banded (banded without scipy), and SuperLU
(when scipy is installed) when the long edges are too many for a low-rank correction (see
``benchmarks/bench_pose_graph.py``).

Gradients: the returned optimum is differentiable w.r.t. the measurements (and the constants:
pitch/roll, fixed nodes' poses) by the implicit-function theorem: backward solves ``H λ = v``
with the exact Hessian of the cost at the returned point and back-propagates ``−λ·∂∇ₓF/∂θ``.
This assumes the returned point is an optimum (converged solve); with ``iters=5`` on a badly
drifted graph it is an approximation. Gradients w.r.t. the free nodes' initial values are zero.
"""

from __future__ import annotations

import math
from typing import Dict, Tuple

import torch

from .._checks import check_int, check_shape
from ..errors import DataError
from ..geometry import R_to_ypr, quat_to_R, wrap_angle_once, ypr_to_R
from ..geometry import quat_conj as _qconj
from ..geometry import quat_exp as _quat_exp
from ..geometry import quat_mul as _qmul
from ..geometry import skew as _skew
from .linear_solvers import (
    SOLVERS,  # noqa: F401 (optimize.SOLVERS: the solver= choices)
    BlockSystem,
    check_solver_options,
    choose_solver,
    dense_matrix,
    prepare_solver,
    solve,
)

__all__ = [
    "measurements_4dof",
    "measurements_6dof",
    "optimize_4dof",
    "optimize_6dof",
    "sequential_edges",
]

_DEG = math.pi / 180.0
HUBER_DELTA = 0.1  # ceres::HuberLoss(0.1) on loop edges (both modes)
LOOP_YAW_WEIGHT = 0.1  # FourDOFWeightError: yaw residual / 10 on loop edges
T_SCALE_6DOF = 0.1  # RelativeRTError: translation residual / 0.1
Q_SCALE_6DOF = 0.01  # RelativeRTError: rotation residual / 0.01


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------

def _huber(s: torch.Tensor, loop: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Ceres HuberLoss(0.1) on loop edges, identity on the others: ``(ρ(s), ρ'(s))``.

    ``s`` is the squared norm of the residual block. The outlier branch is evaluated on a
    clamped ``s`` so its (unused) value and gradient stay finite at ``s = 0``.
    """
    b = HUBER_DELTA * HUBER_DELTA
    out = loop & (s > b)
    sq = torch.sqrt(torch.where(out, s, torch.ones_like(s)))
    rho = torch.where(out, 2.0 * HUBER_DELTA * sq - b, s)
    rho1 = torch.where(out, HUBER_DELTA / sq, torch.ones_like(s))
    return rho, rho1


# --------------------------------------------------------------------------------------------
# the two residual models
# --------------------------------------------------------------------------------------------

class _FourDof:
    """FourDOFError / FourDOFWeightError. State ``x (N, 4) = (t, yaw°)``; tangent = state."""

    p = 4
    rd = 4

    def __init__(self, pitch, roll, i, j, t_meas, yaw_meas, is_loop):
        self.i, self.j, self.t_meas, self.yaw_meas, self.loop = i, j, t_meas, yaw_meas, is_loop
        z = torch.zeros_like(pitch)
        # R_a = Rz(yaw_a) Ry(pitch_a) Rx(roll_a): the constant Ry Rx part per edge, transposed
        self.A = ypr_to_R(torch.stack([z, pitch, roll], -1))[i].mT.contiguous()
        self.AT = self.A.permute(1, 2, 0).contiguous()  # (3, 3, E)
        self.t_meas_t = t_meas.T.contiguous()  # (3, E)
        self.w = torch.where(is_loop, LOOP_YAW_WEIGHT, 1.0).to(pitch.dtype)

    def _parts(self, x):
        # elementwise products with the edge index last (batched (E, 3, 3) bmm's are slow on CPU)
        xi, xj = x[self.i], x[self.j]
        d = (xj[:, :3] - xi[:, :3]).T  # (3, E)
        psi = xi[:, 3] * _DEG
        c, s = torch.cos(psi), torch.sin(psi)
        AT = self.AT
        u0, u1 = c * d[0] + s * d[1], -s * d[0] + c * d[1]  # Rz(ψ)ᵀ d
        rt = AT[:, 0] * u0 + AT[:, 1] * u1 + AT[:, 2] * d[2] - self.t_meas_t
        rpsi = self.w * wrap_angle_once(xj[:, 3] - xi[:, 3] - self.yaw_meas)
        return torch.cat([rt, rpsi[None]]), c, s, d

    def residual_t(self, x):
        """``(rd, E)`` residuals, edge index last."""
        return self._parts(x)[0]

    def residual(self, x):
        return self.residual_t(x).T

    def linearize_t(self, x):
        """``(r (rd, E), J (rd, 2p, E))`` with ``J = [∂r/∂x_i, ∂r/∂x_j]``, edge index last."""
        r, c, s, d = self._parts(x)
        AT = self.AT
        RiT = torch.stack([AT[:, 0] * c - AT[:, 1] * s, AT[:, 0] * s + AT[:, 1] * c, AT[:, 2]], 1)  # A Rz(ψ)ᵀ
        du0, du1 = (-s * d[0] + c * d[1]) * _DEG, (-c * d[0] - s * d[1]) * _DEG
        J = r.new_zeros(4, 8, r.shape[1])
        J[:3, :3] = -RiT
        J[:3, 3] = AT[:, 0] * du0 + AT[:, 1] * du1
        J[:3, 4:7] = RiT
        J[3, 3] = -self.w
        J[3, 7] = self.w
        return r, J

    def linearize(self, x):
        r, J = self.linearize_t(x)
        J = J.permute(2, 0, 1)
        return r.T, J[..., :4], J[..., 4:]

    @staticmethod
    def plus(x, dx):
        # AngleLocalParameterization: plus, then Ceres's single-wrap NormalizeAngle
        return torch.cat([x[:, :3] + dx[:, :3], wrap_angle_once(x[:, 3:] + dx[:, 3:])], -1)

    # exact per-edge cost for the implicit-function backward (torch.func-friendly, unbatched)
    @staticmethod
    def edge_cost(xi, xj, pitch_i, roll_i, tm, ym, loop):
        R = ypr_to_R(torch.stack([xi[3], pitch_i, roll_i]))
        rt = R.mT @ (xj[:3] - xi[:3]) - tm
        w = torch.where(loop, LOOP_YAW_WEIGHT, 1.0)
        r = torch.cat([rt, (w * wrap_angle_once(xj[3] - xi[3] - ym))[None]])
        return 0.5 * _huber((r * r).sum(), loop)[0]


class _SixDof:
    """RelativeRTError. State ``x (N, 7) = (t, q wxyz)``; tangent ``(dt, dθ)`` with Ceres's
    quaternion plus ``q ← (cos|dθ|, sin|dθ| dθ/|dθ|) ⊗ q``."""

    p = 6
    rd = 6

    def __init__(self, i, j, t_meas, q_meas, is_loop):
        self.i, self.j, self.t_meas, self.loop = i, j, t_meas, is_loop
        self.qm_inv = _qconj(q_meas)

    def _parts(self, x):
        xi, xj = x[self.i], x[self.j]
        Ri, Rj = quat_to_R(xi[:, 3:]), quat_to_R(xj[:, 3:])
        d = xj[:, :3] - xi[:, :3]
        rt = ((Ri.mT @ d[..., None])[..., 0] - self.t_meas) / T_SCALE_6DOF
        e = _qmul(_qmul(self.qm_inv, _qconj(xi[:, 3:])), xj[:, 3:])
        rq = 2.0 * e[:, 1:] / Q_SCALE_6DOF
        return torch.cat([rt, rq], -1), Ri, Rj, d, e

    def residual(self, x):
        return self._parts(x)[0]

    def residual_t(self, x):
        return self._parts(x)[0].T

    def linearize_t(self, x):
        """``(r (rd, E), J (rd, 2p, E))`` as :meth:`linearize`, edge index last and with
        elementwise products (batched (E, 3, 3) bmm's are slow on CPU)."""
        xi, xj = x[self.i], x[self.j]
        RiT = quat_to_R(xi[:, 3:]).permute(2, 1, 0)  # (3, 3, E): RiT[a, b] = R_i[b, a]
        Rj = quat_to_R(xj[:, 3:]).permute(1, 2, 0)  # (3, 3, E): Rj[c] = row c of R_j
        d = (xj[:, :3] - xi[:, :3]).T
        rt = ((RiT * d).sum(1) - self.t_meas.T) / T_SCALE_6DOF
        e = _qmul(_qmul(self.qm_inv, _qconj(xi[:, 3:])), xj[:, 3:]).T  # (4, E)
        r = torch.cat([rt, 2.0 * e[1:] / Q_SCALE_6DOF])
        J = r.new_zeros(6, 12, r.shape[1])
        J[:3, :3] = -RiT / T_SCALE_6DOF
        J[:3, 3:6] = torch.linalg.cross(RiT, d.expand(3, 3, -1), dim=1) * (2.0 / T_SCALE_6DOF)  # Rᵢᵀ[d]×
        J[:3, 6:9] = RiT / T_SCALE_6DOF
        # M = (e_w I + [e_v]×) R_jᵀ: column c is e_w R_j[c] + e_v × R_j[c]
        M = (e[0] * Rj + torch.linalg.cross(e[1:].expand(3, 3, -1), Rj, dim=1)).transpose(0, 1) * (2.0 / Q_SCALE_6DOF)
        J[3:, 3:6] = -M
        J[3:, 9:12] = M
        return r, J

    def linearize(self, x):
        r, Ri, Rj, d, e = self._parts(x)
        E = r.shape[0]
        eye = torch.eye(3, dtype=r.dtype, device=r.device)
        # q' = p ⊗ q with p ≈ (1, δ): R' ≈ (I + 2[δ]×) R and e' ≈ e ⊗ (1, ±R_jᵀ δ)
        M = (e[:, :1, None] * eye + _skew(e[:, 1:])) @ Rj.mT * (2.0 / Q_SCALE_6DOF)
        Ji = r.new_zeros(E, 6, 6)
        Jj = r.new_zeros(E, 6, 6)
        Ji[:, :3, :3] = -Ri.mT / T_SCALE_6DOF
        Ji[:, :3, 3:] = Ri.mT @ _skew(d) * (2.0 / T_SCALE_6DOF)
        Ji[:, 3:, 3:] = -M
        Jj[:, :3, :3] = Ri.mT / T_SCALE_6DOF
        Jj[:, 3:, 3:] = M
        return r, Ji, Jj

    @staticmethod
    def plus(x, dx):
        q = _qmul(_quat_exp(dx[:, 3:]), x[:, 3:])
        return torch.cat([x[:, :3] + dx[:, :3], q / q.norm(dim=-1, keepdim=True)], -1)

    @staticmethod
    def edge_cost(di, dj, xi, xj, tm, qm, loop):
        # second-order retraction (1 − |δ|²/2, δ) ⊗ q: enough for the exact Hessian at δ = 0
        def ret(d, q):
            return _qmul(torch.cat([(1.0 - 0.5 * (d[3:] * d[3:]).sum())[None], d[3:]]), q)

        qi, qj = ret(di, xi[3:]), ret(dj, xj[3:])
        Ri = quat_to_R(qi)
        rt = (Ri.mT @ (xj[:3] + dj[:3] - xi[:3] - di[:3]) - tm) / T_SCALE_6DOF
        qi_n = qi / qi.norm()
        qj_n = qj / qj.norm()
        e = _qmul(_qmul(_qconj(qm), _qconj(qi_n)), qj_n)
        r = torch.cat([rt, 2.0 * e[1:] / Q_SCALE_6DOF])
        return 0.5 * _huber((r * r).sum(), loop)[0]


# --------------------------------------------------------------------------------------------
# Levenberg-Marquardt (Ceres trust region, as VINS configures it)
# --------------------------------------------------------------------------------------------

def _lm(prob, x, fixed, iters, *, solver="auto", band=4, function_tolerance=1e-6, gradient_tolerance=1e-10,
        parameter_tolerance=1e-8, initial_radius=1e4, adaptive=True, min_relative_decrease=1e-3):
    """Minimise ``½ Σ ρ(|r_e|²)`` over the free nodes; returns ``(x, info)``."""
    i, j, loop = prob.i, prob.j, prob.loop
    N, p = x.shape[0], prob.p
    free = ~fixed
    dev, dt = x.device, x.dtype
    far = (i - j).abs() > band
    method = choose_solver(solver, dev, int(far.sum()), N, p, prob.rd)
    if method in ("dense", "splu"):
        far = torch.zeros_like(far)
    near = ~far
    ni, nj = i[near], j[near]
    fi, fj = i[far], j[far]
    eye = torch.eye(p, dtype=dt, device=dev)
    cr = prepare_solver(method, N, p, band, ni, nj, fi, fj, prob.rd, dt, dev)

    def evaluate(xx):
        r = prob.residual_t(xx)
        return 0.5 * _huber((r * r).sum(0), loop)[0].sum()

    near_idx = near.nonzero()[:, 0]
    far_idx = far.nonzero()[:, 0]
    # fixed nodes are Ceres constant blocks: their columns vanish from J
    colmask_t = torch.cat([free[None, i].expand(p, -1), free[None, j].expand(p, -1)]).to(dt)  # (2p, E)

    rd = prob.rd
    far_ij = torch.cat([fi, fj])
    F = far_idx.numel()

    def linearize(xx):
        r, J = prob.linearize_t(xx)  # (rd, E), (rd, 2p, E)
        rho, rho1 = _huber((r * r).sum(0), loop)
        J = J.mul_(colmask_t)
        wJ = J * rho1
        # per-edge blocks of JᵀWJ as rd broadcast outer products with the edge index last
        # (contiguous, vectorised; a batched bmm of E tiny products is ~5x slower on CPU)
        Hii = J[0, :p, None] * wJ[0, None, :p]
        Hij = J[0, :p, None] * wJ[0, None, p:]
        Hjj = J[0, p:, None] * wJ[0, None, p:]
        for k in range(1, rd):
            Hii.addcmul_(J[k, :p, None], wJ[k, None, :p])
            Hij.addcmul_(J[k, :p, None], wJ[k, None, p:])
            Hjj.addcmul_(J[k, p:, None], wJ[k, None, p:])
        ge = (wJ * r[:, None]).sum(0)  # (2p, E)
        # accumulate per node with the node index last too (contiguous slices), then transpose once
        g = x.new_zeros(p, N).index_add_(1, i, ge[:p]).index_add_(1, j, ge[p:]).T.contiguous()
        HdT = x.new_zeros(p, p, N).index_add_(2, i, Hii).index_add_(2, j, Hjj)
        Hd_all = HdT.permute(2, 0, 1).contiguous()
        Hij = Hij.permute(2, 0, 1)  # (E, p, p) view
        U = None
        Hd_near = Hd_all
        if F:
            HdT.index_add_(2, far_ij, -torch.cat([Hii[..., far_idx], Hjj[..., far_idx]], -1))
            Hd_near = HdT.permute(2, 0, 1).contiguous()
            Hij = Hij[near_idx]
            Jf = J[:, :, far_idx] * rho1[far_idx].sqrt()  # (rd, 2p, F)
            U = Jf  # (far edges only with the banded solvers) scattered straight into their rhs buffers
        return dict(cost=0.5 * rho.sum(), g=g, Hd_near=Hd_near, Hd_all=Hd_all, Hij=Hij, U=U, J=J, rho1=rho1)

    lin = linearize(x)
    cost = float(lin["cost"])
    info = dict(cost_initial=cost, cost_final=cost, iterations=0, successful_steps=0, converged=False,
                termination="max_iterations", solver=method, cost_history=[cost])
    if not bool(free.any()) or i.numel() == 0:
        info.update(converged=True, termination="no_free_parameters")
        return x, info
    if float(lin["g"].abs().max()) <= gradient_tolerance:
        info.update(converged=True, termination="gradient_tolerance")
        return x, info
    radius, decrease = float(initial_radius), 2.0
    fmask = free[:, None, None]
    for it in range(1, iters + 1):
        info["iterations"] = it
        # Ceres LM: (JᵀJ + diag(JᵀJ)/radius) δ = −g, diag clamped to [1e-6, 1e32]
        damp = lin["Hd_all"].diagonal(0, -2, -1).clamp(1e-6, 1e32) / radius
        Hd = torch.where(fmask, lin["Hd_near"] + torch.diag_embed(damp), eye)
        sys = BlockSystem(Hd, ni, nj, lin["Hij"], lin["U"])
        delta, ok = solve(sys, -lin["g"], method, cr)
        delta = delta * free[:, None]
        if ok:
            Jd = (lin["J"] * torch.cat([delta[i], delta[j]], -1).T).sum(1)  # (rd, E)
            model = -((lin["g"] * delta).sum() + 0.5 * (lin["rho1"] * (Jd * Jd).sum(0)).sum())
            ok = bool(torch.isfinite(model)) and float(model) > 0
        if not ok:  # invalid step: shrink the trust region (Ceres StepIsInvalid)
            if adaptive:
                radius, decrease = radius / decrease, decrease * 2.0
            info["cost_history"].append(cost)
            continue
        if float(delta.norm()) <= parameter_tolerance * (float(x.norm()) + parameter_tolerance):
            info.update(converged=True, termination="parameter_tolerance")
            break
        xc = torch.where(free[:, None], prob.plus(x, delta), x)
        cost_c = float(evaluate(xc))
        if abs(cost - cost_c) <= function_tolerance * abs(cost):
            info.update(converged=True, termination="function_tolerance")
            break
        rel = (cost - cost_c) / float(model)
        if rel > min_relative_decrease:
            x = xc
            info["successful_steps"] += 1
            if adaptive:
                radius = min(1e16, radius / max(1.0 / 3.0, 1.0 - (2.0 * rel - 1.0) ** 3))
                decrease = 2.0
            lin = linearize(x)
            cost = float(lin["cost"])
            info["cost_history"].append(cost)
            if float(lin["g"].abs().max()) <= gradient_tolerance:
                info.update(converged=True, termination="gradient_tolerance")
                break
        else:
            if adaptive:
                radius, decrease = radius / decrease, decrease * 2.0
            info["cost_history"].append(cost)
    info["cost_final"] = cost
    info["gradient_max_norm"] = float(lin["g"].abs().max())
    return x, info


# --------------------------------------------------------------------------------------------
# implicit-function backward
# --------------------------------------------------------------------------------------------

def _ift_setup(edge_cost, hess_args, total_cost, theta, fixed, i, j, N, p):
    """Everything the implicit-function backward reuses across calls on one forward (autograd
    asks once per output row in gradcheck / jacobian): the factor of the exact Hessian at the
    optimum (torch.func per edge block; fixed rows = identity) and the VJP of the cost gradient
    ``∇ₓF(x*, θ)`` w.r.t. ``θ`` (linearised once)."""
    from torch.func import grad, hessian, vjp, vmap

    (Hii, Hij), (_, Hjj) = vmap(hessian(edge_cost, argnums=(0, 1)))(*hess_args)
    free = ~fixed
    dt, dev = Hii.dtype, Hii.device
    Hd = Hii.new_zeros(N, p, p).index_add_(0, i, Hii).index_add_(0, j, Hjj)
    Hd = torch.where(free[:, None, None], Hd, torch.eye(p, dtype=dt, device=dev))
    Hij = Hij * (free[i] & free[j])[:, None, None]
    H = dense_matrix(Hd, i, j, Hij)
    L, info = torch.linalg.cholesky_ex(H)
    # gauge freedom (no fixed node) or an indefinite Hessian: least-squares (pseudo-inverse) answer
    Hinv = None if bool(info == 0) else torch.linalg.pinv(H, hermitian=True)
    d0 = torch.zeros(N, p, dtype=dt, device=dev)
    _, vjp_fn = vjp(lambda *th: grad(total_cost)(d0, *th), *theta)
    return dict(L=L, Hinv=Hinv, vjp=vjp_fn, free=free)


def _ift_grads(cache, v):
    """``−(∂∇ₓF/∂θ)ᵀ H⁻¹ v`` for the output cotangent ``v (N, p)`` (fixed rows ignored)."""
    N, p = v.shape
    rhs = (v * cache["free"][:, None]).reshape(-1, 1)
    lam = torch.cholesky_solve(rhs, cache["L"]) if cache["Hinv"] is None else cache["Hinv"] @ rhs
    lam = lam.reshape(N, p) * cache["free"][:, None]
    return [-g for g in cache["vjp"](lam)]


class _Opt4(torch.autograd.Function):
    @staticmethod
    def forward(ctx, t, yaw, pitch, roll, t_meas, yaw_meas, i, j, is_loop, fixed, opts, box):
        prob = _FourDof(pitch, roll, i, j, t_meas, yaw_meas, is_loop)
        x0 = torch.cat([t, yaw[:, None]], -1)
        o = dict(opts)
        x, info = _lm(prob, x0, fixed, o.pop("iters"), **o)
        box.update(info)
        ctx.save_for_backward(t, yaw, pitch, roll, t_meas, yaw_meas, i, j, is_loop, fixed, x)
        ctx.cache = None
        return x[:, :3].clone(), x[:, 3].clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gt, gyaw):
        t, yaw, pitch, roll, t_meas, yaw_meas, i, j, is_loop, fixed, x = ctx.saved_tensors
        N = t.shape[0]
        gt = gt if gt is not None else t.new_zeros(N, 3)
        gyaw = gyaw if gyaw is not None else yaw.new_zeros(N)
        if ctx.cache is None:
            from torch.func import vmap

            def total(d, t_in, yaw_in, pitch_, roll_, tm, ym):
                # the fixed nodes' values are inputs (constants of the problem), the others the optimum
                xb = torch.cat([torch.where(fixed[:, None], t_in, x[:, :3]),
                                torch.where(fixed, yaw_in, x[:, 3])[:, None]], -1)
                xx = xb + d
                return vmap(_FourDof.edge_cost)(xx[i], xx[j], pitch_[i], roll_[i], tm, ym, is_loop).sum()

            xb = torch.cat([torch.where(fixed[:, None], t, x[:, :3]), torch.where(fixed, yaw, x[:, 3])[:, None]], -1)
            ctx.cache = _ift_setup(_FourDof.edge_cost, (xb[i], xb[j], pitch[i], roll[i], t_meas, yaw_meas, is_loop),
                                   total, (t, yaw, pitch, roll, t_meas, yaw_meas), fixed, i, j, N, 4)
        grads = _ift_grads(ctx.cache, torch.cat([gt, gyaw[:, None]], -1))
        # fixed nodes are returned as given: their output gradient passes straight through
        grads[0] = grads[0] + torch.where(fixed[:, None], gt, 0.0)
        grads[1] = grads[1] + torch.where(fixed, gyaw, 0.0)
        return (*grads, None, None, None, None, None, None)


class _Opt6(torch.autograd.Function):
    @staticmethod
    def forward(ctx, t, q, t_meas, q_meas, i, j, is_loop, fixed, opts, box):
        prob = _SixDof(i, j, t_meas, q_meas, is_loop)
        o = dict(opts)
        x, info = _lm(prob, torch.cat([t, q], -1), fixed, o.pop("iters"), **o)
        box.update(info)
        ctx.save_for_backward(t, q, t_meas, q_meas, i, j, is_loop, fixed, x)
        ctx.cache = None
        return x[:, :3].clone(), x[:, 3:].clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gt, gq):
        t, q, t_meas, q_meas, i, j, is_loop, fixed, x = ctx.saved_tensors
        N = t.shape[0]
        gt = gt if gt is not None else t.new_zeros(N, 3)
        gq = gq if gq is not None else q.new_zeros(N, 4)
        qs = x[:, 3:]
        if ctx.cache is None:
            from torch.func import vmap

            def total(d, t_in, q_in, tm, qm):
                xb = torch.cat([torch.where(fixed[:, None], t_in, x[:, :3]), torch.where(fixed[:, None], q_in, qs)], -1)
                return vmap(_SixDof.edge_cost)(d[i], d[j], xb[i], xb[j], tm, qm, is_loop).sum()

            xb = torch.cat([torch.where(fixed[:, None], t, x[:, :3]), torch.where(fixed[:, None], q, qs)], -1)
            z = x.new_zeros(i.shape[0], 6)
            ctx.cache = _ift_setup(_SixDof.edge_cost, (z, z, xb[i], xb[j], t_meas, q_meas, is_loop), total,
                                   (t, q, t_meas, q_meas), fixed, i, j, N, 6)
        w, a, b, c = qs.unbind(-1)
        # ∂((1, δ) ⊗ q)/∂δ (Ceres's QuaternionParameterization Jacobian), (N, 4, 3): the output
        # cotangent of q in the tangent space of the optimum
        Jp = torch.stack([-a, -b, -c, w, c, -b, -c, w, a, b, -a, w], -1).reshape(N, 4, 3)
        grads = _ift_grads(ctx.cache, torch.cat([gt, (Jp.mT @ gq[..., None])[..., 0]], -1))
        grads[0] = grads[0] + torch.where(fixed[:, None], gt, 0.0)
        grads[1] = grads[1] + torch.where(fixed[:, None], gq, 0.0)
        return (*grads, None, None, None, None, None, None)


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------

def _check_float(a, name, shape, ref=None):
    """A floating point tensor of ``shape`` (a ``check_shape`` pattern), finite, and of ``ref``'s
    dtype and device when given."""
    check_shape(a, shape, name)
    if not a.is_floating_point():
        raise TypeError(f"{name}: expected a floating point tensor, got {a.dtype}")
    if ref is not None and (a.dtype != ref.dtype or a.device != ref.device):
        raise ValueError(f"{name}: expected {ref.dtype} on {ref.device} like t, got {a.dtype} on {a.device}")
    bad = ~torch.isfinite(a.detach())
    if bool(bad.any()):
        k = int(bad.reshape(a.shape[0], -1).any(-1).nonzero()[0, 0]) if a.dim() else 0
        raise DataError(f"{name}: non-finite value (NaN or inf) at row {k}")


def _check_index(a, name, E, N, device):
    """Node indices: an integer tensor of shape ``(E,)`` (any length when ``E`` is None) in
    ``[0, N)``; returned as int64 on ``device``."""
    check_shape(a, ("E",) if E is None else (E,), name)
    if a.dtype.is_floating_point or a.dtype == torch.bool or a.is_complex():
        raise TypeError(f"{name}: expected an integer tensor, got {a.dtype}")
    a = a.to(device=device, dtype=torch.int64)
    if a.numel() and (int(a.min()) < 0 or int(a.max()) >= N):
        raise ValueError(f"{name}: node index out of range [0, {N}) (min {int(a.min())}, max {int(a.max())})")
    return a


def _check_bool(a, name, n, device):
    """A ``(n,)`` bool tensor, returned on ``device``."""
    check_shape(a, (n,), name)
    if a.dtype != torch.bool:
        raise TypeError(f"{name}: expected a bool tensor, got {a.dtype}")
    return a.to(device)


def _check_edges(i, j, N, device):
    i = _check_index(i, "i", None, N, device)
    j = _check_index(j, "j", i.shape[0], N, device)
    if bool((i == j).any()):
        raise ValueError(f"i, j: edge {int((i == j).nonzero()[0, 0])} joins a node to itself")
    return i, j


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------

def sequential_edges(sequence: torch.Tensor, k: int = 4) -> Tuple[torch.Tensor, torch.Tensor]:
    """VINS's sequential edges (§7.8.5): each window slot ``b`` to its previous ``k`` slots
    ``b − 1 .. b − k`` that belong to the same sequence.

    Convention:
        sequence: ``(N,)`` int64, the keyframes' sequence ids in window (list) order.
        Returns ``(i, j)``: ``(E,)`` int64 each, ``i = b − d`` (older node), ``j = b``, ordered
        by ``b`` then ``d = 1..k`` as VINS adds them.
    """
    check_shape(sequence, ("N",), "sequence")
    k = check_int(k, "k")
    N, dev = sequence.shape[0], sequence.device
    b = torch.arange(N, device=dev)[:, None].expand(N, k)
    a = b - torch.arange(1, k + 1, device=dev)[None, :]
    ok = (a >= 0) & (sequence[a.clamp_min(0)] == sequence[b])
    return a[ok], b[ok]


def measurements_4dof(t: torch.Tensor, R: torch.Tensor, i: torch.Tensor, j: torch.Tensor
                      ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sequential-edge measurements from the vio poses (§7.8.5).

    Convention:
        t: ``(N, 3)`` vio ``T_w_i`` (m); R: ``(N, 3, 3)`` vio ``R_w_i``; i, j: ``(E,)`` int64.
        Returns ``t_meas (E, 3) = R_iᵀ (t_j − t_i)`` and ``yaw_meas (E,) = yaw(R_j) − yaw(R_i)``
        in degrees (not wrapped, as VINS).
    """
    _check_float(t, "t", ("N", 3))
    N = t.shape[0]
    _check_float(R, "R", (N, 3, 3), t)
    i, j = _check_edges(i, j, N, t.device)
    t_meas = (R[i].mT @ (t[j] - t[i])[..., None])[..., 0]
    yaw = R_to_ypr(R)[:, 0]
    return t_meas, yaw[j] - yaw[i]


def measurements_6dof(t: torch.Tensor, q: torch.Tensor, i: torch.Tensor, j: torch.Tensor
                      ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sequential-edge measurements of loop_fusion's 6-DoF graph (§7.12).

    Convention:
        t: ``(N, 3)`` vio ``T_w_i`` (m); q: ``(N, 4)`` vio rotations w-first; i, j: ``(E,)`` int64.
        Returns ``t_meas (E, 3) = R_iᵀ (t_j − t_i)`` and ``q_meas (E, 4) = q_i⁻¹ ⊗ q_j`` (w-first,
        unit).
    """
    _check_float(t, "t", ("N", 3))
    N = t.shape[0]
    _check_float(q, "q", (N, 4), t)
    i, j = _check_edges(i, j, N, t.device)
    q = q / q.norm(dim=-1, keepdim=True)
    t_meas = (quat_to_R(q[i]).mT @ (t[j] - t[i])[..., None])[..., 0]
    return t_meas, _qmul(_qconj(q[i]), q[j])


def _opts(iters, solver, band, kw):
    iters = check_int(iters, "iters")
    band = check_solver_options(solver, band)
    bad = set(kw) - {"function_tolerance", "gradient_tolerance", "parameter_tolerance", "initial_radius",
                     "adaptive", "min_relative_decrease"}
    if bad:
        raise TypeError(f"unexpected keyword argument(s) {sorted(bad)}")
    return dict(iters=iters, solver=solver, band=band, **kw)


def optimize_4dof(t: torch.Tensor, yaw: torch.Tensor, pitch: torch.Tensor, roll: torch.Tensor,
                  i: torch.Tensor, j: torch.Tensor, t_meas: torch.Tensor, yaw_meas: torch.Tensor,
                  is_loop: torch.Tensor, fixed: torch.Tensor, iters: int = 5, return_info: bool = False,
                  *, solver: str = "auto", band: int = 4, **ceres_options):
    """VINS ``optimize4DoF`` (§7.8): optimise ``t`` and ``yaw`` of every free node.

    Residual of edge ``e`` (a = ``i[e]``, b = ``j[e]``, ``R_a = ypr2R(yaw_a, pitch_a, roll_a)``):
    ``r_t = R_aᵀ (t_b − t_a) − t_meas``, ``r_ψ = w · NormalizeAngle(yaw_b − yaw_a − yaw_meas)``
    with Ceres's single wrap, ``w = 1/10`` on loop edges (1 otherwise); loop edges carry
    HuberLoss(0.1) on the 4-vector, sequential edges no loss. Cost ``½ Σ ρ(|r|²)``.

    Convention:
        t: ``(N, 3)`` float, metres (initial values: the vio poses as VINS).
        yaw, pitch, roll: ``(N,)`` degrees; pitch and roll are constants.
        i, j: ``(E,)`` int64 node indices; t_meas ``(E, 3)`` m; yaw_meas ``(E,)`` degrees.
        is_loop: ``(E,)`` bool; fixed: ``(N,)`` bool (constant nodes).
        iters: Ceres ``max_num_iterations`` (VINS: 5). solver: ``"auto" | "dense" | "banded" |
        "lapack_banded" | "splu"``; band: node distance treated as banded (VINS: 4 neighbours).
        ceres_options: ``function_tolerance=1e-6``, ``gradient_tolerance=1e-10``,
        ``parameter_tolerance=1e-8``, ``initial_radius=1e4``, ``min_relative_decrease=1e-3``,
        ``adaptive=True`` (False keeps the damping at ``diag/initial_radius``: for comparisons).
        Returns ``(t (N, 3), yaw (N,))`` (yaw single-wrapped after each update; fixed nodes are
        returned unchanged), plus with ``return_info`` a dict: ``cost_initial``, ``cost_final``,
        ``iterations``, ``successful_steps``, ``converged``, ``termination``, ``solver``,
        ``cost_history``, ``gradient_max_norm``. Differentiable w.r.t. t_meas, yaw_meas, pitch,
        roll and the fixed nodes' t/yaw (implicit-function theorem, see the module docstring).

    Raises:
        ValueError: wrong shapes, index out of range, self edges, bad options.
        DataError: a NaN/inf in a pose or measurement (names the argument and row).
    """
    _check_float(t, "t", ("N", 3))
    N = t.shape[0]
    for name, a in (("yaw", yaw), ("pitch", pitch), ("roll", roll)):
        _check_float(a, name, (N,), t)
    i, j = _check_edges(i, j, N, t.device)
    E = i.shape[0]
    _check_float(t_meas, "t_meas", (E, 3), t)
    _check_float(yaw_meas, "yaw_meas", (E,), t)
    is_loop = _check_bool(is_loop, "is_loop", E, t.device)
    fixed = _check_bool(fixed, "fixed", N, t.device)
    opts = _opts(iters, solver, band, ceres_options)
    box: Dict = {}
    t_out, yaw_out = _Opt4.apply(t, yaw, pitch, roll, t_meas, yaw_meas, i, j, is_loop, fixed, opts, box)
    return (t_out, yaw_out, box) if return_info else (t_out, yaw_out)


def optimize_6dof(t: torch.Tensor, q: torch.Tensor, i: torch.Tensor, j: torch.Tensor, t_meas: torch.Tensor,
                  q_meas: torch.Tensor, is_loop: torch.Tensor, fixed: torch.Tensor, iters: int = 5,
                  return_info: bool = False, *, solver: str = "auto", band: int = 4, **ceres_options):
    """loop_fusion's ``optimize6DoF`` (§7.12, ``imu: 0``): optimise ``t`` and ``q`` of every free node.

    RelativeRTError of edge ``e`` (a = ``i[e]``, b = ``j[e]``):
    ``r_t = (R_aᵀ (t_b − t_a) − t_meas) / 0.1``, ``r_q = 2 vec(q_meas⁻¹ ⊗ q_a⁻¹ ⊗ q_b) / 0.01``;
    loop edges carry HuberLoss(0.1) on the 6-vector. Quaternion update as Ceres's
    QuaternionParameterization (``q ← (cos|δ|, sin|δ| δ/|δ|) ⊗ q``), renormalised.

    Convention:
        t: ``(N, 3)`` float, metres; q: ``(N, 4)`` w-first (normalised on input).
        i, j: ``(E,)`` int64; t_meas ``(E, 3)`` m; q_meas ``(E, 4)`` w-first unit.
        is_loop: ``(E,)`` bool; fixed: ``(N,)`` bool. iters, solver, band, ceres_options and the
        info dict as :func:`optimize_4dof`.
        Returns ``(t (N, 3), q (N, 4))`` unit quaternions. Differentiable w.r.t. t_meas, q_meas and
        the fixed nodes' t/q (implicit-function theorem).

    Raises:
        ValueError: wrong shapes, index out of range, self edges, bad options.
        DataError: a NaN/inf or zero quaternion in a pose or measurement.
    """
    _check_float(t, "t", ("N", 3))
    N = t.shape[0]
    _check_float(q, "q", (N, 4), t)
    i, j = _check_edges(i, j, N, t.device)
    E = i.shape[0]
    _check_float(t_meas, "t_meas", (E, 3), t)
    _check_float(q_meas, "q_meas", (E, 4), t)
    for name, a in (("q", q), ("q_meas", q_meas)):
        zero = a.detach().norm(dim=-1) < 1e-12
        if bool(zero.any()):
            raise DataError(f"{name}: zero quaternion at row {int(zero.nonzero()[0, 0])}")
    is_loop = _check_bool(is_loop, "is_loop", E, t.device)
    fixed = _check_bool(fixed, "fixed", N, t.device)
    opts = _opts(iters, solver, band, ceres_options)
    box: Dict = {}
    qn = q / q.norm(dim=-1, keepdim=True)
    qmn = q_meas / q_meas.norm(dim=-1, keepdim=True)
    t_out, q_out = _Opt6.apply(t, qn, t_meas, qmn, i, j, is_loop, fixed, opts, box)
    return (t_out, q_out, box) if return_info else (t_out, q_out)
