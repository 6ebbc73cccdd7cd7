"""``MultiStream``: B sequences read in lock step, one batch per tracker call.

Convention:
    Step ``k`` takes the next readable frame of every stream; each stream keeps its own
    timestamps (they need not agree across streams). A stream that has ended (or, with
    ``skip_bad``, has no readable frame left) is *dead*: it is fed its last image and its last
    timestamp again and ``alive[b]`` is False. Callers ignore a dead stream's tracker output.

    Why "last image, last timestamp": the batch must keep B images; repeating the last frame keeps
    the dead stream's inputs valid (same size, finite, non-decreasing time). Pass ``alive`` as
    ``FeatureTracker.track(..., active=alive)`` so that the tracker leaves a dead stream's state
    untouched and reports nothing for it.

    Iteration stops when every stream has ended, or after ``max_steps`` steps.

    Image sizes: one expected ``(H, W)`` for every stream, or one per stream (a rig or a mixed
    batch: each stream checked against its own config's size). When a step's images differ in
    size, ``Batch.images`` is one ``(B, 1, H, W)`` batch zero-padded at the bottom and right to the
    largest ``H`` and ``W``, and ``Batch.sizes`` holds every stream's ``(H_b, W_b)`` (what
    ``FeatureTracker.track(..., sizes=)`` takes); otherwise ``sizes`` is None.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Iterator, List, Optional, Tuple
from typing import Sequence as Seq

import numpy as np
import torch

from .frames import DataError, Frame, Sequence


@dataclasses.dataclass
class Batch:
    """One step of B streams.

    Attributes:
        step: 0-based step number.
        images: ``(B, 1, H, W)`` uint8 tensor (dead streams: their last image).
        timestamps: ``(B,)`` float64 seconds (dead streams: their last timestamp).
        stamps_ns: ``(B,)`` int64 numpy, exact nanoseconds.
        alive: ``(B,)`` bool tensor: the stream delivered a new frame this step.
        sources: per stream, the file / message of the frame.
        raw: per stream, the ``(H, W)`` uint8 numpy image (for drawing).
        sizes: ``(B, 2)`` int64 numpy ``(H_b, W_b)`` per stream when the images differ in size
            (``images`` is then padded; module docstring), else None.
    """

    step: int
    images: torch.Tensor
    timestamps: torch.Tensor
    stamps_ns: np.ndarray
    alive: torch.Tensor
    sources: List[str]
    raw: List[np.ndarray]
    sizes: Optional[np.ndarray] = None


def image_sizes(raw: Seq[np.ndarray]) -> Optional[np.ndarray]:
    """``(B, 2)`` int64 ``(H_b, W_b)`` of ``raw`` when they differ in size, else None."""
    hw = [tuple(int(x) for x in im.shape[:2]) for im in raw]
    if all(h == hw[0] for h in hw[1:]):
        return None
    return np.asarray(hw, dtype=np.int64)


def stack_images(raw: Seq[np.ndarray], out: Optional[np.ndarray] = None) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """``(B, H, W)`` uint8 of B ``(H_b, W_b)`` images (into ``out`` when given) and their sizes:
    one size: stacked, sizes None; several: zero-padded at the bottom and right to the largest
    (``image_sizes``)."""
    sizes = image_sizes(raw)
    if sizes is None:
        return np.stack(raw, out=out), None
    shape = (len(raw), int(sizes[:, 0].max()), int(sizes[:, 1].max()))
    if out is None:
        out = np.zeros(shape, dtype=np.uint8)
    else:
        out[...] = 0
    for b, im in enumerate(raw):  # one copy per stream, not per pixel
        out[b, : im.shape[0], : im.shape[1]] = im
    return out, sizes


def padded_shape(raw: Seq[np.ndarray]) -> Tuple[int, int, int]:
    """``(B, H, W)`` of :func:`stack_images`'s batch of ``raw``."""
    return (len(raw), max(int(im.shape[0]) for im in raw), max(int(im.shape[1]) for im in raw))


def ns_to_seconds(stamps_ns: np.ndarray) -> np.ndarray:
    """Integer ns → float64 s, splitting whole seconds first (a plain ``ns * 1e-9`` rounds the
    19-digit integer to float64 before scaling)."""
    s = np.asarray(stamps_ns, dtype=np.int64)
    return (s // 1_000_000_000).astype(np.float64) + (s % 1_000_000_000).astype(np.float64) * 1e-9


class MultiStream:
    """Iterate B ``Sequence`` objects together.

    Args:
        sequences: the B sequences.
        size: expected ``(H, W)`` of every image (the config's ``image_height, image_width``),
            or a sequence of one ``(H, W)`` per stream (each stream's config); a frame of another
            size raises ``DataError`` naming it. ``None``: the first frame's, for every stream.
        max_steps: stop after this many steps (``None``: until every stream has ended).

    Raises (while iterating):
        DataError: a bad frame (without ``skip_bad``), a size mismatch, or a stream with no
            readable frame at all.
    """

    def __init__(self, sequences: Seq[Sequence], size: Tuple[int, int] | None = None,
                 max_steps: int | None = None):
        if len(sequences) == 0:
            raise DataError("no input sequence given")
        self.sequences = list(sequences)
        self.sizes: Optional[List[Tuple[int, int]]] = None  # one (H, W) per stream
        self.size = None
        if size is not None and len(size) and isinstance(size[0], (tuple, list, np.ndarray)):
            if len(size) != len(self.sequences):
                raise ValueError(f"size: expected one (H, W) per sequence ({len(self.sequences)}), got {len(size)}")
            self.sizes = [(int(s[0]), int(s[1])) for s in size]
            if all(s == self.sizes[0] for s in self.sizes):
                self.size, self.sizes = self.sizes[0], None
        elif size is not None:
            self.size = (int(size[0]), int(size[1]))
        self.max_steps = None if max_steps is None else int(max_steps)

    @property
    def num_streams(self) -> int:
        return len(self.sequences)

    def __len__(self) -> int:
        """Upper bound of the number of steps (skipped frames make it shorter)."""
        n = max(len(s) for s in self.sequences)
        return n if self.max_steps is None else min(n, self.max_steps)

    @property
    def skipped(self) -> List[Tuple[int, str, str]]:
        """``(stream, source, reason)`` of every frame skipped so far."""
        return [(b, src, why) for b, s in enumerate(self.sequences) for src, why in s.skipped]

    def _check(self, b: int, frame: Frame) -> None:
        h, w = frame.image.shape
        if self.sizes is not None:
            H, W = self.sizes[b]
            if (h, w) != (H, W):
                raise DataError(f"{frame.source}: image size {w}x{h} differs from the expected {W}x{H} of stream {b} "
                                f"(its config's image_width x image_height)")
        elif self.size is None:
            self.size = (h, w)
        elif (h, w) != self.size:
            raise DataError(
                f"{frame.source}: image size {w}x{h} differs from the expected {self.size[1]}x{self.size[0]} "
                f"(the config's image_width x image_height)"
            )

    def __iter__(self) -> Iterator[Batch]:
        iters = [iter(s) for s in self.sequences]
        steps = lockstep(self.sequences, lambda b: next(iters[b], None), self._check, self.max_steps,
                         lambda b: len(self.sequences[b].skipped))
        for step, frames, alive in steps:
            raw = [f.image for f in frames]
            stacked, sizes = stack_images(raw)
            images = torch.from_numpy(stacked[:, None])
            stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
            yield Batch(
                step=step,
                images=images,
                timestamps=torch.from_numpy(ns_to_seconds(stamps)),
                stamps_ns=stamps,
                alive=torch.tensor(alive),
                sources=[f.source for f in frames],
                raw=raw,
                sizes=sizes,
            )


def lockstep(sequences: Seq, next_frame: Callable[[int], Optional[Frame]], check: Callable[[int, Frame], None],
             max_steps: Optional[int], skipped: Callable[[int], int]) -> Iterator[Tuple[int, List[Frame], List[bool]]]:
    """The steps of the module docstring's convention: ``(step, frames, alive)`` per step, ``frames``
    the B streams' current frames (a dead stream's last one), ``alive`` which streams delivered one.

    Shared by ``MultiStream`` and ``pipelines.FrameStream`` (same steps, masks and errors).

    Args:
        sequences: the B streams (for ``len`` and ``name`` in the error message).
        next_frame: ``b -> Frame | None``: stream ``b``'s next readable frame, ``None`` at its end
            (it raises ``DataError`` for a bad frame without ``skip_bad``).
        check: ``(b, frame)``: called on every new frame of stream ``b`` (the size check).
        max_steps: stop after this many steps (``None``: until every stream has ended).
        skipped: ``b -> number of frames of stream b skipped as bad`` (for the error message).

    Raises:
        DataError: a stream ended without a readable frame.
    """
    B = len(sequences)
    last: List[Optional[Frame]] = [None] * B
    ended = [False] * B
    step = 0
    while max_steps is None or step < max_steps:
        alive = [False] * B
        for b in range(B):
            if ended[b]:
                continue
            fr = next_frame(b)
            if fr is None:
                ended[b] = True
                if last[b] is None:
                    s = sequences[b]
                    raise DataError(f"{s.name}: no readable frame in the sequence ({len(s)} listed, "
                                    f"{skipped(b)} skipped as bad)")
                continue
            check(b, fr)
            last[b] = fr
            alive[b] = True
        if not any(alive):
            return
        yield step, list(last), alive  # every entry is set: a stream that never had a frame raised above
        step += 1

__all__ = ["MultiStream", "Batch", "image_sizes", "ns_to_seconds", "padded_shape", "stack_images"]
