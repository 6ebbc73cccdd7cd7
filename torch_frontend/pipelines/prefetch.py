"""Decoding ahead of the tracker: :class:`FrameStream`, ``io.MultiStream``'s batches with the images
decoded in ``torch.utils.data.DataLoader`` worker processes (``workers > 0``) or in this process
(``workers = 0``), and the decode / wait times a summary reports.

Convention:
    Row ``j`` is the ``j``-th listed frame (bad ones included) of every stream. With ``N`` workers,
    worker ``w`` opens its own readers and decodes the rows ``j = w, w + N, ...`` (skipping the
    others' items without decoding them), ``prefetch`` rows ahead each; rows come back in order
    (a small reorder buffer makes sure). This process builds the batches from the rows with
    ``MultiStream``'s rules, so the batches are the same as ``io.MultiStream``'s: the same steps,
    ``alive`` masks, skipped frames (``skip_bad``), errors and messages, raised at the same step (a
    bad frame's ``BadFrameError`` names the pipelines' ``skip_bad_frames``, ``MultiStream``'s the
    readers' ``skip_bad``).
    An error raised by a reader (not a bad frame) travels as the exception itself and is raised
    where ``MultiStream`` would raise it.

    Timing (seconds): ``decode_seconds`` sums the readers' loads (in the workers: summed over
    them, so it may exceed the wall time); ``wait_seconds`` is how long the caller's loop waited
    for rows (with workers: the decode time the workers did not hide; without: the decode itself).

    Pinned memory (``pin_memory``, for a CUDA tracker): each batch's ``images`` is copied into one
    of two pinned staging buffers, so the host-to-device copy can be asynchronous
    (``non_blocking``); without it ``images`` is a plain CPU tensor, as ``MultiStream``'s.

    With ``workers > 0`` the sequences are handed to the workers (inherited by ``fork``, pickled
    otherwise): every ``io`` reader qualifies. A bag is read by every worker (each deserialises
    every message to find its rows, and decodes only its own).
"""

from __future__ import annotations

import heapq
import time
import warnings
from collections import deque
from typing import Any, Iterator, List, Optional, Tuple
from typing import Sequence as Seq

import numpy as np
import torch

from ..errors import BadFrameError, DataError
from ..io.multistream import Batch, MultiStream, lockstep, ns_to_seconds, padded_shape, stack_images

__all__ = ["FrameStream", "DEFAULT_PREFETCH"]

#: rows each worker decodes ahead of the tracker
DEFAULT_PREFETCH = 4

_OK, _BAD, _RAISE, _END = 0, 1, 2, 3


def _rows(seqs, worker: int, workers: int, max_rows: Optional[int], tensors: bool = False) -> Iterator[tuple]:
    """The rows ``j = worker (mod workers)`` as ``(j, slots, decode_seconds)``; a slot is
    ``(_OK, index, stamp_ns, source, image)``, ``(_BAD, source, message)``, ``(_RAISE,
    exception)`` or ``(_END,)``; the image is the reader's ``(H, W)`` uint8 array, or with
    ``tensors`` a tensor (a worker's rows travel through shared memory). Stops after the last row
    any stream has."""
    gens = [s._items() for s in seqs]
    done = [False] * len(seqs)
    j = 0
    while max_rows is None or j < max_rows:
        mine = j % workers == worker
        slots: List[tuple] = []
        t_dec = 0.0
        for b, gen in enumerate(gens):
            if done[b]:
                slots.append((_END,))
                continue
            try:
                item = next(gen, None)
            except Exception as exc:  # a reader error: raised where MultiStream would raise it
                done[b] = True
                slots.append((_RAISE, exc))
                continue
            if item is None:
                done[b] = True
                slots.append((_END,))
                continue
            if not mine:  # another worker's row: listed, not decoded (the row is not sent)
                slots.append((_END,))
                continue
            t0 = time.perf_counter()
            try:
                img = seqs[b]._load(item)  # the reader's decoding, with its colour note
            except DataError as exc:
                slots.append((_BAD, item.source, str(exc)))
            except Exception as exc:
                slots.append((_RAISE, exc))
            else:
                if tensors:  # from_numpy needs a writable array (a bag's image may be a view of its message)
                    img = torch.from_numpy(np.require(img, requirements=("C", "W")))
                slots.append((_OK, item.index, int(item.stamp_ns), item.source, img))
            t_dec += time.perf_counter() - t0
        if all(done) and all(s[0] == _END for s in slots):
            return
        if mine:
            yield j, slots, t_dec
        j += 1


class _Rows(torch.utils.data.IterableDataset):
    """The rows of every worker (``_rows`` of ``get_worker_info().id``)."""

    def __init__(self, seqs, max_rows: Optional[int]):
        super().__init__()
        self.seqs = list(seqs)
        self.max_rows = max_rows

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        w, n = (0, 1) if info is None else (info.id, info.num_workers)
        return _rows(self.seqs, w, n, self.max_rows, tensors=True)


def _as_is(row):
    return row


def _init_worker(_: int) -> None:
    torch.set_num_threads(1)
    try:
        import cv2

        cv2.setNumThreads(1)  # the workers are the parallelism
    except ImportError:  # pragma: no cover
        pass


class FrameStream(MultiStream):
    """Iterate B ``io`` sequences together, decoding ahead (module docstring).

    Args:
        sequences, size, max_steps: as ``io.MultiStream``.
        workers: DataLoader worker processes decoding the frames (0: this process).
        prefetch: rows each worker decodes ahead.
        pin_memory: stage ``images`` in pinned memory (for a CUDA tracker).

    Attributes: ``decode_seconds``, ``wait_seconds`` (after or during iteration), ``skipped``
    (``(stream, source, reason)`` of every frame skipped so far), ``workers``.
    """

    def __init__(self, sequences: Seq[Any], size: Optional[Tuple[int, int]] = None, max_steps: Optional[int] = None,
                 workers: int = 0, prefetch: int = DEFAULT_PREFETCH, pin_memory: bool = False):
        if workers < 0:
            raise ValueError(f"workers must be >= 0, got {workers}")
        super().__init__(sequences, size, max_steps)  # the sequences, size and step checks of MultiStream
        self.workers = int(workers)
        self.prefetch = max(1, int(prefetch))
        self.pin_memory = bool(pin_memory)
        self.decode_seconds = 0.0
        self.wait_seconds = 0.0
        self._skipped: List[List[Tuple[str, str]]] = [[] for _ in self.sequences]
        self._pinned: List[torch.Tensor] = []

    @property
    def skipped(self) -> List[Tuple[int, str, str]]:
        return [(b, src, why) for b, sk in enumerate(self._skipped) for src, why in sk]

    # -- rows ------------------------------------------------------------------------------------
    def _row_iter(self) -> Iterator[tuple]:
        # without skipping, step k uses row k: no row past max_steps is needed
        skipping = any(getattr(s, "skip_bad", False) for s in self.sequences)
        max_rows = None if skipping else self.max_steps
        if self.workers == 0:
            yield from _rows(self.sequences, 0, 1, max_rows)
            return
        with warnings.catch_warnings():
            # torch warns when workers outnumber the cores: the user asked for them
            warnings.filterwarnings("ignore", message="This DataLoader will create")
            loader = torch.utils.data.DataLoader(
                _Rows(self.sequences, max_rows), batch_size=None, num_workers=self.workers,
                prefetch_factor=self.prefetch, collate_fn=_as_is, worker_init_fn=_init_worker)
            it = iter(loader)
        want, held = 0, []
        for row in it:
            heapq.heappush(held, (row[0], id(row), row))
            while held and held[0][0] == want:
                yield heapq.heappop(held)[2]
                want += 1
        while held:  # only if a worker ended early (cannot happen: every worker sees every stream end)
            yield heapq.heappop(held)[2]

    def _stage(self, raw: List[np.ndarray], step: int) -> Tuple[torch.Tensor, Optional[np.ndarray]]:
        """``(B, 1, H, W)`` uint8 images (a fresh tensor, or a pinned staging buffer) and the
        per-stream sizes of a padded batch of mixed sizes (``io.multistream.stack_images``)."""
        if not self.pin_memory:
            stacked, sizes = stack_images(raw)
            return torch.from_numpy(stacked[:, None]), sizes
        B, H, W = padded_shape(raw)
        shape = (B, 1, H, W)
        if not self._pinned or tuple(self._pinned[0].shape) != shape:
            self._pinned = [torch.empty(shape, dtype=torch.uint8).pin_memory() for _ in range(2)]
        buf = self._pinned[step % 2]  # two buffers: one may still be copying to the device
        _, sizes = stack_images(raw, out=buf.numpy()[:, 0])
        return buf, sizes

    # -- batches ---------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[Batch]:
        from ..io.frames import Frame

        B = len(self.sequences)
        self._skipped = [[] for _ in range(B)]
        self.decode_seconds = self.wait_seconds = 0.0
        rows = self._row_iter()
        queues: List[deque] = [deque() for _ in range(B)]
        exhausted = [False] * B

        def pull() -> None:
            t0 = time.perf_counter()
            row = next(rows, None)
            self.wait_seconds += time.perf_counter() - t0
            if row is None:
                for b in range(B):
                    exhausted[b] = True
                return
            _, slots, t_dec = row
            self.decode_seconds += t_dec
            for b, s in enumerate(slots):
                if exhausted[b]:
                    continue
                if s[0] == _END:  # rows come in order: stream b has no frame from this row on
                    exhausted[b] = True
                    continue
                queues[b].append(s)
                if s[0] == _RAISE:
                    exhausted[b] = True

        def next_frame(b: int):
            seq = self.sequences[b]
            while True:
                while not queues[b] and not exhausted[b]:
                    pull()
                if not queues[b]:
                    return None
                s = queues[b].popleft()
                if s[0] == _OK:
                    img = s[4].numpy() if isinstance(s[4], torch.Tensor) else s[4]
                    return Frame(s[1], s[2], img, s[3])
                if s[0] == _RAISE:
                    raise s[1]
                if not getattr(seq, "skip_bad", False):  # the pipelines' option: the CLI maps it to its flag
                    raise BadFrameError.naming(s[2], "skip_bad_frames")
                self._skipped[b].append((s[1], s[2]))

        try:
            steps = lockstep(self.sequences, next_frame, self._check, self.max_steps,
                             lambda b: len(self._skipped[b]))
            for step, frames, alive in steps:
                raw = [f.image for f in frames]
                stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
                images, sizes = self._stage(raw, step)
                yield Batch(step=step, images=images, timestamps=torch.from_numpy(ns_to_seconds(stamps)),
                            stamps_ns=stamps, alive=torch.tensor(alive), sources=[f.source for f in frames], raw=raw,
                            sizes=sizes)
        finally:
            close = getattr(rows, "close", None)
            if close is not None:
                close()  # stops the DataLoader's workers now, not at garbage collection
