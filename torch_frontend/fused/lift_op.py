"""camodocal's PINHOLE lift as one ``torch.library`` custom op (``docs/kernels.md``, "The PINHOLE lift").

``torch_frontend::pinhole_lift(uv, valid, params, iters) -> xy``: ``tracker.stages.lift_normalised``
of a ``PinholeCamera`` (``liftProjective``: ``m_d``, ``iters`` evaluations of camodocal's recursive
distortion removal, the no-distortion shortcut; then ``(x/z, y/z)`` with ``z = 1``), bit for bit the
tensor ``PinholeCamera._lift_impl`` in float64.

* ``uv``: ``(B, N, 2)`` float32 or float64 pixels ``(u, v)``; ``valid``: ``(B, N)`` bool (invalid
  slots give ``+0.0``); ``params``: ``(B, 8)`` or ``(1, 8)`` (every stream) float64
  ``(k1, k2, p1, p2, fx, fy, cx, cy)``; ``iters``: ``undistort_iters`` (>= 1). Result ``(B, N, 2)``
  normalised undistorted coordinates in ``uv``'s dtype (rounded from float64).
* fake: the output's shape; ``"cpu"``: the numba kernel (:mod:`._numba_lift`) over stream groups;
  ``"cuda"``: one Triton launch (:mod:`._triton_lift`), no host sync, a launch count independent of
  B and of the data. A cuda-labelled tensor without a CUDA runtime (``count_step.py``'s simulated
  device) runs the CPU kernel, as the other ops.

No autograd formula: the differentiable tracker lifts with the tensor path (:func:`pinhole_of` is the
door's test; ``lift_normalised`` calls the op only where no gradient is asked for).
"""

from __future__ import annotations

from typing import Optional

import torch

from .ops import _np, _np_out, _run_groups

__all__ = ["pinhole_lift_op", "check_lift_args", "pinhole_of", "pinhole_params", "cuda_selfcheck",
           "PARAM_NAMES"]

Tensor = torch.Tensor

#: the row layout of ``params``: ``PinholeCamera.param_names``
PARAM_NAMES = ("k1", "k2", "p1", "p2", "fx", "fy", "cx", "cy")

torch.library.define("torch_frontend::pinhole_lift", "(Tensor uv, Tensor valid, Tensor params, int iters) -> Tensor")


def check_lift_args(uv: Tensor, valid: Tensor, params: Tensor, iters: int) -> None:
    """``ValueError`` naming the argument unless the shapes / dtypes are the op's (module docstring)."""
    name = "torch_frontend::pinhole_lift"
    if uv.dim() != 3 or uv.shape[-1] != 2 or uv.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name}: uv must be a (B, N, 2) float32/float64 tensor, got {tuple(uv.shape)} {uv.dtype}")
    if valid.dtype != torch.bool or tuple(valid.shape) != tuple(uv.shape[:2]):
        raise ValueError(f"{name}: valid must be a {tuple(uv.shape[:2])} bool tensor, got {tuple(valid.shape)} "
                         f"{valid.dtype}")
    if params.dim() != 2 or params.shape[1] != 8 or params.dtype != torch.float64 or \
            params.shape[0] not in (1, uv.shape[0]):
        raise ValueError(f"{name}: params must be a (1, 8) or ({uv.shape[0]}, 8) float64 tensor "
                         f"(k1, k2, p1, p2, fx, fy, cx, cy), got {tuple(params.shape)} {params.dtype}")
    if iters < 1:
        raise ValueError(f"{name}: iters must be >= 1, got {iters}")


@torch.library.impl("torch_frontend::pinhole_lift", "cpu")
def _lift_cpu(uv: Tensor, valid: Tensor, params: Tensor, iters: int) -> Tensor:
    from ._numba_lift import lift_streams

    check_lift_args(uv, valid, params, iters)
    out = torch.empty(uv.shape, dtype=uv.dtype, device=uv.device)
    B = int(uv.shape[0])
    if out.numel() == 0:
        return out
    a, m, p, o = _np(uv.contiguous()), _np(valid.contiguous()), _np(params.contiguous()), _np_out(out)
    _run_groups(lambda s0, s1: lift_streams(a, m, p, int(iters), o, s0, s1), B)
    return out


@torch.library.register_fake("torch_frontend::pinhole_lift")
def _lift_fake(uv, valid, params, iters):
    return uv.new_empty(uv.shape)


@torch.library.impl("torch_frontend::pinhole_lift", "cuda")
def _lift_cuda(uv, valid, params, iters):
    from ._triton_lift import pinhole_lift_cuda

    check_lift_args(uv, valid, params, iters)
    return pinhole_lift_cuda(uv.contiguous(), valid.contiguous(), params.contiguous(), iters)


#: the op (``torch.ops.torch_frontend.pinhole_lift``): ``pinhole_lift_op(uv, valid, params, iters)``
pinhole_lift_op = torch.ops.torch_frontend.pinhole_lift


# ----------------------------------------------------------------------------------- the door
def pinhole_of(camera) -> Optional[int]:
    """``undistort_iters`` when ``camera`` lifts with camodocal's PINHOLE ``_lift_impl`` (a
    ``PinholeCamera``, a one-model ``CameraBatch`` of them, or its ``index_streams`` rows), else None
    (other models, mixed batches, subclasses with their own ``_lift_impl``: the tensor path)."""
    from ..camera.batch import CameraBatch, _StreamRows
    from ..camera.pinhole import PinholeCamera

    if isinstance(camera, _StreamRows):
        camera = camera.batch
    if isinstance(camera, CameraBatch):
        if camera.model is None:
            return None
        camera = camera._impl[0]
    if not isinstance(camera, PinholeCamera) or type(camera)._lift_impl is not PinholeCamera._lift_impl:
        return None
    return int(camera.undistort_iters)


def pinhole_params(camera, like: Tensor) -> Tensor:
    """``params (n, 8)`` float64 on ``like``'s device for the op, from a camera :func:`pinhole_of`
    accepts: a single camera's values (``n = 1``), a batch's rows (``n = B``, checked against
    ``like (B, ...)``) or an ``index_streams`` sub-batch's rows. The values ``_params_like`` gives
    (a cast to float64 is exact), in one ``stack`` (plus one ``index_select`` for a sub-batch)
    instead of a cast and a reshape per parameter."""
    from ..camera.batch import CameraBatch, _StreamRows

    rows = None
    if isinstance(camera, _StreamRows):
        camera, rows = camera.batch, camera.rows
    P = torch.stack([getattr(camera, n) for n in PARAM_NAMES], -1)  # (8,) or (B, 8)
    if P.dim() == 1:
        P = P.unsqueeze(0)
    if rows is not None:
        P = P.index_select(0, rows.to(P.device))
    elif isinstance(camera, CameraBatch):
        camera._check_streams(like, "points")
    return P.to(device=like.device, dtype=torch.float64)


# ----------------------------------------------------------------------------------- self-check
def selfcheck_case(seed: int = 3):
    """A small built-in case (CPU): 2 streams, 40 points each (EuRoC-like and strongly distorted
    parameters, invalid slots, float32 points)."""
    g = torch.Generator().manual_seed(seed)
    uv = (torch.rand((2, 40, 2), generator=g, dtype=torch.float64) * torch.tensor([752.0, 480.0],
                                                                                 dtype=torch.float64)).float()
    valid = torch.rand((2, 40), generator=g) < 0.8
    params = torch.tensor([[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 458.654, 457.296, 367.215, 248.375],
                           [-0.6, 0.4, 0.01, -0.02, 300.0, 310.0, 370.0, 240.0]], dtype=torch.float64)
    return uv, valid, params, 8


def cuda_selfcheck(device: str = "cuda") -> Optional[str]:
    """None when the CUDA kernel gives the CPU kernel's bits on :func:`selfcheck_case` (float32 and
    float64 points), else why not (run once, outside any capture)."""
    try:
        uv, valid, params, iters = selfcheck_case()
        for x in (uv, uv.double()):
            ref = pinhole_lift_op(x, valid, params, iters)
            got = pinhole_lift_op(x.to(device), valid.to(device), params.to(device), iters)
            if not torch.equal(ref, got.cpu()):
                return "the CUDA lift kernel gives other bits than the CPU kernel on the built-in case"
    except Exception as e:  # noqa: BLE001 - any failure: the tensor lift runs
        return f"the CUDA lift kernel failed its self-check ({type(e).__name__}: {e})"
    return None
