"""Helpers of the back end's ``state_dict`` / ``load_state_dict`` pairs (``PlaceDatabase``,
``KeyFrame`` lists, ``LoopResult`` lists, ``PoseGraph``; the pipeline's ``KeyframeLog``): what a
checkpoint of ``torch-frontend loop`` holds to continue a run bit for bit.

Convention:
    A state is a plain dict of CPU tensors, Python scalars, strings, lists and dicts (what
    ``torch.save`` / ``torch.load(weights_only=True)`` round-trip exactly), with ``kind`` (the class
    it belongs to) and ``version`` (its layout; a reader refuses another version with one line).
    Ragged per-item arrays (keyframe points, keypoints, loop matches) are stored as one
    concatenated tensor plus a ``(K,)`` int64 length per item, so a state has a few tensors
    whatever the number of keyframes.
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence

import torch

from ..errors import DataError

__all__ = ["StateError", "check_same", "check_state", "pack_ragged", "split_ragged"]


class StateError(DataError):
    """A saved state that does not fit what reads it: another kind or version, or another
    configuration (the message names the key, what the state holds and what was expected)."""


def check_state(state: Any, kind: str, version: int, keys: Sequence[str] = ()) -> Dict[str, Any]:
    """``state`` if it is a ``kind`` state of ``version`` holding ``keys``, else :class:`StateError`."""
    if not isinstance(state, dict):
        raise StateError(f"{kind} state: expected a dict, got {type(state).__name__}")
    if state.get("kind") != kind:
        raise StateError(f"{kind} state: this is a {state.get('kind')!r} state, not a {kind!r} one")
    if state.get("version") != version:
        raise StateError(f"{kind} state: version {state.get('version')!r}, this torch-frontend reads version "
                         f"{version} (written by another release: start the run over)")
    missing = [k for k in keys if k not in state]
    if missing:
        raise StateError(f"{kind} state: missing {', '.join(missing)}")
    return state


def check_same(kind: str, key: str, saved: Any, expected: Any) -> None:
    """:class:`StateError` unless the state's ``key`` (``saved``) equals the reader's (``expected``)."""
    if isinstance(saved, torch.Tensor) or isinstance(expected, torch.Tensor):
        same = (isinstance(saved, torch.Tensor) and isinstance(expected, torch.Tensor)
                and saved.shape == expected.shape and saved.dtype == expected.dtype
                and torch.equal(saved.cpu(), expected.cpu()))
    else:
        same = bool(saved == expected)
    if not same:
        raise StateError(f"{kind} state: {key} is {_shown(saved)!r} in the state but {_shown(expected)!r} here")


def _shown(v: Any) -> Any:
    return v.tolist() if isinstance(v, torch.Tensor) else v


def pack_ragged(rows: Sequence[torch.Tensor], empty: Optional[torch.Tensor] = None):
    """``(cat (sum n, ...) on the CPU, lengths (K,) int64)`` of ``K`` tensors ``(n_k, ...)``;
    ``empty``: the ``(0, ...)`` tensor (dtype and trailing shape) used when ``rows`` is empty."""
    lengths = torch.tensor([int(r.shape[0]) for r in rows], dtype=torch.int64)
    if not rows:
        return (torch.zeros(0) if empty is None else empty.detach().cpu()), lengths
    return torch.cat([r.detach().cpu() for r in rows]), lengths


def split_ragged(flat: torch.Tensor, lengths: torch.Tensor, device=None) -> List[torch.Tensor]:
    """The ``K`` tensors of :func:`pack_ragged` (each its own copy, on ``device``)."""
    parts = torch.split(flat, [int(n) for n in lengths.tolist()]) if lengths.numel() else ()
    return [p.to(device).clone() if device is not None else p.clone() for p in parts]
