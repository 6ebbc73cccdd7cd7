"""A rendered revisiting sequence with exact poses and injected VIO drift: the pose graph's test bed.

``torch_frontend.testing.synthetic`` (formerly ``torch_frontend.loop.synthetic``): it renders the
sequence of ``torch-frontend demo --loop`` and of the loop-closure tests.

A camera rig flies a smooth closed loop ``laps`` times inside a box-shaped room whose walls, floor
and ceiling are textured with real photos; every image is ray cast in torch, so depth, 3-D points
and poses are exact. The VIO poses are the true poses moved by a slowly accumulating drift
transform, as a visual-inertial odometry would report them.

Convention:
    * World: z up, metres. The room is ``x in [-Lx/2, Lx/2]``, ``y in [-Ly/2, Ly/2]``,
      ``z in [0, Lz]`` (default 7 x 5 x 3 m); 6 textured planes (4 walls, floor, ceiling).
    * Body frame: x forward, y left, z up. Poses are body-to-world ``(R (…, 3, 3), T (…, 3))``
      float64, as VINS. Yaw/pitch/roll in degrees (``ypr_to_R``: ``Rz(y) Ry(p) Rx(r)``; positive
      pitch = nose down).
    * Camera: pinhole without distortion (``PinholeCamera``, ``fx = fy = 0.6 W``, principal point at
      the image centre ``((W-1)/2, (H-1)/2)``; pixel centres at integer coordinates). Extrinsic
      camera-to-body ``(R_ic, t_ic)``: the camera looks along body +x,
      ``R_ic = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]``, ``t_ic = (0.05, -0.02, 0.01)`` m.
    * Trajectory: phase ``phi = 2 pi f / (keyframes_per_lap * frames_per_keyframe)`` for frame
      ``f``; an ellipse around the room centre (semi-axes 1.6 x 1.0 m, height 1.3 m +- 0.15 m),
      looking outward (yaw = ellipse normal +- 10 deg), pitch 5 +- 3 deg, roll +- 3 deg. Each lap
      is offset from the previous one (radius +5 %, centre +(8, -5) cm, height +5 cm, yaw +3 deg,
      growing smoothly with ``phi``): the second lap revisits the places of the first from slightly
      different poses (a real revisit, not a copy). Frame ``f`` is a keyframe iff
      ``f % frames_per_keyframe == 0``; times ``1.0 + f * keyframe_dt / frames_per_keyframe`` s.
    * Drift: frame ``f`` has a drift transform ``D_f(X) = R_drift[f] X + t_drift[f]`` (``D_0 = I``)
      mapping the true world into the VIO world of that frame: ``R_vio = R_drift R_gt``,
      ``T_vio = R_drift T_gt + t_drift``, and VIO map points ``X_vio = D_f(X_world)``.
      ``D_f = D_{f-1} o E_f`` with ``E_f`` a small rotation about the current true position plus a
      small translation, so the VIO *relative* motion between frames ``f-1, f`` is off by exactly
      ``E_f``: yaw ``yaw_bias_deg + N(0, yaw_drift_deg^2)`` per keyframe (per frame scaled by
      ``1/frames_per_keyframe`` and ``1/sqrt(frames_per_keyframe)``), translation
      ``trans_drift * |step| * (b + 0.5 n)`` (``b`` a fixed random unit direction, ``n ~ N(0, I)``).
      ``"4dof"``: the rotation is about z only (pitch and roll stay exact: the IMU observes them);
      ``"6dof"``: pitch and roll also random-walk (``tilt_drift_deg`` per keyframe); ``None``: none.
    * Textures: by default (``default_textures``) six distinct variants (mirrored / rotated /
      transposed, contrast-equalised with CLAHE) of one real photo shipped in the package (the first
      EuRoC cam0 frame); any six grey images can be passed instead. No part of the room repeats
      another, so places are distinguishable for BRIEF / the vocabulary.
    * Images ``(F, H, W)`` uint8 (bilinear texture lookup at the ray's hit point, rounded; rendered
      in float32); ``depth (F, H, W)`` float32 is the camera z of the surface at each pixel centre.
      ``points_3d`` ray casts any sub-pixel position exactly in float64.
    * Deterministic for a seed (numpy PCG64 for the drift; the rendering has no randomness).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F

from .._checks import check_shape
from ..camera import PinholeCamera
from ..geometry import ypr_to_R
from ..loop.keyframe import KeyFrame, _describe_impl
from ._photo import package_photo

__all__ = [
    "Room",
    "SyntheticSequence",
    "default_textures",
    "make_keyframes",
    "make_room",
    "render_loop_sequence",
]

_F64 = torch.float64
Tensor = torch.Tensor

# camera looks along body +x: camera z -> body x, camera x (right) -> body -y, camera y (down) -> body -z
R_IC_DEFAULT = ((0.0, 0.0, 1.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
T_IC_DEFAULT = (0.05, -0.02, 0.01)


# ---------------------------------------------------------------------------------- textures
def default_textures(clahe: Optional[float] = 3.0) -> List[np.ndarray]:
    """Six distinct textures from the package's own photo (the first EuRoC cam0 frame, 752x480).

    The top 96 rows (a saturated window) are cut off; the 752x384 rest is contrast-equalised with
    OpenCV's CLAHE (clip limit ``clahe``, 8x8 tiles, VINS's ``equalize`` setting; ``None``: off),
    which brings out the texture of the carpet and mattresses (about 2.5x more Shi-Tomasi corners and
    FAST corners per view), and is used in six of its eight dihedral variants (identity, mirrored left-right, rotated 180 deg, mirrored up-down and two
    transposes). BRIEF is neither mirror- nor rotation-invariant, so each variant is a different
    place for the place recognition and the matcher, and no part of the room repeats another.

    Returns:
        list of 6 ``(h, w)`` uint8 arrays: walls +x, +y, -x, -y, floor, ceiling.
    """
    import cv2

    c = np.ascontiguousarray(package_photo()[96:])
    if clahe is not None:
        c = cv2.createCLAHE(float(clahe), (8, 8)).apply(c)
    variants = [c, c[:, ::-1], c[::-1, ::-1], c[::-1, :], c.T, c.T[::-1, ::-1]]
    return [np.ascontiguousarray(v) for v in variants]


# -------------------------------------------------------------------------------------- room
@dataclass(eq=False)
class Room:
    """Textured planar rectangles; ray casting and bilinear texture lookup.

    Convention:
        Plane ``p`` is the rectangle ``origin[p] + s size[p, 0] axis_u[p] + r size[p, 1] axis_v[p]``,
        ``s, r in [0, 1]`` (``axis_u``, ``axis_v`` orthonormal, metres). Its texture ``textures[p]``
        ``(h, w)`` uint8 covers it: ``(s, r) -> texel (x, y) = (s (w - 1), r (h - 1))`` (texel
        centres at integers, bilinear). Viewed from the side the normal ``axis_u x axis_v`` points
        away from, the texture reads unmirrored.
    """

    origin: Tensor  # (P, 3) float64
    axis_u: Tensor  # (P, 3)
    axis_v: Tensor  # (P, 3)
    size: Tensor  # (P, 2)
    textures: List[Tensor]  # P x (h, w) uint8
    convex: bool = False  # True: the planes bound a convex room and rays start inside it
    _atlas: Tensor = field(init=False, repr=False)
    _tex_box: Tensor = field(init=False, repr=False)  # (P, 3): row offset, h, w

    def __post_init__(self) -> None:
        # All textures stacked in one atlas (1-texel gaps), so that shading is ONE grid_sample
        # whatever the plane. Texel coordinates are clamped inside each texture, so bilinear
        # weights of neighbouring textures are exactly 0 (no bleeding).
        Wa = max(int(t.shape[1]) for t in self.textures)
        Ha = sum(int(t.shape[0]) + 1 for t in self.textures)
        atlas = torch.zeros(Ha, Wa, dtype=torch.float32, device=self.origin.device)
        box = []
        y0 = 0
        for t in self.textures:
            h, w = t.shape
            atlas[y0:y0 + h, :w] = t.to(device=atlas.device, dtype=torch.float32)  # exact: 0..255
            box.append((y0, h, w))
            y0 += h + 1
        self._atlas = atlas[None, None]
        self._tex_box = torch.tensor(box, dtype=_F64, device=atlas.device)

    @property
    def normal(self) -> Tensor:
        """``(P, 3)`` unit normals ``axis_u x axis_v``."""
        return torch.linalg.cross(self.axis_u, self.axis_v, dim=-1)

    def cast(self, c: Tensor, d: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """Nearest hit of rays ``c + t d`` (``t > 0``) with the planes.

        Args:
            c: ``(..., 3)`` ray origins; d: ``(..., 3)`` directions (any length; broadcast with c).

        Returns:
            ``t (...)`` float64 in units of ``|d|`` (inf: no hit), ``plane (...)`` int64 (-1: no
            hit), ``st (..., 2)`` float64 plane coordinates in ``[0, 1]``.
        """
        c = c.to(_F64)
        d = d.to(_F64)
        n = self.normal
        num = (self.origin * n).sum(-1) - c @ n.T  # (..., P): n.(o - c); t = num / (n.d)
        P = n.shape[0]
        if self.convex:
            # Inside a closed convex room the nearest positive hit is the exit point, which lies on
            # the boundary: no rectangle test. In inverse depth q = 1/t = (n.d) / num the exit plane
            # is simply argmax q (q > 0: in front): one matmul and one max per pixel.
            q = (d @ n.T) / num
            qmax, plane = q.max(dim=-1)
            none = ~(qmax > 0)
            tmin = torch.where(none, torch.full_like(qmax, math.inf), 1.0 / torch.where(none, torch.ones_like(qmax), qmax))
        else:
            # general scenes: a hit must also lie inside the plane's rectangle
            den = d @ n.T
            ok = den.abs() > 1e-12
            t = num / torch.where(ok, den, torch.ones_like(den))
            co = c[..., None, :] - self.origin
            s = ((co * self.axis_u).sum(-1) + t * (d @ self.axis_u.T)) / self.size[:, 0]
            r = ((co * self.axis_v).sum(-1) + t * (d @ self.axis_v.T)) / self.size[:, 1]
            tol = 1e-9
            hit = ok & (t > 1e-9) & (s >= -tol) & (s <= 1 + tol) & (r >= -tol) & (r <= 1 + tol)
            t = torch.where(hit, t, torch.full_like(t, math.inf))
            tmin, plane = t.min(dim=-1)
            none = torch.isinf(tmin)
        # plane coordinates of the winner: (c - o).u + t d.u, gathered from one (..., 2P) matmul
        pl = plane.clamp_min(0)
        UV = torch.cat([self.axis_u, self.axis_v])  # (2P, 3)
        idx = torch.stack([pl, pl + P], -1)  # (..., 2)
        cc = ((c[..., None, :] - self.origin.repeat(2, 1)) * UV).sum(-1)  # (..., 2P), c's shape
        dd = d @ UV.T
        tt = torch.where(none, torch.zeros_like(tmin), tmin)
        proj = cc.expand(*idx.shape[:-1], 2 * P).gather(-1, idx) + tt[..., None] * dd.gather(-1, idx)
        st = proj / self.size[pl]
        plane = torch.where(none, torch.full_like(plane, -1), plane)
        return tmin, plane, st.clamp(0.0, 1.0)

    def cast_pinhole(self, c: Tensor, R: Tensor, xy1: Tensor, dtype: torch.dtype = _F64
                     ) -> Tuple[Tensor, Tensor, Tensor]:
        """``cast`` for the pixel rays of cameras: ``c + t R xy1`` for ``c (f, 3)``, ``R (f, 3, 3)``
        (camera-to-world) and ``xy1 (M, 3)`` camera rays. Returns ``t, plane, st`` of shape
        ``(f, M)`` / ``(f, M, 2)`` in ``dtype``; ``t`` is the camera z when ``xy1`` has z = 1.

        Convex rooms take a fast path: every per-ray dot product is linear in ``xy1``, so ONE
        ``(M, 3) @ (3, 3P)`` product per frame gives the inverse depths of all planes and the
        plane coordinates' direction terms (the same numbers ``cast`` computes, reassociated). The
        per-frame coefficients are formed in float64; the per-pixel work runs in ``dtype``
        (float32 halves the memory traffic of rendering; ~1e-7 relative error).
        """
        c = c.to(_F64)
        R = R.to(_F64)
        if not self.convex:
            t, plane, st = self.cast(c[:, None, :], xy1.to(_F64) @ R.transpose(-1, -2))
            return t.to(dtype), plane, st.to(dtype)
        n = self.normal
        P = n.shape[0]
        UV = torch.cat([self.axis_u, self.axis_v])  # (2P, 3)
        num = (self.origin * n).sum(-1) - c @ n.T  # (f, P): n.(o - c)
        Rt = R.transpose(-1, -2)
        Mq = (Rt @ n.T) / num[:, None, :]  # (f, 3, P): inverse depth q = (n.d)/num, linear in xy1
        M = torch.cat([Mq, Rt @ UV.T], -1).to(dtype)  # (f, 3, 3P)
        Z = xy1.to(dtype) @ M  # (f, M, 3P)
        qmax, plane = Z[..., :P].max(dim=-1)
        none = ~(qmax > 0)
        t = torch.where(none, torch.full_like(qmax, math.inf), 1.0 / torch.where(none, torch.ones_like(qmax), qmax))
        pl = plane.clamp_min(0)
        idx = torch.stack([pl, pl + P], -1)
        cc = ((c[:, None, :] - self.origin.repeat(2, 1)) * UV).sum(-1).to(dtype)  # (f, 2P)
        tt = torch.where(none, torch.zeros_like(t), t)
        proj = cc.gather(1, idx.flatten(1)).view(idx.shape) + tt[..., None] * Z[..., P:].gather(-1, idx)
        st = proj / self.size.to(dtype)[pl]
        plane = torch.where(none, torch.full_like(plane, -1), plane)
        return t, plane, st.clamp(0.0, 1.0)

    def shade(self, plane: Tensor, st: Tensor) -> Tensor:
        """Bilinear texture values ``(...)`` in ``st``'s dtype (0 where ``plane == -1``) at ``st (..., 2)``."""
        box = self._tex_box.to(st.dtype)[plane.clamp_min(0)]  # (..., 3)
        x = st[..., 0] * (box[..., 2] - 1)
        y = box[..., 0] + st[..., 1] * (box[..., 1] - 1)
        Ha, Wa = self._atlas.shape[-2:]
        grid = torch.stack([2 * x / (Wa - 1) - 1, 2 * y / (Ha - 1) - 1], -1).reshape(1, 1, -1, 2)
        v = F.grid_sample(self._atlas.to(st.dtype), grid, mode="bilinear", padding_mode="border", align_corners=True)
        v = v.reshape(plane.shape)
        return torch.where(plane >= 0, v, torch.zeros_like(v))


def _plane(centre, right, down, width, height):
    """Rectangle seen with image-right ``right`` and image-down ``down`` (unit vectors)."""
    c, r, d = (np.asarray(v, dtype=np.float64) for v in (centre, right, down))
    return c - r * width / 2 - d * height / 2, r, d, (width, height)


def make_room(size: Sequence[float] = (7.0, 5.0, 3.0), textures: Optional[Sequence] = None,
              device=None) -> Room:
    """A box room ``x in [-Lx/2, Lx/2]``, ``y in [-Ly/2, Ly/2]``, ``z in [0, Lz]``, textured inside.

    Args:
        size: ``(Lx, Ly, Lz)`` metres.
        textures: 6 ``(h, w)`` uint8 arrays/tensors for walls +x, +y, -x, -y, floor, ceiling
            (default ``default_textures()``), each read unmirrored from inside the room.
        device: torch device.
    """
    Lx, Ly, Lz = (float(v) for v in size)
    if min(Lx, Ly, Lz) <= 0:
        raise ValueError(f"size: expected positive (Lx, Ly, Lz), got {tuple(size)}")
    tex = default_textures() if textures is None else list(textures)
    if len(tex) != 6:
        raise ValueError(f"textures: expected 6 images (4 walls, floor, ceiling), got {len(tex)}")
    tex_t = []
    for i, t in enumerate(tex):
        tt = torch.as_tensor(np.ascontiguousarray(t)) if not isinstance(t, torch.Tensor) else t
        if tt.dim() != 2 or tt.dtype != torch.uint8 or min(tt.shape) < 2:
            raise ValueError(f"textures[{i}]: expected a 2-D uint8 image of at least 2x2, got "
                             f"{tt.dtype} {tuple(tt.shape)}")
        tex_t.append(tt.to(device))
    h = Lz / 2
    down = (0, 0, -1)
    planes = [
        # walls, seen from inside: looking along +x the image-right direction is -y, etc.
        _plane((Lx / 2, 0, h), (0, -1, 0), down, Ly, Lz),
        _plane((0, Ly / 2, h), (1, 0, 0), down, Lx, Lz),
        _plane((-Lx / 2, 0, h), (0, 1, 0), down, Ly, Lz),
        _plane((0, -Ly / 2, h), (-1, 0, 0), down, Lx, Lz),
        # floor (seen from above) and ceiling (from below); texture width along y
        _plane((0, 0, 0), (0, 1, 0), (1, 0, 0), Ly, Lx),
        _plane((0, 0, Lz), (0, -1, 0), (1, 0, 0), Ly, Lx),
    ]
    o, u, v, s = zip(*planes)

    def T(a):
        return torch.tensor(np.asarray(a, dtype=np.float64), dtype=_F64, device=device)

    return Room(T(o), T(u), T(v), T(s), tex_t, convex=True)


# -------------------------------------------------------------------------------- trajectory
def _trajectory(phi: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """True body poses at phases ``phi (F,)``: ``T (F, 3)``, ``ypr (F, 3)`` degrees."""
    k = phi / (2 * np.pi)  # laps flown; the lap offsets grow smoothly with it
    a, b = 1.6 * (1 + 0.05 * k), 1.0 * (1 + 0.05 * k)
    x = 0.08 * k + a * np.cos(phi)
    y = -0.05 * k + b * np.sin(phi)
    z = 1.3 + 0.15 * np.sin(3 * phi) + 0.05 * k
    # outward normal of the ellipse, then a wobble; unwrapped so yaw is continuous
    yaw = np.degrees(np.unwrap(np.arctan2(np.sin(phi) / b, np.cos(phi) / a)))
    yaw = yaw + 10.0 * np.sin(2 * phi) + 3.0 * k
    pitch = 5.0 + 3.0 * np.sin(2 * phi + 1.0)
    roll = 3.0 * np.sin(3 * phi + 0.5)
    return np.stack([x, y, z], 1), np.stack([yaw, pitch, roll], 1)


def _ypr_np(ypr: np.ndarray) -> np.ndarray:
    return ypr_to_R(torch.from_numpy(np.asarray(ypr, dtype=np.float64))).numpy()


def _drift(T_gt: np.ndarray, fpk: int, kind: Optional[str], rng: np.random.Generator, yaw_rw: float,
           yaw_bias: float, trans: float, tilt_rw: float) -> Tuple[np.ndarray, np.ndarray]:
    """Drift transforms ``(R_drift (F, 3, 3), t_drift (F, 3))`` (see the module docstring)."""
    Fn = T_gt.shape[0]
    R = np.tile(np.eye(3), (Fn, 1, 1))
    t = np.zeros((Fn, 3))
    if kind is None or Fn < 2:
        return R, t
    n = Fn - 1
    sq = 1.0 / math.sqrt(fpk)
    dyaw = yaw_bias / fpk + yaw_rw * sq * rng.standard_normal(n)
    if kind == "6dof":
        dpr = tilt_rw * sq * rng.standard_normal((n, 2))
    else:
        dpr = np.zeros((n, 2))
    bdir = rng.standard_normal(3)
    bdir[2] *= 0.3  # mostly horizontal, as a VIO's position drift
    bdir /= np.linalg.norm(bdir)
    noise = rng.standard_normal((n, 3))
    dR = _ypr_np(np.concatenate([dyaw[:, None], dpr], 1))  # (n, 3, 3)
    steps = np.linalg.norm(np.diff(T_gt, axis=0), axis=1)
    dt = trans * steps[:, None] * (bdir + 0.5 * noise)
    # D_f = D_{f-1} o E_f, E_f(X) = dR (X - p_f) + p_f + dt_f: a sequential recursion over frames
    for f in range(1, Fn):
        p = T_gt[f]
        R[f] = R[f - 1] @ dR[f - 1]
        t[f] = t[f - 1] + R[f - 1] @ (p - dR[f - 1] @ p + dt[f - 1])
    return R, t


# -------------------------------------------------------------------------------- sequence
@dataclass(eq=False)
class SyntheticSequence:
    """A rendered sequence (see the module docstring for every convention).

    Attributes:
        images ``(F, H, W)`` uint8; times ``(F,)`` float64 s; is_keyframe ``(F,)`` bool;
        keyframe_frames ``(K,)`` int64 frame index of each keyframe; phase ``(F,)`` float64 rad
        (``2 pi`` per lap); camera ``PinholeCamera``; R_ic ``(3, 3)``, t_ic ``(3,)`` camera-to-body;
        T_gt ``(F, 3)``, R_gt ``(F, 3, 3)`` true body-to-world; T_vio, R_vio drifted;
        R_drift ``(F, 3, 3)``, t_drift ``(F, 3)`` (``X_vio = R_drift X + t_drift``);
        depth ``(F, H, W)`` float32 camera z; room the scene; seed.
    """

    images: Tensor
    times: Tensor
    is_keyframe: Tensor
    keyframe_frames: Tensor
    phase: Tensor
    camera: PinholeCamera
    R_ic: Tensor
    t_ic: Tensor
    T_gt: Tensor
    R_gt: Tensor
    T_vio: Tensor
    R_vio: Tensor
    R_drift: Tensor
    t_drift: Tensor
    depth: Tensor
    room: Room
    seed: int = 0
    keyframes_per_lap: int = 64

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def num_keyframes(self) -> int:
        return int(self.keyframe_frames.shape[0])

    @property
    def lap(self) -> Tensor:
        """``(F,)`` int64 lap of each frame (0, 1, ...): ``floor(phase / 2 pi)``."""
        return torch.floor(self.phase / (2 * math.pi) + 1e-9).to(torch.long)

    def camera_pose(self, frames: Union[int, Tensor]) -> Tuple[Tensor, Tensor]:
        """True camera-to-world ``(R_w_c (..., 3, 3), T_w_c (..., 3))`` of frame index(es)."""
        fr = torch.as_tensor(frames, dtype=torch.long, device=self.T_gt.device)
        R = self.R_gt[fr]
        return R @ self.R_ic, self.T_gt[fr] + (R @ self.t_ic[:, None])[..., 0]

    def _rays(self, uv: Tensor) -> Tensor:
        """``(..., 2)`` pixels -> ``(..., 3)`` camera rays with z = 1 (pinhole, no distortion)."""
        return self.camera.lift(uv.to(_F64))

    def _points_batched(self, frames: Tensor, uv: Tensor) -> Tensor:
        """``frames (B,)``, ``uv (B, N, 2)`` -> world points ``(B, N, 3)`` (NaN where no surface)."""
        R, c = self.camera_pose(frames)
        d = self._rays(uv) @ R.transpose(-1, -2)  # (B, N, 3)
        t, plane, _ = self.room.cast(c[:, None, :], d)
        X = c[:, None, :] + t[..., None] * d
        return torch.where((plane >= 0)[..., None], X, torch.full_like(X, math.nan))

    def points_3d(self, frame: int, uv: Tensor) -> Tensor:
        """Exact world points seen at pixels ``uv (N, 2)`` of ``frame`` (ray cast in float64).

        Returns ``(N, 3)`` float64 metres (NaN where the ray hits nothing: never in a closed room).
        """
        check_shape(uv, (None, 2), "uv")
        uv = uv.to(device=self.T_gt.device)
        fr = torch.tensor([int(frame)], device=self.T_gt.device)
        return self._points_batched(fr, uv[None])[0]

    def to_vio(self, frame: int, X: Tensor) -> Tensor:
        """World points ``X (..., 3)`` -> the VIO world of ``frame``: ``R_drift X + t_drift``."""
        return X.to(_F64) @ self.R_drift[frame].T + self.t_drift[frame]

    def _visible_fraction(self, X: Tensor, ok: Tensor, j: Tensor) -> Tensor:
        """Fraction of points ``X (B, N, 3)`` (``ok`` mask) inside and unoccluded in frames ``j (B,)``."""
        R, c = self.camera_pose(j)
        Pc = (X - c[:, None, :]) @ R  # camera coordinates (B, N, 3)
        z = Pc[..., 2]
        # keep the projection finite behind the camera (those lanes are masked out below)
        uv = self.camera.project(torch.where((z > 1e-6)[..., None], Pc, torch.ones_like(Pc)))
        W, H = self.images.shape[2], self.images.shape[1]
        inside = ok & (z > 1e-6) & (uv[..., 0] >= 0) & (uv[..., 0] <= W - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= H - 1)
        # occlusion: the surface seen along that ray must be the point itself
        t, _, _ = self.room.cast(c[:, None, :], X - c[:, None, :])
        vis = inside & ((t - 1).abs() < 1e-6)
        return vis.sum(-1).to(_F64) / ok.sum(-1).clamp_min(1).to(_F64)

    def _grid(self, step: int) -> Tensor:
        H, W = self.images.shape[1:]
        ys, xs = torch.meshgrid(torch.arange(step // 2, H, step, dtype=_F64),
                                torch.arange(step // 2, W, step, dtype=_F64), indexing="ij")
        return torch.stack([xs.flatten(), ys.flatten()], -1).to(self.T_gt.device)

    def overlaps(self, i: int, j: int, step: int = 8) -> float:
        """Fraction of the surface points seen by frame ``i`` (a pixel grid with ``step``) that are
        inside frame ``j``'s image and visible (not occluded) from it. Frame indices, not keyframe
        indices; not symmetric."""
        g = self._grid(step)
        X = self._points_batched(torch.tensor([int(i)], device=g.device), g[None])
        ok = torch.isfinite(X).all(-1)
        return float(self._visible_fraction(X, ok, torch.tensor([int(j)], device=g.device))[0])

    def overlap_matrix(self, step: int = 16) -> Tensor:
        """``(K, K)`` float64: ``[a, b] = overlaps(keyframe_frames[a], keyframe_frames[b])``."""
        kf = self.keyframe_frames
        K = kf.shape[0]
        g = self._grid(step)
        X = self._points_batched(kf, g.expand(K, -1, -1))  # (K, N, 3)
        ok = torch.isfinite(X).all(-1)
        X = torch.where(ok[..., None], X, torch.zeros_like(X))
        out = torch.empty(K, K, dtype=_F64, device=kf.device)
        for b in range(K):  # one row of views at a time (keeps temporaries at K x N)
            out[:, b] = self._visible_fraction(X, ok, kf[b].expand(K))
        return out

    def revisit_pairs(self, min_overlap: float = 0.3, min_gap: int = 50, step: int = 16) -> Tensor:
        """Ground-truth loops: keyframe index pairs ``(i, j)``, ``i - j > min_gap`` (VINS only
        queries keyframes more than 50 older), whose views share at least ``min_overlap`` of their
        content both ways (``min(O[i, j], O[j, i])`` of ``overlap_matrix``). ``(P, 2)`` int64, sorted
        by ``i`` then ``j``; keyframe indices (positions in ``make_keyframes``'s list)."""
        O = self.overlap_matrix(step)
        S = torch.minimum(O, O.T)
        K = S.shape[0]
        ii, jj = torch.meshgrid(torch.arange(K), torch.arange(K), indexing="ij")
        m = ((ii - jj) > min_gap) & (S.cpu() >= min_overlap)
        return torch.stack([ii[m], jj[m]], -1)


def render_loop_sequence(
    laps: int = 2,
    keyframes_per_lap: int = 64,
    frames_per_keyframe: int = 1,
    width: int = 320,
    height: int = 240,
    drift: Optional[str] = "4dof",
    seed: int = 0,
    device=None,
    *,
    yaw_drift_deg: float = 0.1,
    yaw_bias_deg: float = 0.05,
    trans_drift: float = 0.01,
    tilt_drift_deg: float = 0.05,
    keyframe_dt: float = 0.5,
    textures: Optional[Sequence] = None,
    room_size: Sequence[float] = (7.0, 5.0, 3.0),
) -> SyntheticSequence:
    """Render a camera flying a closed loop ``laps`` times in a textured room, with VIO drift.

    Convention: see the module docstring (frames, poses, drift, camera, extrinsic).

    Args:
        laps: number of loops flown (>= 1). keyframes_per_lap: keyframes per loop (VINS only
            searches keyframes more than 50 older, so >= 60 makes revisits detectable).
        frames_per_keyframe: frames per keyframe (>= 1; the extra frames are for a tracker).
        width, height: image size in pixels (>= 16).
        drift: ``"4dof"``, ``"6dof"`` or ``None``.
        seed: drift randomness.
        device: torch device of every tensor.
        yaw_drift_deg: yaw random-walk std per keyframe (deg). yaw_bias_deg: yaw drift per keyframe.
        trans_drift: translation drift per metre flown. tilt_drift_deg: pitch/roll random-walk std
            per keyframe (``"6dof"`` only). keyframe_dt: seconds between keyframes.
        textures: 6 images for the room (default ``default_textures()``). room_size: metres.

    Returns:
        :class:`SyntheticSequence`.
    """
    if int(laps) < 1 or int(keyframes_per_lap) < 1 or int(frames_per_keyframe) < 1:
        raise ValueError(f"laps, keyframes_per_lap, frames_per_keyframe: expected >= 1, got "
                         f"{laps}, {keyframes_per_lap}, {frames_per_keyframe}")
    if int(width) < 16 or int(height) < 16:
        raise ValueError(f"width, height: expected >= 16, got {width}x{height}")
    if drift not in ("4dof", "6dof", None):
        raise ValueError(f"drift: expected '4dof', '6dof' or None, got {drift!r}")
    laps, kpl, fpk, W, H = int(laps), int(keyframes_per_lap), int(frames_per_keyframe), int(width), int(height)
    dev = torch.device(device) if device is not None else torch.device("cpu")
    room = make_room(room_size, textures, dev)
    Fn = laps * kpl * fpk
    f_idx = np.arange(Fn)
    phi = 2 * np.pi * f_idx / (kpl * fpk)
    T_np, ypr_np = _trajectory(phi)
    R_np = _ypr_np(ypr_np)
    rng = np.random.default_rng(seed)
    Rd, td = _drift(T_np, fpk, drift, rng, yaw_drift_deg, yaw_bias_deg, trans_drift, tilt_drift_deg)

    def T(a, dt=_F64):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=dev)

    f = 0.6 * W
    camera = PinholeCamera(0.0, 0.0, 0.0, 0.0, f, f, (W - 1) / 2.0, (H - 1) / 2.0, width=W, height=H,
                           camera_name="synthetic", device=dev)
    R_ic, t_ic = T(R_IC_DEFAULT), T(T_IC_DEFAULT)
    T_gt, R_gt = T(T_np), T(R_np)
    R_drift, t_drift = T(Rd), T(td)
    seq = SyntheticSequence(
        images=torch.empty(0), times=T(1.0 + f_idx * keyframe_dt / fpk), is_keyframe=T(f_idx % fpk == 0, torch.bool),
        keyframe_frames=T(f_idx[f_idx % fpk == 0], torch.long), phase=T(phi), camera=camera, R_ic=R_ic, t_ic=t_ic,
        T_gt=T_gt, R_gt=R_gt, T_vio=(R_drift @ T_gt[..., None])[..., 0] + t_drift, R_vio=R_drift @ R_gt,
        R_drift=R_drift, t_drift=t_drift, depth=torch.empty(0), room=room, seed=int(seed), keyframes_per_lap=kpl,
    )
    seq.images, seq.depth = _render(seq, H, W)
    return seq


def _render(seq: SyntheticSequence, H: int, W: int, chunk_pixels: int = 1 << 16) -> Tuple[Tensor, Tensor]:
    """Ray cast every frame: ``(F, H, W)`` uint8 images and float32 depth (camera z)."""
    dev = seq.T_gt.device
    ys, xs = torch.meshgrid(torch.arange(H, dtype=_F64, device=dev), torch.arange(W, dtype=_F64, device=dev),
                            indexing="ij")
    rays = seq._rays(torch.stack([xs, ys], -1).reshape(-1, 2))  # (HW, 3), z = 1 -> t is the depth
    Fn = seq.T_gt.shape[0]
    images = torch.empty(Fn, H, W, dtype=torch.uint8, device=dev)
    depth = torch.empty(Fn, H, W, dtype=torch.float32, device=dev)
    step = max(1, chunk_pixels // (H * W))  # frames per chunk: temporaries stay ~ chunk_pixels x 6 planes
    for f0 in range(0, Fn, step):
        fr = torch.arange(f0, min(Fn, f0 + step), device=dev)
        R, c = seq.camera_pose(fr)
        t, plane, st = seq.room.cast_pinhole(c, R, rays, torch.float32)
        v = seq.room.shade(plane, st)
        images[fr] = v.round().clamp(0, 255).to(torch.uint8).reshape(-1, H, W)
        depth[fr] = t.to(torch.float32).reshape(-1, H, W)
    return images, depth


# ------------------------------------------------------------------------------- keyframes
def make_keyframes(
    seq: SyntheticSequence,
    max_points: int = 150,
    min_dist: float = 20,
    sequence: int = 1,
    *,
    keyframes: Optional[Sequence[int]] = None,
    point_noise: float = 0.0,
    fast_threshold: int = 20,
    pattern=None,
    save_image: bool = False,
) -> List[KeyFrame]:
    """Pose-graph keyframes of ``seq``, as a VIO would hand them over (spec §7.1).

    Per keyframe (in ``seq.keyframe_frames`` order): Shi-Tomasi corners
    (``good_features_to_track(max_points, 0.01, min_dist)``, one batched call over all keyframes)
    as the tracked features; their exact 3-D points mapped into the VIO world of that keyframe
    (``X_vio = R_drift X + t_drift``, plus ``N(0, point_noise^2)`` metres per coordinate if
    ``point_noise > 0``, drawn from ``seq.seed``); normalized coordinates ``lift(uv)/z``; ids unique
    across the sequence (running count); pose = the VIO pose; FAST + BRIEF descriptors
    (``describe_keyframes``: all keyframes in one call on a GPU, one per call on CPU, where that is
    2.4x faster). Deterministic.

    ``keyframes``: optional keyframe indices (positions in ``seq.keyframe_frames``) to make only
    those (e.g. for a quick test); default all.

    Returns:
        list of :class:`KeyFrame` (``index`` -1, ``sequence`` as given).
    """
    from ..corners import good_features_to_track

    kf = seq.keyframe_frames
    if keyframes is not None:
        sel = torch.as_tensor(list(keyframes), dtype=torch.long)
        if sel.numel() and (int(sel.min()) < 0 or int(sel.max()) >= kf.shape[0]):
            raise ValueError(f"keyframes: expected indices in [0, {kf.shape[0]}), got {sel.tolist()}")
        kf = kf[sel.to(kf.device)]
    if kf.numel() == 0:
        return []
    imgs = seq.images[kf][:, None]  # (K, 1, H, W)
    pts, valid = good_features_to_track(imgs, int(max_points), 0.01, float(min_dist))
    X = seq._points_batched(kf, pts.to(_F64))  # (K, N, 3)
    valid = valid & torch.isfinite(X).all(-1)
    X = torch.where(valid[..., None], X, torch.zeros_like(X))
    Xv = X @ seq.R_drift[kf].transpose(-1, -2) + seq.t_drift[kf][:, None, :]
    if point_noise > 0:
        g = torch.Generator().manual_seed(int(seq.seed) + 1)
        Xv = Xv + float(point_noise) * torch.randn(Xv.shape, generator=g, dtype=_F64).to(Xv.device)
    uv = pts.to(torch.float32)
    # Described in chunks of keyframes (one batched call per chunk): BRIEF's temporaries are
    # (chunk, K, 256) int64. On CPU one keyframe per call is fastest (measured 0.031 s/keyframe vs
    # 0.074 with 16 per call, 320x240, ~800 FAST corners: the temporaries then stay in cache and
    # nothing is padded to the largest K); on a GPU all keyframes go in one call.
    per = kf.shape[0] if kf.device.type != "cpu" else 1
    chunks = [_describe_impl(imgs[b0:b0 + per], seq.camera, uv[b0:b0 + per], valid[b0:b0 + per],
                             int(fast_threshold), pattern, None) for b0 in range(0, kf.shape[0], per)]
    norm = seq._rays(uv)[..., :2]
    out: List[KeyFrame] = []
    next_id = 0
    for b in range(kf.shape[0]):  # per keyframe object (not per point)
        m = valid[b]
        n = int(m.sum())
        f = int(kf[b])
        ids = torch.arange(next_id, next_id + n, dtype=torch.int64, device=kf.device)
        next_id += n
        d = {k: v[b % per:b % per + 1] for k, v in chunks[b // per].items()}
        d["window_brief"] = d["window_brief"][:, m]
        out.append(KeyFrame._assemble(
            float(seq.times[f]), sequence, seq.T_vio[f].clone(), seq.R_vio[f].clone(), Xv[b][m].clone(),
            uv[b][m].clone(), norm[b][m].clone(), ids, d, 0, seq.images[f].clone() if save_image else None))
    return out
