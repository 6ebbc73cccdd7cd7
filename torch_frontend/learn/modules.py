"""``nn.Module`` wrappers for training loops: :class:`LucasKanade` (the LK kernel with its settings)
and :class:`TrackerModule` (the pure tracker step, its cameras as sub-modules).

Convention:
    Modules hold settings and (for the tracker) the camera models; they hold no per-sequence state:
    the tracker's state goes in and out of ``forward`` (``state, frame = module(state, images, t)``),
    so BPTT over frames, ``torch.utils.checkpoint`` and ``torch.func`` see a pure function. ``.to()``,
    ``.double()``, ``state_dict()`` and ``parameters()`` behave as for any module; the cameras'
    parameters are frozen until ``module.camera.requires_grad_()``.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Optional, Union

import torch
from torch import nn

from ..lk import GRAD_MODES, track_lk
from ..tracker import FeatureTracker
from .status import BORDER_TEMPERATURE, PHOTO_SIGMA, soft_status

STATUS_MODES = ("hard", "soft", "straight_through")


class LucasKanade(nn.Module):
    """``cv2.calcOpticalFlowPyrLK`` as a module: :func:`~torch_frontend.track_lk` with fixed settings.

    Args:
        win_size, max_level, max_iters, eps, min_eig_threshold, fixed_point, capturable: as
            :func:`~torch_frontend.track_lk` (OpenCV's defaults, VINS's window).
        grad_mode: ``"implicit"`` (default here: the training setting; memory independent of the
            iterations, zero gradient for lost lanes) or ``"unrolled"``.
        status: ``"hard"`` (LK's bool status), ``"soft"`` or ``"straight_through"`` (a float
            confidence, :func:`~torch_frontend.learn.soft_status`).
        sigma, temperature, border: the soft status' settings.
        early_exit: deprecated (``DeprecationWarning``): ``capturable = not early_exit``.

    ``forward(prev, next, pts, valid=None, init_pts=None) -> (next_pts (B, N, 2), status (B, N))``;
    images ``(B, 1, H, W)`` (uint8 or float 0..255) or pyramids, ``pts`` pixels in ``prev``.
    """

    def __init__(self, win_size: Union[int, tuple] = 21, max_level: int = 3, max_iters: int = 30, eps: float = 0.01,
                 min_eig_threshold: float = 1e-4, *, fixed_point: Optional[bool] = None, capturable: bool = False,
                 grad_mode: str = "implicit", status: str = "hard", sigma: float = PHOTO_SIGMA,
                 temperature: float = BORDER_TEMPERATURE, border: int = 1, early_exit: Optional[bool] = None):
        super().__init__()
        if early_exit is not None:
            warnings.warn("LucasKanade: early_exit is deprecated; use capturable (capturable = not early_exit)",
                          DeprecationWarning, stacklevel=2)
            capturable = not early_exit
        if grad_mode not in GRAD_MODES:
            raise ValueError(f"grad_mode: expected one of {GRAD_MODES}, got {grad_mode!r}")
        if status not in STATUS_MODES:
            raise ValueError(f"status: expected one of {STATUS_MODES}, got {status!r}")
        self.win_size, self.max_level, self.max_iters, self.eps = win_size, int(max_level), int(max_iters), float(eps)
        self.min_eig_threshold, self.fixed_point, self.capturable = float(min_eig_threshold), fixed_point, bool(capturable)
        self.grad_mode, self.status = grad_mode, status
        self.sigma, self.temperature, self.border = float(sigma), float(temperature), int(border)

    def forward(self, prev, next, pts: torch.Tensor, valid: Optional[torch.Tensor] = None,
                init_pts: Optional[torch.Tensor] = None):
        out, st = track_lk(prev, next, pts, valid, self.win_size, self.max_level, self.max_iters, self.eps,
                           self.min_eig_threshold, init_pts, fixed_point=self.fixed_point, capturable=self.capturable,
                           grad_mode=self.grad_mode)
        if self.status == "hard":
            return out, st
        win = self.win_size if isinstance(self.win_size, int) else int(self.win_size[0])
        return out, soft_status(prev, next, pts, out, st, win_size=win, sigma=self.sigma, border=self.border,
                                temperature=self.temperature, mode=self.status)

    def extra_repr(self) -> str:
        return (f"win_size={self.win_size}, max_level={self.max_level}, max_iters={self.max_iters}, eps={self.eps}, "
                f"grad_mode={self.grad_mode!r}, status={self.status!r}")


class TrackerModule(nn.Module):
    """The differentiable tracker step (``FeatureTracker(..., differentiable=True)``) as a module.

    Args:
        config: a ``TrackerConfig`` or the path of a VINS config YAML.
        num_streams: B, the streams of each call.
        mode, dtype, fisheye_mask, seed, capturable: as :class:`~torch_frontend.FeatureTracker`.
        grad_mode: LK's gradient, ``"implicit"`` (default) or ``"unrolled"``.

    ``forward(state, images, timestamps, right=None, active=None) -> (new_state, frame)`` is the
    pure step: ``images (B, 1, H, W)`` float grey levels 0..255 (or uint8), ``timestamps (B,)``
    float64 seconds; ``frame.uv``, ``frame.xy`` and ``frame.velocity`` carry gradients to the
    images of this and earlier steps (through ``state``) and to ``camera``'s parameters once
    ``module.camera.requires_grad_()``. ``initial_state()`` starts B streams;
    ``state.detach()`` cuts the graph (truncated BPTT).

    The camera models are sub-modules (``module.camera``, ``module.camera1`` for stereo), so
    ``state_dict()``, ``parameters()`` and ``.to(device)`` see them; they stay float64 (camodocal's
    double precision) whatever ``.float()`` / ``.half()`` asks. Make a new ``initial_state()``
    after moving the module. Per-stream cameras: a ``camera.CameraBatch`` of B cameras (the
    tracker's own, or set with :meth:`use_camera`) is registered the same way: ``state_dict()``
    holds every stream's parameters, ``camera.fx`` ``(B,)`` (mixed models:
    ``camera.groups.<model>.fx``, ``CameraBatch`` docstring), and stream b's outputs get gradients
    through its own rows only. Per-stream configs (``config`` a sequence of B configs whose
    streams fall into several groups, ``FeatureTracker.groups``): ``module.camera`` is None and
    group i's cameras are ``module.groups[i].camera`` / ``.camera1`` (``state_dict`` keys
    ``groups.<i>.camera.fx``, ...), its streams ``module.group_streams[i]``.
    """

    def __init__(self, config, num_streams: Optional[int] = None, *, mode: str = "mono",
                 dtype: torch.dtype = torch.float32, fisheye_mask: Optional[torch.Tensor] = None, seed: int = 0,
                 capturable: bool = False, grad_mode: str = "implicit", device: Union[str, torch.device] = "cpu"):
        super().__init__()
        tracker = FeatureTracker(config, num_streams, device=device, mode=mode, dtype=dtype,
                                 fisheye_mask=fisheye_mask, seed=seed, capturable=capturable, differentiable=True,
                                 grad_mode=grad_mode)
        object.__setattr__(self, "tracker", tracker)  # a plain attribute: not a module, not in state_dict
        self.group_streams = tuple(streams for streams, _ in tracker.groups)
        if len(self.group_streams) > 1:  # per-stream configs in several groups: each group's cameras
            self.camera = self.camera1 = None
            self.groups = nn.ModuleList(_GroupCameras(m.params.camera, m.params.camera1) for _, m in tracker.groups)
        else:
            self.camera = tracker.params.camera
            self.camera1 = tracker.params.camera1  # None without a stereo camera (registered as absent)

    def _apply(self, fn, *args, **kwargs):
        def keep_float64(t: torch.Tensor) -> torch.Tensor:
            # the cameras stay float64 with their values: a dtype change (.float(), .half(), .to(dtype))
            # moves them only (fn then a cast back would round every parameter to float32)
            if t.is_floating_point():
                probe = fn(t.new_empty(0))
                if probe.dtype != t.dtype:
                    return t.to(device=probe.device)
            return fn(t)

        super()._apply(keep_float64, *args, **kwargs)
        # the cameras' parameters moved in place; the trackers' devices, masks and (float64) cameras follow
        device = next(self.parameters()).device
        t = self.tracker
        t.device = device
        for _, member in t.groups:  # (this tracker itself when its streams share one config)
            member.device = device
            member.params = member.params.to(device)
        inverse = getattr(t, "_inverse", None)  # a mixed tracker's stream order on the device
        if inverse is not None:
            t._inverse = inverse.to(device)
        return self

    def use_camera(self, camera, camera1=None) -> None:
        """Track with ``camera`` (and, fusion stereo, ``camera1``; None keeps the current one): a
        single ``CameraModel`` or a ``camera.CameraBatch`` of ``num_streams`` per-stream cameras
        (e.g. ``CameraBatch.repeat(module.camera, B)`` to learn each stream's intrinsics). It is
        moved to the module's device as float64 (in place, as ``nn.Module.to``) and registered as
        the module's ``camera`` (``state_dict``, ``parameters``). ``ValueError`` when a batch's
        stream count is not the tracker's, or the tracker has several stream groups."""
        t = self.tracker
        if len(self.group_streams) > 1:
            raise ValueError(f"use_camera: this tracker has {len(self.group_streams)} stream groups (per-stream "
                             f"configs); set each group's camera on its tracker (tracker.groups)")
        for name, cam in (("camera", camera), ("camera1", camera1)):
            n = getattr(cam, "num_streams", None)
            if n is not None and n != t.B:
                raise ValueError(f"{name}: a camera batch of {n} streams for a tracker of {t.B} streams")
        camera = camera.to(device=t.device, dtype=torch.float64)
        camera1 = t.params.camera1 if camera1 is None else camera1.to(device=t.device, dtype=torch.float64)
        t.params = dataclasses.replace(t.params, camera=camera, camera1=camera1)  # checks the values
        self.camera, self.camera1 = camera, camera1

    def stream_camera(self, stream: int, camera1: bool = False):
        """``(module, row)``: where stream ``stream``'s camera 0 (``camera1``: camera 1) parameters
        live. A single camera shared by the stream's group: ``(camera, None)`` (its 0-d ``fx`` is
        the stream's); a ``CameraBatch``: its one-model batch and the stream's row
        (``module.fx[row]``)."""
        if not 0 <= stream < self.tracker.B:
            raise ValueError(f"stream: expected 0 <= stream < {self.tracker.B}, got {stream}")
        i = next(i for i, streams in enumerate(self.group_streams) if stream in streams)
        holder = self if len(self.group_streams) == 1 else self.groups[i]
        cam = holder.camera1 if camera1 else holder.camera
        if cam is None:
            return None, None
        if hasattr(cam, "locate"):
            return cam.locate(self.group_streams[i].index(stream))
        return cam, None

    @property
    def num_streams(self) -> int:
        return self.tracker.B

    def initial_state(self):
        """The state of B streams that have seen nothing, on the module's device."""
        return self.tracker.initial_state()

    def forward(self, state, images, timestamps, right=None, active=None):
        return self.tracker.step(state, images, timestamps, right=right, active=active)

    def extra_repr(self) -> str:
        t = self.tracker
        p = t.groups[0][1].params
        return (f"mode={t.mode!r}, num_streams={t.B}, max_cnt={t.K}, grad_mode={p.lk_grad_mode!r}, "
                f"capturable={p.capturable}" + (f", groups={len(self.group_streams)}" if len(self.group_streams) > 1
                                                else ""))


class _GroupCameras(nn.Module):
    """One stream group's cameras as sub-modules (``camera``, ``camera1`` or None) of a
    :class:`TrackerModule` with per-stream configs."""

    def __init__(self, camera, camera1) -> None:
        super().__init__()
        self.camera = camera
        self.camera1 = camera1


__all__ = ["LucasKanade", "TrackerModule", "STATUS_MODES"]
