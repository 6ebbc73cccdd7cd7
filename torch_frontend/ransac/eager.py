"""The default (eager) path of the OpenCV method: ``findFundamentalMat(FM_RANSAC)``'s sequential
RANSAC loop, and its LMedS fallback for 8..14 points, replayed exactly on B problems at once.

Every round takes a block of minimal samples per problem (32, 64, 128, ..., never more than the
current iteration bound allows), solves them with the batched 7-point solver, scores every model on
every point in parallel and then replays OpenCV's sequential bookkeeping on the round (first
strictly better model, adaptive iteration bound after every sample, exact stopping sample), so the
inlier masks are OpenCV's. One host sync per round (loop control and sample tables; a second one
in large rounds, which score real roots only) plus one at the start (per-problem counts).

Performance notes (CPU, see ``benchmarks/bench_ransac.py``): small problems are bound by the number
of torch ops per round, so the first round is small (32 samples: with few outliers OpenCV stops
within it), both images share one gather / normalisation in the 7-point solver, and a problem's
final mask is the one its best model was counted with (no re-scoring pass). Large batches are bound
by scoring (float64, exact as OpenCV's double arithmetic).

Convention: as ``_find_fundamental_impl`` (``torch_frontend.ransac``); inside, a group's points are
``x12 (G, N, 4)`` float64 ``(x1, y1, x2, y2)`` with its valid slots compacted to the front.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from .. import _tuning
from .._checks import gather_slots, valid_first_order
from .bounds import _lmeds_iters, _niters_table_on, _table_rows, ransac_update_num_iters
from .consts import _consts
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
from .scoring import _epipolar_errors, _homogeneous, _inlier_mask
from .seven_point import _run_7point

_LMEDS_EXACT_FIT = 1e-12  # px^2: LMedS medians below this are ties (see _robust_group)


def _compact(valid: torch.Tensor, *tensors: torch.Tensor, width: int):
    """Move the valid slots of each row to the front and cut to ``width`` (the largest count, known
    on the host); returns the original slot ids too (the random stream is keyed by slot id, so
    compaction changes nothing)."""
    width = max(width, 1)
    order = valid_first_order(valid)[:, :width]
    return order, [gather_slots(t, order) for t in (valid, *tensors)]


def _lmeds_sigma_scale(n: torch.Tensor) -> torch.Tensor:
    """OpenCV LMedS's inlier scale ``2.5 * 1.4826 * (1 + 5 / max(n - 7, 1))`` for ``n`` points
    (float64; the inlier bound is ``max(0.001, scale * sqrt(median))``)."""
    return 2.5 * 1.4826 * (1.0 + 5.0 / (n - _MODEL_POINTS).clamp_min(1).to(torch.float64))


def _robust_group(x12, valid, n_host, states, thr2, confidence, max_iters, H, lmeds, fused=False):
    """Run RANSAC (``lmeds=False``) or LMedS on one group of problems (all rows use one method).

    ``x12: (G, N, 4)`` float64 ``(x1, y1, x2, y2)``, finite (zero at masked-out slots), valid slots
    compacted to the front (``valid (G, N)``, ``n_host`` the per-row counts as Python ints); ``states`` per-row
    ``cv::RNG`` states; ``H`` the largest round (None: from a memory budget). Returns the best model
    ``(G, 3, 3)``, inlier mask ``(G, N)``, ok ``(G,)`` and samples drawn ``(G,)``.

    RANSAC reproduces OpenCV's sequential loop exactly although a round evaluates many samples at
    once: within a round the running best count (cummax), the iteration bound after every sample
    and the first sample after which OpenCV would stop are all computed, and only samples up to that
    one count. Hence the result does not depend on the round sizes, which are chosen for speed
    (``_tuning.Strategy.ransac_*``): a first round of ``ransac_first_round`` samples, then each
    round takes all samples still allowed by the current bound (it only shrinks), capped by ``H``
    / the memory budget ``ransac_round_elems``.

    ``fused`` (RANSAC only): each round's models are scored, counted and replayed by one
    ``torch_frontend::ransac_score`` op (``fused/ransac_op.py``), which stops at OpenCV's last
    sample of the round instead of scoring the whole round.
    """
    G, N = valid.shape
    dev = x12.device
    strategy = _tuning.for_device(dev)
    k7 = _consts(dev)
    n = valid.sum(-1)
    nf = n.to(torch.float64)
    num = _lmeds_iters(confidence, max_iters) if lmeds else max(int(max_iters), 1)
    streams = [_subset_stream(st, nb) for st, nb in zip(states, n_host)]
    fused = fused and not lmeds
    # the tensor scoring's homogeneous points (the fused op reads x12 and valid itself)
    h1 = None if fused else _homogeneous(x12[..., :2], valid)
    h2 = None if fused else _homogeneous(x12[..., 2:], valid)
    best_F = torch.zeros(G, 3, 3, dtype=torch.float64, device=dev)
    best_inl = torch.zeros(G, N, dtype=torch.bool, device=dev)  # RANSAC: the best model's mask
    best_score = torch.full((G,), float("inf") if lmeds else -1.0, dtype=torch.float64, device=dev)
    done = torch.zeros(G, dtype=torch.int64, device=dev)
    niters = torch.full((G,), num, dtype=torch.int64, device=dev)
    done_h, niters_h = [0] * G, [num] * G
    if fused:
        from ..fused.ransac_op import ransac_score_op

        table = _niters_table_on(_table_rows(N), max_iters, confidence, dev)
    rnd = 0
    while True:
        if rnd:
            done_h, niters_h = torch.stack([done, niters]).tolist()  # the one host sync per round
        act_l = [i for i in range(G) if done_h[i] < niters_h[i]]
        if not act_l:
            break
        A = len(act_l)
        Hr = max(niters_h[i] - done_h[i] for i in act_l)
        if not lmeds:  # rounds of 32, 64, 128, ...: at most ~2x the samples OpenCV draws
            Hr = min(Hr, strategy.ransac_first_round << rnd)
        Hr = min(Hr, H if H is not None else max(16, strategy.ransac_round_elems // max(A * N, 1)))
        rnd += 1
        # sample tables of this round (host, lazily generated and cached per (state, n))
        idx_np = np.zeros((A, Hr, _MODEL_POINTS), dtype=np.int64)
        ok_np = np.zeros((A, Hr), dtype=bool)
        for j, i in enumerate(act_l):
            lo = done_h[i]
            hi = min(lo + Hr, niters_h[i])
            idx_np[j, : hi - lo] = streams[i].upto(hi)[lo:hi]
            ok_np[j, : hi - lo] = True
        idx = torch.from_numpy(idx_np).to(dev)
        g_ok = None if fused else torch.from_numpy(ok_np).to(dev)
        if A == G:  # common case (B = 1, or all problems still running): no gathers
            a12, b1, b2, d0, n0, nfa, prev = x12, h1, h2, done, niters, nf, best_score
            av, an = valid, n
        else:
            act = torch.tensor(act_l, dtype=torch.int64, device=dev)
            a12, b1, b2 = x12[act], (None if fused else h1[act]), (None if fused else h2[act])
            d0, n0, nfa, prev = done[act], niters[act], nf[act], best_score[act]
            av, an = valid[act], n[act]
        flat = idx.view(A, Hr * _MODEL_POINTS, 1).expand(-1, -1, 4)
        smp = a12.gather(1, flat).view(A * Hr, _MODEL_POINTS, 2, 2)
        n_live = int(ok_np.sum())
        if n_live < A * Hr:
            # problems near their bound leave lanes past it: solve only the live samples (known on
            # the host) and put the models back in (problem, sample) order
            live = torch.from_numpy(np.flatnonzero(ok_np.reshape(-1))).to(dev)
            Fl, fl_ok = _run_7point(smp[live], k7)
            Fh = torch.zeros(A * Hr, 3, 9, dtype=Fl.dtype, device=dev).index_copy_(0, live, Fl)
            fok = torch.zeros(A * Hr, 3, dtype=torch.bool, device=dev).index_copy_(0, live, fl_ok)
        else:
            Fh, fok = _run_7point(smp, k7)  # (A*Hr, 3, 9), (A*Hr, 3)
        fok = fok.view(A, Hr * 3)
        Fh = Fh.view(A, Hr * 3, 3, 3)  # garbage where not fok: never counted, never kept
        if lmeds:
            err = _epipolar_errors(Fh, b1, b2)  # (A, N, 3Hr), inf at masked-out slots
            kth = (nfa.to(torch.int64) // 2)[:, None, None].expand(-1, 1, Hr * 3)
            med = err.sort(dim=1).values.gather(1, kth)[:, 0]
            # Deviation: with n <= 13 the median index n // 2 <= 6 falls among the 7 sample points,
            # whose errors are rounding noise (~1e-25 px^2), so OpenCV's pick among exact fits is
            # decided by floating-point noise. Medians below (1e-6 px)^2 are treated as equal and
            # the first such model in OpenCV's draw order wins (deterministic, same statistics).
            med = med.clamp_min(_LMEDS_EXACT_FIT)
            score = torch.where(fok, med, torch.full_like(med, float("inf")))
            cand, k = score.min(-1)  # first minimum = OpenCV's sequential strict "<"
            better = cand < prev
            new_n = n0
            used = torch.minimum(d0 + Hr, n0) - d0
        elif fused:
            # scoring, counts, OpenCV's sequential acceptance and bound, its stopping sample: one op
            live = torch.from_numpy(ok_np.sum(1)).to(dev)
            bst, new_n, dn, k, new_inl = ransac_score_op(Fh.view(A, Hr * 3, 9), fok, a12, av, an, table, live,
                                                         prev.to(torch.int64), n0, d0, thr2)
            better = k >= 0
            k = k.clamp_min(0)
            cand = bst.to(torch.float64)
            used = dn - d0
        else:
            if A * Hr * 3 * N > strategy.ransac_compact_elems:
                # score only real roots: most samples have one, so move valid models to the front
                # (stable, keeps OpenCV's order) and cut to the largest valid count of any problem
                vorder = torch.argsort((~fok).to(torch.int8), dim=1, stable=True)
                kmax = max(int(fok.sum(1).max()), 1)
                vorder = vorder[:, :kmax]
                Fv = Fh.gather(1, vorder[..., None, None].expand(-1, -1, 3, 3))
                cnt = torch.full((A, Hr * 3), -1.0, dtype=torch.float64, device=dev)
                mask = _inlier_mask(Fv, b1, b2, thr2)  # (A, N, kmax)
                cnt.scatter_(1, vorder, mask.sum(1).to(torch.float64))
            else:  # small round: scoring everything is cheaper than the compaction
                vorder = None
                mask = _inlier_mask(Fh, b1, b2, thr2)  # (A, N, 3Hr)
                cnt = mask.sum(1).to(torch.float64)
            cnt = torch.where(fok, cnt, torch.full_like(cnt, -1.0))
            c3 = cnt.view(A, Hr, 3)
            floor = prev.clamp_min(_MODEL_POINTS - 1)  # accept only > max(best, modelPoints - 1)
            run_best = torch.maximum(torch.cummax(c3.amax(-1), dim=1).values, prev[:, None])  # after sample i
            improved = run_best > floor[:, None]
            ep = (nfa[:, None] - run_best) / nfa[:, None]
            n_after = torch.where(
                improved, ransac_update_num_iters(confidence, ep, _MODEL_POINTS, n0[:, None].expand(A, Hr)), n0[:, None]
            )
            ar = torch.arange(Hr, device=dev)
            stop = (d0[:, None] + ar + 1 >= n_after) | ~g_ok  # OpenCV: for (iter = 0; iter < niters; iter++)
            i_stop = torch.where(stop.any(1), stop.to(torch.int8).argmax(1), torch.full_like(d0, Hr - 1))
            within = ar[None, :] <= i_stop[:, None]
            cm = torch.where(within[..., None], c3, torch.full_like(c3, -1.0)).view(A, Hr * 3)
            cand, k = cm.max(-1)  # first maximum = OpenCV's sequential strict ">"
            better = cand > floor
            new_n = n_after.gather(1, i_stop[:, None])[:, 0]
            used = i_stop + 1
        newF = Fh.gather(1, k[:, None, None, None].expand(-1, 1, 3, 3))[:, 0]
        if not lmeds:
            # keep the winning model's mask of this round (OpenCV keeps the mask it counted, too)
            if not fused:
                col = k if vorder is None else (vorder == k[:, None]).to(torch.int8).argmax(1)
                new_inl = mask.gather(2, col[:, None, None].expand(-1, N, 1))[..., 0]
            if A == G:
                best_inl = torch.where(better[:, None], new_inl, best_inl)
            else:
                best_inl[act] = torch.where(better[:, None], new_inl, best_inl[act])
        if A == G:
            best_F = torch.where(better[:, None, None], newF, best_F)
            best_score = torch.where(better, cand, best_score)
            niters = new_n
            done = d0 + used
        else:
            best_F[act] = torch.where(better[:, None, None], newF, best_F[act])
            best_score[act] = torch.where(better, cand, prev)
            niters[act] = new_n
            done[act] = d0 + used
    if lmeds:
        have = torch.isfinite(best_score)
        sigma = (_lmeds_sigma_scale(n) * torch.where(have, best_score, torch.zeros_like(best_score)).sqrt()).clamp_min(0.001)
        err = _epipolar_errors(best_F[:, None], h1, h2)[..., 0]
        inl = (err.to(torch.float32) <= (sigma * sigma).to(torch.float32)[:, None]) & valid
        ok = have & (inl.sum(-1) >= _MODEL_POINTS)
    else:
        ok = best_score >= _MODEL_POINTS
        inl = best_inl
    return best_F, inl, ok, done


def _find_fundamental_eager(p1: torch.Tensor, p2: torch.Tensor, valid: torch.Tensor, threshold: float,
                            confidence: float, max_iters: int, states: Sequence[int], batch_hypotheses,
                            pts: _Points | None = None, fused: bool = False) -> FundamentalFit:
    """``_find_fundamental_impl(..., method="opencv")`` on the default path (arguments as there;
    ``pts``: :func:`_opencv_points` of the call when the caller has them; ``fused``: RANSAC's
    scoring by the fused op, see :func:`_robust_group`). The problems are
    grouped by method (RANSAC rows, LMedS rows), each group compacted to its valid slots and solved
    by :func:`_robust_group`."""
    B, N = valid.shape
    dev = p1.device
    pts = _opencv_points(p1, p2, valid) if pts is None else pts
    n_host = pts.n.tolist()  # host sync: sample tables are per (seed, n)
    F, inliers, ok, iters, method, _ = _unsolved(pts, torch.float64)
    for lmeds, lo, hi in ((False, _MIN_RANSAC_POINTS, None), (True, _MIN_POINTS, _MIN_RANSAC_POINTS)):
        sel = [b for b in range(B) if n_host[b] >= lo and (hi is None or n_host[b] < hi)]
        if not sel:
            continue
        # all rows in one group (the usual case): plain slices, no index copies
        rows = slice(None) if len(sel) == B else torch.tensor(sel, dtype=torch.int64, device=dev)
        order, (gv, g12) = _compact(pts.eff[rows], pts.x12[rows], width=max(n_host[b] for b in sel))
        gF, ginl, gok, gdone = _robust_group(
            g12, gv, [n_host[b] for b in sel], [states[b] for b in sel], threshold * threshold,
            confidence, max_iters, batch_hypotheses, lmeds, fused,
        )
        full_inl = torch.zeros(len(sel), N, dtype=torch.bool, device=dev).scatter_(1, order, ginl)
        F[rows] = torch.where(gok[:, None, None], _canonical_sign(gF), F[rows])
        inliers[rows] = torch.where(gok[:, None], full_inl, pts.eff[rows])
        ok[rows] = gok
        iters[rows] = gdone
    return FundamentalFit(F.to(p1.dtype), inliers, ok, iters, method, None)
