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

import threading
import warnings
from typing import Optional

import torch

from ..errors import ConfigError
from .layout import DEFAULT_PAD, PyramidLayout, lk_pad

__all__ = ["BACKENDS", "PyramidLayout", "DEFAULT_PAD", "lk_pad", "resolve_backend", "unavailable_reason",
           "MIN_FUSED_WIDTH", "resolve_clahe_backend", "clahe_unavailable_reason", "resolve_ransac_backend",
           "resolve_corner_backend", "resolve_lift_backend"]

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
    from .. import _tuning

    req = "auto" if requested is None else requested
    if req not in BACKENDS:
        raise ConfigError(f"lk_backend must be one of {BACKENDS} or None, got {requested!r}")
    if req == "tensor":
        return "tensor"
    dev = torch.device(device)
    if req == "auto" and _tuning.for_device(dev).lk_backend != "fused":
        return "tensor"
    why = unavailable_reason(dev)
    if why is None:
        return "fused"
    if req == "fused":
        raise ConfigError(f"lk_backend='fused' cannot run on {dev.type}: {why}")
    warn_once(f"torch_frontend: the fused LK cannot run on {dev.type} ({why}); the tensor LK runs instead "
              "(the same results up to OpenCV's float summation order, docs/kernels.md)")
    return "tensor"


# ---------------------------------------------------------------------------------------------
# CLAHE (``fused/clahe_op.py``): its own probe, so that the LK's availability does not hide its modules'

_CLAHE_STATUS: dict = {}  # device kind -> None (available) or why not


def clahe_unavailable_reason(device) -> Optional[str]:
    """Why the fused CLAHE cannot run on ``device``, or None when it can: the fused kernels'
    availability (:func:`unavailable_reason`, not cached again here, so that it stays the one answer),
    then the CLAHE kernels' modules (probed once per device type)."""
    kind = torch.device(device).type
    why = unavailable_reason(device)
    if why is not None or not (kind == "cpu" or (kind == "cuda" and torch.cuda.is_available())):
        return why
    with _LOCK:
        if kind in _CLAHE_STATUS:
            return _CLAHE_STATUS[kind]
    try:
        if kind == "cpu":
            from . import _numba_clahe  # noqa: F401
        else:
            from . import _triton_clahe  # noqa: F401
    except Exception as e:  # noqa: BLE001 - any import failure means: use the tensor CLAHE
        why = f"the CLAHE kernel cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
    with _LOCK:
        _CLAHE_STATUS.setdefault(kind, why)
        return _CLAHE_STATUS[kind]


def resolve_clahe_backend(requested: Optional[str], device) -> str:
    """The CLAHE backend (``"fused"``: ``torch_frontend::clahe``, or ``"tensor"``: ``equalize``'s tensor
    CLAHE) a call on ``device`` runs for ``requested``, as :func:`resolve_backend`: ``None`` / ``"auto"``:
    the device's ``_tuning`` strategy (``Strategy.clahe_backend``), falling back to the tensor CLAHE with
    one warning where the fused kernel cannot run; ``"fused"``: the fused kernel or a ``ConfigError``
    saying why not; ``"tensor"``: the tensor CLAHE. Both give OpenCV's bits."""
    from .. import _tuning

    req = "auto" if requested is None else requested
    if req not in BACKENDS:
        raise ConfigError(f"clahe_backend must be one of {BACKENDS} or None, got {requested!r}")
    if req == "tensor":
        return "tensor"
    dev = torch.device(device)
    if req == "auto" and _tuning.for_device(dev).clahe_backend != "fused":
        return "tensor"
    why = clahe_unavailable_reason(dev)
    if why is None:
        return "fused"
    if req == "fused":
        raise ConfigError(f"clahe_backend='fused' cannot run on {dev.type}: {why}")
    warn_once(f"torch_frontend: the fused CLAHE cannot run on {dev.type} ({why}); the tensor CLAHE runs instead "
              "(the same bits, docs/kernels.md)")
    return "tensor"


# ---------------------------------------------------------------------------------------------
# F-RANSAC's scoring op (fused/ransac_op.py): its own availability (its modules, its CUDA self-check)

_RANSAC_STATUS: dict = {}


def _probe_ransac(kind: str) -> Optional[str]:
    if kind == "cpu":
        try:
            from . import _numba_ransac, ransac_op  # noqa: F401
        except Exception as e:  # noqa: BLE001
            return f"numba cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        return None
    if kind == "cuda":
        if not torch.cuda.is_available():
            return None  # simulated device, fakes: the CPU kernel runs
        try:
            from . import _triton_ransac, ransac_op  # noqa: F401
        except Exception as e:  # noqa: BLE001
            return f"Triton cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        return ransac_op.cuda_selfcheck()
    return f"no fused kernel for device type {kind!r}"


def resolve_ransac_backend(requested: Optional[str], device) -> str:
    """The F-RANSAC scoring backend (``"fused"`` or ``"tensor"``) for ``requested`` on ``device``, as
    :func:`resolve_backend` does for the LK (``Strategy.ransac_backend``; ``"auto"`` falls back with one
    warning, an explicit ``"fused"`` that cannot run is a ``ConfigError``). The two give the same
    inlier masks up to OpenCV's float32 rounding of an error at the threshold (docs/kernels.md)."""
    from .. import _tuning

    req = "auto" if requested is None else requested
    if req not in BACKENDS:
        raise ConfigError(f"ransac_backend must be one of {BACKENDS} or None, got {requested!r}")
    if req == "tensor":
        return "tensor"
    dev = torch.device(device)
    if req == "auto" and _tuning.for_device(dev).ransac_backend != "fused":
        return "tensor"
    with _LOCK:
        known = dev.type in _RANSAC_STATUS
        why = _RANSAC_STATUS.get(dev.type)
    if not known:
        why = _probe_ransac(dev.type)
        capturing = dev.type == "cuda" and torch.cuda.is_available() and torch.cuda.is_current_stream_capturing()
        if capturing and why is not None:  # a self-check cannot run inside a capture: ask again later
            raise ConfigError("the fused RANSAC scoring is resolved on its first call, which must run outside a "
                              f"CUDA graph capture ({why}); make a first call (or build the tracker) before capturing")
        with _LOCK:
            why = _RANSAC_STATUS.setdefault(dev.type, why)
    if why is None:
        return "fused"
    if req == "fused":
        raise ConfigError(f"ransac_backend='fused' cannot run on {dev.type}: {why}")
    warn_once(f"torch_frontend: the fused RANSAC scoring cannot run on {dev.type} ({why}); the tensor scoring "
              "runs instead (docs/kernels.md)")
    return "tensor"


# ---------------------------------------------------------------------------------------------
# detection (``torch_frontend::good_features``, fused/corners_op.py)


def _probe_corners(kind: str) -> Optional[str]:
    if kind == "cpu":
        try:
            from . import _numba_corners, corners_op  # noqa: F401
        except Exception as e:  # noqa: BLE001 - any import failure means: use the tensor path
            return f"numba cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        return None
    if kind == "cuda":
        if not torch.cuda.is_available():
            return None  # the simulated device, fakes: the CPU kernel runs
        try:
            from . import _triton_corners, corners_op  # noqa: F401
        except Exception as e:  # noqa: BLE001
            return f"Triton cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        from .selfcheck import corners_selfcheck

        return corners_selfcheck()
    return f"no fused kernel for device type {kind!r}"


def resolve_corner_backend(requested: Optional[str], device) -> str:
    """The detection backend (``"fused"`` or ``"tensor"``) on ``device`` for ``requested``, with
    :func:`resolve_backend`'s semantics: ``None`` / ``"auto"``: ``_tuning``'s ``corner_backend`` for
    the device, falling back to the tensor path with one warning where the fused op cannot run;
    ``"fused"``: the op or a ``ConfigError`` saying why not; ``"tensor"``: ``corners/``."""
    from .. import _tuning

    req = "auto" if requested is None else requested
    if req not in BACKENDS:
        raise ConfigError(f"corner_backend must be one of {BACKENDS} or None, got {requested!r}")
    if req == "tensor":
        return "tensor"
    dev = torch.device(device)
    if req == "auto" and _tuning.for_device(dev).corner_backend != "fused":
        return "tensor"
    key = ("corners", dev.type)
    with _LOCK:
        known = key in _STATUS
        why = _STATUS.get(key)
    if not known:
        why = _probe_corners(dev.type)
        with _LOCK:
            why = _STATUS.setdefault(key, why)
    if why is None:
        return "fused"
    if req == "fused":
        raise ConfigError(f"corner_backend='fused' cannot run on {dev.type}: {why}")
    warn_once(f"torch_frontend: the fused detection cannot run on {dev.type} ({why}); the tensor path runs "
              "instead (the same corners, docs/kernels.md)")
    return "tensor"


# ---------------------------------------------------------------------------------------------
# the PINHOLE lift (``torch_frontend::pinhole_lift``, fused/lift_op.py)


def _probe_lift(kind: str) -> Optional[str]:
    if kind == "cpu":
        try:
            from . import _numba_lift, lift_op  # noqa: F401
        except Exception as e:  # noqa: BLE001 - any import failure means: use the tensor lift
            return f"numba cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        return None
    if kind == "cuda":
        if not torch.cuda.is_available():
            return None  # the simulated device, fakes: the CPU kernel runs
        try:
            from . import _triton_lift, lift_op  # noqa: F401
        except Exception as e:  # noqa: BLE001
            return f"Triton cannot be loaded ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
        return lift_op.cuda_selfcheck()
    return f"no fused kernel for device type {kind!r}"


def resolve_lift_backend(requested: Optional[str], device) -> str:
    """The PINHOLE lift's backend (``"fused"``: ``torch_frontend::pinhole_lift``, or ``"tensor"``: the
    camera's ``_lift_impl``) on ``device`` for ``requested``, with :func:`resolve_backend`'s semantics
    (``Strategy.lift_backend``; ``"auto"`` falls back with one warning, an explicit ``"fused"`` that
    cannot run is a ``ConfigError``). The same bits either way; other camera models always lift with
    the tensor path."""
    from .. import _tuning

    req = "auto" if requested is None else requested
    if req not in BACKENDS:
        raise ConfigError(f"lift_backend must be one of {BACKENDS} or None, got {requested!r}")
    if req == "tensor":
        return "tensor"
    dev = torch.device(device)
    if req == "auto" and getattr(_tuning.for_device(dev), "lift_backend", "tensor") != "fused":
        return "tensor"
    key = ("lift", dev.type)
    with _LOCK:
        known = key in _STATUS
        why = _STATUS.get(key)
    if not known:
        why = _probe_lift(dev.type)
        with _LOCK:
            why = _STATUS.setdefault(key, why)
    if why is None:
        return "fused"
    if req == "fused":
        raise ConfigError(f"lift_backend='fused' cannot run on {dev.type}: {why}")
    warn_once(f"torch_frontend: the fused PINHOLE lift cannot run on {dev.type} ({why}); the tensor lift runs "
              "instead (the same bits, docs/kernels.md)")
    return "tensor"
