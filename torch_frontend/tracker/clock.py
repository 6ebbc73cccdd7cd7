"""VINS-Mono's ``img_callback`` clock rules (spec §3.2), per stream: skip, restart, publish.

Convention:
    ``t (B,)`` float64 seconds; ``arrived (B,)`` bool, the streams that got an image this step (the
    caller's ``active``; the others keep their clock exactly). All decisions are masks, so every
    stream runs through the same tensor code.

Rules, per stream with an image:

1. the first image (``first_image_flag``) only starts the clock; it is not tracked;
2. a step of more than ``restart_gap`` (1 s) or backwards in time restarts the stream: the image is
   dropped, ``first_image_flag`` is set again (so the next image is skipped too) and
   ``pub_count = 1``; the tracker's features are *not* cleared;
3. otherwise the image is tracked, and published when ``C round(pub_count / (t - first_image_time))
   <= freq``; when that rate is within ``freq_reset_tolerance * freq`` of ``freq`` the rate window
   restarts (``first_image_time = t``, ``pub_count = 0``). A duplicate stamp gives rate +inf: not
   published.

The decisions depend on the timestamps, ``active`` and the clock state only, so the host can take
them before the upload: :class:`HostClock` runs the same rules on the host's copy of the clock (the
tracker's mirror, numpy), and :func:`publish_plan` turns the number of publishing streams into the step's
variant (:class:`PublishPlan`: track only, a sub-batch of ``lane_sizes`` lanes, or every stream).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import warnings
import weakref
from typing import List, NamedTuple, Optional, Tuple

import numpy as np
import torch

from .params import TrackerParams
from .state import ClockState

Tensor = torch.Tensor


class ClockDecision(NamedTuple):
    """What the clock decided for this step, each ``(B,)`` bool."""

    tracked: Tensor  # the image is tracked (readImage runs)
    publish: Tensor  # PUB_THIS_FRAME
    restarted: Tensor  # a restart was signalled (gap or time going backwards)


def c_round(x: Tensor) -> Tensor:
    """C ``round``: half away from zero (VINS's publish-rate rule), not Python's banker's rounding.

    Exact for every float: ``x - trunc(x)`` is exact, whereas ``floor(|x| + 0.5)`` rounds
    0.49999999999999994 up (the addition rounds to 1.0). inf stays inf."""
    whole = torch.trunc(x)
    frac = x - whole
    frac = torch.where(torch.isfinite(x), frac, torch.zeros_like(frac))
    return whole + torch.sign(frac) * (frac.abs() >= 0.5).to(x.dtype)


def mono_clock(clock: ClockState, t: Tensor, arrived: Tensor, params: TrackerParams):
    """Apply the ``img_callback`` rules to one image per stream.

    Returns ``(clock, decision)``: the clock after this image *before* the published frame is
    counted (:func:`count_published` does that once the frame is built) and the
    :class:`ClockDecision`.
    """
    freq = float(params.freq)
    first = clock.first_image_flag & arrived
    gap = arrived & ~clock.first_image_flag & ((t - clock.last_image_time > params.restart_gap)
                                               | (t < clock.last_image_time))
    tracked = arrived & ~clock.first_image_flag & ~gap
    first_image_time = torch.where(first, t, clock.first_image_time)
    last_image_time = torch.where(first | tracked, t, torch.where(gap, torch.zeros_like(t), clock.last_image_time))
    pub_count = torch.where(gap, torch.ones_like(clock.pub_count), clock.pub_count)
    flag = torch.where(first, torch.zeros_like(first), torch.where(gap, torch.ones_like(first), clock.first_image_flag))
    dt = t - first_image_time
    # a duplicate stamp (dt == 0) gives rate +inf: never published; the clamp keeps the unused
    # lanes finite
    rate = torch.where(dt > 0, pub_count.to(torch.float64) / dt.clamp_min(1e-300), torch.full_like(t, math.inf))
    publish = tracked & (c_round(rate) <= freq)
    reset = publish & ((rate - freq).abs() < params.freq_reset_tolerance * freq)
    clock = dataclasses.replace(
        clock, first_image_flag=flag, first_image_time=torch.where(reset, t, first_image_time),
        last_image_time=last_image_time, pub_count=torch.where(reset, torch.zeros_like(pub_count), pub_count))
    return clock, ClockDecision(tracked=tracked, publish=publish, restarted=gap)


def count_published(clock: ClockState, publish: Tensor):
    """After a published frame: ``pub_count += 1``; the first published frame of a stream is not
    sent (``init_pub``, spec §3.2 step 7). Returns ``(clock, sent)``."""
    sent = publish & clock.init_pub
    clock = dataclasses.replace(clock, init_pub=clock.init_pub | publish,
                                pub_count=torch.where(publish, clock.pub_count + 1, clock.pub_count))
    return clock, sent


@dataclasses.dataclass
class HostClock:
    """The host's mirror of a :class:`ClockState` (the fields that decide publishing), numpy
    ``(B,)`` arrays: ``first_image_flag`` bool, ``first_image_time`` / ``last_image_time`` float64 s,
    ``pub_count`` int64. :meth:`step` applies :func:`mono_clock`'s rules and
    :func:`count_published`'s count in numpy: host work of a few microseconds per step, where the
    same rules as ~35 CPU torch ops cost ~0.3 ms of dispatch. The decisions are the device's bit for
    bit: the same float64 operations in the same order (one division, a subtraction, C rounding by
    ``trunc``, comparisons), each correctly rounded in IEEE arithmetic on both sides."""

    first_image_flag: np.ndarray
    first_image_time: np.ndarray
    last_image_time: np.ndarray
    pub_count: np.ndarray

    @classmethod
    def initial(cls, batch: int) -> HostClock:
        """As ``ClockState.initial``."""
        return cls(np.ones(batch, bool), np.zeros(batch), np.zeros(batch), np.ones(batch, np.int64))

    @classmethod
    def of(cls, clock: ClockState) -> HostClock:
        """A device clock read back (one host sync per field on a GPU)."""
        return cls(*(getattr(clock, f.name).detach().cpu().numpy().copy() for f in dataclasses.fields(cls)))

    def step(self, t: np.ndarray, arrived: np.ndarray, params: TrackerParams):
        """:func:`mono_clock` then :func:`count_published` for ``t (B,)`` float64 and ``arrived (B,)``
        bool. Returns ``(clock after the step, publish (B,) bool)``."""
        return self.decide(t, arrived, params)[:2]

    def decide(self, t: np.ndarray, arrived: np.ndarray, params: TrackerParams):
        """:meth:`step`, and the step's ``tracked (B,)`` bool (the device's ``ClockDecision.tracked``):
        ``(clock after the step, publish, tracked)``."""
        freq = float(params.freq)
        flag0, last0 = self.first_image_flag, self.last_image_time
        first = flag0 & arrived
        gap = arrived & ~flag0 & ((t - last0 > params.restart_gap) | (t < last0))
        tracked = arrived & ~flag0 & ~gap
        first_image_time = np.where(first, t, self.first_image_time)
        last_image_time = np.where(first | tracked, t, np.where(gap, 0.0, last0))
        pub_count = np.where(gap, 1, self.pub_count)
        flag = np.where(first, False, np.where(gap, True, flag0))
        dt = t - first_image_time
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            rate = np.where(dt > 0, pub_count.astype(np.float64) / np.maximum(dt, 1e-300), math.inf)
            whole = np.trunc(rate)
            frac = np.where(np.isfinite(rate), rate - whole, 0.0)
        rounded = whole + np.sign(frac) * (np.abs(frac) >= 0.5)
        publish = tracked & (rounded <= freq)
        reset = publish & (np.abs(rate - freq) < params.freq_reset_tolerance * freq)
        pub_count = np.where(reset, 0, pub_count) + publish  # the reset, then count_published's += 1
        clock = HostClock(flag, np.where(reset, t, first_image_time), last_image_time, pub_count)
        return clock, publish, tracked


def lane_sizes(batch: int) -> Tuple[int, ...]:
    """The sub-batch sizes of the publish stages for ``batch`` streams: the powers of two below
    ``batch``, then ``batch`` itself (every stream under masks, no gather). Padding is under half of
    a sub-batch, and B streams need at most ``ceil(log2 B) + 2`` captured variants with track-only
    (each one a whole-step compile: fewer, coarser sizes keep ``compile()`` affordable)."""
    sizes = tuple(1 << i for i in range(max(batch - 1, 0).bit_length()) if 1 << i < batch)
    return sizes + (batch,)


class PublishPlan(NamedTuple):
    """The step variant chosen on the host from the publishing count (static: a compiled step is
    captured once per plan). ``lanes``: 0, no stream publishes (track only: no rejectWithF, setMask,
    addPoints or updateID); ``batch``, every stream runs the publish stages under masks; in between,
    the publishing streams (and ``lanes - n`` non-publishing ones as padding) are gathered into a
    sub-batch of ``lanes`` streams for those stages and written back. ``every_tracked``: the host
    knows that every stream is tracked (the steady state: no first image, gap or inactive stream),
    so the step keeps this frame's pyramid as it is instead of selecting it per stream (the select
    reads and writes every level of both pyramids: ~13 MB per EuRoC stream per step)."""

    lanes: int
    batch: int
    every_tracked: bool = False

    @property
    def name(self) -> str:
        """``track``, ``all`` or ``sub<lanes>``, ``_every`` appended with ``every_tracked`` (labels,
        the compiled variants' names)."""
        base = "track" if self.lanes == 0 else "all" if self.lanes >= self.batch else f"sub{self.lanes}"
        return base + "_every" if self.every_tracked else base


def publish_plan(n_publish: int, batch: int, every_tracked: bool = False) -> PublishPlan:
    """The plan for ``n_publish`` publishing streams out of ``batch``: the smallest of
    :func:`lane_sizes` that holds them (0 lanes when none publishes); ``every_tracked`` as
    :class:`PublishPlan`'s (True only where every stream is tracked in this step)."""
    if not 0 <= n_publish <= batch:
        raise ValueError(f"n_publish: expected 0..{batch}, got {n_publish}")
    if n_publish == 0:
        return PublishPlan(0, batch, bool(every_tracked))
    return PublishPlan(next(n for n in lane_sizes(batch) if n >= n_publish), batch, bool(every_tracked))


#: consecutive restarting steps of one stream after which :class:`RestartWatch` warns (once per
#: stream): one gap is a pause in a recording; three in a row mean nothing will ever be published
RESTART_WARN_STEPS = 3


def _host_values(x, batch: int, dtype) -> Optional[List]:
    """``x`` as a list of ``batch`` Python values when it is on the host (a number, a sequence, a
    numpy array or a CPU tensor), else None (a device tensor: reading it would be a host sync)."""
    if isinstance(x, torch.Tensor):
        if x.device.type != "cpu":
            return None
        try:  # a CPU tensor: no copy, no kernel, no sync (one alias op, detach, under a dispatch mode)
            x = (x.detach() if x.requires_grad else x).numpy()
        except (RuntimeError, TypeError):  # a fake or wrapped tensor: no values to read
            return None
    try:
        import numpy as np

        v = np.asarray(x, dtype=dtype).reshape(-1)
    except (TypeError, ValueError):
        return None
    if v.size == 1:
        v = np.repeat(v, batch)
    return v.tolist() if v.size == batch else None


def _outside_package() -> int:
    """The ``stacklevel`` of the first frame outside ``torch_frontend``, for a warning issued here."""
    pkg = __file__.rsplit("tracker", 1)[0]
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(pkg):
        frame, level = frame.f_back, level + 1
    return level


def _gap_hint(gaps: List[float]) -> str:
    """What a run of restarting steps most likely means, from the sizes of its steps (seconds)."""
    if all(g < 0 for g in gaps):
        return "time goes backwards at every step: are the frames in order?"
    g = sorted(abs(x) for x in gaps)[len(gaps) // 2]
    if g >= 1e6:
        return f"steps of ~{g:.2g} look like nanoseconds (EuRoC, ROS stamps): divide the timestamps by 1e9"
    if g >= 5e3:
        return f"steps of ~{g:.2g} look like microseconds: divide the timestamps by 1e6"
    if g >= 5:
        return f"steps of ~{g:.2g} look like milliseconds: divide the timestamps by 1e3"
    return "are the frames really more than 1 s apart? VINS restarts a stream on every such step"


class RestartWatch:
    """Host-side watch over the timestamps a ``FeatureTracker`` is given: a stream whose last
    ``RESTART_WARN_STEPS`` steps were each a restart by the clock's rule (a step of more than
    ``restart_gap`` s, or backwards) gets one ``UserWarning`` naming the steps it saw and their
    likely unit (nanoseconds or milliseconds passed as seconds make every frame a restart: ``valid``
    all False, nothing published). Once per stream per watch.

    It reads only values that are on the host already (Python numbers, sequences, numpy arrays,
    CPU tensors): timestamps or ``active`` given as device tensors are not watched (reading them
    would be a host sync on the capturable path). It follows one chain of states: a step from a
    state other than the one the previous watched step returned (``reset()``, ``initial_state()``,
    an older state) starts the watch afresh.
    """

    def __init__(self, batch: int, restart_gap: float, steps: int = RESTART_WARN_STEPS):
        self.batch, self.restart_gap, self.steps = int(batch), float(restart_gap), int(steps)
        self.warned: set = set()
        self._forget()

    def _forget(self) -> None:
        self.last: List[Optional[float]] = [None] * self.batch
        self.run: List[List[float]] = [[] for _ in range(self.batch)]
        self._follows = None

    def observe(self, state, timestamps, active) -> None:
        """Look at one step's ``timestamps`` (and ``active``) from ``state``; warn where a stream's
        run of restarting steps reaches ``steps`` (the warning points at the first caller outside
        the package)."""
        if self._follows is None or self._follows() is not state:
            self._forget()
        t = _host_values(timestamps, self.batch, "float64")
        a = [True] * self.batch if active is None else _host_values(active, self.batch, "bool")
        if t is None or a is None:
            self._forget()
            return
        for b in range(self.batch):
            if not a[b]:
                continue
            last, self.last[b] = self.last[b], t[b]
            if last is None:
                continue
            gap = t[b] - last
            if gap > self.restart_gap or gap < 0:
                self.run[b] = (self.run[b] + [gap])[-self.steps:]
            else:
                self.run[b] = []
            if len(self.run[b]) == self.steps and b not in self.warned:
                self.warned.add(b)
                seen = ", ".join(f"{g:.4g} s" for g in self.run[b])
                warnings.warn(f"timestamps of stream {b}: {self.steps} steps in a row restarted it (steps {seen}: "
                              f"each more than {self.restart_gap:g} s or backwards), so it publishes nothing; "
                              f"{_gap_hint(self.run[b])}", UserWarning, stacklevel=_outside_package())

    def follow(self, state) -> None:
        """The state the watched step returned: the next :meth:`observe` continues from it."""
        try:
            self._follows = weakref.ref(state)
        except TypeError:  # not weak-referenceable: watch every step as a continuation
            self._follows = lambda: state


__all__ = ["mono_clock", "count_published", "ClockDecision", "c_round", "HostClock", "lane_sizes",
           "PublishPlan", "publish_plan", "RestartWatch", "RESTART_WARN_STEPS"]
