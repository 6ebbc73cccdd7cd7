"""``CameraBatch``: B per-stream cameras (any mix of the camodocal models) as one module.

Convention:
    * stream ``b`` is camera ``b`` of the list the batch was built from (``CameraBatch.from_cameras``);
      ``len(batch) == B``, ``batch[b]`` / ``batch.camera(b)`` is stream b's own single
      :class:`~torch_frontend.camera.CameraModel` (same values, a copy: it shares nothing);
    * ``lift(uv)``: ``uv (B, ..., 2)`` pixels ``(u, v)`` -> ``(B, ..., 3)`` rays; ``project(P)``:
      ``P (B, ..., 3)`` camera-frame points -> ``(B, ..., 2)`` pixels; ``undistort(uv)``:
      ``(B, ..., 2)`` normalised ``(x/z, y/z)``. Units and per-model meanings are the single models'
      (``base.py``). The leading dimension is the stream; the rest are any number of point
      dimensions (at least one: ``(B, N, 2)``); float32 or float64, CPU or CUDA, parameters cast
      to the input's dtype and device on every call (differentiably, as the single models);
    * the values are bit for bit stream b's single camera's: each stream's parameters broadcast
      as ``(B, 1, ..., 1)`` (Scaramuzza's polynomials ``(B, 1, ..., 1, L)``) through the single
      models' own elementwise code, and IEEE elementwise ops give the same bits whatever the
      broadcast; the Kannala-Brandt critical points are one LAPACK ``eigvals`` per camera. One
      caveat of torch itself, not of the batch: on the CPU ``atan2`` (Kannala-Brandt ``lift`` /
      ``project``, Scaramuzza's ``project``) rounds differently (1 ulp) in its vectorised body and
      its scalar tail, so where an element lands in a tensor can change its last bit — camera b
      on ``uv[b]`` alone and on row b of ``uv`` can differ. Row b of the batch always equals
      camera b on ``uv`` (row b), and equals camera b on ``uv[b]`` on CUDA, for every model
      without ``atan2``, and where each stream's point count is a multiple of 64 (and torch does
      not split the tensor over threads: one thread, or under its 32768-element grain).

Storage (``state_dict``):
    * one model (every stream the same camodocal model with the same options, e.g.
      ``undistort_iters``): the model's parameter names, each ``(B,)`` (Scaramuzza's ``poly``
      ``(B, 5)``, ``inv_poly`` ``(B, 20)``): ``fx``, ``k1``, ... Row b is stream b's;
    * mixed models: one homogeneous sub-batch per (model, options) group in ``groups`` (an
      ``nn.ModuleDict``), named by the model (``pinhole``, ``kannala_brandt``, ``mei``,
      ``pinhole_full``, ``scaramuzza``; a model seen with a second option set gets ``pinhole_2``
      ...), each with its streams' rows in stream order: ``groups.pinhole.fx (B_pinhole,)``.
      ``group_streams[name]`` is the tuple of stream indices of group ``name`` (row i of the
      group is stream ``group_streams[name][i]``); the index buffers are not in ``state_dict``.
    Parameters are ``nn.Parameter``s with ``requires_grad=False`` until ``requires_grad_()``; then
    stream b's gradient lands in its own rows only (each stream's parameters are used by its own
    points only). ``to(device, dtype)``, ``double()`` etc. work as for any module.

Mixed batches: each group's streams are gathered (``index_select`` by a host-known list, kept as
a device buffer: no upload per call), computed with the group's model, and put back in stream
order (one ``cat`` + ``index_select``): the launches grow with the number of distinct models, not
with B.

Tracker duck typing: a batch is a valid ``TrackerParams.camera`` / ``camera1`` for a tracker of B
streams: ``_params_like(x)`` for ``x (B, K, 2)`` gives the per-stream parameters already shaped
``(B, 1)`` and ``_lift_impl(x, **those)`` lifts each stream with its own camera, exactly as the
tracker calls a single camera; ``index_streams(rows)`` is the same for a sub-batch of streams
(``rows (n,)`` int64 on the device: the capturable step's publish lanes, sync-free).
"""

from __future__ import annotations

import inspect
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import torch
from torch import nn

from .._checks import check_shape
from .base import CameraModel
from .factory import MODELS

#: keyword-only constructor arguments every model has (the rest are model options, e.g.
#: ``undistort_iters``, that change the computation and so split a mixed batch into groups)
_COMMON_KWARGS = ("width", "height", "camera_name", "dtype", "device")
#: the key of a stream's model in ``CameraBatch.params_dict`` entries
MODEL_KEY = "model_type"


def model_options(camera: CameraModel) -> Dict[str, Any]:
    """The model options of ``camera`` (its constructor's keyword-only arguments other than
    ``width, height, camera_name, dtype, device``): ``{"undistort_iters": 8}`` for a pinhole."""
    sig = inspect.signature(type(camera).__init__)
    names = [n for n, p in sig.parameters.items() if p.kind is inspect.Parameter.KEYWORD_ONLY and n not in _COMMON_KWARGS]
    return {n: getattr(camera, n) for n in names}


def _group_name(model: type, taken: Sequence[str]) -> str:
    base = next((k for k, v in MODELS.items() if v is model), model.__name__.lower())
    name, i = base, 1
    while name in taken:
        i += 1
        name = f"{base}_{i}"
    return name


def _subclasses(cls: type) -> List[type]:
    out = []
    for sub in cls.__subclasses__():
        out += [sub] + _subclasses(sub)
    return out


def _model_of(model_type: str) -> type:
    """The model class of a camodocal ``model_type`` (any letter case; a user's own ``CameraModel``
    subclass by its exact ``model_type``)."""
    cls = MODELS.get(str(model_type).lower())
    if cls is None:
        cls = next((c for c in _subclasses(CameraModel) if c.model_type == model_type), None)
    if cls is None:
        raise ValueError(f"{MODEL_KEY}: unknown camodocal model {model_type!r}; expected one of "
                         f"{sorted(c.model_type for c in MODELS.values())}")
    return cls


class CameraBatch(nn.Module):
    """B per-stream cameras (module docstring: shapes, storage, mixed models).

    Build with :meth:`from_cameras` (or ``CameraBatch(cameras)``); the dtype is the cameras'
    promoted parameter dtype unless given, the device the first camera's unless given.

    Attributes:
        num_streams: B.
        model: the model class when every stream has one model (with one option set), else None.
        model_type: that model's camodocal string, or ``"mixed"``.
        model_types, camera_names, widths, heights: per stream.
        width, height: the common image size, 0 where the streams differ (unknown, as a model's 0).
        group_streams: mixed batches: group name -> stream indices (empty for one model).
    """

    #: every stream's model accepts ``lift(..., jacobian="implicit")`` (set per batch)
    implicit_lift: bool

    def __init__(self, cameras: Sequence[CameraModel], *, dtype: Optional[torch.dtype] = None,
                 device: Optional[torch.device] = None) -> None:
        super().__init__()
        cameras = list(cameras)
        if not cameras:
            raise ValueError("CameraBatch: expected at least one camera, got an empty sequence")
        for b, cam in enumerate(cameras):
            if not isinstance(cam, CameraModel):
                raise TypeError(f"CameraBatch: stream {b}: expected a CameraModel, got {type(cam).__name__}")
        first = next(iter(cameras[0].parameters()))
        if dtype is None:
            dtype = first.dtype
            for cam in cameras[1:]:
                dtype = torch.promote_types(dtype, next(iter(cam.parameters())).dtype)
        if device is None:
            device = first.device
        self.num_streams = len(cameras)
        self.model_types = tuple(c.model_type for c in cameras)
        self.camera_names = tuple(c.camera_name for c in cameras)
        self.widths = tuple(int(c.width) for c in cameras)
        self.heights = tuple(int(c.height) for c in cameras)
        self.width = self.widths[0] if len(set(self.widths)) == 1 else 0
        self.height = self.heights[0] if len(set(self.heights)) == 1 else 0
        # groups: (model class, options) in order of first appearance
        keys: List[Tuple[type, Tuple[Tuple[str, Any], ...]]] = []
        members: List[List[int]] = []
        for b, cam in enumerate(cameras):
            key = (type(cam), tuple(sorted(model_options(cam).items())))
            if key not in keys:
                keys.append(key)
                members.append([])
            members[keys.index(key)].append(b)
        self.group_streams: Dict[str, Tuple[int, ...]] = {}
        if len(keys) == 1:
            model, options = keys[0]
            self.model = model
            self.model_type = model.model_type
            self.options = dict(options)
            self.implicit_lift = bool(model.implicit_lift)
            for name in model.param_names:
                # a copy of every value (stack copies): the batch shares nothing with the cameras
                t = torch.stack([getattr(c, name).detach().to(device=device, dtype=dtype) for c in cameras])
                self.register_parameter(name, nn.Parameter(t, requires_grad=False))
            # the model's own _lift_impl / _project_impl (they read only the options from self);
            # a plain attribute in a tuple: not a sub-module, not in state_dict, never moved
            self._impl = (model.from_params(cameras[0].params_dict(), **dict(options)),)
            return
        self.model = None
        self.model_type = "mixed"
        self.options = {}
        self.groups = nn.ModuleDict()
        for (model, _), rows in zip(keys, members):
            name = _group_name(model, list(self.groups.keys()))
            self.groups[name] = CameraBatch([cameras[b] for b in rows], dtype=dtype, device=device)
            self.group_streams[name] = tuple(rows)
            self.register_buffer(f"_rows_{name}", torch.tensor(rows, dtype=torch.int64, device=device),
                                 persistent=False)
        order = [b for rows in members for b in rows]  # the groups' outputs concatenated
        inverse = [0] * len(order)
        for i, b in enumerate(order):
            inverse[b] = i
        self.register_buffer("_inverse", torch.tensor(inverse, dtype=torch.int64, device=device), persistent=False)
        self.implicit_lift = all(g.implicit_lift for g in self.groups.values())

    # ------------------------------------------------------------------ construction / access
    @classmethod
    def from_cameras(cls, cameras: Sequence[CameraModel], *, dtype: Optional[torch.dtype] = None,
                     device: Optional[torch.device] = None) -> CameraBatch:
        """The batch of ``cameras`` (stream b = ``cameras[b]``), any mix of models; values copied."""
        return cls(cameras, dtype=dtype, device=device)

    stack = from_cameras

    @classmethod
    def repeat(cls, camera: CameraModel, num_streams: int) -> CameraBatch:
        """``num_streams`` copies of ``camera`` (e.g. to train per-stream intrinsics from one calibration)."""
        if num_streams < 1:
            raise ValueError(f"num_streams: expected >= 1, got {num_streams}")
        return cls([camera] * int(num_streams))

    def __len__(self) -> int:
        return self.num_streams

    def _stream(self, b: int) -> int:
        if isinstance(b, bool) or not isinstance(b, int):
            raise TypeError(f"CameraBatch: a stream index is an int, got {type(b).__name__}")
        if not -self.num_streams <= b < self.num_streams:
            raise IndexError(f"CameraBatch: stream {b} out of range for {self.num_streams} streams")
        return b % self.num_streams

    def camera(self, b: int) -> CameraModel:
        """Stream b's own single camera: the same values, dtype and device, sharing no storage."""
        batch, b = self.locate(b)
        if batch is not self:
            return batch.camera(b)
        p = next(iter(self.parameters()))
        values = {n: getattr(self, n)[b].detach().clone() for n in self.model.param_names}
        return self.model.from_params(values, width=self.widths[b], height=self.heights[b],
                                      camera_name=self.camera_names[b], dtype=p.dtype, device=p.device,
                                      **self.options)

    def locate(self, b: int) -> Tuple[CameraBatch, int]:
        """``(batch, row)``: the one-model batch holding stream b's parameters and its row there
        (this batch and ``b`` for one model; a mixed batch's group), e.g. ``batch.fx[row]``."""
        b = self._stream(b)
        if self.model is not None:
            return self, b
        g = next(g for g, rows in self.group_streams.items() if b in rows)
        return self.groups[g], self.group_streams[g].index(b)

    def __getitem__(self, b: int) -> CameraModel:
        return self.camera(b)

    def cameras(self) -> List[CameraModel]:
        """Every stream's single camera, in stream order."""
        return [self.camera(b) for b in range(self.num_streams)]

    def params_dict(self) -> List[Dict[str, Any]]:
        """Per stream ``{"model_type": ..., name: value}`` (values as the single model's
        ``params_dict``: Python floats, lists for Scaramuzza's polynomials)."""
        return [{MODEL_KEY: cam.model_type, **cam.params_dict()} for cam in self.cameras()]

    @classmethod
    def param_problems(cls, params: Sequence[Mapping[str, Any]]) -> List[Tuple[str, str]]:
        """The single models' :meth:`CameraModel.param_problems` per stream of ``params`` (the
        :meth:`params_dict` layout), as ``[("fx (stream 2)", problem)]``; empty when none. (The
        tracker raises ``camera.fx (stream 2): must be > 0 ...`` for the first.)"""
        out: List[Tuple[str, str]] = []
        for b, p in enumerate(params):
            if MODEL_KEY not in p:
                raise ValueError(f"CameraBatch.param_problems: stream {b}: no {MODEL_KEY!r} key")
            model = _model_of(p[MODEL_KEY])
            out += [(f"{key} (stream {b})", why) for key, why in model.param_problems(p)]
        return out

    def problems(self) -> List[Tuple[str, str]]:
        """:meth:`param_problems` of this batch's values."""
        return self.param_problems(self.params_dict())

    def extra_repr(self) -> str:
        items = [f"num_streams={self.num_streams}", f"model_type={self.model_type!r}"]
        if self.model is not None:
            # every stream's values, as a single model's repr has its own (what tells calibrations apart)
            items += [f"{n}={getattr(self, n).detach().cpu().tolist()!r}" for n in self.model.param_names]
            items += [f"{k}={v!r}" for k, v in self.options.items()]
            p = next(iter(self.parameters()))
            items.append(f"dtype={p.dtype}, device={p.device}")
        else:
            items.append("groups={" + ", ".join(f"{n!r}: {list(r)}" for n, r in self.group_streams.items()) + "}")
        return ", ".join(items)

    # ------------------------------------------------------------------ the tracker's interface
    def _check_streams(self, x: torch.Tensor, name: str) -> None:
        if x.dim() < 2 or x.shape[0] != self.num_streams:
            raise ValueError(f"{name}: a camera batch of {self.num_streams} streams expects shape "
                             f"({self.num_streams}, ..., {x.shape[-1] if x.dim() else '?'}) (stream first, "
                             f"then the points), got {tuple(x.shape)}")

    def _params_like(self, x: torch.Tensor, rows: Optional[torch.Tensor] = None) -> Dict[str, torch.Tensor]:
        """Parameters cast to ``x``'s dtype/device and shaped ``(n, 1, ..., 1)`` (vectors ``(n, 1,
        ..., 1, L)``) to broadcast against ``x (n, ..., C)``; ``n = B`` or, with ``rows (n,)``, the
        streams ``rows`` (one model only). Mixed batches: keys ``"<group>.<name>"``, each group's
        rows."""
        if rows is None:
            self._check_streams(x, "points")
        return self._shaped(x.dim(), x.device, x.dtype, rows)

    def _shaped(self, ndim: int, device, dtype, rows: Optional[torch.Tensor] = None) -> Dict[str, torch.Tensor]:
        if self.model is None:
            return {f"{g}.{n}": t for g, sub in self.groups.items() for n, t in sub._shaped(ndim, device, dtype).items()}
        ones = (1,) * (ndim - 2)
        out = {}
        for n in self.model.param_names:
            p = getattr(self, n)
            if rows is not None:
                p = p.index_select(0, rows)
            p = p.to(device=device, dtype=dtype)  # differentiable: float64 leaves get float32 inputs' gradients
            out[n] = p.reshape((p.shape[0],) + ones + tuple(p.shape[1:]))
        return out

    def _grouped(self, x: torch.Tensor, p: Mapping[str, torch.Tensor], fn: str, **kw) -> torch.Tensor:
        """Mixed batches: each group's ``fn`` on its streams of ``x``, back in stream order."""
        outs = []
        for g, sub in self.groups.items():
            rows = getattr(self, f"_rows_{g}")
            if rows.device != x.device:
                rows = rows.to(x.device)
            sp = {n[len(g) + 1:]: t for n, t in p.items() if n.startswith(g + ".")}
            outs.append(getattr(sub, fn)(x.index_select(0, rows), **sp, **kw))
        inv = self._inverse if self._inverse.device == x.device else self._inverse.to(x.device)
        return torch.cat(outs, 0).index_select(0, inv)

    def _lift_impl(self, uv: torch.Tensor, converged: bool = False, **p: torch.Tensor) -> torch.Tensor:
        """Every stream's model's ``_lift_impl`` on ``uv (B, ..., 2)`` with ``p`` from :meth:`_params_like`."""
        if self.model is None:
            return self._grouped(uv, p, "_lift_impl", converged=converged)
        kw = {"converged": True} if converged else {}  # only the implicit-lift models take the flag
        return self._impl[0]._lift_impl(uv, **p, **kw)

    def _project_impl(self, P: torch.Tensor, **p: torch.Tensor) -> torch.Tensor:
        if self.model is None:
            return self._grouped(P, p, "_project_impl")
        return self._impl[0]._project_impl(P, **p)

    def index_streams(self, rows: torch.Tensor) -> _StreamRows:
        """The cameras of the streams ``rows (n,)`` (int64, on the device; distinct) as an object
        with this batch's ``_params_like`` / ``_lift_impl`` for points ``(n, ..., 2)``: what the
        tracker lifts a sub-batch of streams with (no host sync)."""
        return _StreamRows(self, rows)

    def _as_float(self, x: torch.Tensor) -> torch.Tensor:
        return x if x.is_floating_point() else x.to(next(iter(self.parameters())).dtype)

    # ------------------------------------------------------------------ public maths
    def lift(self, uv: torch.Tensor, *, jacobian: str = "unrolled") -> torch.Tensor:
        """camodocal ``liftProjective`` per stream: ``uv (B, ..., 2)`` pixels -> ``(B, ..., 3)``.

        ``jacobian``: as :meth:`CameraModel.lift` (``"implicit"`` where every stream's model has it).
        """
        check_shape(uv, ("*", 2), "uv")
        self._check_streams(uv, "uv")
        uv = self._as_float(uv)
        if jacobian == "unrolled":
            return self._lift_impl(uv, **self._params_like(uv))
        if jacobian != "implicit":
            raise ValueError(f"jacobian must be 'unrolled' or 'implicit', got {jacobian!r}")
        if not self.implicit_lift:
            bad = sorted({t for t in self.model_types if not _model_of(t).implicit_lift})
            raise ValueError(f"CameraBatch.lift: jacobian='implicit' is not available for model(s) {bad}")
        return self._lift_impl(uv, converged=True, **self._params_like(uv))

    def project(self, P: torch.Tensor) -> torch.Tensor:
        """camodocal ``spaceToPlane`` per stream: ``P (B, ..., 3)`` -> pixels ``(B, ..., 2)``."""
        check_shape(P, ("*", 3), "P")
        self._check_streams(P, "P")
        P = self._as_float(P)
        return self._project_impl(P, **self._params_like(P))

    def undistort(self, uv: torch.Tensor, *, jacobian: str = "unrolled") -> torch.Tensor:
        """``(x/z, y/z)`` of :meth:`lift` per stream: ``(B, ..., 2)`` (VINS ``undistortedPoints``)."""
        P = self.lift(uv, jacobian=jacobian)
        return P[..., :2] / P[..., 2:3]

    def forward(self, P: torch.Tensor) -> torch.Tensor:
        """Same as :meth:`project`."""
        return self.project(P)


class _StreamRows:
    """Streams ``rows`` of a :class:`CameraBatch`, for points ``(n, ..., 2)`` (the tracker's
    ``_params_like`` / ``_lift_impl`` interface only).

    One model: the parameter rows are gathered (``index_select``, differentiable). Mixed models
    (which stream has which model is on the device only): the points are scattered into a full
    ``(B, ...)`` block (other streams at pixel 0, the tracker's harmless point), lifted by every
    group and the ``rows`` gathered back."""

    def __init__(self, batch: CameraBatch, rows: torch.Tensor) -> None:
        self.batch, self.rows = batch, rows

    def _params_like(self, x: torch.Tensor) -> Dict[str, torch.Tensor]:
        if self.batch.model is None:  # the full batch's (see _lift_impl)
            return self.batch._shaped(x.dim(), x.device, x.dtype)
        return self.batch._params_like(x, rows=self.rows)

    def _lift_impl(self, uv: torch.Tensor, converged: bool = False, **p: torch.Tensor) -> torch.Tensor:
        if self.batch.model is not None:
            return self.batch._lift_impl(uv, converged=converged, **p)
        full = uv.new_zeros((self.batch.num_streams,) + uv.shape[1:]).index_copy(0, self.rows, uv)
        return self.batch._lift_impl(full, converged=converged, **p).index_select(0, self.rows)


def index_streams(camera, rows: torch.Tensor):
    """``camera`` restricted to the streams ``rows``: a batch's :meth:`CameraBatch.index_streams`,
    a single camera itself (every stream shares it)."""
    sub = getattr(camera, "index_streams", None)
    return camera if sub is None else sub(rows)


__all__ = ["CameraBatch", "index_streams", "model_options", "MODEL_KEY"]
