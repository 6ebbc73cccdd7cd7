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
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

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


__all__ = ["mono_clock", "count_published", "ClockDecision", "c_round"]
