"""Bag of binary words: a DBoW2-style hierarchical vocabulary for 256-bit BRIEF descriptors.

Convention:
    * Descriptors are packed ``(..., K, 4) int64``: bit ``i`` of the 256-bit BRIEF string is bit
      ``i mod 64`` of word ``i div 64`` (the layout of VINS's ``brief_k10L6.bin`` and of
      ``boost::dynamic_bitset`` blocks). A ``valid (..., K) bool`` mask marks real descriptors.
    * Tree: node 0 is the root (parent ``-1``); every other node has a parent, a packed descriptor
      and a weight; leaves carry a word id. Children keep the order in which they were appended to
      their parent (file order for loaded vocabularies, cluster order for trained ones), because
      the descent breaks distance ties in favour of the FIRST child (DBoW2: strict ``<``).
    * A bag of words is a :class:`BowVector` ``(words (B, K) int64, weights (B, K) float64)``: per
      document the distinct word ids in ascending order followed by ``-1`` padding (weight 0). It
      is the sparse analogue of DBoW2's ``std::map<WordId, WordValue>``; ``K`` is the descriptor
      capacity, so no document can overflow. ``bow_to_dense`` gives ``(B, W)`` for small ``W``.

Transform (DBoW2 ``TemplatedVocabulary::transform``): from the root pick the child with the smallest
Hamming distance (first child wins ties) until a leaf; word weight = leaf weight (IDF for TF_IDF/IDF,
1 for TF/BINARY); words with weight ``<= 0`` are skipped (stop words, e.g. ``ln(N/N) = 0``). TF and
TF_IDF sum the weights of repeated words, IDF and BINARY keep one copy (``addIfNotExist``). Then the
vector is normalised as the scoring type requires (L1 for L1/CHI_SQUARE/KL/BHATTACHARYYA, L2 for
L2, none for DOT_PRODUCT). DBoW2 skips the ``1/n`` TF factor whenever it normalises, and so do we:
after L1 normalisation ``count/n`` and ``count`` give the same vector.

Training (DBoW2 ``create`` = hierarchical k-medians, ``HKmeansStep``), done level by level with all
nodes of a level processed together:
    * a node with ``<= k`` descriptors gets one child per descriptor (duplicates included);
    * otherwise k-means++ seeding: first centre uniform, each next one drawn with probability
      proportional to the Hamming distance ``D(x)`` to the nearest chosen centre (DBoW2's comment
      says ``D(x)^2`` but its code uses the plain distance; we follow the code). When all ``D(x)``
      are 0 seeding stops early (fewer than ``k`` children, as DBoW2);
    * iterate: assign to the nearest centre (first wins ties), centre = bitwise majority of its
      group, bit set iff ``count > n/2`` (DBoW2 ``FBrief::meanValue``: ties give 0, an empty group
      gives the all-zero descriptor and still becomes a child); stop when no assignment changes;
    * children with more than one descriptor are split again while ``level < L``;
    * leaves get word ids in node-id order; IDF weight ``ln(N / N_i)`` with ``N`` the number of
      training documents and ``N_i`` the number of documents in which some descriptor TRANSFORMS
      to word ``i`` (DBoW2 ``setNodeWeights``), 0 when ``N_i = 0``.
    Deviation: node ids are assigned breadth-first (level by level), DBoW2's depth-first. Only the
    numbering differs; the random draws are torch's, so trees are not bit-identical to DBoW2's.
"""

from __future__ import annotations

import math
import os
import re
import time
from pathlib import Path
from typing import NamedTuple, Optional, Sequence, Union

import numpy as np
import torch

from ..errors import ConfigError
from .features import _unpack_bits

__all__ = [
    "BowVector",
    "Vocabulary",
    "bow_to_dense",
    "L1_NORM",
    "L2_NORM",
    "CHI_SQUARE",
    "KL",
    "BHATTACHARYYA",
    "DOT_PRODUCT",
    "TF_IDF",
    "TF",
    "IDF",
    "BINARY",
]

# DBoW2 enum codes (ScoringType, WeightingType).
L1_NORM, L2_NORM, CHI_SQUARE, KL, BHATTACHARYYA, DOT_PRODUCT = range(6)
TF_IDF, TF, IDF, BINARY = range(4)

_FORMAT = "torch_frontend.vocabulary/1"
_CHUNK = 1 << 16  # rows per chunk in the distance kernels: bounds the (n, k, 4) temporaries
_BIG = 1 << 20  # distance of a missing child / centre (> 256)

PathLike = Union[str, os.PathLike]


class BowVector(NamedTuple):
    """Sparse bags of words: ``words (B, K) int64`` ascending then ``-1``; ``weights (B, K)``."""

    words: torch.Tensor
    weights: torch.Tensor


# ----------------------------------------------------------------------------------------------
# Bit helpers (private: the public Hamming lives in loop/features.py)


def _popcount_bytes(x: torch.Tensor) -> torch.Tensor:
    """Popcount of every byte of int64 ``x``: ``(..., n) -> (..., 8n) uint8``.

    SWAR on unsigned bytes: uint8 arithmetic wraps by definition and shifts are logical, so no
    sign-extension or signed overflow can creep in, and a SIMD lane holds 8x more bytes than
    int64 words (about 6x faster than SWAR on int64 halves on CPU).
    """
    h = x.contiguous().view(torch.uint8)
    h = h - ((h >> 1) & 0x55)
    h = (h & 0x33) + ((h >> 2) & 0x33)
    return (h + (h >> 4)) & 0x0F


def _hamming_packed(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamming distance of broadcastable packed descriptors ``(..., 4) -> (...) int32``."""
    a, b = torch.broadcast_tensors(a, b)
    h = _popcount_bytes(a ^ b)  # (..., 32) bytes <= 8
    # Pairwise halving adds stay in uint8 (<= 128 after four rounds); cheaper than a reduction
    # kernel over a 32-wide last dimension.
    h = h[..., :16] + h[..., 16:]
    h = h[..., :8] + h[..., 8:]
    h = h[..., :4] + h[..., 4:]
    h = h[..., :2] + h[..., 2:]
    return h[..., 0].to(torch.int32) + h[..., 1]


def _pack_bits(bits: torch.Tensor) -> torch.Tensor:
    """``(..., 256) bool/int -> (..., 4) int64`` (inverse of ``_unpack_bits``)."""
    shifts = torch.arange(64, device=bits.device, dtype=torch.int64)
    b = bits.reshape(*bits.shape[:-1], 4, 64).to(torch.int64)
    # Distinct powers of two: the sum never carries; bit 63 contributes INT64_MIN (two's complement).
    return (b << shifts).sum(-1)


class _OneProcess:
    """The communicator of one process: every reduction is the identity.

    Training takes a communicator so that ``distributed.kmedians`` runs the same code over the
    ranks of a process group (its ``_Comm`` has these methods, with all-reduces): ``sum_``,
    ``max_``, ``min_`` reduce in place and return the tensor, ``gather`` stacks every rank's
    tensor, ``offset`` places this rank's items in the global (rank-major) order, ``take`` fetches
    rows by global index from the rank that holds them, ``unique`` gives the ids present on any
    rank. Here they cost nothing, so the single-process path runs the plain algorithm.
    """

    rank = 0
    world = 1

    def sum_(self, t: torch.Tensor) -> torch.Tensor:
        return t

    max_ = min_ = sum_

    def gather(self, t: torch.Tensor) -> torch.Tensor:
        """``(world, *t.shape)``: ``t`` of every rank."""
        return t[None]

    def offset(self, n: int, device) -> tuple:
        """``(this rank's offset, global total)`` of ``n`` items per rank."""
        return 0, n

    def take(self, x: torch.Tensor, gidx: torch.Tensor, offset: int) -> torch.Tensor:
        """Rows ``gidx`` (global indices; this rank holds ``offset ..``) of ``x``, on every rank."""
        return x[gidx]

    def unique(self, ids: torch.Tensor, size: int) -> tuple:
        """``(ids present on any rank (ascending), index of each of ``ids`` in them)``; ids in
        ``[0, size)``."""
        return torch.unique(ids, return_inverse=True)


_ONE_PROCESS = _OneProcess()


def _segment_argmax(key: torch.Tensor, seg: torch.Tensor, m: int, comm=_ONE_PROCESS, offset: int = 0,
                    total: Optional[int] = None) -> torch.Tensor:
    """Index of the first maximum of ``key`` within each of ``m`` segments.

    Over ranks (``comm``): ``key`` holds the global items ``offset ..`` of ``total``; the result is
    a global index, the same on every rank (MAX of the maxima, then MIN of the indices reaching it:
    the first wins, as in one process).
    """
    n = key.numel() if total is None else total
    mx = torch.full((m,), -math.inf, dtype=key.dtype, device=key.device)
    mx = comm.max_(mx.scatter_reduce(0, seg, key, "amax", include_self=True))
    ar = torch.arange(offset, offset + key.numel(), device=key.device)
    cand = torch.where(key == mx[seg], ar, torch.full_like(ar, n))
    first = torch.full((m,), n, dtype=torch.int64, device=key.device)
    first = comm.min_(first.scatter_reduce(0, seg, cand, "amin", include_self=True))
    return first.clamp(max=max(n - 1, 0))


def _assign(x: torch.Tensor, cent: torch.Tensor, g: torch.Tensor, ncent: torch.Tensor) -> torch.Tensor:
    """Nearest centre (first wins ties) of each descriptor ``x (n, 4)`` among ``cent[g] (n, k, 4)``.

    XOR + popcount on the gathered centres. (A padded per-group ±1 matmul was tried: on the
    memory-bound 2-core CI box its buffer traffic made it slower; on a GPU it may win.)
    """
    k = cent.shape[1]
    out = torch.empty(x.shape[0], dtype=torch.int64, device=x.device)
    ar = torch.arange(k, device=x.device)
    for s in range(0, x.shape[0], _CHUNK):
        gs = g[s:s + _CHUNK]
        d = _hamming_packed(x[s:s + _CHUNK, None, :], cent[gs])
        d = d.masked_fill(ar >= ncent[gs, None], _BIG)
        out[s:s + _CHUNK] = d.argmin(1)  # torch.argmin returns the first minimum
    return out


def _majority(bits: torch.Tensor, grp: torch.Tensor, m: int, comm=_ONE_PROCESS) -> torch.Tensor:
    """Per-group bitwise majority (``2*count > n``) of ``bits (n, 256)``: ``(m, 4) int64``.

    float32 counts (``index_add_`` is faster in float32 than in int32 on CPU) are exact integers
    below 2^24 members per group, so their sum over ranks is exact in any order.
    """
    counts = torch.zeros(m, 256, dtype=torch.float32, device=bits.device)
    for s in range(0, bits.shape[0], _CHUNK):
        counts.index_add_(0, grp[s:s + _CHUNK], bits[s:s + _CHUNK].to(torch.float32))
    comm.sum_(counts)
    sizes = comm.sum_(torch.bincount(grp, minlength=m)).to(torch.float32)
    return _pack_bits(2.0 * counts > sizes[:, None])


def _rand(n: int, generator: Optional[torch.Generator], device: torch.device) -> torch.Tensor:
    """``(n,)`` float64 uniforms on ``device``, drawn on the generator's own device (a CPU
    generator with CUDA data draws on the host and uploads; ``torch.rand`` would reject it)."""
    gdev = device if generator is None else generator.device
    return torch.rand(n, generator=generator, device=gdev, dtype=torch.float64).to(device)


def _kmedians_level(x, bits, g, m, k, generator, max_iter, comm=_ONE_PROCESS):
    """Binary k-medians with k-means++ seeding for ``m`` independent groups at once.

    Args:
        x: (n, 4) int64 descriptors; bits: (n, 256) uint8 unpacked; g: (n,) group in [0, m).
        comm: the communicator (``_OneProcess``; over ranks: this rank's rows of the groups).
    Returns:
        cent (m, k, 4) int64, ncent (m,) int64 centres per group, assign (n,) int64, iterations.
    """
    dev = x.device
    n = x.shape[0]
    off, N = comm.offset(n, dev)
    cent = torch.zeros(m, k, 4, dtype=torch.int64, device=dev)
    ncent = torch.ones(m, dtype=torch.int64, device=dev)
    # 1. First centre uniformly at random per group (max of iid uniforms = uniform choice).
    # Every rank draws the global vector and takes its slice.
    u = _rand(N, generator, dev)[off:off + n]
    cent[:, 0] = comm.take(x, _segment_argmax(u, g, m, comm, off, N), off)
    mind = _hamming_packed(x, cent[g, 0]).to(torch.float64)
    going = torch.ones(m, dtype=torch.bool, device=dev)
    for c in range(1, k):
        # sums of integer distances in float64: exact below 2^53, in any order
        dsum = comm.sum_(torch.zeros(m, dtype=torch.float64, device=dev).index_add_(0, g, mind))
        going = going & (dsum > 0)
        if not bool(going.any()):
            break
        # 2. Draw one point per group with probability ∝ D(x): Efraimidis–Spirakis keys
        # log(u)/w, max per group (w = 0 gives -inf and is never drawn while some w > 0).
        u = _rand(N, generator, dev).clamp_min(1e-300)
        logu = torch.log(u)[off:off + n]  # the log of the whole draw, as one process takes it
        key = torch.where(mind > 0, logu / mind.clamp_min(1e-300), torch.full_like(mind, -math.inf))
        rows = comm.take(x, _segment_argmax(key, g, m, comm, off, N), off)
        cent[going, c] = rows[going]
        ncent = torch.where(going, torch.full_like(ncent, c + 1), ncent)
        d = _hamming_packed(x, cent[g, c]).to(torch.float64)
        mind = torch.where(going[g], torch.minimum(mind, d), mind)
    assign = _assign(x, cent, g, ncent)
    live = torch.ones(m, dtype=torch.bool, device=dev)
    it = 0
    slots = torch.arange(k, device=dev)
    while True:
        # Groups whose assignment did not change are converged: recomputing their centres would
        # reproduce the same centres and assignment, so only live groups are iterated.
        sub = live[g].nonzero().squeeze(1)
        gs = g[sub]
        cid = gs * k + assign[sub]
        uniq, inv = comm.unique(cid, m * k)  # the centres with members, ascending
        flat = cent.view(m * k, 4)
        # Every centre of a live group is recomputed; an empty group's mean is all zeros (DBoW2).
        live_slots = (live[:, None] & (slots < ncent[:, None])).view(-1)
        flat[live_slots] = 0
        flat[uniq] = _majority(bits[sub], inv, uniq.numel(), comm)
        new = _assign(x[sub], cent, gs, ncent)
        changed = new != assign[sub]
        assign[sub] = new
        it += 1
        flags = torch.zeros(m, dtype=torch.uint8, device=dev)  # uint8: all-reducible
        flags[gs[changed]] = 1
        live = comm.max_(flags).bool()
        if not bool(live.any()) or (max_iter is not None and it >= max_iter):
            break
    return cent, ncent, assign, it


def _hkmeans(x: torch.Tensor, k: int, L: int, generator, progress: bool, max_iter, comm=_ONE_PROCESS):
    """Hierarchical k-medians; returns ``parent (M,)`` and ``desc (M, 4)`` in node-id order
    (over ranks, ``comm``: ``x`` is this rank's rows, the result is the same on every rank)."""
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
        P, pl = comm.unique(node[idx], next_id)  # parents with active descriptors, in id (= creation) order
        if P.numel() == 0:
            break
        m = P.numel()
        size = comm.sum_(torch.bincount(pl, minlength=m))
        small_p = size <= k
        small = small_p[pl]
        ncent = torch.where(small_p, size, torch.zeros_like(size))
        local = torch.empty_like(idx)
        # Small groups: one child per descriptor, in the global descriptor order (stable sort
        # keeps it; the group's descriptors on lower ranks come first).
        sl = pl[small]
        order = torch.sort(sl, stable=True).indices
        lcnt = torch.bincount(sl, minlength=m)
        start = torch.cumsum(lcnt, 0) - lcnt
        rank = torch.empty_like(sl)
        rank[order] = torch.arange(sl.numel(), device=dev) - start[sl[order]]
        if comm.world > 1:  # a collective: every rank takes part
            rank += comm.gather(lcnt)[: comm.rank].sum(0)[sl]
        local[small] = rank
        big_p = ~small_p
        iters = 0
        cent = None
        if bool(big_p.any()):
            remap = torch.cumsum(big_p.to(torch.int64), 0) - 1
            bsel = (~small).nonzero().squeeze(1)
            gb = remap[pl[bsel]]
            mb = int(big_p.sum())
            cent, nc, a, iters = _kmedians_level(x[idx[bsel]], bits[idx[bsel]], gb, mb, k, generator, max_iter,
                                                 comm)
            ncent[big_p] = nc
            local[bsel] = a
        base = next_id + torch.cumsum(ncent, 0) - ncent
        child = base[pl] + local
        T = int(ncent.sum())
        lvl_parent = torch.repeat_interleave(P, ncent)
        lvl_desc = torch.zeros(T, 4, dtype=torch.int64, device=dev)
        lvl_desc[child[small] - next_id] = x[idx[small]]
        comm.sum_(lvl_desc)  # over ranks: each small child's descriptor lives on one rank, exact
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


# ----------------------------------------------------------------------------------------------


def bow_to_dense(bow: BowVector, num_words: int) -> torch.Tensor:
    """Dense ``(B, num_words)`` copy of a :class:`BowVector` (tests / small vocabularies)."""
    words, weights = bow
    out = torch.zeros(words.shape[0], num_words + 1, dtype=weights.dtype, device=weights.device)
    idx = torch.where(words >= 0, words, torch.full_like(words, num_words))
    out.scatter_add_(1, idx, weights)
    return out[:, :num_words]


def _aggregate(words: torch.Tensor, weights: torch.Tensor, summed: bool) -> BowVector:
    """Merge repeated words per row: ``(B, K)`` ids (``-1`` = none) -> sorted distinct ids."""
    B, K = words.shape
    sentinel = torch.iinfo(torch.int64).max
    key = torch.where(words >= 0, words, torch.full_like(words, sentinel))
    skey, perm = torch.sort(key, dim=1, stable=True)
    sw = weights.gather(1, perm)
    first = torch.ones_like(skey, dtype=torch.bool)
    first[:, 1:] = skey[:, 1:] != skey[:, :-1]
    grp = torch.cumsum(first.to(torch.int64), 1) - 1
    out_w = torch.full_like(words, sentinel).scatter(1, grp, skey)
    if summed:
        out_v = torch.zeros_like(weights).scatter_add(1, grp, sw)
    else:  # addIfNotExist: all copies carry the same weight
        out_v = torch.zeros_like(weights).scatter_reduce(1, grp, sw, "amax", include_self=False)
    none = out_w == sentinel
    return BowVector(out_w.masked_fill(none, -1), out_v.masked_fill(none, 0.0))


class Vocabulary:
    """Hierarchical vocabulary of binary words (DBoW2 ``TemplatedVocabulary<FBrief>``).

    Build with :meth:`train`, :meth:`load`, :meth:`load_vins_bin` or :meth:`load_dbow2_yaml`.

    Attributes (tensors on ``self.device``):
        parent (M,) int64 (root -1), node_desc (M, 4) int64, node_weight (M,) float64,
        node_word (M,) int64 (-1 for inner nodes), word_node (W,) int64,
        children (M, kmax) int64 padded with -1 (child order matters for ties), is_leaf (M,).
    """

    def __init__(self, k: int, L: int, parent, node_desc, node_weight, node_word,
                 scoring: int = L1_NORM, weighting: int = TF_IDF, order: Optional[Sequence[int]] = None,
                 source: str = "<memory>"):
        parent = np.asarray(torch.as_tensor(parent).cpu(), dtype=np.int64).reshape(-1)
        M = parent.shape[0]
        node_desc = torch.as_tensor(node_desc, dtype=torch.int64).cpu()
        node_weight = torch.as_tensor(node_weight, dtype=torch.float64).cpu()
        node_word = np.asarray(torch.as_tensor(node_word).cpu(), dtype=np.int64).reshape(-1)
        if M < 1 or parent[0] != -1:
            raise ConfigError("node 0 must be the root (parent -1)", path=source)
        if node_desc.shape != (M, 4) or node_weight.shape != (M,) or node_word.shape != (M,):
            raise ConfigError(f"inconsistent node arrays: {M} parents, desc {tuple(node_desc.shape)}, "
                              f"weight {tuple(node_weight.shape)}, word {node_word.shape}", path=source)
        if M > 1 and (parent[1:].min() < 0 or parent[1:].max() >= M):
            raise ConfigError("a node's parent id is out of range", path=source)
        if scoring not in range(6) or weighting not in range(4):
            raise ConfigError(f"unknown scoring {scoring} / weighting {weighting}", path=source)
        self.k, self.L, self.scoring, self.weighting = int(k), int(L), int(scoring), int(weighting)
        # Children table: each node appended to its parent's list in `order` (default id order).
        pos = np.arange(M, dtype=np.int64)
        if order is not None:
            order = np.asarray(order, dtype=np.int64)
            if sorted(order.tolist()) != list(range(M)):
                raise ConfigError("node order is not a permutation of the node ids", path=source)
            pos[order] = np.arange(M)
        nonroot = np.arange(1, M, dtype=np.int64)
        srt = nonroot[np.lexsort((pos[nonroot], parent[nonroot]))]
        par_s = parent[srt]
        cnt = np.bincount(par_s, minlength=M)
        start = np.cumsum(cnt) - cnt
        rank = np.arange(srt.shape[0]) - start[par_s]
        kmax = max(int(cnt.max()) if M > 1 else 1, 1)
        children = np.full((M, kmax), -1, dtype=np.int64)
        children[par_s, rank] = srt
        # Depth by breadth-first walk from the root (also rejects cycles / unreachable nodes).
        depth, frontier, seen = 0, np.array([0]), 1
        while True:
            nxt = children[frontier].reshape(-1)
            nxt = nxt[nxt >= 0]
            if nxt.size == 0:
                break
            depth += 1
            seen += nxt.size
            frontier = nxt
            if seen > M:
                break
        if seen != M:
            raise ConfigError(f"tree is malformed: {seen} of {M} nodes reachable from the root", path=source)
        is_leaf = cnt == 0
        if M > 1 and np.any(node_word[~is_leaf] >= 0):
            raise ConfigError("an inner node carries a word id", path=source)
        used = node_word[node_word >= 0]
        if np.unique(used).size != used.size:
            raise ConfigError("a word id is used by more than one node", path=source)
        W = int(node_word.max()) + 1 if M > 0 else 0
        word_node = np.full(W, -1, dtype=np.int64)
        has = node_word >= 0
        word_node[node_word[has]] = np.nonzero(has)[0]
        self.depth = depth
        self.device = torch.device("cpu")
        self.parent = torch.from_numpy(parent)
        self.node_desc = node_desc.contiguous()
        self.node_weight = node_weight.contiguous()
        self.node_word = torch.from_numpy(node_word)
        self.word_node = torch.from_numpy(word_node)
        self.children = torch.from_numpy(children)
        self.is_leaf = torch.from_numpy(is_leaf)

    # -- properties -------------------------------------------------------------------------
    @property
    def num_nodes(self) -> int:
        return int(self.parent.shape[0])

    @property
    def num_words(self) -> int:
        return int(self.word_node.shape[0])

    @property
    def word_weights(self) -> torch.Tensor:
        """(W,) float64 weight of each word (0 where the word has no node)."""
        w = self.node_weight[self.word_node.clamp(min=0)]
        return torch.where(self.word_node >= 0, w, torch.zeros_like(w))

    def __len__(self) -> int:
        return self.num_words

    def __repr__(self) -> str:
        return (f"Vocabulary(k={self.k}, L={self.L}, nodes={self.num_nodes}, words={self.num_words}, "
                f"scoring={self.scoring}, weighting={self.weighting}, device={self.device})")

    def to(self, device) -> Vocabulary:
        """Move the tree tensors to ``device`` (in place; returns self)."""
        device = torch.device(device)
        for name in ("parent", "node_desc", "node_weight", "node_word", "word_node", "children", "is_leaf"):
            setattr(self, name, getattr(self, name).to(device))
        self.device = device
        return self

    # -- transform ------------------------------------------------------------------------------
    def _descend(self, flat: torch.Tensor) -> torch.Tensor:
        """Leaf node id of each packed descriptor ``(n, 4) -> (n,)``."""
        flat = flat.to(self.device)
        out = torch.zeros(flat.shape[0], dtype=torch.int64, device=self.device)
        for s in range(0, flat.shape[0], _CHUNK):
            x = flat[s:s + _CHUNK]
            cur = torch.zeros(x.shape[0], dtype=torch.int64, device=self.device)
            for _ in range(self.depth):  # a loop over levels; every descriptor steps together
                ch = self.children[cur]
                d = _hamming_packed(x[:, None, :], self.node_desc[ch.clamp(min=0)])
                d = d.masked_fill(ch < 0, _BIG)
                nxt = ch.gather(1, d.argmin(1, keepdim=True)).squeeze(1)  # first child wins ties
                cur = torch.where(self.is_leaf[cur], cur, nxt)
            out[s:s + _CHUNK] = cur
        return out

    def transform_words(self, desc: torch.Tensor, valid: Optional[torch.Tensor] = None):
        """Word id and weight of every descriptor.

        Args:
            desc: (..., K, 4) int64 packed BRIEF; valid: (..., K) bool (default all).
        Returns:
            words (..., K) int64 (-1 where invalid), weights (..., K) float64 (0 where invalid).
        """
        desc, valid = self._check(desc, valid)
        leaf = self._descend(desc.reshape(-1, 4)).reshape(valid.shape)
        words = torch.where(valid, self.node_word[leaf], torch.full_like(leaf, -1))
        w = self.node_weight[leaf]
        w = torch.where(valid & (words >= 0), w, torch.zeros_like(w))
        return words, w

    def transform(self, desc: torch.Tensor, valid: Optional[torch.Tensor] = None) -> BowVector:
        """Bag of words of each document (batched DBoW2 ``transform``).

        Args:
            desc: (B, K, 4) int64 packed BRIEF (any leading shape is flattened to B);
            valid: (B, K) bool (default all).
        Returns:
            BowVector(words (B, K) int64 ascending then -1, weights (B, K) float64), normalised
            as the scoring type requires (L1 for the shipped VINS vocabulary).
        """
        desc, valid = self._check(desc, valid)
        K = desc.shape[-2]
        words, w = self.transform_words(desc, valid)
        words = words.reshape(-1, K)
        w = w.reshape(-1, K)
        keep = (words >= 0) & (w > 0)  # DBoW2 skips stopped words (weight <= 0)
        words = torch.where(keep, words, torch.full_like(words, -1))
        w = torch.where(keep, w, torch.zeros_like(w))
        bow = _aggregate(words, w, summed=self.weighting in (TF, TF_IDF))
        v = bow.weights
        if self.scoring in (L1_NORM, CHI_SQUARE, KL, BHATTACHARYYA):
            nrm = v.abs().sum(1, keepdim=True)
        elif self.scoring == L2_NORM:
            nrm = v.square().sum(1, keepdim=True).sqrt()
        else:
            nrm = torch.ones_like(v[:, :1])
        v = v / torch.where(nrm > 0, nrm, torch.ones_like(nrm))
        return BowVector(bow.words, v)

    def _check(self, desc, valid):
        if not isinstance(desc, torch.Tensor) or desc.dtype != torch.int64:
            raise ValueError("desc: expected an int64 tensor of packed BRIEF descriptors (..., K, 4)")
        if desc.ndim < 2 or desc.shape[-1] != 4:
            raise ValueError(f"desc: expected shape (*, K, 4), got {tuple(desc.shape)}")
        if valid is None:
            valid = torch.ones(desc.shape[:-1], dtype=torch.bool, device=desc.device)
        if valid.shape != desc.shape[:-1]:
            raise ValueError(f"valid: expected shape {tuple(desc.shape[:-1])}, got {tuple(valid.shape)}")
        return desc.to(self.device), valid.to(self.device, torch.bool)

    # -- training -------------------------------------------------------------------------------
    @classmethod
    def train(cls, desc: torch.Tensor, valid: Optional[torch.Tensor] = None, k: int = 10, L: int = 6,
              generator: Optional[torch.Generator] = None, progress: bool = False,
              weighting: int = TF_IDF, scoring: int = L1_NORM, max_iter: Optional[int] = None) -> Vocabulary:
        """Train a vocabulary by hierarchical binary k-medians (DBoW2 ``create``).

        Args:
            desc: (D, K, 4) int64 packed descriptors of D training documents (images); any
                leading shape ``(..., K, 4)`` is flattened to D documents.
            valid: (D, K) bool mask (default all).
            k, L: branching factor and depth. generator: torch.Generator for the seeding (any
                device: a CPU one with device descriptors draws on the host and uploads).
            max_iter: cap on k-medians iterations per level (None = until no assignment changes,
                as DBoW2).
        Returns:
            Vocabulary on ``desc.device``; IDF weights ``ln(D / N_i)`` for TF_IDF/IDF.
        """
        if k < 2 or L < 1:
            raise ConfigError(f"need k >= 2 and L >= 1, got k={k}, L={L}")
        if not isinstance(desc, torch.Tensor) or desc.dtype != torch.int64 or desc.ndim < 3 or desc.shape[-1] != 4:
            raise ValueError("desc: expected int64 (D, K, 4) training documents, got "
                             f"{getattr(desc, 'dtype', type(desc))} {tuple(getattr(desc, 'shape', ()))}")
        K = desc.shape[-2]
        D = desc.numel() // (4 * K) if K else 0
        if valid is None:
            valid = torch.ones(desc.shape[:-1], dtype=torch.bool, device=desc.device)
        if valid.shape != desc.shape[:-1]:
            raise ValueError(f"valid: expected shape {tuple(desc.shape[:-1])}, got {tuple(valid.shape)}")
        vflat = valid.reshape(-1).to(torch.bool)
        x = desc.reshape(-1, 4)[vflat]
        doc = torch.arange(D, device=desc.device).repeat_interleave(K)[vflat]
        if x.shape[0] == 0:
            raise ValueError("desc: no valid training descriptors")
        parent, ndesc = _hkmeans(x, k, L, generator, progress, max_iter)
        M = parent.shape[0]
        cnt = torch.bincount(parent[1:], minlength=M)
        leaf = cnt == 0
        leaf[0] = False
        node_word = torch.full((M,), -1, dtype=torch.int64, device=desc.device)
        node_word[leaf] = torch.arange(int(leaf.sum()), device=desc.device)
        # the constructor builds the tree on the host (numpy); the weights are set on the device below
        voc = cls(k, L, parent, ndesc, torch.zeros(M, dtype=torch.float64, device="cpu"), node_word,
                  scoring=scoring, weighting=weighting)
        voc.to(desc.device)
        W = voc.num_words
        if weighting in (TF, BINARY):
            ww = torch.ones(W, dtype=torch.float64, device=voc.device)
        else:
            words = voc.node_word[voc._descend(x)]
            pairs = torch.unique(doc * W + words)
            Ni = torch.bincount(pairs % W, minlength=W).to(torch.float64)
            ww = torch.where(Ni > 0, torch.log(D / Ni.clamp_min(1)), torch.zeros_like(Ni))
        voc.node_weight[voc.word_node] = ww
        return voc

    # -- persistence ------------------------------------------------------------------------------
    STATE_VERSION = 1

    def state_dict(self) -> dict:
        """The vocabulary as CPU tensors (what :meth:`save` writes, for a checkpoint)."""
        return {"kind": "Vocabulary", "version": self.STATE_VERSION, "k": self.k, "L": self.L,
                "scoring": self.scoring, "weighting": self.weighting, "parent": self.parent.cpu(),
                "node_desc": self.node_desc.cpu(), "node_weight": self.node_weight.cpu(),
                "node_word": self.node_word.cpu(), "order": torch.from_numpy(self._order())}

    @classmethod
    def from_state_dict(cls, state: dict, device=None) -> Vocabulary:
        """The vocabulary of :meth:`state_dict` (on ``device``); ``StateError`` for another version."""
        from .state import check_state

        st = check_state(state, "Vocabulary", cls.STATE_VERSION, ("k", "L", "parent", "node_desc", "node_weight",
                                                                  "node_word", "order"))
        voc = cls(int(st["k"]), int(st["L"]), st["parent"], st["node_desc"], st["node_weight"], st["node_word"],
                  int(st["scoring"]), int(st["weighting"]), order=st["order"].numpy(), source="a checkpoint's vocabulary")
        return voc.to(device) if device is not None else voc

    def _order(self) -> np.ndarray:
        ch = self.children.cpu().numpy()
        return np.concatenate([[0], ch[ch >= 0]]).astype(np.int64)

    def save(self, path: PathLike) -> None:
        """Save in the package's own ``.npz`` format (atomic: temp file + rename)."""
        path = Path(path)
        arrays = dict(
            format=np.array(_FORMAT), k=np.array(self.k), L=np.array(self.L),
            scoring=np.array(self.scoring), weighting=np.array(self.weighting),
            parent=self.parent.cpu().numpy(), node_desc=self.node_desc.cpu().numpy(),
            node_weight=self.node_weight.cpu().numpy(), node_word=self.node_word.cpu().numpy(),
            order=self._order(),
        )
        _atomic_write(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def load(cls, path: PathLike, device=None) -> Vocabulary:
        """Load a vocabulary written by :meth:`save`."""
        try:
            with np.load(Path(path), allow_pickle=False) as z:
                if str(z["format"]) != _FORMAT:
                    raise ConfigError(f"unknown format {z['format']!s}", path=path)
                voc = cls(int(z["k"]), int(z["L"]), z["parent"], torch.from_numpy(z["node_desc"]),
                          torch.from_numpy(z["node_weight"]), z["node_word"], int(z["scoring"]),
                          int(z["weighting"]), order=z["order"], source=str(path))
        except (OSError, KeyError, ValueError) as e:
            if isinstance(e, ConfigError):
                raise
            raise ConfigError(f"cannot read vocabulary: {e}", path=path) from e
        return voc.to(device) if device is not None else voc

    @classmethod
    def load_vins_bin(cls, path: PathLike, device=None) -> Vocabulary:
        """Load VINS's binary ``brief_k10L6.bin`` (spec §7.4).

        Layout (little endian): int32 ``k, L, scoringType, weightingType, nNodes, nWords``; node
        records of 48 bytes ``int32 nodeId, int32 parentId, float64 weight, uint64 desc[4]``;
        ``nWords`` records ``int32 nodeId, int32 wordId``. The root is implicit. Assumption: whether
        ``nNodes`` counts the root is not pinned down, so the number of node records is taken from
        the file size and must be ``nNodes`` or ``nNodes - 1``. Children are appended in file order.
        """
        path = Path(path)
        try:
            data = path.read_bytes()
        except OSError as e:
            raise ConfigError(f"cannot read: {e}", path=path) from e
        if len(data) < 24:
            raise ConfigError("file shorter than the 24-byte header", path=path)
        k, L, sc, wt, nN, nW = (int(v) for v in np.frombuffer(data, "<i4", 6))
        rest = len(data) - 24 - 8 * nW
        if nW < 0 or rest < 0 or rest % 48 or rest // 48 not in (nN, nN - 1):
            raise ConfigError(f"size {len(data)} B does not match nNodes={nN}, nWords={nW}", path=path)
        R = rest // 48
        rec = np.frombuffer(data, np.dtype([("nid", "<i4"), ("pid", "<i4"), ("w", "<f8"), ("d", "<u8", (4,))]),
                            count=R, offset=24)
        wrec = np.frombuffer(data, np.dtype([("nid", "<i4"), ("wid", "<i4")]), count=nW, offset=24 + 48 * R)
        return cls._from_records(k, L, sc, wt, rec["nid"], rec["pid"], rec["w"],
                                 rec["d"].astype("<u8").view(np.int64).reshape(R, 4), wrec["nid"], wrec["wid"],
                                 str(path), device)

    def save_vins_bin(self, path: PathLike) -> None:
        """Write the VINS binary layout (``nNodes`` = records, root excluded); atomic."""
        order = self._order()[1:]
        rec = np.zeros(order.size, np.dtype([("nid", "<i4"), ("pid", "<i4"), ("w", "<f8"), ("d", "<u8", (4,))]))
        rec["nid"] = order
        rec["pid"] = self.parent.cpu().numpy()[order]
        rec["w"] = self.node_weight.cpu().numpy()[order]
        rec["d"] = self.node_desc.cpu().numpy()[order].view(np.uint64)
        wn = self.word_node.cpu().numpy()
        wrec = np.zeros(wn.size, np.dtype([("nid", "<i4"), ("wid", "<i4")]))
        wrec["nid"] = wn
        wrec["wid"] = np.arange(wn.size)
        hdr = np.array([self.k, self.L, self.scoring, self.weighting, order.size, wn.size], "<i4")
        _atomic_write(Path(path), lambda f: f.write(hdr.tobytes() + rec.tobytes() + wrec.tobytes()))

    @classmethod
    def load_dbow2_yaml(cls, path: PathLike, device=None) -> Vocabulary:
        """Load DBoW2's OpenCV-FileStorage YAML (optionally ``.gz``).

        ``vocabulary: {k, L, scoringType, weightingType, nodes: [{nodeId, parentId, weight,
        descriptor}], words: [{wordId, nodeId}]}``, root implicit, children in file order. A
        descriptor string is either 32 space-separated byte values (``FORB::toString``; byte j
        holds bits 8j..8j+7, LSB first) or a 256-character ``0/1`` string (``FBrief::toString`` =
        ``dynamic_bitset::to_string``: first character = bit 255).
        """
        path = Path(path)
        try:
            if path.suffix == ".gz":
                import gzip

                text = gzip.open(path, "rt").read()
            else:
                text = path.read_text()
        except OSError as e:
            raise ConfigError(f"cannot read: {e}", path=path) from e

        def head(key):
            m = re.search(r"\b" + key + r"\s*:\s*(-?\d+)", text)
            if m is None:
                raise ConfigError("missing key", path=path, key=key)
            return int(m.group(1))

        k, L, sc, wt = head("k"), head("L"), head("scoringType"), head("weightingType")
        node_re = re.compile(r'nodeId\s*:\s*(\d+)\s*,\s*parentId\s*:\s*(\d+)\s*,\s*weight\s*:\s*([^,\s}]+)\s*,'
                             r'\s*descriptor\s*:\s*"([^"]*)"')
        word_re = re.compile(r"wordId\s*:\s*(\d+)\s*,\s*nodeId\s*:\s*(\d+)")
        nodes = node_re.findall(text)
        words = word_re.findall(text)
        R = len(nodes)
        nid = np.fromiter((int(n[0]) for n in nodes), np.int64, R)
        pid = np.fromiter((int(n[1]) for n in nodes), np.int64, R)
        w = np.fromiter((float(n[2]) for n in nodes), np.float64, R)
        desc = np.zeros((R, 32), np.uint8)
        for i, n in enumerate(nodes):
            s = n[3].strip()
            if len(s) == 256 and set(s) <= {"0", "1"}:
                bits = np.frombuffer(s[::-1].encode(), np.uint8) - ord("0")
                desc[i] = np.packbits(bits, bitorder="little")
            else:
                vals = [int(v) for v in s.split()]
                if len(vals) != 32:
                    raise ConfigError(f"node {n[0]}: descriptor has {len(vals)} bytes, expected 32", path=path)
                desc[i] = vals
        d64 = desc.view("<i8").reshape(R, 4) if R else np.zeros((0, 4), np.int64)
        wid = np.fromiter((int(x[0]) for x in words), np.int64, len(words))
        wnid = np.fromiter((int(x[1]) for x in words), np.int64, len(words))
        return cls._from_records(k, L, sc, wt, nid, pid, w, d64, wnid, wid, str(path), device)

    @classmethod
    def _from_records(cls, k, L, sc, wt, nid, pid, w, d64, wnid, wid, source, device):
        nid = np.asarray(nid, np.int64)
        R = nid.size
        M = R + 1
        if R and (nid.min() < 1 or nid.max() >= M or np.unique(nid).size != R):
            raise ConfigError("node ids must be 1..nNodes, each once (root implicit)", path=source)
        parent = np.full(M, -1, np.int64)
        parent[nid] = pid
        nd = np.zeros((M, 4), np.int64)
        nd[nid] = d64
        nw = np.zeros(M, np.float64)
        nw[nid] = w
        node_word = np.full(M, -1, np.int64)
        wnid = np.asarray(wnid, np.int64)
        if wnid.size and (wnid.min() < 1 or wnid.max() >= M):
            raise ConfigError("a word refers to a missing node", path=source)
        node_word[wnid] = wid
        order = np.concatenate([[0], nid])
        voc = cls(k, L, parent, torch.from_numpy(nd), torch.from_numpy(nw), node_word, sc, wt,
                  order=order, source=source)
        return voc.to(device) if device is not None else voc


def _atomic_write(path: Path, write) -> None:
    """Write via a temp file in the same folder, then rename (never a half-written file)."""
    from .._atomic import atomic_path

    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as f:
        write(f)
