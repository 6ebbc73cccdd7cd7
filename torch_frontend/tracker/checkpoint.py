"""``FeatureTracker.state_dict`` / ``load_state_dict``: a tracker's state as plain, device-free
values, and back (what a checkpoint of a long run keeps, ``pipelines.checkpoint``).

Convention:
    The state (``tracker.state``) is serialised as a pytree, whatever its structure: the leaves of
    ``torch.utils._pytree.tree_flatten(state)`` (tensors moved to the CPU, detached; other leaves
    as they are) and the tree's ``treespec_dumps`` text. So a state made of several sub-states
    (one per stream group) needs nothing here. Host-side pieces are kept as plain values: the
    ``RestartWatch`` (mono's warning about restarting timestamps: what it has seen, which streams
    it warned). The clock's host mirror (capturable mono) is not kept: it is, by definition, the
    state's clock, read back once by the first step after loading.

    The dict: ``version`` (:data:`STATE_DICT_VERSION`), ``kind``, ``mode``, ``num_streams``,
    ``capacity`` (``max_cnt``), ``dtype``, ``lk_backend`` (the resolved pyramid / LK kernels: a tracker
    with others refuses the dict), ``config`` (:func:`config_fingerprint`), ``treespec``,
    ``leaves``, ``restarts`` (None for fusion). Every value is a tensor, a string, a number, None
    or a list / dict of those: ``torch.save`` it and ``torch.load(..., weights_only=True,
    map_location="cpu")`` reads it on any machine (saved on CUDA, loaded on the CPU).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, List

import numpy as np
import torch
import torch.utils._pytree as pytree

__all__ = ["STATE_DICT_VERSION", "config_fingerprint", "load_tracker_state_dict", "tracker_state_dict"]

#: the format of :func:`tracker_state_dict`; a dict of another version is refused
STATE_DICT_VERSION = 1
_KIND = "torch_frontend.FeatureTracker"
# config fields that name files (and where the settings came from), not settings: a config moved
# elsewhere is the same config
_CONFIG_PATHS = ("path", "raw", "cam0_calib", "cam1_calib", "origin")


def _plain(v: Any) -> str:
    """A config value as a short exact string (floats by ``repr``: equal strings, equal values)."""
    return repr(v.tolist() if isinstance(v, np.ndarray) else v)


def config_fingerprint(config) -> Dict[str, str]:
    """What of a ``TrackerConfig`` decides the tracker's outputs, as ``{key: exact value string}``
    in the config's field order: the VINS keys (``max_cnt``, ``freq``, ...), the cameras'
    parameters (``camera.fx``, ``camera1.k1``, ..., with ``camera.model`` and size), the
    extrinsics. The file's path and the raw key table are left out (a copy of the same config
    elsewhere is the same config). Per-stream configs (a sequence, ``FeatureTracker.configs``): the
    one config's keys where every stream's are equal, else every stream's as ``stream <b> <key>``."""
    if isinstance(config, (list, tuple)):
        fps = [config_fingerprint(c) for c in config]
        if all(f == fps[0] for f in fps[1:]):
            return fps[0]
        return {f"stream {b} {k}": v for b, f in enumerate(fps) for k, v in f.items()}
    out: Dict[str, str] = {}
    for f in dataclasses.fields(config):
        if f.name in _CONFIG_PATHS:
            continue
        v = getattr(config, f.name)
        if f.name in ("camera", "camera1"):
            if v is None:
                out[f.name] = "None"
                continue
            out[f"{f.name}.model"] = type(v).__name__
            out[f"{f.name}.size"] = f"{int(v.width)}x{int(v.height)}"
            for k, p in v.params_dict().items():
                out[f"{f.name}.{k}"] = _plain(p)
            continue
        out[f.name] = _plain(v)
    return out


def _first_difference(saved: Dict[str, str], now: Dict[str, str]) -> str | None:
    """The first key (in ``now``'s order, then ``saved``'s) whose value differs, as
    ``"key (saved: a, this tracker: b)"``; None when equal."""
    for k in list(now) + [k for k in saved if k not in now]:
        a, b = saved.get(k, "absent"), now.get(k, "absent")
        if a != b:
            return f"{k} (saved: {a}, this tracker: {b})"
    return None


def _restart_watch_dict(watch) -> Dict[str, Any] | None:
    if watch is None:
        return None
    return {"warned": sorted(int(b) for b in watch.warned), "last": list(watch.last),
            "run": [list(r) for r in watch.run]}


def tracker_state_dict(tracker) -> Dict[str, Any]:
    """The state of ``tracker`` (a ``FeatureTracker``) as plain values (module docstring). The
    tensors are copies on the CPU: later steps do not change the dict."""
    leaves, spec = pytree.tree_flatten(tracker.state)
    cpu: List[Any] = [x.detach().to("cpu", copy=True) if isinstance(x, torch.Tensor) else x for x in leaves]
    return {
        "version": STATE_DICT_VERSION,
        "kind": _KIND,
        "mode": tracker.mode,
        "num_streams": int(tracker.B),
        "capacity": int(tracker.K),
        "dtype": str(tracker.dtype),
        "lk_backend": tracker.lk_backend,
        "config": config_fingerprint(tracker.configs),
        "treespec": pytree.treespec_dumps(spec),
        "leaves": cpu,
        "restarts": _restart_watch_dict(getattr(tracker, "_restarts", None)),
    }


def load_tracker_state_dict(tracker, d: Dict[str, Any]) -> None:
    """Give ``tracker`` the state ``d`` (from :func:`tracker_state_dict`, of any device): its
    tensors move to ``tracker.device``.

    Raises:
        ValueError: ``d`` is not such a dict, of another version, or of a tracker with another
            mode, stream count, capacity, dtype or config (the message names the first key that
            differs and both values).
    """
    if not isinstance(d, dict) or d.get("kind") != _KIND:
        raise ValueError(f"load_state_dict: not a FeatureTracker state_dict (expected a dict with kind {_KIND!r}, "
                         f"got {type(d).__name__}{'' if not isinstance(d, dict) else ' kind ' + repr(d.get('kind'))})")
    if d.get("version") != STATE_DICT_VERSION:
        raise ValueError(f"load_state_dict: state_dict version {d.get('version')!r}, this torch-frontend reads "
                         f"version {STATE_DICT_VERSION} only")
    def same(key: str, mine) -> None:
        if d.get(key) != mine:
            raise ValueError(f"load_state_dict: the state is of a tracker with {key} {d.get(key)!r}, this one has "
                             f"{mine!r}")

    same("mode", tracker.mode)
    same("num_streams", int(tracker.B))
    diff = _first_difference(d.get("config", {}), config_fingerprint(tracker.configs))
    if diff is not None:
        raise ValueError(f"load_state_dict: the state is of another config: {diff}")
    same("capacity", int(tracker.K))
    same("dtype", str(tracker.dtype))
    # the kernels decide bits: a state saved with one LK continued with the other would drift silently
    # (a dict without the key predates the fused kernels: the tensor ones)
    saved_lk = d.get("lk_backend", "tensor")
    if saved_lk != tracker.lk_backend:
        raise ValueError(f"load_state_dict: the state is of a tracker with lk_backend {saved_lk!r}, this one has "
                         f"{tracker.lk_backend!r} (other kernels, other bits): build it with lk_backend={saved_lk!r}")
    try:
        spec = pytree.treespec_loads(d["treespec"])
        leaves = [x.to(tracker.device) if isinstance(x, torch.Tensor) else x for x in d["leaves"]]
        state = pytree.tree_unflatten(leaves, spec)
    except (KeyError, TypeError, ValueError, NotImplementedError) as exc:
        raise ValueError(f"load_state_dict: the saved state does not rebuild ({type(exc).__name__}: {exc})") from None
    mine = pytree.tree_structure(tracker.initial_state())
    if type(state) is not type(tracker.state) or _root_fields(spec) != _root_fields(mine):
        raise ValueError(f"load_state_dict: the saved state is a {type(state).__name__} of another structure than "
                         f"this tracker's {type(tracker.state).__name__}")
    tracker.state = state
    # the clock's host mirror follows a state by identity: the first step from this state reads
    # the clock back once (a state from elsewhere, FeatureTracker._host_clock)
    if hasattr(tracker, "_mirror"):
        tracker._mirror = None
    watch = getattr(tracker, "_restarts", None)
    saved = d.get("restarts")
    if watch is not None and saved is not None:
        watch.warned = {int(b) for b in saved["warned"]}
        watch.last = list(saved["last"])
        watch.run = [list(r) for r in saved["run"]]
        watch.follow(tracker.state)


def _root_fields(spec) -> Any:
    """The root node's type and context of a treespec (its fields, not the optional subtrees)."""
    return (spec.type, spec.context)
