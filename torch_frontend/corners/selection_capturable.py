"""The capturable selection of ``goodFeaturesToTrack`` (``capturable=True``, for CUDA graphs / a
whole-step compile): shape-static, no host syncs, and a kernel count that depends on neither B nor
the data.

The same rules as the default selection (:mod:`.selection`); what the default path decides on the
host (how many candidates, chunks and rounds) is a fixed budget here. The candidates of each stream
are ranked by one top-k of a unique integer key (OpenCV's order and tie order) and a fixed
:class:`GreedyBudget` replaces the data-dependent chunks and rounds; an ``overflow (B,)`` flag says
where the budget was too small for OpenCV's exact answer, and wherever it is False the corners are
the default path's, bit for bit. The budget is sized from measured maxima (:data:`GFTT_BUDGET`).

:func:`_pair_conflicts` and :func:`_resolve_dense` (greedy acceptance in a fixed number of rounds)
also serve the capturable setMask (``masks``).
"""

from __future__ import annotations

import contextlib
import math
from typing import NamedTuple, Tuple

import torch

from .._cache import cached
from .selection import _nms_candidates

__all__ = ["GreedyBudget", "GFTT_BUDGET"]

_I64_MIN = -(1 << 63)  # the key of a non-candidate: below every candidate's key


class GreedyBudget(NamedTuple):
    """Fixed work of the capturable GFTT selection (per stream and call).

    ``block``: candidates kept per stream, the best in OpenCV's order (one top-k). The greedy
    minimum-distance pass then runs in rank *windows*: window 0 holds the ``first`` best
    candidates; each of the ``windows`` later ones the next ``survivors`` candidates (rank order
    kept) that no corner accepted so far excludes (a raster of the accepted corners' discs, one
    gather per candidate). A window resolves among itself on a dense ``(n + 1)²`` bool conflict
    matrix (n its size, one dump slot) in ``rounds_first`` (window 0) / ``rounds`` rounds of two
    kernels each. Per stream and window: ~``13 B x n²`` to build the matrix, ``3 B x n²`` a round,
    ~``2.5 B x H x W`` for the raster (the later windows); kernels ~``40 + 2 x rounds`` a window,
    whatever B and the data.
    """

    block: int
    first: int
    rounds_first: int
    survivors: int
    rounds: int
    windows: int = 4


#: The tracker's budget: measured maxima with headroom. Measured on what the tracker sees:
#: max_cnt 150, quality 0.01, min_dist 30 / 25 / 20; every frame as a first frame (no mask, 150
#: new corners; CLAHE and raw) and, with CLAHE, in the steady state (setMask's mask of the
#: previous frame's OpenCV corners, jittered, ``n_max = 150 - kept``). Frames: EuRoC mini cam0 /
#: cam1, V1_01 micro cam0 / cam1 (every 4th / 3rd), the Middlebury pair, the synthetic flight
#: (3,294 calls; windows of 256 candidates).
#:
#: ==========================================================  =========  ======  ========
#: quantity (max over the calls)                               EuRoC      all     budget
#: ==========================================================  =========  ======  ========
#: candidate rank OpenCV's answer reaches (150th corner, or    1,995      2,763   8,192
#: every candidate where a stream runs out)
#: windows of 256 until the last corner is decided             4          4       5
#: rounds until window 0 (the 256 best) is decided             10         10      14
#: rounds until a later window is decided                      12         12      16
#: ==========================================================  =========  ======  ========
#:
#: (1 window: 45 % of the calls, 3: 47 %, 4: 6 %.) The kernel count depends on the windows and
#: rounds only.
GFTT_BUDGET = GreedyBudget(block=8192, first=256, rounds_first=14, survivors=256, rounds=16, windows=4)


@cached(64)
def _lower(n: int, device: torch.device) -> torch.Tensor:
    """(n, n) bool, ``[i, j]`` True iff ``j < i < n - 1``: the strictly higher ranks of every slot
    but the last (the dump slot, whose row stays empty; cached)."""
    m = torch.ones(n, n, dtype=torch.bool, device=device).tril(-1)
    m[n - 1].fill_(False)
    return m


@cached(64)
def _pixel_table(height: int, width: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Raster index -> ``(x, y, y * (width + 1) + x)``: (H*W, 3) integers, a cached constant (one
    gather replaces the div / mod / stack per call; the third column indexes a raster with one
    spare column)."""
    i = torch.arange(height * width, device=device)
    x, y = i % width, torch.div(i, width, rounding_mode="floor")
    return torch.stack((x, y, y * (width + 1) + x), -1).to(dtype)


@cached(64)
def _iota(n: int, device: torch.device) -> torch.Tensor:
    """``arange(n)`` int64 (cached constant)."""
    return torch.arange(n, device=device)


@cached(16)
def _i64_min(device: torch.device) -> torch.Tensor:
    """``_I64_MIN`` as a 0-dim int64 tensor on ``device`` (cached constant: ``where(..., out=)`` takes
    no Python number)."""
    return torch.tensor(_I64_MIN, device=device)


@cached(64)
def _iota32(n: int, device: torch.device) -> torch.Tensor:
    """``arange(n)`` int32 (cached constant)."""
    return torch.arange(n, dtype=torch.int32, device=device)


@cached(16)
def _i32_minus_one(device: torch.device) -> torch.Tensor:
    """``-1`` as a 0-dim int32 tensor on ``device`` (cached constant)."""
    return torch.tensor(-1, dtype=torch.int32, device=device)


@cached(16)
def _f32_zero(device: torch.device) -> torch.Tensor:
    """``0.0`` as a 0-dim float32 tensor on ``device`` (cached constant, as :func:`_i64_min`)."""
    return torch.zeros((), dtype=torch.float32, device=device)


def _distance_threshold(d2_max: int) -> Tuple[torch.dtype, float]:
    """``(dtype, t)`` such that for integer points, ``cdist(p, p) <= t`` in ``dtype`` iff ``d² <=
    d2_max``: t is the midpoint of ``sqrt(d2_max)`` and ``sqrt(d2_max + 1)``, which lie many ulps
    apart (float32 while ``d2_max < 2**18``: the gap ``1 / (2 sqrt(n))`` is >= 16 ulps of
    ``sqrt(n)``), so cdist's rounding (a few ulps of an exact integer sum of squares) cannot cross
    it. A negative ``d2_max`` conflicts nothing (t < 0)."""
    if d2_max < 0:
        return torch.float32, -1.0
    dt = torch.float32 if d2_max < (1 << 18) else torch.float64
    return dt, 0.5 * (math.sqrt(d2_max) + math.sqrt(d2_max + 1))


def _pair_conflicts(p: torch.Tensor, d2_max: int) -> torch.Tensor:
    """``d² <= d2_max`` of all pairs of ``p`` (B, n, 2) integer points -> (B, n, n) bool: one cdist
    (4 B a pair in float32, computed directly, not by a matmul) and one comparison, instead of
    integer differences, squares and sums (~40 B a pair)."""
    dt, t = _distance_threshold(d2_max)
    q = p.to(dt)
    with _no_autocast(p.device):  # autocast would run a float64 cdist in float32
        return torch.cdist(q, q, compute_mode="donot_use_mm_for_euclid_dist") <= t


def _no_autocast(device: torch.device):
    """A context without autocast for ``device`` when it is on (else a no-op)."""
    if torch.is_autocast_enabled(device.type):
        return torch.autocast(device.type, enabled=False)
    return contextlib.nullcontext()


def _resolve_dense(conf: torch.Tensor, valid: torch.Tensor, rounds: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Greedy acceptance in a fixed number of rounds (no host check), 2 kernels a round.

    ``conf`` (B, n, n) bool, ``[i, j]`` iff ``j < i`` in rank and j excludes i; the last slot is a
    dump slot: its row must be empty and its column is overwritten here (``~valid``). ``valid``
    (B, n) bool: the candidates to decide (the dump slot False). Returns ``accepted`` and
    ``undecided`` (B, n) bool after ``rounds`` rounds (the dump slot: accepted). Every decision
    taken is the sequential greedy one (by induction on rank); above the first undecided
    candidate the result is exact.

    One state per slot, 0 rejected / 1 undecided / 2 accepted (``s``), or its complement ``c = 2 -
    s``. A round is ``c_i = max_j conf[i, j] s_j``: 2 (an accepted higher conflict: reject), 1 (one
    undecided: wait), 0 (all rejected: accept), i.e. the new state in the complement form; the next
    round is the mirror ``s_i = min_j (conf[i, j] ? c_j : 2)``. So the rounds alternate between the
    two forms and need no update kernel. The dump slot (empty row) stays accepted in both forms
    and every invalid slot conflicts with it (its column), so it is rejected in the first round and
    stays so; an accepted slot's higher conflicts are all rejected, so it stays accepted.
    """
    n = conf.shape[-1]
    # the dump slot's column (its row stays empty); a copy into the view, not ``out=`` a strided
    # view (dynamo breaks the graph there)
    conf[:, :n - 1, n - 1] = ~valid[:, :n - 1]
    s = valid.to(torch.uint8)
    s[:, n - 1].fill_(2)
    c = torch.empty_like(s)
    for r in range(rounds):
        if r % 2 == 0:
            torch.amax(conf * s[:, None, :], -1, out=c)
        else:
            torch.amin(torch.where(conf, c[:, None, :], 2), -1, out=s)
    if rounds % 2 == 0:
        return s == 2, s == 1
    return c == 0, c == 1


@cached(32)
def _disc_spans(d2_max: int, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    """Row offsets ``dy`` (-rho..rho, rho = isqrt(d2_max)) of the integer disc ``dx² + dy² <=
    d2_max`` and each row's half width ``isqrt(d2_max - dy²)``: (2 rho + 1,) int64 device constants
    (cached; built on the device: no upload, traceable)."""
    rho = math.isqrt(d2_max)
    dys = torch.arange(2 * rho + 1, device=device) - rho
    # floor(sqrt(v)) in float64 is isqrt(v) for v < 2**52: sqrt(k² - 1) < k - 1 / (2k) lies far
    # more than an ulp below k
    hws = (d2_max - dys * dys).double().sqrt_().floor_().long()
    return dys, hws


def _greedy_capturable(xy: torch.Tensor, cvalid: torch.Tensor, mc: torch.Tensor, r2i: int, height: int, width: int,
                       budget: GreedyBudget) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`.selection._greedy_accept` with a fixed schedule (:class:`GreedyBudget`'s windows).

    ``xy`` (B, C, 3) integer ``(x, y, y * (width + 1) + x)`` in rank order, ``cvalid`` (B, C),
    ``mc`` (B,) corner budgets; a conflict is ``d² < r2i``. Returns ``accepted`` (B, C) bool,
    ``undecided`` (B, C) bool (decisions the rounds left open, or candidates a full window left
    out) and ``more`` (B,) bool (candidates after the last window were not looked at). Every
    decision taken is the sequential greedy one; the result is OpenCV's above the first open
    decision.

    OpenCV's 3x3 grid of cell ``cvRound(min_distance)`` needs no test here: two integer points
    two cells apart differ by >= cell + 1 > min_distance in a coordinate, so they never conflict.
    """
    B, C, _ = xy.shape
    dev = xy.device
    H, W = height, width
    d2_max = r2i - 1  # integer d²: d² < r2i  <=>  d² <= r2i - 1
    rho = math.isqrt(d2_max)
    n0 = min(budget.first, C)
    n1 = min(budget.survivors, C)
    nwin = max(budget.windows, 0) if n0 < C else 0
    rank = _iota(C, dev)
    accepted = torch.zeros(B, C + 1, dtype=torch.bool, device=dev)  # column C: the dump column
    undecided = torch.zeros(B, C + 1, dtype=torch.bool, device=dev)
    count = torch.zeros(B, dtype=torch.long, device=dev)
    pos = torch.zeros(B, dtype=torch.long, device=dev)  # ranks below pos have been looked at
    diff = blocked = more = None
    if nwin:
        # the accepted corners' discs as row spans: +1 at the start, -1 (255) after the end, rho
        # spare rows above and below each stream and one spare column (every index in range); a
        # pixel lies in at most 5 discs (accepted corners are pairwise farther apart than the disc
        # radius: seen from the pixel they are > 60 degrees apart), so uint8 counts are exact
        dys, hws = _disc_spans(d2_max, dev)
        hws1 = hws + 1
        rowoff = (dys + rho) * (W + 1)  # (2 rho + 1,)
        base = (_iota(B, dev) * ((H + 2 * rho) * (W + 1)))[:, None]
        diff = torch.zeros(B * (H + 2 * rho) * (W + 1), dtype=torch.uint8, device=dev)
        fidx = xy[..., 2].long()  # flat raster index of each candidate
    for w in range(1 + nwin):
        n = n0 if w == 0 else n1
        elig = cvalid & (count < mc)[:, None]  # streams still collecting
        if w > 0:
            cover = diff.view(B, H + 2 * rho, W + 1)[:, rho:rho + H].cumsum(-1, dtype=torch.uint8)
            blocked = cover.view(B, H * (W + 1)).gather(1, fidx) != 0
            elig &= ~blocked
            elig &= rank >= pos[:, None]
        # the window: the first n eligible candidates (rank order kept) in n slots + a dump slot
        k = torch.cumsum(elig, 1)
        sel = elig & (k <= n)
        slot = torch.where(sel, k - 1, n)
        more = k[:, -1] > n
        if w < nwin:
            # the n-th eligible candidate is at rank (k < n).sum(); all ranks after it are open
            pos = torch.where(more, (k < n).sum(1) + 1, C)
        wxy = torch.zeros(B, n + 1, 2, dtype=xy.dtype, device=dev)
        wxy.scatter_(1, slot[..., None].expand(B, C, 2), xy[..., :2])
        wval = torch.zeros(B, n + 1, dtype=torch.bool, device=dev)
        wval.scatter_(1, slot, sel)  # every write to the dump slot is False
        wrank = torch.full((B, n + 1), C, dtype=torch.long, device=dev)
        wrank.scatter_(1, slot, torch.where(sel, rank, C))
        conf = _pair_conflicts(wxy, d2_max)
        conf &= _lower(n + 1, dev)
        acc, und = _resolve_dense(conf, wval, budget.rounds_first if w == 0 else budget.rounds)
        acc = acc[:, :n]
        accepted.scatter_(1, wrank[:, :n], acc)
        undecided.scatter_(1, wrank[:, :n], und[:, :n])
        if w < nwin:
            count += acc.sum(1)
            x = wxy[:, :n, 0, None].long()
            x0 = (x - hws).clamp_min_(0)
            x1 = (x + hws1).clamp_max_(W)
            row = (wxy[:, :n, 1, None].long() * (W + 1) + base[..., None]) + rowoff
            inc = acc.to(torch.uint8)[..., None]  # 0 for the slots not accepted
            diff.index_put_((row + x0,), inc, accumulate=True)
            diff.index_put_((row + x1,), inc * 255, accumulate=True)
    return accepted[:, :C], undecided[:, :C], more


def _top_keys(bits: torch.Tensor, k: int, ib: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` largest keys ``bits * 2**ib + raster`` of every row of ``bits (B, HW)`` int32 >= 0
    (``HW <= 2**ib``, ``ib <= 31``), in descending order: ``(raster (B, k) int64, bits > 0)``,
    i.e. ``topk(bits.long() * 2**ib + arange(HW), k)`` (unique keys: a unique answer), without an
    int64 plane: two int32 top-k over the image (4-byte keys: half the passes over half the
    bytes of an int64 top-k) and one sort of the ``k`` winners.

    1. ``topk(bits, k)`` (ties in any order) finds ``v``, the k-th largest bits, and every element
       above it (``n_gt < k`` of them: all are among the k);
    2. the rest of the answer is the ``k - n_gt`` raster-last elements of the tie class ``bits ==
       v``: a top-k of their raster indices (-1 elsewhere; the class has at least ``k - n_gt``
       members, the ones step 1 found), in descending order, the j-th filling the j-th slot that
       step 1 did not fill with an element above ``v``;
    3. the k chosen keys (distinct pixels, so distinct keys) sorted descending.
    """
    B, HW = bits.shape
    dev = bits.device
    v1, i1 = torch.topk(bits, k, dim=1, sorted=False)
    vk = v1.amin(1, keepdim=True)  # (B, 1): the k-th largest
    tie = torch.where(bits == vk, _iota32(HW, dev), _i32_minus_one(dev))
    r2 = torch.topk(tie, k, dim=1).values  # raster indices of the tie class, descending (then -1)
    del tie
    gt = v1 > vk
    slot = torch.cumsum(~gt, 1).sub_(1).clamp_min_(0)  # j-th slot not above v -> j-th tie
    raster = torch.where(gt, i1, r2.gather(1, slot))
    key = torch.add(raster, torch.where(gt, v1, vk), alpha=1 << ib)  # int64, exact (< 2**62)
    key = torch.sort(key, dim=1, descending=True).values
    return key.bitwise_and((1 << ib) - 1), key >= (1 << ib)


def _select_corners_capturable(
    resp: torch.Tensor,
    mc: torch.Tensor,
    quality_level: float,
    min_distance: float,
    m: torch.Tensor | None,
    K: int,
    budget: GreedyBudget,
    finite: bool = False,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`.selection._select_corners` with fixed work (the ``capturable`` path), no input checks.
    ``finite``: the caller knows ``resp`` holds no NaN (the response of a uint8 image), which
    lets the NMS read ``resp`` without a thresholded copy (the same candidates).

    The candidates of each stream are ranked by one top-k of a unique integer key (response
    bits, then raster index: OpenCV's order and tie order) and the best ``budget.block`` enter
    :func:`_greedy_capturable`. Returns ``pts (B, K, 2)``, ``valid (B, K)`` as
    :func:`.selection._select_corners` and ``overflow (B,)`` bool: True where OpenCV's answer needs a candidate beyond the block
    (fewer than ``mc`` corners accepted and more candidates than the block holds) or a decision
    the rounds left open above the ``mc``-th accepted corner. Where False, the result equals
    :func:`.selection._select_corners`'s exactly.
    """
    B, H, W = resp.shape
    dev = resp.device
    HW = H * W
    if K <= 0 or B == 0 or HW == 0:
        return (torch.zeros(B, max(K, 0), 2, dtype=resp.dtype, device=dev),
                torch.zeros(B, max(K, 0), dtype=torch.bool, device=dev), torch.zeros(B, dtype=torch.bool, device=dev))
    mc = mc.clamp_max(K)
    Cb = min(budget.block, HW)

    if m is None:
        max_val = resp.flatten(1).amax(1)
    else:
        max_val = torch.where(m, resp, float("-inf")).flatten(1).amax(1)
    max_val = torch.nan_to_num(max_val, nan=0.0, posinf=0.0, neginf=0.0)  # == where(isfinite, ., 0)
    thr = (max_val.double() * float(quality_level)).to(resp.dtype)
    above = resp > thr[:, None, None]
    ib = max(1, (HW - 1).bit_length())  # bits of a raster index
    # 0 <= quality_level <= 1: every candidate's response is > 0 (below), so its float32 bits, read
    # as an int32, are positive and ordered as the values
    positive = resp.dtype == torch.float32 and ib <= 31 and 0.0 <= quality_level <= 1.0
    if positive and finite:
        # NMS on resp itself, no thresholded copy: for a pixel p with resp_p > thr >= 0, t's 3x3
        # max is t_p iff resp_p >= resp_q for every neighbour q (one with resp_q <= thr has t_q = 0
        # < resp_p and resp_q < resp_p), i.e. iff resp_p == dilate3x3(resp)_p (no NaN: ``finite``),
        # and t_p = resp_p != 0; a pixel with resp_p <= thr is no candidate in either form. thr < 0
        # only where max_val < 0 (below): no pixel of the mask (or the image) passes, and outside a
        # mask nothing survives ``cand &= m``. So the same candidates.
        cand, t = _nms_candidates(resp, above, windowed=True), resp
    else:
        t = torch.where(above, resp, 0.0)
        cand = _nms_candidates(t, windowed=positive)
    del above
    if m is not None:
        cand &= m
    cand = cand.view(B, HW)
    n_cand = cand.sum(1)

    if positive:
        # Candidates are > 0: a candidate has resp > thr. With 0 <= q <= 1, thr >= 0 unless
        # max_val < 0 (max_val: NaN, +-inf -> 0, so finite), and then thr = q max_val >= max_val
        # (rounding is monotone and max_val is a float32) >= every response that can be a
        # candidate (all of them, or with a mask the masked ones, the only candidates kept): none.
        # So the key of the branch below is, on a candidate, ``(bits << ib) + raster`` (its
        # sign flip is a no-op on positive bits), built here in two passes (the bits of t, which
        # is resp there, zero elsewhere; then one int64 add, exact: < 2**(31 + ib) <= 2**62)
        # instead of seven. A non-candidate gets its raster index, below every candidate's key
        # (>= 2**ib), instead of the int64 minimum: the top-k's candidates and their order are
        # the same; only the filler lanes (cvalid False) may name other pixels, and those are
        # never eligible, scattered to a dump slot or dropped (outputs unchanged).
        bits = torch.where(cand.view(B, H, W), t, _f32_zero(dev), out=None if t is resp else t)
        bits = bits.view(B, HW).view(torch.int32)
        del t
        idx, cvalid = _top_keys(bits, Cb, ib)
        del bits
    elif resp.dtype == torch.float32 and ib <= 31:
        # unique int64 key, larger = earlier in OpenCV's order: float32 bits made order-preserving
        # as signed ints (negative values: flip the magnitude bits), then the raster index (ties:
        # later raster position first)
        # (in place on the one int64 copy: two int64 planes at a time, the step's peak memory)
        del t  # image-sized: dropped before the int64 keys exist (the step's peak memory)
        bits = resp.reshape(B, HW).view(torch.int32).to(torch.int64)
        neg = bits >> 31
        bits ^= neg.bitwise_and_(0x7FFFFFFF)
        del neg
        bits.bitwise_left_shift_(ib).add_(_iota(HW, dev))
        key = torch.where(cand, bits, _i64_min(dev), out=bits)  # elementwise, into its own input
        del bits
        top = torch.topk(key, Cb, dim=1)
        idx, cvalid = top.indices, top.values != _I64_MIN
    else:
        del t
        # general dtype: a stable descending sort of the reversed raster order (ties: later first)
        vals = torch.where(cand, resp.reshape(B, HW), float("-inf")).flip(1)
        srt = torch.sort(vals, dim=1, descending=True, stable=True)
        idx = (HW - 1) - srt.indices[:, :Cb]
        cvalid = srt.values[:, :Cb] != float("-inf")

    return _finish(idx, cvalid, n_cand, mc, min_distance, H, W, K, budget, Cb, resp.dtype)


def _select_from_keys(bits: torch.Tensor, mc: torch.Tensor, min_distance: float, H: int, W: int, K: int,
                      budget: GreedyBudget, dtype: torch.dtype) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_select_corners_capturable` from the candidates' keys ``bits (B, H * W)`` int32 (a
    candidate's float32 response bits, > 0; 0 elsewhere), as the fused CUDA op's kernels write them
    (``fused/_triton_corners.py``): the same top-k and greedy windows, so the same result and flag.
    ``mc`` (B,) int64 >= 0; ``K >= 1``; ``dtype`` of ``pts``."""
    HW = H * W
    mc = mc.clamp_max(K)
    Cb = min(budget.block, HW)
    n_cand = (bits != 0).sum(1)
    ib = max(1, (HW - 1).bit_length())
    idx, cvalid = _top_keys(bits, Cb, ib)
    return _finish(idx, cvalid, n_cand, mc, min_distance, H, W, K, budget, Cb, dtype)


def _finish(idx: torch.Tensor, cvalid: torch.Tensor, n_cand: torch.Tensor, mc: torch.Tensor, min_distance: float,
            H: int, W: int, K: int, budget: GreedyBudget, Cb: int,
            dtype: torch.dtype) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The greedy pass and the compaction of :func:`_select_corners_capturable` from the ranked
    candidates ``idx`` (B, Cb) raster indices and ``cvalid`` (B, Cb) (see there)."""
    B = idx.shape[0]
    dev = idx.device
    # int32 positions while the raster index y * (W + 1) + x fits
    cdt = torch.int32 if H * (W + 1) < (1 << 31) else torch.int64
    xy = _pixel_table(H, W, cdt, dev).index_select(0, idx.reshape(-1)).view(B, Cb, 3)
    if min_distance < 1:  # OpenCV: no distance test, the first max_corners candidates
        accepted, undecided, more = cvalid, None, None
    else:
        r2i = int(math.ceil(min_distance * min_distance))  # integer d²: d² < r²  <=>  d² < ceil(r²)
        accepted, undecided, more = _greedy_capturable(xy, cvalid, mc, r2i, H, W, budget)

    cum = torch.cumsum(accepted, 1)  # (B, Cb) int64: accepted up to and including each rank
    n_acc = cum[:, -1]
    # candidates that were never looked at (beyond the block, or beyond the last window: all
    # ranked below every resolved one) matter iff fewer than mc corners were found
    short = n_cand > Cb
    if more is not None:
        short |= more
    overflow = short & (n_acc < mc)
    if undecided is not None:
        # the first open decision matters iff fewer than mc corners were accepted above it
        overflow |= (undecided & (cum - accepted.long() < mc[:, None])).any(1)
    keep = accepted & (cum <= mc[:, None])
    # compact into (B, K): kept corners at b * K + rank, the rest into one dump slot
    slot = torch.where(keep, cum + _stream_offsets(B, K, dev), B * K)
    out = torch.zeros(B * K + 1, 2, dtype=dtype, device=dev)
    out.index_put_((slot.view(-1),), xy[..., :2].reshape(-1, 2).to(dtype))
    n = torch.minimum(n_acc, mc)
    valid = _iota(K, dev) < n[:, None]
    return out[:B * K].view(B, K, 2), valid, overflow


@cached(64)
def _stream_offsets(B: int, K: int, device: torch.device) -> torch.Tensor:
    """``b * K - 1`` per stream, (B, 1) int64 (cached constant): flat slot of rank ``cum - 1``."""
    return (torch.arange(B, device=device) * K - 1)[:, None]
