"""``TrackerParams``: every setting of the tracker step, VINS's hard-coded constants by name.

Convention:
    Names follow VINS (config keys such as ``max_cnt``, ``min_dist``, ``F_threshold`` keep their
    spelling; VINS's hard-coded constants get the names of ``docs/spec.md`` §2). Each constant's
    comment cites the spec section that states it. Pixels are image pixels ``(x, y)``, times are
    seconds. A ``TrackerParams`` is frozen and hashable: the step treats it as static.

The step reads nothing else: the config file (``TrackerConfig``) fills the first block
(:meth:`TrackerParams.from_config`); everything below it is the same in every VINS config.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Optional, Tuple

import torch

from .._checks import check_shape
from ..corners import check_block
from ..equalize import check_grid
from ..errors import ConfigError
from ..lk import LKOptions
from ..masks import fisheye_mask as analytic_fisheye_mask
from ..ransac import METHODS as F_METHODS

MODES = ("mono", "fusion")


@dataclasses.dataclass(frozen=True)
class TrackerParams:
    """Static settings of :func:`torch_frontend.tracker.step`.

    Attributes (from the config, spec §1.2 / §1.5):
        mode: ``"mono"`` (VINS-Mono ``feature_tracker``) or ``"fusion"`` (VINS-Fusion tracker).
        width, height: ``COL``, ``ROW`` of the config (mono checks images against them; fusion
            uses each image's actual size, spec §6.2).
        max_cnt, min_dist, freq, F_threshold, equalize, fisheye, flow_back: the VINS keys; F_method
            (this library's key): rejectWithF's estimator, ``"opencv"`` (VINS) or ``"lo"`` (LO-RANSAC)
            (``freq`` already mapped 0 -> 100 by the config reader).
        seed: ``cv::RNG`` seed of every F-RANSAC problem (OpenCV re-seeds identically per call).
        camera, camera1: the camodocal models of camera 0 and (fusion stereo) camera 1
            (``CameraModel`` modules, float64 on the tracker's device).
        fisheye_mask: ``(H, W)`` uint8 (255 = allowed) for mono ``fisheye: 1`` configs, else None.
        capturable: the step is shape-static and free of host synchronisation (CUDA graphs,
            ``torch.compile(fullgraph=True)``): fixed budgets with per-element freezing instead of
            early exits, every stage runs for every stream under masks, and the kernel count does
            not depend on B. False: the eager path tuned for the CPU (early exit, compaction,
            stream groups). Both give identical results wherever ``frame.overflow`` is False.
        differentiable: float images stay float through the step so that ``uv``, ``xy`` and
            ``velocity`` of tracked features carry gradients to the images (and to the cameras'
            parameters): the door rounds and clamps as cv_bridge but straight through, CLAHE's
            gradient is its LUT's local slope (straight-through), the pyramid's 8-bit rounding is
            straight-through, LK's gradient follows ``lk_grad_mode``; detection, status, RANSAC and
            setMask stay discrete masks. The values are the 8-bit path's, bit for bit.
        lk_grad_mode: differentiable only: LK's ``grad_mode``, ``"implicit"`` (default: the
            implicit-function gradient of the converged level-0 solution, memory independent of
            the iterations, zero for lost lanes) or ``"unrolled"`` (every iteration, as computed).
        lk_backend: the pyramid's and the LK's kernels, resolved (``fused.resolve_backend``):
            ``"fused"`` (one custom op each, OpenCV's bits; ``FeatureTracker``'s default on the CPU
            and CUDA) or ``"tensor"`` (the tensor kernels; the default of params built by hand).
        clahe_backend: CLAHE's kernel, resolved (``fused.resolve_clahe_backend``): ``"fused"`` (the
            one op ``torch_frontend::clahe``; ``FeatureTracker``'s default on the CPU and CUDA) or
            ``"tensor"`` (``equalize``'s tensor CLAHE; the default of params built by hand). The
            same bits either way.
        corner_backend: goodFeaturesToTrack's kernels, resolved (``fused.resolve_corner_backend``):
            ``"fused"`` (the ``good_features`` op; ``FeatureTracker``'s default on the CPU and CUDA)
            or ``"tensor"`` (``corners/``; the default of params built by hand). The same corners.
        lift_backend: the PINHOLE camera's lift (``lift_normalised``), resolved
            (``fused.resolve_lift_backend``): ``"fused"`` (the ``pinhole_lift`` op; ``FeatureTracker``'s
            default on the CPU and CUDA) or ``"tensor"`` (the camera's ``_lift_impl``; the default of
            params built by hand). The same bits; other models always lift with the tensor path.

    The remaining fields are VINS's hard-coded constants; change them only to experiment.
    """

    mode: str = "mono"
    width: int = 752
    height: int = 480
    max_cnt: int = 150
    min_dist: int = 30
    freq: int = 10
    F_threshold: float = 1.0
    equalize: bool = False
    fisheye: bool = False
    flow_back: bool = False
    seed: int = 0
    camera: Any = dataclasses.field(default=None, compare=False, repr=False)
    camera1: Any = dataclasses.field(default=None, compare=False, repr=False)
    fisheye_mask: Optional[Any] = dataclasses.field(default=None, compare=False, repr=False)
    capturable: bool = False
    differentiable: bool = False
    lk_grad_mode: str = "implicit"
    lk_backend: str = "tensor"
    clahe_backend: str = "tensor"
    corner_backend: str = "tensor"
    lift_backend: str = "tensor"

    # --- img_callback clock rules (mono), spec §3.2
    restart_gap: float = 1.0  # s: a larger step (or time going backwards) restarts the stream
    freq_reset_tolerance: float = 0.01  # |rate - FREQ| < 0.01 FREQ restarts the rate window

    # --- CLAHE (mono, ``equalize``), spec §2 / §5.3
    clahe_clip_limit: float = 3.0
    clahe_tile_grid: Tuple[int, int] = (8, 8)

    # --- pyramidal LK, spec §2 / §5.1
    lk_win_size: int = 21
    lk_max_level: int = 3
    lk_max_iters: int = 30
    lk_eps: float = 0.01
    lk_min_eig_threshold: float = 1e-4
    # capturable step only: LK iterations run per level (None = lk_max_iters, exact; an int or one
    # per level, level 0 first). A smaller budget is fewer launches per step; a point still
    # iterating when it ends raises frame.overflow (lk.LKOptions.iter_budget)
    lk_iter_budget: Any = None
    # capturable step only, full budget: after 8 iterations on every lane, the rest on a sub-batch
    # of 1/lk_tail_share of the lanes (a lane left without a seat raises frame.overflow; 1: every
    # lane, every iteration; lk.LKOptions.tail_share)
    lk_tail_share: int = 8
    # default path only: the LK's per-iteration kernel through torch.compile (False; True or the
    # torch.compile keywords, normalised to sorted pairs: lk.LKOptions.compile_step), this
    # tracker's setting (FeatureTracker.compile on a non-capturable tracker)
    lk_compile_step: Any = False
    # VINS-Fusion: LK from a prediction and the temporal backward check use one level, spec §6.2
    fusion_short_max_level: int = 1
    # VINS-Fusion: fewer tracks from the prediction than this => plain LK instead, spec §6.2
    prediction_min_tracked: int = 10
    # VINS-Fusion FLOW_BACK: accept iff |back - start| <= this (px), spec §6.3
    flow_back_threshold: float = 0.5

    # --- inBorder, spec §2 / §3.6 step 5b: 1 <= cvRound(x) < COL - 1 (and y likewise)
    border_size: int = 1

    # --- rejectWithF, spec §2 / §3.8: 7-point RANSAC on the virtual pinhole. (VINS skips it below
    # 8 points; the RANSAC kernel itself applies that rule, see ransac.find_fundamental.)
    focal_length: float = 460.0  # FOCAL_LENGTH of the virtual pinhole, principal point (COL/2, ROW/2)
    ransac_confidence: float = 0.99
    ransac_max_iters: int = 1000  # OpenCV's default cap on minimal samples (spec §3.8)
    # the estimator (config key F_method): "opencv" = VINS's cv::findFundamentalMat, exactly;
    # "lo" = LO-RANSAC, the same samples and 1 px test with local optimisation (ransac.find_fundamental)
    F_method: str = "opencv"

    # --- goodFeaturesToTrack, spec §2 / §5.2: Shi-Tomasi on 3x3 blocks (Harris' k unused)
    gftt_quality_level: float = 0.01
    gftt_block_size: int = 3
    gftt_harris_k: float = 0.04

    # --- velocities, spec §3.10 / §6.2: mono assigns ids after undistortion, so a feature gets a
    # velocity from its 3rd processed observation; fusion assigns ids at detection (2nd observation)
    mono_velocity_min_count: int = 3
    fusion_velocity_min_count: int = 2

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode: expected 'mono' or 'fusion', got {self.mode!r}")
        if self.max_cnt <= 0 or self.min_dist < 0:
            raise ValueError(f"max_cnt must be > 0 and min_dist >= 0 for tracking, got max_cnt={self.max_cnt}, "
                             f"min_dist={self.min_dist}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size: expected positive width and height, got {self.width}x{self.height}")
        if not self.freq > 0:
            raise ValueError(f"freq: expected a publish rate > 0 Hz (a config's 0 reads as 100), got {self.freq}")
        if self.F_method not in F_METHODS:
            raise ValueError(f"F_method: expected one of {F_METHODS}, got {self.F_method!r}")
        if not math.isfinite(self.F_threshold):
            raise ValueError(f"F_threshold: expected a finite number of pixels, got {self.F_threshold}")
        for name in ("camera", "camera1"):
            cam = getattr(self, name)
            problems = [] if cam is None else type(cam).param_problems(cam.params_dict())
            if problems:  # a camera built by hand (the readers check calibration files themselves)
                key, why = problems[0]
                raise ValueError(f"{name}.{key}: {why}")
        self.check_image_size(self.height, self.width)
        # the derived options are built here, not on first use inside a traced step: Python 3.11's
        # cached_property takes a lock on first access, which torch.compile cannot trace
        if isinstance(self.lk_iter_budget, list):  # params stay hashable
            object.__setattr__(self, "lk_iter_budget", tuple(self.lk_iter_budget))
        try:
            if self.lk_compile_step is not False:  # hashable: the normalised torch.compile keywords
                object.__setattr__(self, "lk_compile_step", LKOptions(compile_step=self.lk_compile_step).compile_step)
            self.lk_options, self.lk_short_options, self.lk_stereo_options  # noqa: B018
        except ConfigError as exc:  # name the tracker's field, not LKOptions'
            raise ConfigError(f"lk_iter_budget / lk_tail_share / lk_grad_mode / lk_compile_step / lk_backend / lk_*: "
                              f"{exc}") from None

    def check_image_size(self, height: int, width: int) -> None:
        """The kernels' size checks for ``height x width`` images (the step calls the kernels
        without theirs): CLAHE's padding, the corner response's borders."""
        if self.uses_clahe:
            check_grid(height, width, *self.clahe_tile_grid)
        check_block(height, width, self.gftt_block_size)

    @classmethod
    def from_config(cls, config, mode: str = "mono", seed: int = 0, **overrides) -> TrackerParams:
        """Params of a ``TrackerConfig`` (VINS keys, its cameras) for ``mode``; ``overrides``
        replace any field. Mono ``fisheye: 1`` configs get the analytic disc mask of
        ``torch_frontend.fisheye_mask`` unless ``fisheye_mask`` is given."""
        fields = dict(
            mode=mode, width=int(config.image_width), height=int(config.image_height),
            max_cnt=int(config.max_cnt), min_dist=int(config.min_dist), freq=int(config.freq),
            F_threshold=float(config.F_threshold), F_method=str(getattr(config, "F_method", "opencv")),
            equalize=bool(config.equalize), fisheye=bool(config.fisheye),
            flow_back=bool(config.flow_back), seed=int(seed), camera=config.camera, camera1=config.camera1,
        )
        fields.update(overrides)
        params = cls(**fields)
        if not params.uses_fisheye_mask:
            params = dataclasses.replace(params, fisheye_mask=None)
        elif params.fisheye_mask is None:
            params = dataclasses.replace(params, fisheye_mask=analytic_fisheye_mask(params.height, params.width))
        return params

    def to(self, device) -> TrackerParams:
        """The same params with the cameras (float64) and the mask (checked: ``(H, W)``) on ``device``."""

        def move(cam):
            return None if cam is None else cam.to(device=device, dtype=torch.float64)

        mask = self.fisheye_mask
        if mask is not None:
            mask = torch.as_tensor(mask)
            check_shape(mask, (self.height, self.width), "fisheye_mask")
            mask = mask.to(device, torch.uint8)
        return dataclasses.replace(self, camera=move(self.camera), camera1=move(self.camera1), fisheye_mask=mask)

    # ------------------------------------------------------------------ derived settings
    @functools.cached_property
    def lk_options(self) -> LKOptions:
        """VINS's LK call (spec §2), OpenCV's fixed point (the tracker's pyramids are 8-bit), on the
        step's path (``capturable``)."""
        return LKOptions(win_size=(self.lk_win_size, self.lk_win_size), max_level=self.lk_max_level,
                         max_iters=self.lk_max_iters, eps=self.lk_eps, min_eig_threshold=self.lk_min_eig_threshold,
                         fixed_point=True, capturable=self.capturable, iter_budget=self.lk_iter_budget,
                         tail_share=self.lk_tail_share,
                         grad_mode=self.lk_grad_mode if self.differentiable else "unrolled",
                         compile_step=self.lk_compile_step, backend=self.lk_backend)

    @functools.cached_property
    def lk_short_options(self) -> LKOptions:
        """VINS-Fusion's one-level LK (from a prediction; the temporal backward check)."""
        return dataclasses.replace(self.lk_options, max_level=self.fusion_short_max_level)

    @functools.cached_property
    def lk_stereo_options(self) -> LKOptions:
        """VINS-Fusion's left -> right LK (no guess): every lane every iteration (``tail_share`` 1).
        The disparities are tens of pixels, so many lanes iterate long (the golden stereo run
        overflows the default tail's seats); the tail split pays for temporal tracking only."""
        return dataclasses.replace(self.lk_options, tail_share=1)

    @property
    def uses_clahe(self) -> bool:
        """VINS-Mono equalises when ``equalize`` is set; VINS-Fusion never does (spec §6.2 step 1)."""
        return self.mode == "mono" and self.equalize

    @property
    def uses_fisheye_mask(self) -> bool:
        """Only VINS-Mono applies the fisheye mask (spec §3.13, §6.2 step 4)."""
        return self.mode == "mono" and self.fisheye

    @property
    def velocity_min_count(self) -> int:
        return self.mono_velocity_min_count if self.mode == "mono" else self.fusion_velocity_min_count


__all__ = ["TrackerParams", "MODES"]
