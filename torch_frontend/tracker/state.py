"""``TrackerState``: everything the tracker carries from one step to the next (a registered pytree).

Convention:
    Leading dimension B (streams) on every tensor; times are float64 seconds (epoch stamps need
    float64: float32 resolves 1.4e9 s to 128 s). The state is a plain value: :func:`step` returns a
    new one and never writes into its input (the only exception is the pyramid's padded-level cache,
    a memo of values derived from the pyramid itself, see ``Pyramid.padded``).

    ``TrackerState``, ``FeatureTable`` and ``FeatureFrame`` are registered with
    ``torch.utils._pytree``, so ``torch.func`` transforms, ``tree_map`` (e.g. moving a state to
    another device) and checkpointing see their tensors.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import torch
import torch.utils._pytree as pytree

from ..pyramid import Pyramid
from .frame import FeatureFrame
from .table import FeatureTable

Tensor = torch.Tensor


@dataclasses.dataclass
class ClockState:
    """VINS-Mono ``img_callback``'s per-stream clock (spec §3.2), each ``(B,)``.

    Attributes:
        first_image_flag: bool, the next image is a "first image" (skipped).
        first_image_time: float64 s, start of the publish-rate window.
        last_image_time: float64 s, the last image's stamp (0 after a restart).
        pub_count: int64, published frames in the current rate window (starts at 1).
        init_pub: bool, the stream has published once (the first published frame is not sent).
    """

    first_image_flag: Tensor
    first_image_time: Tensor
    last_image_time: Tensor
    pub_count: Tensor
    init_pub: Tensor

    @classmethod
    def initial(cls, batch: int, device) -> ClockState:
        f64 = torch.float64
        return cls(first_image_flag=torch.ones(batch, device=device, dtype=torch.bool),
                   first_image_time=torch.zeros(batch, device=device, dtype=f64),
                   last_image_time=torch.zeros(batch, device=device, dtype=f64),
                   pub_count=torch.ones(batch, device=device, dtype=torch.int64),
                   init_pub=torch.zeros(batch, device=device, dtype=torch.bool))


@dataclasses.dataclass
class TrackerState:
    """The tracker's state between steps.

    Attributes:
        features: the feature table (:class:`FeatureTable`), ``(B, K, ...)``.
        clock: mono's publish/restart clock (:class:`ClockState`); unused by fusion.
        prev_time: (B,) float64, stamp of the last processed frame (velocities' ``dt``).
        has_image: (B,) bool, a previous processed image (and pyramid) exists.
        next_id: (B,) int64, the stream's next feature id (ids are per stream).
        has_prediction: (B,) bool, fusion: ``set_prediction`` gave a prediction for the next step.
        prev_pyramid: the last processed image's pyramid (None before the first one).
    """

    features: FeatureTable
    clock: ClockState
    prev_time: Tensor
    has_image: Tensor
    next_id: Tensor
    has_prediction: Tensor
    prev_pyramid: Optional[Pyramid] = None

    @classmethod
    def initial(cls, batch: int, capacity: int, *, device, dtype: torch.dtype, fusion: bool) -> TrackerState:
        """The state of B streams that have seen nothing (as a freshly constructed VINS tracker)."""
        return cls(
            features=FeatureTable.empty(batch, capacity, device=device, dtype=dtype, fusion=fusion),
            clock=ClockState.initial(batch, device),
            prev_time=torch.zeros(batch, device=device, dtype=torch.float64),
            has_image=torch.zeros(batch, device=device, dtype=torch.bool),
            next_id=torch.zeros(batch, device=device, dtype=torch.int64),
            has_prediction=torch.zeros(batch, device=device, dtype=torch.bool),
        )

    @property
    def batch(self) -> int:
        return int(self.has_image.shape[0])

    def replace(self, **fields) -> TrackerState:
        return dataclasses.replace(self, **fields)

    def detach(self) -> TrackerState:
        """The same state cut from the autograd graph (truncated BPTT: a differentiable tracker's
        state carries the graph of every step since the last ``detach``)."""
        return pytree.tree_map(lambda x: x.detach() if isinstance(x, torch.Tensor) else x, self)

    @property
    def requires_grad(self) -> bool:
        """Some tensor of the state carries an autograd graph (a differentiable tracker's)."""
        return any(isinstance(x, torch.Tensor) and x.requires_grad for x in pytree.tree_leaves(self))


def _register_dataclass(cls) -> None:
    """Register a dataclass as a pytree node whose children are its fields, in order."""
    names = [f.name for f in dataclasses.fields(cls)]

    def flatten(obj):
        return [getattr(obj, n) for n in names], None

    def unflatten(values, _context):
        return cls(**dict(zip(names, values)))

    def flatten_with_keys(obj):
        return [(pytree.GetAttrKey(n), getattr(obj, n)) for n in names], None

    pytree.register_pytree_node(cls, flatten, unflatten, flatten_with_keys_fn=flatten_with_keys,
                                serialized_type_name=f"{cls.__module__}.{cls.__qualname__}")


def _register_pyramid() -> None:
    """``Pyramid`` as a pytree node: a packed pyramid's one child is its packed tensor (the levels are
    views into it, rebuilt on unflatten), context ``[rounded, height, width, max_level, pad]``;
    otherwise its levels (and gradients), context ``rounded``. The padded-level cache is a memo and
    is not carried through flatten/unflatten."""
    def flatten(p):
        if p.packed is not None:
            lay = p.layout
            return [p.packed], [p.rounded, lay.height, lay.width, lay.max_level, lay.pad]
        return [p.levels, p.grads], p.rounded

    def unflatten(values, context):
        if isinstance(context, (list, tuple)):  # packed (a list after treespec_loads)
            _, H, W, L, pad = context
            return Pyramid.from_packed(values[0], H, W, L, pad)
        levels, grads = values
        return Pyramid(list(levels), None if grads is None else list(grads), context)

    pytree.register_pytree_node(Pyramid, flatten, unflatten, serialized_type_name="torch_frontend.pyramid.Pyramid")


for _cls in (FeatureTable, ClockState, TrackerState, FeatureFrame):
    _register_dataclass(_cls)
_register_pyramid()

__all__ = ["TrackerState", "ClockState"]
