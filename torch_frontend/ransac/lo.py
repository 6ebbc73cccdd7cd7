"""LO-RANSAC (``method="lo"``): OpenCV's hypotheses and inlier test, each model OpenCV's loop
accepts locally optimised (weighted 8-point refits), the adaptive bound from the optimised
counts, a final refit; on the default path (:func:`_find_fundamental_lo`) and the capturable one
(:func:`_find_fundamental_lo_capturable`, a fixed budget of optimised models).

It keeps ~97 % of the true inliers where OpenCV keeps ~87 % and its F is ~4x closer to the truth
(``benchmarks/results/fundamental_accuracy.md``). Its refits avoid the linalg ops that check
errors on the host (inverse iteration with ``lu_factor_ex``/``lu_solve``, ``refit.py``) and the
batched matmuls whose last bits depend on the batch, so a problem's result is the same in any
batch, and the capturable variant is sync-free as well.

Convention: as ``_find_fundamental_impl``; models inside are pixel models ``(B, 9)`` row-major
(any scale) unless stated. LMedS problems (8..14 points) get the OpenCV method's result.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
import torch

from .. import _tuning
from .._cache import cached
from .bounds import _niters_table_on
from .capturable import _counts_capturable, _fit_capturable, _front_capturable, _lmeds_capturable
from .consts import _Consts, _consts
from .eager import _find_fundamental_eager
from .refit import _normal_matrix, _rank2, _refit_fixed_epipole, _refit_impl, _smallest_eigvec
from .result import (
    _MIN_POINTS,
    _MIN_RANSAC_POINTS,
    _MODEL_POINTS,
    FundamentalFit,
    _canonical_sign,
    _opencv_points,
    _Points,
    _unsolved,
)
from .samples import _subset_stream
from .scoring import _outer_products, _score_rows, _score_terms
from .seven_point import _run_7point

#: weighted 8-point refits per local optimisation: the first on the hypothesis' inliers with unit
#: weights, then Sampson weights of the previous refit on its inliers; the last one is made rank
#: 2 and replaces the hypothesis if it has at least as many inliers (measured on the planted
#: scenes: keeping the best of every refit instead, or rank 2 in every refit, gives the same recall
#: and F error to 0.1 %)
_LO_STEPS = 3
#: capturable path: accepted models locally optimised per problem in OpenCV's order (a fixed
#: budget), then one more: the remaining acceptable model with the most inliers (so that a problem
#: that overflows still ends with its best hypothesis optimised; ``overflow`` is then True)
_LO_EVENTS = 4
#: inverse iteration: solves with the shifted normal matrix per eigenvector in a local
#: optimisation step (warm-started at the previous step; measured: 2..8 give the same recall and F
#: error); the final refit uses refit._EIG_POWER_FINAL
_EIG_POWER_LO = 3
#: Sampson weights: the denominator is floored at this fraction of its mean over the inliers
_SAMPSON_FLOOR = 0.1
_LO_INDICES = 64  # cached index blocks (start, count): the rounds of a call and the capturable block


@cached(_LO_INDICES)
def _lo_index(start: int, count: int, device: torch.device):
    """Models ``3 start .. 3 (start + count) - 1`` of a block: their global index and sample index,
    ``(3 count,)`` int64 each (cached: the capturable path's block is one constant)."""
    m = torch.arange(3 * start, 3 * (start + count), dtype=torch.int64, device=device)
    return m, torch.div(m, 3, rounding_mode="floor")


class _LOContext(NamedTuple):
    """Per-call data of the local optimisation (:func:`_lo_context`)."""

    An: torch.Tensor  # (B, N, 9) epipolar rows in Hartley-normalised coordinates (all valid points)
    Kn2p: torch.Tensor  # (B, 9, 9): vec(F) = Kn2p vec(Fn) (normalised -> pixel models, row-major)
    Kp2n: torch.Tensor  # (B, 9, 9): its inverse
    outer: torch.Tensor  # (B, N, 9): pixel h2 (x) h1 (scoring), 0 at masked-out slots
    thr2: float
    bounds: torch.Tensor  # (N + 1, N + 2) int64: the iteration bound [n, best count + 1]
    bound_row: torch.Tensor  # (B,) int64: n (N + 2) + 1 (+ best count = the index into bounds)
    k: _Consts


def _lo_context(x12, eff, n, outer, thr2, bounds, k) -> _LOContext:
    """The local optimisation's fixed normalisation: per problem and image the centroid and RMS
    distance sqrt(2) of all valid points (``refit_fundamental``'s rule with unit weights; it only
    conditions the normal matrix, the reweighted solution hardly depends on it), the normalised
    epipolar rows and the maps between normalised and pixel models."""
    B, N = eff.shape
    w = eff.to(torch.float64)[..., None, None]  # (B, N, 1, 1)
    W = n.clamp_min(1).to(torch.float64)[:, None, None]  # (B, 1, 1)
    x = x12.view(B, N, 2, 2)
    c = (x * w).sum(1) / W  # (B, image, 2)
    d = (x - c[:, None]) * w
    r2 = (d * d).sum((1, 3)) / W[..., 0]  # (B, image): mean squared distance
    s = torch.sqrt(2.0 / torch.where(r2 > 0, r2, torch.ones_like(r2)))
    h = torch.nn.functional.pad(d * s[:, None, :, None], (0, 1), value=1.0)  # (B, N, image, 3)
    An = (h[:, :, 1, :, None] * h[:, :, 0, None, :]).flatten(-2)  # _epipolar_rows' order
    # T^T = [[s, 0, 0], [0, s, 0], [-s cx, -s cy, 1]]; T^-T = [[1/s, 0, 0], [0, 1/s, 0], [cx, cy, 1]]
    top = s[..., None, None] * k.eye23  # (B, image, 2, 3)
    Tt = torch.cat([top, torch.nn.functional.pad(c * -s[..., None], (0, 1), value=1.0)[:, :, None]], 2)
    Ti = torch.cat([top / (s * s)[..., None, None], torch.nn.functional.pad(c, (0, 1), value=1.0)[:, :, None]], 2)
    Kn2p = (Tt[:, 1, :, None, :, None] * Tt[:, 0, None, :, None, :]).reshape(B, 9, 9)
    Kp2n = (Ti[:, 1, :, None, :, None] * Ti[:, 0, None, :, None, :]).reshape(B, 9, 9)
    return _LOContext(An, Kn2p, Kp2n, outer, thr2, bounds, n * (N + 2) + 1, k)


def _lo_score(Fp: torch.Tensor, ctx: _LOContext, weights: bool = True):
    """OpenCV's inlier test of pixel models ``Fp (B, 9)`` (any scale) on every point: the mask
    ``(B, N)``, the counts ``(B,)`` int32 and (``weights``, else None) the Sampson weights ``(B,
    N)`` (:func:`_sampson_weights`). The terms of :func:`_score_terms` as elementwise products and
    sums (a batched matmul's last bits depend on the batch and on memory alignment)."""
    B = Fp.shape[0]
    rows = (Fp[:, :, None] * ctx.k.select).sum(1).view(B, 5, 1, 9)  # _score_rows
    o = (rows * ctx.outer[:, None]).sum(-1)  # (B, 5, N)
    o = o * o
    s2 = o[:, 1] + o[:, 2]
    s1 = o[:, 3] + o[:, 4]
    smin = torch.minimum(s1, s2)
    bound = smin if ctx.thr2 == 1.0 else smin * ctx.thr2
    inl = (o[:, 0] <= bound) & (smin > 0)
    cnt = inl.sum(-1, dtype=torch.int32)
    return inl, cnt, _sampson_weights(s1 + s2, inl, cnt, ctx.k) if weights else None


def _sampson_weights(den: torch.Tensor, inl: torch.Tensor, cnt: torch.Tensor, k: _Consts) -> torch.Tensor:
    """IRLS weights ``(B, N)`` that turn the algebraic error into the Sampson error: ``1 / den`` at
    inliers (``den = |F x1|_xy^2 + |F^T x2|_xy^2``), 0 elsewhere, with den floored at
    ``_SAMPSON_FLOOR`` times its mean over the inliers: a point near the epipole has a tiny den,
    and unbounded, its weight decides the fit alone (measured on EuRoC frames with sub-pixel
    motion: one weight 2000x the median turned a 150-inlier model into a 100-inlier one)."""
    mean = torch.where(inl, den, k.zero).sum(-1) / cnt.clamp_min(1)
    return torch.where(inl, torch.maximum(den, (_SAMPSON_FLOOR * mean)[:, None]).reciprocal(), k.zero)


def _lo_refine(F0: torch.Tensor, inl0: torch.Tensor, cnt0: torch.Tensor, ctx: _LOContext):
    """Local optimisation of pixel models ``F0 (B, 9)`` with inliers ``inl0`` and counts ``cnt0``:
    ``_LO_STEPS`` iteratively reweighted 8-point refits (the first on the inliers with unit
    weights, then :func:`_sampson_weights` of the previous refit on its inliers: the weighted
    algebraic error is then the Sampson error), each re-scored with OpenCV's test for the next
    one's inliers; the last one, made rank 2, is returned with its mask and count if it has at
    least as many inliers as ``F0``, else ``F0`` (rounded to float32, see below) and its own."""
    # The hypothesis rounded to float32: a 7-point model's last bits depend on the batch it was
    # solved in (batched CPU matmuls), the rounded one does not, and as a starting point (and
    # a model to score) it is as good
    F0 = F0.to(torch.float32).to(torch.float64)
    f = (ctx.Kp2n @ F0[..., None])[..., 0]  # warm start, normalised coordinates
    bF, bI, bC = F0, inl0, cnt0
    w = inl0.to(torch.float64)
    B = F0.shape[0]
    for j in range(_LO_STEPS):
        M = _normal_matrix(ctx.An, w)
        f = _smallest_eigvec(M, f, ctx.k, _EIG_POWER_LO)
        if j == _LO_STEPS - 1:
            f = _rank2(f.view(B, 3, 3), ctx.k).view(B, 9)
        Fp = (ctx.Kn2p @ f[..., None])[..., 0]
        inl, cnt, w = _lo_score(Fp, ctx, j < _LO_STEPS - 1)
        if j == _LO_STEPS - 1:
            take = cnt >= bC
            bF = torch.where(take[:, None], Fp, bF)
            bI = torch.where(take[:, None], inl, bI)
            bC = torch.where(take, cnt, bC)
    return bF, bI, bC


class _LOState(NamedTuple):
    """The replayed loop's state per problem: the acceptance bar (best count, at least 6: OpenCV
    accepts a model with more than ``max(best, modelPoints - 1)`` inliers), the iteration bound, the
    global index of the last accepted model (-1: none), the best model, its mask and count."""

    bar: torch.Tensor  # (B,) int32
    bound: torch.Tensor  # (B,) int64
    last: torch.Tensor  # (B,) int64
    F: torch.Tensor  # (B, 9) float64, pixel model (any scale)
    inl: torch.Tensor  # (B, N) bool
    cnt: torch.Tensor  # (B,) int32, -1: no model


def _lo_init(B: int, N: int, max_iters: int, device) -> _LOState:
    i64 = dict(dtype=torch.int64, device=device)
    return _LOState(torch.full((B,), _MODEL_POINTS - 1, dtype=torch.int32, device=device),
                    torch.full((B,), max(int(max_iters), 1), **i64), torch.full((B,), -1, **i64),
                    torch.zeros(B, 9, dtype=torch.float64, device=device),
                    torch.zeros(B, N, dtype=torch.bool, device=device),
                    torch.full((B,), -1, dtype=torch.int32, device=device))


def _lo_last_sample(st: _LOState) -> torch.Tensor:
    """The last sample OpenCV's loop draws given the state: ``for (iter = 0; iter < niters; iter++)``
    with ``niters`` the bound set while sample ``last // 3`` was scored: ``max(last // 3, bound - 1)``."""
    return torch.maximum(torch.div(st.last, 3, rounding_mode="floor"), st.bound - 1)


def _lo_eligible(st: _LOState, cnt: torch.Tensor, index) -> torch.Tensor:
    """``(B, 3 K)`` bool: the block's models that OpenCV's loop would accept next (after the last
    accepted one, drawn before the loop stops, with more inliers than the bar)."""
    midx, msmp = index
    return (midx > st.last[:, None]) & (msmp <= _lo_last_sample(st)[:, None]) & (cnt > st.bar[:, None])


def _lo_event(st: _LOState, Fm, mask, cnt, index, ctx: _LOContext, most: bool = False):
    """One new best model per problem (where there is one in the block): the first eligible model
    (``most``: the eligible one with the most inliers, the first of equals), locally optimised; the
    bar and the bound then follow the optimised count (OpenCV's ``RANSACUpdateNumIters`` with the
    LO inlier ratio). Returns the new state and ``(B,)`` bool (a model was accepted)."""
    N = mask.shape[-1]
    elig = _lo_eligible(st, cnt, index)
    if most:
        has, j = torch.where(elig, cnt, ctx.k.minus_one).max(1)
        has = has >= 0
    else:
        has, j = elig.to(torch.int8).max(1)
        has = has > 0
    F0 = Fm.gather(1, j[:, None, None].expand(-1, 1, 9))[:, 0]
    I0 = mask.gather(1, j[:, None, None].expand(-1, 1, N))[:, 0]
    C0 = cnt.gather(1, j[:, None])[:, 0]
    F1, I1, C1 = _lo_refine(F0, I0, C0, ctx)
    bound = ctx.bounds.take(ctx.bound_row + C1)
    return _LOState(torch.where(has, C1, st.bar), torch.where(has, bound, st.bound),
                    torch.where(has, index[0].gather(0, j), st.last), torch.where(has[:, None], F1, st.F),
                    torch.where(has[:, None], I1, st.inl), torch.where(has, C1, st.cnt)), has


def _sampson_den(x1: torch.Tensor, x2: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """``|F x1|_xy^2 + |F^T x2|_xy^2`` ``(B, N)`` of pixel points ``(B, N, 2)`` and models ``(B, 3, 3)``,
    elementwise (see :func:`_lo_score`)."""
    l2 = (torch.nn.functional.pad(x1, (0, 1), value=1.0)[:, :, None, :] * F[:, None]).sum(-1)  # F x1
    l1 = (torch.nn.functional.pad(x2, (0, 1), value=1.0)[:, :, :, None] * F[:, None]).sum(-2)  # F^T x2
    return (l2[..., :2] * l2[..., :2]).sum(-1) + (l1[..., :2] * l1[..., :2]).sum(-1)


def _lo_final(p1, p2, eff, st: _LOState, ctx: _LOContext):
    """The final refit on the final inliers and its inliers: ``F (B, 3, 3)`` float64 unit norm,
    largest entry positive, and OpenCV's test of it ``(B, N)``. On the points as given (float64),
    weighted by the inlier mask over Sampson denominators (:func:`_sampson_weights`): an 8-point
    refit (:func:`_refit_impl`: ``refit_fundamental``'s normalisation and rank-2 rule, with the
    host-sync-free eigensolvers, warm-started at the best model; its weights from the best model),
    then :func:`_refit_fixed_epipole` (weights from that refit), then OpenCV's test.
    Differentiable w.r.t. ``p1, p2`` (the mask and the best model are constants). Where the refit
    is not finite (fewer than 8 inliers) or has fewer inliers than the best model (a degenerate
    configuration), the best model and its mask are kept (no gradient there)."""
    f64 = torch.float64
    x1 = torch.where(eff[..., None], p1.to(f64), 0.0)  # no NaN in any product (clean gradients)
    x2 = torch.where(eff[..., None], p2.to(f64), 0.0)
    F0 = st.F.view(-1, 3, 3)
    k = ctx.k
    F = _refit_impl(x1, x2, _sampson_weights(_sampson_den(x1, x2, F0), st.inl, st.cnt, k), warm=F0, k=k)
    F = _refit_fixed_epipole(x1, x2, _sampson_weights(_sampson_den(x1, x2, F), st.inl, st.cnt, k), F, k)
    inl, cnt, _ = _lo_score(F.detach().reshape(-1, 9), ctx, False)
    good = torch.isfinite(F).flatten(1).all(-1) & (cnt >= st.cnt)
    F = torch.where(good[:, None, None], F, _canonical_sign(F0))
    return F, torch.where(good[:, None], inl, st.inl)


def _find_fundamental_lo_capturable(p1, p2, valid, threshold: float, confidence: float, max_iters: int,
                                    states: Sequence[int], block) -> FundamentalFit:
    """``method="lo"``, ``capturable=True``: ``capturable._find_fundamental_capturable``'s samples,
    models and inlier counts (one block of ``K`` samples), then OpenCV's loop replayed with local
    optimisation: ``_LO_EVENTS`` times the next accepted model (the first one after the last
    accepted that has more inliers than the current LO count, drawn before the bound stops the
    loop) is locally optimised and sets the bar and the bound; then the final refit. A fixed
    number of kernels; ``overflow`` where the block ended before OpenCV's loop would have (as the
    OpenCV path) or a further model would have been accepted after the budget. LMedS problems
    (8..14 points) get the OpenCV path's result."""
    sp = _front_capturable(p1, p2, valid, confidence, max_iters, states, block)
    if isinstance(sp, FundamentalFit):  # N < 8
        return sp
    F, inl, ok, iters, overflow = _lmeds_capturable(sp)
    if sp.has_r:
        B, N, K, is_r = sp.B, sp.N, sp.K, sp.is_r
        thr2 = threshold * threshold
        mask, cnt = _counts_capturable(sp, thr2)
        ctx = _lo_context(sp.x12, sp.eff, sp.n, sp.outer, thr2, sp.tabs.niters, sp.k)
        index = _lo_index(0, K, p1.device)
        st = _lo_init(B, N, max_iters, p1.device)
        for _ in range(_LO_EVENTS):
            st, _ = _lo_event(st, sp.Fm, mask, cnt, index, ctx)
        st, more = _lo_event(st, sp.Fm, mask, cnt, index, ctx, most=True)  # past the budget
        last = _lo_last_sample(st)
        Ff, inl_f = _lo_final(p1, p2, sp.eff, st, ctx)
        F = torch.where(is_r[:, None], Ff.view(B, 9), F)
        inl = torch.where(is_r[:, None], inl_f, inl)
        ok = torch.where(is_r, st.cnt > _MODEL_POINTS - 1, ok)
        iters = torch.where(is_r, torch.clamp_max(last + 1, K), iters)
        over_r = is_r & ((last >= K) | more)
        overflow = over_r if overflow is None else overflow | over_r
    return _fit_capturable(sp, F, inl, ok, iters, overflow, p1.dtype)


def _find_fundamental_lo(p1, p2, valid, threshold: float, confidence: float, max_iters: int,
                         states: Sequence[int], batch_hypotheses) -> FundamentalFit:
    """``method="lo"``, ``capturable=False``: the capturable path's algorithm (the same models, loop,
    local optimisation and final refit, so the same result where that path does not overflow),
    with the default path's early exits: rounds of 32, 64, ... samples for the problems still
    running (one host sync per round and one per accepted model), as many accepted models as
    OpenCV's loop finds (never ``overflow``). LMedS problems (8..14 points) get the OpenCV path's
    result (``eager._find_fundamental_eager``)."""
    B, N = valid.shape
    dev, out_dtype = p1.device, p1.dtype
    pts = _opencv_points(p1, p2, valid)
    n_host = pts.n.tolist()  # host sync: sample tables are per (seed, n)
    F, inliers, ok, iters, method, _ = _unsolved(pts, out_dtype)
    lmeds = [b for b in range(B) if _MIN_POINTS <= n_host[b] < _MIN_RANSAC_POINTS]
    if lmeds:
        rows = torch.tensor(lmeds, dtype=torch.int64, device=dev)
        r = _find_fundamental_eager(p1[rows], p2[rows], valid[rows], threshold, confidence, max_iters,
                                    [states[b] for b in lmeds], batch_hypotheses, _Points(*(t[rows] for t in pts)))
        F = F.index_copy(0, rows, r.F)
        inliers[rows] = r.inliers
        ok[rows] = r.ok
        iters[rows] = r.num_iters
    sel = [b for b in range(B) if n_host[b] >= _MIN_RANSAC_POINTS]
    if not sel:
        return FundamentalFit(F, inliers, ok, iters, method, None)
    R = len(sel)
    rows = slice(None) if R == B else torch.tensor(sel, dtype=torch.int64, device=dev)
    x12, eff_r, n_r = pts.x12[rows], pts.eff[rows], pts.n[rows]
    k = _consts(dev)
    thr2 = threshold * threshold
    Mx = max(int(max_iters), 1)
    ctx = _lo_context(x12, eff_r, n_r, _outer_products(x12, eff_r), thr2, _niters_table_on(N, Mx, confidence, dev), k)
    order = torch.sort(eff_r, dim=-1, descending=True, stable=True).indices
    streams = [_subset_stream(states[b], n_host[b]) for b in sel]
    st = _lo_init(R, N, Mx, dev)
    strategy = _tuning.for_device(dev)
    act, s0, rnd = list(range(R)), 0, 0
    last_h = [Mx - 1] * R
    while act:
        A = len(act)
        Hr = min(strategy.ransac_first_round << rnd, max(last_h[i] for i in act) + 1 - s0,
                 batch_hypotheses if batch_hypotheses is not None
                 else max(16, strategy.ransac_round_elems // max(A * N, 1)))
        rnd += 1
        idx = np.zeros((A, Hr, _MODEL_POINTS), dtype=np.int64)
        for j, i in enumerate(act):
            idx[j] = streams[i].upto(s0 + Hr)[s0 : s0 + Hr]
        full = A == R
        a = slice(None) if full else torch.tensor(act, dtype=torch.int64, device=dev)
        sub = st if full else _LOState(*(t[a] for t in st))
        cx = ctx if full else ctx._replace(An=ctx.An[a], Kn2p=ctx.Kn2p[a], Kp2n=ctx.Kp2n[a], outer=ctx.outer[a],
                                           bound_row=ctx.bound_row[a])
        slot = order[a].gather(1, torch.from_numpy(idx).to(dev).view(A, Hr * _MODEL_POINTS))
        smp = x12[a].gather(1, slot[..., None].expand(-1, -1, 4)).view(A * Hr, _MODEL_POINTS, 2, 2)
        Fm, fok = _run_7point(smp, k)
        Fm = Fm.view(A, Hr * 3, 9)
        d2, smin = _score_terms(_score_rows(Fm, k), cx.outer)
        bound = smin if thr2 == 1.0 else smin * thr2
        mask = (d2 <= bound) & (smin > 0)  # (A, 3 Hr, N): capturable._counts_capturable's test
        cnt = torch.where(fok.view(A, Hr * 3), mask.sum(-1, dtype=torch.int32), k.minus_one)
        index = _lo_index(s0, Hr, dev)
        while bool(_lo_eligible(sub, cnt, index).any()):  # host sync per accepted model
            sub, _ = _lo_event(sub, Fm, mask, cnt, index, cx)
        if full:
            st = sub
        else:
            st = _LOState(*(t.index_copy(0, a, u) for t, u in zip(st, sub)))
        s0 += Hr
        last_a = _lo_last_sample(sub).tolist()  # host sync per round
        for j, i in enumerate(act):
            last_h[i] = last_a[j]
        act = [i for i in act if last_h[i] >= s0]
    okr = st.cnt > _MODEL_POINTS - 1
    Ff, inl_f = _lo_final(p1[rows], p2[rows], eff_r, st, ctx)
    Ff = torch.where(okr[:, None, None], Ff, math.nan).to(out_dtype)
    inl_r = torch.where(okr[:, None], inl_f, eff_r)
    it_r = _lo_last_sample(st) + 1
    if R == B:
        return FundamentalFit(Ff, inl_r, okr, it_r, method, None)
    return FundamentalFit(F.index_copy(0, rows, Ff), inliers.index_copy(0, rows, inl_r), ok.index_copy(0, rows, okr),
                          iters.index_copy(0, rows, it_r), method, None)
