"""Per-stream configs: B streams, each with its own camera, image size and VINS keys, in one tracker.

Convention:
    A mixed batch is partitioned on the host, once, into **stream groups**: streams whose configs
    give equal :class:`TrackerParams` (every VINS key and constant: size, ``max_cnt``, ``min_dist``,
    ``F_threshold``, ``F_method``, ``equalize``, ``fisheye``, ``freq``, ...) and equal cameras (model
    and values; ``cam1`` too) share a group. Each group runs the homogeneous step unchanged (its own
    kernels, its own compiled variants), so stream ``b`` of a mixed batch is exactly the one-stream
    tracker of config ``b``: a stream's results never depend on the other streams of its step (the
    property every kernel already keeps), whichever group they are in. Launches grow with the
    number of groups, never with B.

    Stream ``b``'s rows are row ``index[b]`` of its group; the merged :class:`FeatureFrame` is
    ``(B, K, ...)`` with ``K`` = the largest ``max_cnt``; a group with a smaller ``max_cnt`` fills
    its first ``max_cnt`` slots and pads the rest as empty (id -1, not valid, not present, zeros).
    The state of a mixed tracker is a :class:`GroupedState` (a pytree of the groups'
    :class:`TrackerState`).

    Images of a mixed batch: a list of B images ``(H_b, W_b)`` / ``(1, H_b, W_b)`` (each stream its
    own size), or one ``(B, 1, H, W)`` / ``(B, H, W)`` tensor, padded at the bottom and right, with
    ``sizes (B, 2)`` = ``(H_b, W_b)`` per stream (a host sequence or CPU tensor: the split happens on
    the host, before any upload).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.utils._pytree as pytree

from ..config import TrackerConfig, load_config
from .frame import FeatureFrame
from .state import TrackerState

Tensor = torch.Tensor

#: empty-slot values of the frame's per-slot fields where a group has fewer slots than K (the
#: homogeneous tracker's own empty slots: id -1, nothing valid; every float 0)
_EMPTY_ID = -1
_PER_SLOT = ("ids", "uv", "xy", "velocity", "track_count", "valid", "present", "prev_uv", "prev_valid",
             "right_uv", "right_xy", "right_velocity", "right_valid")
#: per-stream fields that a group may leave None (default path: no overflow; a mono-camera group in a
#: fusion batch: no right_*) while another group gives a tensor; filled with these
_PER_STREAM_DEFAULT = {"overflow": False}


def _is_config_sequence(config) -> bool:
    return isinstance(config, (list, tuple))


def stream_configs(config, num_streams: Optional[int]) -> List[TrackerConfig]:
    """The B per-stream configs of ``FeatureTracker(config, num_streams)``: one config (a
    ``TrackerConfig`` or a path) broadcast to ``num_streams`` (default 1), or a sequence of B configs
    (``num_streams`` None or equal to its length). Paths are loaded once each."""
    if _is_config_sequence(config):
        if len(config) == 0:
            raise ValueError("config: expected a config or a sequence of per-stream configs, got an empty sequence")
        if num_streams is not None and int(num_streams) != len(config):
            raise ValueError(f"num_streams: {num_streams} differs from the {len(config)} per-stream configs given "
                             f"(give one config to broadcast it, or num_streams=None)")
        loaded: Dict[str, TrackerConfig] = {}
        out = []
        for i, c in enumerate(config):
            if isinstance(c, TrackerConfig):
                out.append(c)
            elif isinstance(c, (str, os.PathLike)):
                key = os.fspath(c)
                if key not in loaded:
                    loaded[key] = load_config(key)
                out.append(loaded[key])
            else:
                raise TypeError(f"config[{i}]: expected a TrackerConfig or a path, got {type(c).__name__}")
        return out
    if num_streams is None:
        num_streams = 1
    if int(num_streams) < 1:
        raise ValueError(f"num_streams: expected >= 1, got {num_streams}")
    if not isinstance(config, TrackerConfig):
        config = load_config(config)
    return [config] * int(num_streams)


def camera_key(camera) -> Any:
    """What makes two cameras the same calibration: model, every parameter value (exact floats),
    size and model options (``extra_repr`` holds them all)."""
    if camera is None:
        return None
    return type(camera).__name__, camera.extra_repr()


def group_key(params, mask) -> Any:
    """Streams with equal keys share a group: equal params (the dataclass compares every field
    but the cameras and the mask), equal cameras, the same fisheye mask object."""
    return params, camera_key(params.camera), camera_key(params.camera1), None if mask is None else id(mask)


@dataclasses.dataclass(frozen=True)
class StreamGroup:
    """Streams of one group: their global indices ``streams`` (ascending), on the host."""

    streams: Tuple[int, ...]

    @property
    def size(self) -> int:
        return len(self.streams)

    def index(self, device) -> Tensor:
        """The streams as an int64 tensor on ``device``, built once per device (a per-step
        ``torch.tensor`` would be a blocking host-to-device copy on CUDA)."""
        return _index_tensor(self.streams, torch.device(device))


_INDEX_CACHE: Dict[Tuple[Tuple[int, ...], torch.device], Tensor] = {}


def _index_tensor(streams: Tuple[int, ...], device: torch.device) -> Tensor:
    key = (streams, device)
    t = _INDEX_CACHE.get(key)
    if t is None:
        t = _INDEX_CACHE[key] = torch.tensor(streams, dtype=torch.int64, device=device)
    return t


def partition(keys: Sequence[Any]) -> List[StreamGroup]:
    """Streams grouped by equal key, groups in the order of their first stream."""
    order: Dict[Any, List[int]] = {}
    for b, k in enumerate(keys):
        order.setdefault(k, []).append(b)
    return [StreamGroup(tuple(s)) for s in order.values()]


@dataclasses.dataclass
class GroupedState:
    """The state of a mixed tracker: one :class:`TrackerState` per stream group, in group order."""

    groups: Tuple[TrackerState, ...]

    @property
    def batch(self) -> int:
        return sum(s.batch for s in self.groups)

    def detach(self) -> GroupedState:
        return GroupedState(tuple(s.detach() for s in self.groups))

    @property
    def requires_grad(self) -> bool:
        return any(s.requires_grad for s in self.groups)


def _flatten(state):
    return list(state.groups), len(state.groups)


def _unflatten(values, _n):
    return GroupedState(tuple(values))


def _flatten_with_keys(state):
    return [(pytree.SequenceKey(i), s) for i, s in enumerate(state.groups)], len(state.groups)


pytree.register_pytree_node(GroupedState, _flatten, _unflatten, flatten_with_keys_fn=_flatten_with_keys,
                            serialized_type_name="torch_frontend.tracker.streams.GroupedState")


# ---------------------------------------------------------------------------------------------
# splitting the inputs


def _host_sizes(sizes, batch: int) -> np.ndarray:
    if isinstance(sizes, torch.Tensor):
        if sizes.device.type != "cpu":
            raise ValueError("sizes: expected (H, W) per stream on the host (a list or CPU tensor: the batch is "
                             f"split before the upload), got a tensor on {sizes.device}")
        sizes = sizes.tolist()
    arr = np.asarray(sizes)
    if arr.shape != (batch, 2) or not np.issubdtype(arr.dtype, np.integer) and not np.all(arr == np.round(arr)):
        raise ValueError(f"sizes: expected ({batch}, 2) integers (H, W) per stream, got {arr.tolist()!r}")
    return arr.astype(np.int64)


def split_images(images, sizes, groups: Sequence[StreamGroup], batch: int, name: str = "images", device=None
                 ) -> Tuple[List[Any], List[Tuple[int, int]]]:
    """``images`` of B streams as one ``(B_g, 1, H_g, W_g)`` (or ``(B_g, H_g, W_g)``) batch per group,
    and every stream's ``(H, W)``.

    A list of B images: each group's images are stacked (they must share a size: a group's
    streams have one config). A tensor ``(B, [1,] H, W)``: rows taken per group, cropped to
    ``sizes`` where given (the top-left ``H_b x W_b`` of a padded batch). ``device``: where the
    groups' batches go; on a device other than the CPU the batch is uploaded once (a list: padded
    on the host first) and split there, so the step has one image upload whatever the groups."""
    if isinstance(images, (list, tuple)):
        if sizes is not None:
            raise ValueError(f"sizes: give sizes with one padded {name} tensor; a list of {name} has their own")
        if len(images) != batch:
            raise ValueError(f"{name}: expected {batch} images (one per stream), got {len(images)}")
        tensors = [torch.as_tensor(im) for im in images]
        for b, im in enumerate(tensors):
            if im.dim() not in (2, 3) or (im.dim() == 3 and im.shape[0] != 1):
                raise ValueError(f"{name}[{b}]: expected (H, W) or (1, H, W), got {tuple(im.shape)}")
        hw = [(int(im.shape[-2]), int(im.shape[-1])) for im in tensors]
        on_device = device is not None and torch.device(device).type != "cpu" and all(
            im.device.type == "cpu" for im in tensors)
        if on_device and len({im.dtype for im in tensors}) == 1:
            # one padded host batch, one upload, then the tensor path (split on the device)
            H, W = max(h for h, _ in hw), max(w for _, w in hw)
            padded = tensors[0].new_zeros((batch, 1, H, W))
            for b, im in enumerate(tensors):
                padded[b, 0, :hw[b][0], :hw[b][1]] = im.reshape(hw[b])
            return split_images(padded.to(device), [list(x) for x in hw], groups, batch, name)
        out = []
        for g in groups:
            sz = {hw[b] for b in g.streams}
            if len(sz) > 1:
                shown = ", ".join(f"stream {b}: {hw[b][1]}x{hw[b][0]}" for b in g.streams)
                raise ValueError(f"{name}: streams {list(g.streams)} share one config but their images differ in "
                                 f"size ({shown}); LK needs one size per config")
            out.append(torch.stack([tensors[b].reshape(1, *hw[b]) for b in g.streams]))
        return out, hw
    if not isinstance(images, torch.Tensor):
        images = torch.as_tensor(images)
    if device is not None and len(groups) > 1 and images.device != torch.device(device):
        images = images.to(device)  # one upload; the groups' rows are taken on the device
    if images.dim() not in (3, 4) or images.shape[0] != batch:
        raise ValueError(f"{name}: expected {batch} streams (B, 1, H, W), a list of {batch} images, got "
                         f"{tuple(images.shape)}")
    H, W = int(images.shape[-2]), int(images.shape[-1])
    if sizes is None:
        hw = [(H, W)] * batch
    else:
        arr = _host_sizes(sizes, batch)
        bad = [b for b in range(batch) if not (1 <= arr[b, 0] <= H and 1 <= arr[b, 1] <= W)]
        if bad:
            b = bad[0]
            raise ValueError(f"sizes[{b}]: (H, W) = {tuple(arr[b].tolist())} does not fit the padded {name} "
                             f"{H}x{W} (W x H)")
        hw = [(int(h), int(w)) for h, w in arr]
    out = []
    for g in groups:
        sz = {hw[b] for b in g.streams}
        if len(sz) > 1:
            raise ValueError(f"sizes: streams {list(g.streams)} share one config but differ in size "
                             f"({[hw[b] for b in g.streams]}); LK needs one size per config")
        h, w = hw[g.streams[0]]
        rows = images if g.size == batch else images.index_select(0, g.index(images.device))
        out.append(rows if (h, w) == (H, W) else rows[..., :h, :w])
    return out, hw


# ---------------------------------------------------------------------------------------------
# merging the frames


def _pad_slots(x: Tensor, K: int, name: str) -> Tensor:
    k = x.shape[1]
    if k == K:
        return x
    fill = _EMPTY_ID if name == "ids" else 0
    pad = x.new_full((x.shape[0], K - k) + tuple(x.shape[2:]), fill)
    return torch.cat((x, pad), 1)


def merge_frames(frames: Sequence[FeatureFrame], groups: Sequence[StreamGroup], K: int,
                 inverse: Optional[Tensor]) -> FeatureFrame:
    """The groups' frames as one ``(B, K, ...)`` frame in stream order (``inverse``: for every
    stream its row in the groups' concatenation; None when that is the identity)."""
    out = {}
    for f in dataclasses.fields(FeatureFrame):
        vals = [getattr(fr, f.name) for fr in frames]
        if all(v is None for v in vals):
            out[f.name] = None
            continue
        ref = next(v for v in vals if v is not None)
        parts = []
        for v, fr in zip(vals, frames):
            Bg = fr.batch_size
            if v is None:
                if f.name in _PER_SLOT:
                    v = ref.new_full((Bg, fr.ids.shape[1]) + tuple(ref.shape[2:]), 0)
                else:
                    v = ref.new_full((Bg,) + tuple(ref.shape[1:]), _PER_STREAM_DEFAULT.get(f.name, 0))
            parts.append(_pad_slots(v, K, f.name) if f.name in _PER_SLOT else v)
        cat = torch.cat(parts, 0)
        out[f.name] = cat if inverse is None else cat.index_select(0, inverse.to(cat.device))
    return FeatureFrame(**out)


def inverse_order(groups: Sequence[StreamGroup]) -> Optional[List[int]]:
    """For every stream its row in the concatenation of the groups (None: the identity)."""
    order = [b for g in groups for b in g.streams]
    if order == sorted(order):
        return None
    inv = [0] * len(order)
    for row, b in enumerate(order):
        inv[b] = row
    return inv


__all__ = ["GroupedState", "StreamGroup", "group_key", "merge_frames", "partition", "split_images", "stream_configs"]
