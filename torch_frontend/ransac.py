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

Capturable path (``capturable=True``; :func:`_find_fundamental_static`): shape-static, no host sync
after a warm-up call, a kernel count (~300) independent of B and of the data, for CUDA graphs and
``torch.compile``. The sample tables of every point count 8..N are built once and kept on the
device; every problem evaluates one fixed block of ``max_iters`` samples (its OpenCV bookkeeping
replayed with scans, so the same result; a smaller block reports ``overflow`` where OpenCV would
have drawn more); the 7-point null space comes from Gram-Schmidt instead of a batched QR. Memory:
~30 MB per problem of 150 points (float64 scores of 3000 models x 150 points); on the CPU it is
~15x slower than the default path, which stays the CPU's choice.

LO-RANSAC (``method="lo"``; :func:`_find_fundamental_lo`, :func:`_find_fundamental_lo_static`):
the same hypotheses and inlier test, each model OpenCV's loop accepts locally optimised (weighted
8-point refits), the adaptive bound from the optimised counts, a final refit. It keeps ~97 % of
the true inliers where OpenCV keeps ~87 % and its F is ~4x closer to the truth
(``benchmarks/results/fundamental_accuracy.md``). Its refits avoid the linalg ops that check
errors on the host (inverse iteration with ``lu_factor_ex``/``lu_solve``) and the batched
matmuls whose last bits depend on the batch, so a problem's result is the same in any batch, and
the capturable variant (a fixed budget of optimised models) is sync-free as well.
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
from ._compiler import outside_graphs

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
        overflow: ``(B,)`` bool, the capturable path's hypothesis block was too small for OpenCV's
            exact answer (it would have drawn more samples); the problem's other fields are then
            not OpenCV's. Always False on the default path and with the default block.
    """

    ok: torch.Tensor
    num_iters: torch.Tensor
    method: torch.Tensor

    def __new__(cls, F, inliers, ok, num_iters, method, overflow=None):
        self = super().__new__(cls, F, inliers)
        self.ok = ok
        self.num_iters = num_iters
        self.method = method
        self._overflow = overflow
        return self

    @property
    def overflow(self) -> torch.Tensor:
        # made on first use: the default path (never overflows) does not pay a kernel for it
        if self._overflow is None:
            self._overflow = torch.zeros_like(self.ok)
        return self._overflow

    def __reduce__(self):
        return (FundamentalResult, (self.F, self.inliers, self.ok, self.num_iters, self.method, self._overflow))


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


def _solve_cubic_opencv(c: torch.Tensor, *, full: bool = False, phases: torch.Tensor | None = None):
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

    ``full``: evaluate the rare branches always (no host check; the capturable path); ``phases``:
    :data:`_CUBIC_PHASES` already on ``c``'s device and dtype (no upload per call).
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
    if phases is None:
        phases = _CUBIC_PHASES.to(c.device, c.dtype)
    x3 = (-2.0 * torch.sqrt(Q))[..., None] * torch.cos((theta * (1.0 / 3.0))[..., None] + phases) - t2[..., None]
    # d < 0: one root
    e = (torch.sqrt(-d) + R.abs()).pow(1.0 / 3.0)
    e = torch.where(R > 0, -e, e)
    zero = torch.zeros_like(mc)
    roots = torch.where(three[..., None], x3, torch.stack([(e + Q / e) - t2, zero, zero], -1))
    ok = torch.stack([cubic, three, three], -1)
    # rare branches (a double root, a negligible c0): on the CPU skipped when no lane needs them
    # (a free check there; elsewhere it would be a host sync)
    dbl = cubic & (d == 0)
    if full or not _tuning.for_device(c.device).host_checks_free or bool((dbl | ~cubic).any()):
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
    capturable: bool = False,
    method: str = "opencv",
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
        capturable: shape-static and free of host syncs after a first call with the same seeds,
            N, ``max_iters`` and ``confidence`` (CUDA graphs, ``torch.compile``): every problem
            evaluates a fixed block of ``batch_hypotheses`` samples (default and at most
            ``max_iters``: exact); the result is the default path's (``F`` up to rounding)
            wherever ``overflow`` is False. Memory ~30 MB per problem of 150 points at the
            default block.
        method: ``"opencv"`` (default): OpenCV's FM_RANSAC exactly, the convention below.
            ``"lo"``: LO-RANSAC on the same hypotheses, see "LO-RANSAC" below.

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

    LO-RANSAC (``method="lo"``, n >= 15; 8..14 points get the LMedS result above):
        * Hypotheses, their order and the inlier test are OpenCV's (the same samples, 7-point
          models and ``max(d1^2, d2^2) <= threshold^2``). OpenCV's loop is replayed, but every
          model it accepts (more inliers than the current best, at least 7) is locally optimised:
          3 iteratively reweighted 8-point refits on its inliers (unit weights, then Sampson
          weights; Hartley-normalised over all valid points; the last one rank 2, kept if it has
          at least as many inliers as the hypothesis), each re-scored for the next refit's inliers.
        * The optimised inlier count is the new best: later hypotheses must beat it, and the
          iteration bound is OpenCV's ``RANSACUpdateNumIters(confidence, (n - count) / n, 7,
          bound)`` with it (LO counts are higher, so the loop stops earlier than OpenCV's).
        * Final refit, on the points as given and the best model's inliers, Sampson-weighted: an
          8-point refit (``refit_fundamental``'s normalisation and rank-2 rule), then one with its
          epipole held fixed (rank 2 without a projection: Hartley & Zisserman's algebraic
          minimisation); ``F`` is it and ``inliers`` its inliers (OpenCV's test) unless it has
          fewer inliers than the best optimised model (degenerate data), which is then kept. ``F``
          is differentiable w.r.t. ``p1, p2`` through the final refit (mask and the weights' model
          held fixed).
        * ``capturable``: a fixed budget of 4 optimised models per problem in OpenCV's order plus
          one more (the best remaining hypothesis); ``overflow`` where OpenCV's loop would have
          accepted another model or drawn past the block. Elsewhere the result is the default
          path's (masks, ``ok``, ``num_iters``, ``method`` exactly, ``F`` up to rounding).
        * Memory and speed: as the OpenCV path (the loop stops earlier, and each accepted model
          costs a local optimisation; ``benchmarks/bench_fundamental_accuracy.py``).

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
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    states = _seeds(valid.shape[0], generator, seed)
    return _find_fundamental_impl(p1, p2, valid, float(threshold), float(confidence), max_iters, states, H,
                                  capturable=capturable, method=method)


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
    *,
    capturable: bool = False,
    method: str = "opencv",
) -> FundamentalResult:
    """:func:`find_fundamental` without input checks.

    Args:
        p1, p2: ``(B, N, 2)`` float, pixels ``(x, y)``, matched slot by slot.
        valid: ``(B, N)`` bool.
        threshold: inlier distance in pixels, > 0 (the public function maps ``<= 0`` to 3).
        confidence: in ``(0, 1)`` (the public function maps other values to 0.99).
        max_iters: cap on minimal samples per problem.
        states: B ``cv::RNG`` states as Python ints (:func:`_seeds`).
        batch_hypotheses: largest round (>= 1), or None for the memory budget. With
            ``capturable``: the block of minimal samples per problem (None: ``max_iters``, exact).
        capturable: the shape-static, host-sync-free path (:func:`_find_fundamental_static`): the
            same ``F`` (up to rounding), ``inliers``, ``ok``, ``num_iters`` and ``method`` wherever
            its ``overflow`` is False.
        method: ``"opencv"`` (OpenCV's FM_RANSAC, exactly) or ``"lo"`` (LO-RANSAC, see
            :func:`find_fundamental`; :func:`_find_fundamental_lo` and, with ``capturable``,
            :func:`_find_fundamental_lo_static`).

    Returns:
        :class:`FundamentalResult`, as :func:`find_fundamental`.
    """
    if method != "opencv":
        if method != "lo":
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        lo = _find_fundamental_lo_static if capturable else _find_fundamental_lo
        return lo(p1, p2, valid, threshold, confidence, max_iters, states, batch_hypotheses)
    if capturable:
        return _find_fundamental_static(p1, p2, valid, threshold, confidence, max_iters, states, batch_hypotheses)
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
# the capturable path: one static block of hypotheses per problem, no host syncs
# ----------------------------------------------------------------------------------------------
#: The capturable path scores the block's RANSAC models in this many pieces (a fixed number, so
#: the kernel count does not depend on B). Memory knob only: measured at N = 150, K = 1000 (CPU,
#: peak per problem): 1 piece 28 MB, 297 kernels; 4 pieces 14 MB, 326 kernels.
_STATIC_SCORE_CHUNKS = 1
_STATIC_CACHE: dict = {}  # (states, N, K, max_iters, confidence, device) -> _StaticTables
_STATIC_CACHE_SIZE = 8  # a tracker needs one entry; first in, first out beyond this
_STATE_SAMPLES: dict = {}  # (state, N, K) -> (N - 7, K, 7) int64 numpy: one state's sample tables
_STATE_SAMPLES_SIZE = 16  # host memory: 8 MB each for N = 150, K = 1000; first in, first out
_STATIC_CONSTS: dict = {}  # device -> _StaticConsts
_LMEDS_ITERS: dict = {}  # (confidence, max_iters) -> int


class _StaticTables(NamedTuple):
    """Device tables of one capturable configuration (see :func:`_static_tables`)."""

    idx: torch.Tensor  # (S * (N - 7), K, 7) int64: the first K subsets of (state s, n) at row s * (N - 7) + n - 8
    state_row: torch.Tensor | None  # (B,) int64: s * (N - 7) for each problem's state; None when S == 1
    niters: torch.Tensor  # (N + 1, N + 2) int64: the iteration bound with best count b at n points, [n, b + 1]
    per_n: torch.Tensor  # (N + 1, 4) int64 per point count n: table row, n (N + 2) + 1, median rank, method
    sigma: torch.Tensor  # (N + 1,) float64: LMedS's 2.5 * 1.4826 * (1 + 5 / max(n - 7, 1))
    ar1: torch.Tensor  # (K,) int64: 1, 2, ..., K (samples drawn after each sample of the block)
    block: torch.Tensor  # () int64: K


class _StaticConsts(NamedTuple):
    """Small device constants of the capturable path (see :func:`_static_consts`)."""

    null_rows: torch.Tensor  # (2, 9): OpenCV's SVD completion vectors r7, r8 (_opencv_null_seeds)
    basis: torch.Tensor  # (2, 2): [u; w] -> [u - w; w], i.e. [f1 - f2; f2]
    cubic_scale: torch.Tensor  # (4,): <cof F_p, F_q> -> cubic coefficients (det F = <cof F, F> / 3)
    phases: torch.Tensor  # (3,): _CUBIC_PHASES
    select: torch.Tensor  # (9, 45): a row-major F -> its 5 scoring rows (_score_rows)
    eye23: torch.Tensor  # (2, 3): the s-part of rows 0, 1 of a normalisation's T^T
    one: torch.Tensor  # () float64 1 (0-dim operands of torch.where: no scalar_tensor launch)
    zero: torch.Tensor  # () float64 0
    inf: torch.Tensor  # () float64 inf
    nan: torch.Tensor  # () float64 nan
    minus_one: torch.Tensor  # () int32 -1


def _static_consts(device: torch.device) -> _StaticConsts:
    """The capturable path's constants on ``device``, uploaded once. (The caches of this path are
    plain dicts read without a lock, their builders kept out of ``torch.compile`` graphs: a
    steady-state call traces to dict look-ups, with no graph break.)"""
    k = _STATIC_CONSTS.get(device)
    return _build_static_consts(device) if k is None else k


@outside_graphs
def _build_static_consts(device: torch.device) -> _StaticConsts:
    """:func:`_static_consts`' cache miss (outside compiled graphs)."""
    f64 = dict(dtype=torch.float64, device=device)
    # scoring rows (see _score_rows): with o = h2 (x) h1 (entry 3 i + j) the outer product of a
    # point pair, x2^T F x1 = sum_q o_q F_q; (F x1)_r = sum_j o_{6 + j} F_{3 r + j} (h2_2 = 1 at a
    # valid point); (F^T x2)_c = sum_i o_{3 i + 2} F_{3 i + c} (h1_2 = 1)
    sel = torch.zeros(9, 5, 9, dtype=torch.float64)
    for q in range(9):
        sel[q, 0, q] = 1.0
    for r in range(2):
        for j in range(3):
            sel[3 * r + j, 1 + r, 6 + j] = 1.0
    for c in range(2):
        for i in range(3):
            sel[3 * i + c, 3 + c, 3 * i + 2] = 1.0
    scalar = dict(device=device)
    k = _StaticConsts(
        null_rows=_OPENCV_NULL_SEEDS.T.contiguous().to(device),
        basis=torch.tensor([[1.0, -1.0], [0.0, 1.0]], **f64),
        cubic_scale=torch.tensor([1.0 / 3.0, 1.0, 1.0, 1.0 / 3.0], **f64),
        phases=_CUBIC_PHASES.to(device),
        select=sel.view(9, 45).to(device),
        eye23=torch.eye(2, 3, **f64),
        one=torch.tensor(1.0, **f64),
        zero=torch.tensor(0.0, **f64),
        inf=torch.tensor(math.inf, **f64),
        nan=torch.tensor(math.nan, **f64),
        minus_one=torch.tensor(-1, dtype=torch.int32, **scalar),
    )
    with _STREAM_LOCK:
        return _STATIC_CONSTS.setdefault(device, k)


def _static_tables(states: Sequence[int], N: int, K: int, max_iters: int, confidence: float,
                   device: torch.device) -> _StaticTables:
    """OpenCV's samples and iteration bounds for a capturable call, on ``device``: the first ``K``
    subsets of the sample stream of every point count ``n`` in ``[8, N]`` and every distinct state
    of ``states``, and ``RANSACUpdateNumIters`` for every ``(n, best count)``. Built once (on the
    host, under the stream lock) and cached per ``(states, N, K, max_iters, confidence, device)``;
    a steady-state call is a dict look-up (no lock, no upload). The tracker passes one state for
    all problems (OpenCV re-seeds identically on every call), so the tables depend on n only."""
    key = (tuple(states), N, K, max_iters, confidence, device)
    tab = _STATIC_CACHE.get(key)
    return _build_static_tables(key) if tab is None else tab


@outside_graphs
def _build_static_tables(key) -> _StaticTables:
    """:func:`_static_tables`' cache miss (outside compiled graphs; under the stream lock)."""
    states, N, K, max_iters, confidence, device = key
    with _STREAM_LOCK:
        tab = _STATIC_CACHE.get(key)
        if tab is not None:
            return tab
        uniq = list(dict.fromkeys(states)) or [_state_of(OPENCV_SEED)]  # (B = 0: any table)
        rows = N - _MODEL_POINTS  # n = 8 .. N
        idx = np.stack([_state_samples(st, N, K) for st in uniq])
        state_row = None
        if len(uniq) > 1:
            pos = {st: s * rows for s, st in enumerate(uniq)}
            state_row = torch.tensor([pos[st] for st in states], dtype=torch.int64, device=device)
        niters = _niters_table(N, max_iters, confidence)
        ns = torch.arange(N + 1, dtype=torch.int64)
        per_n = torch.stack([
            (ns - _MIN_POINTS).clamp(0, N - _MIN_POINTS),  # the table row (before the state offset)
            ns * (N + 2) + 1,  # + best count = the index into niters
            (ns // 2).clamp(max=min(N, _MIN_RANSAC_POINTS - 1) - 1),  # LMedS: OpenCV's upper median
            (ns >= _MIN_POINTS).to(torch.int64) + (ns >= _MIN_RANSAC_POINTS).to(torch.int64),  # METHOD_*
        ], -1)
        # _robust_group's very expression (so the same float64 values)
        sigma = 2.5 * 1.4826 * (1.0 + 5.0 / (ns - _MODEL_POINTS).clamp_min(1).to(torch.float64))
        tab = _StaticTables(
            idx=torch.from_numpy(idx.reshape(-1, K, _MODEL_POINTS)).to(device),
            state_row=state_row,
            niters=niters.to(device),
            per_n=per_n.to(device),
            sigma=sigma.to(device),
            ar1=torch.arange(1, K + 1, dtype=torch.int64, device=device),
            block=torch.tensor(K, dtype=torch.int64, device=device),
        )
        while len(_STATIC_CACHE) >= _STATIC_CACHE_SIZE:
            _STATIC_CACHE.pop(next(iter(_STATIC_CACHE)))
        _STATIC_CACHE[key] = tab
        return tab


def _niters_table(N: int, max_iters: int, confidence: float) -> torch.Tensor:
    """OpenCV's iteration bound for every point count and best inlier count, ``(N + 1, N + 2)``
    int64 on the host: entry ``[n, b + 1]`` is the bound after a sample whose running best count is
    b (-1: no model yet): max_iters unless b > 6 (OpenCV: goodCount > max(maxGoodCount,
    modelPoints - 1)), else ``RANSACUpdateNumIters(conf, (n - b) / n, 7, bound)``. With one cap
    (max_iters) instead of the running bound: the same integers, as the bound only shrinks (see
    _robust_group, whose ep expression this is, so the values are its own)."""
    cap = max(int(max_iters), 1)
    nf = torch.arange(N + 1, dtype=torch.float64)[:, None]
    b = torch.arange(-1, N + 1, dtype=torch.float64)[None, :]
    it = ransac_update_num_iters(confidence, (nf - b) / nf, _MODEL_POINTS,  # (n = 0: unused garbage)
                                 torch.full((N + 1, N + 2), cap, dtype=torch.int64))
    return torch.where(b > _MODEL_POINTS - 1, it, cap)


def _state_samples(state: int, N: int, K: int) -> np.ndarray:
    """The first ``K`` subsets of ``cv::RNG(state)``'s stream for every n in ``[8, N]``, ``(N - 7,
    K, 7)`` int64 (host; cached, so calls of different B with one state share the ~5 ms per n of
    generation). Called under ``_STREAM_LOCK``."""
    key = (state, N, K)
    tab = _STATE_SAMPLES.get(key)
    if tab is None:
        tab = np.empty((N - _MODEL_POINTS, K, _MODEL_POINTS), dtype=np.int64)
        for r in range(N - _MODEL_POINTS):  # not through _SUBSET_CACHE: each stream is read once
            tab[r] = _SubsetStream(state, r + _MIN_POINTS).upto(K)[:K]
        while len(_STATE_SAMPLES) >= _STATE_SAMPLES_SIZE:
            _STATE_SAMPLES.pop(next(iter(_STATE_SAMPLES)))
        _STATE_SAMPLES[key] = tab
    return tab


def _lmeds_iters(confidence: float, max_iters: int) -> int:
    """OpenCV's LMedS sample count ``max(3, RANSACUpdateNumIters(confidence, 0.45, 7, max_iters))``
    as ``_robust_group`` computes it (cached: no host tensors per capturable call)."""
    it = _LMEDS_ITERS.get((confidence, max_iters))
    return _build_lmeds_iters(confidence, max_iters) if it is None else it


@outside_graphs
def _build_lmeds_iters(confidence: float, max_iters: int) -> int:
    """:func:`_lmeds_iters`' cache miss (outside compiled graphs)."""
    it0 = ransac_update_num_iters(
        confidence, torch.tensor(_LMEDS_OUTLIER_RATIO), _MODEL_POINTS, torch.tensor(max(int(max_iters), 1))
    )
    return _LMEDS_ITERS.setdefault((confidence, max_iters), max(int(it0), 3))


def _solve_cubic_static(c: torch.Tensor, k: _StaticConsts):
    """:func:`_solve_cubic_opencv` (every branch) in fewer kernels, for the capturable path: the
    same operations on every value it returns, so the same ``ok`` and, where ok, the same roots bit
    for bit; roots where not ok are garbage (not zero). ``c (M, 4)`` float64."""
    ac = c.abs()
    mc = ac.amax(-1)
    big = (ac >= (_DBL_EPSILON * mc)[:, None]) & (mc >= _DBL_EPSILON)[:, None]  # |c_k| >= eps m, m >= eps
    cubic = big[:, 0]
    cs = c * mc.reciprocal()[:, None]  # x.reciprocal() == 1.0 / x: the same bits
    a1, a2, a3 = (cs[:, 1:] * cs[:, 0].reciprocal()[:, None]).unbind(-1)
    a11 = a1 * a1
    Q = (a11 - 3.0 * a2) * (1.0 / 9.0)
    a3_27 = 27.0 * a3
    R = (a1 * (2.0 * a1 * a1 - 9.0 * a2) + a3_27) * (1.0 / 54.0)
    two_a2 = 2.0 * a2
    d = (a11 * (a2 * a2 - 4.0 * a1 * a3) + two_a2 * (9.0 * a1 * a3 - two_a2 * a2) - a3_27 * a3) * (1.0 / 108.0)
    three = cubic & (d > 0)
    dbl = cubic & (d == 0)
    t2 = a1 * (1.0 / 3.0)
    theta = torch.acos(R / torch.sqrt(Q * Q * Q))
    x3 = (-2.0 * torch.sqrt(Q))[:, None] * torch.cos((theta * (1.0 / 3.0))[:, None] + k.phases) - t2[:, None]
    aR = R.abs()
    e = (torch.sqrt(-d) + aR).pow(1.0 / 3.0)
    e = torch.where(R > 0, -e, e)
    cr = torch.sign(R) * aR.pow(1.0 / 3.0)  # _cbrt(R)
    a13 = a1 / 3.0
    y0, y1 = -2.0 * cr - a13, cr - a13
    roots = torch.where(three[:, None], x3, torch.stack([torch.where(dbl, y0, (e + Q / e) - t2), y1, y1], -1))
    ok = torch.stack([cubic, three | (dbl & (y0 != y1)), three], -1)
    # negligible c0: the quadratic of the unscaled coefficients, or the linear root
    c1, c2, c3 = c[:, 1], c[:, 2], c[:, 3]
    quad = big[:, 1] & ~cubic
    lin = big[:, 2] & ~(cubic | big[:, 1])
    qd = c2 * c2 - 4.0 * c1 * c3
    sqd = torch.sqrt(qd)
    q1 = (-c2 + sqd) * 0.5
    q2 = (c2 + sqd) * -0.5
    q = torch.where(q1.abs() > q2.abs(), q1, q2)
    qroots = torch.stack([torch.where(quad, q / c1, -c3 / c2), c3 / q, q], -1)
    qok = torch.stack([torch.where(quad, qd >= 0, lin), quad & (qd > 0), cubic], -1)
    roots = torch.where(cubic[:, None], roots, qroots)
    return roots, torch.where(cubic[:, None], ok, qok) & (roots.abs() < math.inf)


def _run_7point_static(m: torch.Tensor, k: _StaticConsts):
    """:func:`_run_7point` without a factorisation: ``m (M, 7, 2, 2)`` float64 -> ``F (M, 3, 9)``
    (row-major, unit Frobenius norm; garbage where not ok) and ``ok (M, 3)`` (a real root, a usable
    normalisation, a finite model, the sample not degenerate), in OpenCV's model order.

    The same models as :func:`_run_7point` up to rounding: the same normalisation and 7x9 system
    (bit for bit) and collinearity test; OpenCV's null-space basis (``f1 ~ P r7``, ``f2`` the unit
    vector of ``P r8`` orthogonal to ``f1``, P the projection onto the null space) from modified
    Gram-Schmidt on the rows ``[A; r7; r8]`` (7 fixed steps of three batched ops and one
    re-orthogonalisation; what is left of r7 and r8 is ``P r7`` and ``P r8``) instead of a complete
    QR, which loops per matrix on CUDA; the cubic's coefficients ``<cof F_p, F_q>`` of
    both basis models in one matmul; its roots :func:`_solve_cubic_opencv`'s (every branch
    evaluated, no host check: :func:`_solve_cubic_static`).
    """
    M = m.shape[0]
    degenerate = _collinear_last(m).any(-1)
    c = m.mean(1, keepdim=True)  # (M, 1, 2, 2)
    dm = m - c
    s = dm.norm(dim=-1).mean(1)  # (M, 2)
    good = (s >= _FLT_EPSILON).all(-1)
    s = math.sqrt(2.0) / torch.where(good[:, None], s, k.one)
    nm = dm * s[:, None, :, None]
    h = torch.nn.functional.pad(nm, (0, 1), value=1.0)  # (M, 7, image, 3)
    A = (h[:, :, 1, :, None] * h[:, :, 0, None, :]).flatten(-2)  # (M, 7, 9): _epipolar_rows' order
    R = torch.cat([A, k.null_rows.expand(M, 2, 9)], 1)  # (M, 9, 9)
    qs = []
    for _ in range(_MODEL_POINTS):  # modified Gram-Schmidt: remove row 0 from the rows below it
        g = R @ R[:, :1].transpose(-1, -2)  # (M, rows, 1): <r_0, r_i>
        qs.append(R[:, 0])
        R = torch.baddbmm(R[:, 1:], g[:, 1:] / g[:, :1], R[:, :1], alpha=-1.0)
    # one more (classical) projection against the orthogonalised rows ("twice is enough"): the
    # residual |A P r| drops from ~eps cond(A) |A| |r| (1e-12 on tracker-like samples) to ~eps
    Qr = torch.stack(qs, 1)  # (M, 7, 9)
    R = torch.baddbmm(R, (R @ Qr.transpose(-1, -2)) / (Qr * Qr).sum(-1)[:, None], Qr, alpha=-1.0)
    # R = [P r7; P r8]: u ~ P r7, w the part of P r8 orthogonal to u, both unit
    G = R @ R.transpose(-1, -2)  # (M, 2, 2)
    w = torch.addcmul(R[:, 1], R[:, 0], (G[:, 1, 0] / G[:, 0, 0])[:, None], value=-1.0)
    uw = torch.stack([R[:, 0], w], 1)
    uw = uw / uw.norm(dim=-1, keepdim=True)
    Fab = k.basis @ uw  # (M, 2, 9): Fa = u - w = f1 - f2, Fb = w = f2; F(alpha) = alpha Fa + Fb
    F3 = Fab.view(M, 2, 3, 3)
    cof = torch.linalg.cross(F3.roll(-1, -2), F3.roll(-2, -2), dim=-1)  # rows r1 x r2, r2 x r0, r0 x r1
    # det(alpha Fa + Fb) = alpha^3 det Fa + alpha^2 <cof Fa, Fb> + alpha <cof Fb, Fa> + det Fb
    coeffs = (cof.view(M, 2, 9) @ Fab.transpose(-1, -2)).view(M, 4) * k.cubic_scale
    roots, rok = _solve_cubic_static(coeffs, k)  # (M, 3), OpenCV's order
    Fn = torch.addcmul(Fab[:, 1:], roots[..., None], Fab[:, :1])  # (M, 3, 9)
    # de-normalise: F = T2^T Fn T1, i.e. vec(F) = (T2^T (x) T1^T) vec(Fn), with T^T = [[s, 0, 0],
    # [0, s, 0], [-s cx, -s cy, 1]] per image
    top = s[..., None, None] * k.eye23  # (M, 2, 2, 3)
    bot = torch.nn.functional.pad(c[:, 0] * -s[..., None], (0, 1), value=1.0)  # (M, 2, 3)
    Tt = torch.cat([top, bot[:, :, None]], 2)  # (M, image, 3, 3)
    kron = (Tt[:, 1, :, None, :, None] * Tt[:, 0, None, :, None, :]).view(M, 9, 9)
    F = Fn @ kron.transpose(-1, -2)  # (M, 3, 9)
    nrm = F.norm(dim=-1)  # (M, 3)
    # _run_7point's nrm > 0 holds: alpha Fa + Fb = alpha u + (1 - alpha) w != 0 (u, w orthonormal)
    ok = rok & (good & ~degenerate)[:, None] & (nrm < math.inf)
    return F / nrm[..., None], ok


def _score_rows(F: torch.Tensor, k: _StaticConsts) -> torch.Tensor:
    """``F (B, K, 9)`` row-major models -> ``(B, 5, K, 9)`` rows mapping a point pair's outer product
    ``h2 (x) h1`` to ``x2^T F x1, (F x1)_0, (F x1)_1, (F^T x2)_0, (F^T x2)_1`` (a 0/1 selection: exact),
    so that one batched matmul scores every model on every point (five planes: contiguous passes)."""
    B, K = F.shape[:2]
    return (F.reshape(B * K, 9) @ k.select).view(B, K, 5, 9).transpose(1, 2).contiguous()


def _score_terms(rows: torch.Tensor, outer: torch.Tensor):
    """``rows (B, 5, K, 9)`` (:func:`_score_rows`, or a slice of it) on ``outer (B, N, 9)`` ->
    ``d2 = (x2^T F x1)^2`` and ``smin = min(|(F x1)_xy|^2, |(F^T x2)_xy|^2)`` (``_epipolar_terms``'),
    each ``(B, K, N)``; both 0 at masked-out slots (their outer product is 0)."""
    B, _, K = rows.shape[:3]
    o = torch.bmm(rows.reshape(B, 5 * K, 9), outer.transpose(1, 2))
    o = o.mul_(o).view(B, 5, K, outer.shape[1])
    l2 = o[:, 1] + o[:, 2]
    return o[:, 0], torch.minimum(o[:, 3] + o[:, 4], l2, out=l2)


def _canonical_sign_unit(F: torch.Tensor) -> torch.Tensor:
    """:func:`_canonical_sign` of unit-norm ``F (B, 9)``: the sign only (3 kernels fewer)."""
    return F * F.gather(-1, F.abs().argmax(-1, keepdim=True)).sign()


def _find_fundamental_static(p1, p2, valid, threshold, confidence, max_iters, states, block):
    """:func:`_find_fundamental_impl` with ``capturable=True``: static shapes, no host syncs after a
    warm-up call with the same ``(states, N, max_iters, confidence, block)``, a kernel count
    independent of B and of the data.

    Every problem takes the first ``K`` samples of its OpenCV stream (``K = block``; default and at
    most ``max_iters``, which is exact) from one table look-up (:func:`_static_tables`, for both
    methods) and all are solved in one batched 7-point call. RANSAC scores the ``3 K`` models on
    all points (``_STATIC_SCORE_CHUNKS`` batched matmuls) and replays OpenCV's loop with scans over
    the block: the running best count (``cummax``), the iteration bound after every sample (a table
    look-up), the first sample that reaches its bound, the first strictly better model up to it.
    That is ``_robust_group`` in one round, hence its result. LMedS scores the first ``min(K, L)``
    samples (``L = _lmeds_iters``, 300 for VINS) on the first 14 valid points (all of an 8..14
    point problem's). Both branches run on the whole batch; ``torch.where`` picks by point count.

    ``overflow``: a RANSAC problem that did not reach its bound within ``K`` samples, or an LMedS
    problem when ``K < L``; never with the default block.
    """
    sp = _static_front(p1, p2, valid, confidence, max_iters, states, block)
    if isinstance(sp, FundamentalResult):  # N < 8
        return sp
    F, inl, ok, iters, overflow = _static_lmeds(sp)
    if sp.has_r:
        # RANSAC (>= 15 points): the inlier count of every model, then OpenCV's loop replayed
        B, N, K, k, tabs, per_n, is_r = sp.B, sp.N, sp.K, sp.k, sp.tabs, sp.per_n, sp.is_r
        mask, cnt = _static_counts(sp, threshold * threshold)
        cnt = cnt.view(B, K, 3)
        run_best = torch.cummax(cnt.amax(-1), 1).values  # the best count after each sample
        n_after = tabs.niters.take(run_best + per_n[:, 1, None])  # the bound after each sample
        reached, i_stop = (tabs.ar1 >= n_after).to(torch.int8).max(1)  # OpenCV: iter < niters
        used = torch.where(reached > 0, i_stop + 1, tabs.block)
        cm = torch.where((tabs.ar1 <= used[:, None])[..., None], cnt, k.minus_one).view(B, 3 * K)
        cand, k_r = cm.max(-1)  # first maximum: OpenCV's sequential strict ">"
        F = torch.where(is_r[:, None], sp.Fm.gather(1, k_r[:, None, None].expand(-1, 1, 9))[:, 0], F)
        inl = torch.where(is_r[:, None], mask.gather(1, k_r[:, None, None].expand(-1, 1, N))[:, 0], inl)
        ok = torch.where(is_r, cand > _MODEL_POINTS - 1, ok)
        iters = torch.where(is_r, used, iters)
        over_r = is_r & (reached == 0)
        overflow = over_r if overflow is None else overflow | over_r
    return _static_result(sp, F, inl, ok, iters, overflow, p1.dtype)


class _StaticFront(NamedTuple):
    """What both capturable estimators share (:func:`_static_front`): the problems' points, their
    first ``Kt`` OpenCV samples solved, the models' scoring rows."""

    B: int
    N: int
    K: int  # RANSAC block (samples per problem)
    K_l: int  # LMedS samples scored
    L: int  # OpenCV's LMedS sample count
    has_r: bool  # N >= 15: some problem may run RANSAC
    k: _StaticConsts
    tabs: _StaticTables
    x12: torch.Tensor  # (B, N, 4) float64 (x1, y1, x2, y2), float32-rounded, zero at masked-out slots
    eff: torch.Tensor  # (B, N) bool: valid and finite
    n: torch.Tensor  # (B,) int64 valid, finite points
    per_n: torch.Tensor  # (B, 4) int64: tabs.per_n of n
    ge8: torch.Tensor  # (B,) bool: n >= 8
    is_r: torch.Tensor  # (B,) bool: n >= 15 (RANSAC)
    order: torch.Tensor  # (B, N) int64: valid slots first (valid_first_order)
    Fm: torch.Tensor  # (B, 3 Kt, 9) float64 models, row-major (garbage where not fok)
    fok: torch.Tensor  # (B, 3 Kt) bool
    rows: torch.Tensor  # (B, 5, 3 Kt, 9): _score_rows of Fm
    outer: torch.Tensor  # (B, N, 9): h2 (x) h1, 0 at masked-out slots


def _static_front(p1, p2, valid, confidence, max_iters, states, block):
    """The first part of :func:`_find_fundamental_static` (shared with the capturable LO-RANSAC):
    a :class:`_StaticFront`, or the final :class:`FundamentalResult` when ``N < 8``."""
    B, N = valid.shape
    dev, out_dtype = p1.device, p1.dtype
    f64 = torch.float64
    M = max(int(max_iters), 1)
    K = M if block is None else max(1, min(int(block), M))
    L = _lmeds_iters(confidence, max_iters)
    K_l = min(K, L)
    has_r = N >= _MIN_RANSAC_POINTS
    Kt = K if has_r else K_l  # samples solved per problem

    # OpenCV rounds the points to float32; the solver runs in float64 (as _find_fundamental_impl).
    # A sum of float32-range values is finite iff all are (no overflow in float64)
    x12 = torch.cat([p1.detach(), p2.detach()], -1).to(torch.float32).to(f64)  # (B, N, 4)
    eff = valid & (x12.sum(-1).abs() < math.inf)
    n = eff.sum(-1)
    if N < _MIN_POINTS:  # static: no problem can estimate
        z = torch.zeros_like(eff[:, 0]) if N else torch.zeros(B, dtype=torch.bool, device=dev)
        F = torch.full((B, 3, 3), math.nan, dtype=out_dtype, device=dev)
        return FundamentalResult(F, eff, z, torch.zeros_like(n), z.to(torch.int8), z)
    k = _static_consts(dev)
    tabs = _static_tables(states, N, Kt, M, confidence, dev)
    per_n = tabs.per_n.index_select(0, n)  # (B, 4): row, niters offset, median rank, method
    ge8 = per_n[:, 3] > METHOD_NONE
    is_r = per_n[:, 3] > METHOD_LMEDS
    x12 = torch.where(eff[..., None], x12, k.zero)  # finite everywhere (both where branches are evaluated)

    # the samples: positions among the valid points in slot order (OpenCV's arrays) -> slots
    row = per_n[:, 0] if tabs.state_row is None else per_n[:, 0] + tabs.state_row
    order = torch.sort(eff, dim=-1, descending=True, stable=True).indices  # valid_first_order
    slot = order.gather(1, tabs.idx.index_select(0, row).view(B, Kt * _MODEL_POINTS))
    smp = x12.gather(1, slot[..., None].expand(-1, -1, 4)).view(B * Kt, _MODEL_POINTS, 2, 2)
    Fm, fok = _run_7point_static(smp, k)
    Fm = Fm.view(B, Kt * 3, 9)
    fok = fok.view(B, Kt * 3)
    rows = _score_rows(Fm, k)  # (B, 5, 3 Kt, 9)
    # outer products h2 (x) h1 of the homogeneous points, 0 at masked-out slots (_homogeneous)
    h = torch.cat([x12.view(B, N, 2, 2), eff[:, :, None, None].expand(B, N, 2, 1).to(f64)], -1)
    outer = (h[:, :, 1, :, None] * h[:, :, 0, None, :]).flatten(-2)  # (B, N, 9)
    return _StaticFront(B, N, K, K_l, L, has_r, k, tabs, x12, eff, n, per_n, ge8, is_r, order, Fm, fok, rows,
                        outer)


def _static_lmeds(sp: _StaticFront):
    """LMedS (8..14 points) of the capturable path on every problem: ``F (B, 9)``, ``inl (B, N)``,
    ``ok``, ``iters`` and ``overflow`` (None when the block holds OpenCV's LMedS samples)."""
    N, K_l, L, k, tabs, per_n, n, eff, rows, outer = (sp.N, sp.K_l, sp.L, sp.k, sp.tabs, sp.per_n, sp.n, sp.eff,
                                                      sp.rows, sp.outer)
    # the median error of each model over the first 14 valid points
    Wd = min(N, _MIN_RANSAC_POINTS - 1)
    d2, smin = _score_terms(rows[:, :, : 3 * K_l], outer.gather(1, sp.order[:, :Wd, None].expand(-1, -1, 9)))
    # _epipolar_errors: inf where a line is degenerate (d2 / 0; 0 / 0 at masked-out slots)
    err = torch.nan_to_num(d2 / smin, nan=math.inf, posinf=math.inf)  # (B, 3 K_l, Wd)
    kth = per_n[:, 2, None, None].expand(-1, 3 * K_l, 1)
    med = err.sort(dim=-1).values.gather(2, kth)[..., 0].clamp_min_(_LMEDS_EXACT_FIT)  # see _robust_group
    cand_l, k_l = torch.where(sp.fok[:, : 3 * K_l], med, k.inf).min(-1)  # first minimum: OpenCV's "<"
    have = cand_l < math.inf
    best = rows.gather(2, k_l[:, None, None, None].expand(-1, 5, 1, 9))  # (B, 5, 1, 9)
    d2, smin = _score_terms(best, outer)
    err = torch.nan_to_num(d2[:, 0] / smin[:, 0], nan=math.inf, posinf=math.inf)  # (B, N)
    sigma = (tabs.sigma.index_select(0, n) * torch.where(have, cand_l, k.zero).sqrt()).clamp_min_(0.001)
    inl = (err.to(torch.float32) <= (sigma * sigma).to(torch.float32)[:, None]) & eff
    ok = have & (inl.sum(-1) >= _MODEL_POINTS) & sp.ge8
    F = sp.Fm.gather(1, k_l[:, None, None].expand(-1, 1, 9))[:, 0]
    iters = sp.ge8 * K_l
    overflow = sp.ge8 & ~sp.is_r if K_l < L else None
    return F, inl, ok, iters, overflow


def _static_counts(sp: _StaticFront, thr2: float):
    """RANSAC scoring of the block: the inlier masks ``(B, 3 K, N)`` of every model (OpenCV's test,
    ``_inlier_mask``'s) and the counts ``(B, 3 K)`` int32, -1 where a sample gave no model."""
    rows, outer, K = sp.rows, sp.outer, sp.K
    parts, step = [], -(-3 * K // _STATIC_SCORE_CHUNKS)
    for a in range(0, 3 * K, step):
        d2, smin = _score_terms(rows[:, :, a : a + step], outer)
        bound = smin if thr2 == 1.0 else smin * thr2
        parts.append((d2 <= bound) & (smin > 0))  # (B, models, N): _inlier_mask's test
    mask = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
    # int32 counts: a bool sum into int64 converts the whole mask first (10x slower on the CPU)
    return mask, torch.where(sp.fok, mask.sum(-1, dtype=torch.int32), sp.k.minus_one)  # -1: no model


def _static_result(sp: _StaticFront, F, inl, ok, iters, overflow, out_dtype) -> FundamentalResult:
    """The capturable path's :class:`FundamentalResult` from unit-norm ``F (B, 9)`` and the rest."""
    if overflow is None:
        overflow = torch.zeros_like(sp.ge8)
    F = torch.where(ok[:, None], _canonical_sign_unit(F), sp.k.nan).view(sp.B, 3, 3)
    return FundamentalResult(F.to(out_dtype), torch.where(ok[:, None], inl, sp.eff), ok, iters,
                             sp.per_n[:, 3].to(torch.int8), overflow)


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
    return _refit_impl(p1, p2, weights)


def _refit_impl(p1: torch.Tensor, p2: torch.Tensor, weights: torch.Tensor, warm: torch.Tensor | None = None,
                lk: _LOConsts | None = None) -> torch.Tensor:
    """:func:`refit_fundamental` without input checks. ``warm``: ``(B, 3, 3)`` a model near the
    solution (any scale; ``lk`` its device constants): both eigenvectors then come from the
    host-sync-free solvers :func:`_smallest_eigvec` (inverse iteration from ``warm``) and
    :func:`_rank2` instead of ``torch.linalg.eigh`` (the same matrix up to rounding where the
    smallest eigenvalue is well separated; near a degenerate (planar) configuration the member of
    the family of solutions closest to ``warm``)."""
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
    M = (A * w[..., None]).transpose(-1, -2) @ A if warm is None else _normal_matrix(A, w)  # (B, 9, 9)
    M = torch.where(ok[:, None, None], M, torch.eye(9, dtype=dtype, device=p1.device).expand_as(M) * torch.arange(1, 10, dtype=dtype, device=p1.device))
    zero = torch.zeros_like(s1)
    one = torch.ones_like(s1)
    if warm is None:
        f = torch.linalg.eigh(M).eigenvectors[..., 0]  # smallest eigenvalue
        Fh = f.view(-1, 3, 3)
        v = torch.linalg.eigh(Fh.transpose(-1, -2) @ Fh).eigenvectors[..., 0]  # (B, 3)
        Fh = Fh - (Fh @ v[..., None]) @ v[..., None, :]
    else:
        # the warm model in the normalised coordinates: Fn = T2^-T F T1^-1, T^-1 = [[1/s, 0, cx],
        # [0, 1/s, cy], [0, 0, 1]]
        def _Tinv(s, c):
            r = 1.0 / s
            return torch.stack([torch.stack([r, zero, c[:, 0]], -1), torch.stack([zero, r, c[:, 1]], -1),
                                torch.stack([zero, zero, one], -1)], -2)

        f0 = (_Tinv(s2, c2).transpose(-1, -2) @ warm.to(dtype) @ _Tinv(s1, c1)).reshape(-1, 9)
        Fh = _rank2(_smallest_eigvec(M, f0, lk, _EIG_POWER_FINAL).view(-1, 3, 3), lk)

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


# ----------------------------------------------------------------------------------------------
# LO-RANSAC (method="lo"): OpenCV's hypotheses and inlier test, each new best model locally
# optimised, the iteration bound from the optimised inlier counts, a final refit
# ----------------------------------------------------------------------------------------------
METHODS = ("opencv", "lo")
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
#: inverse iteration: solves with the shifted normal matrix per eigenvector, in a local
#: optimisation step (warm-started at the previous step; measured: 2..8 give the same recall and F
#: error) and in the final refit (converged to ~1e-12 from a 1e-2 start on tracker-like scenes)
_EIG_POWER_LO = 3
_EIG_POWER_FINAL = 8
#: relative shift of the normal matrix (keeps an exact null space invertible; eigenvectors unchanged)
_EIG_SHIFT = 1e-12
#: rank 2: power iteration on the adjugate of ``F^T F`` (dominant eigenvector = smallest of F^T F),
#: raised to the ``2^k``-th power by k squarings
_RANK2_SQUARINGS = 3
#: Sampson weights: the denominator is floored at this fraction of its mean over the inliers
_SAMPSON_FLOOR = 0.1
_LO_CONSTS: dict = {}  # device -> _LOConsts
_LO_BOUNDS: dict = {}  # (N, max_iters, confidence, device) -> (N + 1, N + 2) int64 iteration bounds
_LO_INDEX: dict = {}  # (start, count, device) -> (global model index, its sample index)


class _LOConsts(NamedTuple):
    """Device constants of LO-RANSAC (see :func:`_lo_consts`)."""

    shift: torch.Tensor  # (9, 9) float64: _EIG_SHIFT * I
    shift6: torch.Tensor  # (6, 6) float64: _EIG_SHIFT * I
    eye9: torch.Tensor  # (9, 9) float64: I
    eye3: torch.Tensor  # (3, 3) float64: I
    select: torch.Tensor  # (9, 45): _StaticConsts.select
    eye23: torch.Tensor  # (2, 3) float64
    zero: torch.Tensor  # () float64
    minus_one: torch.Tensor  # () int32 -1


def _lo_consts(device: torch.device) -> _LOConsts:
    k = _LO_CONSTS.get(device)
    return _build_lo_consts(device) if k is None else k


@outside_graphs
def _build_lo_consts(device: torch.device) -> _LOConsts:
    sk = _static_consts(device)
    eye9 = torch.eye(9, dtype=torch.float64, device=device)
    k = _LOConsts(shift=_EIG_SHIFT * eye9, shift6=_EIG_SHIFT * eye9[:6, :6].contiguous(), eye9=eye9,
                  eye3=eye9[:3, :3].contiguous(), select=sk.select,
                  eye23=sk.eye23, zero=sk.zero, minus_one=sk.minus_one)
    with _STREAM_LOCK:
        return _LO_CONSTS.setdefault(device, k)


def _lo_bounds(N: int, max_iters: int, confidence: float, device: torch.device) -> torch.Tensor:
    """:func:`_niters_table` on ``device`` (cached): the default path's bound look-up."""
    key = (N, max_iters, confidence, device)
    t = _LO_BOUNDS.get(key)
    if t is None:
        t = _niters_table(N, max_iters, confidence).to(device)
        with _STREAM_LOCK:
            while len(_LO_BOUNDS) >= _STATIC_CACHE_SIZE:
                _LO_BOUNDS.pop(next(iter(_LO_BOUNDS)))
            t = _LO_BOUNDS.setdefault(key, t)
    return t


def _lo_index(start: int, count: int, device: torch.device):
    """Models ``3 start .. 3 (start + count) - 1`` of a block: their global index and sample index,
    ``(3 count,)`` int64 each (cached: the capturable path's block is one constant)."""
    key = (start, count, device)
    t = _LO_INDEX.get(key)
    return _build_lo_index(key) if t is None else t


@outside_graphs
def _build_lo_index(key):
    start, count, device = key
    m = torch.arange(3 * start, 3 * (start + count), dtype=torch.int64, device=device)
    t = (m, torch.div(m, 3, rounding_mode="floor"))
    with _STREAM_LOCK:
        while len(_LO_INDEX) >= 64:
            _LO_INDEX.pop(next(iter(_LO_INDEX)))
        return _LO_INDEX.setdefault(key, t)


def _smallest_eigvec(M: torch.Tensor, f0: torch.Tensor, lk: _LOConsts, power: int) -> torch.Tensor:
    """Unit eigenvector of the smallest eigenvalue of symmetric PSD ``M (B, n, n)`` (n = 9, or 6 in
    :func:`_refit_fixed_epipole`) by inverse iteration from ``f0 (B, n)``, with no host sync: ``power`` solves with one LU factor of
    ``M / tr M + shift I`` (``lu_factor_ex``, no error check). The error shrinks by ``(mu1 + shift) /
    (mu2 + shift)`` per solve (mu the eigenvalues of ``M / tr M``); where the two smallest are
    (nearly) equal, as for a planar scene, the result stays near ``f0``'s component in that
    eigenspace. Vector solves, not an inverse: on the CPU ``inv_ex``, ``cholesky_solve`` and the
    9x9 ``bmm`` give a problem different last bits in different batches (the algorithm or the BLAS
    path depends on the batch and on memory alignment), ``lu_factor_ex`` / ``lu_solve`` of a
    vector do not. Differentiable (autograd through the factorisation and the solves)."""
    tr = M.diagonal(dim1=-2, dim2=-1).sum(-1)
    shift = lk.shift if M.shape[-1] == 9 else lk.shift6
    LU, piv, _ = torch.linalg.lu_factor_ex(torch.addcdiv(shift, M, tr[:, None, None]))
    f = f0[..., None]
    for _ in range(power):  # the norm grows to ~shift^-power (1e96 for 8): fine in float64
        f = torch.linalg.lu_solve(LU, piv, f)
    f = f[..., 0]
    return f / f.norm(dim=-1, keepdim=True)


def _normal_matrix(A: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``sum_i w_i a_i a_i^T`` for rows ``A (B, N, 9)`` and weights ``w (B, N)``: ``(B, 9, 9)`` as an
    elementwise product and a sum (the same bits for a problem in any batch, unlike ``bmm``)."""
    Aw = A * w[..., None]
    return (Aw[:, :, :, None] * A[:, :, None, :]).sum(1)


def _rank2(Fh: torch.Tensor, lk: _LOConsts) -> torch.Tensor:
    """``Fh (I - v v^T)`` for ``Fh (B, 3, 3)``, v the right singular vector of the smallest singular
    value (``refit_fundamental``'s rank-2 rule), with no host sync: v is the dominant eigenvector of
    the adjugate of ``S = Fh^T Fh`` (its eigenvalues are the products of pairs of S's, the largest
    belongs to S's smallest), by powers of the adjugate, from its row of largest norm. The result has
    rank <= 2 whatever the convergence (a projection); it is the closest rank-2 matrix when the
    ratio of the two smallest singular values is small (``(s3 / s2)^(2^(k+1))``)."""
    v = _null_vector(Fh)[:, None]  # (B, 1, 3)
    return torch.baddbmm(Fh, Fh @ v.transpose(-1, -2), v, alpha=-1.0)


def _null_vector(Fh: torch.Tensor) -> torch.Tensor:
    """:func:`_rank2`'s v, ``(B, 3)`` unit: the right singular vector of ``Fh``'s smallest singular
    value (of a rank-2 F: its right epipole, ``F v = 0``)."""
    S = Fh.transpose(-1, -2) @ Fh
    C = torch.linalg.cross(S.roll(-1, -2), S.roll(-2, -2), dim=-1)  # cofactors = adjugate (symmetric)
    for _ in range(_RANK2_SQUARINGS):
        C = C @ C
    v = C.gather(1, C.norm(dim=-1).argmax(-1)[:, None, None].expand(-1, 1, 3))[:, 0]
    return v / v.norm(dim=-1, keepdim=True)


def _refit_fixed_epipole(x1: torch.Tensor, x2: torch.Tensor, w: torch.Tensor, F: torch.Tensor,
                         lk: _LOConsts) -> torch.Tensor:
    """A weighted 8-point refit with ``F``'s right epipole held fixed (the algebraic minimisation of
    Hartley & Zisserman, sec. 11.3, one step): the rows of ``Fn`` are confined to the plane
    orthogonal to the epipole e, ``f = N g`` with ``N = I_3 (x) [u v]`` (u, v an orthonormal basis of
    that plane), and g is the smallest eigenvector of ``N^T M N`` (6x6; inverse iteration from the
    projection of ``F``). Rank 2 by construction: no projection afterwards, which is what makes it
    more accurate than the plain 8-point fit (measured on the planted scenes of
    ``benchmarks/bench_fundamental_accuracy.py`` after the plain refit: median F error 0.068 px
    instead of 0.075 at 0 % outliers, 0.090 instead of 0.100 at 40 %).

    ``x1, x2 (B, N, 2)`` float64, finite (zero where ``w == 0``); ``w (B, N)`` >= 0; ``F (B, 3, 3)``
    pixel model, rank 2. Hartley normalisation over the points of positive weight (unit weights,
    RMS distance sqrt(2)). Returns ``(B, 3, 3)`` unit norm, largest entry positive, NaN with fewer
    than 8 points of positive weight. Differentiable w.r.t. the points, ``w`` and ``F``."""
    B = F.shape[0]
    use = w > 0
    ok = use.sum(-1) >= _MIN_POINTS
    wu = use.to(w.dtype)
    W = wu.sum(-1).clamp_min(1.0)[:, None]

    def _normalise(x):
        c = (wu[..., None] * x).sum(1) / W  # (B, 2)
        d = x - c[:, None]
        r2 = (wu * (d * d).sum(-1)).sum(-1, keepdim=True) / W
        s = torch.sqrt(2.0 / torch.where(r2 > 0, r2, torch.ones_like(r2)))  # (B, 1)
        one, zero = torch.ones_like(s), torch.zeros_like(s)
        T = torch.cat([s, zero, -s * c[:, :1], zero, s, -s * c[:, 1:], zero, zero, one], -1).view(B, 3, 3)
        r = 1.0 / s
        Ti = torch.cat([r, zero, c[:, :1], zero, r, c[:, 1:], zero, zero, one], -1).view(B, 3, 3)
        return d * s[..., None], T, Ti

    n1, T1, T1i = _normalise(x1)
    n2, T2, T2i = _normalise(x2)
    M = _normal_matrix(_epipolar_rows(n1[..., 0], n1[..., 1], n2[..., 0], n2[..., 1]), w)
    Fn = T2i.transpose(-1, -2) @ F @ T1i
    e = _null_vector(Fn)
    a = lk.eye3.index_select(0, e.abs().argmin(-1))  # the axis least aligned with e
    u = torch.linalg.cross(e, a)
    u = u / u.norm(dim=-1, keepdim=True)
    Bm = torch.stack([u, torch.linalg.cross(e, u)], -1)  # (B, 3, 2)
    N = (lk.eye3[None, :, None, :, None] * Bm[:, None, :, None, :]).reshape(B, 9, 6)
    MN = (M[:, :, :, None] * N[:, None, :, :]).sum(2)  # (B, 9, 6), elementwise (see _smallest_eigvec)
    Mg = (N[:, :, :, None] * MN[:, :, None, :]).sum(1)  # (B, 6, 6)
    g = _smallest_eigvec(Mg, (N * Fn.reshape(B, 9, 1)).sum(1), lk, _EIG_POWER_FINAL)
    F = T2.transpose(-1, -2) @ (N * g[:, None, :]).sum(-1).view(B, 3, 3) @ T1
    return torch.where(ok[:, None, None], _canonical_sign(F), math.nan)


class _LOContext(NamedTuple):
    """Per-call data of the local optimisation (:func:`_lo_context`)."""

    An: torch.Tensor  # (B, N, 9) epipolar rows in Hartley-normalised coordinates (all valid points)
    Kn2p: torch.Tensor  # (B, 9, 9): vec(F) = Kn2p vec(Fn) (normalised -> pixel models, row-major)
    Kp2n: torch.Tensor  # (B, 9, 9): its inverse
    outer: torch.Tensor  # (B, N, 9): pixel h2 (x) h1 (scoring), 0 at masked-out slots
    thr2: float
    bounds: torch.Tensor  # (N + 1, N + 2) int64: the iteration bound [n, best count + 1]
    bound_row: torch.Tensor  # (B,) int64: n (N + 2) + 1 (+ best count = the index into bounds)
    lk: _LOConsts


def _lo_context(x12, eff, n, outer, thr2, bounds, lk) -> _LOContext:
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
    top = s[..., None, None] * lk.eye23  # (B, image, 2, 3)
    Tt = torch.cat([top, torch.nn.functional.pad(c * -s[..., None], (0, 1), value=1.0)[:, :, None]], 2)
    Ti = torch.cat([top / (s * s)[..., None, None], torch.nn.functional.pad(c, (0, 1), value=1.0)[:, :, None]], 2)
    Kn2p = (Tt[:, 1, :, None, :, None] * Tt[:, 0, None, :, None, :]).reshape(B, 9, 9)
    Kp2n = (Ti[:, 1, :, None, :, None] * Ti[:, 0, None, :, None, :]).reshape(B, 9, 9)
    return _LOContext(An, Kn2p, Kp2n, outer, thr2, bounds, n * (N + 2) + 1, lk)


def _lo_score(Fp: torch.Tensor, ctx: _LOContext, weights: bool = True):
    """OpenCV's inlier test of pixel models ``Fp (B, 9)`` (any scale) on every point: the mask
    ``(B, N)``, the counts ``(B,)`` int32 and (``weights``, else None) the Sampson weights ``(B,
    N)`` (:func:`_sampson_weights`). The terms of :func:`_score_terms` as elementwise products and
    sums (a batched matmul's last bits depend on the batch and on memory alignment)."""
    B = Fp.shape[0]
    rows = (Fp[:, :, None] * ctx.lk.select).sum(1).view(B, 5, 1, 9)  # _score_rows
    o = (rows * ctx.outer[:, None]).sum(-1)  # (B, 5, N)
    o = o * o
    s2 = o[:, 1] + o[:, 2]
    s1 = o[:, 3] + o[:, 4]
    smin = torch.minimum(s1, s2)
    bound = smin if ctx.thr2 == 1.0 else smin * ctx.thr2
    inl = (o[:, 0] <= bound) & (smin > 0)
    cnt = inl.sum(-1, dtype=torch.int32)
    return inl, cnt, _sampson_weights(s1 + s2, inl, cnt, ctx.lk) if weights else None


def _sampson_weights(den: torch.Tensor, inl: torch.Tensor, cnt: torch.Tensor, lk: _LOConsts) -> torch.Tensor:
    """IRLS weights ``(B, N)`` that turn the algebraic error into the Sampson error: ``1 / den`` at
    inliers (``den = |F x1|_xy^2 + |F^T x2|_xy^2``), 0 elsewhere, with den floored at
    ``_SAMPSON_FLOOR`` times its mean over the inliers: a point near the epipole has a tiny den,
    and unbounded, its weight decides the fit alone (measured on EuRoC frames with sub-pixel
    motion: one weight 2000x the median turned a 150-inlier model into a 100-inlier one)."""
    mean = torch.where(inl, den, lk.zero).sum(-1) / cnt.clamp_min(1)
    return torch.where(inl, torch.maximum(den, (_SAMPSON_FLOOR * mean)[:, None]).reciprocal(), lk.zero)


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
        f = _smallest_eigvec(M, f, ctx.lk, _EIG_POWER_LO)
        if j == _LO_STEPS - 1:
            f = _rank2(f.view(B, 3, 3), ctx.lk).view(B, 9)
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
        has, j = torch.where(elig, cnt, ctx.lk.minus_one).max(1)
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
    lk = ctx.lk
    F = _refit_impl(x1, x2, _sampson_weights(_sampson_den(x1, x2, F0), st.inl, st.cnt, lk), warm=F0, lk=lk)
    F = _refit_fixed_epipole(x1, x2, _sampson_weights(_sampson_den(x1, x2, F), st.inl, st.cnt, lk), F, lk)
    inl, cnt, _ = _lo_score(F.detach().reshape(-1, 9), ctx, False)
    good = torch.isfinite(F).flatten(1).all(-1) & (cnt >= st.cnt)
    F = torch.where(good[:, None, None], F, _canonical_sign(F0))
    return F, torch.where(good[:, None], inl, st.inl)


def _find_fundamental_lo_static(p1, p2, valid, threshold, confidence, max_iters, states, block):
    """``method="lo"``, ``capturable=True``: :func:`_find_fundamental_static`'s samples, models and
    inlier counts (one block of ``K`` samples), then OpenCV's loop replayed with local
    optimisation: ``_LO_EVENTS`` times the next accepted model (the first one after the last
    accepted that has more inliers than the current LO count, drawn before the bound stops the
    loop) is locally optimised and sets the bar and the bound; then the final refit. A fixed
    number of kernels; ``overflow`` where the block ended before OpenCV's loop would have (as the
    OpenCV path) or a further model would have been accepted after the budget. LMedS problems
    (8..14 points) get the OpenCV path's result."""
    sp = _static_front(p1, p2, valid, confidence, max_iters, states, block)
    if isinstance(sp, FundamentalResult):  # N < 8
        return sp
    F, inl, ok, iters, overflow = _static_lmeds(sp)
    if sp.has_r:
        B, N, K, is_r = sp.B, sp.N, sp.K, sp.is_r
        thr2 = threshold * threshold
        lk = _lo_consts(p1.device)
        mask, cnt = _static_counts(sp, thr2)
        ctx = _lo_context(sp.x12, sp.eff, sp.n, sp.outer, thr2, sp.tabs.niters, lk)
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
    return _static_result(sp, F, inl, ok, iters, overflow, p1.dtype)


def _find_fundamental_lo(p1, p2, valid, threshold, confidence, max_iters, states, batch_hypotheses):
    """``method="lo"``, ``capturable=False``: the capturable path's algorithm (the same models, loop,
    local optimisation and final refit, so the same result where that path does not overflow),
    with the default path's early exits: rounds of 32, 64, ... samples for the problems still
    running (one host sync per round and one per accepted model), as many accepted models as
    OpenCV's loop finds (never ``overflow``). LMedS problems (8..14 points) get the OpenCV path's
    result (:func:`_find_fundamental_impl`)."""
    B, N = valid.shape
    dev, out_dtype = p1.device, p1.dtype
    f64 = torch.float64
    x12 = torch.cat([p1.detach(), p2.detach()], -1).to(torch.float32).to(f64)
    eff = valid & (x12.sum(-1).abs() < math.inf)
    n = eff.sum(-1)
    n_host = n.tolist()  # host sync: sample tables are per (seed, n)
    F = torch.full((B, 3, 3), math.nan, dtype=out_dtype, device=dev)
    inliers = eff.clone()
    ok = torch.zeros(B, dtype=torch.bool, device=dev)
    iters = torch.zeros(B, dtype=torch.int64, device=dev)
    method = (n >= _MIN_POINTS).to(torch.int8) + (n >= _MIN_RANSAC_POINTS).to(torch.int8)
    lmeds = [b for b in range(B) if _MIN_POINTS <= n_host[b] < _MIN_RANSAC_POINTS]
    if lmeds:
        rows = torch.tensor(lmeds, dtype=torch.int64, device=dev)
        r = _find_fundamental_impl(p1.detach()[rows], p2.detach()[rows], valid[rows], threshold, confidence,
                                   max_iters, [states[b] for b in lmeds], batch_hypotheses)
        F = F.index_copy(0, rows, r.F)
        inliers[rows] = r.inliers
        ok[rows] = r.ok
        iters[rows] = r.num_iters
    sel = [b for b in range(B) if n_host[b] >= _MIN_RANSAC_POINTS]
    if not sel:
        return FundamentalResult(F, inliers, ok, iters, method)
    R = len(sel)
    rows = slice(None) if R == B else torch.tensor(sel, dtype=torch.int64, device=dev)
    x12, eff_r, n_r = x12[rows], eff[rows], n[rows]
    x12 = torch.where(eff_r[..., None], x12, 0.0)
    k = _static_consts(dev)
    lk = _lo_consts(dev)
    thr2 = threshold * threshold
    Mx = max(int(max_iters), 1)
    h = torch.cat([x12.view(R, N, 2, 2), eff_r[:, :, None, None].expand(R, N, 2, 1).to(f64)], -1)
    outer = (h[:, :, 1, :, None] * h[:, :, 0, None, :]).flatten(-2)  # (R, N, 9), as _static_front
    ctx = _lo_context(x12, eff_r, n_r, outer, thr2, _lo_bounds(N, Mx, confidence, dev), lk)
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
        Fm, fok = _run_7point_static(smp, k)
        Fm = Fm.view(A, Hr * 3, 9)
        d2, smin = _score_terms(_score_rows(Fm, k), cx.outer)
        bound = smin if thr2 == 1.0 else smin * thr2
        mask = (d2 <= bound) & (smin > 0)  # (A, 3 Hr, N): _static_counts' test
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
        return FundamentalResult(Ff, inl_r, okr, it_r, method)
    return FundamentalResult(F.index_copy(0, rows, Ff), inliers.index_copy(0, rows, inl_r), ok.index_copy(0, rows, okr),
                             iters.index_copy(0, rows, it_r), method)
