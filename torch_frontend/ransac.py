"""Batched fundamental-matrix RANSAC (OpenCV ``findFundamentalMat(FM_RANSAC)`` semantics) and a
differentiable weighted 8-point refit.

VINS-Mono's ``rejectWithF`` (spec §3.8, §5.4) lifts every track into a 460-px virtual pinhole and
calls ``cv2.findFundamentalMat(un_cur, un_forw, FM_RANSAC, F_threshold, 0.99)``. This module solves B
such problems together: every round takes a block of minimal samples per problem (32, 64, 128, ...,
never more than the current iteration bound allows), solves them with a batched 7-point solver,
scores every candidate on every point in parallel and then replays OpenCV's sequential bookkeeping
on the round (first strictly better model, adaptive iteration bound after every sample, exact
stopping sample), so the inlier masks are OpenCV's.

Convention:
    * ``p1, p2: (B, N, 2)`` float, pixels ``(x, y)`` of the virtual pinhole; ``valid: (B, N)`` bool.
      Masked-out slots may hold anything (NaN included); valid slots with a non-finite coordinate are
      treated as masked out (and reported as outliers).
    * ``F: (B, 3, 3)`` maps image-1 points to image-2 epipolar lines: ``[p2, 1] F [p1, 1]^T = 0``
      (OpenCV's convention). Returned F are scaled to unit Frobenius norm, with the entry of largest
      magnitude positive (OpenCV instead scales to ``F[2, 2] = 1``, which is ill-conditioned for
      rectified-stereo-like geometry where ``F[2, 2] ~ 0``).
    * Inlier test (OpenCV ``FMEstimatorCallback::computeError``): ``max(d1^2, d2^2) <= threshold^2``
      with ``dk`` the distance of the point in image k to its epipolar line (points are rounded to
      float32 first, as OpenCV does; arithmetic in float64).

Seeding rule (determinism; see :func:`find_fundamental`): problem b's minimal samples are exactly
the ones OpenCV's ``getSubset`` draws with ``cv::RNG(seed_b)`` for its n_b valid points taken in slot
order (``next() % n_b``, repeated indices redrawn). The default seed is OpenCV's own
(``(uint64)-1``, re-seeded on every call), which is why the masks equal cv2's. The sample stream
depends only on (seed_b, n_b): nothing depends on b, B, N, the padding layout, the round size or the
other problems, so a problem gets the same result in any batch as in a single call with the same
seed. The index tables are generated on the host lazily (only as many samples as the rounds reach),
vectorised (numpy: jump-ahead lanes for the multiply-with-carry stream, all candidate subset starts
at once for the redraw rule) and cached process-wide per (seed, n) in a small LRU, so a tracker whose
point count changes every frame pays ~0.1-1 ms once per new n instead of rebuilding 1000 samples.
The cache is thread-safe (calls from several threads give the single-threaded results).

Performance notes (CPU, see ``benchmarks/bench_ransac.py``): small problems are bound by the number
of torch ops per round, so the first round is small (32 samples: with few outliers OpenCV stops
within it), both images share one gather / normalisation in the 7-point solver, and a problem's
final mask is the one its best model was counted with (no re-scoring pass). Large batches are bound
by scoring (float64, exact as OpenCV's double arithmetic).
"""

from __future__ import annotations

import collections
import math
import threading
from typing import NamedTuple, Sequence, Tuple, Union

import numpy as np
import torch

from . import _tuning
from ._checks import check_points, check_shape, default_valid, gather_slots, valid_first_order

__all__ = ["FundamentalResult", "find_fundamental", "refit_fundamental", "ransac_update_num_iters"]

_FLT_EPSILON = 1.1920928955078125e-07
_DBL_MIN = 2.2250738585072014e-308
_MODEL_POINTS = 7
_LMEDS_OUTLIER_RATIO = 0.45  # OpenCV LMeDSPointSetRegistrator: fixed prior for its iteration count
_MIN_POINTS = 8  # VINS rejectWithF skips F estimation below 8 tracks
_LMEDS_EXACT_FIT = 1e-12  # px^2: LMedS medians below this are ties (see _robust_group)
_MIN_RANSAC_POINTS = 15  # OpenCV: 8..14 points => LMedS even when FM_RANSAC is asked for
_DEFAULT_THRESHOLD = 3.0  # px: findFundamentalMat's threshold when given one <= 0
_DEFAULT_CONFIDENCE = 0.99  # findFundamentalMat's confidence when given one outside (0, 1)
_DBL_EPSILON = 2.220446049250313e-16

METHOD_NONE, METHOD_LMEDS, METHOD_RANSAC = 0, 1, 2


# ----------------------------------------------------------------------------------------------
# result type
# ----------------------------------------------------------------------------------------------
class _FundamentalPair(NamedTuple):
    F: torch.Tensor
    inliers: torch.Tensor


class FundamentalResult(_FundamentalPair):
    """Result of :func:`find_fundamental`; unpacks as ``F, inliers = find_fundamental(...)``.

    Attributes:
        F: ``(B, 3, 3)`` best RANSAC (or LMedS) 7-point hypothesis, unit Frobenius norm, largest
            entry positive; NaN where ``ok`` is False.
        inliers: ``(B, N)`` bool inlier mask from the RANSAC scoring (never True on a masked-out
            slot). Where ``ok`` is False every valid (finite) point is reported as an inlier, so that
            a tracker keeps its tracks (spec §3.8).
        ok: ``(B,)`` bool, a model was found (OpenCV would return a non-empty F).
        num_iters: ``(B,)`` int64 number of minimal samples drawn for the problem.
        method: ``(B,)`` int8, 0 = none (< 8 valid points), 1 = LMedS (8..14), 2 = RANSAC (>= 15).
    """

    ok: torch.Tensor
    num_iters: torch.Tensor
    method: torch.Tensor

    def __new__(cls, F, inliers, ok, num_iters, method):
        self = super().__new__(cls, F, inliers)
        self.ok = ok
        self.num_iters = num_iters
        self.method = method
        return self

    def __reduce__(self):
        return (FundamentalResult, (self.F, self.inliers, self.ok, self.num_iters, self.method))


# ----------------------------------------------------------------------------------------------
# OpenCV's random sample stream (cv::RNG, multiply-with-carry), generated lazily on the host and
# cached process-wide per (state, n)
# ----------------------------------------------------------------------------------------------
_U32 = 0xFFFFFFFF
_U64 = 0xFFFFFFFFFFFFFFFF
_MWC_A = 4164903690
OPENCV_SEED = -1  # cv::RNG((uint64)-1), the state OpenCV's RANSAC/LMedS re-seed with on every call
_RAW_CACHE: collections.OrderedDict = collections.OrderedDict()  # state -> _RawStream
_RAW_CACHE_STATES = 16  # LRU bound: a fresh generator seed per call must not grow memory forever
_SUBSET_CACHE: collections.OrderedDict = collections.OrderedDict()  # (state, n) -> _SubsetStream
_SUBSET_CACHE_SIZE = 512  # <= 512 x (1000, 7) int32 = 14 MB; the tracker needs one entry per n
# Thread safety: every growth of a cached stream and every LRU update holds this lock (re-entrant:
# a subset stream grows its raw stream while holding it). Reading a table that is long enough takes
# no lock: a stream publishes its grown table with one attribute assignment once it is complete,
# so a reader sees the old table or the new one, never a half-built one, and both start with the
# same rows (tables only grow). Growth is geometric, so the lock is taken a few times per stream.
_STREAM_LOCK = threading.RLock()


_MWC_M = _MWC_A * 2**32 - 1
_MWC_BINV = pow(2**32, -1, _MWC_M)


class _RawStream:
    """Outputs of ``cv::RNG(state).next()`` (``state = lo32(state) * 4164903690 + hi32(state)``,
    output ``lo32(state)``), grown on demand.

    The recurrence is sequential, but it is a multiply-with-carry generator: with ``m = a 2^32 - 1``
    every state below m satisfies ``next(s) = s 2^-32 mod m`` (``2^32 next(s) = m lo32(s) + s``). So
    the stream is cut into lanes whose start states are jumped to with one modular power each
    (Python ints) and the lanes are stepped together in numpy uint64 (no overflow: s < m < 2^64).

    Thread-safe (see ``_STREAM_LOCK``): ``vals`` is replaced, never modified in place, and ``s``
    (the state after ``vals``) is only read and written under the lock."""

    __slots__ = ("vals", "s")

    def __init__(self, state: int):
        self.vals = np.zeros(0, dtype=np.int64)
        self.s = state

    def upto(self, count: int) -> np.ndarray:
        """At least the first ``count`` outputs (a longer array when it was grown further)."""
        vals = self.vals
        if vals.size >= count:
            return vals
        with _STREAM_LOCK:
            return self._grow(count)

    def _grow(self, count: int) -> np.ndarray:
        have = self.vals.size
        if have >= count:  # another thread grew it while this one waited for the lock
            return self.vals
        count = max(count, 2 * have, 256)
        s, head = self.s, []
        while s >= _MWC_M and have + len(head) < count:  # a seed above m: step until below it
            s = (s & _U32) * _MWC_A + (s >> 32)
            head.append(s & _U32)
        todo = count - have - len(head)
        lanes = -(-todo // 64) if todo > 0 else 0
        parts = [np.asarray(head, dtype=np.int64)]
        if lanes:
            T = -(-todo // lanes)
            jump = pow(_MWC_BINV, T, _MWC_M)
            starts = []
            for _ in range(lanes):
                starts.append(s)
                s = s * jump % _MWC_M
            S = np.asarray(starts, dtype=np.uint64)
            out = np.empty((lanes, T), dtype=np.uint64)
            lo, mul, sh = np.uint64(_U32), np.uint64(_MWC_A), np.uint64(32)
            for t in range(T):
                S = (S & lo) * mul + (S >> sh)
                out[:, t] = S
            parts.append((out & lo).astype(np.int64).reshape(-1))
            # s is now the state after lanes * T draws (>= todo)
        vals = np.concatenate([self.vals, *parts])
        self.s = s
        self.vals = vals  # publish: complete before it is visible
        return vals


def _raw_stream(state: int) -> _RawStream:
    with _STREAM_LOCK:
        st = _RAW_CACHE.get(state)
        if st is None:
            st = _RAW_CACHE[state] = _RawStream(state)
            while len(_RAW_CACHE) > _RAW_CACHE_STATES:
                _RAW_CACHE.popitem(last=False)
        else:
            _RAW_CACHE.move_to_end(state)
        return st


class _SubsetStream:
    """The 7-point index subsets OpenCV's ``getSubset`` draws for ``n`` points with ``cv::RNG(state)``:
    ``rng.uniform(0, n) = next() % n``, redrawn while it repeats an index of the subset. (OpenCV also
    redraws a subset whose last point is collinear with two others; here such a subset is kept and
    marked degenerate instead, see ``_collinear_last``.) Generated lazily, as many as asked for.

    Vectorised: the subset that starts at stream position p (and the position after it) depends only
    on p, not on what came before, so it is computed for every p of a block at once (draw j is
    redrawn iff the previous occurrence of its value lies at or after p); then the chain
    0 -> end(0) -> end(end(0)) ... picks OpenCV's subsets (a cheap host loop over samples).

    Thread-safe (see ``_STREAM_LOCK``): ``table`` is replaced, never modified in place, and ``pos``
    (the stream position after ``table``) is only read and written under the lock."""

    __slots__ = ("raw", "n", "table", "pos")

    def __init__(self, state: int, n: int):
        self.raw = _raw_stream(state)
        self.n = n
        self.table = np.zeros((0, _MODEL_POINTS), dtype=np.int32)
        self.pos = 0  # stream position of the next subset

    def _slow(self, p: int):
        """One subset from position p by the sequential rule (rare: windows with many redraws)."""
        cur: list = []
        while len(cur) < _MODEL_POINTS:
            v = int(self.raw.upto(p + 64)[p]) % self.n
            p += 1
            if v not in cur:
                cur.append(v)
        return cur, p

    def upto(self, count: int) -> np.ndarray:
        """At least the first ``count`` subsets, ``(>= count, 7)`` int32."""
        table = self.table
        if table.shape[0] >= count:
            return table
        with _STREAM_LOCK:
            return self._grow(count)

    def _grow(self, count: int) -> np.ndarray:
        have = self.table.shape[0]
        if have >= count:  # another thread grew it while this one waited for the lock
            return self.table
        need = count - have
        if have == 0 or need < have:  # grow geometrically: few extensions per stream
            need = max(need, have, 16)
        n = self.n
        # expected draws per subset: sum_i n / (n - i), i < 7; 8 (+ margin) for n >= 50
        per = sum(n / (n - i) for i in range(_MODEL_POINTS)) if n > _MODEL_POINTS else 64.0
        W = _MODEL_POINTS + max(8, int(4 * (per - _MODEL_POINTS)) + 4)  # window of draws per start
        out = np.empty((need, _MODEL_POINTS), dtype=np.int32)
        k, p0 = 0, self.pos
        while k < need:
            P = int((need - k) * per * 1.2) + 16  # candidate start positions in this block
            v = self.raw.upto(p0 + P + W)[p0 : p0 + P + W] % n
            L = v.size
            # prev[q]: previous position of the same value in the block (-1 if none)
            order = np.argsort(v, kind="stable")
            sv = v[order]
            prev = np.full(L, -1, dtype=np.int64)
            same = sv[1:] == sv[:-1]
            prev[order[1:][same]] = order[:-1][same]
            starts = np.arange(P)
            idx = starts[:, None] + np.arange(W)[None, :]  # (P, W)
            acc = prev[idx] < starts[:, None]  # not a repeat of a draw of this subset
            cs = np.cumsum(acc, axis=1, dtype=np.int16)
            complete = cs[:, -1] >= _MODEL_POINTS
            end = (cs >= _MODEL_POINTS).argmax(axis=1) + 1
            take = acc & (cs <= _MODEL_POINTS)
            rowpos = np.cumsum(complete) - 1  # row of each complete start in `subs`
            subs = v[idx][take & complete[:, None]].reshape(-1, _MODEL_POINTS)
            end_l, comp_l, row_l = end.tolist(), complete.tolist(), rowpos.tolist()
            p, k0, rows, slow = 0, k, [], []
            while k < need and p < P:
                if comp_l[p]:
                    rows.append(row_l[p])
                    p += end_l[p]
                else:
                    cur, q = self._slow(p0 + p)
                    rows.append(0)
                    slow.append((k, cur))
                    p = q - p0
                k += 1
            out[k0:k] = subs[rows] if rows else 0
            for j, cur in slow:
                out[j] = cur
            p0 += p
        table = np.concatenate([self.table, out])
        self.pos = p0
        self.table = table  # publish: complete before it is visible
        return table


def _subset_stream(state: int, n: int) -> _SubsetStream:
    key = (state, n)
    with _STREAM_LOCK:
        st = _SUBSET_CACHE.get(key)
        if st is None:
            st = _SUBSET_CACHE[key] = _SubsetStream(state, n)
            while len(_SUBSET_CACHE) > _SUBSET_CACHE_SIZE:
                _SUBSET_CACHE.popitem(last=False)
        else:
            _SUBSET_CACHE.move_to_end(key)
        return st


def _clear_sample_caches() -> None:
    """Empty the process-wide sample-table caches (tests, benchmarks; streams already handed out
    stay valid)."""
    with _STREAM_LOCK:
        _SUBSET_CACHE.clear()
        _RAW_CACHE.clear()


def _opencv_samples(state: int, n: int, num: int) -> torch.Tensor:
    """The first ``num`` subsets of :class:`_SubsetStream` ``(state, n)`` as ``(num, 7)`` int64."""
    return torch.from_numpy(_subset_stream(state, n).upto(num)[:num].astype(np.int64))


def _state_of(seed: int) -> int:
    """Seed -> ``cv::RNG`` state: two's complement 64 bits; 0 means OpenCV's ``(uint64)-1`` too, so
    ``seed=0``, ``seed=-1`` and no seed all reproduce cv2 (``cv::RNG(0)``'s own 0xffffffff state is
    not reachable, nobody needs it)."""
    s = int(seed) & _U64
    return s if s else _U64


# ----------------------------------------------------------------------------------------------
# OpenCV helpers
# ----------------------------------------------------------------------------------------------
def ransac_update_num_iters(confidence: float, ep: torch.Tensor, model_points: int, max_iters: torch.Tensor) -> torch.Tensor:
    """OpenCV ``RANSACUpdateNumIters`` elementwise: ``ep`` outlier ratio, ``max_iters`` current bound."""
    p = min(max(float(confidence), 0.0), 1.0)
    ep = ep.to(torch.float64).clamp(0.0, 1.0)
    num = math.log(max(1.0 - p, _DBL_MIN))
    denom_raw = 1.0 - (1.0 - ep) ** model_points
    denom = torch.log(denom_raw.clamp_min(_DBL_MIN))
    mi = max_iters.to(torch.float64)
    capped = (denom >= 0) | (-num >= mi * (-denom))
    # cvRound = round half to even, as torch.round
    it = torch.where(capped, mi, torch.round(num / torch.where(denom < 0, denom, torch.full_like(denom, -1.0))))
    it = torch.where(denom_raw < _DBL_MIN, torch.zeros_like(it), it)
    return it.to(max_iters.dtype)


def _solve_cubic(c: torch.Tensor):
    """Real roots of ``c[...,0] x^3 + c[...,1] x^2 + c[...,2] x + c[...,3]`` (float64, batched).

    Returns ``roots (..., 3)`` and ``ok (..., 3)`` bool. All lanes stay finite (both branches of every
    ``torch.where`` are evaluated). Roots are polished with two Newton steps on the original cubic.

    Not ``kornia.geometry.solvers.solve_cubic``: measured (kornia 0.9.0) on the 22 380 cubics of
    ``tests/test_ransac.py`` its roots equal these in only 12 % of rows (three-root rows in another
    order, max |diff| 2e-13), and it zero-pads instead of flagging which slots are real roots.

    Root order: not OpenCV's (three real roots come as largest, middle, smallest); the 7-point
    solver uses :func:`_solve_cubic_opencv`, the Lambda Twist P3P (``loop/pnp.py``) this one.
    """
    a, b, cc, d = c.unbind(-1)
    scale = c.abs().amax(-1).clamp_min(1e-300)
    a, b, cc, d = a / scale, b / scale, cc / scale, d / scale
    one = torch.ones_like(a)
    is_cubic = a.abs() > 1e-12
    a_s = torch.where(is_cubic, a, one)
    p, q, r = b / a_s, cc / a_s, d / a_s
    # depressed cubic t^3 + P t + Q, x = t - p/3
    P = q - p * p / 3.0
    Q = 2.0 * p ** 3 / 27.0 - p * q / 3.0 + r
    disc = (Q / 2.0) ** 2 + (P / 3.0) ** 3
    # one real root (disc > 0): Cardano
    sq = torch.sqrt(disc.clamp_min(0.0))
    u = -Q / 2.0 + sq
    v = -Q / 2.0 - sq
    t1 = torch.sign(u) * u.abs().pow(1.0 / 3.0) + torch.sign(v) * v.abs().pow(1.0 / 3.0)
    # three real roots (disc <= 0): trigonometric
    mneg = (-P / 3.0).clamp_min(0.0)
    m = 2.0 * torch.sqrt(mneg)
    pos = mneg > 0
    den = torch.where(pos, P * m, -one)
    arg = torch.where(pos, (3.0 * Q / den).clamp(-1.0, 1.0), torch.zeros_like(Q))
    theta = torch.acos(arg) / 3.0
    t3 = m[..., None] * torch.cos(theta[..., None] - _CUBIC_PHASES.to(c.device, c.dtype))
    one_root = (disc > 0)[..., None]
    roots = torch.where(one_root, t1[..., None], t3) - (p / 3.0)[..., None]
    ok = torch.cat([torch.ones_like(one_root), ~one_root, ~one_root], -1)
    # quadratic / linear fallback (OpenCV solveCubic handles a == 0 the same way); on the CPU it is
    # skipped when no lane needs it (a free check there; elsewhere it would be a host sync)
    if not _tuning.for_device(c.device).host_checks_free or not bool(is_cubic.all()):
        is_quad = b.abs() > 1e-12
        b_s = torch.where(is_quad, b, one)
        qd = cc * cc - 4.0 * b * d
        sqd = torch.sqrt(qd.clamp_min(0.0))
        qr = torch.stack([(-cc + sqd) / (2.0 * b_s), (-cc - sqd) / (2.0 * b_s)], -1)
        c_s = torch.where(cc.abs() > 1e-12, cc, one)
        lin = -d / c_s
        quad_roots = torch.where(is_quad[..., None], qr, torch.stack([lin, lin], -1))
        quad_ok = torch.where(
            is_quad[..., None],
            (qd >= 0)[..., None].expand_as(qr),
            torch.stack([cc.abs() > 1e-12, torch.zeros_like(is_quad)], -1),
        )
        quad_roots = torch.cat([quad_roots, torch.zeros_like(quad_roots[..., :1])], -1)
        quad_ok = torch.cat([quad_ok, torch.zeros_like(quad_ok[..., :1])], -1)
        roots = torch.where(is_cubic[..., None], roots, quad_roots)
        ok = torch.where(is_cubic[..., None], ok, quad_ok)
    # Newton polish (guards against cancellation when |a| is small but above the cut-off)
    A, Bq, C, D = (t[..., None] for t in (a, b, cc, d))
    A3, B2 = 3.0 * A, 2.0 * Bq
    for _ in range(2):
        f = ((A * roots + Bq) * roots + C) * roots + D
        fp = (A3 * roots + B2) * roots + C
        big = fp.abs() > 1e-300
        step = torch.where(big, f / torch.where(big, fp, torch.ones_like(fp)), torch.zeros_like(f))
        new = roots - step
        roots = torch.where(torch.isfinite(new) & (step.abs() < 1e3 * (1.0 + roots.abs())), new, roots)
    ok = ok & torch.isfinite(roots)
    return torch.where(ok, roots, torch.zeros_like(roots)), ok


def _solve_cubic_opencv(c: torch.Tensor):
    """Real roots of ``c[...,0] x^3 + c[...,1] x^2 + c[...,2] x + c[...,3]`` as ``cv::solveCubic``
    finds them (its form in OpenCV 4.14: coefficients scaled by their largest magnitude, expanded
    discriminant): the same number, in the same order, by the same formulas (float64, batched, no
    gradients).

    Returns ``roots (..., 3)`` and ``ok (..., 3)`` bool, the real roots first (zero where not ok).

    Convention (``cv::solveCubic``; its branch decisions are taken on OpenCV's own arithmetic, the
    very operations in the same order, so for the same coefficients the number of roots is cv2's,
    also at a double root where it depends on rounding). With ``m = max |c_k|`` and ``eps`` the
    float64 epsilon:
        * ``|c0| >= eps m``: ``a_k = (c_k / m) / (c0 / m)``, ``Q = (a1^2 - 3 a2) / 9``,
          ``R = (2 a1^3 - 9 a1 a2 + 27 a3) / 54`` and ``d = Q^3 - R^2`` (expanded, as OpenCV).
          ``d > 0``: three roots ``-2 sqrt(Q) cos((theta + 2 pi k) / 3) - a1 / 3``, ``theta =
          acos(R / sqrt(Q^3))``, k = 0, 1, 2, i.e. the smallest, the largest, then the middle one.
          ``d == 0``: the simple root, then the double one (one root if they coincide).
          ``d < 0``: one root.
        * ``|c0| < eps m``: the quadratic's roots, the one from the larger ``|q|`` of ``q = (-c2 +-
          sqrt(disc)) / 2`` first (one root if ``disc == 0``, none if ``disc < 0``); ``|c1| < eps m``
          too: the linear root; ``|c2| < eps m`` too (or ``m < eps``): no root.
    The order of the 7-point models decides which of two models with equal inlier counts RANSAC
    keeps (OpenCV: the first). No Newton polish (OpenCV's models come from these very formulas);
    where OpenCV's formulas give NaN (an ``acos`` argument past 1 by rounding) the root is not ok.
    Unlike :func:`_solve_cubic`, lanes of branches not taken may hold NaN (no gradients here).
    """
    mc = c.abs().amax(-1)
    c0, c1, c2, c3 = c.unbind(-1)
    tiny = _DBL_EPSILON * mc
    cubic = (c0.abs() >= tiny) & (mc >= _DBL_EPSILON)
    # OpenCV's expressions, operation by operation (C++ evaluates left to right; its x86 builds do
    # not contract into fused multiply-adds), so the sign of d is OpenCV's bit for bit
    cs = c * (1.0 / mc)[..., None]
    a1, a2, a3 = (cs[..., 1:] * (1.0 / cs[..., 0])[..., None]).unbind(-1)
    a11 = a1 * a1
    Q = (a11 - 3.0 * a2) * (1.0 / 9.0)
    R = (a1 * (2.0 * a1 * a1 - 9.0 * a2) + 27.0 * a3) * (1.0 / 54.0)
    two_a2 = 2.0 * a2
    d = (a11 * (a2 * a2 - 4.0 * a1 * a3) + two_a2 * (9.0 * a1 * a3 - two_a2 * a2) - 27.0 * a3 * a3) * (1.0 / 108.0)
    three = cubic & (d > 0)
    t2 = a1 * (1.0 / 3.0)
    # d > 0: trigonometric form
    theta = torch.acos(R / torch.sqrt(Q * Q * Q))
    x3 = (-2.0 * torch.sqrt(Q))[..., None] * torch.cos((theta * (1.0 / 3.0))[..., None]
                                                        + _CUBIC_PHASES.to(c.device, c.dtype)) - t2[..., None]
    # d < 0: one root
    e = (torch.sqrt(-d) + R.abs()).pow(1.0 / 3.0)
    e = torch.where(R > 0, -e, e)
    zero = torch.zeros_like(mc)
    roots = torch.where(three[..., None], x3, torch.stack([(e + Q / e) - t2, zero, zero], -1))
    ok = torch.stack([cubic, three, three], -1)
    # rare branches (a double root, a negligible c0): on the CPU skipped when no lane needs them
    # (a free check there; elsewhere it would be a host sync)
    dbl = cubic & (d == 0)
    if not _tuning.for_device(c.device).host_checks_free or bool((dbl | ~cubic).any()):
        no = torch.zeros_like(cubic)
        cr = _cbrt(R)
        a13 = a1 / 3.0
        y0, y1 = -2.0 * cr - a13, cr - a13
        roots = torch.where(dbl[..., None], torch.stack([y0, y1, zero], -1), roots)
        ok = torch.where(dbl[..., None], torch.stack([~no, y0 != y1, no], -1), ok)
        # negligible c0: quadratic (on the unscaled coefficients, as OpenCV) or linear
        quad = ~cubic & (c1.abs() >= tiny) & (mc >= _DBL_EPSILON)
        lin = ~cubic & ~quad & (c2.abs() >= tiny) & (mc >= _DBL_EPSILON)
        qd = c2 * c2 - 4.0 * c1 * c3
        sqd = torch.sqrt(qd)
        q1 = (-c2 + sqd) * 0.5
        q2 = (c2 + sqd) * -0.5
        q = torch.where(q1.abs() > q2.abs(), q1, q2)
        qroots = torch.where(quad[..., None], torch.stack([q / c1, c3 / q, zero], -1),
                             torch.stack([-c3 / c2, zero, zero], -1))
        qok = torch.where(quad[..., None], torch.stack([qd >= 0, qd > 0, no], -1), torch.stack([lin, no, no], -1))
        roots = torch.where(cubic[..., None], roots, qroots)
        ok = torch.where(cubic[..., None], ok, qok)
    ok = ok & torch.isfinite(roots)
    return torch.where(ok, roots, torch.zeros_like(roots)), ok


def _cbrt(x: torch.Tensor) -> torch.Tensor:
    """Real cube root (``std::cbrt``; torch has none), odd in ``x``."""
    return torch.sign(x) * x.abs().pow(1.0 / 3.0)


_CUBIC_PHASES = 2.0 * math.pi * torch.arange(3, dtype=torch.float64) / 3.0


def _opencv_null_seeds() -> torch.Tensor:
    """The two vectors OpenCV's ``SVDecomp(..., FULL_UV)`` of the 7x9 system completes ``V`` with:
    its Jacobi SVD draws, for each missing row, 9 entries ``+-1/9`` from a fresh ``cv::RNG(0x12345678)``
    (sign from bit 8 of ``next()``) and orthogonalises them against the rows before. So OpenCV's
    null-space basis of ``run7Point`` is ``f1 = P r7 / |P r7|``, ``f2`` = the unit vector of ``P r8``
    orthogonal to ``f1`` (P the projection onto the null space). Returned as ``(9, 2)`` columns
    ``r7, r8`` of +-1 (the scale does not matter)."""
    s, cols = 0x12345678, []
    for _ in range(2):
        col = []
        for _ in range(9):
            s = (s & _U32) * _MWC_A + (s >> 32)
            col.append(1.0 if s & 256 else -1.0)
        cols.append(col)
    return torch.tensor(cols, dtype=torch.float64).T.contiguous()


_OPENCV_NULL_SEEDS = _opencv_null_seeds()
_PAIRS_CACHE: dict = {}


def _cofactor(M: torch.Tensor) -> torch.Tensor:
    """Cofactor matrix of ``(..., 3, 3)``: rows are cross products of the other two rows."""
    r0, r1, r2 = M.unbind(-2)
    return torch.stack([torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)], -2)


def _epipolar_rows(x0, y0, x1, y1):
    """Rows of the linear system ``[x1 y1 1] F [x0 y0 1]^T = 0`` in OpenCV's (row-major F) order."""
    one = torch.ones_like(x0)
    return torch.stack([x1 * x0, x1 * y0, x1, y1 * x0, y1 * y0, y1, x0, y0, one], -1)


def _collinear_last(m: torch.Tensor) -> torch.Tensor:
    """OpenCV ``haveCollinearPoints`` for a full 7-point subset: is the last point on a line through
    two earlier ones (or too close to one)? ``m: (M, 7, ..., 2)`` -> ``(M, ...)`` bool."""
    d = m[:, :-1] - m[:, -1:]  # (M, 6, ..., 2)
    key = str(m.device)
    if key not in _PAIRS_CACHE:  # pairs k < j of the six difference vectors
        _PAIRS_CACHE[key] = torch.tril_indices(6, 6, offset=-1, device=m.device)
    j, k = _PAIRS_CACHE[key]
    d1, d2 = d[:, j], d[:, k]
    cross = d2[..., 0] * d1[..., 1] - d2[..., 1] * d1[..., 0]
    tol = _FLT_EPSILON * (d1.abs().sum(-1) + d2.abs().sum(-1))
    return (cross.abs() <= tol).any(1)


def _run_7point(m: torch.Tensor):
    """Batched OpenCV ``run7Point``. ``m: (M, 7, 2, 2)`` float64 (sample point, image, x/y) -> ``F (M,
    3, 3, 3)`` (up to three solutions, unit Frobenius norm), ``ok (M, 3)`` and ``degenerate (M,)``
    (OpenCV's collinearity check of the last sample point, in either image).

    Like OpenCV: Hartley-style normalisation (centroid, mean distance sqrt(2)), the two-dimensional
    null space of the 7x9 system (here from a complete QR of its transpose: the last two columns of
    Q, which is much faster than a batched SVD and equally stable for a rank-7 system), the real
    roots of det(a*F1 + (1 - a)*F2) = 0, then de-normalisation. Both images are handled in one
    tensor (half the small ops).

    Model order = OpenCV's (which of two models with the same inlier count RANSAC keeps depends on
    it): F1, F2 are OpenCV's own basis of the null space (:func:`_opencv_null_seeds`; any other
    basis gives the same models in another order), so the cubic is OpenCV's up to rounding, and its
    roots come in ``cv::solveCubic``'s order (:func:`_solve_cubic_opencv`).
    """
    degenerate = _collinear_last(m).any(-1)
    c = m.mean(1, keepdim=True)  # (M, 1, 2, 2)
    dm = m - c
    s = dm.norm(dim=-1).mean(1)  # (M, 2)
    good = (s >= _FLT_EPSILON).all(-1)
    s = math.sqrt(2.0) / torch.where(good[:, None], s, torch.ones_like(s))
    nm = dm * s[:, None, :, None]
    A = _epipolar_rows(nm[..., 0, 0], nm[..., 0, 1], nm[..., 1, 0], nm[..., 1, 1])  # (M, 7, 9)
    Nb = torch.linalg.qr(A.transpose(-1, -2), mode="complete").Q[..., 7:]  # (M, 9, 2) null space
    # OpenCV's basis of the null space (see _opencv_null_seeds), so that the cubic in alpha is
    # OpenCV's and its roots come in OpenCV's order: in Nb coordinates f1 ~ u = P r7 and f2 ~ v,
    # orthogonal to u on the side of P r8
    cf = Nb.transpose(-1, -2) @ _OPENCV_NULL_SEEDS.to(m.device)  # (M, 2, 2): columns P r7, P r8
    u0, u1 = cf[:, 0, 0], cf[:, 1, 0]  # u: P r7 (its length does not matter: the roots are
    side = torch.where(u0 * cf[:, 1, 1] - u1 * cf[:, 0, 1] < 0, -1.0, 1.0)  # those of any multiple)
    su0, su1 = side * u0, side * u1  # v = side * (-u1, u0): orthogonal to u, as long, towards P r8
    # f1 - f2 = (u0 + su1) n1 + (u1 - su0) n2, f2 = -su1 n1 + su0 n2 (n1, n2 the columns of Nb),
    # as elementwise products (a batched 9x2 @ 2x2 matmul costs more)
    coef = torch.stack([u0 + su1, -su1, u1 - su0, su0], -1).view(-1, 1, 2, 2)
    Fab = (Nb[..., None] * coef).sum(-2)  # (M, 9, 2): OpenCV's f1 - f2 and f2 (up to one scale)
    Fa = Fab[..., 0].reshape(-1, 3, 3)  # F(alpha) = alpha * Fa + Fb = alpha f1 + (1 - alpha) f2
    Fb = Fab[..., 1].reshape(-1, 3, 3)
    # det(alpha*Fa + Fb) = alpha^3 det Fa + alpha^2 <cof Fa, Fb> + alpha <Fa, cof Fb> + det Fb
    ca, cb = _cofactor(Fa), _cofactor(Fb)  # det M = <M, cof M> / 3 = <row 0, cof row 0>
    coeffs = torch.stack(
        [
            (Fa[:, 0] * ca[:, 0]).sum(-1),
            (ca * Fb).sum((-1, -2)),
            (Fa * cb).sum((-1, -2)),
            (Fb[:, 0] * cb[:, 0]).sum(-1),
        ],
        -1,
    )
    roots, rok = _solve_cubic_opencv(coeffs)  # (M, 3), OpenCV's order
    Fn = roots[..., None, None] * Fa[:, None] + Fb[:, None]  # (M, 3, 3, 3)
    # de-normalise: F = T2^T Fn T1, T = [[s, 0, -s cx], [0, s, -s cy], [0, 0, 1]]
    zero = torch.zeros_like(s)
    sc = -s[..., None] * c[:, 0]  # (M, 2, 2): -s * (cx, cy) per image
    T = torch.stack([s, zero, sc[..., 0], zero, s, sc[..., 1], zero, zero, torch.ones_like(s)], -1)
    T = T.view(-1, 2, 3, 3)
    F = T[:, None, 1].transpose(-1, -2) @ Fn @ T[:, None, 0]
    nrm = F.flatten(-2).norm(dim=-1)
    fok = rok & good[:, None] & (nrm > 0) & torch.isfinite(nrm)
    F = F / torch.where(fok, nrm, torch.ones_like(nrm))[..., None, None]
    F = torch.where(fok[..., None, None], F, torch.zeros_like(F))
    return F, fok, degenerate


def _homogeneous(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``(B, N, 2)`` points (zero at masked-out slots) -> ``(B, N, 3)`` homogeneous points, with
    ``(0, 0, 0)`` at masked-out slots: their epipolar lines are degenerate (``s = 0``), so they never
    count as inliers and have infinite error, without a mask op on the ``(B, N, K)`` score tensors."""
    return torch.cat([x, valid[..., None].to(x.dtype)], -1)


def _epipolar_terms(F: torch.Tensor, h1: torch.Tensor, h2: torch.Tensor):
    """Algebraic residual and line norms for K models on N points, as three batched matmuls.

    ``F: (B, K, 3, 3)``, ``h1, h2: (B, N, 3)`` (see ``_homogeneous``) -> ``d2 = (x2^T F x1)^2``,
    ``s2 = |(F x1)_xy|^2`` and ``s1 = |(F^T x2)_xy|^2``, each ``(B, N, K)``."""
    B, K = F.shape[:2]
    outer = (h2[..., :, None] * h1[..., None, :]).flatten(-2)  # (B, N, 9)
    d = outer @ F.flatten(-2).transpose(-1, -2)  # (B, N, K)
    # F x1, rows 0 and 1 of every model: columns [row0 of model 0..K-1, row1 of model 0..K-1]
    l2 = h1 @ F[:, :, :2, :].transpose(1, 2).reshape(B, 2 * K, 3).transpose(-1, -2)  # (B, N, 2K)
    l1 = h2 @ F[:, :, :, :2].permute(0, 3, 1, 2).reshape(B, 2 * K, 3).transpose(-1, -2)
    l2 = l2 * l2  # x*x: much cheaper than pow/square on CPU
    l1 = l1 * l1
    return d * d, l1[..., :K] + l1[..., K:], l2[..., :K] + l2[..., K:]


def _epipolar_errors(F: torch.Tensor, h1: torch.Tensor, h2: torch.Tensor) -> torch.Tensor:
    """OpenCV ``computeError``: ``max(d1^2, d2^2)`` squared point-to-epipolar-line distances,
    ``(B, N, K)`` for ``F: (B, K, 3, 3)``; inf where a line is degenerate (and at masked-out slots)."""
    d2, s1, s2 = _epipolar_terms(F, h1, h2)
    smin = torch.minimum(s1, s2)
    pos = smin > 0
    return torch.where(pos, d2 / torch.where(pos, smin, torch.ones_like(smin)), torch.full_like(d2, float("inf")))


def _inlier_mask(F: torch.Tensor, h1: torch.Tensor, h2: torch.Tensor, thr2: float) -> torch.Tensor:
    """``max(d1^2, d2^2) <= thr^2`` for K models on N points -> ``(B, N, K)`` bool, without divisions:
    ``d^2 <= thr^2 * min(s1, s2)`` (and a non-degenerate line; never at a masked-out slot).

    OpenCV compares ``(float)err <= (float)thr^2``; this differs only for errors within float32
    rounding of the threshold."""
    d2, s1, s2 = _epipolar_terms(F, h1, h2)
    smin = torch.minimum(s1, s2)
    bound = smin if thr2 == 1.0 else smin * thr2  # x * 1.0 == x: skip a full pass (VINS: 1 px)
    return (d2 <= bound) & (smin > 0)


def _canonical_sign(F: torch.Tensor) -> torch.Tensor:
    """Unit Frobenius norm with the largest-magnitude entry positive (``(..., 3, 3)``)."""
    flat = F.flatten(-2)
    nrm = flat.norm(dim=-1, keepdim=True)
    flat = flat / torch.where(nrm > 0, nrm, torch.ones_like(nrm))
    idx = flat.abs().argmax(-1, keepdim=True)
    sgn = torch.where(flat.gather(-1, idx) < 0, -1.0, 1.0).to(flat.dtype)
    return (flat * sgn).view_as(F)


# ----------------------------------------------------------------------------------------------
# the batched robust loop
# ----------------------------------------------------------------------------------------------
def _compact(valid: torch.Tensor, *tensors: torch.Tensor, width: int):
    """Move the valid slots of each row to the front and cut to ``width`` (the largest count, known
    on the host); returns the original slot ids too (the random stream is keyed by slot id, so
    compaction changes nothing)."""
    width = max(width, 1)
    order = valid_first_order(valid)[:, :width]
    return order, [gather_slots(t, order) for t in (valid, *tensors)]


def _robust_group(x1, x2, valid, n_host, states, thr2, confidence, max_iters, H, lmeds):
    """Run RANSAC (``lmeds=False``) or LMedS on one group of problems (all rows use one method).

    ``x1, x2: (G, N, 2)`` float64, finite (zero at masked-out slots), valid slots compacted to the
    front (``valid (G, N)``, ``n_host`` the per-row counts as Python ints); ``states`` per-row
    ``cv::RNG`` states; ``H`` the largest round (None: from a memory budget). Returns the best model
    ``(G, 3, 3)``, inlier mask ``(G, N)``, ok ``(G,)`` and samples drawn ``(G,)``.

    RANSAC reproduces OpenCV's sequential loop exactly although a round evaluates many samples at
    once: within a round the running best count (cummax), the iteration bound after every sample
    and the first sample after which OpenCV would stop are all computed, and only samples up to that
    one count. Hence the result does not depend on the round sizes, which are chosen for speed
    (``_tuning.Strategy.ransac_*``): a first round of ``ransac_first_round`` samples, then each
    round takes all samples still allowed by the current bound (it only shrinks), capped by ``H``
    / the memory budget ``ransac_round_elems``.
    """
    G, N = valid.shape
    dev = x1.device
    strategy = _tuning.for_device(dev)
    n = valid.sum(-1)
    nf = n.to(torch.float64)
    if lmeds:
        it0 = ransac_update_num_iters(
            confidence, torch.tensor(_LMEDS_OUTLIER_RATIO), _MODEL_POINTS, torch.tensor(max(int(max_iters), 1))
        )
        num = max(int(it0), 3)
    else:
        num = max(int(max_iters), 1)
    streams = [_subset_stream(st, nb) for st, nb in zip(states, n_host)]
    x12 = torch.cat([x1, x2], -1)  # (G, N, 4): one gather per round for both images
    h1 = _homogeneous(x1, valid)
    h2 = _homogeneous(x2, valid)
    best_F = torch.zeros(G, 3, 3, dtype=torch.float64, device=dev)
    best_inl = torch.zeros(G, N, dtype=torch.bool, device=dev)  # RANSAC: the best model's mask
    best_score = torch.full((G,), float("inf") if lmeds else -1.0, dtype=torch.float64, device=dev)
    done = torch.zeros(G, dtype=torch.int64, device=dev)
    niters = torch.full((G,), num, dtype=torch.int64, device=dev)
    done_h, niters_h = [0] * G, [num] * G
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
        g_ok = torch.from_numpy(ok_np).to(dev)
        if A == G:  # common case (B = 1, or all problems still running): no gathers
            a12, b1, b2, d0, n0, nfa, prev = x12, h1, h2, done, niters, nf, best_score
        else:
            act = torch.tensor(act_l, dtype=torch.int64, device=dev)
            a12, b1, b2 = x12[act], h1[act], h2[act]
            d0, n0, nfa, prev = done[act], niters[act], nf[act], best_score[act]
        flat = idx.view(A, Hr * _MODEL_POINTS, 1).expand(-1, -1, 4)
        smp = a12.gather(1, flat).view(A * Hr, _MODEL_POINTS, 2, 2)
        n_live = int(ok_np.sum())
        if n_live < A * Hr:
            # problems near their bound leave lanes past it: solve only the live samples (known on
            # the host) and put the models back in (problem, sample) order
            live = torch.from_numpy(np.flatnonzero(ok_np.reshape(-1))).to(dev)
            Fl, fl_ok, deg = _run_7point(smp[live])
            Fh = torch.zeros(A * Hr, 3, 3, 3, dtype=Fl.dtype, device=dev).index_copy_(0, live, Fl)
            fok = torch.zeros(A * Hr, 3, dtype=torch.bool, device=dev).index_copy_(0, live, fl_ok & ~deg[:, None])
            fok = fok.view(A, Hr * 3)
        else:
            Fh, fok, degenerate = _run_7point(smp)  # (A*Hr, 3, 3, 3), (A*Hr, 3), (A*Hr,)
            fok = (fok & ~degenerate[:, None]).view(A, Hr * 3)
        Fh = Fh.view(A, Hr * 3, 3, 3)
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
        sigma = 2.5 * 1.4826 * (1.0 + 5.0 / (n - _MODEL_POINTS).clamp_min(1).to(torch.float64))
        sigma = (sigma * torch.where(have, best_score, torch.zeros_like(best_score)).sqrt()).clamp_min(0.001)
        err = _epipolar_errors(best_F[:, None], h1, h2)[..., 0]
        inl = (err.to(torch.float32) <= (sigma * sigma).to(torch.float32)[:, None]) & valid
        ok = have & (inl.sum(-1) >= _MODEL_POINTS)
    else:
        ok = best_score >= _MODEL_POINTS
        inl = best_inl
    return best_F, inl, ok, done


def _seeds(B: int, generator: torch.Generator | None = None,
           seed: Union[None, int, Sequence[int], torch.Tensor] = None) -> list:
    """Per-problem ``cv::RNG`` states as B Python ints, from ``seed`` / ``generator`` as
    :func:`find_fundamental` takes them (see its seeding rule; the default is OpenCV's own state).
    A caller that runs many calls with the same seeds computes them once and passes them to
    :func:`_find_fundamental_impl`."""
    if seed is not None:
        s = torch.as_tensor(seed, dtype=torch.int64).cpu()
        if s.dim() == 0:
            s = s.expand(B)
        check_shape(s, (B,), "seed")
        return [_state_of(v) for v in s.tolist()]
    if generator is not None:
        v = torch.randint(-(2**63), 2**63 - 1, (1,), dtype=torch.int64, generator=generator, device=generator.device)
        return [_state_of(int(v.item()))] * B
    return [_state_of(OPENCV_SEED)] * B


def find_fundamental(
    p1: torch.Tensor,
    p2: torch.Tensor,
    valid: torch.Tensor | None = None,
    threshold: float = 1.0,
    confidence: float = 0.99,
    max_iters: int = 1000,
    generator: torch.Generator | None = None,
    batch_hypotheses: int | None = None,
    seed: Union[None, int, Sequence[int], torch.Tensor] = None,
) -> FundamentalResult:
    """Robust fundamental matrices for B point-set pairs at once (``cv2.findFundamentalMat`` with
    ``FM_RANSAC``, batched).

    Args:
        p1, p2: ``(B, N, 2)`` float, pixels ``(x, y)`` (VINS: the 460-px virtual pinhole), matched
            slot by slot.
        valid: ``(B, N)`` bool, which slots hold a correspondence (default all). Masked-out slots may
            contain NaN.
        threshold: inlier distance in pixels (VINS ``F_threshold``); ``<= 0`` means 3 (OpenCV).
        confidence: RANSAC confidence for the adaptive iteration bound (outside (0, 1): 0.99).
        max_iters: cap on minimal samples per problem (OpenCV default 1000).
        generator: optional ``torch.Generator``; one int64 is drawn from it (``torch.randint`` on the
            generator's device) and used as the ``cv::RNG`` state of every problem of the call.
        batch_hypotheses: the largest number of minimal samples evaluated per problem per round
            (rounds grow 32, 64, 128, ... up to it and never exceed the current iteration bound).
            None (default): from a memory budget (about 2^20 problem x sample x point lanes per
            round). Memory/speed knob only: results do not depend on it.
        seed: optional int or ``(B,)`` ints, per-problem ``cv::RNG`` states (two's complement, so
            ``-1`` is ``(uint64)-1``; 0 is mapped to it as well; takes precedence over
            ``generator``). Default (neither given), 0 or -1: OpenCV's own seed for every problem,
            so the masks reproduce cv2's.

    Returns:
        :class:`FundamentalResult` ``(F, inliers)`` with extra attributes ``ok``, ``num_iters``,
        ``method``.

    Convention:
        Per problem with n valid, finite correspondences:
        * n < 8: no estimation (VINS skips it): F NaN, every valid point an inlier, ``ok`` False.
        * 8 <= n <= 14: OpenCV's silent LMedS fallback: ``max(3, RANSACUpdateNumIters(conf, 0.45,
          7, max_iters))`` (300 for 0.99) 7-point samples, the model of least median error (upper
          median, ``err[n // 2]`` of the sorted errors), inliers ``err <= sigma^2`` with
          ``sigma = max(0.001, 2.5 * 1.4826 * (1 + 5 / (n - 7)) * sqrt(median))``; ``ok`` iff at
          least 7 inliers. ``threshold`` is ignored, as in OpenCV. Deviation: medians below
          (1e-6 px)^2 count as equal (first in draw order wins). For n <= 13 OpenCV's median rank
          n // 2 <= 6 lies among the sample's own 7 exact-fit points, so its choice between models
          is floating-point noise and cannot be reproduced; from n = 14 on the masks are OpenCV's.
        * n >= 15: RANSAC with the 7-point solver (up to three models per sample, each scored, in
          OpenCV's order); a model replaces the best one only with strictly more inliers (and at
          least 7: of two models with the same count the first drawn is kept, as in OpenCV); the
          iteration bound follows OpenCV's ``RANSACUpdateNumIters(confidence, outlier ratio, 7,
          bound)``, capped by ``max_iters``. Rounds run while some problem is below its bound;
          within a round the bound is replayed after every sample, so each problem stops at exactly
          OpenCV's last sample (``num_iters``) and later samples of the round are discarded.
        * All outliers (unrelated points): as OpenCV, some 7-point model that fits its own sample
          (>= 7 inliers, ``ok`` True) after ``max_iters`` samples.
        * No model found (all samples degenerate, e.g. all points identical): F NaN, every valid
          point an inlier, ``ok`` False.
        The returned F is the best minimal-sample model (as OpenCV; no re-fit), unit Frobenius norm,
        largest entry positive; re-fit with :func:`refit_fundamental` on ``inliers`` if wanted.
        Points are rounded to float32 (as OpenCV), all arithmetic is float64; F is returned in the
        dtype of ``p1``. Not differentiable (the mask is discrete; see :func:`refit_fundamental`).
        One host sync per round (loop control and sample tables; a second one in large rounds,
        which score real roots only) plus one at the start (per-problem counts).

    Seeding rule:
        Sample g of problem b is the g-th 7-subset OpenCV's ``getSubset`` would draw with
        ``cv::RNG(seed_b)`` from the n_b valid points in slot order. It depends only on (seed_b,
        n_b), so a problem in a batch gives exactly the same result as a single call on its valid
        points with the same seed. (Deviation: OpenCV redraws a subset whose last point is
        collinear with two others within FLT_EPSILON; here that sample just yields no model, so on
        such degenerate data the later samples differ from OpenCV's.)
    """
    check_points(p1, "p1")
    check_points(p2, "p2")
    check_shape(p2, tuple(p1.shape), "p2")
    valid = default_valid(p1, valid)
    threshold, confidence = opencv_threshold_confidence(threshold, confidence)
    H = None if batch_hypotheses is None else int(batch_hypotheses)
    if H is not None and H < 1:
        raise ValueError(f"batch_hypotheses: expected >= 1, got {batch_hypotheses}")
    states = _seeds(valid.shape[0], generator, seed)
    return _find_fundamental_impl(p1, p2, valid, float(threshold), float(confidence), max_iters, states, H)


def opencv_threshold_confidence(threshold: float, confidence: float) -> Tuple[float, float]:
    """``findFundamentalMat``'s own argument rules: a threshold ``<= 0`` means 3 px, a confidence
    outside ``[DBL_EPSILON, 1 - DBL_EPSILON]`` means 0.99."""
    if threshold <= 0:
        threshold = _DEFAULT_THRESHOLD
    if not (_DBL_EPSILON <= confidence <= 1 - _DBL_EPSILON):
        confidence = _DEFAULT_CONFIDENCE
    return float(threshold), float(confidence)


def _find_fundamental_impl(
    p1: torch.Tensor,
    p2: torch.Tensor,
    valid: torch.Tensor,
    threshold: float,
    confidence: float,
    max_iters: int,
    states: Sequence[int],
    batch_hypotheses: int | None,
) -> FundamentalResult:
    """:func:`find_fundamental` without input checks.

    Args:
        p1, p2: ``(B, N, 2)`` float, pixels ``(x, y)``, matched slot by slot.
        valid: ``(B, N)`` bool.
        threshold: inlier distance in pixels, > 0 (the public function maps ``<= 0`` to 3).
        confidence: in ``(0, 1)`` (the public function maps other values to 0.99).
        max_iters: cap on minimal samples per problem.
        states: B ``cv::RNG`` states as Python ints (:func:`_seeds`).
        batch_hypotheses: largest round (>= 1), or None for the memory budget.

    Returns:
        :class:`FundamentalResult`, as :func:`find_fundamental`.
    """
    B, N = valid.shape
    dev, out_dtype = p1.device, p1.dtype
    H = batch_hypotheses

    # OpenCV converts the points to float32 before anything else; the solver then runs in float64
    x1 = p1.detach().to(torch.float32).to(torch.float64)
    x2 = p2.detach().to(torch.float32).to(torch.float64)
    finite = torch.isfinite(x1).all(-1) & torch.isfinite(x2).all(-1)
    eff = valid & finite
    # keep masked-out lanes finite: every later torch.where evaluates both branches
    x1 = torch.where(eff[..., None], x1, torch.zeros_like(x1))
    x2 = torch.where(eff[..., None], x2, torch.zeros_like(x2))
    n = eff.sum(-1)
    n_host = n.tolist()  # host sync: sample tables are per (seed, n)

    F = torch.full((B, 3, 3), float("nan"), dtype=torch.float64, device=dev)
    inliers = eff.clone()
    ok = torch.zeros(B, dtype=torch.bool, device=dev)
    iters = torch.zeros(B, dtype=torch.int64, device=dev)
    method = torch.full((B,), METHOD_NONE, dtype=torch.int8, device=dev)
    method = torch.where(n >= _MIN_POINTS, torch.full_like(method, METHOD_LMEDS), method)
    method = torch.where(n >= _MIN_RANSAC_POINTS, torch.full_like(method, METHOD_RANSAC), method)

    for code, lo, hi in ((METHOD_RANSAC, _MIN_RANSAC_POINTS, None), (METHOD_LMEDS, _MIN_POINTS, _MIN_RANSAC_POINTS)):
        sel = [b for b in range(B) if n_host[b] >= lo and (hi is None or n_host[b] < hi)]
        if not sel:
            continue
        # all rows in one group (the usual case): plain slices, no index copies
        rows = slice(None) if len(sel) == B else torch.tensor(sel, dtype=torch.int64, device=dev)
        order, (gv, g1, g2) = _compact(eff[rows], x1[rows], x2[rows], width=max(n_host[b] for b in sel))
        gF, ginl, gok, gdone = _robust_group(
            g1, g2, gv, [n_host[b] for b in sel], [states[b] for b in sel], threshold * threshold,
            confidence, max_iters, H, code == METHOD_LMEDS,
        )
        full_inl = torch.zeros(len(sel), N, dtype=torch.bool, device=dev).scatter_(1, order, ginl)
        F[rows] = torch.where(gok[:, None, None], _canonical_sign(gF), F[rows])
        inliers[rows] = torch.where(gok[:, None], full_inl, eff[rows])
        ok[rows] = gok
        iters[rows] = gdone
    return FundamentalResult(F.to(out_dtype), inliers, ok, iters, method)




# ----------------------------------------------------------------------------------------------
# differentiable weighted 8-point refit
# ----------------------------------------------------------------------------------------------
def refit_fundamental(p1: torch.Tensor, p2: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted, normalised 8-point fundamental matrix, differentiable w.r.t. points and weights.

    Args:
        p1, p2: ``(B, N, 2)`` float, pixels ``(x, y)``.
        weights: ``(B, N)`` float >= 0 (or bool, e.g. the ``inliers`` of :func:`find_fundamental`).
            Slots with weight 0 or a non-finite coordinate are ignored (they may hold NaN).

    Returns:
        ``F: (B, 3, 3)`` in the dtype of ``p1``, ``[p2, 1] F [p1, 1]^T ~ 0``; NaN for problems with
        fewer than 8 slots of positive weight.

    Convention:
        * Hartley normalisation per image with weighted centroid and weighted RMS distance sqrt(2)
          (RMS rather than OpenCV's mean distance: it is smooth where a point hits the centroid).
        * The algebraic solution is the eigenvector of the smallest eigenvalue of the 9x9 weighted
          normal matrix ``sum_i w_i a_i a_i^T`` (``torch.linalg.eigh``); rank 2 is enforced as
          ``F (I - v v^T)`` with v the smallest eigenvector of ``F^T F`` (the same matrix as zeroing
          the smallest singular value, without the sign ambiguity of an SVD).
        * Output scaled to unit Frobenius norm with the largest-magnitude entry positive.
        Gradients are well defined when the two smallest eigenvalues of the normal matrix (and of
        ``F^T F``) are distinct, i.e. for >= 8 points in general position.
    """
    check_points(p1, "p1")
    check_points(p2, "p2")
    check_shape(p2, tuple(p1.shape), "p2")
    check_shape(weights, tuple(p1.shape[:-1]), "weights")
    dtype = p1.dtype
    w = weights.to(dtype)
    finite = torch.isfinite(p1).all(-1) & torch.isfinite(p2).all(-1) & torch.isfinite(w)
    use = finite & (w > 0)
    w = torch.where(use, w, torch.zeros_like(w))
    # masked lanes -> 0 so that no NaN reaches a product (gradients of where are where(use, g, 0))
    x1 = torch.where(use[..., None], p1, torch.zeros_like(p1))
    x2 = torch.where(use[..., None], p2, torch.zeros_like(p2))
    ok = use.sum(-1) >= _MIN_POINTS
    W = w.sum(-1, keepdim=True)
    W = torch.where(ok[:, None], W, torch.ones_like(W))

    def _normalise(x):
        c = (w[..., None] * x).sum(-2) / W  # (B, 2)
        d = x - c[:, None]
        r2 = (w * (d * d).sum(-1)).sum(-1, keepdim=True) / W  # weighted mean squared distance
        r2 = torch.where(ok[:, None] & (r2 > 0), r2, torch.ones_like(r2))
        s = torch.sqrt(2.0 / r2)  # (B, 1)
        return d * s[..., None], c, s[:, 0]

    n1, c1, s1 = _normalise(x1)
    n2, c2, s2 = _normalise(x2)
    A = _epipolar_rows(n1[..., 0], n1[..., 1], n2[..., 0], n2[..., 1])  # (B, N, 9)
    M = (A * w[..., None]).transpose(-1, -2) @ A  # (B, 9, 9)
    M = torch.where(ok[:, None, None], M, torch.eye(9, dtype=dtype, device=p1.device).expand_as(M) * torch.arange(1, 10, dtype=dtype, device=p1.device))
    f = torch.linalg.eigh(M).eigenvectors[..., 0]  # smallest eigenvalue
    Fh = f.view(-1, 3, 3)
    v = torch.linalg.eigh(Fh.transpose(-1, -2) @ Fh).eigenvectors[..., 0]  # (B, 3)
    Fh = Fh - (Fh @ v[..., None]) @ v[..., None, :]
    zero = torch.zeros_like(s1)
    one = torch.ones_like(s1)

    def _T(s, c):
        return torch.stack(
            [
                torch.stack([s, zero, -s * c[:, 0]], -1),
                torch.stack([zero, s, -s * c[:, 1]], -1),
                torch.stack([zero, zero, one], -1),
            ],
            -2,
        )

    F = _T(s2, c2).transpose(-1, -2) @ Fh @ _T(s1, c1)
    F = _canonical_sign(F)
    return torch.where(ok[:, None, None], F, torch.full_like(F, float("nan")))
