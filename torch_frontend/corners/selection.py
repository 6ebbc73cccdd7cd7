"""The default (eager, host-driven) selection of ``goodFeaturesToTrack`` (spec §5.2): exact, all
candidates, work sized by the data.

The rules are OpenCV's: threshold relative to the maximum inside the mask, 3x3 dilation NMS with
equality, 1-pixel border, descending response with ties broken by later raster position first
(OpenCV's ``greaterThanPtr``), then greedy minimum-distance acceptance including OpenCV's grid
detail (a conflict needs ``d² < min_distance²`` *and* the two corners in the same or adjacent cells
of size ``cvRound(min_distance)``). The greedy pass is tensor code: candidates are processed in
rank chunks (128, 256, then 512) and, within a chunk, the survivors of the test against earlier
accepted corners in parallel rounds (:func:`_resolve_rounds`), which gives exactly the sequential
result. There is no candidate cap: on EuRoC frames (CLAHE, quality 0.01) there are ~5200-6400
candidates per frame and OpenCV's 150th corner is found at rank ~1500-1900, i.e. ~5 chunks; work
stops at the chunk where every stream has its ``max_corners``. Measured on the 24 repo frames:
identical corners in identical order to ``cv2.goodFeaturesToTrack``.

Speed (CPU, 1 thread): the candidates of all streams are one flat list (NMS by 1-D shifted
maxima, one ``nonzero``, two stable sorts), and image-sized passes run on groups of streams of
about one 752x480 frame (``_tuning.Strategy.corner_streams``); the host reads the candidate count
and checks each chunk and round (a few syncs per call).
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import torch

from .. import _tuning

__all__: list = []


def _select_corners(
    resp: torch.Tensor,
    mc: torch.Tensor,
    quality_level: float,
    min_distance: float,
    m: torch.Tensor | None,
    capacity: int | None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """GFTT selection on ``resp`` (B, H, W) float with ``mc`` (B,) int64 >= 0 corners per stream and
    ``m`` (B, H, W) bool or None; no input checks. See :func:`good_features_to_track`."""
    B, H, W = resp.shape
    dev = resp.device
    K = capacity if capacity is not None else (int(mc.max()) if B > 0 else 0)
    out_pts = torch.zeros(B, K, 2, dtype=resp.dtype, device=dev)
    out_valid = torch.zeros(B, K, dtype=torch.bool, device=dev)
    if K <= 0 or B == 0:
        return out_pts, out_valid
    mc = mc.clamp_max(K)
    strategy = _tuning.for_device(dev)

    # max inside the mask (VINS-Fusion-gpu#25); an empty mask gives maxVal 0 like minMaxLoc.
    if m is None:
        max_val = resp.flatten(1).amax(1)
    else:
        max_val = torch.where(m, resp, float("-inf")).flatten(1).amax(1)
    max_val = torch.where(torch.isfinite(max_val), max_val, torch.zeros_like(max_val))
    # threshold() on a float32 image casts its double threshold to float
    thr = (max_val.double() * float(quality_level)).to(resp.dtype)
    # candidates: t != 0 and t == its 3x3 dilation (border excluded), t = resp thresholded to 0.
    # On CPU by groups of streams (as _response_impl: image-sized temporaries stay cache-sized).
    # The candidates of all streams form one flat list of indices into (B*H*W,), raster order
    # (nonzero: one host sync per group, for its length).
    per = strategy.corner_streams(B, H, W) or B
    flats = []
    for b0 in range(0, B, per):
        r = resp[b0:b0 + per]
        t = torch.where(r > thr[b0:b0 + per, None, None], r, 0.0)
        cand = _nms_candidates(t)
        if m is not None:
            cand &= m[b0:b0 + per]
        f = cand.view(-1).nonzero().squeeze(1)
        flats.append(f + b0 * H * W if b0 else f)
    flat = flats[0] if len(flats) == 1 else torch.cat(flats)
    if flat.numel() == 0:
        return out_pts, out_valid
    # order per stream: response descending, ties later raster index first (greaterThanPtr)
    v = resp.reshape(-1)[flat]  # == t at candidates (t != 0 there)
    ib = max(1, (H * W - 1).bit_length())  # bits of a raster index
    if resp.dtype == torch.float32 and 32 + ib + max(1, (B - 1).bit_length()) <= 62:
        # one sort of a unique int64 key (stream, value descending, raster index descending).
        # float32 bits -> int with the same order (negative values: flip the magnitude bits)
        bits = v.view(torch.int32).to(torch.int64)
        bits = bits ^ ((bits >> 31) & 0x7FFFFFFF)
        b = torch.div(flat, H * W, rounding_mode="floor")
        pix = flat - b * (H * W)
        key = (b << (32 + ib)) + ((0x7FFFFFFF - bits) << ib) + ((1 << ib) - 1 - pix)
        o = torch.sort(key).indices
        b, pix = b[o], pix[o]
    else:
        # general: flip (-> stream and raster index descending), stable sort by value
        # descending, stable sort by stream ascending
        flat = flat.flip(0)
        flat = flat[torch.sort(v.flip(0), descending=True, stable=True).indices]
        b = torch.div(flat, H * W, rounding_mode="floor")
        sb = torch.sort(b, stable=True)
        b = sb.values
        flat = flat[sb.indices]
        pix = flat - b * (H * W)
    counts = torch.bincount(b, minlength=B)
    M = int(counts.max())  # host sync: the candidate count decides the work
    rank = torch.arange(flat.numel(), device=dev) - (torch.cumsum(counts, 0) - counts)[b]
    slot = b * M + rank
    pos_flat = torch.zeros(B * M, 2, dtype=torch.long, device=dev)
    pos_flat[slot, 0] = pix % W
    pos_flat[slot, 1] = torch.div(pix, W, rounding_mode="floor")
    cvalid = torch.zeros(B * M, dtype=torch.bool, device=dev)
    cvalid[slot] = True
    pos = pos_flat.view(B, M, 2)  # (B, M, 2) long, rank order
    cvalid = cvalid.view(B, M)

    accepted = _greedy_accept(pos, cvalid, mc, min_distance, strategy.gftt_chunk, strategy.gftt_chunk_max)

    # cut at max_corners by rank and compact into (B, K)
    rank = torch.cumsum(accepted.long(), 1) - 1
    keep = accepted & (rank < mc[:, None])
    slot = torch.where(keep, rank, torch.full_like(rank, K))  # K = dump slot
    pts_buf = torch.zeros(B, K + 1, 2, dtype=resp.dtype, device=dev)
    pts_buf.scatter_(1, slot[..., None].expand(B, M, 2), pos.to(resp.dtype))
    val_buf = torch.zeros(B, K + 1, dtype=torch.bool, device=dev)
    val_buf.scatter_(1, slot, keep)
    out_valid = val_buf[:, :K]
    out_pts = torch.where(out_valid[..., None], pts_buf[:, :K], torch.zeros_like(pts_buf[:, :K]))
    return out_pts, out_valid


def _resolve_rounds(conf_t: torch.Tensor, und: torch.Tensor) -> torch.Tensor:
    """Greedy acceptance in parallel rounds.

    ``conf_t`` (B, C, C) float 0/1, *transposed* conflicts: ``conf_t[b, j, i] = 1`` iff j is
    ranked above i and accepting j excludes i. ``und`` (B, C) bool: candidates still to decide
    (others are out). Returns accepted (B, C): i accepted iff no accepted j conflicts with it -
    the sequential greedy result. Each round rejects candidates with an accepted higher conflict
    and accepts those whose higher conflicts are all decided; the highest undecided one is
    always decided, and real data needs a handful of rounds (one host check each).
    """
    acc = torch.zeros_like(und)
    if not bool(und.any()):
        return acc
    # state rows: [accepted, undecided] as 0/1 floats
    state = torch.zeros(und.shape[0], 2, und.shape[1], dtype=conf_t.dtype, device=und.device)
    state[:, 1] = und
    while True:
        # one (B, 2, C) x (B, C, C) matmul answers both questions for every i: any accepted /
        # any undecided higher conflict (this layout is ~4x faster on CPU than (B, C, C) x
        # (B, C, 2); counts are small integers, exact in float32)
        blocked, waiting = (torch.bmm(state, conf_t) > 0).unbind(1)
        und = und & ~blocked  # rejected: an accepted higher conflict
        acc |= und & ~waiting  # accepted: every higher conflict decided, none accepted
        und &= waiting
        if not bool(und.any()):
            return acc
        state[:, 0] = acc
        state[:, 1] = und


def _nms_candidates(t: torch.Tensor, above: Optional[torch.Tensor] = None, windowed: bool = False) -> torch.Tensor:
    """``t != 0 & t == dilate3x3(t)`` of (B, H, W), False on the 1-pixel image border.

    The 3x3 max is taken on the flat (B*H*W,) buffer with 1-D shifts (contiguous, vectorised
    maxima; ~10x faster on CPU than 2-D slices or ``max_pool2d``). A shift by one mixes the end
    of a row with the start of the next, and a shift by W mixes streams, but only in windows
    centred on border pixels, which are never candidates.

    ``windowed`` (the capturable path's; ``t`` contiguous, no NaN): the same maximum as one
    reduction over overlapping 3x3 windows of the same flat buffer (each value read once instead
    of four pairwise maxima; a maximum is exact and, without NaN, independent of the order, so
    the same candidates). ``above`` (B, H, W) bool: instead of ``t != 0``, the centre must be
    ``above``.
    """
    B, H, W = t.shape
    cand = torch.zeros(B, H, W, dtype=torch.bool, device=t.device)
    N = B * H * W
    if H < 3 or W < 3:
        return cand
    f = t.reshape(-1)
    if windowed:  # d[k]: 3x3 max centred on k + W + 1
        d = f.as_strided((N - 2 * W - 2, 3, 3), (1, W, 1)).amax((1, 2))
    else:
        r = torch.maximum(f[:-2], f[1:-1])  # r[j]: row max centred on j + 1
        r = torch.maximum(r, f[2:], out=r)
        d = torch.maximum(r[:-2 * W], r[W:-W])  # d[k]: 3x3 max centred on k + W + 1
        d = torch.maximum(d, r[2 * W:], out=d)
    centre = f[W + 1:N - W - 1]
    c = cand.view(-1)[W + 1:N - W - 1]
    torch.eq(centre, d, out=c)
    c &= (centre != 0) if above is None else above.reshape(-1)[W + 1:N - W - 1]
    # fill_ on views, not ``cand[...] = False`` (a Python scalar is uploaded as a tensor first)
    cand[:, ::H - 1, :].fill_(False)  # rows 0 and H - 1
    cand[:, :, ::W - 1].fill_(False)  # columns 0 and W - 1
    return cand


def _greedy_accept(pos: torch.Tensor, cvalid: torch.Tensor, mc: torch.Tensor, min_distance: float,
                   chunk: int, chunk_max: int) -> torch.Tensor:
    """Exact sequential greedy minimum-distance acceptance, in tensor rounds.

    ``pos`` (B, M, 2) integer pixel positions in rank order, ``cvalid`` (B, M), ``mc`` (B,) the
    per-stream corner budget (acceptance stops mattering once a stream has ``mc`` corners).
    Returns ``accepted`` (B, M) bool: candidate i accepted iff no *accepted* higher-ranked
    candidate conflicts with it - exactly OpenCV's sequential loop.

    Candidates are processed in rank chunks of ``chunk``, doubling up to ``chunk_max`` (speed and
    memory only: ``_tuning.Strategy.gftt_chunk``). A
    chunk's candidates first test the corners accepted in earlier chunks (a fixed buffer of
    max(mc) slots); the survivors are compacted (rank order kept) and resolve among themselves
    in rounds: every undecided candidate with an accepted higher
    conflict is rejected; every undecided candidate whose higher conflicts are all decided (none
    accepted) is accepted. By induction on rank this is the greedy result, and each round
    decides at least the highest undecided candidate. Chunks stop once every stream has its
    ``mc`` corners or has run out of candidates (one host check per chunk and per round).
    """
    B, M, _ = pos.shape
    dev = pos.device
    accepted = torch.zeros(B, M, dtype=torch.bool, device=dev)
    if min_distance < 1:
        # OpenCV: no distance test, simply the first max_corners candidates
        return cvalid.clone()
    cell = int(round(min_distance))  # cvRound (half to even)
    r2i = int(math.ceil(min_distance * min_distance))  # integer d²: d² < r²  <=>  d² < ceil(r²)
    # chunks are small, so d² by broadcasting in int32 is cheap (and, unlike a matmul, immune to
    # TF32 on CUDA). Coordinates < 2**15 keep d² < 2**31.
    pi = pos.to(torch.int32) if int(pos.max()) < 32768 else pos
    # separate contiguous x / y: broadcasting strided slices is several times slower on CPU
    xs, ys = pi[..., 0].contiguous(), pi[..., 1].contiguous()
    # OpenCV only looks at the 3x3 neighbouring cells of size cvRound(min_distance); when that
    # rounds down, pairs in cells two apart are not conflicts. Only then test the cells.
    need_cells = cell < min_distance
    gx, gy = xs // cell, ys // cell

    def conflicts(a, b) -> torch.Tensor:
        """a, b: (x, y, cell x, cell y) tuples of (B, Ca) / (B, Cb) -> (B, Ca, Cb) bool."""
        # in place: (B, Ca, Cb) temporaries of several MB at B=8 cost page faults when fresh
        dx = a[0][:, :, None] - b[0][:, None, :]
        dx *= dx
        dy = a[1][:, :, None] - b[1][:, None, :]
        dy *= dy
        dx += dy
        c = dx < r2i
        if need_cells:
            c &= (a[2][:, :, None] - b[2][:, None, :]).abs() <= 1
            c &= (a[3][:, :, None] - b[3][:, None, :]).abs() <= 1
        return c

    # accepted corners of earlier chunks: fixed-capacity buffer of Kcap = max(mc) slots plus a
    # dump slot. A stream only collects while it has < mc <= Kcap corners, so it never needs more.
    kcap = int(mc.max()) if B > 0 else 0
    acc_buf = tuple(torch.zeros(B, kcap + 1, dtype=t.dtype, device=dev) for t in (xs, ys, gx, gy))
    acc_ok = torch.zeros(B, kcap + 1, dtype=torch.bool, device=dev)
    count = torch.zeros(B, dtype=torch.long, device=dev)
    filled = 0  # max(count), capped at kcap (host copy)
    start, size = 0, chunk
    while start < M:
        stop = min(start + size, M)
        # later chunks are mostly rejected by the accepted buffer: grow them (fewer rounds of
        # Python overhead) while the survivors alone enter the quadratic in-chunk resolution
        size = min(2 * size, chunk_max)
        live = count < mc  # streams still collecting
        v = cvalid[:, start:stop] & live[:, None]
        if not bool(v.any()):
            break
        cur = tuple(t[:, start:stop] for t in (xs, ys, gx, gy))
        und = v
        if filled > 0:  # only the filled part of the buffer (slots >= a stream's count are off)
            hit = conflicts(cur, tuple(t[:, :filled] for t in acc_buf))
            hit &= acc_ok[:, None, :filled]
            und = v & ~hit.any(-1)
        S = int(und.sum(1).max())
        if S > 0:
            # compact the survivors (rank order kept) and resolve them among themselves
            order = torch.sort(und.to(torch.uint8), dim=1, descending=True, stable=True).indices[:, :S]
            sur = tuple(torch.gather(t, 1, order) for t in cur)
            sv = torch.gather(und, 1, order)
            conf = conflicts(sur, sur)  # symmetric; transposed layout [j, i] for _resolve_rounds
            conf &= torch.ones(S, S, dtype=torch.bool, device=dev).triu(1)  # j < i: j ranked higher
            conf &= sv[:, :, None]
            acc = _resolve_rounds(conf.to(torch.float32), sv)
            accepted[:, start:stop].scatter_(1, order, acc)
            # append to the buffer in rank order (beyond kcap -> dump slot)
            slot = torch.cumsum(acc, 1) - 1 + count[:, None]
            slot = torch.where(acc & (slot < kcap), slot, kcap)
            for buf, t in zip(acc_buf, sur):
                buf.scatter_(1, slot, t)
            acc_ok.scatter_(1, slot, acc)
            acc_ok[:, kcap] = False
            count += acc.sum(1)
            filled = min(int(count.max()), kcap)
        start = stop
    return accepted


