"""A synthetic flight: a camera flying over a real photo (a plane), with the exact homographies.

Two test beds with sub-pixel truth: every frame is the photo seen through a known homography, so
where each tracked point should be is known exactly.

* :func:`synthetic_flight` (numpy + cv2, no torch): one fixed, deterministic flight over the package
  photo, rounded to uint8 frames: the tracker's test bed.
* :func:`fly_over` (torch, batched): ``B`` random flights (a ``torch.Generator`` draws them) of a
  pinhole camera over any photo, float frames, the homographies as tensors (:class:`Flight`); and
  :class:`Degradation` / :func:`degrade`: blur, gamma, exposure, vignetting and noise, drawn per image
  from the generator: the learned front end's training data (``notebooks/05_learned_frontend``).

Convention (both):
    * ``H_k`` maps texture pixels to frame-``k`` pixels, ``(x, y, 1)`` homogeneous, pixel centres at
      integer coordinates in both images; frame ``k`` -> frame ``j`` is ``H_j H_k^-1``
      (:meth:`Flight.relative`), what ``learn.tracking_loss(..., homography=...)`` takes.
    * Rendering: supersampled (bilinear, reflected border) and area-averaged, so that interpolation
      blur does not bias sub-pixel positions.

``synthetic_flight``:
    * The texture is the package photo (``package_photo``, the first EuRoC cam0 frame, 752x480).
    * Motion: ~2-3 px/frame translation, slow rotation (0.002 rad/frame) and zoom (+0.15 %/frame),
      mild perspective.
    * Rendering: 4x supersampled (``warpPerspective``, ``INTER_AREA``), rounded to uint8.
      Deterministic (no randomness).

``fly_over``:
    * The texture is a plane ``z = 0`` in the world, one texture pixel per world unit. A pinhole
      camera (focal ``max(H, W)`` px, principal point at the frame centre, world -> camera
      ``R = R_tilt R_z(yaw)``, centre ``(X, Y, -h)``) looks down at it: ``H_k = K [r1 r2 -R C]``,
      not normalised (the third coordinate of ``H_k (u, v, 1)`` is the point's depth, > 0 in view).
      ``scale = f / h`` frame pixels per texture pixel.
    * Per flight (drawn from the generator, uniform in the given ranges): the start scale, the speed
      (frame px/frame, of the centre of view) and its direction, the yaw (any) and yaw rate, the zoom
      rate (scale x ``exp(rate)`` per frame) and a linearly varying tilt (roll and pitch). The path is
      placed so that the view stays on the photo where the photo is large enough (otherwise it is
      centred and the reflected border shows).
    * Frames ``(B, T, 1, H, W)`` float grey levels 0..255 (not rounded unless ``quantize``), rendered
      in float64 on the CPU with ``supersample`` x ``supersample`` samples per pixel, then cast to
      ``dtype`` and moved to ``device``.

Degradations (:class:`Degradation`, per image, in this order, as in a camera): Gaussian blur (optics,
``blur_sigma`` px), vignetting (gain ``1 / (1 + k r^2)^2``, ``r`` the distance from the image centre
over the half diagonal), exposure (a gain), Gaussian noise (``noise_sigma`` grey levels, before the
response curve), the response curve ``255 (x / 255)^gamma``, clipping to 0..255 and (``quantize``)
rounding to integer grey levels. Deterministic given the generator's state: the same seed gives the
same parameters and the same noise, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from .._checks import as_image_batch, check_shape
from ..errors import ConfigError
from ._photo import package_photo

__all__ = ["synthetic_flight", "fly_over", "Flight", "Degradation", "degrade", "DEGRADATIONS"]

Tensor = torch.Tensor

#: supersampling factor of the rendering (per axis)
SUPERSAMPLE = 4


def synthetic_flight(n_frames: int = 16, size: Tuple[int, int] = (400, 640)
                     ) -> Tuple[List[np.ndarray], List[np.ndarray]]:
    """Frames of a camera flying over the package photo, and the exact homographies.

    Args:
        n_frames: number of frames.
        size: ``(H, W)`` of every frame, pixels.

    Returns:
        ``frames``: ``n_frames`` ``(H, W)`` uint8 arrays; ``Hs``: ``n_frames`` ``(3, 3)`` float64
        homographies texture -> frame (see the module docstring).
    """
    tex = package_photo().astype(np.float32)
    H, W = size
    frames, Hs = [], []
    s = SUPERSAMPLE
    S = np.diag([s, s, 1.0])
    for k in range(n_frames):
        a = 0.002 * k
        sc = 1.0 + 0.0015 * k
        tx, ty = 40 + 2.5 * k, 30 + 1.5 * k
        c, si = np.cos(a) * sc, np.sin(a) * sc
        # frame point = A @ texture point (texture -> frame), mild perspective
        A = np.array([[c, -si, -tx], [si, c, -ty], [2e-6 * k, -1e-6 * k, 1.0]])
        big = cv2.warpPerspective(tex, S @ A, (W * s, H * s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        img = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
        # the supersampled pixel grid: frame pixel centre x maps to big pixel centre s*x + (s-1)/2
        C = np.array([[1.0 / s, 0, (1.0 / s - 1) / 2], [0, 1.0 / s, (1.0 / s - 1) / 2], [0, 0, 1]])
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
        Hs.append(C @ S @ A)
    return frames, Hs


# --------------------------------------------------------------------------------------------------
# fly_over: batched random flights (torch)

#: supersampling factor per axis of :func:`fly_over`'s renderer (3 x 3 bilinear samples per pixel:
#: enough that the box filter, not the bilinear kernel, sets the frames' blur)
FLY_SUPERSAMPLE = 3
#: the path keeps this margin (x the view's half diagonal on the photo) from the photo's edge
VIEW_MARGIN = 1.15


def reprojection_errors(observations, homographies) -> np.ndarray:
    """Ground-truth errors of tracks on a flight (px, float64): a feature id first seen at ``uv0`` in
    frame ``k0`` must be at ``H_k H_k0^-1 uv0`` in frame ``k``. ``observations``: per frame ``(ids (n,),
    uv (n, 2))`` numpy arrays; ``homographies``: per frame ``(3, 3)`` (``synthetic_flight``'s ``Hs``).
    One error per observation after the first of its id, in frame order."""
    birth, errs = {}, []
    for k, (ids, uv) in enumerate(observations):
        for i, p in zip(np.asarray(ids).tolist(), np.asarray(uv, dtype=np.float64)):
            if i not in birth:
                birth[i] = (k, p)
                continue
            k0, p0 = birth[i]
            q = homographies[k] @ np.linalg.inv(homographies[k0]) @ np.array([p0[0], p0[1], 1.0])
            errs.append(np.hypot(*(q[:2] / q[2] - p)))
    return np.array(errs, dtype=np.float64)


@dataclass(frozen=True)
class Flight:
    """``B`` flights of ``T`` frames over a photo (module docstring, "fly_over").

    Attributes:
        frames: ``(B, T, 1, H, W)`` float grey levels 0..255.
        homographies: ``(B, T, 3, 3)`` float64, texture pixels -> frame-``k`` pixels.
    """

    frames: Tensor
    homographies: Tensor

    @property
    def batch(self) -> int:
        return int(self.frames.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[1])

    def relative(self, k: int, j: Optional[int] = None) -> Tensor:
        """``(B, 3, 3)`` float64: frame-``k`` pixels -> frame-``j`` pixels (default ``j = k + 1``)."""
        j = k + 1 if j is None else j
        return self.homographies[:, j] @ torch.linalg.inv(self.homographies[:, k])

    def pair(self, k: int, j: Optional[int] = None) -> Tuple[Tensor, Tensor, Tensor]:
        """Frames ``k`` and ``j`` (default ``k + 1``), ``(B, 1, H, W)`` each, and :meth:`relative`."""
        j = k + 1 if j is None else j
        return self.frames[:, k], self.frames[:, j], self.relative(k, j)

    def pairs(self) -> Tuple[Tensor, Tensor, Tensor]:
        """All consecutive pairs as one batch of ``B (T - 1)`` (flight-major): ``prev``, ``next``
        ``(B (T - 1), 1, H, W)`` and the homographies ``prev -> next`` ``(B (T - 1), 3, 3)``."""
        B, T = self.batch, self.n_frames
        rel = self.homographies[:, 1:] @ torch.linalg.inv(self.homographies[:, :-1])
        shape = (B * (T - 1),) + tuple(self.frames.shape[2:])
        return (self.frames[:, :-1].reshape(shape), self.frames[:, 1:].reshape(shape),
                rel.reshape(B * (T - 1), 3, 3))


def _uniform(lo_hi, n: int, g: Optional[torch.Generator], log: bool = False) -> Tensor:
    """``(n,)`` float64 uniform in ``[lo, hi]`` (log-uniform with ``log``); a number is a fixed value."""
    lo, hi = (lo_hi, lo_hi) if isinstance(lo_hi, (int, float)) else (float(lo_hi[0]), float(lo_hi[1]))
    if hi < lo or (log and lo <= 0):
        raise ConfigError(f"range {lo_hi!r}: expected lo <= hi" + (" and lo > 0" if log else ""))
    u = torch.rand(n, generator=g, dtype=torch.float64)
    if log:
        return torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
    return lo + u * (hi - lo)


def _rot_x(a: Tensor) -> Tensor:
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([o, z, z, z, c, -s, z, s, c], -1).view(*a.shape, 3, 3)


def _rot_y(a: Tensor) -> Tensor:
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, z, s, z, o, z, -s, z, c], -1).view(*a.shape, 3, 3)


def _rot_z(a: Tensor) -> Tensor:
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, -s, z, s, c, z, z, z, o], -1).view(*a.shape, 3, 3)


def _texture_batch(texture, B: int) -> Tensor:
    """The photo as ``(B, 1, Ht, Wt)`` float64 (a 2-D array/tensor or a batch of 1 or ``B``)."""
    t = torch.as_tensor(np.ascontiguousarray(texture) if isinstance(texture, np.ndarray) else texture)
    if t.dim() == 2:
        t = t[None, None]
    t = as_image_batch(t, "texture").to(device="cpu", dtype=torch.float64)  # rendered on the CPU
    if t.shape[0] not in (1, B):
        raise ValueError(f"texture: expected a batch of 1 or {B}, got {tuple(t.shape)}")
    return t.expand(B, -1, -1, -1)


def fly_over(texture, n_frames: int = 8, size: Tuple[int, int] = (192, 192), *, batch: int = 1,
             generator: Optional[torch.Generator] = None, scale=(0.85, 1.15), speed=(1.0, 4.0),
             yaw_rate: float = 0.01, zoom_rate: float = 0.005, tilt: float = 0.1, tilt_rate: float = 0.005,
             supersample: int = FLY_SUPERSAMPLE, quantize: bool = False, dtype: torch.dtype = torch.float32,
             device=None) -> Flight:
    """``batch`` random flights of a camera over a photo, with the exact homographies (module
    docstring, "fly_over").

    Args:
        texture: the photo, ``(Ht, Wt)`` (numpy or torch, uint8 or float grey levels) or
            ``(1 | batch, 1, Ht, Wt)``.
        n_frames: ``T``, frames per flight (>= 1).
        size: ``(H, W)`` of the frames, pixels.
        batch: ``B``, number of flights.
        generator: draws every random quantity (CPU ``torch.Generator``; None: the global one).
        scale: ``(lo, hi)`` start scale, frame px per texture px (a number: fixed).
        speed: ``(lo, hi)`` px/frame of the view's centre, in frame pixels.
        yaw_rate, zoom_rate, tilt_rate: maxima of ``|rate|`` (rad/frame, log-scale/frame, rad/frame).
        tilt: maximum ``|roll|``, ``|pitch|`` at the start (rad).
        supersample: samples per pixel and axis (>= 1).
        quantize: round the frames to integer grey levels (an 8-bit camera).
        dtype, device: of ``frames`` (the homographies are float64 on ``device``).

    Returns:
        :class:`Flight`.
    """
    H, W = (int(size[0]), int(size[1]))
    B, T, s = int(batch), int(n_frames), int(supersample)
    if B < 1 or T < 1 or s < 1 or H < 2 or W < 2:
        raise ConfigError(f"fly_over: need batch, n_frames, supersample >= 1 and size >= 2, got "
                          f"batch={batch}, n_frames={n_frames}, supersample={supersample}, size={size}")
    tex = _texture_batch(texture, B)
    Ht, Wt = tex.shape[-2:]
    g = generator
    # --- the flights' parameters (all drawn up front, in a fixed order: determinism)
    sc0 = _uniform(scale, B, g)
    v = _uniform(speed, B, g) / sc0  # texture px / frame
    heading = _uniform((-math.pi, math.pi), B, g)
    yaw0 = _uniform((-math.pi, math.pi), B, g)
    dyaw = _uniform((-yaw_rate, yaw_rate), B, g)
    dzoom = _uniform((-zoom_rate, zoom_rate), B, g)
    tilt0 = _uniform((-tilt, tilt), 2 * B, g).view(2, B)
    dtilt = _uniform((-tilt_rate, tilt_rate), 2 * B, g).view(2, B)
    place = torch.rand(2, B, generator=g, dtype=torch.float64)
    k = torch.arange(T, dtype=torch.float64)
    f = float(max(H, W))
    sc = sc0[:, None] * torch.exp(dzoom[:, None] * k)  # (B, T)
    h = f / sc
    # the view's half diagonal on the photo (texture px), with room for tilt and zoom
    r = VIEW_MARGIN * 0.5 * math.hypot(H, W) / sc.min(1).values * (1 + 2 * math.tan(tilt + tilt_rate * T))
    dx, dy = v * torch.cos(heading) * (T - 1), v * torch.sin(heading) * (T - 1)
    start = []
    for d, size_t, u in ((dx, Wt, place[0]), (dy, Ht, place[1])):
        lo, hi = r - torch.clamp(d, max=0), size_t - 1 - r - torch.clamp(d, min=0)
        start.append(torch.where(hi >= lo, lo + u * (hi - lo), (size_t - 1 - d) / 2))  # too small: centred
    X = start[0][:, None] + v[:, None] * torch.cos(heading)[:, None] * k
    Y = start[1][:, None] + v[:, None] * torch.sin(heading)[:, None] * k
    C = torch.stack((X, Y, -h), -1)  # (B, T, 3): the camera centre, world
    R = (_rot_x(tilt0[0][:, None] + dtilt[0][:, None] * k) @ _rot_y(tilt0[1][:, None] + dtilt[1][:, None] * k)
         @ _rot_z(yaw0[:, None] + dyaw[:, None] * k))  # (B, T, 3, 3) world -> camera
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    # not normalised: the third coordinate of H_k (u, v, 1) is the point's depth (det H_k = f^2 h > 0)
    Hs = K @ torch.stack((R[..., 0], R[..., 1], -(R @ C.unsqueeze(-1))[..., 0]), -1)  # (B, T, 3, 3)
    # --- rendering: the s x s sample positions of every frame pixel, mapped to the photo
    o = (torch.arange(s, dtype=torch.float64) + 0.5) / s - 0.5
    ys = (torch.arange(H, dtype=torch.float64)[:, None] + o).reshape(-1)
    xs = (torch.arange(W, dtype=torch.float64)[:, None] + o).reshape(-1)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    grid_h = torch.stack((gx, gy, torch.ones_like(gx)), -1).reshape(-1, 3)  # (H s W s, 3)
    Hinv = torch.linalg.inv(Hs)
    frames = torch.empty(B, T, 1, H, W, dtype=dtype, device=device)
    for t in range(T):  # one frame of every flight at a time: memory B (H s)(W s), not T times that
        q = grid_h @ Hinv[:, t].transpose(1, 2)  # (B, H s W s, 3)
        uv = q[..., :2] / q[..., 2:]
        # align_corners=True: -1 / +1 are the centres of the photo's first / last pixels
        nrm = torch.stack((uv[..., 0] * (2.0 / (Wt - 1)) - 1, uv[..., 1] * (2.0 / (Ht - 1)) - 1), -1)
        big = F.grid_sample(tex, nrm.view(B, H * s, W * s, 2), mode="bilinear", padding_mode="reflection",
                            align_corners=True)
        img = F.avg_pool2d(big, s) if s > 1 else big
        if quantize:
            img = torch.round(img).clamp(0, 255)
        frames[:, t] = img.to(dtype=dtype, device=device)
    return Flight(frames, Hs.to(device))


# --------------------------------------------------------------------------------------------------
# degradations

#: the degradation kinds, in the order they are applied
DEGRADATIONS = ("blur", "vignetting", "exposure", "noise", "gamma")
#: Gaussian blur kernels reach this many sigmas
BLUR_RADIUS_SIGMAS = 3.0


@dataclass(frozen=True)
class Degradation:
    """Per-image degradation parameters (module docstring, "Degradations"); every field ``(B,)``
    float64.

    Attributes:
        blur_sigma: Gaussian blur, px (0: none).
        vignetting: ``k`` of the gain ``1 / (1 + k r^2)^2`` (0: none; 1 darkens the corners to 1/4).
        exposure: gain (1: none).
        noise_sigma: Gaussian noise, grey levels (0: none).
        gamma: response curve exponent (1: none).
    """

    blur_sigma: Tensor
    vignetting: Tensor
    exposure: Tensor
    noise_sigma: Tensor
    gamma: Tensor

    @property
    def batch(self) -> int:
        return int(self.gamma.shape[0])

    @staticmethod
    def identity(batch: int) -> Degradation:
        """No degradation (``apply`` returns its input clipped to 0..255)."""
        z, o = torch.zeros(batch, dtype=torch.float64), torch.ones(batch, dtype=torch.float64)
        return Degradation(z, z, o, z, o)

    @staticmethod
    def sample(batch: int, generator: Optional[torch.Generator] = None, *, blur_sigma=(0.0, 1.5),
               vignetting=(0.0, 0.8), exposure=(0.5, 2.0), noise_sigma=(0.0, 6.0),
               gamma=(0.55, 1.8)) -> Degradation:
        """``batch`` degradations drawn from ``generator``: uniform in ``(lo, hi)`` (exposure and gamma
        log-uniform), a number fixes a kind (e.g. ``blur_sigma=0`` switches blur off)."""
        g = generator
        return Degradation(_uniform(blur_sigma, batch, g), _uniform(vignetting, batch, g),
                           _uniform(exposure, batch, g, log=True), _uniform(noise_sigma, batch, g),
                           _uniform(gamma, batch, g, log=True))

    def apply(self, images: Tensor, generator: Optional[torch.Generator] = None, *,
              quantize: bool = False) -> Tensor:
        """Degrade ``images (B, 1, H, W)`` (float grey levels 0..255; uint8 accepted): a new float
        tensor (``images``' float dtype, float32 for uint8), clipped to 0..255, rounded with
        ``quantize``. ``generator`` draws the noise (CPU; None: the global generator). The
        operations are differentiable in the images (except where clipped or quantized)."""
        x = as_image_batch(images, "images")
        B, _, H, W = x.shape
        for name in ("blur_sigma", "vignetting", "exposure", "noise_sigma", "gamma"):
            check_shape(getattr(self, name), (B,), name)
        dt = x.dtype if x.is_floating_point() else torch.float32
        x = x.to(dt)
        dev = x.device

        def per_image(t: Tensor) -> Tensor:
            return t.to(dtype=dt, device=dev).view(B, 1, 1, 1)

        # blur: separable Gaussian per image (one grouped conv per axis), reflected border
        smax = float(self.blur_sigma.max()) if B else 0.0
        if smax > 0:
            rad = max(1, int(math.ceil(BLUR_RADIUS_SIGMAS * smax)))
            if rad >= min(H, W):
                raise ValueError(f"blur_sigma {smax} px: kernel radius {rad} does not fit a {H}x{W} image")
            tt = torch.arange(-rad, rad + 1, dtype=torch.float64)
            sig = self.blur_sigma.to(torch.float64).clamp_min(1e-3)[:, None]
            ker = torch.exp(-0.5 * (tt / sig) ** 2)
            ker = torch.where(self.blur_sigma[:, None] > 0, ker, (tt == 0).to(torch.float64))
            ker = (ker / ker.sum(1, keepdim=True)).to(dtype=dt, device=dev)
            y = F.pad(x.view(1, B, H, W), (rad, rad, rad, rad), mode="reflect")
            y = F.conv2d(y, ker.view(B, 1, 1, -1), groups=B)
            x = F.conv2d(y, ker.view(B, 1, -1, 1), groups=B).view(B, 1, H, W)
        # vignetting: radial gain about the image centre
        yy = torch.arange(H, dtype=dt, device=dev).view(H, 1) - (H - 1) / 2
        xx = torch.arange(W, dtype=dt, device=dev).view(1, W) - (W - 1) / 2
        r2 = (xx * xx + yy * yy) / (((H - 1) / 2) ** 2 + ((W - 1) / 2) ** 2)
        x = x / (1 + per_image(self.vignetting) * r2) ** 2
        x = x * per_image(self.exposure)
        noise = torch.randn(B, 1, H, W, generator=generator, dtype=torch.float64).to(dtype=dt, device=dev)
        x = x + per_image(self.noise_sigma) * noise
        # the response curve: clamp first, a negative base has no real power
        x = 255.0 * (x.clamp(0, 255) / 255.0) ** per_image(self.gamma)
        x = x.clamp(0, 255)
        return torch.round(x) if quantize else x


def degrade(images: Tensor, generator: Optional[torch.Generator] = None, *, quantize: bool = False,
            **ranges) -> Tuple[Tensor, Degradation]:
    """Degrade every image of ``images (B, 1, H, W)`` with its own :meth:`Degradation.sample`
    (``ranges`` as there), the parameters and then the noise drawn from ``generator``:
    ``(degraded (B, 1, H, W), the Degradation)``."""
    B = as_image_batch(images, "images").shape[0]
    d = Degradation.sample(B, generator, **ranges)
    return d.apply(images, generator, quantize=quantize), d

