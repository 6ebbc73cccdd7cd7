"""The capturable selection of ``goodFeaturesToTrack`` (``capturable=True``, for CUDA graphs / a
whole-step compile): shape-static, no host syncs, and a kernel count that depends on neither B nor
the data.

The same rules as the default selection (:mod:`.selection`); what the default path decides on the
host (how many candidates, chunks and rounds) is a fixed budget here. The candidates of each stream
are ranked by one top-k of a unique integer key (OpenCV's order and tie order) and a fixed
:class:`GreedyBudget` replaces the data-dependent chunks and rounds; an ``overflow (B,)`` flag says
where the budget was too small for OpenCV's exact answer, and wherever it is False the corners are
the default path's, bit for bit. The budget is sized from measured maxima (:data:`GFTT_BUDGET`).

:func:`_resolve_fixed` (greedy acceptance in a fixed number of rounds) also serves the capturable
setMask (``masks``).
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

# The far placeholder of the accepted-corner buffer, per coordinate dtype: farther than
# min_distance from every pixel (coordinates >= 0, min_distance < |far|). int32 coordinates up to
# _I32_SPAN keep every d² (to the placeholder too) below 2**31: 2 * (2**14 + 2**13)² < 2**31.
_FAR = {torch.int32: -(1 << 13), torch.int64: -(1 << 28)}
_I32_SPAN = 1 << 14


class GreedyBudget(NamedTuple):
    """Fixed work of the capturable GFTT selection (per stream and call).

    ``block``: candidates kept per stream, the best in OpenCV's order (one top-k). The greedy
    minimum-distance pass runs in two stages: the ``first`` best candidates resolve among
    themselves in ``rounds_first`` rounds on a dense ``first x first`` conflict matrix; the rest
    of the block is tested against the corners accepted there, and its survivors (rank order
    kept, at most ``survivors`` of them) resolve among themselves in ``rounds`` rounds. Memory
    per stream ~``13 B x (first² + survivors²) + 9 B x block x max_corners``; kernels
    ~``130 + 4 x (rounds_first + rounds)`` per call (response included), whatever B and the data.
    """

    block: int
    first: int
    rounds_first: int
    survivors: int
    rounds: int


#: The tracker's budget: measured maxima with headroom. Measured through these kernels (1,800
#: calls) on what the tracker sees: max_cnt 150, quality 0.01, min_dist 30 / 25 / 20; the calls of
#: mono (CLAHE) and fusion (raw) trackers in steady state, with setMask's masks of the tracked
#: features; and every frame as a first frame (no mask, 150 new corners; CLAHE and raw). Frames:
#: EuRoC mini cam0 / cam1, V1_01 micro cam0 / cam1, the Middlebury pair, the synthetic flight.
#:
#: ==========================================================  =========  ======  ========
#: quantity (max over the calls)                               EuRoC      all     budget
#: ==========================================================  =========  ======  ========
#: candidate rank OpenCV's answer reaches (150th corner, or    1,995      2,763   8,192
#: every candidate where a stream runs out)
#: rounds until every first-stage (1,024) candidate decided    13         13      24
#: second-stage survivors up to the last kept corner           158        283     768
#: rounds until every second-stage survivor decided            11         11      24
#: ==========================================================  =========  ======  ========
#:
#: (the maxima: flight and Middlebury at min_dist 30; rounds: a tight distribution, mode 8.) The
#: kernel count (~320 per call) depends on the rounds only; the bmm of a round reads
#: ``4 B x (first² + survivors²)`` per stream.
GFTT_BUDGET = GreedyBudget(block=8192, first=1024, rounds_first=24, survivors=768, rounds=24)


@cached(64)
def _upper(n: int, device: torch.device) -> torch.Tensor:
    """(n, n) bool, True on and above the diagonal: ``[j, i]`` with ``j <= i`` in rank (cached)."""
    return torch.ones(n, n, dtype=torch.bool, device=device).triu()


@cached(64)
def _pixel_table(height: int, width: int, cell: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Raster index -> ``(x, y)`` (``cell > 0``: ``(x, y, x // cell, y // cell)``): (H*W, 2 | 4)
    integers, a cached constant (one gather replaces the div / mod / stack per call)."""
    i = torch.arange(height * width, device=device)
    cols = [i % width, torch.div(i, width, rounding_mode="floor")]
    if cell > 0:
        cols += [torch.div(cols[0], cell, rounding_mode="floor"), torch.div(cols[1], cell, rounding_mode="floor")]
    return torch.stack(cols, -1).to(dtype)


@cached(64)
def _iota(n: int, device: torch.device) -> torch.Tensor:
    """``arange(n)`` int64 (cached constant)."""
    return torch.arange(n, device=device)


def _resolve_fixed(conf: torch.Tensor, und: torch.Tensor, rounds: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """:func:`.selection._resolve_rounds` with a fixed number of rounds (no host check), 4 kernels a
    round.

    ``conf`` (B, C, C) bool, transposed conflicts *with the diagonal*: ``conf[b, j, i]`` iff
    ``j <= i`` in rank and j excludes i (every candidate excludes itself). ``und`` (B, C) bool.
    Returns ``accepted`` and ``undecided`` (B, C) bool after ``rounds`` rounds. Every decision
    taken is the sequential greedy one (by induction on rank); all is decided iff ``undecided``
    is empty, and above the first undecided candidate the result is exact.

    One state ``s`` per candidate: 0 rejected, 1 undecided, A accepted (A a power of two > C).
    ``c = s @ conf`` is ``s_i`` plus the higher conflicts' states: an undecided candidate has
    ``c = 1`` when every higher conflict is rejected (accept: s = A), ``2 <= c <= C`` while one is
    undecided (wait), ``c > A`` once one is accepted (reject: s = 0); an accepted one keeps ``c = A``
    (its higher conflicts are all rejected). So ``s *= h(c)`` with ``h = A, 1, 0`` on
    ``c <= 1.5 < c <= A + 0.5 < c``. Integers below 2**24: exact in float32 (TF32 too).
    """
    B, C = und.shape
    A = 1 << max(1, C.bit_length())  # > C
    dt = torch.float32 if (C + 1) * A < (1 << 24) else torch.float64
    dev = und.device
    bounds, table = _round_tables(A, dt, dev)
    s = und.to(dt).unsqueeze(1)  # (B, 1, C)
    conf = conf.to(dt)
    with _no_autocast(dev):  # a lower-precision matmul would not keep the counts exact
        for _ in range(rounds):
            s.mul_(table[torch.bucketize(torch.bmm(s, conf), bounds)])
    s = s.squeeze(1)
    return s == A, s == 1


@cached(64)
def _round_tables(A: int, dtype: torch.dtype, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    """:func:`_resolve_fixed`'s bucket bounds ``(1.5, A + 0.5)`` and factors ``(A, 1, 0)`` (cached)."""
    i = torch.arange(3, device=device, dtype=dtype)  # built on the device (no upload, traceable)
    return i[:2] * (A - 1) + 1.5, torch.where(i == 0, float(A), (i == 1).to(dtype))


def _no_autocast(device: torch.device):
    """A context without autocast for ``device`` when it is on (else a no-op)."""
    if torch.is_autocast_enabled(device.type):
        return torch.autocast(device.type, enabled=False)
    return contextlib.nullcontext()


def _conflicts(a: torch.Tensor, b: torch.Tensor, r2i: int, cells: bool) -> torch.Tensor:
    """OpenCV's GFTT conflicts of ``a`` (B, Ca, 2 | 4) and ``b`` (B, Cb, 2 | 4) integer ``(x, y[, cell
    x, cell y])`` -> (B, Ca, Cb) bool: ``d² < r2i`` (and, with ``cells``, neighbouring grid cells)."""
    d = a[:, :, None, :2] - b[:, None, :, :2]
    c = d.mul_(d).sum(-1, dtype=d.dtype) < r2i
    if cells:
        c &= (a[:, :, None, 2:] - b[:, None, :, 2:]).abs_().le_(1).all(-1)
    return c


def _greedy_capturable(xy: torch.Tensor, cvalid: torch.Tensor, mc: torch.Tensor, min_distance: float, kcap: int,
                   budget: GreedyBudget) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`.selection._greedy_accept` with a fixed schedule (:class:`GreedyBudget`'s two stages).

    ``xy`` (B, C, 2 | 4) integer positions (and grid cells) in rank order, ``cvalid`` (B, C),
    ``mc`` (B,) corner budgets <= ``kcap``. Returns ``accepted`` (B, C) bool, ``undecided``
    (B, C) bool (decisions the rounds left open) and ``n_surv`` (B,) (second-stage survivors,
    of which only ``budget.survivors`` are resolved). Every decision taken is the sequential
    greedy one; the result is OpenCV's above the first open decision.
    """
    B, C, nc = xy.shape
    dev = xy.device
    cells = nc == 4
    r2i = int(math.ceil(min_distance * min_distance))  # integer d²: d² < r²  <=>  d² < ceil(r²)
    far = _FAR[xy.dtype]
    F1 = min(budget.first, C)

    # stage 1: the best F1 candidates, dense
    cur = xy[:, :F1]
    und = cvalid[:, :F1] & (mc > 0)[:, None]
    conf = _conflicts(cur, cur, r2i, cells)  # d = 0 on the diagonal: a conflict, as _resolve_fixed wants
    conf &= _upper(F1, dev)
    acc1, left1 = _resolve_fixed(conf, und, budget.rounds_first)
    if F1 == C:
        return acc1, left1, torch.zeros(B, dtype=torch.long, device=dev)

    # the accepted corners in rank order in a (B, kcap + 1) buffer: free slots and the dump slot
    # (beyond kcap, and the rejected) hold a point farther than min_distance from every pixel
    slot = torch.cumsum(acc1, 1).sub_(1).clamp_max_(kcap)
    slot = torch.where(acc1, slot, kcap)
    buf = torch.full((B, kcap + 1, nc), far, dtype=xy.dtype, device=dev)
    buf.scatter_(1, slot[..., None].expand(B, F1, nc), cur)
    buf[:, kcap].fill_(far)
    count = acc1.sum(1)

    # stage 2: the rest, against stage 1's corners; the survivors compacted (rank order kept) into
    # S slots plus a dump slot, resolved among themselves
    rest = xy[:, F1:]
    R = C - F1
    S = min(budget.survivors, R)
    und = cvalid[:, F1:] & (count < mc)[:, None]  # streams still collecting
    und &= ~_conflicts(rest, buf, r2i, cells).any(-1)
    pos = torch.cumsum(und, 1)  # 1-based survivor index
    slot = torch.where(und, (pos - 1).clamp_max_(S), S)
    sur = torch.full((B, S + 1, nc), far, dtype=xy.dtype, device=dev)
    sur.scatter_(1, slot[..., None].expand(B, R, nc), rest)
    sv = torch.zeros(B, S + 1, dtype=torch.bool, device=dev)
    sv.scatter_(1, slot, und)
    sv[:, S].fill_(False)  # the dump slot is never a candidate
    conf = _conflicts(sur, sur, r2i, cells)
    conf &= _upper(S + 1, dev)
    acc2, left2 = _resolve_fixed(conf, sv, budget.rounds)
    accepted = torch.cat((acc1, torch.gather(acc2, 1, slot)), 1)
    undecided = torch.cat((left1, torch.gather(left2, 1, slot)), 1)
    return accepted, undecided, pos[:, -1]


def _select_corners_capturable(
    resp: torch.Tensor,
    mc: torch.Tensor,
    quality_level: float,
    min_distance: float,
    m: torch.Tensor | None,
    K: int,
    budget: GreedyBudget,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`.selection._select_corners` with fixed work (the ``capturable`` path), no input checks.

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
    t = torch.where(resp > thr[:, None, None], resp, 0.0)
    cand = _nms_candidates(t)
    if m is not None:
        cand &= m
    cand = cand.view(B, HW)
    n_cand = cand.sum(1)

    ib = max(1, (HW - 1).bit_length())  # bits of a raster index
    if resp.dtype == torch.float32 and ib <= 31:
        # unique int64 key, larger = earlier in OpenCV's order: float32 bits made order-preserving
        # as signed ints (negative values: flip the magnitude bits), then the raster index (ties:
        # later raster position first)
        bits = resp.reshape(B, HW).view(torch.int32).to(torch.int64)
        bits ^= (bits >> 31) & 0x7FFFFFFF
        key = torch.where(cand, (bits << ib) + _iota(HW, dev), _I64_MIN)
        top = torch.topk(key, Cb, dim=1)
        idx, cvalid = top.indices, top.values != _I64_MIN
    else:
        # general dtype: a stable descending sort of the reversed raster order (ties: later first)
        vals = torch.where(cand, resp.reshape(B, HW), float("-inf")).flip(1)
        srt = torch.sort(vals, dim=1, descending=True, stable=True)
        idx = (HW - 1) - srt.indices[:, :Cb]
        cvalid = srt.values[:, :Cb] != float("-inf")

    if min_distance < 1:  # OpenCV: no distance test, the first max_corners candidates
        xy = _pixel_table(H, W, 0, torch.int32, dev).index_select(0, idx.reshape(-1)).view(B, Cb, 2)
        accepted, undecided = cvalid, None
    else:
        cell = int(round(min_distance))  # cvRound (half to even)
        cells = cell < min_distance  # OpenCV's 3x3 cell neighbourhood matters only then
        # int32 coordinates while d² (also to the far placeholder) stays below 2**31
        cdt = torch.int32 if max(H, W) <= _I32_SPAN and min_distance < -_FAR[torch.int32] else torch.int64
        xy = _pixel_table(H, W, cell if cells else 0, cdt, dev).index_select(0, idx.reshape(-1))
        xy = xy.view(B, Cb, -1)
        accepted, undecided, n_surv = _greedy_capturable(xy, cvalid, mc, min_distance, K, budget)

    cum = torch.cumsum(accepted, 1)  # (B, Cb) int64: accepted up to and including each rank
    n_acc = cum[:, -1]
    # candidates that were never looked at (beyond the block, or second-stage survivors beyond
    # their slots: all ranked below every resolved one) matter iff fewer than mc corners were found
    short = n_cand > Cb
    if undecided is not None:
        short |= n_surv > min(budget.survivors, max(Cb - budget.first, 0))
    overflow = short & (n_acc < mc)
    if undecided is not None:
        # the first open decision matters iff fewer than mc corners were accepted above it
        overflow |= (undecided & (cum - accepted.long() < mc[:, None])).any(1)
    keep = accepted & (cum <= mc[:, None])
    # compact into (B, K): kept corners at b * K + rank, the rest into one dump slot
    slot = torch.where(keep, cum + _stream_offsets(B, K, dev), B * K)
    out = torch.zeros(B * K + 1, 2, dtype=resp.dtype, device=dev)
    out.index_put_((slot.view(-1),), xy[..., :2].reshape(-1, 2).to(resp.dtype))
    n = torch.minimum(n_acc, mc)
    valid = _iota(K, dev) < n[:, None]
    return out[:B * K].view(B, K, 2), valid, overflow


@cached(64)
def _stream_offsets(B: int, K: int, device: torch.device) -> torch.Tensor:
    """``b * K - 1`` per stream, (B, 1) int64 (cached constant): flat slot of rank ``cum - 1``."""
    return (torch.arange(B, device=device) * K - 1)[:, None]
