"""The tracker's stages, named after VINS's (spec §3.6, §6.2), each a pure batched function.

Convention:
    Stages take and return a :class:`~torch_frontend.tracker.table.FeatureTable` (B streams, K
    slots, valid slots packed at the front in VINS order) plus per-stream ``(B,)`` bool masks that
    say which streams the stage applies to; a stream outside the mask comes out unchanged. Images
    are ``(B, 1, H, W)`` uint8 (validated once by the tracker's door), pixels ``(x, y)`` with pixel
    centres at integer coordinates, times float64 seconds. ``stage(name)`` is a context manager the
    caller may use to time or label the kernels (a no-op by default).

Order of a mono step (``readImage``): :func:`equalize` -> :func:`image_pyramid` ->
:func:`track_features` (LK, inBorder, compaction, ``track_cnt += 1``) -> on published frames
:func:`reject_with_f` -> :func:`set_mask` -> :func:`add_points` -> :func:`update_id` ->
:func:`undistorted_points`. Fusion: the same without CLAHE and rejectWithF, detection on every
frame, and :func:`track_right` for the stereo camera.
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple, Optional, Tuple

import torch

from .. import _tuning
from .._autodiff import derivative_wanted
from .._cache import cached
from .._checks import gather_slots
from .._compiler import constant_result
from ..corners import _good_features_impl
from ..equalize import _clahe_impl, _clahe_straight_through
from ..fused import lk_pad
from ..fused.layout import PyramidLayout
from ..lk import _forward_backward_impl, _track_lk_impl
from ..lk.fused_path import fused_applies
from ..lk.track import _level_cap
from ..masks import _distance_mask_impl
from ..pyramid import Pyramid, _build_pyramid_impl
from ..ransac import _find_fundamental_impl, _seeds, opencv_threshold_confidence
from .params import TrackerParams
from .table import FeatureTable, where_streams

Tensor = torch.Tensor


def no_stage(name: str):
    """The default ``stage`` hook: labels nothing."""
    return contextlib.nullcontext()


# ---------------------------------------------------------------------------------------------
# images


def merge_overflow(*flags: Optional[Tensor]) -> Optional[Tensor]:
    """``(B,)`` OR of the stages' overflow flags (None: a stage on the default path, which is exact)."""
    out = None
    for f in flags:
        if f is not None:
            out = f if out is None else out | f
    return out


def equalize(img: Tensor, params: TrackerParams) -> Tensor:
    """CLAHE (``createCLAHE(3.0, 8x8)``, spec §5.3) when the mode equalises, else the image.
    ``params.differentiable``: float32 in and out, the same values, the gradient of the LUT's local
    slope (straight-through, ``equalize._clahe_straight_through``)."""
    if not params.uses_clahe:
        return img
    gx, gy = params.clahe_tile_grid
    if params.differentiable:  # a float image with a graph: the 8-bit values and a slope
        out = _clahe_straight_through(img[:, 0], params.clahe_clip_limit, gx, gy, capturable=params.capturable,
                                      backend=params.clahe_backend)
    else:
        out = _clahe_impl(img[:, 0], params.clahe_clip_limit, gx, gy, capturable=params.capturable,
                          backend=params.clahe_backend).image
    return out.unsqueeze(1)


def image_pyramid(img: Tensor, params: TrackerParams) -> Pyramid:
    """The LK pyramid of an 8-bit image: levels rounded as OpenCV's 8-bit ``pyrDown`` (LK fidelity);
    no full-image derivatives (the LK takes them from the windows it reads). A float32 image of
    the differentiable step gives the same levels, its rounding straight-through."""
    return _build_pyramid_impl(img, params.lk_max_level, with_gradients=False, round_levels=True,
                               pad=lk_pad(params.lk_options.win_size), backend=params.lk_backend)


def front_group(img: Tensor, prev_pyr: Optional[Pyramid], pts: Tensor, params: TrackerParams) -> Optional[int]:
    """Streams per group of the fused front (:func:`front`), or None where the step runs CLAHE, the
    pyramid and the LK as three stage ops over the whole batch: the device's strategy groups
    (``_tuning.Strategy.front_group``: the CPU), the mode equalises (mono), the 8-bit path (not
    differentiable, uint8 images) with the fused CLAHE and LK, a previous packed pyramid of this
    frame's layout (the state; the first frame has none), and an LK call the fused op runs
    (``fused_applies``). The same bits either way."""
    group = _tuning.for_device(img.device).front_group
    if group is None or not params.uses_clahe or params.differentiable or img.dtype != torch.uint8:
        return None
    if params.clahe_backend != "fused" or params.lk_backend != "fused" or prev_pyr is None or prev_pyr.packed is None:
        return None
    H, W = img.shape[-2:]
    lay = PyramidLayout(int(H), int(W), params.lk_max_level, lk_pad(params.lk_options.win_size))
    if prev_pyr.layout != lay or not fused_applies(prev_pyr, prev_pyr, pts, None, params.lk_options):
        return None
    return group


def front(img: Tensor, prev_pyr: Pyramid, table: FeatureTable, run: Tensor, params: TrackerParams, group: int):
    """:func:`equalize`, :func:`image_pyramid` and the LK of :func:`track_features` (mono) as the one op
    ``torch_frontend::front`` (``fused/front_op.py``): ``group`` streams at a time, each stream's
    image and pyramid reused while in cache. Returns ``(equalised image (B, 1, H, W), pyramid,
    (next_pts, status, overflow))``, the three stages' values bit for bit (``overflow``: all False on
    the capturable path, else None)."""
    from ..fused.front_op import front_op

    opts = params.lk_options
    ww, wh = opts.win_size
    lay = prev_pyr.layout
    gx, gy = params.clahe_tile_grid
    top = _level_cap(prev_pyr, prev_pyr, opts.max_level, opts.win_size)
    pts = table.pts.detach()
    eq, packed, nxt, st, _ = front_op(img[:, 0], prev_pyr.packed, pts, table.valid & run.unsqueeze(-1),
                                      float(params.clahe_clip_limit), gx, gy, lay.max_level, lay.pad, top, ww, wh,
                                      opts.max_iters, opts.eps, opts.min_eig_threshold, group)
    pyr = Pyramid.from_packed(packed, lay.height, lay.width, lay.max_level, lay.pad)
    of = torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device) if params.capturable else None
    return eq.unsqueeze(1), pyr, (nxt.to(table.pts.dtype), st, of)


def select_pyramid(mask: Tensor, new: Pyramid, old: Optional[Pyramid], capturable: bool = False) -> Pyramid:
    """Per stream: ``new`` where ``mask``, else ``old``. The common case (every stream) keeps ``new``
    as it is, with its padded-level cache (one host sync to know). ``capturable``: always the
    per-stream select (no sync), the padded levels cached on both selected as well."""
    if old is None or (not capturable and bool(mask.all())):
        return new
    if new.packed is not None and old.packed is not None and new.layout == old.layout:  # one select
        lay = new.layout
        return Pyramid.from_packed(where_streams(mask, new.packed, old.packed), lay.height, lay.width, lay.max_level,
                                   lay.pad)
    out = Pyramid(levels=[where_streams(mask, n, o) for n, o in zip(new.levels, old.levels)], rounded=new.rounded)
    if capturable:
        # the LK pads the next image's levels once and reuses them when it is the previous image;
        # keep that reuse across the select (cached entries of both pyramids, same keys)
        out._padded = {k: where_streams(mask, v, old._padded[k]) for k, v in new._padded.items() if k in old._padded}
    return out


# ---------------------------------------------------------------------------------------------
# readImage: LK, inBorder, compaction


def in_border(pts: Tensor, width: int, height: int, border: int = 1) -> Tensor:
    """VINS ``inBorder``: ``cvRound`` (half to even, as ``torch.round``), then
    ``border <= x < W - border`` and ``border <= y < H - border``. NaN is outside."""
    r = torch.round(torch.nan_to_num(pts.detach(), nan=-1e9))
    x, y = r[..., 0], r[..., 1]
    return (x >= border) & (x < width - border) & (y >= border) & (y < height - border)


def _lk_stage(table: FeatureTable, prev_pyr: Pyramid, pyr: Pyramid, lk_valid: Tensor, has_prediction: Tensor,
              params: TrackerParams):
    """:func:`track_features`'s LK calls: ``(next_pts, status, overflow)``."""
    fusion = params.mode == "fusion"
    cap = params.capturable
    # capturable: the prediction branch runs whenever the mode can have predictions (no sync)
    if fusion and (cap or bool(has_prediction.any())):
        nxt_p, st_p, of_p = _track_lk_impl(prev_pyr, pyr, table.pts, lk_valid, table.prediction,
                                           params.lk_short_options, capturable=cap)
        nxt, st, of = _track_lk_impl(prev_pyr, pyr, table.pts, lk_valid, None, params.lk_options, capturable=cap)
        use = has_prediction & (st_p.sum(1) >= params.prediction_min_tracked)
        nxt, st = where_streams(use, nxt_p, nxt), where_streams(use, st_p, st)
        of = None if of is None else torch.where(use, of_p, of)
    else:
        nxt, st, of = _track_lk_impl(prev_pyr, pyr, table.pts, lk_valid, None, params.lk_options, capturable=cap)
    if fusion and params.flow_back:
        st, of_b = _forward_backward_impl(prev_pyr, pyr, table.pts, nxt, st, params.lk_options,
                                          params.fusion_short_max_level, params.flow_back_threshold, True,
                                          capturable=cap)
        of = merge_overflow(of, of_b)
    return nxt, st, of


def track_features(table: FeatureTable, prev_pyr: Pyramid, pyr: Pyramid, run: Tensor, tracked: Tensor,
                   has_prediction: Tensor, params: TrackerParams, *, stage=no_stage,
                   lk: Optional[Tuple[Tensor, Tensor, Optional[Tensor]]] = None) -> Tuple[FeatureTable, Optional[Tensor]]:
    """``readImage``'s tracking part (spec §3.6 step 5-6, §6.2 step 2-3) for the ``run`` streams.

    LK from the previous pyramid (fusion: from the prediction with one level where the stream has
    one, falling back to plain LK when fewer than ``prediction_min_tracked`` points track; and the
    FLOW_BACK check), the ``inBorder`` test on the image's own size, a stable compaction, then
    ``track_cnt += 1`` for every feature of the ``tracked`` streams. ``prev_pts`` holds the pixels
    before this step. Returns ``(table, overflow)`` (the LK budgets' flag; None on the default path).

    The LK is VINS's call (21x21, 30 iterations, eps 0.01, minEig 1e-4, spec §2;
    ``params.lk_options``), VINS-Fusion's one-level call from the prediction
    (``params.lk_short_options``), OpenCV's fixed point on the 8-bit pyramids; the FLOW_BACK check
    (spec §6.3) tracks back with one level from the result, starting at the points, and keeps those
    that come back within ``flow_back_threshold`` px (float differences, the norm in double, as VINS).
    ``lk``: the LK's ``(next_pts, status, overflow)`` computed already (mono: :func:`front`).
    """
    run_slots = run.unsqueeze(-1)
    H, W = pyr.levels[0].shape[-2:]
    if lk is not None:
        nxt, st, of = lk
    else:
        with stage("lk"):
            nxt, st, of = _lk_stage(table, prev_pyr, pyr, table.valid & run_slots, has_prediction, params)
    st = st & in_border(nxt, W, H, params.border_size)
    moved = table.replace(prev_pts=table.pts,
                          pts=torch.where(run_slots.unsqueeze(-1), nxt.to(table.pts.dtype), table.pts))
    table = moved.compact(torch.where(run_slots, table.valid & st, table.valid))
    cnt = table.track_cnt
    of = None if of is None else of & run
    return table.replace(track_cnt=torch.where(table.valid & tracked.unsqueeze(-1), cnt + 1, cnt)), of


# ---------------------------------------------------------------------------------------------
# rejectWithF


def lift_normalised(camera, pts: Tensor, valid: Tensor, backend: str = "tensor") -> Tensor:
    """``liftProjective`` then ``(x/z, y/z)`` (VINS ``undistortedPoints``), ``(B, K, 2)`` in
    ``pts``'s dtype; 0 in invalid slots.

    Lifted in float64 (camodocal uses double); invalid slots are lifted at a harmless point and
    ``|z| < 1e-12`` is clamped so that the division stays finite (``torch.where`` evaluates both
    branches: a NaN there would poison gradients). ``backend="fused"`` (``params.lift_backend``, resolved):
    a PINHOLE camera lifts with the one op ``torch_frontend::pinhole_lift`` (the same bits) unless a
    gradient is asked for; other models always with their ``_lift_impl``.
    """
    if backend == "fused":
        xy = _fused_lift(camera, pts, valid)
        if xy is not None:
            return xy
    safe = torch.where(valid.unsqueeze(-1), pts.to(torch.float64), torch.zeros_like(pts, dtype=torch.float64))
    P = camera._lift_impl(safe, **camera._params_like(safe))
    z = P[..., 2:3]
    z = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    xy = P[..., :2] / z
    return torch.where(valid.unsqueeze(-1), xy, torch.zeros_like(xy)).to(pts.dtype)


def _fused_lift(camera, pts: Tensor, valid: Tensor) -> Optional[Tensor]:
    """:func:`lift_normalised` by the fused PINHOLE op, or None where it does not apply (another
    model, a mixed camera batch, a gradient asked for: the op has no autograd formula)."""
    from ..fused.lift_op import pinhole_lift_op, pinhole_of, pinhole_params

    iters = pinhole_of(camera)
    if iters is None or pts.dim() != 3 or not pts.is_floating_point() or pts.dtype not in (torch.float32,
                                                                                          torch.float64):
        return None
    params = pinhole_params(camera, pts)
    if derivative_wanted(pts, params):
        return None
    return pinhole_lift_op(pts, valid, params, iters)


@cached(32)
def _pinhole_centre(width: int, height: int, device) -> Tensor:
    """The virtual pinhole's principal point ``(COL / 2, ROW / 2)`` (2,) float64, built once per device
    (a per-call ``torch.tensor`` would be a blocking host-to-device copy on CUDA)."""
    return torch.tensor([width / 2.0, height / 2.0], dtype=torch.float64, device=device)


def virtual_pinhole(camera, pts: Tensor, valid: Tensor, params: TrackerParams) -> Tensor:
    """rejectWithF's points: lifted, on the 460-px virtual pinhole with principal point
    ``(COL / 2, ROW / 2)`` (spec §3.8), float64 pixels."""
    xy = lift_normalised(camera, pts, valid, params.lift_backend).to(torch.float64)
    return params.focal_length * xy + _pinhole_centre(params.width, params.height, pts.device)


def reject_with_f(table: FeatureTable, publish: Tensor, camera, params: TrackerParams, *,
                  stage=no_stage) -> Tuple[FeatureTable, Optional[Tensor]]:
    """``rejectWithF`` (spec §3.8) on the ``publish`` streams: F-RANSAC between ``prev_pts`` and
    ``pts`` on the virtual pinhole, then a compaction by the inlier mask. Returns ``(table,
    overflow)`` (RANSAC's hypothesis block too small; None on the default path).

    The RANSAC kernel applies VINS's rule itself: below 8 points (or when no model is found) it
    reports ``ok = False`` and the stream keeps every feature. ``capturable``: RANSAC runs for every
    stream (the others masked out), with no host sync to skip it. ``params.F_method``: ``"opencv"``
    (VINS, exact) or ``"lo"`` (LO-RANSAC: the same samples and test, locally optimised models).
    """
    if not params.capturable and not bool(publish.any()):  # host sync: nobody publishes (every other frame)
        return table, None
    # RANSAC's result is a mask: no graph through the lift and the solver (the compaction below
    # keeps the features' gradients)
    if params.differentiable:  # no_grad does not stop forward AD: the points are detached as well
        with torch.no_grad():
            res = _ransac(table.replace(pts=table.pts.detach(), prev_pts=table.prev_pts.detach()), publish, camera,
                          params, stage)
    else:
        res = _ransac(table, publish, camera, params, stage)
    apply = (publish & res.ok).unsqueeze(-1)
    table = table.compact(torch.where(apply, table.valid & res.inliers, table.valid))
    return table, (None if res.overflow is None else res.overflow & publish)


def _ransac(table: FeatureTable, publish: Tensor, camera, params: TrackerParams, stage):
    """rejectWithF's F-RANSAC on the ``publish`` streams (a ``ransac.FundamentalFit``)."""
    fv = table.valid & publish.unsqueeze(-1)
    # both point sets lifted in one call (one set of kernels)
    p12 = virtual_pinhole(camera, torch.cat((table.prev_pts, table.pts), 1), torch.cat((fv, fv), 1), params)
    p1, p2 = p12.split(table.capacity, 1)
    # one fixed seed per call, as OpenCV re-seeds its RNG identically on every call: a stream's
    # result then depends neither on the other streams nor on the call history
    threshold, confidence = opencv_threshold_confidence(params.F_threshold, params.ransac_confidence)
    with stage("ransac"):
        args = (p1, p2, fv, threshold, confidence, params.ransac_max_iters, _ransac_states(table.batch, params.seed),
                None)
        return _find_fundamental_impl(*args, capturable=params.capturable, method=params.F_method)


@constant_result
def _ransac_states(batch: int, seed: int) -> tuple:
    """The ``cv::RNG`` state of every stream's problem (the same seed for all), computed once (a
    constant for ``torch.compile``: dynamo bakes the tuple in instead of tracing the seeding)."""
    return _ransac_states_cached(batch, seed)


@cached(16)
def _ransac_states_cached(batch: int, seed: int) -> tuple:
    return tuple(_seeds(batch, seed=seed))


# ---------------------------------------------------------------------------------------------
# setMask, addPoints


class Detection(NamedTuple):
    """The streams setMask ran on and their masks: ``rows`` in stream order, ``mask (len(rows), H,
    W)`` uint8 (None when no stream detects). Default path: ``rows`` are exactly the detecting
    streams and ``detect`` is None. Capturable: ``rows`` is every stream (no host sync picks them)
    and ``detect (B,)`` says which ones detect."""

    rows: Tensor
    mask: Optional[Tensor]
    detect: Optional[Tensor] = None


@cached(32)
def _stream_rows(batch: int, device) -> Tensor:
    """``arange(B)`` on ``device``, built once (the capturable path's "every stream")."""
    return torch.arange(batch, device=device)


def _rows_of(table: FeatureTable, rows: Tensor, x: Tensor) -> Tensor:
    """The ``rows`` streams of ``x (B, ...)`` (``x`` itself when they are every stream)."""
    return x if rows.numel() == table.batch else x.index_select(0, rows)


def _to_streams(detection: Detection, x: Tensor, other: Tensor) -> Tensor:
    """``(B, ...)``: the detecting streams' rows of ``x`` (one per ``detection.rows``), ``other``'s
    elsewhere (neither is written into)."""
    if detection.detect is not None:  # capturable: every stream ran, the mask picks
        return where_streams(detection.detect, x, other)
    if detection.rows.numel() == other.shape[0]:
        return x
    return other.index_copy(0, detection.rows, x)


def set_mask(table: FeatureTable, detect: Tensor, params: TrackerParams, base_mask: Optional[Tensor],
             height: int, width: int, *, stage=no_stage) -> Tuple[FeatureTable, Detection, Optional[Tensor]]:
    """VINS ``setMask`` (spec §3.7) for the ``detect`` streams: features sorted by track count
    (descending; ties by slot order: a stable sort, where VINS's ``std::sort`` is unstable, see the
    spec), each kept iff its rounded pixel is still 255 in the mask, which then gets a filled disc of
    radius ``min_dist``; dropped features leave the table. Streams outside ``detect`` come out
    unchanged (identity order, keep = valid: the table is already packed).

    The path only changes which streams run. Default: only the detecting streams pay for the mask
    (mono: the published ones, about one frame in two at 20 Hz with freq 10), one host sync picks
    them. ``capturable``: every stream runs (no sync). The third value is the overflow flag of the
    capturable path's fixed rounds (None on the default path).
    """
    B, K = table.valid.shape
    dev = table.valid.device
    if params.capturable:
        detection = Detection(_stream_rows(B, dev), None, detect)
    else:
        detection = Detection(detect.nonzero().flatten(), None)
        if detection.rows.numel() == 0:
            return table, detection, None
    rows = detection.rows
    valid, cnt = _rows_of(table, rows, table.valid), _rows_of(table, rows, table.track_cnt)
    order = _setmask_order(valid, cnt)
    pts_s = gather_slots(_rows_of(table, rows, _mask_points(table)), order)
    cnt_s, valid_s = torch.gather(cnt, 1, order), torch.gather(valid, 1, order)
    n = rows.numel()
    fused = params.lk_backend == "fused"  # the fused kernels run here: setMask's op too (same bits)
    if fused:  # the op only reads its base mask: one for every stream, no copy
        mask = _full_mask(height, width, dev) if base_mask is None else base_mask.reshape(1, height, width)
    elif base_mask is None:
        mask = torch.full((n, height, width), 255, dtype=torch.uint8, device=dev)
    else:
        mask = base_mask.expand(n, height, width).clone()  # written into: one copy per stream
    with stage("mask"):
        res = _distance_mask_impl(pts_s, cnt_s, valid_s, float(params.min_dist), mask, capturable=params.capturable,
                                  backend="fused" if fused else "tensor")
    order = _to_streams(detection, order, _slot_rows(B, K, dev))
    keep = _to_streams(detection, valid_s & res.keep, table.valid)
    # the fused op is exact (no budget): its overflow is all False, left out
    overflow = None if res.overflow is None or fused else res.overflow & detect
    return table.permute(order).compact(keep), Detection(rows, res.mask, detection.detect), overflow


def _mask_points(table: FeatureTable) -> Tensor:
    """The pixels setMask rounds into its mask: a discrete choice, so without a graph (the table's
    permutation keeps the features' gradients)."""
    return table.pts.detach() if derivative_wanted(table.pts) else table.pts


def _setmask_order(valid: Tensor, track_cnt: Tensor) -> Tensor:
    """setMask's visiting order ``(n, K)`` of ``valid`` / ``track_cnt`` ``(n, K)``: track count
    descending, ties by slot (stable), empty slots last."""
    key = torch.where(valid, track_cnt, torch.full_like(track_cnt, -1))
    return torch.sort(-key, dim=1, stable=True).indices


@cached(8)
def _full_mask(height: int, width: int, device) -> Tensor:
    """``(1, H, W)`` uint8 of 255 on ``device``, built once: the fused setMask's base mask without a
    fisheye mask (read only)."""
    return torch.full((1, height, width), 255, dtype=torch.uint8, device=device)


@cached(32)
def _slot_rows(batch: int, capacity: int, device) -> Tensor:
    """``(B, K)`` identity slot order, built once."""
    return torch.arange(capacity, device=device).expand(batch, capacity)


def add_points(table: FeatureTable, img: Tensor, detection: Detection, params: TrackerParams, *,
               stage=no_stage) -> Tuple[FeatureTable, Optional[Tensor]]:
    """``goodFeaturesToTrack`` into the free slots (spec §3.6 step 7c-d, §5.2): ``max_cnt - n``
    corners (quality 0.01, ``min_dist``, setMask's mask) per detecting stream, appended in
    response order with ``ids = -1``, ``track_cnt = 1`` (``is_new``). Returns ``(table, overflow)``
    (the fixed candidate block / rounds too small; None on the default path). The streams are
    setMask's ``detection.rows``; capturable: every stream with ``K = max_cnt`` outputs (no host
    sync for the count), the non-detecting ones masked out."""
    rows = detection.rows
    if rows.numel() == 0:  # default path, no stream detects
        return table.append(table.pts[:, :0], table.valid[:, :0]), None
    if derivative_wanted(img):  # corners are a discrete choice: detected pixels carry no gradient
        img = img.detach()
    n_max = table.capacity - _rows_of(table, rows, table.valid).sum(1)
    with stage("detection"):
        res = _good_features_impl(_rows_of(table, rows, img), n_max, params.gftt_quality_level, float(params.min_dist),
                                  detection.mask != 0, False, params.gftt_block_size, params.gftt_harris_k,
                                  table.capacity if params.capturable else None, capturable=params.capturable,
                                  backend=params.corner_backend)
    if detection.detect is not None:  # capturable: every stream ran
        return table.append(res.pts, res.valid & detection.detect.unsqueeze(-1)), res.overflow & detection.detect
    pts, valid = res.pts, res.valid
    if rows.numel() != table.batch:  # the other streams add nothing (fresh zeros: filled in place)
        pts = pts.new_zeros(table.batch, pts.shape[1], 2).index_copy_(0, rows, pts)
        valid = valid.new_zeros(table.batch, valid.shape[1]).index_copy_(0, rows, valid)
    return table.append(pts, valid), None


# ---------------------------------------------------------------------------------------------
# updateID, undistortedPoints


def update_id(table: FeatureTable, next_id: Tensor) -> Tuple[FeatureTable, Tensor]:
    """VINS ``updateID`` (spec §3.9): new features get ``next_id, next_id + 1, ...`` in slot order;
    returns the table and the streams' next ids. Ids are per stream."""
    new = table.is_new
    ids = torch.where(new, next_id.unsqueeze(-1) + torch.cumsum(new.to(torch.int64), dim=1) - 1, table.ids)
    return table.replace(ids=ids), next_id + new.sum(1)


def _velocity(un: Tensor, un_prev: Tensor, moving: Tensor, dt: Tensor) -> Tensor:
    """``(un - un_prev) / dt`` where ``moving (B, K)``, else 0. ``dt (B,)`` seconds; a duplicate
    stamp (``dt == 0``) gives zero velocity where VINS divides by zero (inf/NaN). The safe divisor
    keeps the unused lanes finite. As VINS's ``ptsVelocity``: the difference of the points' own dtype
    (``cv::Point2f``) divided by the double ``dt``, rounded once to the points' dtype (a float32 ``dt``
    rounds twice: 1 ulp off where ``dt`` is not a float32, e.g. 0.1 s; tests/test_lockstep.py)."""
    dt = dt.to(torch.float64).view(-1, 1, 1)
    moving = moving.unsqueeze(-1) & (dt != 0)
    v = ((un - un_prev).to(torch.float64) / torch.where(dt == 0, torch.ones_like(dt), dt)).to(un.dtype)
    return torch.where(moving, v, torch.zeros_like(un))


def undistorted_points(table: FeatureTable, camera, dt: Tensor, params: TrackerParams, *,
                       stage=no_stage) -> Tuple[FeatureTable, Tensor]:
    """VINS ``undistortedPoints`` (spec §3.10, §6.2 step 5): lift every feature to normalised
    coordinates (``un_pts``) and its velocity against the previous frame's point of the same slot,
    ``dt`` = time since the stream's previous processed frame. A feature has a velocity from its
    ``velocity_min_count``-th observation on (mono 3: ids are assigned after undistortion; fusion 2).
    Returns ``(table, velocity (B, K, 2))``."""
    with stage("undistort"):
        un = lift_normalised(camera, table.pts, table.valid, params.lift_backend)
    moving = table.valid & (table.track_cnt >= params.velocity_min_count)
    return table.replace(un_pts=un), _velocity(un, table.un_pts, moving, dt)


class RightView(NamedTuple):
    """Camera 1's observations of the left features (VINS-Fusion stereo), each ``(B, K, ...)``."""

    uv: Tensor
    xy: Tensor
    velocity: Tensor
    valid: Tensor


def track_right(table: FeatureTable, pyr: Pyramid, right: Tensor, tracked: Tensor, camera1, dt: Tensor,
                params: TrackerParams, *, stage=no_stage) -> Tuple[FeatureTable, RightView, Optional[Tensor]]:
    """VINS-Fusion's stereo step (spec §6.2 step 6): LK from the left image to ``right`` (3 levels,
    no guess), with FLOW_BACK the backward check (3 levels, from the right result) and the right
    ``inBorder``; camera-1 undistortion and a right velocity where the slot also had a right
    observation in the previous frame. The left features are not reduced. The third value is the
    LK budgets' overflow flag (None on the default path)."""
    valid = table.valid & tracked.unsqueeze(-1)
    with stage("pyramid"):
        rpyr = image_pyramid(right, params)
    with stage("lk"):
        ruv, rst, of = _track_lk_impl(pyr, rpyr, table.pts, valid, None, params.lk_stereo_options,
                                      capturable=params.capturable)
        if params.flow_back:  # the backward check from the right result, no guess (spec §6.3)
            rst, of_b = _forward_backward_impl(pyr, rpyr, table.pts, ruv, rst, params.lk_stereo_options,
                                               params.lk_max_level, params.flow_back_threshold, False,
                                               capturable=params.capturable)
            of = merge_overflow(of, of_b)
    if params.flow_back:
        rst = rst & in_border(ruv, right.shape[-1], right.shape[-2], params.border_size)
    rvalid = valid & rst
    uv = torch.where(rvalid.unsqueeze(-1), ruv.to(table.pts.dtype), torch.zeros_like(table.pts))
    with stage("undistort"):
        xy = lift_normalised(camera1, uv, rvalid, params.lift_backend)
    vel = _velocity(xy, table.right_un, rvalid & table.right_valid, dt)
    of = None if of is None else of & tracked
    return table.replace(right_un=xy, right_valid=rvalid), RightView(uv, xy, vel, rvalid), of




# ---------------------------------------------------------------------------------------------
# the estimator's hooks (VINS-Fusion)


def remove_features(table: FeatureTable, drop: Tensor) -> FeatureTable:
    """VINS-Fusion ``removeOutliers`` (spec §6.5): drop the slots where ``drop (B, K)`` is True;
    the rest is compacted (every column, so a prediction stays with its feature)."""
    return table.compact(table.valid & ~drop).committed()


def set_prediction(table: FeatureTable, ids: Tensor, uv: Tensor, valid: Tensor) -> Tuple[FeatureTable, Tensor]:
    """VINS-Fusion ``setPrediction`` (spec §6.4): the predicted pixel of each feature by id (the first
    valid entry with its id), else its current pixel. ``ids (B, M)`` int64, ``uv (B, M, 2)`` pixels,
    ``valid (B, M)`` bool. Returns the table and ``has_prediction (B,)``: a stream with at least one
    predicted feature tracks from the predictions in its next step."""
    match = (table.ids.unsqueeze(-1) == ids.unsqueeze(1)) & valid.unsqueeze(1) & table.valid.unsqueeze(-1)  # (B, K, M)
    has = match.any(-1)
    first = match.to(torch.int8).argmax(-1)
    pred = torch.gather(uv.to(table.pts.dtype), 1, first.unsqueeze(-1).expand(-1, -1, 2))
    return table.replace(prediction=torch.where(has.unsqueeze(-1), pred, table.pts)), has.any(-1)


__all__ = [
    "merge_overflow", "equalize", "image_pyramid", "select_pyramid", "track_features", "in_border", "lift_normalised",
    "virtual_pinhole", "reject_with_f", "set_mask", "add_points", "update_id", "undistorted_points",
    "track_right", "remove_features", "set_prediction", "Detection", "RightView", "no_stage", "where_streams",
]
