"""Implicit-function gradients of the LK (``grad_mode="implicit"``; ``docs/lk.md``).

At the converged level-0 solution ``y*`` the LK equations ``F(y*, theta) = 0`` hold (``theta``: the
points and both level-0 images), so ``dy*/dtheta = -A^-1 dF/dtheta`` with ``A = dF/dy`` the true
Jacobian (bilinear derivative of the next image, not the Gauss-Newton matrix): two differentiable
Newton steps at the detached solution give the exact first and second derivatives of the converged
solution, with memory independent of the iteration count (:func:`_implicit_attach`). The coarse
levels and ``init_pts`` only pick the basin: no gradient; lost, capped and ill-posed lanes get an
exactly zero gradient.

Convention:
    As :mod:`.windows`: points-last ``(2, m)`` lanes, window origins ``u = origin + win``.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from .._autodiff import has_tangent
from .._cache import cached
from ..pyramid import Pyramid
from .options import LKOptions
from .windows import _lane_index, _Level, _level_start, _template, _win_consts

# a lane gets a gradient only where the level-0 system at the solution is well posed:
# det(A) >= _IMPLICIT_MIN_DET_RATIO det(G) (A the true Jacobian of the normal equations' residual,
# G the Gauss-Newton matrix: equal under brightness constancy) and the Newton step at the solution
# is at most _IMPLICIT_MAX_STEP pixels (the solution is a root of the float equations)
_IMPLICIT_MIN_DET_RATIO = 0.05
_IMPLICIT_MAX_STEP = 0.1
_IMPLICIT_REFINE = 2  # Newton refinements of the linearisation point (no graph)


def _levels_have_tangent(*pyramids: Pyramid) -> bool:
    """Some level of these pyramids has a forward-mode tangent (forward-AD dual tensors,
    ``torch.func.jvp``): ``torch.no_grad`` does not stop forward-mode AD, so a pass that must not
    carry one runs on :func:`_detached` levels."""
    return any(has_tangent(t) for p in pyramids for t in p.levels)


def _wants_grad(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, init: Optional[torch.Tensor]) -> bool:
    """Some derivative of the level-0 solution may be recorded: the points, the initial guess or a
    level-0 image has a forward-mode tangent, or one requires a gradient while gradients are
    recorded (dual tensors do not set ``requires_grad``, and ``no_grad`` does not stop them)."""
    ts = (pts, prev.levels[0], nxt.levels[0], init)
    if any(t is not None and has_tangent(t) for t in ts):
        return True
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in ts)


def _detached(p: Pyramid) -> Pyramid:
    """``p`` with detached levels (and cached padded levels): no gradient, no tangent."""
    out = Pyramid([t.detach() for t in p.levels], None, p.rounded)
    out._padded = {k: v.detach() for k, v in p._padded.items()}
    return out


@cached(32)
def _patch_offsets(Wp: int, ww: int, wh: int, device) -> torch.Tensor:
    """Flat offsets ``(wh + 1, ww + 2)`` of the bilinear patch of a window whose origin ``u`` is
    addressed as in :class:`_Level` (padded rows/columns start at ``u + 1``)."""
    dy, dx = torch.arange(wh + 1, device=device), torch.arange(ww + 2, device=device)
    return dy[:, None] * Wp + dx[None, :] + (Wp + 1)


def _newton_terms(lv: _Level, q: torch.Tensor, lane: torch.Tensor, iv: torch.Tensor, g: torch.Tensor, k: dict):
    """The level's LK residual and its Jacobian at window origins ``q`` ``(2, m)`` (float bilinear,
    differentiable w.r.t. ``q``, the next level and, through ``iv``/``g``, the previous one):
    ``F = sum_x g(x) (32 J(q + x) - iv(x))`` ``(2, m)`` (the normal equations' right-hand side,
    ``G delta = -F``) and ``A = dF/dq`` ``(2, 2, m)`` (``A[i, j] = sum_x g_i dJ/dq_j``; ``A = G``
    under brightness constancy), plus the lanes whose window is inside ``[-win, size)``. Layout as
    the iterations' (pitched, ``g`` zero on the junk column)."""
    ww, wh = lv.ww, lv.wh
    ip = torch.floor(q.detach())
    u = ip + k["win"]
    uc = torch.clamp(u, min=k["zero"], max=lv.spanm1)
    inside = (uc == u).all(0)
    base = (uc.long() * lv.jstr).sum(0) + lane
    idx = base.view(-1, 1, 1) + _patch_offsets(lv.Wp, ww, wh, lv.Jp.device)
    P = lv.Jp.index_select(0, idx.view(-1)).view(idx.shape).to(q.dtype)  # (m, wh + 1, ww + 2)
    m = P.shape[0]

    def flat(t):
        return t.reshape(m, -1)

    j00, j01 = flat(P[:, :wh, :ww + 1]), flat(P[:, :wh, 1:])
    j10, j11 = flat(P[:, 1:, :ww + 1]), flat(P[:, 1:, 1:])
    a, b = (q - ip).unsqueeze(-1).unbind(0)  # (m, 1) each
    val = (1 - b) * ((1 - a) * j00 + a * j01) + b * ((1 - a) * j10 + a * j11)
    da = (1 - b) * (j01 - j00) + b * (j11 - j10)
    db = (1 - a) * (j10 - j00) + a * (j11 - j01)
    F = (g * (32.0 * val - iv).unsqueeze(1)).sum(-1).t()  # (2, m)
    A = (g.unsqueeze(2) * (32.0 * torch.stack((da, db), 1)).unsqueeze(1)).sum(-1)  # (m, 2, 2)
    return F, A.permute(1, 2, 0), inside


def _solve2(A: torch.Tensor, F: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """``A^-1 F`` for ``(2, 2, m)`` / ``(2, m)`` in closed form, 0 where not ``ok`` (the masked lanes'
    inputs are replaced first, so that neither the value nor the gradient can be NaN there)."""
    eye = torch.eye(2, dtype=A.dtype, device=A.device).unsqueeze(-1)
    A = torch.where(ok, A, eye)
    F = torch.where(ok, F, 0.0)
    det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    det = torch.where(ok, det, 1.0)
    x0 = A[1, 1] * F[0] - A[0, 1] * F[1]
    x1 = A[0, 0] * F[1] - A[1, 0] * F[0]
    return torch.stack((x0, x1)) / det


def _implicit_attach(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, out: torch.Tensor, mask: torch.Tensor,
                     opts: LKOptions) -> Tuple[torch.Tensor, torch.Tensor]:
    """Attach the implicit-function gradient to a forward LK result (values unchanged).

    At the converged level-0 solution ``y*`` the LK equations ``F(y*, theta) = 0`` hold (``F`` =
    :func:`_newton_terms`' residual, ``theta`` = the points and both level-0 images), so
    ``dy*/dtheta = -A^-1 dF/dtheta`` with ``A = dF/dy``: one 2x2 solve per point. It is realised as two
    differentiable Newton steps from the detached solution, ``y1 = N(y*)``, ``y2 = N(y1)`` with
    ``N(y) = y - A(y)^-1 F(y)``; the result is ``y* + (y2 - y2.detach())`` (value ``y*`` exactly).
    One step gives the exact first derivative (``dN/dy = 0`` at a root of ``F``), the second the exact
    second derivative (so that ``gradgradcheck`` holds), with the forward's residual (``|F|`` after
    ``eps``-stopping and fixed-point rounding) as the only error.

    Levels: only level 0 is differentiated. The root of level 0's equations does not depend on
    where the iteration started, so the coarse levels and ``init_pts`` (which only pick the basin)
    get no gradient. ``A`` is the true Jacobian (bilinear derivative of the next image), not the
    Gauss-Newton ``G``, so the gradient is that of the converged solution.

    Args:
        prev, nxt: the pyramids (level 0 carries the image gradients).
        pts: ``(B, N, 2)`` points in ``prev``; ``out``: ``(B, N, 2)`` the forward's result (detached).
        mask: ``(B, N)`` bool, lanes to differentiate (status True, not capped at level 0).

    Returns:
        ``next_pts (B, N, 2)`` with the gradient attached, and the ``(B, N)`` lanes that received one
        (``mask`` and well posed: window inside, ``det A >= 0.05 det G``, Newton step at the solution
        <= 0.1 px); the others get an exactly zero gradient.
    """
    B, N, _ = pts.shape
    M = B * N
    dtype, dev = pts.dtype, pts.device
    ww, wh = opts.win_size
    k = _win_consts(ww, wh, dtype, dev)
    half = k["half"]
    H, W = nxt.levels[0].shape[-2:]
    lv = _Level(prev.padded(0, wh + 1, ww + 1, dtype), nxt.padded(0, wh + 1, ww + 1, dtype), H, W, (ww, wh), dtype)
    mask = mask.reshape(M)
    p0 = torch.where(mask, pts.reshape(M, 2).t(), 0.0)  # masked lanes: finite, zero gradient
    lanes = _lane_index(B, N, dev)
    uc, frac, proc = _level_start(lv, p0, mask, 0, k)
    ucl = torch.where(proc, uc, k["zero"]).long()
    iv, g = _template(lv, ucl, frac, lanes, False, dtype, k, sync=False)
    lane = lanes * lv.HWp
    ystar = out.detach().reshape(M, 2).t()
    if not ystar.is_floating_point() or ystar.dtype != dtype:
        ystar = ystar.to(dtype)
    q0 = torch.where(proc, ystar - half, 0.0)
    with torch.no_grad():
        # linearise at the root of the float equations: the forward stopped at |delta| <= eps (and
        # solved the fixed-point equations in 8-bit mode); two Newton steps (true Jacobian) refine
        # the point at which the derivatives are taken, not the returned value
        gd = g.detach()
        Gd = (gd.unsqueeze(2) * gd.unsqueeze(1)).sum(-1)  # (m, 2, 2)
        detG = Gd[:, 0, 0] * Gd[:, 1, 1] - Gd[:, 0, 1] * Gd[:, 1, 0]
        ok = proc & (detG > 0)
        qr = q0
        for it in range(_IMPLICIT_REFINE + 1):
            Fd, Ad, inside = _newton_terms(lv, qr, lane, iv.detach(), gd, k)
            detA = Ad[0, 0] * Ad[1, 1] - Ad[0, 1] * Ad[1, 0]
            ok = ok & inside & (detA >= _IMPLICIT_MIN_DET_RATIO * detG)
            step = _solve2(Ad, Fd, ok)
            if it == 0:
                ok = ok & (step.abs() <= _IMPLICIT_MAX_STEP).all(0)
            if it < _IMPLICIT_REFINE:
                qr = qr - torch.where(ok, step, 0.0)
        ok = ok & ((qr - q0).abs() <= _IMPLICIT_MAX_STEP).all(0)
        q0 = torch.where(ok, qr, q0)
    F0, A0, _ = _newton_terms(lv, q0, lane, iv, g, k)
    c1 = _solve2(A0, F0, ok)
    q1 = q0 + (c1.detach() - c1)  # value q0, derivative of N(q0) = q0 - A^-1 F
    F1, A1, _ = _newton_terms(lv, q1, lane, iv, g, k)
    c2 = _solve2(A1, F1, ok)
    corr = q1 - c2
    corr = corr - corr.detach()  # exactly 0 (finite), the derivative of N(N(q0))
    res = ystar + torch.where(ok, corr, 0.0)
    return res.t().reshape(B, N, 2), ok.view(B, N)
