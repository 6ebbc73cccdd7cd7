"""Place recognition database: DBoW2 inverted file with VINS's modified L1 query and loop rule.

Convention:
    * Bags of words are :class:`~torch_frontend.loop.vocabulary.BowVector`
      ``(words (B, K) int64 ascending then -1, weights (B, K) float)``, L1-normalised, weights > 0
      (what ``Vocabulary.transform`` returns for the VINS vocabulary: L1_NORM + TF_IDF).
    * Streams: ONE database holds ``num_streams`` independent streams (cameras / robots). Entry ids
      are per stream, 0, 1, 2, ... in insertion order, exactly like DBoW2's ``add`` (= VINS keyframe
      ``index``); a query only ever sees entries of its own stream. Internally the inverted file is
      a single sorted posting array keyed by ``stream * W + word``, so ``query_many`` answers
      queries from any mix of streams with one searchsorted + scatter.
    * Score (DBoW2 ``L1Scoring`` via ``queryL1``): ``1 - ½‖v − w‖₁``. For L1-normalised non-negative
      vectors this is ``½ Σ_common (|v_i| + |w_i| − |v_i − w_i|) = Σ_common min(v_i, w_i)``, summed
      over the inverted-file rows of the query's words only. Entries that share no word with the
      query get no result (DBoW2).
    * VINS's filter (spec §7.4): an entry passes iff ``entry < max_id`` or ``max_id == -1`` or
      ``entry == n_entries - 1`` (the latest entry of the stream always passes). Results sorted by
      score descending; equal scores keep the smaller id first (DBoW2's ``std::sort`` leaves the
      order of ties unspecified). Missing results are ``id -1, score 0``.
    * ``detect_loop`` (spec §7.5): query top 4 with ``max_id = index − 50``, then add; loop iff
      ``ret[0] > 0.05`` and some ``ret[i≥1] > 0.015`` and ``index > 50``; answer = the oldest id
      among ``ret[0]`` and the ``ret[i≥1]`` with score > 0.015; else −1.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple, Union

import torch

from ..errors import ConfigError
from .vocabulary import L1_NORM, BowVector, Vocabulary

__all__ = ["PlaceDatabase"]

IntLike = Union[int, torch.Tensor]


class PlaceDatabase:
    """DBoW2 ``TemplatedDatabase`` (``use_di = false``) over ``num_streams`` independent streams.

    Args:
        vocabulary: the :class:`Vocabulary` (only its word count and scoring type are used) or the
            number of words ``W``.
        num_streams: B; entry ids are per stream.
        device / dtype: where the inverted file lives (weights float64 by default).
    """

    tail_min = 4096  # postings the tail run may hold before it is merged into the main run

    def __init__(self, vocabulary: Union[Vocabulary, int], num_streams: int = 1, device=None,
                 dtype: torch.dtype = torch.float64):
        if isinstance(vocabulary, Vocabulary):
            if vocabulary.scoring != L1_NORM:
                raise ConfigError(f"PlaceDatabase implements L1 scoring only, vocabulary has {vocabulary.scoring}")
            self.num_words = vocabulary.num_words
            device = vocabulary.device if device is None else device
        else:
            self.num_words = int(vocabulary)
        if num_streams < 1:
            raise ConfigError(f"num_streams must be >= 1, got {num_streams}")
        self.num_streams = int(num_streams)
        self.device = torch.device("cpu" if device is None else device)
        self.dtype = dtype
        # Inverted file: two sorted runs of postings (key = stream * W + word, entry, weight),
        # sorted by key then entry (entries of a stream are appended in id order and merges keep
        # it). New postings are merged into the small `tail` run; the tail is merged into `main`
        # once it exceeds 1/8 of it, so an add costs O(tail) amortised instead of O(all postings).
        self._main = self._empty_run()
        self._tail = self._empty_run()
        self._size = torch.zeros(self.num_streams, dtype=torch.int64, device=self.device)
        self._size_host = [0] * self.num_streams  # host copy: shapes of score tables need it

    # -- bookkeeping ----------------------------------------------------------------------------
    def size(self, stream: int = 0) -> int:
        """Number of entries of ``stream``."""
        return self._size_host[stream]

    def __len__(self) -> int:
        return sum(self._size_host)

    @property
    def num_postings(self) -> int:
        return int(self._main[0].numel() + self._tail[0].numel())

    def _empty_run(self):
        return (torch.empty(0, dtype=torch.int64, device=self.device),
                torch.empty(0, dtype=torch.int64, device=self.device),
                torch.empty(0, dtype=self.dtype, device=self.device))

    def _check_bow(self, bow) -> BowVector:
        words, weights = bow
        if words.ndim == 1:
            words, weights = words[None], weights[None]
        if words.ndim != 2 or words.shape != weights.shape:
            raise ValueError(f"bow: expected words/weights (B, K), got {tuple(words.shape)} / {tuple(weights.shape)}")
        if words.numel() and int(words.max()) >= self.num_words:
            raise ValueError(f"bow: word id {int(words.max())} >= vocabulary size {self.num_words}")
        return BowVector(words.to(self.device, torch.int64), weights.to(self.device, self.dtype))

    def _streams(self, streams: Optional[IntLike], n: int) -> torch.Tensor:
        if streams is None:
            s = torch.zeros(n, dtype=torch.int64, device=self.device)
        else:
            s = torch.as_tensor(streams, dtype=torch.int64, device=self.device).reshape(-1)
            if s.numel() == 1 and n != 1:
                s = s.expand(n)
        if s.shape != (n,):
            raise ValueError(f"streams: expected shape ({n},), got {tuple(s.shape)}")
        if n and (int(s.min()) < 0 or int(s.max()) >= self.num_streams):
            raise ValueError(f"streams: ids must be in [0, {self.num_streams})")
        return s

    # -- state -----------------------------------------------------------------------------------
    STATE_VERSION = 1

    def state_dict(self) -> Dict[str, Any]:
        """The database as CPU tensors (a checkpoint's part): both posting runs as they are (the
        split into main and tail decides the order of the score sums, so it is kept), the stream
        sizes, and the word count, stream count and dtype it was built with."""
        return {"kind": "PlaceDatabase", "version": self.STATE_VERSION, "num_words": self.num_words,
                "num_streams": self.num_streams, "dtype": str(self.dtype).replace("torch.", ""),
                "main": [t.cpu() for t in self._main], "tail": [t.cpu() for t in self._tail],
                "size": list(self._size_host)}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        """Restore :meth:`state_dict` onto this database's device; ``StateError`` (nothing
        changed) for another version, word count, stream count or dtype."""
        from .state import check_same, check_state

        check_state(state, "PlaceDatabase", self.STATE_VERSION, ("num_words", "num_streams", "main", "tail", "size"))
        for key, here in (("num_words", self.num_words), ("num_streams", self.num_streams),
                          ("dtype", str(self.dtype).replace("torch.", ""))):
            check_same("PlaceDatabase", key, state[key], here)
        dt = (torch.int64, torch.int64, self.dtype)
        self._main = tuple(t.to(self.device, d) for t, d in zip(state["main"], dt))
        self._tail = tuple(t.to(self.device, d) for t, d in zip(state["tail"], dt))
        self._size_host = [int(n) for n in state["size"]]
        self._size = torch.tensor(self._size_host, dtype=torch.int64, device=self.device)

    # -- add --------------------------------------------------------------------------------------
    def add(self, bow: BowVector, stream: int = 0) -> int:
        """Add one bag of words to ``stream``; returns its entry id (0, 1, 2, ... per stream)."""
        words, weights = self._check_bow(bow)
        if words.shape[0] != 1:
            raise ValueError(f"add: expected one bag of words, got {words.shape[0]} (use add_many)")
        return int(self.add_many(BowVector(words, weights), streams=[stream])[0])

    def add_many(self, bows: BowVector, streams: Optional[IntLike] = None) -> torch.Tensor:
        """Add ``B`` bags at once; row ``i`` goes to ``streams[i]`` (default: stream ``i``).

        Rows for the same stream get consecutive ids in row order. Returns ``(B,)`` entry ids.
        """
        words, weights = self._check_bow(bows)
        B = words.shape[0]
        s = self._streams(torch.arange(B, device=self.device) if streams is None else streams, B)
        # Per-stream ids: current size + rank of the row among earlier rows of the same stream.
        same = (s[:, None] == s[None, :]) & torch.ones(B, B, dtype=torch.bool, device=self.device).tril(-1)
        ids = self._size[s] + same.sum(1)
        self._size += torch.bincount(s, minlength=self.num_streams)
        for b in s.tolist():
            self._size_host[b] += 1
        keep = (words >= 0) & (weights > 0)
        key = (s[:, None] * self.num_words + words)[keep]
        ent = ids[:, None].expand_as(words)[keep]
        val = weights[keep]
        # Rows are in row order, so within one key the entries already ascend: a stable sort by
        # key gives (key, entry) order; then merge into the sorted postings in O(P + n).
        order = torch.sort(key, stable=True).indices
        self._tail = self._merge(self._tail, (key[order], ent[order], val[order]))
        if self._tail[0].numel() > max(self.tail_min, self._main[0].numel() // 8):
            self._main = self._merge(self._main, self._tail)
            self._tail = self._empty_run()
        return ids

    def _merge(self, run, new):
        """Merge sorted run ``new`` (all entries newer than ``run``'s) into sorted ``run``."""
        (okey, oent, oval), (key, ent, val) = run, new
        n_old, n_new = okey.numel(), key.numel()
        if n_new == 0:
            return run
        # New entries have larger ids than every old entry of their stream, so they go after the
        # old postings with the same key (right insertion point) and the (key, entry) order holds.
        pos_new = torch.searchsorted(okey, key, right=True) + torch.arange(n_new, device=self.device)
        is_new = torch.zeros(n_old + n_new, dtype=torch.bool, device=self.device)
        is_new[pos_new] = True
        pos_old = (~is_new).nonzero().squeeze(1)
        nk = torch.empty(n_old + n_new, dtype=torch.int64, device=self.device)
        ne = torch.empty_like(nk)
        nv = torch.empty(n_old + n_new, dtype=self.dtype, device=self.device)
        nk[pos_new], ne[pos_new], nv[pos_new] = key, ent, val
        nk[pos_old], ne[pos_old], nv[pos_old] = okey, oent, oval
        return nk, ne, nv

    # -- query ------------------------------------------------------------------------------------
    def scores_many(self, bows: BowVector, max_id: IntLike = -1, streams: Optional[IntLike] = None):
        """All L1 scores through the inverted file: ``(Q, E) float`` and ``hit (Q, E) bool``.

        ``E`` = the largest stream size; ``hit`` marks entries that share a word with the query and
        pass the ``max_id`` / latest-entry filter (only those are results).
        """
        words, weights = self._check_bow(bows)
        Q, K = words.shape
        s = self._streams(streams, Q)
        mid = torch.as_tensor(max_id, dtype=torch.int64, device=self.device).reshape(-1).expand(Q)
        E = max(self._size_host) if self._size_host else 0
        scores = torch.zeros(Q, E, dtype=self.dtype, device=self.device)
        hits = torch.zeros(Q, E, dtype=torch.bool, device=self.device)
        if E == 0:
            return scores, hits
        qk = s[:, None] * self.num_words + words
        ok = (words >= 0) & (weights > 0)
        for rkey, rent, rval in (self._main, self._tail):
            if rkey.numel() == 0:
                continue
            lo = torch.searchsorted(rkey, qk)
            hi = torch.searchsorted(rkey, qk, right=True)
            cnt = torch.where(ok, hi - lo, torch.zeros_like(lo)).reshape(-1)
            total = int(cnt.sum())
            if total == 0:
                continue
            # Expand every query word into its inverted-file row (variable length), no loop.
            row = torch.repeat_interleave(torch.arange(Q * K, device=self.device), cnt)
            first = torch.cumsum(cnt, 0) - cnt
            post = lo.reshape(-1)[row] + torch.arange(total, device=self.device) - first[row]
            q = row // K
            ent = rent[post]
            last = self._size[s][q] - 1
            m = mid[q]
            passed = (ent < m) | (m == -1) | (ent == last)
            contrib = torch.minimum(weights.reshape(-1)[row], rval[post])
            flat = q * E + ent
            scores.view(-1).index_add_(0, flat[passed], contrib[passed])
            hits.view(-1)[flat[passed]] = True
        return scores, hits

    def query_many(self, bows: BowVector, max_results: int = 4, max_id: IntLike = -1,
                   streams: Optional[IntLike] = None) -> Tuple[torch.Tensor, torch.Tensor]:
        """Batched VINS ``queryL1``.

        Args:
            bows: Q bags (words/weights (Q, K)); max_id: int or (Q,) (−1 = no limit);
            streams: (Q,) stream of each query (default 0).
        Returns:
            ids (Q, max_results) int64 (−1 = no result), scores (Q, max_results), descending.
        """
        scores, hits = self.scores_many(bows, max_id, streams)
        Q, E = scores.shape
        key = torch.where(hits, scores, torch.full_like(scores, -1.0))
        # Stable sort: equal scores keep the smaller entry id first.
        srt, idx = torch.sort(key, dim=1, descending=True, stable=True)
        n = min(max_results, E)
        ids = torch.full((Q, max_results), -1, dtype=torch.int64, device=self.device)
        out = torch.zeros(Q, max_results, dtype=self.dtype, device=self.device)
        good = srt[:, :n] >= 0
        ids[:, :n] = torch.where(good, idx[:, :n], torch.full_like(idx[:, :n], -1))
        out[:, :n] = torch.where(good, srt[:, :n], torch.zeros_like(srt[:, :n]))
        return ids, out

    def query(self, bow: BowVector, max_results: int = 4, max_id: int = -1, stream: int = 0):
        """One query: ``(ids (R,), scores (R,))`` with only real results (R <= max_results)."""
        ids, sc = self.query_many(bow, max_results, max_id, [stream])
        n = int((ids[0] >= 0).sum())
        return ids[0, :n], sc[0, :n]

    # -- loop detection ---------------------------------------------------------------------------
    def detect_loop_many(self, bows: BowVector, index: IntLike, streams: Optional[IntLike] = None,
                         min_gap: int = 50, score_first: float = 0.05, score_other: float = 0.015,
                         return_scores: bool = False):
        """VINS ``detectLoop`` for B keyframes of B DIFFERENT streams: query, then add each.

        Args:
            bows: (B, K) bags; index: (B,) or int keyframe index (VINS: = the new entry's id);
            streams: (B,) distinct stream ids (default 0..B-1).
            return_scores: also return the candidate's score and the best score of the query.
        Returns:
            (B,) int64 loop candidate (oldest qualifying entry) or −1; with ``return_scores`` also
            ``(B,)`` the candidate's score (0 without one) and ``(B,)`` the best score (0 when the
            query had no result), e.g. for a per-keyframe score plot.
        """
        words, weights = self._check_bow(bows)
        B = words.shape[0]
        s = self._streams(torch.arange(B, device=self.device) if streams is None else streams, B)
        if torch.unique(s).numel() != B:
            raise ValueError("detect_loop_many: one keyframe per stream per call (streams must be distinct)")
        idx = torch.as_tensor(index, dtype=torch.int64, device=self.device).reshape(-1).expand(B)
        ids, sc = self.query_many(BowVector(words, weights), 4, idx - min_gap, s)
        self.add_many(BowVector(words, weights), s)
        have = ids >= 0
        other = have[:, 1:] & (sc[:, 1:] > score_other)
        find = have[:, 0] & (sc[:, 0] > score_first) & other.any(1) & (idx > min_gap)
        big = torch.iinfo(torch.int64).max
        cand = torch.where(other, ids[:, 1:], torch.full_like(ids[:, 1:], big)).amin(1)
        oldest = torch.minimum(ids[:, 0], cand)
        out = torch.where(find, oldest, torch.full_like(oldest, -1))
        if not return_scores:
            return out
        hit = (ids == out[:, None]) & find[:, None]
        cand_score = torch.where(hit, sc, torch.zeros_like(sc)).amax(1)
        best_score = torch.where(have[:, 0], sc[:, 0], torch.zeros_like(sc[:, 0]))
        return out, cand_score, best_score

    def detect_loop(self, bow: BowVector, index: int, stream: int = 0) -> int:
        """VINS ``detectLoop(kf, index)`` for one keyframe: candidate entry id or −1."""
        return int(self.detect_loop_many(bow, [index], [stream])[0])
