"""OpenCV's random minimal samples: the ``cv::RNG`` stream (multiply-with-carry) and the 7-point
index subsets ``getSubset`` draws from it, generated lazily on the host and cached process-wide.

Convention:
    * A *state* is a ``cv::RNG`` state as a Python int in ``[1, 2^64)`` (:func:`_state_of` maps a
      seed to it); :data:`OPENCV_SEED` is the state OpenCV's RANSAC/LMedS re-seed with on every
      call, so the default samples are cv2's.
    * Subsets are ``(k, 7)`` int32 positions among a problem's n valid points in slot order
      (``next() % n``, repeated indices redrawn).

The streams are grown on demand, vectorised (numpy: jump-ahead lanes for the multiply-with-carry
stream, all candidate subset starts at once for the redraw rule) and cached per state and per
(state, n) (:func:`_raw_stream`, :func:`_subset_stream`), so a tracker whose point count changes
every frame pays ~0.1-1 ms once per new n instead of rebuilding 1000 samples.

Thread safety: every growth of a stream holds ``_STREAM_LOCK`` (re-entrant: a subset stream grows
its raw stream while holding it). Reading a table that is long enough takes no lock: a stream
publishes its grown table with one attribute assignment once it is complete, so a reader sees the
old table or the new one, never a half-built one, and both start with the same rows (tables only
grow). Growth is geometric, so the lock is taken a few times per stream. Two threads that miss the
cache for the same key at once get the same stream object (the cache keeps the first one built).
"""

from __future__ import annotations

import threading

import numpy as np
import torch

from .._cache import cached
from .result import _MIN_POINTS, _MODEL_POINTS

__all__ = ["OPENCV_SEED"]

_U32 = 0xFFFFFFFF
_U64 = 0xFFFFFFFFFFFFFFFF
_MWC_A = 4164903690
OPENCV_SEED = -1  # cv::RNG((uint64)-1), the state OpenCV's RANSAC/LMedS re-seed with on every call
_RAW_STREAMS = 16  # LRU bound: a fresh generator seed per call must not grow memory forever
_SUBSET_STREAMS = 512  # <= 512 x (1000, 7) int32 = 14 MB; the tracker needs one entry per n
_STATE_TABLES = 16  # host memory: 8 MB each for N = 150, K = 1000
_STREAM_LOCK = threading.RLock()  # held while a stream grows (see the module docstring)


_MWC_M = _MWC_A * 2**32 - 1
_MWC_BINV = pow(2**32, -1, _MWC_M)


class _RawStream:
    """Outputs of ``cv::RNG(state).next()`` (``state = lo32(state) * 4164903690 + hi32(state)``,
    output ``lo32(state)``), grown on demand.

    The recurrence is sequential, but it is a multiply-with-carry generator: with ``m = a 2^32 - 1``
    every state below m satisfies ``next(s) = s 2^-32 mod m`` (``2^32 next(s) = m lo32(s) + s``). So
    the stream is cut into lanes whose start states are jumped to with one modular power each
    (Python ints) and the lanes are stepped together in numpy uint64 (no overflow: s < m < 2^64).

    Thread-safe (see the module docstring): ``vals`` is replaced, never modified in place, and ``s``
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


@cached(_RAW_STREAMS)
def _raw_stream(state: int) -> _RawStream:
    """The process-wide :class:`_RawStream` of ``state`` (grown by whoever needs more of it)."""
    return _RawStream(state)


class _SubsetStream:
    """The 7-point index subsets OpenCV's ``getSubset`` draws for ``n`` points with ``cv::RNG(state)``:
    ``rng.uniform(0, n) = next() % n``, redrawn while it repeats an index of the subset. (OpenCV also
    redraws a subset whose last point is collinear with two others; here such a subset is kept and
    marked degenerate instead, see ``_collinear_last``.) Generated lazily, as many as asked for.

    Vectorised: the subset that starts at stream position p (and the position after it) depends only
    on p, not on what came before, so it is computed for every p of a block at once (draw j is
    redrawn iff the previous occurrence of its value lies at or after p); then the chain
    0 -> end(0) -> end(end(0)) ... picks OpenCV's subsets (a cheap host loop over samples).

    Thread-safe (see the module docstring): ``table`` is replaced, never modified in place, and ``pos``
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


@cached(_SUBSET_STREAMS)
def _subset_stream(state: int, n: int) -> _SubsetStream:
    """The process-wide :class:`_SubsetStream` of ``(state, n)``."""
    return _SubsetStream(state, n)


@cached(_STATE_TABLES)
def _state_samples(state: int, N: int, K: int) -> np.ndarray:
    """The first ``K`` subsets of ``cv::RNG(state)``'s stream for every n in ``[8, N]``, ``(N - 7,
    K, 7)`` int64 (host; cached, so calls of different B with one state share the ~5 ms per n of
    generation)."""
    tab = np.empty((N - _MODEL_POINTS, K, _MODEL_POINTS), dtype=np.int64)
    for r in range(N - _MODEL_POINTS):  # not through _subset_stream's cache: each stream is read once
        tab[r] = _SubsetStream(state, r + _MIN_POINTS).upto(K)[:K]
    return tab


def _clear_sample_caches() -> None:
    """Empty the process-wide sample caches (tests, benchmarks; streams already handed out stay
    valid). ``torch_frontend.clear_caches()`` empties them too, with every other cache."""
    _subset_stream.cache_clear()
    _raw_stream.cache_clear()
    _state_samples.cache_clear()


def _opencv_samples(state: int, n: int, num: int) -> torch.Tensor:
    """The first ``num`` subsets of :class:`_SubsetStream` ``(state, n)`` as ``(num, 7)`` int64."""
    return torch.from_numpy(_subset_stream(state, n).upto(num)[:num].astype(np.int64))


def _state_of(seed: int) -> int:
    """Seed -> ``cv::RNG`` state: two's complement 64 bits; 0 means OpenCV's ``(uint64)-1`` too, so
    ``seed=0``, ``seed=-1`` and no seed all reproduce cv2 (``cv::RNG(0)``'s own 0xffffffff state is
    not reachable, nobody needs it)."""
    s = int(seed) & _U64
    return s if s else _U64
