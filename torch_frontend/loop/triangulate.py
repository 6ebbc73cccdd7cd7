"""Multi-view triangulation of feature tracks (batched linear DLT + Gauss-Newton refinement).

The loop-closure CLI builds keyframes from the front end's tracks and a pose file, without depth:
each tracked feature seen in several frames is triangulated from its normalised observations.

Convention:
    * Camera poses are **camera-to-world** ``(R_wc (..., F, 3, 3), t_wc (..., F, 3))``: a point
      ``X_c`` in camera f is ``X_w = R_wc[f] X_c + t_wc[f]``. From VINS's body-to-world pose
      ``(R_w_i, T_w_i)`` and the camera-to-body extrinsic ``(R_ic, t_ic)`` (``qic``, ``tic``):
      ``R_wc = R_w_i R_ic``, ``t_wc = R_w_i t_ic + T_w_i`` (``camera_poses``).
    * Observations are normalised image coordinates ``(x, y) = (X_c / Z_c, Y_c / Z_c)``
      (``camera.lift(uv)`` divided by its z), ``obs_norm (..., P, F, 2)`` for P tracks in F
      frames, ``mask (..., P, F)`` bool = track p is observed in frame f. Unobserved entries may
      hold anything (NaN included); they are never read.
    * Leading dims ``...`` (a batch B of streams, or none) must be equal on every argument.
    * Units: world units of ``t_wc`` (metres), angles in degrees, reprojection errors in
      normalised-plane units (multiply by the focal length for pixels).
"""

from __future__ import annotations

import math
from typing import Tuple

import torch

__all__ = ["camera_poses", "triangulate_points", "DEFAULT_MAX_REPROJ"]

#: default reprojection threshold: 3 px at VINS's virtual focal length 460 px (normalised units)
DEFAULT_MAX_REPROJ = 3.0 / 460.0

# a view counts for Gauss-Newton only in front of the camera by at least this much (world units);
# keeps 1/z finite (points on a camera centre come out of a zero-baseline DLT)
_MIN_Z = 1e-6


def camera_poses(R_w_i: torch.Tensor, T_w_i: torch.Tensor, R_ic: torch.Tensor, t_ic: torch.Tensor
                 ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Camera-to-world poses from body-to-world poses and the camera-to-body extrinsic.

    Convention:
        ``R_w_i (..., 3, 3)``, ``T_w_i (..., 3)`` body-to-world (VINS); ``R_ic (3, 3)`` / ``(..., 3, 3)``
        and ``t_ic (3,)`` / ``(..., 3)`` camera-to-body (VINS ``qic``, ``tic``). Returns
        ``R_wc = R_w_i R_ic`` and ``t_wc = R_w_i t_ic + T_w_i`` (broadcast).
    """
    if R_w_i.shape[-2:] != (3, 3):
        raise ValueError(f"R_w_i: expected shape (..., 3, 3), got {tuple(R_w_i.shape)}")
    if T_w_i.shape[-1:] != (3,):
        raise ValueError(f"T_w_i: expected shape (..., 3), got {tuple(T_w_i.shape)}")
    if R_ic.shape[-2:] != (3, 3):
        raise ValueError(f"R_ic: expected shape (..., 3, 3), got {tuple(R_ic.shape)}")
    if t_ic.shape[-1:] != (3,):
        raise ValueError(f"t_ic: expected shape (..., 3), got {tuple(t_ic.shape)}")
    return R_w_i @ R_ic, (R_w_i @ t_ic[..., None]).squeeze(-1) + T_w_i


def _check(R_wc, t_wc, obs_norm, mask, min_views):
    for name, x in (("R_wc", R_wc), ("t_wc", t_wc), ("obs_norm", obs_norm), ("mask", mask)):
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if R_wc.ndim < 3 or R_wc.shape[-2:] != (3, 3):
        raise ValueError(f"R_wc: expected shape (..., F, 3, 3), got {tuple(R_wc.shape)}")
    lead, F = tuple(R_wc.shape[:-3]), R_wc.shape[-3]
    if tuple(t_wc.shape) != lead + (F, 3):
        raise ValueError(f"t_wc: expected shape {lead + (F, 3)} (from R_wc), got {tuple(t_wc.shape)}")
    if obs_norm.ndim != len(lead) + 3 or tuple(obs_norm.shape[:len(lead)]) != lead \
            or tuple(obs_norm.shape[-2:]) != (F, 2):
        raise ValueError(f"obs_norm: expected shape {lead + ('P', F, 2)} (from R_wc), got {tuple(obs_norm.shape)}")
    P = obs_norm.shape[-3]
    if tuple(mask.shape) != lead + (P, F):
        raise ValueError(f"mask: expected shape {lead + (P, F)} (from obs_norm), got {tuple(mask.shape)}")
    if mask.dtype != torch.bool:
        raise TypeError(f"mask: expected torch.bool, got {mask.dtype}")
    if not (R_wc.is_floating_point() and t_wc.is_floating_point() and obs_norm.is_floating_point()):
        raise TypeError("R_wc, t_wc, obs_norm: expected floating point tensors")
    devs = {R_wc.device, t_wc.device, obs_norm.device, mask.device}
    if len(devs) != 1:
        raise ValueError(f"R_wc, t_wc, obs_norm, mask: expected one device, got {sorted(map(str, devs))}")
    if int(min_views) < 2:
        raise ValueError(f"min_views: expected >= 2 (one view has no depth), got {min_views}")
    return lead, P, F


def triangulate_points(
    R_wc: torch.Tensor,
    t_wc: torch.Tensor,
    obs_norm: torch.Tensor,
    mask: torch.Tensor,
    min_views: int = 2,
    min_parallax_deg: float = 1.0,
    max_reproj: float = DEFAULT_MAX_REPROJ,
    refine_iters: int = 3,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Triangulate P tracks observed in F frames of known pose; batched over leading dims.

    Convention (see the module docstring for poses and observations):
        ``R_wc (..., F, 3, 3)``, ``t_wc (..., F, 3)`` camera-to-world; ``obs_norm (..., P, F, 2)``
        normalised ``(x, y)``; ``mask (..., P, F)`` bool. Returns ``X (..., P, 3)`` world points
        (dtype of ``obs_norm``) and ``ok (..., P)`` bool.

        1. Linear DLT: the ``2F x 4`` system ``x P3 - P1 = 0, y P3 - P2 = 0`` of the observing views
           (unobserved rows zeroed), centred on the mean observing camera centre for conditioning;
           ``X`` = smallest eigenvector of ``A^T A`` (computed in float64, also for float32 input).
        2. ``refine_iters`` Gauss-Newton steps on the sum of squared normalised reprojection
           errors (3x3 normal equations per point, lightly damped; a step is kept only if it
           lowers the cost).
        3. ``ok`` = at least ``min_views`` observations, parallax >= ``min_parallax_deg`` (the
           largest angle between the world-frame ray of the first observing view and that of any
           other observing view: rotation-compensated, so a zero baseline gives ~0), depth > 0
           in every observing view, and every observing view's reprojection error (Euclidean,
           normalised units) <= ``max_reproj``.

        ``X`` of rejected points is finite but meaningless (e.g. a camera centre for a zero
        baseline, the origin for fewer than 2 views). Differentiable w.r.t. ``R_wc``, ``t_wc``
        and ``obs_norm`` (``ok`` is a mask); masked-out lanes stay finite so they never poison a
        gradient.

    Args:
        min_views: >= 2. min_parallax_deg: degrees. max_reproj: normalised units (default
            ``3 / 460``, 3 px at VINS's focal length 460). refine_iters: >= 0.

    Raises:
        ValueError/TypeError: shapes, dtypes, devices, ``min_views < 2``.
    """
    lead, P, F = _check(R_wc, t_wc, obs_norm, mask, min_views)
    if int(refine_iters) < 0:
        raise ValueError(f"refine_iters: expected >= 0, got {refine_iters}")
    B = math.prod(lead)
    dt = obs_norm.dtype
    X, ok = _triangulate_impl(
        R_wc.to(dt).reshape(B, F, 3, 3), t_wc.to(dt).reshape(B, F, 3), obs_norm.reshape(B, P, F, 2),
        mask.reshape(B, P, F), int(min_views), float(min_parallax_deg), float(max_reproj), int(refine_iters))
    return X.reshape(*lead, P, 3), ok.reshape(*lead, P)


def _project(R_cw, t_cw, X, m):
    """Camera coordinates, projections and masked residual inputs of X (B, P, 3) in every view."""
    Pc = torch.einsum("bfij,bpj->bpfi", R_cw, X) + t_cw[:, None]  # (B, P, F, 3)
    z = Pc[..., 2]
    use = m & (z > _MIN_Z)
    # z of unused views replaced by 1 so 1/z stays finite (torch.where differentiates both branches)
    zs = torch.where(use, z, torch.ones_like(z))
    return Pc, z, zs, use


def _cost(R_cw, t_cw, X, obs, m):
    Pc, z, zs, use = _project(R_cw, t_cw, X, m)
    r = (Pc[..., :2] / zs[..., None] - obs) * use[..., None]
    return (r * r).sum((-1, -2)), use


def _triangulate_impl(R_wc, t_wc, obs, m, min_views, min_parallax_deg, max_reproj, refine_iters):
    B, P, F, _ = obs.shape
    dt, dev = obs.dtype, obs.device
    # unobserved entries may be NaN: replace them (where, not multiply: NaN * 0 = NaN)
    obs = torch.where(m[..., None], obs, torch.zeros_like(obs))
    mf = m.to(dt)
    count = m.sum(-1)  # (B, P)
    R_cw = R_wc.transpose(-1, -2)
    t_cw = -(R_cw @ t_wc[..., None]).squeeze(-1)  # (B, F, 3)

    # ---- 1. linear DLT, centred on the mean observing camera centre c (conditioning: the 4th
    # column then holds the camera coordinates of c, of the size of the baseline)
    c = torch.einsum("bpf,bfi->bpi", mf, t_wc) / count.clamp_min(1)[..., None].to(dt)  # (B, P, 3)
    c_cam = torch.einsum("bfij,bpj->bpfi", R_cw, c) + t_cw[:, None]  # c in every camera (B, P, F, 3)
    x, y = obs[..., 0], obs[..., 1]
    r1, r2, r3 = R_cw[:, None, :, 0], R_cw[:, None, :, 1], R_cw[:, None, :, 2]  # (B, 1, F, 3)
    row_x = torch.cat([x[..., None] * r3 - r1, (x * c_cam[..., 2] - c_cam[..., 0])[..., None]], -1)
    row_y = torch.cat([y[..., None] * r3 - r2, (y * c_cam[..., 2] - c_cam[..., 1])[..., None]], -1)
    A = torch.stack([row_x, row_y], -2) * mf[..., None, None]  # (B, P, F, 2, 4)
    A = A.to(torch.float64)
    M = torch.einsum("bpfki,bpfkj->bpij", A, A)  # (B, P, 4, 4)
    # Lanes without two views get a fixed matrix whose smallest eigenvector is (0, 0, 0, 1) -> X = c;
    # a tiny distinct diagonal breaks exact eigenvalue ties elsewhere (eigh's backward divides by
    # eigenvalue gaps: a tie would give 0/0 = NaN gradients even where the upstream gradient is 0).
    tr = M.diagonal(dim1=-2, dim2=-1).sum(-1)  # (B, P)
    ramp = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64, device=dev)
    M = M + torch.diag_embed((1e-13 * tr[..., None] + 1e-30) * ramp)
    fallback = torch.diag(torch.tensor([2.0, 3.0, 4.0, 1.0], dtype=torch.float64, device=dev))
    M = torch.where((count >= 2)[..., None, None], M, fallback)
    _, V = torch.linalg.eigh(M)
    h = V[..., 0].to(dt)  # (B, P, 4), unit norm, sign arbitrary (cancels in h[:3] / h[3])
    w = h[..., 3]
    tiny = 1e-12 if dt == torch.float64 else 1e-6
    # a point at infinity (w ~ 0) is kept finite, far away; it fails the parallax test
    w_safe = torch.where(w.abs() > tiny, w, torch.where(w >= 0, tiny, -tiny) * torch.ones_like(w))
    X = c + h[..., :3] / w_safe[..., None]

    # ---- 2. Gauss-Newton on the reprojection error
    eye = torch.eye(3, dtype=dt, device=dev)
    cost, _ = _cost(R_cw, t_cw, X, obs, m)
    for _ in range(refine_iters):
        Pc, z, zs, use = _project(R_cw, t_cw, X, m)
        u, v = Pc[..., 0] / zs, Pc[..., 1] / zs
        uf = use.to(dt)
        r = torch.stack([u - obs[..., 0], v - obs[..., 1]], -1) * uf[..., None]  # (B, P, F, 2)
        inv_z = uf / zs
        zero = torch.zeros_like(u)
        dproj = torch.stack([torch.stack([inv_z, zero, -u * inv_z], -1),
                             torch.stack([zero, inv_z, -v * inv_z], -1)], -2)  # (B, P, F, 2, 3)
        J = dproj @ R_cw[:, None]  # d r / d X
        H = torch.einsum("bpfki,bpfkj->bpij", J, J)
        g = torch.einsum("bpfki,bpfk->bpi", J, r)
        solvable = use.sum(-1) >= 2
        lam = 1e-9 * H.diagonal(dim1=-2, dim2=-1).sum(-1) + 1e-30  # light Levenberg damping
        Hs = torch.where(solvable[..., None, None], H + lam[..., None, None] * eye, eye)
        gs = torch.where(solvable[..., None], g, torch.zeros_like(g))
        X_new = X - torch.linalg.solve(Hs, gs[..., None]).squeeze(-1)
        X_new = torch.where(torch.isfinite(X_new), X_new, X)
        cost_new, use_new = _cost(R_cw, t_cw, X_new, obs, m)
        # keep a step only if it lowers the cost without losing a view to negative depth
        better = solvable & (cost_new < cost) & (use_new.sum(-1) >= use.sum(-1))
        X = torch.where(better[..., None], X_new, X)
        cost = torch.where(better, cost_new, cost)

    # ---- 3. acceptance
    Pc, z, zs, use = _project(R_cw, t_cw, X, m)
    err = (Pc[..., :2] / zs[..., None] - obs).norm(dim=-1)  # (B, P, F)
    max_err = torch.where(m, err, torch.zeros_like(err)).amax(-1)
    depth_ok = (use == m).all(-1)
    # parallax: world rays of the observing views vs the first observing view
    with torch.no_grad():
        ray = torch.cat([obs, torch.ones_like(obs[..., :1])], -1)
        ray = torch.einsum("bfij,bpfj->bpfi", R_wc, ray)
        ray = ray / ray.norm(dim=-1, keepdim=True)
        first = torch.argmax(m.to(torch.uint8), dim=-1)  # (B, P) first True (0 if none)
        ref = torch.gather(ray, 2, first[..., None, None].expand(B, P, 1, 3))
        cosang = (ray * ref).sum(-1).clamp(-1.0, 1.0)
        min_cos = torch.where(m, cosang, torch.ones_like(cosang)).amin(-1)
        parallax_ok = min_cos <= math.cos(math.radians(min_parallax_deg))
    finite = torch.isfinite(X).all(-1)
    ok = (count >= min_views) & parallax_ok & depth_ok & (max_err <= max_reproj) & finite
    X = torch.where(finite[..., None], X, torch.zeros_like(X))
    return X, ok
