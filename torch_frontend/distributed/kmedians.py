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
    * centres (bitwise majority): the per-(centre, bit) counts are float32 integers, exact in any
      order below 2^24 members per centre (as one process's counts), the group sizes int64; a bit
      is set iff ``2 count > size``; the centres with members: an all-reduce MAX of a presence
      mask (``_Comm.unique``);
    * group sizes, child numbering of groups of <= k descriptors (an exclusive prefix over ranks
      of each group's local count), convergence flags, IDF document counts: integer all-reduces;
    * assignments (nearest centre, first wins ties) are per descriptor, so local.

    The algorithm is ``loop.vocabulary``'s, run with this module's communicator ``_Comm`` (the
    one-process communicator there makes every reduction the identity). Every rank runs the same
    collectives in the same order: control flow depends on reduced values only. ``group=None``
    and no initialised process group: one process, ``Vocabulary.train``'s result.
"""

from __future__ import annotations

from typing import List, Optional

import torch

from ..errors import ConfigError
from ..loop.vocabulary import BINARY, L1_NORM, TF, TF_IDF, Vocabulary, _hkmeans

__all__ = ["train_vocabulary"]


class _Comm:
    """All-reduces over ``group`` (identity for a single process): the communicator that
    ``loop.vocabulary._hkmeans`` takes (``loop.vocabulary._OneProcess`` is its one-process twin)."""

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

    def take(self, x: torch.Tensor, gidx: torch.Tensor, offset: int) -> torch.Tensor:
        """Rows ``gidx`` (global indices) of the distributed ``x (n, 4) int64``, on every rank."""
        loc = gidx - offset
        mine = (loc >= 0) & (loc < x.shape[0])
        out = torch.zeros(gidx.shape[0], 4, dtype=torch.int64, device=x.device)
        out[mine] = x[loc[mine]]
        return self.sum_(out)  # one rank holds each row, the others add zeros: exact

    def unique(self, ids: torch.Tensor, size: int) -> tuple:
        """``(ids in [0, size) present on any rank (ascending), index of each of ``ids`` in them)``."""
        present = torch.zeros(size, dtype=torch.uint8, device=ids.device)
        present[ids] = 1
        uniq = self.max_(present).nonzero().squeeze(1)
        return uniq, torch.searchsorted(uniq, ids)


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
    parent, ndesc = _hkmeans(x, k, L, generator, progress, max_iter, comm)
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
