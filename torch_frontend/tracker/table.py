"""``FeatureTable``: the per-stream feature arrays of VINS as one fixed-capacity padded table.

Convention:
    Every column is ``(B, K, ...)``: B streams, K = ``max_cnt`` slots. Valid slots are packed at
    the front in VINS's vector order (a stable compaction, VINS's ``reduceVector``), so slot order
    *is* VINS's array order: it decides which features survive ``setMask`` and which ids new
    features get (spec §3.6, §3.7, §3.9). Empty slots hold ``ids == -1``, ``track_cnt == 0`` after a
    step is committed; their other values are unspecified (finite).

    Columns that a mode or a stage does not use are ``None`` and cost nothing: mono carries no
    right-camera or prediction columns, and the step-local columns (``prev_pts``, ``prev_tracked``,
    ``is_new``) exist only inside one step.

    Every column moves together: :meth:`permute`, :meth:`compact` and :meth:`append` apply one
    slot order to all of them, so a column cannot fall out of step with the others.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import torch

from .._checks import gather_slots, valid_first_order

Tensor = torch.Tensor


def where_streams(mask: Tensor, new: Tensor, old: Tensor) -> Tensor:
    """Stream b of ``new`` where ``mask[b]`` (``(B,)`` bool), else of ``old`` (``(B, ...)`` each)."""
    return torch.where(mask.reshape(mask.shape + (1,) * (new.dim() - 1)), new, old)


@dataclasses.dataclass
class FeatureTable:
    """VINS's parallel feature arrays, ``(B, K, ...)`` each.

    Attributes:
        pts: (B, K, 2) float, pixels (x, y) in the stream's latest image (``forw_pts``/``cur_pts``).
        ids: (B, K) int64, -1 where not (yet) assigned.
        track_cnt: (B, K) int64, frames the feature has been tracked in (1 = just detected).
        valid: (B, K) bool, the slot holds a feature.
        un_pts: (B, K, 2) float, normalised undistorted points of the last processed frame
            (``cur_un_pts``; the previous frame's map for the velocities).
        right_un: (B, K, 2) float or None, fusion stereo: camera 1's normalised points of the last frame.
        right_valid: (B, K) bool or None, fusion stereo: the slot had a camera-1 observation.
        prediction: (B, K, 2) float or None, fusion: predicted pixels for the next frame.
        prev_pts: (B, K, 2) float or None, step-local: the pixels before this step's LK (``cur_pts``).
        prev_tracked: (B, K) bool or None, step-local (fusion): tracked from the previous frame.
        is_new: (B, K) bool or None, step-local: detected in this step.
    """

    pts: Tensor
    ids: Tensor
    track_cnt: Tensor
    valid: Tensor
    un_pts: Tensor
    right_un: Optional[Tensor] = None
    right_valid: Optional[Tensor] = None
    prediction: Optional[Tensor] = None
    prev_pts: Optional[Tensor] = None
    prev_tracked: Optional[Tensor] = None
    is_new: Optional[Tensor] = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def empty(cls, batch: int, capacity: int, *, device, dtype: torch.dtype, fusion: bool = False) -> FeatureTable:
        """An all-empty table (fusion: with the right-camera and prediction columns)."""
        B, K = batch, capacity

        def zeros(*shape, dt=dtype):
            return torch.zeros(*shape, device=device, dtype=dt)

        extra = {}
        if fusion:
            extra = dict(right_un=zeros(B, K, 2), right_valid=zeros(B, K, dt=torch.bool), prediction=zeros(B, K, 2))
        return cls(pts=zeros(B, K, 2), ids=torch.full((B, K), -1, device=device, dtype=torch.int64),
                   track_cnt=zeros(B, K, dt=torch.int64), valid=zeros(B, K, dt=torch.bool),
                   un_pts=zeros(B, K, 2), **extra)

    # ------------------------------------------------------------------ columns
    def columns(self) -> dict:
        """The columns that are present (not None), by name."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}

    def replace(self, **columns) -> FeatureTable:
        return dataclasses.replace(self, **columns)

    def _map(self, fn) -> FeatureTable:
        return dataclasses.replace(self, **{k: fn(k, v) for k, v in self.columns().items()})

    @property
    def batch(self) -> int:
        return int(self.valid.shape[0])

    @property
    def capacity(self) -> int:
        return int(self.valid.shape[1])

    # ------------------------------------------------------------------ moving slots
    def permute(self, order: Tensor) -> FeatureTable:
        """Every column reordered by ``order (B, K)`` slot indices."""
        return self._map(lambda _, v: gather_slots(v, order))

    def compact(self, keep: Tensor) -> FeatureTable:
        """VINS ``reduceVector``: keep the slots where ``keep (B, K)`` is True, packed at the front in
        their order (the dropped ones follow, also in order). ``valid`` becomes the packed ``keep``."""
        order = valid_first_order(keep)
        out = dataclasses.replace(self, valid=keep).permute(order)
        return out

    def append(self, new_pts: Tensor, new_valid: Tensor) -> FeatureTable:
        """VINS ``addPoints``: write detections into the free slots after the valid ones.

        new_pts: (B, Kn, 2) pixels in detection order; new_valid: (B, Kn) bool. Detections beyond
        the capacity are dropped. New slots get ``ids = -1``, ``track_cnt = 1``, ``is_new = True``
        and zeros (False) in every other column; ``is_new`` is False elsewhere.
        """
        B, K = self.valid.shape
        is_new = torch.zeros_like(self.valid)
        if new_pts.shape[1] == 0:
            return self.replace(is_new=is_new)
        # detection r of stream b goes to slot n_keep[b] + r; slot K is a dump slot, cut below
        rank = torch.cumsum(new_valid.to(torch.int64), dim=1) - 1
        slot = self.valid.sum(1, keepdim=True) + rank
        ok = new_valid & (slot < K)
        slot = torch.where(ok, slot, torch.full_like(slot, K))
        fills = dict(pts=new_pts, valid=ok, ids=-1, track_cnt=1, is_new=ok)

        def write(name, col):
            padded = torch.cat([col, torch.zeros_like(col[:, :1])], dim=1)
            value = fills.get(name, 0)
            idx = slot if col.dim() == 2 else slot.unsqueeze(-1).expand(-1, -1, *col.shape[2:])
            if isinstance(value, Tensor):
                src = value.to(col.dtype)
            else:
                src = torch.full(idx.shape, value, dtype=col.dtype, device=col.device)
            return padded.scatter(1, idx, src)[:, :K]

        return self.replace(is_new=is_new)._map(write)

    # ------------------------------------------------------------------ per stream
    def where_streams(self, active: Tensor, other: FeatureTable) -> FeatureTable:
        """Stream b from ``self`` where ``active[b]`` else from ``other`` (same columns present)."""
        return self._map(lambda name, new: where_streams(active, new, getattr(other, name)))

    def streams(self, rows: Tensor) -> FeatureTable:
        """The streams ``rows (n,)`` int64 of every column, ``(n, K, ...)`` (a sub-batch)."""
        return self._map(lambda _, v: v.index_select(0, rows))

    def with_streams(self, rows: Tensor, sub: FeatureTable) -> FeatureTable:
        """A copy with stream ``rows[i]`` of every column replaced by ``sub``'s row i (``rows (n,)``
        distinct, ``sub`` with the same columns present)."""
        return self._map(lambda name, v: v.index_copy(0, rows, getattr(sub, name)))

    def committed(self) -> FeatureTable:
        """The table as it is stored between steps: empty slots hold ``ids = -1`` and
        ``track_cnt = 0``, a right observation needs a feature, and the step-local columns are dropped."""
        v = self.valid
        out = self.replace(ids=torch.where(v, self.ids, torch.full_like(self.ids, -1)),
                           track_cnt=torch.where(v, self.track_cnt, torch.zeros_like(self.track_cnt)),
                           prev_pts=None, prev_tracked=None, is_new=None)
        if out.right_valid is not None:
            out = out.replace(right_valid=out.right_valid & v)
        return out


__all__ = ["FeatureTable", "where_streams"]
