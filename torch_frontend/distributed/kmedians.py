"""``loop.Vocabulary.train`` with the training descriptors spread over the ranks of a process group:
the same vocabulary as one process with the same seed, bit for bit.

Convention:
    Rank ``r`` holds the documents (images) ``[D_0 + ... + D_{r-1}, ...)`` of the training set, in
    order (``env.shard_indices`` blocks), as ``(D_r, K_r, 4)`` packed descriptors with a ``valid``
    mask; the global descriptor order is rank 0's, then rank 1's, ... (what one process sees after
    ``pad_ragged`` of all documents). Every rank gets the whole vocabulary.

    Why it is exact (each step of ``loop.vocabulary._hkmeans`` / ``_kmedians_level``):

    * random draws: every rank holds the same generator (required: the global RNG's state differs
      between ranks) and draws the *global* vector (``torch.rand(N)``, ``N`` descriptors of the
      level), then takes its slice, and the keys' ``log`` is taken on the whole vector, as one
      process does;
    * "first maximum per group" (k-means++ seeding): an all-reduce MAX of the per-group maxima
      (exact), then an all-reduce MIN of the global indices that reach it (first wins, as in one
      process); the chosen descriptor comes from its rank by an int64 SUM with zeros elsewhere;
    * centres (bitwise majority): the per-(centre, bit) counts and the group sizes are integers,
      all-reduced as int32/int64 (exact in any order), and a bit is set iff ``2 count > size``
      (one process compares float32 counts, the same numbers below 2^24 members per centre);
    * group sizes, child numbering of groups of <= k descriptors (an exclusive prefix over ranks
      of each group's local count), convergence flags, IDF document counts: integer all-reduces;
    * assignments (nearest centre, first wins ties) are per descriptor, so local.

    Every rank runs the same collectives in the same order: control flow depends on reduced values
    only. ``group=None`` and no initialised process group: one process, ``Vocabulary.train``'s
    result.
"""

from __future__ import annotations

import math
import time
from typing import List, Optional

import torch

from ..errors import ConfigError
from ..loop.features import _unpack_bits
from ..loop.vocabulary import (
    _CHUNK,
    BINARY,
    L1_NORM,
    TF,
    TF_IDF,
    Vocabulary,
    _assign,
    _hamming_packed,
    _pack_bits,
)

__all__ = ["train_vocabulary"]


class _Comm:
    """All-reduces over ``group`` (identity for a single process)."""

    def __init__(self, group=None):
        import torch.distributed as dist

        self.dist = dist
        self.on = dist.is_available() and dist.is_initialized() and dist.get_world_size(group) > 1
        self.group = group
        self.rank = dist.get_rank(group) if self.on else 0
        self.world = dist.get_world_size(group) if self.on else 1

    def _reduce(self, t: torch.Tensor, op) -> torch.Tensor:
        if self.on:
            self.dist.all_reduce(t, op=op, group=self.group)
        return t

    def sum_(self, t: torch.Tensor) -> torch.Tensor:
        return self._reduce(t, self.dist.ReduceOp.SUM if self.on else None)

    def max_(self, t: torch.Tensor) -> torch.Tensor:
        return self._reduce(t, self.dist.ReduceOp.MAX if self.on else None)

    def min_(self, t: torch.Tensor) -> torch.Tensor:
        return self._reduce(t, self.dist.ReduceOp.MIN if self.on else None)

    def gather(self, t: torch.Tensor) -> torch.Tensor:
        """``(world, *t.shape)``: ``t`` of every rank (same shape on all)."""
        if not self.on:
            return t[None]
        parts: List[torch.Tensor] = [torch.empty_like(t) for _ in range(self.world)]
        self.dist.all_gather(parts, t.contiguous(), group=self.group)
        return torch.stack(parts)

    def offset(self, n: int, device) -> tuple:
        """``(this rank's offset, global total)`` of ``n`` items per rank (rank-major order)."""
        counts = self.gather(torch.tensor([n], dtype=torch.int64, device=device))[:, 0].tolist()
        return int(sum(counts[: self.rank])), int(sum(counts))


def _first_max(comm: _Comm, key: torch.Tensor, seg: torch.Tensor, m: int, offset: int, total: int) -> torch.Tensor:
    """Global index of the first maximum of ``key`` within each of ``m`` segments
    (``loop.vocabulary._segment_argmax`` over ranks)."""
    dev = key.device
    mx = torch.full((m,), -math.inf, dtype=key.dtype, device=dev)
    mx = comm.max_(mx.scatter_reduce(0, seg, key, "amax", include_self=True))
    ar = torch.arange(key.numel(), device=dev) + offset
    cand = torch.where(key == mx[seg], ar, torch.full_like(ar, total))
    first = torch.full((m,), total, dtype=torch.int64, device=dev)
    first = comm.min_(first.scatter_reduce(0, seg, cand, "amin", include_self=True))
    return first.clamp(max=max(total - 1, 0))


def _take(comm: _Comm, x: torch.Tensor, gidx: torch.Tensor, offset: int) -> torch.Tensor:
    """Rows ``gidx`` (global indices) of the distributed ``x (n, 4) int64``, on every rank."""
    loc = gidx - offset
    mine = (loc >= 0) & (loc < x.shape[0])
    out = torch.zeros(gidx.shape[0], 4, dtype=torch.int64, device=x.device)
    out[mine] = x[loc[mine]]
    return comm.sum_(out)  # one rank holds each row, the others add zeros: exact


def _rand(n: int, generator, device) -> torch.Tensor:
    """``(n,)`` float64 uniforms drawn on the generator's device, then moved to ``device`` (as
    ``loop.vocabulary`` draws them: a CPU generator with CUDA descriptors draws on the host)."""
    gdev = device if generator is None else generator.device
    return torch.rand(n, generator=generator, device=gdev, dtype=torch.float64).to(device)


def _kmedians_level(comm: _Comm, x, bits, g, m, k, generator, max_iter):
    """``loop.vocabulary._kmedians_level`` over ranks (``x``, ``bits``, ``g``: this rank's rows)."""
    dev = x.device
    n = x.shape[0]
    off, N = comm.offset(n, dev)
    cent = torch.zeros(m, k, 4, dtype=torch.int64, device=dev)
    ncent = torch.ones(m, dtype=torch.int64, device=dev)
    u = _rand(N, generator, dev)[off:off + n]
    cent[:, 0] = _take(comm, x, _first_max(comm, u, g, m, off, N), off)
    mind = _hamming_packed(x, cent[g, 0]).to(torch.float64)
    going = torch.ones(m, dtype=torch.bool, device=dev)
    for c in range(1, k):
        # sums of integer distances in float64: exact below 2^53, in any order
        dsum = comm.sum_(torch.zeros(m, dtype=torch.float64, device=dev).index_add_(0, g, mind))
        going = going & (dsum > 0)
        if not bool(going.any()):
            break
        u = _rand(N, generator, dev).clamp_min(1e-300)
        logu = torch.log(u)[off:off + n]  # log of the whole draw, as one process takes it
        key = torch.where(mind > 0, logu / mind.clamp_min(1e-300), torch.full_like(mind, -math.inf))
        rows = _take(comm, x, _first_max(comm, key, g, m, off, N), off)
        cent[going, c] = rows[going]
        ncent = torch.where(going, torch.full_like(ncent, c + 1), ncent)
        d = _hamming_packed(x, cent[g, c]).to(torch.float64)
        mind = torch.where(going[g], torch.minimum(mind, d), mind)
    assign = _assign(x, cent, g, ncent)
    live = torch.ones(m, dtype=torch.bool, device=dev)
    it = 0
    slots = torch.arange(k, device=dev)
    while True:
        sub = live[g].nonzero().squeeze(1)
        gs = g[sub]
        cid = gs * k + assign[sub]
        present = torch.zeros(m * k, dtype=torch.uint8, device=dev)
        present[cid] = 1
        uniq = comm.max_(present).nonzero().squeeze(1)  # the centres with members, ascending
        inv = torch.searchsorted(uniq, cid)
        flat = cent.view(m * k, 4)
        live_slots = (live[:, None] & (slots < ncent[:, None])).view(-1)
        flat[live_slots] = 0
        U = uniq.numel()
        counts = torch.zeros(U, 256, dtype=torch.int32, device=dev)
        bsub = bits[sub]
        for s in range(0, bsub.shape[0], _CHUNK):
            counts.index_add_(0, inv[s:s + _CHUNK], bsub[s:s + _CHUNK].to(torch.int32))
        comm.sum_(counts)
        sizes = comm.sum_(torch.bincount(inv, minlength=U))
        flat[uniq] = _pack_bits(2 * counts.to(torch.int64) > sizes[:, None])
        new = _assign(x[sub], cent, gs, ncent)
        changed = new != assign[sub]
        assign[sub] = new
        it += 1
        flags = torch.zeros(m, dtype=torch.uint8, device=dev)
        flags[gs[changed]] = 1
        live = comm.max_(flags).bool()
        if not bool(live.any()) or (max_iter is not None and it >= max_iter):
            break
    return cent, ncent, assign, it


def _hkmeans(comm: _Comm, x: torch.Tensor, k: int, L: int, generator, progress: bool, max_iter):
    """``loop.vocabulary._hkmeans`` over ranks: ``parent (M,)``, ``desc (M, 4)`` on every rank."""
    dev = x.device
    n = x.shape[0]
    parents = [torch.full((1,), -1, dtype=torch.int64, device=dev)]
    descs = [torch.zeros(1, 4, dtype=torch.int64, device=dev)]
    next_id = 1
    node = torch.zeros(n, dtype=torch.int64, device=dev)
    active = torch.ones(n, dtype=torch.bool, device=dev)
    bits = _unpack_bits(x)
    for lev in range(1, L + 1):
        t0 = time.perf_counter()
        idx = active.nonzero().squeeze(1)
        cnt = torch.zeros(next_id, dtype=torch.int64, device=dev)
        cnt = comm.sum_(cnt.index_add_(0, node[idx], torch.ones_like(idx)))
        P = (cnt > 0).nonzero().squeeze(1)  # parents with active descriptors, in id order
        if P.numel() == 0:
            break
        pl = torch.searchsorted(P, node[idx])
        m = P.numel()
        size = cnt[P]
        small_p = size <= k
        small = small_p[pl]
        ncent = torch.where(small_p, size, torch.zeros_like(size))
        local = torch.empty_like(idx)
        # small groups: one child per descriptor in the global descriptor order
        sl = pl[small]
        order = torch.sort(sl, stable=True).indices
        lcnt = torch.bincount(sl, minlength=m)
        start = torch.cumsum(lcnt, 0) - lcnt
        rank = torch.empty_like(sl)
        rank[order] = torch.arange(sl.numel(), device=dev) - start[sl[order]]
        below = comm.gather(lcnt)[: comm.rank].sum(0)  # the group's descriptors on lower ranks
        local[small] = rank + below[sl]
        big_p = ~small_p
        iters = 0
        cent = None
        if bool(big_p.any()):
            remap = torch.cumsum(big_p.to(torch.int64), 0) - 1
            bsel = (~small).nonzero().squeeze(1)
            gb = remap[pl[bsel]]
            mb = int(big_p.sum())
            cent, nc, a, iters = _kmedians_level(comm, x[idx[bsel]], bits[idx[bsel]], gb, mb, k, generator, max_iter)
            ncent[big_p] = nc
            local[bsel] = a
        base = next_id + torch.cumsum(ncent, 0) - ncent
        child = base[pl] + local
        T = int(ncent.sum())
        lvl_parent = torch.repeat_interleave(P, ncent)
        lvl_desc = torch.zeros(T, 4, dtype=torch.int64, device=dev)
        lvl_desc[child[small] - next_id] = x[idx[small]]
        comm.sum_(lvl_desc)  # each small child's descriptor lives on one rank: exact
        if cent is not None:  # the same centres on every rank: filled after the sum
            bb = base[big_p]
            slot = torch.arange(k, device=dev)
            ok = slot < ncent[big_p][:, None]
            lvl_desc[(bb[:, None] + slot - next_id)[ok]] = cent[ok]
        node[idx] = child
        csize = comm.sum_(torch.bincount(child - next_id, minlength=T))
        active[idx] = (csize[child - next_id] > 1) & (lev < L)
        parents.append(lvl_parent)
        descs.append(lvl_desc)
        next_id += T
        if progress and comm.rank == 0:
            print(f"[vocabulary] level {lev}: {m} parents ({int(big_p.sum())} clustered), "
                  f"{T} nodes, {iters} k-medians iterations, {time.perf_counter() - t0:.2f} s")
    return torch.cat(parents), torch.cat(descs)


def train_vocabulary(desc: torch.Tensor, valid: Optional[torch.Tensor] = None, k: int = 10, L: int = 6,
                     generator: Optional[torch.Generator] = None, progress: bool = False,
                     weighting: int = TF_IDF, scoring: int = L1_NORM, max_iter: Optional[int] = None,
                     group=None) -> Vocabulary:
    """``Vocabulary.train`` (hierarchical binary k-medians, DBoW2 ``create``) on the documents of
    every rank of ``group`` (default: the default process group; none initialised: this process).

    Args:
        desc: ``(D_r, K, 4)`` int64 packed descriptors of this rank's documents (module docstring);
            ``D_r`` may be 0.
        valid: ``(D_r, K)`` bool (default all).
        k, L, generator, progress, weighting, scoring, max_iter: as ``Vocabulary.train``;
            ``generator`` must be in the same state on every rank (the same seed). ``progress``
            prints on rank 0 only.
        group: the process group (every rank of it must call this function).

    Returns:
        the vocabulary (on ``desc.device``), the same on every rank and the same as
        ``Vocabulary.train`` of all documents in one process.
    """
    if k < 2 or L < 1:
        raise ConfigError(f"need k >= 2 and L >= 1, got k={k}, L={L}")
    if not isinstance(desc, torch.Tensor) or desc.dtype != torch.int64 or desc.ndim < 3 or desc.shape[-1] != 4:
        raise ValueError("desc: expected int64 (D, K, 4) training documents, got "
                         f"{getattr(desc, 'dtype', type(desc))} {tuple(getattr(desc, 'shape', ()))}")
    comm = _Comm(group)
    if generator is None and comm.world > 1:
        raise ValueError("generator: give every rank a torch.Generator seeded alike (the global RNG's state "
                         "differs between ranks, and every rank must draw the same numbers)")
    dev = desc.device
    K = desc.shape[-2]
    D = desc.numel() // (4 * K) if K else 0
    if valid is None:
        valid = torch.ones(desc.shape[:-1], dtype=torch.bool, device=dev)
    if valid.shape != desc.shape[:-1]:
        raise ValueError(f"valid: expected shape {tuple(desc.shape[:-1])}, got {tuple(valid.shape)}")
    vflat = valid.reshape(-1).to(torch.bool)
    x = desc.reshape(-1, 4)[vflat]
    doc = torch.arange(D, device=dev).repeat_interleave(K)[vflat]
    totals = comm.sum_(torch.tensor([x.shape[0], D], dtype=torch.int64, device=dev)).tolist()
    if totals[0] == 0:
        raise ValueError("desc: no valid training descriptors")
    D_all = int(totals[1])
    parent, ndesc = _hkmeans(comm, x, k, L, generator, progress, max_iter)
    M = parent.shape[0]
    cnt = torch.bincount(parent[1:], minlength=M)
    leaf = cnt == 0
    leaf[0] = False
    node_word = torch.full((M,), -1, dtype=torch.int64, device=dev)
    node_word[leaf] = torch.arange(int(leaf.sum()), device=dev)
    voc = Vocabulary(k, L, parent, ndesc, torch.zeros(M, dtype=torch.float64), node_word,
                     scoring=scoring, weighting=weighting)
    voc.to(dev)
    W = voc.num_words
    if weighting in (TF, BINARY):
        ww = torch.ones(W, dtype=torch.float64, device=voc.device)
    else:
        words = voc.node_word[voc._descend(x)] if x.shape[0] else torch.zeros(0, dtype=torch.int64, device=dev)
        pairs = torch.unique(doc * W + words)
        Ni = comm.sum_(torch.bincount(pairs % W, minlength=W)).to(torch.float64)  # documents: one rank each
        ww = torch.where(Ni > 0, torch.log(D_all / Ni.clamp_min(1)), torch.zeros_like(Ni))
    voc.node_weight[voc.word_node] = ww
    return voc
