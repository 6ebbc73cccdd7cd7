"""``FeatureTracker``: the VINS-Mono front end (and VINS-Fusion's tracker) for B streams at once.

Convention:
    Each of the B streams has its own clock, feature table and id counter. A feature table is a
    fixed-capacity set of ``max_cnt`` slots: ``pts (B, K, 2)`` pixels (x, y), ``ids (B, K)`` int64
    (-1 in empty slots), ``track_cnt (B, K)``, ``valid (B, K)``. Valid slots are always packed at
    the front in VINS's array order (stable compaction), so array order is VINS's vector order and
    decides, as in VINS, which features survive ``setMask`` and which ids new features get.

    Ids are per stream: stream b numbers its features 0, 1, 2, ... (VINS uses one counter per
    process, which is the same thing for one camera). 64-bit.

    The per-frame branches of VINS (first frame skipped, restart, publish or not, detection or not)
    differ per stream by masks; every stream runs through the same tensor code each call.

Steps per call (mode ``"mono"``, spec §3.2 and §3.6): clock rules → CLAHE (``equalize``) →
pyramid → LK from the previous frame → border test → compaction → ``track_cnt += 1`` → on
published frames: F-RANSAC on the 460-px virtual pinhole, setMask, good features for free slots →
ids → undistortion and velocities.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ._checks import as_image_batch, check_shape, gather_slots, valid_first_order
from .config import TrackerConfig, load_config

FOCAL_LENGTH = 460.0  # VINS's virtual pinhole for F-RANSAC (spec §2)
WINDOW_SIZE = 20  # track-count colour saturation (debug image)


@dataclasses.dataclass
class FeatureFrame:
    """One processed time step of all B streams.

    Attributes:
        ids: (B, K) int64, -1 in empty slots.
        uv: (B, K, 2) float, distorted pixels (x, y).
        xy: (B, K, 2) float, normalised undistorted coordinates (x/z, y/z).
        velocity: (B, K, 2) float, normalised units per second (VINS's rule per mode).
        track_count: (B, K) int64.
        valid: (B, K) bool, the features VINS would publish (mono: ``track_cnt > 1`` on published
            frames; fusion: every tracked feature).
        present: (B, K) bool, every feature in the tracker's table after this step (including
            just-detected ones, which the debug image draws).
        published: (B,) bool, this step built a feature message (mono: PUB_THIS_FRAME; the very
            first one is not sent, see ``sent``).
        sent: (B,) bool, the message would be sent to the estimator (mono: not on the first
            published frame).
        restarted: (B,) bool, a restart was signalled (gap > 1 s or time went backwards).
        tracked: (B,) bool, the image was processed (mono skips first images and restarts).
        timestamps: (B,) float64 seconds.
        right_uv, right_xy, right_velocity, right_valid: stereo (fusion) observations of the same
            slots in camera 1, or None.
    """

    ids: torch.Tensor
    uv: torch.Tensor
    xy: torch.Tensor
    velocity: torch.Tensor
    track_count: torch.Tensor
    valid: torch.Tensor
    present: torch.Tensor
    published: torch.Tensor
    sent: torch.Tensor
    restarted: torch.Tensor
    tracked: torch.Tensor
    timestamps: torch.Tensor
    prev_uv: Optional[torch.Tensor] = None
    prev_valid: Optional[torch.Tensor] = None
    right_uv: Optional[torch.Tensor] = None
    right_xy: Optional[torch.Tensor] = None
    right_velocity: Optional[torch.Tensor] = None
    right_valid: Optional[torch.Tensor] = None

    @property
    def batch_size(self) -> int:
        return int(self.ids.shape[0])

    def _rows(self, b: int, mask: torch.Tensor):
        sel = mask[b].nonzero().flatten()
        return sel

    def to_point_cloud(self, b: int = 0) -> Dict[str, np.ndarray]:
        """Stream ``b`` in the VINS-Mono ``sensor_msgs/PointCloud`` layout.

        Returns a dict with ``points`` (M, 3) float32 rows (x, y, 1), and the five channels as
        float32 arrays in VINS order: ``id``, ``u``, ``v``, ``vx``, ``vy`` (the id is float32 as
        in VINS: exact up to 2**24). Also ``stamp`` (seconds).
        """
        sel = self._rows(b, self.valid)
        xy = self.xy[b, sel].detach().cpu().double().numpy()
        uv = self.uv[b, sel].detach().cpu().double().numpy()
        vel = self.velocity[b, sel].detach().cpu().double().numpy()
        ids = self.ids[b, sel].cpu().numpy()
        pts = np.concatenate([xy, np.ones((len(sel), 1))], axis=1).astype(np.float32)
        return {
            "stamp": float(self.timestamps[b]),
            "points": pts,
            "id": ids.astype(np.float32),
            "u": uv[:, 0].astype(np.float32),
            "v": uv[:, 1].astype(np.float32),
            "vx": vel[:, 0].astype(np.float32),
            "vy": vel[:, 1].astype(np.float32),
        }

    def to_vins_fusion(self, b: int = 0) -> Dict[int, List[Tuple[int, np.ndarray]]]:
        """Stream ``b`` as VINS-Fusion's ``{id: [(camera_id, [x, y, z, u, v, vx, vy])]}`` (ordered by id;
        camera 0 first, camera 1 second where a right observation exists)."""
        out: Dict[int, List[Tuple[int, np.ndarray]]] = {}
        sel = self._rows(b, self.valid)
        ids = self.ids[b, sel].cpu().numpy()
        xy = self.xy[b, sel].detach().cpu().double().numpy()
        uv = self.uv[b, sel].detach().cpu().double().numpy()
        vel = self.velocity[b, sel].detach().cpu().double().numpy()
        right = None
        if self.right_valid is not None:
            rv = self.right_valid[b, sel].cpu().numpy()
            rxy = self.right_xy[b, sel].detach().cpu().double().numpy()
            ruv = self.right_uv[b, sel].detach().cpu().double().numpy()
            rvel = self.right_velocity[b, sel].detach().cpu().double().numpy()
            right = (rv, rxy, ruv, rvel)
        order = np.argsort(ids, kind="stable")
        for j in order:
            obs = [(0, np.array([xy[j, 0], xy[j, 1], 1.0, uv[j, 0], uv[j, 1], vel[j, 0], vel[j, 1]]))]
            if right is not None and right[0][j]:
                rxy, ruv, rvel = right[1][j], right[2][j], right[3][j]
                obs.append((1, np.array([rxy[0], rxy[1], 1.0, ruv[0], ruv[1], rvel[0], rvel[1]])))
            out[int(ids[j])] = obs
        return out


# ----------------------------------------------------------------------------------------------
# small batched helpers


def _compact(valid: torch.Tensor, *tensors: torch.Tensor):
    """Stable compaction: move valid slots to the front, keeping their order (VINS ``reduceVector``).

    valid: (B, K) bool; tensors: (B, K, ...). Returns (valid, *tensors) permuted.
    """
    order = valid_first_order(valid)
    return (gather_slots(valid, order),) + tuple(gather_slots(t, order) for t in tensors)



def _in_border(pts: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """VINS ``inBorder``: cvRound (half to even, as torch.round) then 1 <= x < W-1, 1 <= y < H-1."""
    r = torch.round(torch.nan_to_num(pts.detach(), nan=-1e9))
    x, y = r[..., 0], r[..., 1]
    return (x >= 1) & (x < width - 1) & (y >= 1) & (y < height - 1)


def _where_stream(active: torch.Tensor, new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
    """Per-stream select: ``active (B,)`` broadcast over the trailing dims."""
    a = active.reshape(active.shape + (1,) * (new.dim() - 1))
    return torch.where(a, new, old)


def _c_round(x: torch.Tensor) -> torch.Tensor:
    """C ``round``: half away from zero (VINS's publish-rate rule), not Python's banker's rounding."""
    return torch.sign(x) * torch.floor(x.abs() + 0.5)


class _StageTimer:
    """Optional per-stage wall-clock accounting (``FeatureTracker.stage_times``), for benchmarks.

    A no-op unless enabled; when enabled it synchronises CUDA at stage boundaries so that the times
    are real (which costs a little throughput).
    """

    def __init__(self):
        self.times: Optional[Dict[str, float]] = None
        self._name = None

    def __call__(self, name: str):
        self._name = name
        return self

    def __enter__(self):
        if self.times is not None:
            import time

            if torch.cuda.is_available():
                torch.cuda.synchronize()
            self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        if self.times is not None:
            import time

            if torch.cuda.is_available():
                torch.cuda.synchronize()
            self.times[self._name] = self.times.get(self._name, 0.0) + time.perf_counter() - self._t0
        return False


@dataclasses.dataclass
class TrackerState:
    """Everything the tracker carries between calls (one small dataclass of tensors)."""

    pts: torch.Tensor  # (B, K, 2) current pixels
    ids: torch.Tensor  # (B, K) int64
    track_cnt: torch.Tensor  # (B, K) int64
    valid: torch.Tensor  # (B, K) bool
    un_pts: torch.Tensor  # (B, K, 2) normalised undistorted points of the last processed frame
    has_image: torch.Tensor  # (B,) bool: a previous (processed) image exists
    first_image_flag: torch.Tensor  # (B,) bool
    first_image_time: torch.Tensor  # (B,) float64
    last_image_time: torch.Tensor  # (B,) float64
    prev_time: torch.Tensor  # (B,) float64
    pub_count: torch.Tensor  # (B,) int64
    init_pub: torch.Tensor  # (B,) bool
    next_id: torch.Tensor  # (B,) int64
    prev_pyramid: Optional[object] = None
    prev_right_un: Optional[torch.Tensor] = None  # (B, K, 2)
    prev_right_valid: Optional[torch.Tensor] = None  # (B, K) bool
    prediction: Optional[torch.Tensor] = None  # (B, K, 2)
    has_prediction: Optional[torch.Tensor] = None  # (B,) bool: set_prediction was called for the stream


class FeatureTracker:
    """The VINS front end for ``num_streams`` streams tracked together.

    Args:
        config: a ``TrackerConfig`` or the path of a VINS config YAML.
        num_streams: B, the number of streams (cameras or sequences) tracked in each call.
        device: where the state and the work live.
        mode: ``"mono"`` (VINS-Mono ``feature_tracker`` node) or ``"fusion"`` (VINS-Fusion tracker).
        dtype: float dtype of points and images inside the tracker (float32 default).
        fisheye_mask: optional ``(H, W)`` uint8 mask for ``fisheye: 1`` configs; default: the
            analytic disc of ``torch_frontend.fisheye_mask``.
        seed: F-RANSAC seed, used for every problem of every call (OpenCV re-seeds identically on
            each call), so a stream's result does not depend on the other streams.

    ``track(images, timestamps)`` takes ``images (B, 1, H, W)`` (uint8 or float 0..255; ``(B, H, W)``
    accepted) with ``H, W`` = the config's ``image_height``, ``image_width``, and ``timestamps`` a
    ``(B,)`` float64 tensor or sequence of seconds, and returns a ``FeatureFrame``.
    """

    def __init__(
        self,
        config: Union[TrackerConfig, str],
        num_streams: int = 1,
        device: Union[str, torch.device] = "cpu",
        mode: str = "mono",
        dtype: torch.dtype = torch.float32,
        fisheye_mask: Optional[torch.Tensor] = None,
        seed: int = 0,
    ):
        if not isinstance(config, TrackerConfig):
            config = load_config(config)
        if mode not in ("mono", "fusion"):
            raise ValueError(f"mode: expected 'mono' or 'fusion', got {mode!r}")
        if config.camera is None:
            raise ValueError(f"config {config.path}: has no camera; the tracker needs one")
        if config.max_cnt <= 0 or config.min_dist < 0:
            raise ValueError(
                f"config {config.path}: max_cnt must be > 0 and min_dist >= 0 for tracking, "
                f"got max_cnt={config.max_cnt}, min_dist={config.min_dist}"
            )
        if num_streams < 1:
            raise ValueError(f"num_streams: expected >= 1, got {num_streams}")
        self.config = config
        self.mode = mode
        self.B = int(num_streams)
        self.K = int(config.max_cnt)
        self.device = torch.device(device)
        self.dtype = dtype
        self.width = int(config.image_width)
        self.height = int(config.image_height)
        self.camera = config.camera.to(device=self.device, dtype=torch.float64)
        self.camera1 = None if config.camera1 is None else config.camera1.to(device=self.device, dtype=torch.float64)
        self.seed = int(seed)
        self.lk_kwargs = dict(win_size=21, max_level=3, max_iters=30, eps=0.01, min_eig_threshold=1e-4)
        self.base_mask = self._make_base_mask(fisheye_mask)
        self._stage = _StageTimer()
        self.reset()

    def compile(self, enable: bool = True) -> None:
        """Use ``torch.compile`` for the LK iteration kernel (the hot loop), with eager as the
        fallback (``enable=False``). Compilation happens on the first call (seconds to minutes)."""
        from .lk import compile_step

        compile_step(enable)

    @property
    def stage_times(self) -> Optional[Dict[str, float]]:
        """Seconds spent per stage since ``enable_stage_times()`` (None when disabled)."""
        return self._stage.times

    def enable_stage_times(self, enabled: bool = True) -> None:
        """Start (or stop) accumulating per-stage wall-clock times (CLAHE, pyramid, LK, RANSAC,
        mask, detection, undistort) into ``stage_times``."""
        self._stage.times = {} if enabled else None

    # ------------------------------------------------------------------ set-up

    def _make_base_mask(self, fisheye_mask: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
        if self.mode != "mono" or not self.config.fisheye:
            return None
        if fisheye_mask is None:
            from .masks import fisheye_mask as make_mask

            fisheye_mask = make_mask(self.height, self.width)
        fisheye_mask = torch.as_tensor(fisheye_mask)
        check_shape(fisheye_mask, (self.height, self.width), "fisheye_mask")
        return fisheye_mask.to(self.device, torch.uint8)

    def reset(self) -> None:
        """Forget everything: all streams start again as at construction."""
        B, K, dev = self.B, self.K, self.device
        f64 = torch.float64
        self.state = TrackerState(
            pts=torch.zeros(B, K, 2, device=dev, dtype=self.dtype),
            ids=torch.full((B, K), -1, device=dev, dtype=torch.int64),
            track_cnt=torch.zeros(B, K, device=dev, dtype=torch.int64),
            valid=torch.zeros(B, K, device=dev, dtype=torch.bool),
            un_pts=torch.zeros(B, K, 2, device=dev, dtype=self.dtype),
            has_image=torch.zeros(B, device=dev, dtype=torch.bool),
            first_image_flag=torch.ones(B, device=dev, dtype=torch.bool),
            first_image_time=torch.zeros(B, device=dev, dtype=f64),
            last_image_time=torch.zeros(B, device=dev, dtype=f64),
            prev_time=torch.zeros(B, device=dev, dtype=f64),
            pub_count=torch.ones(B, device=dev, dtype=torch.int64),
            init_pub=torch.zeros(B, device=dev, dtype=torch.bool),
            next_id=torch.zeros(B, device=dev, dtype=torch.int64),
            prev_right_un=torch.zeros(B, K, 2, device=dev, dtype=self.dtype),
            prev_right_valid=torch.zeros(B, K, device=dev, dtype=torch.bool),
            prediction=torch.zeros(B, K, 2, device=dev, dtype=self.dtype),
            has_prediction=torch.zeros(B, device=dev, dtype=torch.bool),
        )

    # ------------------------------------------------------------------ helpers

    def _images(self, images, name: str) -> torch.Tensor:
        img = as_image_batch(torch.as_tensor(images), name)
        if img.shape[0] != self.B:
            raise ValueError(f"{name}: expected {self.B} streams (B, 1, H, W), got {tuple(img.shape)}")
        if self.mode == "mono" and (img.shape[-2], img.shape[-1]) != (self.height, self.width):
            raise ValueError(
                f"{name}: image size {img.shape[-1]}x{img.shape[-2]} differs from the config's "
                f"image_width x image_height = {self.width}x{self.height} ({self.config.path})"
            )
        img = img.to(self.device)
        if img.dtype != torch.uint8:
            # VINS works on 8-bit images; float input is rounded and clamped the way cv_bridge would.
            img = img.round().clamp(0, 255).to(torch.uint8)
        return img

    def _timestamps(self, timestamps) -> torch.Tensor:
        t = torch.as_tensor(timestamps, dtype=torch.float64)
        if t.dim() == 0:
            t = t.expand(self.B)
        check_shape(t, (self.B,), "timestamps")
        if not torch.isfinite(t).all():
            raise ValueError("timestamps: expected finite seconds, got a NaN or infinity")
        return t.to(self.device)

    def _undistort(self, cam, pts: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        # Lift in float64 (camodocal uses double); empty slots get a harmless point so that the
        # division by z stays finite.
        safe = torch.where(valid.unsqueeze(-1), pts.to(torch.float64), torch.zeros_like(pts, dtype=torch.float64))
        P = cam.lift(safe)
        z = P[..., 2:3]
        z = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
        xy = P[..., :2] / z
        return torch.where(valid.unsqueeze(-1), xy, torch.zeros_like(xy)).to(self.dtype)

    def _virtual_pinhole(self, pts: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        xy = self._undistort(self.camera, pts, valid).to(torch.float64)
        c = torch.tensor([self.width / 2.0, self.height / 2.0], dtype=torch.float64, device=pts.device)
        return FOCAL_LENGTH * xy + c

    def _pyramid(self, img_u8: torch.Tensor):
        from .pyramid import build_pyramid

        # uint8 in: the levels are rounded per level as OpenCV's 8-bit pyramid (LK fidelity). No
        # full-image derivatives: the LK takes them from the windows it reads (see lk._template).
        return build_pyramid(img_u8, self.lk_kwargs["max_level"], with_gradients=False)

    def _select_pyramid(self, active: torch.Tensor, new, old):
        # the common case (every stream processed) keeps the new pyramid as it is: no copy of all
        # levels (one host sync to know). The tracker's pyramids carry no gradients (see _pyramid).
        if old is None or bool(active.all()):
            return new
        from .pyramid import Pyramid

        levels = [_where_stream(active, n, o) for n, o in zip(new.levels, old.levels)]
        return Pyramid(levels=levels, rounded=new.rounded)

    # ------------------------------------------------------------------ public API

    def track(self, images, timestamps, right=None, active=None) -> FeatureFrame:
        """Process one image per stream. See the class docstring.

        Args:
            images: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float 0..255.
            timestamps: ``(B,)`` seconds (float64 tensor or sequence).
            right: fusion stereo only: camera 1's images, tracked left→right with the same ids.
            active: optional ``(B,)`` bool; a stream with False is left exactly as it was (its
                clock, features and ids do not change), e.g. a sequence that has ended while the
                others go on. Its outputs are empty for this step.
        """
        img = self._images(images, "images")
        t = self._timestamps(timestamps)
        if active is None:
            user_active = torch.ones(self.B, dtype=torch.bool, device=self.device)
        else:
            user_active = torch.as_tensor(active, device=self.device).to(torch.bool)
            check_shape(user_active, (self.B,), "active")
        if self.mode == "mono":
            if right is not None:
                raise ValueError("right: stereo images are only supported with mode='fusion'")
            return self._track_mono(img, t, user_active)
        r = None if right is None else self._images(right, "right")
        if r is not None and self.camera1 is None:
            raise ValueError(f"right: the config {self.config.path} has no cam1_calib (num_of_cam 2)")
        return self._track_fusion(img, t, r, user_active)

    def remove(self, stream: int, ids: Sequence[int]) -> None:
        """Drop features by id from one stream (VINS-Fusion ``removeOutliers``)."""
        if not 0 <= stream < self.B:
            raise ValueError(f"stream: expected 0 <= stream < {self.B}, got {stream}")
        s = self.state
        drop_ids = torch.as_tensor(list(ids), dtype=torch.int64, device=self.device)
        if drop_ids.numel() == 0:
            return
        hit = (s.ids[stream].unsqueeze(-1) == drop_ids).any(-1) & s.valid[stream]
        valid = s.valid.clone()
        valid[stream] &= ~hit
        self._apply_compaction(valid)

    def set_prediction(self, ids: torch.Tensor, uv: torch.Tensor, valid: Optional[torch.Tensor] = None) -> None:
        """Predicted pixels for the next frame per id (VINS-Fusion ``setPrediction``).

        ids: (B, M) int64; uv: (B, M, 2) pixels; valid: (B, M) bool. In a stream with at least one
        valid prediction, the next ``track`` starts LK from the predicted pixels (features without
        one from their previous position) with one pyramid level, falling back to plain LK when
        fewer than 10 track; other streams track as usual. Consumed by the next ``track``.
        """
        check_shape(ids, (self.B, "M"), "ids")
        check_shape(uv, (self.B, ids.shape[1], 2), "uv")
        s = self.state
        ids = ids.to(self.device)
        v = torch.ones_like(ids, dtype=torch.bool) if valid is None else valid.to(self.device, torch.bool)
        match = (s.ids.unsqueeze(-1) == ids.unsqueeze(1)) & v.unsqueeze(1) & s.valid.unsqueeze(-1)  # (B, K, M)
        has = match.any(-1)
        j = match.to(torch.int8).argmax(-1)  # first match
        pred = torch.gather(uv.to(self.device, self.dtype), 1, j.unsqueeze(-1).expand(-1, -1, 2))
        s.prediction = torch.where(has.unsqueeze(-1), pred, s.pts)
        s.has_prediction = has.any(-1)

    # ------------------------------------------------------------------ internals

    def _apply_compaction(self, valid: torch.Tensor) -> None:
        s = self.state
        # the prediction moves with its slot, so remove() after set_prediction() keeps them aligned
        (s.valid, s.pts, s.ids, s.track_cnt, s.un_pts, s.prev_right_un, s.prev_right_valid, s.prediction) = _compact(
            valid, s.pts, s.ids, s.track_cnt, s.un_pts, s.prev_right_un, s.prev_right_valid, s.prediction
        )
        s.ids = torch.where(s.valid, s.ids, torch.full_like(s.ids, -1))
        s.prev_right_valid = s.prev_right_valid & s.valid

    def _lk(self, prev_pyr, pyr, pts, valid, **overrides):
        from .lk import track_lk

        kw = dict(self.lk_kwargs)
        kw.update(overrides)
        with self._stage("lk"):
            return track_lk(prev_pyr, pyr, pts, valid, **kw)

    def _detect(self, img_u8, pts, valid, track_cnt, do_detect: torch.Tensor, base_mask):
        """setMask + good features into the free slots for the streams in ``do_detect``.

        Returns the new (pts, valid, track_cnt, is_new) in VINS's order: the tracked features
        sorted by track count (ties by array order), then the detections in response order.
        """
        from .corners import good_features_to_track
        from .masks import distance_mask

        B, K = valid.shape
        dev = valid.device
        order = torch.arange(K, device=dev).expand(B, K).clone()
        # Only the detecting streams pay for setMask and GFTT (mono: the published ones, about one
        # frame in two at 20 Hz with freq 10). One host sync per frame picks them.
        sel = do_detect.nonzero().flatten()
        n_sel = int(sel.numel())
        if n_sel == 0:
            empty = torch.zeros(B, 0, 2, device=dev, dtype=pts.dtype)
            return order, valid, valid.sum(1), empty, torch.zeros(B, 0, device=dev, dtype=torch.bool)
        every = n_sel == B
        pick = (lambda x: x) if every else (lambda x: x.index_select(0, sel))  # noqa: E731
        v_sub, c_sub = pick(valid), pick(track_cnt)
        # setMask: visit by descending track count, ties by index (stable sort; VINS's std::sort is
        # unstable, see the spec §3.7 — a deterministic, documented difference).
        key = torch.where(v_sub, c_sub, torch.full_like(c_sub, -1))
        o_sub = torch.sort(-key, dim=1, stable=True).indices
        pts_s, valid_s, cnt_s = gather_slots(pick(pts), o_sub), gather_slots(v_sub, o_sub), gather_slots(c_sub, o_sub)
        with self._stage("mask"):
            keep, mask = distance_mask(
                pts_s, cnt_s, valid_s, self.config.min_dist,
                # the image's own size: VINS-Fusion uses the actual size, Mono checked it equals the config
                base_mask=base_mask, height=img_u8.shape[-2], width=img_u8.shape[-1],
            )
        valid_s = valid_s & keep
        n_max = self.K - valid_s.sum(1)
        with self._stage("detection"):
            p_sub, nv_sub = good_features_to_track(
                pick(img_u8), n_max, quality_level=0.01, min_distance=self.config.min_dist, mask=mask
            )
        if every:
            order, new_pts, new_valid = o_sub, p_sub, nv_sub
        else:
            order[sel] = o_sub
            valid_s_full = valid.clone()
            valid_s_full[sel] = valid_s
            valid_s = valid_s_full
            new_pts = torch.zeros(B, p_sub.shape[1], 2, device=dev, dtype=p_sub.dtype)
            new_valid = torch.zeros(B, p_sub.shape[1], device=dev, dtype=torch.bool)
            new_pts[sel] = p_sub
            new_valid[sel] = nv_sub
        n_keep = valid_s.sum(1)
        return order, valid_s, n_keep, new_pts, new_valid

    def _track_common(self, img, t, active, publish):
        """LK, border test, compaction and track_cnt for the ``active`` streams; detection on the
        ``publish`` streams. Returns the equalised images and the previous positions."""
        s = self.state
        cfg = self.config
        img_eq = img
        if self.mode == "mono" and cfg.equalize:
            from .clahe import clahe

            with self._stage("clahe"):
                img_eq = clahe(img)
        with self._stage("pyramid"):
            pyr = self._pyramid(img_eq)
        prev_pyr = s.prev_pyramid if s.prev_pyramid is not None else pyr
        run = active & s.has_image
        lk_valid = s.valid & run.unsqueeze(-1)
        prev_pts = s.pts
        if self.mode == "fusion" and bool(s.has_prediction.any()):
            nxt1, st1 = self._lk(prev_pyr, pyr, s.pts, lk_valid, max_level=1, init_pts=s.prediction)
            nxt, st = self._lk(prev_pyr, pyr, s.pts, lk_valid)
            use = s.has_prediction & (st1.sum(1) >= 10)  # VINS: < 10 tracked => plain LK instead
            nxt = _where_stream(use, nxt1, nxt)
            st = _where_stream(use, st1, st)
            s.has_prediction = s.has_prediction & ~run  # consumed (kept for streams not processed now)
        else:
            nxt, st = self._lk(prev_pyr, pyr, s.pts, lk_valid)
        if self.mode == "fusion" and cfg.flow_back:
            back, st_b = self._lk(pyr, prev_pyr, nxt, lk_valid & st, max_level=1, init_pts=s.pts)
            dist = (back - s.pts).norm(dim=-1)
            st = st & st_b & (dist <= 0.5)
        st = st & _in_border(nxt, self.width if self.mode == "mono" else img.shape[-1],
                             self.height if self.mode == "mono" else img.shape[-2])
        new_valid = torch.where(run.unsqueeze(-1), s.valid & st, s.valid)
        new_pts = torch.where(run.unsqueeze(-1).unsqueeze(-1), nxt.to(self.dtype), s.pts)
        (valid, pts, prev_pts, ids, cnt, un_prev, r_un, r_valid) = _compact(
            new_valid, new_pts, prev_pts, s.ids, s.track_cnt, s.un_pts, s.prev_right_un, s.prev_right_valid
        )
        cnt = torch.where(valid & active.unsqueeze(-1), cnt + 1, cnt)
        return img_eq, pyr, valid, pts, prev_pts, ids, cnt, un_prev, r_un, r_valid

    def _track_mono(self, img: torch.Tensor, t: torch.Tensor, user_active: torch.Tensor) -> FeatureFrame:
        s = self.state
        cfg = self.config
        freq = float(cfg.freq)
        # --- img_callback clock rules (spec §3.2), per stream; streams the caller marked inactive
        # keep every piece of state
        first = s.first_image_flag & user_active
        gap = user_active & ~s.first_image_flag & ((t - s.last_image_time > 1.0) | (t < s.last_image_time))
        active = user_active & ~s.first_image_flag & ~gap
        first_image_time = torch.where(first, t, s.first_image_time)
        last_image_time = torch.where(first | active, t, torch.where(gap, torch.zeros_like(t), s.last_image_time))
        pub_count = torch.where(gap, torch.ones_like(s.pub_count), s.pub_count)
        flag = torch.where(first, torch.zeros_like(first), torch.where(gap, torch.ones_like(first), s.first_image_flag))
        dt_pub = t - first_image_time
        # duplicate stamp: r = +inf, never published
        r = torch.where(dt_pub > 0, pub_count.to(torch.float64) / dt_pub.clamp_min(1e-300),
                        torch.full_like(t, math.inf))
        publish = active & (_c_round(r) <= freq)
        reset = publish & ((r - freq).abs() < 0.01 * freq)
        first_image_time = torch.where(reset, t, first_image_time)
        pub_count = torch.where(reset, torch.zeros_like(pub_count), pub_count)

        # --- readImage (spec §3.6) for active streams
        img_eq, pyr, valid, pts, prev_pts, ids, cnt, un_prev, r_un, r_valid = self._track_common(img, t, active, publish)

        # rejectWithF on published streams with >= 8 features
        n = valid.sum(1)
        do_f = publish & (n >= 8)
        if bool(do_f.any()):
            from .ransac import find_fundamental

            fv = valid & do_f.unsqueeze(-1)
            p1 = self._virtual_pinhole(prev_pts, fv)
            p2 = self._virtual_pinhole(pts, fv)
            # a fixed seed per call, as OpenCV re-seeds its RNG identically on every call: a stream's
            # result then does not depend on the other streams or on the call history
            with self._stage("ransac"):
                res = find_fundamental(p1, p2, fv, threshold=cfg.F_threshold, confidence=0.99, seed=self.seed)
            inliers = res[1]
            ok = getattr(res, "ok", None)
            if ok is None:
                ok = torch.ones_like(do_f)
            apply = do_f & ok
            valid = torch.where(apply.unsqueeze(-1), valid & inliers, valid)
            (valid, pts, prev_pts, ids, cnt, un_prev, r_un, r_valid) = _compact(
                valid, pts, prev_pts, ids, cnt, un_prev, r_un, r_valid
            )

        # setMask + detection on published streams
        order, valid_s, n_keep, new_pts, new_valid = self._detect(img_eq, pts, valid, cnt, publish, self.base_mask)
        pts, ids, cnt, un_prev = (gather_slots(x, order) for x in (pts, ids, cnt, un_prev))
        valid, pts, ids, cnt, un_prev = _compact(valid_s, pts, ids, cnt, un_prev)
        pts, valid, ids, cnt, is_new = self._append(pts, valid, ids, cnt, new_pts, new_valid, n_keep)

        # undistortion and velocity (Mono: a feature's first two observations have zero velocity)
        with self._stage("undistort"):
            un = self._undistort(self.camera, pts, valid)
        dt = (t - s.prev_time).to(self.dtype).unsqueeze(-1).unsqueeze(-1)
        # VINS divides by dt even when a duplicate stamp makes it 0 (inf/NaN velocities); here such
        # a step reports zero velocity. The safe divisor keeps the unused lanes finite.
        moving = (valid & (cnt >= 3) & ~is_new).unsqueeze(-1) & (dt != 0)
        vel = torch.where(moving, (un - un_prev) / torch.where(dt == 0, torch.ones_like(dt), dt),
                          torch.zeros_like(un))

        # ids for the new features, in array order (updateID)
        new_ids = s.next_id.unsqueeze(-1) + torch.cumsum(is_new.to(torch.int64), dim=1) - 1
        ids = torch.where(is_new, new_ids, ids)
        next_id = s.next_id + is_new.sum(1)

        # commit per stream: inactive streams keep their state
        a2 = active.unsqueeze(-1)
        a3 = a2.unsqueeze(-1)
        s.pts = torch.where(a3, pts, s.pts)
        s.valid = torch.where(a2, valid, s.valid)
        s.ids = torch.where(a2, torch.where(valid, ids, torch.full_like(ids, -1)), s.ids)
        s.track_cnt = torch.where(a2, torch.where(valid, cnt, torch.zeros_like(cnt)), s.track_cnt)
        s.un_pts = torch.where(a3, un, s.un_pts)
        s.next_id = torch.where(active, next_id, s.next_id)
        s.prev_time = torch.where(active, t, s.prev_time)
        s.prev_pyramid = self._select_pyramid(active, pyr, s.prev_pyramid)
        s.has_image = s.has_image | active
        sent = publish & s.init_pub
        s.init_pub = s.init_pub | publish
        s.pub_count = torch.where(publish, pub_count + 1, pub_count)
        s.first_image_flag = flag
        s.first_image_time = first_image_time
        s.last_image_time = last_image_time

        out_valid = s.valid & (s.track_cnt > 1) & publish.unsqueeze(-1)
        zero2 = torch.zeros_like(s.pts)
        return FeatureFrame(
            ids=s.ids.clone(),
            uv=s.pts.clone(),
            xy=s.un_pts.clone(),
            velocity=torch.where(a3, vel, zero2),
            track_count=s.track_cnt.clone(),
            valid=out_valid,
            present=s.valid.clone(),
            published=publish,
            sent=sent,
            restarted=gap,
            tracked=active,
            timestamps=t,
        )

    def _append(self, pts, valid, ids, cnt, new_pts, new_valid, n_keep):
        """Write detections into the free slots after the kept features (VINS ``addPoints``)."""
        B, K = valid.shape
        Kn = new_pts.shape[1]
        is_new = torch.zeros_like(valid)
        if Kn == 0:
            return pts, valid, ids, cnt, is_new
        rank = torch.cumsum(new_valid.to(torch.int64), dim=1) - 1
        slot = n_keep.unsqueeze(-1) + rank
        ok = new_valid & (slot < K)
        slot = torch.where(ok, slot, torch.full_like(slot, K))  # K = a dump slot, dropped below
        pad = lambda x, fill: torch.cat([x, torch.full_like(x[:, :1], fill)], dim=1)  # noqa: E731
        pts_p = pad(pts, 0).scatter(1, slot.unsqueeze(-1).expand(-1, -1, 2), new_pts.to(pts.dtype))
        valid_p = pad(valid, False).scatter(1, slot, ok)
        ids_p = pad(ids, -1).scatter(1, slot, torch.full_like(slot, -1))
        cnt_p = pad(cnt, 0).scatter(1, slot, torch.ones_like(slot))
        new_p = pad(is_new, False).scatter(1, slot, ok)
        return pts_p[:, :K], valid_p[:, :K], ids_p[:, :K], cnt_p[:, :K], new_p[:, :K]

    def _track_fusion(self, img: torch.Tensor, t: torch.Tensor, right: Optional[torch.Tensor],
                      active: torch.Tensor) -> FeatureFrame:
        s = self.state
        img_eq, pyr, valid, pts, prev_pts, ids, cnt, un_prev, r_un_prev, r_valid_prev = self._track_common(
            img, t, active, active
        )
        prev_valid_ids = valid & (cnt >= 2)  # tracked from the previous frame (drawn as arrows)
        prev_uv = prev_pts
        order, valid_s, n_keep, new_pts, new_valid = self._detect(img_eq, pts, valid, cnt, active, None)
        pts, prev_uv, ids, cnt, un_prev, r_un_prev, r_valid_prev, prev_valid_ids = (
            gather_slots(x, order) for x in (pts, prev_uv, ids, cnt, un_prev, r_un_prev, r_valid_prev, prev_valid_ids)
        )
        valid, pts, prev_uv, ids, cnt, un_prev, r_un_prev, r_valid_prev, prev_valid_ids = _compact(
            valid_s, pts, prev_uv, ids, cnt, un_prev, r_un_prev, r_valid_prev, prev_valid_ids
        )
        pts, valid2, ids, cnt, is_new = self._append(pts, valid, ids, cnt, new_pts, new_valid, n_keep)
        grow = lambda x: torch.where(is_new.unsqueeze(-1) if x.dim() == 3 else is_new, torch.zeros_like(x), x)  # noqa: E731
        prev_uv, un_prev, r_un_prev = grow(prev_uv), grow(un_prev), grow(r_un_prev)
        r_valid_prev = r_valid_prev & ~is_new & valid2
        prev_valid_ids = prev_valid_ids & ~is_new & valid2
        valid = valid2
        # VINS-Fusion assigns ids at detection
        new_ids = s.next_id.unsqueeze(-1) + torch.cumsum(is_new.to(torch.int64), dim=1) - 1
        ids = torch.where(is_new, new_ids, ids)
        next_id = s.next_id + is_new.sum(1)

        un = self._undistort(self.camera, pts, valid)
        first_call = ~s.has_image
        dt = (t - s.prev_time).to(self.dtype).view(-1, 1, 1)
        moving = (valid & (cnt >= 2) & ~first_call.unsqueeze(-1)).unsqueeze(-1) & (dt != 0)
        dt = torch.where(dt == 0, torch.ones_like(dt), dt)  # zero velocity on a duplicate stamp
        vel = torch.where(moving, (un - un_prev) / dt, torch.zeros_like(un))

        right_uv = right_xy = right_vel = right_valid = None
        r_un_new = torch.zeros_like(un)
        r_valid_new = torch.zeros_like(valid)
        if right is not None:
            rpyr = self._pyramid(right)
            ruv, rst = self._lk(pyr, rpyr, pts, valid)
            if self.config.flow_back:
                back, bst = self._lk(rpyr, pyr, ruv, valid & rst)
                rst = rst & bst & _in_border(ruv, right.shape[-1], right.shape[-2]) & ((back - pts).norm(dim=-1) <= 0.5)
            right_valid = valid & rst
            right_uv = torch.where(right_valid.unsqueeze(-1), ruv.to(self.dtype), torch.zeros_like(pts))
            right_xy = self._undistort(self.camera1, right_uv, right_valid)
            rmoving = right_valid & r_valid_prev & ~first_call.unsqueeze(-1)
            right_vel = torch.where(rmoving.unsqueeze(-1), (right_xy - r_un_prev) / dt, torch.zeros_like(right_xy))
            r_un_new, r_valid_new = right_xy, right_valid

        # commit per stream: inactive streams keep their state
        keep = lambda new, old: _where_stream(active, new, old)  # noqa: E731
        ids = torch.where(valid, ids, torch.full_like(ids, -1))
        cnt = torch.where(valid, cnt, torch.zeros_like(cnt))
        s.pts, s.valid, s.ids, s.track_cnt, s.un_pts = (
            keep(pts, s.pts), keep(valid, s.valid), keep(ids, s.ids), keep(cnt, s.track_cnt), keep(un, s.un_pts))
        s.prev_right_un = keep(r_un_new, s.prev_right_un)
        s.prev_right_valid = keep(r_valid_new, s.prev_right_valid)
        s.next_id = keep(next_id, s.next_id)
        s.prev_time = keep(t, s.prev_time)
        s.prev_pyramid = self._select_pyramid(active, pyr, s.prev_pyramid)
        s.has_image = s.has_image | active
        a2 = active.unsqueeze(-1)
        valid = valid & a2
        if right_valid is not None:
            right_valid = right_valid & a2
        return FeatureFrame(
            ids=torch.where(valid, ids, torch.full_like(ids, -1)), uv=pts.clone(), xy=un.clone(),
            velocity=torch.where(valid.unsqueeze(-1), vel, torch.zeros_like(vel)), track_count=cnt.clone(),
            valid=valid.clone(), present=valid.clone(), published=active.clone(), sent=active.clone(),
            restarted=torch.zeros_like(active), tracked=active.clone(), timestamps=t,
            prev_uv=prev_uv, prev_valid=prev_valid_ids,
            right_uv=right_uv, right_xy=right_xy, right_velocity=right_vel, right_valid=right_valid,
        )


__all__ = ["FeatureTracker", "FeatureFrame", "TrackerState"]
