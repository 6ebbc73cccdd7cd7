"""One pure tracker step: ``state, frame = step(state, images, timestamps, params)``.

Convention:
    ``images (B, 1, H, W)`` uint8 (``(B, H, W)``, any strides and float 0..255 accepted at the door:
    float is rounded and clamped as cv_bridge would; NaN pixels and float images in 0..1 are
    refused), ``timestamps (B,)`` float64 seconds (float32 only where it resolves a millisecond:
    not epoch seconds; integer tensors and arrays are refused, naming the likely unit), ``active (B,)`` bool (a stream with False is left exactly as it was, e.g.
    a sequence that has ended). The state is not modified: the step returns a new
    :class:`TrackerState` and a :class:`FeatureFrame`.

    Mono (VINS-Mono ``feature_tracker``, spec §3): clock rules -> CLAHE -> pyramid -> LK, inBorder,
    compaction, ``track_cnt += 1`` -> on published frames rejectWithF, setMask, addPoints ->
    updateID -> undistortedPoints. Fusion (VINS-Fusion tracker, spec §6): every image is tracked
    and detects, no CLAHE and no rejectWithF, ids at detection, optional stereo.

:func:`step` validates its inputs once; :func:`step_impl` is the same step on validated inputs
(what ``FeatureTracker`` calls after its own checks).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Callable, Optional, Tuple

import torch

from .._autodiff import derivative_wanted, is_vmapped, straight_through
from .._checks import as_image_batch, check_shape
from ..lk import _prime_next_pyramid, exact_float32
from .clock import ClockDecision, PublishPlan, count_published, mono_clock
from .frame import FeatureFrame
from .params import TrackerParams
from .stages import (
    add_points,
    equalize,
    front,
    front_group,
    image_pyramid,
    merge_overflow,
    no_stage,
    reject_with_f,
    select_pyramid,
    set_mask,
    track_features,
    track_right,
    undistorted_points,
    update_id,
)
from .state import TrackerState

Tensor = torch.Tensor

#: timestamps in a float type narrower than float64 are refused where its resolution at the given
#: times is coarser than this (s): float32 resolves epoch seconds (1.4e9 s) only to 128 s, so frames
#: share times and the clock publishes nothing; float32 seconds since the start (< 2^14 s, 4.5 h) pass
TIMESTAMP_RESOLUTION = 1e-3


# ---------------------------------------------------------------------------------------------
# the door


def _check_float_values(img: Tensor, rounded: Tensor, name: str) -> None:
    """Refuse float images the 8-bit conversion would silently turn into garbage: NaN pixels
    (they would become 0) and images in 0..1 (every stream whose values are all <= 1 with a
    fractional one: rounding leaves a black and white image). One host sync, float input only."""
    flat, frac = img.flatten(1), (img != rounded).flatten(1)
    nan = torch.isnan(flat).any(1)
    unit = (flat.amax(1) <= 1) & frac.any(1)
    bad_nan, bad_unit = torch.stack((nan.any(), unit.any())).tolist()
    if bad_nan:
        streams = nan.nonzero().flatten().tolist()
        raise ValueError(f"{name}: NaN pixels in stream(s) {streams} (not a grey level: 8-bit conversion would "
                         f"read them as 0)")
    if bad_unit:
        streams = unit.nonzero().flatten().tolist()
        raise ValueError(f"{name}: image values look like 0..1 (stream(s) {streams}: all <= 1, not integers); "
                         f"this library expects grey levels 0..255 (multiply by 255)")


def check_images(images, params: TrackerParams, batch: int, device, name: str = "images",
                 size: Optional[Tuple[int, int]] = None) -> Tensor:
    """``images`` as contiguous ``(B, 1, H, W)`` uint8 on ``device`` (``params.differentiable``: float32
    with the same values, straight-through gradients: :func:`_straight_through_8bit`). Mono: ``H, W`` must be the
    config's; fusion tracks each image at its real size as VINS-Fusion (spec §6.2; the config's
    size is the estimator's), any size the kernels can work on, but ``size`` (the previous image's
    ``(H, W)``) when given: LK needs both images of a pair at one size. Float input: NaN pixels and
    0..1 images raise ``ValueError`` (:func:`_check_float_values`)."""
    if is_vmapped(images):
        raise ValueError(f"{name}: torch.func.vmap of a tracker step is not supported (its CPU path has host "
                         f"syncs and data-dependent shapes that vmap cannot batch); the step is batched "
                         f"already: put the outer batch into the streams, FeatureTracker(cfg, num_streams=V * B)")
    img = as_image_batch(torch.as_tensor(images), name)
    if img.shape[0] != batch:
        raise ValueError(f"{name}: expected {batch} streams (B, 1, H, W), got {tuple(img.shape)}")
    hw = (int(img.shape[-2]), int(img.shape[-1]))
    if params.mode == "mono" and hw != (params.height, params.width):
        raise ValueError(f"{name}: image size {hw[1]}x{hw[0]} differs from the config's "
                         f"image_width x image_height = {params.width}x{params.height}")
    if size is not None and hw != tuple(size):
        raise ValueError(f"{name}: image size {hw[1]}x{hw[0]} differs from the previous image's {size[1]}x{size[0]}")
    if params.mode != "mono":
        params.check_image_size(*hw)
    img = img.to(device)
    if params.differentiable:
        return _straight_through_8bit(img, name)
    if img.requires_grad:
        warnings.warn(f"{name}: the images require a gradient, but this tracker is not differentiable: the "
                      f"8-bit path rounds them and cuts the graph (use FeatureTracker(..., differentiable=True))",
                      UserWarning, stacklevel=4)
    if img.dtype != torch.uint8:
        # VINS works on 8-bit images; float input is rounded and clamped the way cv_bridge would.
        rounded = img.round()
        _check_float_values(img, rounded, name)
        img = rounded.clamp(0, 255).to(torch.uint8)
    # the kernels view images as flat rows: a transposed or expanded image is copied (no-op otherwise)
    return img.contiguous()


def _straight_through_8bit(img: Tensor, name: str) -> Tensor:
    """The differentiable tracker's door: ``(B, 1, H, W)`` float32 holding the 8-bit path's grey
    levels exactly (uint8 as is; float rounded half to even and clamped to 0..255 as cv_bridge), with
    the gradient of the clamp alone (straight through the rounding: the identity inside 0..255).

    float32 because the 8-bit path's pyramid is float32; the cast is differentiable, so a float64
    image gets its gradient (``_autodiff.straight_through``: the value is the rounded image bit for bit)."""
    if img.dtype == torch.uint8:
        return img.to(torch.float32).contiguous()
    rounded = img.detach().round()
    _check_float_values(img.detach(), rounded, name)
    hard = rounded.clamp(0, 255).to(torch.float32)
    if not derivative_wanted(img):
        return hard.contiguous()
    return straight_through(img.clamp(0, 255).to(torch.float32), hard).contiguous()


def _narrow_float(timestamps) -> Optional[torch.dtype]:
    """The float dtype of a tensor / numpy array or scalar narrower than float64, else None."""
    if isinstance(timestamps, torch.Tensor):
        dt = timestamps.dtype
    elif hasattr(timestamps, "dtype") and hasattr(timestamps, "shape"):  # numpy, without importing it
        dt = torch.as_tensor(timestamps).dtype
    else:
        return None  # Python numbers and sequences are converted to float64 exactly
    return dt if dt.is_floating_point and torch.finfo(dt).bits < 64 else None


def _integer_dtype(timestamps) -> Optional[torch.dtype]:
    """The integer dtype of a tensor / numpy array (``bool`` included), else None (Python numbers
    and sequences are seconds, converted to float64)."""
    if isinstance(timestamps, torch.Tensor):
        dt = timestamps.dtype
    elif hasattr(timestamps, "dtype") and hasattr(timestamps, "shape"):  # numpy, without importing it
        dt = torch.as_tensor(timestamps).dtype
    else:
        return None
    return None if dt.is_floating_point or dt.is_complex else dt


#: (smallest magnitude, unit, divisor to seconds) of integer epoch times, largest first: seconds are
#: ~1.7e9, milliseconds ~1.7e12, microseconds ~1.7e15, nanoseconds (EuRoC, ROS stamps) ~1.7e18
EPOCH_UNITS = ((1e17, "nanoseconds", "1e9"), (1e14, "microseconds", "1e6"), (1e11, "milliseconds", "1e3"))


def unit_hint(magnitude: float) -> Optional[Tuple[str, str]]:
    """``(unit, divisor)`` that epoch times of about ``magnitude`` most likely count (None: they
    could be seconds)."""
    for low, unit, div in EPOCH_UNITS:
        if magnitude >= low:
            return unit, div
    return None


def check_timestamps(timestamps, batch: int, device) -> Tensor:
    """``(B,)`` float64 finite seconds on ``device`` (a scalar is broadcast to every stream).

    An integer tensor or array is refused (``ValueError``): integer times are nanoseconds or
    milliseconds far more often than seconds (EuRoC's int64 ns would make every frame a restart, so
    nothing would be published); the message names the likely unit from the values' size. Python
    numbers and sequences are seconds. A float32 (or narrower) tensor or array is refused where it
    cannot resolve ``TIMESTAMP_RESOLUTION`` at its times (epoch seconds): the precision is gone
    before the cast.
    """
    whole = _integer_dtype(timestamps)
    if whole is not None:
        vals = torch.as_tensor(timestamps)
        tmax = float(vals.abs().max()) if vals.numel() and whole != torch.bool else 0.0  # an error: a sync is fine
        dt = str(whole).replace("torch.", "")
        unit = unit_hint(tmax)
        if unit is not None:
            hint = (f"values around {tmax:.2g} look like {unit[0]}{' (EuRoC, ROS stamps)' if unit[1] == '1e9' else ''}: "
                    f"pass timestamps.double() / {unit[1]}")
        else:
            hint = ("if they count seconds pass timestamps.double(); nanoseconds or milliseconds since the start: "
                    "timestamps.double() / 1e9 or / 1e3")
        raise ValueError(f"timestamps are {dt} (integers, up to {tmax:.6g}): expected float64 seconds; {hint}")
    narrow = _narrow_float(timestamps)
    t = torch.as_tensor(timestamps, dtype=torch.float64)
    if t.dim() == 0:
        t = t.expand(batch)
    check_shape(t, (batch,), "timestamps")
    if not torch.isfinite(t).all():
        raise ValueError("timestamps: expected finite seconds, got a NaN or infinity")
    if narrow is not None:
        tmax = float(t.abs().max())
        step = torch.finfo(narrow).eps * 2.0 ** math.floor(math.log2(tmax)) if tmax > 0 else 0.0
        if step > TIMESTAMP_RESOLUTION:
            dt = str(narrow).replace("torch.", "")
            raise ValueError(f"timestamps are {dt}: epoch seconds need float64 ({dt} resolves {tmax:.6g} s only "
                             f"to {step:g} s, so frames share times and nothing is published)")
    return t.to(device)


def check_active(active, batch: int, device) -> Tensor:
    """``(B,)`` bool on ``device``; None means every stream."""
    if active is None:
        return torch.ones(batch, dtype=torch.bool, device=device)
    a = torch.as_tensor(active, device=device).to(torch.bool)
    check_shape(a, (batch,), "active")
    return a


def step(state: TrackerState, images, timestamps, params: TrackerParams, *, right=None, active=None,
         stage=no_stage) -> Tuple[TrackerState, FeatureFrame]:
    """One tracker step for B streams: validate, then :func:`step_impl`.

    Args:
        state: the streams' state (``TrackerState.initial(...)`` or the previous step's).
        images: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float 0..255.
        timestamps: ``(B,)`` seconds (float64 tensor or sequence), or one number for every stream.
        params: the static settings (:class:`TrackerParams`, with the cameras).
        right: fusion stereo only: camera 1's images, tracked left -> right with the same ids.
        active: optional ``(B,)`` bool; streams with False are left exactly as they were.
        stage: optional ``stage(name)`` context-manager factory (timing / labels).

    Returns:
        ``(new_state, frame)``.
    """
    img, t, arrived, r = check_inputs(state, params, images, timestamps, right, active)
    if torch.compiler.is_compiling():
        return step_impl(state, img, t, params, right=r, active=arrived, stage=stage)
    with exact_float32(img.device):  # CUDA: TF32 off while the step runs (the LK's exact window sums)
        return step_impl(state, img, t, params, right=r, active=arrived, stage=stage)


def check_inputs(state: TrackerState, params: TrackerParams, images, timestamps, right=None, active=None,
                 config_name: str = "the config"):
    """The door of :func:`step`: ``(images, timestamps, active, right)`` checked and normalised."""
    B, dev = state.batch, state.has_image.device
    prev = None if state.prev_pyramid is None else tuple(state.prev_pyramid.levels[0].shape[-2:])
    img = check_images(images, params, B, dev, size=prev)
    t = check_timestamps(timestamps, B, dev)
    arrived = check_active(active, B, dev)
    r = None
    if right is not None:
        if params.mode == "mono":
            raise ValueError("right: stereo images are only supported with mode='fusion'")
        if params.camera1 is None:
            raise ValueError(f"right: {config_name} has no cam1_calib (num_of_cam 2)")
        r = check_images(right, params, B, dev, "right", size=tuple(img.shape[-2:]))
    return img, t, arrived, r


def step_impl(state: TrackerState, img: Tensor, t: Tensor, params: TrackerParams, *, right: Optional[Tensor],
              active: Tensor, stage=no_stage, plan: Optional[PublishPlan] = None,
              regions: Optional[Callable] = None) -> Tuple[TrackerState, FeatureFrame]:
    """:func:`step` on validated inputs (``img (B, 1, H, W)`` uint8, ``t (B,)`` float64, ``active (B,)``
    bool, all on the state's device). Under ``torch.func`` transforms and forward-AD dual tensors
    every kernel takes its differentiable reference form where its own tensors carry a derivative
    (``_tuning.inplace_ok``), so no step-wide switch is needed.

    ``plan`` (mono, capturable; ``FeatureTracker`` takes it from its host mirror of the clock,
    ``clock.publish_plan``): which streams run the publish stages. It must hold every stream the
    clock publishes in this step (at least as many lanes); None runs them on every stream under
    masks. The outputs are the same for every plan that holds the publishing streams.

    ``regions`` (mono; ``FeatureTracker.compile(regions=True)``): ``regions(name, fn, *args)`` runs
    each of the step's three parts (:func:`_mono_track`, the publish stages, :func:`_mono_finish`),
    e.g. each compiled once and shared by every step variant; ``name`` says which code and which
    static arguments (the part's compiled graph). None calls them directly (one graph when the
    whole step is traced)."""
    if params.mode == "mono":
        return _mono(state, img, t, params, active, stage, plan, regions)
    return _fusion(state, img, t, right, params, active, stage)


# ---------------------------------------------------------------------------------------------
# the two modes


def _track(state: TrackerState, img: Tensor, tracked: Tensor, params: TrackerParams, stage):
    """CLAHE, pyramid and LK (``readImage`` up to ``track_cnt += 1``) for the ``tracked`` streams: on the
    CPU (mono, a previous pyramid) one op that works through a group of streams at a time
    (:func:`~.stages.front`), elsewhere three stage ops over the batch; the same bits. Returns ``(table, pyramid, equalised image, has_prediction after this step, overflow)``."""
    run = tracked & state.has_image  # streams with a previous image to track from
    group = front_group(img, state.prev_pyramid, state.features.pts, params)
    if group is not None:  # the CPU: the three stages as one op, a group of streams at a time
        with stage("front"):
            img_eq, pyr, lk = front(img, state.prev_pyramid, state.features, run, params, group)
        prev_pyr = state.prev_pyramid
    else:
        with stage("clahe"):
            img_eq = equalize(img, params)
        with stage("pyramid"):
            pyr = image_pyramid(img_eq, params)
        prev_pyr, lk = (state.prev_pyramid if state.prev_pyramid is not None else pyr), None
    table, overflow = track_features(state.features, prev_pyr, pyr, run, tracked, state.has_prediction, params,
                                     stage=stage, lk=lk)
    return table, pyr, img_eq, state.has_prediction & ~run, overflow  # a prediction is consumed by its step


def _detect(table, img_eq, detect: Tensor, params: TrackerParams, stage):
    """setMask and addPoints for the ``detect`` streams (on the image's own size, as VINS-Fusion;
    mono checked at the door that it is the config's)."""
    base = params.fisheye_mask if params.uses_fisheye_mask else None
    table, detection, of_mask = set_mask(table, detect, params, base, img_eq.shape[-2], img_eq.shape[-1], stage=stage)
    table, of_gftt = add_points(table, img_eq, detection, params, stage=stage)
    return table, merge_overflow(of_mask, of_gftt)


def _commit(state: TrackerState, table, next_id: Tensor, t: Tensor, pyr, tracked: Tensor, capturable: bool,
            every_tracked: bool = False, **changes) -> TrackerState:
    """The new state: streams in ``tracked`` take this step's table, id counter, time and pyramid;
    the others keep theirs exactly. ``every_tracked`` (the host's plan: ``tracked`` is all True):
    this step's pyramid as it is (the per-stream select would give the same values)."""
    return dataclasses.replace(
        state, features=table.committed().where_streams(tracked, state.features),
        next_id=torch.where(tracked, next_id, state.next_id), prev_time=torch.where(tracked, t, state.prev_time),
        prev_pyramid=pyr if every_tracked else select_pyramid(tracked, pyr, state.prev_pyramid, capturable),
        has_image=state.has_image | tracked,
        **changes)


def _frame(new: TrackerState, velocity: Tensor, tracked: Tensor, valid: Tensor, present: Tensor,
           decision: ClockDecision, sent: Tensor, t: Tensor, overflow: Optional[Tensor], **extra) -> FeatureFrame:
    """The published frame, from the committed table (copies: the frame never aliases the state).
    ``overflow`` None (the default path, exact) becomes all False."""
    f = new.features
    if overflow is None:
        overflow = torch.zeros_like(tracked)
    uv, xy = f.pts.clone(), f.un_pts.clone()
    if derivative_wanted(uv, xy):
        # empty slots hold stale values of lost features: same values, no gradient through them
        keep = f.valid.unsqueeze(-1)
        uv, xy = torch.where(keep, uv, uv.detach()), torch.where(keep, xy, xy.detach())
    return FeatureFrame(
        ids=f.ids.clone(), uv=uv, xy=xy,
        velocity=torch.where((tracked.unsqueeze(-1) & f.valid).unsqueeze(-1), velocity, torch.zeros_like(velocity)),
        track_count=f.track_cnt.clone(), valid=valid, present=present, published=decision.publish, sent=sent,
        restarted=decision.restarted, tracked=decision.tracked, timestamps=t, overflow=overflow, **extra)


def _publish_stages(table, img_eq, publish: Tensor, params: TrackerParams, stage, camera=None):
    """readImage's published-frame part (spec §3.6 step 7) for the ``publish`` streams:
    rejectWithF, setMask, addPoints. Returns ``(table, overflow)``. ``camera``: the streams' camera
    (default ``params.camera``; a sub-batch's own rows of a per-stream ``CameraBatch``)."""
    table, of_f = reject_with_f(table, publish, params.camera if camera is None else camera, params, stage=stage)
    table, of_det = _detect(table.replace(prev_pts=None), img_eq, publish, params, stage)
    return table, merge_overflow(of_f, of_det)


def _publish_lanes(table, img_eq, publish: Tensor, lanes: int, params: TrackerParams, stage):
    """:func:`_publish_stages` on a sub-batch of ``lanes`` streams that holds every publishing one.

    The lanes are the publishing streams first, then non-publishing ones as padding, each group in
    stream order (a stable sort of the device's own ``publish`` mask: no index upload, no sync;
    the host chose ``lanes`` only). A non-publishing lane comes out of the masked stages exactly as
    it went in (identity order, nothing appended), so writing every lane back is exact. Each
    stream's stages depend on no other stream (RANSAC seeds every problem alike, detection and
    setMask are per image), so the sub-batch gives the full batch's bits."""
    rows = torch.sort((~publish).to(torch.uint8), stable=True).indices[:lanes]
    # a per-stream camera batch (camera.CameraBatch) lifts the sub-batch with its rows' cameras
    sub_camera = params.camera.index_streams(rows) if hasattr(params.camera, "index_streams") else params.camera
    sub, of = _publish_stages(table.streams(rows), img_eq.index_select(0, rows), publish.index_select(0, rows),
                              params, stage, camera=sub_camera)
    full = table.replace(prev_pts=None, is_new=torch.zeros_like(table.valid))
    if of is not None:
        of = torch.zeros_like(publish).index_copy(0, rows, of)
    return full.with_streams(rows, sub), of


def _inline(name: str, fn: Callable, *args):
    """:func:`step_impl`'s default ``regions``: call the part itself."""
    return fn(*args)


def _mono_track(state, img, t, params, arrived, stage):
    """The mono step's first part: the clock, then CLAHE, pyramid and LK for the tracked streams.
    Returns ``(clock, decision, table, pyramid, equalised image, has_prediction, LK overflow)``."""
    clock, decision = mono_clock(state.clock, t, arrived, params)
    return (clock, decision) + _track(state, img, decision.tracked, params, stage)


def _mono_finish(state, table, t, pyr, clock, decision, has_prediction, of_lk, of_pub, numbered: bool,
                 every_tracked: bool, params, stage):
    """The mono step's last part: undistortion and velocities, updateID (``numbered``: some stream
    ran the publish stages), the published count, the new state and the frame."""
    tracked, publish = decision.tracked, decision.publish
    table, velocity = undistorted_points(table, params.camera, t - state.prev_time, params, stage=stage)
    if numbered:
        table, next_id = update_id(table, state.next_id)  # after undistortion, as VINS (spec §3.9, §3.10)
    else:
        next_id = state.next_id
    clock, sent = count_published(clock, publish)
    new = _commit(state, table, next_id, t, pyr, tracked, params.capturable, clock=clock,
                  has_prediction=has_prediction, every_tracked=every_tracked)
    f = new.features
    # VINS-Mono publishes features tracked at least once after detection (spec §3.11)
    valid = f.valid & (f.track_cnt > 1) & publish.unsqueeze(-1)
    return new, _frame(new, velocity, tracked, valid, f.valid.clone(), decision, sent, t,
                       merge_overflow(of_lk, of_pub))


def _mono(state, img, t, params, arrived, stage, plan: Optional[PublishPlan] = None,
          regions: Optional[Callable] = None):
    run = _inline
    if regions is not None:
        run = regions
        if state.prev_pyramid is None:
            # the first step: this image's pyramid as the previous one, so that the track part's
            # graph is every later step's (compiled once, not twice). The same values as _track's
            # own fallback (prev = this step's pyramid), so the step's results are the same
            first = _prime_next_pyramid(image_pyramid(equalize(img, params), params), params.lk_options,
                                       state.features.pts.dtype)
            state = dataclasses.replace(state, prev_pyramid=first)
    clock, decision, table, pyr, img_eq, has_prediction, of_lk = run("track", _mono_track, state, img, t, params,
                                                                     arrived, stage)
    publish = decision.publish
    lanes = table.batch if plan is None else min(plan.lanes, table.batch)
    if lanes == 0:  # nobody publishes: no rejectWithF, setMask, addPoints; updateID has nothing to number
        table, of_pub = table.replace(prev_pts=None), None
    elif lanes < table.batch:
        table, of_pub = run(f"publish_{lanes}", _publish_lanes, table, img_eq, publish, lanes, params, stage)
    else:
        table, of_pub = run("publish", _publish_stages, table, img_eq, publish, params, stage)
    every = plan is not None and plan.every_tracked
    return run(f"finish_{'numbered' if lanes else 'unnumbered'}{'_every' if every else ''}", _mono_finish, state,
               table, t, pyr, clock, decision, has_prediction, of_lk, of_pub, lanes > 0, every, params, stage)


def _fusion(state, img, t, right, params, arrived, stage):
    # VINS-Fusion: no clock rules, every image is tracked, published and detects (spec §6.2, §6.7)
    decision = ClockDecision(tracked=arrived, publish=arrived, restarted=torch.zeros_like(arrived))
    table, pyr, img_eq, has_prediction, of_lk = _track(state, img, arrived, params, stage)
    table, of_det = _detect(table, img_eq, arrived, params, stage)
    of_right = None
    table, next_id = update_id(table, state.next_id)  # ids at detection (spec §6.2 step 4)
    dt = t - state.prev_time
    table, velocity = undistorted_points(table, params.camera, dt, params, stage=stage)
    extra = dict(prev_uv=table.prev_pts, prev_valid=table.valid & (table.track_cnt >= 2) & arrived.unsqueeze(-1))
    if right is not None:
        table, view, of_right = track_right(table, pyr, right, arrived, params.camera1, dt, params, stage=stage)
        extra.update(right_uv=view.uv, right_xy=view.xy, right_velocity=view.velocity,
                     right_valid=view.valid & arrived.unsqueeze(-1))
    else:
        table = table.replace(right_un=torch.zeros_like(table.right_un), right_valid=torch.zeros_like(table.right_valid))
    new = _commit(state, table, next_id, t, pyr, arrived, params.capturable, has_prediction=has_prediction)
    valid = new.features.valid & arrived.unsqueeze(-1)
    return new, _frame(new, velocity, arrived, valid, valid.clone(), decision, arrived.clone(), t,
                       merge_overflow(of_lk, of_det, of_right), **extra)


__all__ = ["step", "step_impl", "check_inputs", "check_images", "check_timestamps", "check_active", "unit_hint"]
