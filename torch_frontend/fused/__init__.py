"""The fused-kernel layer: OpenCV's pyramid and pyramidal LK each as one custom op (``docs/kernels.md``).

Eager tensor ops write every intermediate to memory; an iterative per-point stage such as the LK's
iterations is then bound by op launches and memory passes, and its float sums are taken in another
order than OpenCV's. Here each stage is one ``torch.library.custom_op`` (:mod:`.ops`) with a CPU
kernel in numba (:mod:`._numba_lk`, :mod:`._numba_pyramid`: OpenCV's x86 arithmetic line by line,
bit-identical to ``cv2.calcOpticalFlowPyrLK``) and a CUDA kernel in Triton (:mod:`._triton_lk`,
:mod:`._triton_pyramid`: the same lane-by-lane contract); the tensor kernels (``lk/``, ``pyramid``)
stay as the readable reference, the fallback and the differentiable (``grad_mode="unrolled"``) path.

Which LK a device runs is a ``_tuning`` strategy (``Strategy.lk_backend``: ``"fused"`` on the CPU
and CUDA, ``"tensor"`` elsewhere), overridden per call (``track_lk(lk_backend=...)``) or per tracker
(``FeatureTracker(..., lk_backend=...)``); :func:`resolve_backend` turns a request into the backend
used. The fused LK covers OpenCV's 8-bit fixed-point setting (``fixed_point``, float32 points, the
full iteration count, windows at least 8 pixels wide); other settings run the tensor LK.

Availability: the CPU kernels need numba (a core dependency; if it cannot load, the tensor LK runs
and one warning says why); CUDA needs Triton and passes a self-check against stored bits first
(:mod:`.selfcheck`, run outside any capture). A cuda-labelled tensor without a CUDA runtime (the
simulated device of ``count_step.py``, fake tensors) runs the op through its CPU kernel.
"""

from __future__ import annotations

import importlib
import threading
import warnings
from typing import Optional

import torch

from ..errors import ConfigError
from .layout import DEFAULT_PAD, PyramidLayout, lk_pad

__all__ = ["BACKENDS", "PyramidLayout", "DEFAULT_PAD", "lk_pad", "resolve_backend", "unavailable_reason",
           "MIN_FUSED_WIDTH", "resolve_clahe_backend", "clahe_unavailable_reason", "resolve_ransac_backend",
           "resolve_corner_backend", "resolve_lift_backend", "stage_unavailable_reason"]

#: the LK backends a caller may ask for (``None`` / ``"auto"``: the device's strategy)
BACKENDS = ("auto", "fused", "tensor")

#: the fused LK's narrowest window: its kernels read window rows in 8-pixel blocks
MIN_FUSED_WIDTH = 8

_LOCK = threading.Lock()
_STATUS: dict = {}   # device kind -> None (available) or why not; filled once per kind
_WARNED: set = set()


def _probe(kind: str) -> Optional[str]:
    if kind == "cpu":
        try:
            import numba  # noqa: F401

            from . import _numba_lk, _numba_mask, _numba_pyramid  # noqa: F401
        except Exception as e:  # noqa: BLE001 - any import failure means: use the tensor LK
            return f"numba cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        return None
    if kind == "cuda":
        if not torch.cuda.is_available():
            return None  # cuda-labelled tensors without a runtime (simulated device, fakes): the CPU kernel runs
        try:
            import triton  # noqa: F401

            from . import _triton_lk, _triton_mask, _triton_pyramid  # noqa: F401
        except Exception as e:  # noqa: BLE001
            return f"Triton cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        from .selfcheck import cuda_selfcheck

        return cuda_selfcheck()
    return f"no fused kernel for device type {kind!r}"


def unavailable_reason(device) -> Optional[str]:
    """Why the fused kernels cannot run on ``device`` (a ``torch.device`` or string), or None when they
    can. Probed once per device type (CUDA: Triton importable and the self-check passed)."""
    kind = torch.device(device).type
    with _LOCK:
        if kind in _STATUS:
            return _STATUS[kind]
    why = _probe(kind)
    with _LOCK:
        _STATUS.setdefault(kind, why)
        return _STATUS[kind]


def warn_once(message: str) -> None:
    """``warnings.warn(message)`` the first time this message is seen in the process."""
    with _LOCK:
        if message in _WARNED:
            return
        _WARNED.add(message)
    warnings.warn(message, RuntimeWarning, stacklevel=3)


def resolve_backend(requested: Optional[str], device) -> str:
    """The LK backend (``"fused"`` or ``"tensor"``) a call on ``device`` runs for ``requested``:
    ``None`` / ``"auto"``: the device's ``_tuning`` strategy, falling back to the tensor LK with one
    warning when the fused kernels cannot run there; ``"fused"``: the fused kernels or a
    ``ConfigError`` saying why not; ``"tensor"``: the tensor LK."""
    return _resolve("lk", requested, device)


# ---------------------------------------------------------------------------------------------
# The other fused stages: one mechanism. A stage runs fused where the fused kernels can
# (:func:`unavailable_reason`, the LK's answer, never cached again) and its own modules load (and, on
# a CUDA runtime, its own self-check passes): that second answer is cached per (stage, device type)
# in ``_STATUS``. CLAHE's and setMask's CUDA kernels are in the LK's self-check (selfcheck.EXPECTED).

#: stage -> (its backend's parameter and Strategy field, what messages call it, what runs instead,
#: CPU modules, CUDA modules, the CUDA self-check as "module:function" or None)
_STAGES = {
    "lk": ("lk_backend", "LK",
           "the tensor LK runs instead (the same results up to OpenCV's float summation order, docs/kernels.md)",
           (), (), None),
    "clahe": ("clahe_backend", "CLAHE", "the tensor CLAHE runs instead (the same bits, docs/kernels.md)",
              ("_numba_clahe", "clahe_op"), ("_triton_clahe", "clahe_op"), None),
    "ransac": ("ransac_backend", "RANSAC scoring", "the tensor scoring runs instead (docs/kernels.md)",
               ("_numba_ransac", "ransac_op"), ("_triton_ransac", "ransac_op"), "ransac_op:cuda_selfcheck"),
    "corners": ("corner_backend", "detection", "the tensor path runs instead (the same corners, docs/kernels.md)",
                ("_numba_corners", "corners_op"), ("_triton_corners", "corners_op"), "selfcheck:corners_selfcheck"),
    "lift": ("lift_backend", "PINHOLE lift", "the tensor lift runs instead (the same bits, docs/kernels.md)",
             ("_numba_lift", "lift_op"), ("_triton_lift", "lift_op"), "lift_op:cuda_selfcheck"),
}


def _probe_stage(stage: str, kind: str) -> Optional[str]:
    _, _, _, cpu_modules, cuda_modules, check = _STAGES[stage]
    try:
        for name in cpu_modules if kind == "cpu" else cuda_modules:
            importlib.import_module(f".{name}", __name__)
    except Exception as e:  # noqa: BLE001 - any import failure means: use the tensor path
        lib = "numba" if kind == "cpu" else "Triton"
        return f"{lib} cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
    if kind == "cuda" and check is not None:
        module, function = check.split(":")
        return getattr(importlib.import_module(f".{module}", __name__), function)()
    return None


def stage_unavailable_reason(stage: str, device) -> Optional[str]:
    """Why the fused kernel of ``stage`` (a key of ``_STAGES``) cannot run on ``device``, or None when it
    can: :func:`unavailable_reason`, then the stage's modules and CUDA self-check (probed once per
    device type; a probe inside a CUDA graph capture is an error: resolve before capturing)."""
    kind = torch.device(device).type
    why = unavailable_reason(kind)
    if why is not None or stage == "lk" or not (kind == "cpu" or (kind == "cuda" and torch.cuda.is_available())):
        return why  # cuda-labelled tensors without a runtime (simulated device, fakes): the CPU kernels run
    key = (stage, kind)
    with _LOCK:
        if key in _STATUS:
            return _STATUS[key]
    why = _probe_stage(stage, kind)
    if why is not None and kind == "cuda" and torch.cuda.is_current_stream_capturing():
        raise ConfigError(f"the fused {_STAGES[stage][1]} is resolved on its first call, which must run outside a "
                          f"CUDA graph capture ({why}); make a first call (or build the tracker) before capturing")
    with _LOCK:
        return _STATUS.setdefault(key, why)


def _resolve(stage: str, requested: Optional[str], device) -> str:
    """``resolve_*_backend``'s one body: ``None`` / ``"auto"``: the device's ``_tuning`` strategy, falling
    back to the tensor path with one warning where the fused kernel cannot run; ``"fused"``: the fused
    kernel or a ``ConfigError`` saying why not; ``"tensor"``: the tensor path."""
    from .. import _tuning

    field, label, instead = _STAGES[stage][:3]
    req = "auto" if requested is None else requested
    if req not in BACKENDS:
        raise ConfigError(f"{field} must be one of {BACKENDS} or None, got {requested!r}")
    if req == "tensor":
        return "tensor"
    dev = torch.device(device)
    if req == "auto" and getattr(_tuning.for_device(dev), field) != "fused":
        return "tensor"
    why = stage_unavailable_reason(stage, dev)
    if why is None:
        return "fused"
    if req == "fused":
        raise ConfigError(f"{field}='fused' cannot run on {dev.type}: {why}")
    warn_once(f"torch_frontend: the fused {label} cannot run on {dev.type} ({why}); {instead}")
    return "tensor"


def clahe_unavailable_reason(device) -> Optional[str]:
    """Why the fused CLAHE cannot run on ``device``, or None when it can (:func:`stage_unavailable_reason`)."""
    return stage_unavailable_reason("clahe", device)


def resolve_clahe_backend(requested: Optional[str], device) -> str:
    """The CLAHE backend (``"fused"``: ``torch_frontend::clahe``, or ``"tensor"``: ``equalize``'s tensor
    CLAHE) for ``requested`` on ``device``, as :func:`resolve_backend` (``Strategy.clahe_backend``).
    Both give OpenCV's bits."""
    return _resolve("clahe", requested, device)


def resolve_ransac_backend(requested: Optional[str], device) -> str:
    """The F-RANSAC scoring backend (``"fused"`` or ``"tensor"``) for ``requested`` on ``device``, as
    :func:`resolve_backend` (``Strategy.ransac_backend``). The two give the same inlier masks up to
    OpenCV's float32 rounding of an error at the threshold (docs/kernels.md)."""
    return _resolve("ransac", requested, device)


def resolve_corner_backend(requested: Optional[str], device) -> str:
    """The detection backend (``"fused"``: ``torch_frontend::good_features``, or ``"tensor"``:
    ``corners/``) for ``requested`` on ``device``, as :func:`resolve_backend`
    (``Strategy.corner_backend``); the same corners either way."""
    return _resolve("corners", requested, device)


def resolve_lift_backend(requested: Optional[str], device) -> str:
    """The PINHOLE lift's backend (``"fused"``: ``torch_frontend::pinhole_lift``, or ``"tensor"``: the
    camera's ``_lift_impl``) for ``requested`` on ``device``, as :func:`resolve_backend`
    (``Strategy.lift_backend``). The same bits either way; other camera models always lift with the
    tensor path."""
    return _resolve("lift", requested, device)
