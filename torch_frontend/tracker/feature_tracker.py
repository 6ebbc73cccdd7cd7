"""``FeatureTracker``: the VINS-Mono front end (and VINS-Fusion's tracker) for B streams, as a thin
stateful wrapper over the pure :func:`~torch_frontend.tracker.step`.

Convention:
    Each of the B streams has its own clock, feature table and id counter; ids are per stream
    (stream b numbers its features 0, 1, 2, ...; VINS's one counter per process is the same thing
    for one camera), int64. The per-frame branches of VINS (first frame skipped, restart, publish or
    not, detection or not) differ per stream by masks; every stream runs through the same tensor
    code in each call. ``tracker.state`` is the current :class:`TrackerState`; ``track`` replaces it
    with the step's new state.
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings
import weakref
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.utils._pytree as pytree

from .. import fused as _fused
from .._checks import check_device, check_shape
from .._compiler import prepare_compile
from ..config import TrackerConfig
from ..fused import resolve_backend, resolve_clahe_backend, resolve_corner_backend, resolve_ransac_backend
from ..lk import exact_float32
from .clock import HostClock, PublishPlan, RestartWatch, publish_plan
from .frame import FeatureFrame
from .params import TrackerParams
from .stages import remove_features, set_prediction
from .state import TrackerState
from .streams import (
    GroupedState,
    StreamGroup,
    group_key,
    inverse_order,
    merge_frames,
    partition,
    split_images,
    stream_cameras,
    stream_configs,
)
from .track_step import check_active, check_images, check_inputs, check_timestamps, step_impl


class _StageTimer:
    """Per-stage wall-clock accounting (``FeatureTracker.stage_times``), for benchmarks: the step's
    ``stage(name)`` hook. A no-op unless enabled; when enabled it synchronises CUDA at stage
    boundaries so that the times are real (which costs a little throughput)."""

    def __init__(self):
        self.times: Optional[Dict[str, float]] = None

    def __call__(self, name: str):
        return _StageSpan(self, name)


class _StageSpan:
    def __init__(self, timer: _StageTimer, name: str):
        self.timer, self.name = timer, name

    def __enter__(self):
        if self.timer.times is not None:
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        times = self.timer.times
        if times is not None:
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            times[self.name] = times.get(self.name, 0.0) + time.perf_counter() - self.t0
        return False


def _pure_step(state: TrackerState, img, t, params: TrackerParams, right, active, plan: Optional[PublishPlan] = None,
               regions: Optional[Callable] = None):
    """The compiled unit: :func:`step_impl` on validated inputs, no stage hooks (their timers
    synchronise)."""
    return step_impl(state, img, t, params, right=right, active=active, plan=plan, regions=regions)


def _own_code(fn: Callable, name: str) -> Callable:
    """``fn`` called through a function with a code object of its own, named ``name``: dynamo keeps
    compiled graphs (and its recompile limit) per code object, so each gets its own."""
    def own(*args):
        return fn(*args)

    own.__code__ = own.__code__.replace(co_name=name, co_qualname=name)
    own.__name__ = own.__qualname__ = name
    return own


class _Regions:
    """The mono step's parts, compiled separately (``step_impl``'s ``regions``): each name (a part
    and its static arguments: ``track``, ``publish``, ``publish_<lanes>``, ``finish_...``) is
    compiled on its first call and reused by every step variant that calls it, so a run compiles
    the LK once, not once per variant. ``compiler(fn)`` compiles one part."""

    def __init__(self, compiler: Callable[[Callable], Callable]):
        self.compiler = compiler
        self.parts: Dict[str, Callable] = {}

    def __call__(self, name: str, fn: Callable, *args):
        part = self.parts.get(name)
        if part is None:
            part = self.parts[name] = self.compiler(_own_code(fn, "_part_" + name))
        return part(*args)


def _variant_step(plan: Optional[PublishPlan]) -> Callable:
    """:func:`_pure_step` with ``plan`` fixed, as a function with a code object of its own: dynamo
    keeps compiled graphs per code object, so the variants of one closure would share one cache
    (and its recompile limit); their own code objects make each variant a separate compiled
    callable, traced and captured once."""
    def variant(state, img, t, params, right, active):
        return _pure_step(state, img, t, params, right, active, plan)

    return _own_code(variant, "_step_" + ("full" if plan is None else plan.name))


class _CompiledStep:
    """The compiled step variants (one per :class:`PublishPlan`, compiled on first use) with the
    eager fallback and, for CUDA graphs, outputs cloned out of the graph's memory pool (the next
    replay overwrites them). ``compiler(fn)`` compiles one variant (``torch.compile`` with the
    tracker's options)."""

    def __init__(self, compiler: Callable[[Callable], Callable], cuda_graphs: bool, fallback: bool,
                 regions: bool = False):
        self.compiler, self.cuda_graphs, self.fallback = compiler, cuda_graphs, fallback
        self.variants: Dict[Optional[PublishPlan], Callable] = {}
        #: the compiled parts shared by every variant (``compile(regions=True)``), else None
        self.regions: Optional[_Regions] = _Regions(compiler) if regions else None
        self.failed: Optional[BaseException] = None

    def _variant(self, plan: Optional[PublishPlan]) -> Callable:
        if self.regions is None:
            return self.compiler(_variant_step(plan))
        return functools.partial(_pure_step, plan=plan, regions=self.regions)  # eager glue between parts

    def __call__(self, state, img, t, params, right, active, plan: Optional[PublishPlan] = None):
        if self.failed is None:
            try:
                fn = self.variants.get(plan)
                if fn is None:
                    # the package's per-size constants (``_cache.cached``) are built by one eager step
                    # first (pure: its result is dropped): a cache miss inside a fullgraph trace cannot
                    # be built outside the graph, and the compiled step failed on a cold cache
                    _pure_step(state, img, t, params, right, active, plan)
                    fn = self.variants[plan] = self._variant(plan)
                if self.cuda_graphs:
                    torch.compiler.cudagraph_mark_step_begin()
                out = fn(state, img, t, params, right, active)
                if self.cuda_graphs:
                    out = _clone_out_of_pool(out)
                return out
            except Exception as exc:  # the compiler failed (not a bad input: those are checked before)
                if not self.fallback:
                    raise
                self.failed = exc
                warnings.warn(f"FeatureTracker.compile: the compiled step failed ({type(exc).__name__}: {exc}); "
                              f"running eager from now on", RuntimeWarning, stacklevel=3)
        return _pure_step(state, img, t, params, right, active, plan)


def _clone_out_of_pool(out):
    """A CUDA-graph step's ``(state, frame)`` cloned out of the graph's memory pool (the next replay
    overwrites it). The state's pyramid is a pytree of its levels only, so its padded-level cache
    (``Pyramid.padded``: the LK reads the previous levels' padded copies) is cloned across by hand:
    without it the next step pads them again and fails the graph's guard on the cache once."""
    cloned = pytree.tree_map(lambda x: x.clone() if isinstance(x, torch.Tensor) else x, out)
    old, new = out[0], cloned[0]
    src, dst = getattr(old, "prev_pyramid", None), getattr(new, "prev_pyramid", None)
    if src is not None and dst is not None and src is not dst:
        dst._padded = {k: v.clone() for k, v in src._padded.items()}
    return cloned


def _host_array(x: torch.Tensor) -> np.ndarray:
    """A CPU tensor's values as a new numpy array (B values: microseconds). A copy, not
    ``Tensor.numpy``'s alias: the caller's timestamps tensor is uploaded next, and an alias held by
    the mirror would tie the two (``cuda_sim`` then no longer sees that upload as the input's)."""
    return np.array(x.tolist(), dtype=np.float64 if x.is_floating_point() else bool)


class FeatureTracker:
    """The VINS front end for ``num_streams`` streams tracked together.

    Args:
        config: a ``TrackerConfig`` or the path of a VINS config YAML.
        num_streams: B, the number of streams (cameras or sequences) tracked in each call.
        device: where the state and the work live; one this process cannot use (``"cuda"`` with a
            CPU-only torch, ``"cuda:3"`` on a one-GPU machine, ``"mps"`` off a Mac) raises a
            ``ValueError`` naming it and the available devices.
        mode: ``"mono"`` (VINS-Mono ``feature_tracker`` node) or ``"fusion"`` (VINS-Fusion tracker).
        dtype: float dtype of points inside the tracker (float32 default).
        fisheye_mask: optional ``(H, W)`` uint8 mask for ``fisheye: 1`` configs; default: the
            analytic disc of ``torch_frontend.fisheye_mask``.
        seed: F-RANSAC seed, used for every problem of every call (OpenCV re-seeds identically on
            each call), so a stream's result does not depend on the other streams.
        capturable: True: every per-frame operation is shape-static and free of host
            synchronisation (fixed budgets, every stage for every stream under masks, a kernel
            count independent of B), so the step can be captured in a CUDA graph or compiled whole
            (:meth:`compile`); ``frame.overflow`` says where a budget was too small. False: the
            eager path tuned for the CPU (early exits, compaction, stream groups). None (default):
            True on a non-CPU device, False on the CPU (the name follows ``torch.optim``'s
            ``capturable``). Both paths give identical results wherever ``frame.overflow`` is False.
        lk_iter_budget: capturable only: LK iterations per pyramid level (None: VINS's 30, exact;
            an int, or a tuple per level, level 0 first). Each iteration is ~21 launches per level
            whatever B, so e.g. ``(16, 14, 12, 10)`` saves ~1,400 launches per step; a point that
            would need more iterations sets ``frame.overflow`` for its stream.
        lk_tail_share: capturable only, full budget: after 8 LK iterations on every point, the
            rest run on a sub-batch of ``1/lk_tail_share`` of the points, those still iterating
            first (on real frames a handful: ~60 % fewer LK bytes than every point every
            iteration); a point left without a seat sets ``frame.overflow``. 1: no sub-batch.
        differentiable: keep float images float through the step (the learned-VIO path): ``uv``,
            ``xy`` and ``velocity`` of tracked features carry gradients to the images of this and
            earlier steps (through the state) and to the cameras' parameters (after
            ``tracker.camera.requires_grad_()``). CLAHE's gradient is its LUT's local slope and the
            8-bit roundings are straight-through; detection, status, RANSAC and setMask stay
            discrete masks. The outputs equal the 8-bit path's bit for bit. See
            ``docs/differentiability.md``.
        grad_mode: differentiable only: LK's gradient, ``"implicit"`` (default: implicit-function
            gradient of the converged level-0 solution, zero for lost lanes, memory independent of
            the iterations) or ``"unrolled"`` (through every iteration).
        lk_backend: the pyramid's and the LK's kernels: None / ``"auto"`` (default: the device's
            ``_tuning`` strategy: the fused kernels on the CPU and CUDA, one custom op each, status
            and positions bit-identical to OpenCV's ``calcOpticalFlowPyrLK``), ``"fused"`` (an error
            where they cannot run) or ``"tensor"`` (the tensor kernels). Resolved once here
            (``self.lk_backend``); checkpoints record it (``state_dict``). ``docs/kernels.md``.
        clahe_backend: CLAHE's kernel (mono with ``equalize``): None / ``"auto"`` (default: the
            device's ``_tuning`` strategy: the one fused op ``torch_frontend::clahe`` on the CPU and
            CUDA), ``"fused"`` (an error where it cannot run) or ``"tensor"`` (``equalize``'s tensor
            CLAHE). Both give OpenCV's bits. Resolved once here (``self.clahe_backend``).
        corner_backend: goodFeaturesToTrack's kernels, as ``lk_backend``: None / ``"auto"``
            (default: the fused op on the CPU and CUDA), ``"fused"`` or ``"tensor"``; the same
            corners either way (``self.corner_backend``; ``docs/kernels.md``, "Detection").
        lift_backend: the PINHOLE camera's lift, as ``lk_backend``: None / ``"auto"`` (default: the
            fused op ``torch_frontend::pinhole_lift`` on the CPU and CUDA), ``"fused"`` or ``"tensor"``;
            the same bits either way; other models and the differentiable step lift with the tensor
            path (``self.lift_backend``; ``docs/kernels.md``, "The PINHOLE lift").

    ``track(images, timestamps)`` takes ``images (B, 1, H, W)`` (uint8 or float 0..255; ``(B, H, W)``
    accepted) and ``timestamps`` a ``(B,)`` float64 tensor or sequence of seconds, and returns a
    :class:`FeatureFrame`. Integer tensors and arrays (EuRoC's int64 nanoseconds, milliseconds)
    are refused with a ``ValueError`` naming the likely unit; a mono stream whose last 3 steps each
    restarted its clock (more than 1 s, or backwards: seconds that are really ns or ms) warns once
    (``UserWarning``) naming those steps; only timestamps on the host are watched (a CUDA tensor
    is not read, so the step stays free of host syncs). Image size: mono requires ``H, W`` = the config's ``image_height``,
    ``image_width`` (``ValueError`` otherwise); fusion tracks each image at its real size, as
    VINS-Fusion does (spec §6.2: the config's size is the estimator's), so any size works as long
    as consecutive images keep one. ``step(state, ...)`` is the same without touching ``self.state``.
    """

    def __init__(
        self,
        config: Union[TrackerConfig, str, Sequence[Union[TrackerConfig, str]]],
        num_streams: Optional[int] = None,
        device: Union[str, torch.device] = "cpu",
        mode: str = "mono",
        dtype: torch.dtype = torch.float32,
        fisheye_mask=None,
        seed: int = 0,
        capturable: Optional[bool] = None,
        lk_iter_budget=None,
        lk_tail_share: int = 8,
        differentiable: bool = False,
        grad_mode: str = "implicit",
        lk_backend: Optional[str] = None,
        clahe_backend: Optional[str] = None,
        corner_backend: Optional[str] = None,
        lift_backend: Optional[str] = None,
    ):
        configs = stream_configs(config, num_streams)  # B configs; one given is every stream's
        for c in configs:
            if c.camera is None:
                raise ValueError(f"config {c.path}: has no camera; the tracker needs one")
        self.configs: Tuple[TrackerConfig, ...] = tuple(configs)
        self.B = len(configs)
        self.device = check_device(device)  # a ValueError naming it and what is available
        self.dtype = dtype
        if capturable is None:
            capturable = self.device.type != "cpu"
        self.capturable = bool(capturable)
        self.differentiable = bool(differentiable)
        masks = self._stream_masks(fisheye_mask)
        #: the pyramid's and the LK's kernels, ``"fused"`` or ``"tensor"`` (resolved for this device)
        self.lk_backend = resolve_backend(lk_backend, self.device)
        #: CLAHE's kernel, ``"fused"`` or ``"tensor"`` (resolved for this device; the same bits)
        self.clahe_backend = resolve_clahe_backend(clahe_backend, self.device)
        resolve_ransac_backend(None, self.device)  # the RANSAC op's probe (CUDA: its self-check) here, outside any capture
        #: goodFeaturesToTrack's kernels, ``"fused"`` or ``"tensor"`` (resolved; the same corners)
        self.corner_backend = resolve_corner_backend(corner_backend, self.device)
        #: the PINHOLE lift's kernel, ``"fused"`` or ``"tensor"`` (resolved; the same bits)
        self.lift_backend = _fused.resolve_lift_backend(lift_backend, self.device)
        options = dict(mode=mode, seed=int(seed), capturable=self.capturable, lk_iter_budget=lk_iter_budget,
                       lk_tail_share=lk_tail_share, differentiable=self.differentiable, lk_grad_mode=grad_mode,
                       lk_backend=self.lk_backend, clahe_backend=self.clahe_backend,
                       corner_backend=self.corner_backend, lift_backend=self.lift_backend)
        built: Dict[Tuple[int, int], TrackerParams] = {}
        for b, c in enumerate(configs):
            if (id(c), id(masks[b])) not in built:
                try:
                    built[id(c), id(masks[b])] = TrackerParams.from_config(c, fisheye_mask=masks[b], **options)
                except ValueError as exc:
                    raise ValueError(f"config {c.path}: {exc}") from None
        groups = partition([group_key(built[id(c), id(masks[b])], masks[b]) for b, c in enumerate(configs)])
        self._groups: Optional[Tuple[StreamGroup, ...]] = None
        self._members: Tuple[FeatureTracker, ...] = ()
        self._stage = _StageTimer()
        self._compiled: Optional[_CompiledStep] = None
        if len(groups) > 1:
            # per-stream configs: one homogeneous tracker per group of equal configs (tracker.streams)
            kwargs = dict(device=self.device, mode=mode, dtype=dtype, seed=seed, capturable=self.capturable,
                          lk_iter_budget=lk_iter_budget, lk_tail_share=lk_tail_share,
                          differentiable=self.differentiable, grad_mode=grad_mode, lk_backend=self.lk_backend,
                          clahe_backend=self.clahe_backend, corner_backend=self.corner_backend,
                          lift_backend=self.lift_backend)
            self._groups = tuple(groups)
            self._members = tuple(FeatureTracker(configs[g.streams[0]], g.size, fisheye_mask=masks[g.streams[0]],
                                                 **kwargs) for g in groups)
            for g, m in zip(groups, self._members):
                m._use_stream_configs([configs[b] for b in g.streams])
            inv = inverse_order(groups)
            self._inverse = None if inv is None else torch.tensor(inv, dtype=torch.int64, device=self.device)
            self._params = None
            self._restarts = None
            self.state = self.initial_state()
            return
        self._params = built[id(configs[0]), id(masks[0])].to(self.device)
        # mono: warns once per stream when its timestamps restart the clock at every step (clock.RestartWatch)
        self._restarts = RestartWatch(self.B, self.params.restart_gap) if self.params.mode == "mono" else None
        self._use_stream_configs(configs)
        self.reset()

    def _use_stream_configs(self, configs: Sequence[TrackerConfig]) -> None:
        """The streams' own configs (one group: equal settings and camera models): their cameras,
        one :class:`~torch_frontend.camera.CameraBatch` where the calibrations differ."""
        self.configs = tuple(configs)
        cam, cam1 = stream_cameras([c.camera for c in configs]), stream_cameras([c.camera1 for c in configs])
        if cam is not configs[0].camera or cam1 is not configs[0].camera1:
            self._params = dataclasses.replace(self._params, camera=cam, camera1=cam1).to(self.device)

    def _stream_masks(self, fisheye_mask) -> List[Optional[torch.Tensor]]:
        """``fisheye_mask`` per stream: None, one ``(H, W)`` mask for every stream, or a sequence of B
        (None entries: the analytic disc)."""
        if isinstance(fisheye_mask, (list, tuple)):
            if len(fisheye_mask) != self.B:
                raise ValueError(f"fisheye_mask: expected one mask (or None) per stream, {self.B}, got "
                                 f"{len(fisheye_mask)}")
            return list(fisheye_mask)
        return [fisheye_mask] * self.B

    # ------------------------------------------------------------------ per-stream configs
    @property
    def mixed(self) -> bool:
        """The streams have different configs (cameras, sizes or VINS keys): the step runs one
        homogeneous sub-step per group of equal configs (``tracker.streams``)."""
        return self._groups is not None

    @property
    def groups(self) -> Tuple[Tuple[Tuple[int, ...], FeatureTracker], ...]:
        """``((streams, tracker), ...)``: each group's streams (global indices) and its homogeneous
        tracker; one group of every stream (this tracker) when the configs are one."""
        if self._groups is None:
            return ((tuple(range(self.B)), self),)
        return tuple((g.streams, m) for g, m in zip(self._groups, self._members))

    def _locate(self, stream: int) -> Tuple[FeatureTracker, int]:
        for streams, member in self.groups:
            if stream in streams:
                return member, streams.index(stream)
        raise ValueError(f"stream: expected 0 <= stream < {self.B}, got {stream}")

    def stream_params(self, stream: int) -> TrackerParams:
        """Stream ``stream``'s :class:`TrackerParams` (its camera, size and VINS keys)."""
        if not 0 <= stream < self.B:
            raise ValueError(f"stream: expected 0 <= stream < {self.B}, got {stream}")
        return self._locate(stream)[0].params

    @property
    def params(self) -> TrackerParams:
        """The streams' :class:`TrackerParams` (one config for all); a mixed tracker has one per
        stream: :meth:`stream_params`."""
        if self._groups is not None:
            raise AttributeError("params: this tracker has per-stream configs "
                                 f"({len(self._groups)} groups); use tracker.stream_params(b)")
        return self._params

    @params.setter
    def params(self, value: TrackerParams) -> None:
        if self._groups is not None:
            raise AttributeError("params: a tracker with per-stream configs has no single params to set")
        self._params = value

    @property
    def config(self) -> TrackerConfig:
        """The streams' config (one for all); a tracker of per-stream configs (a mixed one, or one
        with per-stream calibrations) has one per stream: ``configs[b]``."""
        first = self.configs[0]
        if self._groups is not None or any(c is not first for c in self.configs[1:]) and \
                getattr(self.params, "camera", None) is not first.camera:
            raise AttributeError("config: this tracker has per-stream configs; use tracker.configs[b]")
        return first

    # ------------------------------------------------------------------ read-only views
    @property
    def mode(self) -> str:
        return self._members[0].mode if self._groups is not None else self.params.mode

    @property
    def K(self) -> int:
        """Slots per stream: the (largest) ``max_cnt``; a stream with a smaller one never fills more."""
        if self._groups is not None:
            return max(m.K for m in self._members)
        return self.params.max_cnt

    @property
    def camera(self):
        """The streams' camera 0 (one config); a mixed tracker: :attr:`cameras`."""
        if self._groups is not None:
            raise AttributeError("camera: this tracker has per-stream cameras; use tracker.cameras[b]")
        return self.params.camera

    @property
    def camera1(self):
        if self._groups is not None:
            raise AttributeError("camera1: this tracker has per-stream cameras; use tracker.cameras1[b]")
        return self.params.camera1

    @property
    def cameras(self) -> Tuple:
        """Every stream's camera 0 (stream b's model; streams of one group share one object)."""
        return tuple(self.stream_params(b).camera for b in range(self.B))

    @property
    def cameras1(self) -> Tuple:
        """Every stream's camera 1 (None where a stream has no stereo camera)."""
        return tuple(self.stream_params(b).camera1 for b in range(self.B))

    @property
    def stage_times(self) -> Optional[Dict[str, float]]:
        """Seconds spent per stage since ``enable_stage_times()`` (None when disabled; a mixed
        tracker: summed over its groups)."""
        if self._groups is not None:
            parts = [m.stage_times for m in self._members]
            if parts[0] is None:
                return None
            total: Dict[str, float] = {}
            for part in parts:
                for k, v in part.items():
                    total[k] = total.get(k, 0.0) + v
            return total
        return self._stage.times

    def enable_stage_times(self, enabled: bool = True) -> None:
        """Start (or stop) accumulating per-stage wall-clock times (CLAHE, pyramid, LK, RANSAC,
        mask, detection, undistort) into ``stage_times``; on the CPU a mono step's CLAHE, pyramid and
        LK after the first frame are one op, timed as ``"front"``."""
        for m in self._members:
            m.enable_stage_times(enabled)
        self._stage.times = {} if enabled else None

    def compile(self, enable: bool = True, *, fallback: bool = True, regions: Optional[bool] = None,
                **compile_kwargs) -> None:
        """Compile the step with ``torch.compile`` (``enable=False``: back to eager).

        With ``capturable=True`` the step after the input checks is compiled with
        ``fullgraph=True`` (on CUDA ``mode="reduce-overhead"``, i.e. CUDA graphs: launches are
        replayed, not issued one by one); ``compile_kwargs`` (``mode``, ``backend``, ``dynamic``,
        ...) override those defaults. Mono runs one step variant per publish plan (track only, every
        stream, a sub-batch of 1, 2, 4, ... publishing streams: ``clock.publish_plan``), each first
        run as one eager step (which fills the package's caches: a cache miss cannot be built
        inside a trace). ``regions`` says what is compiled:

        * ``False`` (the default on CUDA): each variant's whole step, one graph (one CUDA graph per
          variant), compiled when a step first needs it.
        * ``True`` (the default on the CPU; mono only, fusion compiles its one step whole): the
          step's three parts (clock + CLAHE + pyramid + LK, the publish stages per sub-batch size,
          undistortion + ids + the new state), each compiled once and shared by every variant that
          runs it, with the few host-side choices between them in eager Python. A mono run compiles
          the LK once instead of once per variant: on the CPU backend (inductor, a cold cache,
          this 2-core machine, 2026-12-05) a mono EuRoC run's first three steps took 214 + 4 + 59 s,
          where the three whole-step variants took 245 + 197 + 296 s (4.6 min in all instead of
          12.3; ``benchmarks/compile_time.py [--whole]``). On CUDA this makes three
          CUDA graphs per step: not yet run on a GPU.

        Inductor fuses and reorders float reductions, so a compiled step's values may differ from
        the eager step's in the last bits (measured: identical for the first three EuRoC sample
        frames, then drifting); the eager capturable step is the one pinned bit for bit to the CPU
        path. With ``fallback`` (default) a step that fails to compile warns once and runs eager
        from then on, so a tracker never stops because of the compiler. The outputs of a
        CUDA-graph replay live in the graph's memory pool: the step clones the new state and frame
        out of it, so they stay valid after the next replay.

        With ``capturable=False`` (the CPU-tuned path, whose early exits need the host) only the LK
        iteration kernel is compiled, for this tracker only (its ``params.lk_compile_step``:
        ``LKOptions.compile_step`` with ``compile_kwargs``; other trackers keep theirs). A mixed
        tracker compiles each group's step."""
        if self._groups is not None:
            for m in self._members:
                m.compile(enable, fallback=fallback, regions=regions, **compile_kwargs)
            return
        if not self.capturable:
            self.params = dataclasses.replace(self.params, lk_compile_step=(dict(compile_kwargs) or True) if enable
                                              else False)
            return
        if not enable:
            self._compiled = None
            return
        opts = dict(fullgraph=True)
        if self.device.type == "cuda":
            opts["mode"] = "reduce-overhead"
        opts.update(compile_kwargs)
        if regions is None:  # one CUDA graph per step on a GPU; on the CPU, the compile time
            regions = self.device.type == "cpu"
        prepare_compile()  # the package's assume_constant_result marks, applied before tracing
        # one compiled callable per step variant (PublishPlan), each compiled and captured on first
        # use; or (mono, regions) the step's parts, each compiled once and shared by the variants
        self._compiled = _CompiledStep(functools.partial(torch.compile, **opts), self.device.type == "cuda", fallback,
                                       regions=bool(regions) and self.mode == "mono")

    # ------------------------------------------------------------------ state
    def initial_state(self) -> Union[TrackerState, GroupedState]:
        """The state of B streams that have seen nothing (a mixed tracker: a :class:`GroupedState`)."""
        if self._groups is not None:
            return GroupedState(tuple(m.initial_state() for m in self._members))
        return TrackerState.initial(self.B, self.K, device=self.device, dtype=self.dtype,
                                    fusion=self.mode == "fusion")

    def reset(self) -> None:
        """Forget everything: all streams start again as at construction."""
        for m in self._members:
            m.reset()
        if self._groups is not None:
            self.state = GroupedState(tuple(m.state for m in self._members))
            return
        self.state = self.initial_state()
        self._mirror: Optional[Tuple[weakref.ref, HostClock]] = None
        if self._plans:
            self._remember_clock(self.state, HostClock.initial(self.B))

    def state_dict(self) -> Dict:
        """The tracker's state as plain CPU values with a version field (``tracker.checkpoint``):
        ``torch.save`` it; a tracker of the same config, mode and stream count continues from it
        with :meth:`load_state_dict`, on any device, bit for bit as this one would."""
        from .checkpoint import tracker_state_dict

        return tracker_state_dict(self)

    def load_state_dict(self, state_dict: Dict) -> None:
        """Continue from ``state_dict`` (:meth:`state_dict` of this or another tracker, saved on any
        device). ``ValueError`` naming what differs for another version, mode, stream count or
        config."""
        from .checkpoint import load_tracker_state_dict

        load_tracker_state_dict(self, state_dict)

    # ------------------------------------------------------------------ the clock's host mirror
    @property
    def _plans(self) -> bool:
        """The step's variant is chosen on the host (:meth:`_plan`): mono on the capturable path,
        where the publish-only stages would otherwise run on every stream under masks (the default
        path skips them already, with syncs that cost nothing on the CPU; fusion publishes every
        frame)."""
        return self.capturable and self.mode == "mono"

    def _remember_clock(self, state: TrackerState, host: HostClock) -> None:
        """``host`` (CPU) is the value of ``state.clock``: the next step from ``state`` plans without
        reading the device (a weak reference: a state that is gone is not kept alive)."""
        self._mirror = (weakref.ref(state.clock), host)

    def _host_clock(self, state: TrackerState) -> HostClock:
        """``state.clock`` on the host: the mirror when ``state`` is the one the last step returned
        (or the initial state), else read back from the device (a state from elsewhere, e.g. a
        saved one: one host sync, once; the mirror follows it from then on)."""
        if self._mirror is not None and self._mirror[0]() is state.clock:
            return self._mirror[1]
        return HostClock.of(state.clock)

    def _plan(self, state: TrackerState, t_host: torch.Tensor, active_host: torch.Tensor) -> Tuple[PublishPlan, HostClock]:
        """The step's variant from the host mirror of the clock (``t_host``, ``active_host`` CPU
        tensors; the clock's rules in numpy before the upload: no sync) and the mirror after the step.
        A step that tracks every stream says so in its plan (``every_tracked``)."""
        host, publish, tracked = self._host_clock(state).decide(_host_array(t_host), _host_array(active_host),
                                                                self.params)
        return publish_plan(int(np.count_nonzero(publish)), self.B, bool(tracked.all())), host

    # ------------------------------------------------------------------ the step
    def step(self, state, images, timestamps, right=None, active=None, sizes=None):
        """The pure step with this tracker's params: ``(new_state, frame)``; ``state`` is not changed.

        Args:
            state: a state of this tracker (``initial_state()``, ``self.state`` or a previous result).
            images: ``(B, 1, H, W)`` or ``(B, H, W)``, uint8 or float 0..255; or a list of B images
                ``(H_b, W_b)`` / ``(1, H_b, W_b)``, each stream at its own size (per-stream configs).
            timestamps: ``(B,)`` seconds (float64 tensor or sequence).
            right: fusion stereo only: camera 1's images, tracked left -> right with the same ids
                (the same forms as ``images``).
            active: optional ``(B,)`` bool; a stream with False is left exactly as it was (its
                clock, features and ids do not change), e.g. a sequence that has ended while the
                others go on. Its outputs are empty for this step.
            sizes: with one padded ``images`` tensor, ``(B, 2)`` ``(H_b, W_b)`` per stream (host):
                stream b's image is the top-left ``H_b x W_b`` (``right`` padded alike).

        Capturable mono: the host replays the clock on its own copy (``clock.host_clock_step``) and
        picks the step's variant (``clock.publish_plan``) before the upload, so unpublished frames
        skip rejectWithF, setMask and detection without a sync. Give ``timestamps`` and ``active``
        on the host for that (device tensors are read back: a sync).
        """
        if self._groups is not None or sizes is not None or isinstance(images, (list, tuple)):
            return self._grouped_step(state, images, timestamps, right, active, sizes)
        plan = host = None
        if self._plans:
            # the publish decision on the host, before the upload (timestamps and active given on the
            # device are read back: a sync; host ones cost none)
            # (the step's door below converts the caller's own object again: its upload stays the
            # input upload, one copy, not a copy of a host-side copy)
            plan, host = self._plan(state, check_timestamps(timestamps, self.B, "cpu"),
                                    check_active(active, self.B, "cpu"))
        img, t, arrived, r = check_inputs(state, self.params, images, timestamps, right, active,
                                          config_name=f"the config {self.configs[0].path}")
        if self._restarts is not None:  # host values only: no sync (clock.RestartWatch)
            self._restarts.observe(state, timestamps, active)
        return self._run(state, img, t, arrived, r, plan, host)

    def _run(self, state, img, t, arrived, r, plan, host):
        """The step on checked inputs (the door's outputs) and the host's plan; keeps the mirrors."""
        # CUDA: TF32 off while the step runs (the capturable LK's exact window sums; restored after)
        with exact_float32(self.device):
            if self._compiled is not None:
                new, frame = self._compiled(state, img, t, self.params, r, arrived, plan)
            else:
                new, frame = step_impl(state, img, t, self.params, right=r, active=arrived, stage=self._stage,
                                       plan=plan)
        if host is not None:
            self._remember_clock(new, host)
        if self._restarts is not None:
            self._restarts.follow(new)
        return new, frame

    def _grouped_step(self, state, images, timestamps, right, active, sizes):
        """:meth:`step` of per-stream inputs (a list of images, a padded batch with ``sizes``) or of a
        mixed tracker: the whole batch checked once (each stream against its own config), uploaded
        once, split per group on the device (``tracker.streams``), each group's homogeneous step on
        its rows, the frames merged in stream order."""
        groups = self._groups or (StreamGroup(tuple(range(self.B))),)
        members = self._members or (self,)
        dev = self.device
        imgs, hw = split_images(images, sizes, groups, self.B, device=dev)
        rights = [None] * len(groups) if right is None else \
            split_images(right, sizes, groups, self.B, "right", device=dev)[0]
        for b in range(self.B):  # each stream against its own config (host shapes, no sync)
            p = members[0].params if self._groups is None else self.stream_params(b)
            if p.mode == "mono" and hw[b] != (p.height, p.width):
                name = self.configs[b].path
                raise ValueError(f"images[{b}]: image size {hw[b][1]}x{hw[b][0]} differs from stream {b}'s config "
                                 f"{name}: image_width x image_height = {p.width}x{p.height}")
        if self._groups is None:
            return self.step(state, imgs[0], timestamps, right=rights[0], active=active)
        if not isinstance(state, GroupedState) or len(state.groups) != len(self._members):
            raise ValueError(f"state: expected this tracker's GroupedState of {len(self._members)} stream groups "
                             f"(tracker.initial_state()), got {type(state).__name__}")
        on_host = not (isinstance(timestamps, torch.Tensor) and timestamps.device.type != "cpu")
        act_host = not (isinstance(active, torch.Tensor) and active.device.type != "cpu")
        t_all = check_timestamps(timestamps, self.B, dev)  # checked on the host, one upload
        a_all = check_active(active, self.B, dev)
        need_host = any(m._plans or m._restarts is not None for m in self._members)
        # the host's copies for the groups' plans and restart watches (device ones are read back: a
        # sync, as for a homogeneous tracker given device timestamps)
        t_host = check_timestamps(timestamps, self.B, "cpu") if need_host else None
        a_host = check_active(active, self.B, "cpu") if need_host else None
        news, frames = [], []
        for g, m, s, im, r in zip(self._groups, self._members, state.groups, imgs, rights):
            idx = g.index(dev)
            t_g, a_g = t_all.index_select(0, idx), a_all.index_select(0, idx)
            th = None if t_host is None else t_host[list(g.streams)]
            ah = None if a_host is None else a_host[list(g.streams)]
            plan = host = None
            if m._plans:
                plan, host = m._plan(s, th, ah)
            prev = None if s.prev_pyramid is None else tuple(s.prev_pyramid.levels[0].shape[-2:])
            img = check_images(im, m.params, g.size, dev, size=prev)
            rr = None
            if r is not None:
                if m.mode == "mono":
                    raise ValueError("right: stereo images are only supported with mode='fusion'")
                if m.params.camera1 is None:
                    raise ValueError(f"right: streams {list(g.streams)}: the config {m.configs[0].path} has no "
                                     f"cam1_calib (num_of_cam 2)")
                rr = check_images(r, m.params, g.size, dev, "right", size=tuple(img.shape[-2:]))
            if m._restarts is not None:
                m._restarts.observe(s, th if on_host else t_g, ah if act_host else a_g)
            new, frame = m._run(s, img, t_g, a_g, rr, plan, host)
            news.append(new)
            frames.append(frame)
        return GroupedState(tuple(news)), merge_frames(frames, self._groups, self.K, self._inverse)

    def track(self, images, timestamps, right=None, active=None, sizes=None) -> FeatureFrame:
        """Process one image per stream (see :meth:`step` for the arguments) and keep the new state."""
        self.state, frame = self.step(self.state, images, timestamps, right=right, active=active, sizes=sizes)
        return frame

    # ------------------------------------------------------------------ the estimator's hooks
    def remove(self, stream: int, ids: Sequence[int]) -> None:
        """Drop features by id from one stream (VINS-Fusion ``removeOutliers``)."""
        if not 0 <= stream < self.B:
            raise ValueError(f"stream: expected 0 <= stream < {self.B}, got {stream}")
        if self._groups is not None:
            member, local = self._locate(stream)
            member.state = self.state.groups[self._members.index(member)]
            member.remove(local, ids)
            self.state = GroupedState(tuple(m.state if m is member else s
                                            for m, s in zip(self._members, self.state.groups)))
            return
        drop_ids = torch.as_tensor(list(ids), dtype=torch.int64, device=self.device)
        if drop_ids.numel() == 0:
            return
        table = self.state.features
        hit = (table.ids.unsqueeze(-1) == drop_ids).any(-1)
        hit &= torch.arange(self.B, device=self.device).unsqueeze(-1) == stream
        self.state = self.state.replace(features=remove_features(table, hit))

    def set_prediction(self, ids: torch.Tensor, uv: torch.Tensor, valid: Optional[torch.Tensor] = None) -> None:
        """Predicted pixels for the next frame per id (VINS-Fusion ``setPrediction``).

        ids: (B, M) int64; uv: (B, M, 2) pixels; valid: (B, M) bool. In a stream with at least one
        valid prediction, the next ``track`` starts LK from the predicted pixels (features without
        one from their previous position) with one pyramid level, falling back to plain LK when
        fewer than 10 track; other streams track as usual. Consumed by the next ``track``.
        """
        check_shape(ids, (self.B, "M"), "ids")
        check_shape(uv, (self.B, ids.shape[1], 2), "uv")
        if self._groups is not None:
            news = []
            for g, m, s in zip(self._groups, self._members, self.state.groups):
                idx = g.index(ids.device)
                m.state = s
                m.set_prediction(ids.index_select(0, idx), uv.index_select(0, idx.to(uv.device)),
                                 None if valid is None else valid.index_select(0, idx.to(valid.device)))
                news.append(m.state)
            self.state = GroupedState(tuple(news))
            return
        ids = ids.to(self.device)
        v = torch.ones_like(ids, dtype=torch.bool) if valid is None else valid.to(self.device, torch.bool)
        table, has = set_prediction(self.state.features, ids, uv.to(self.device), v)
        self.state = self.state.replace(features=table, has_prediction=has)


__all__ = ["FeatureTracker"]
