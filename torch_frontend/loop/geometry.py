"""Rotation helpers of VINS's pose graph: yaw/pitch/roll in degrees, quaternions, Rodrigues.

Convention:
    * Rotations are ``(..., 3, 3)`` matrices; any leading batch shape; float32 or float64; every
      function is differentiable (``torch.autograd.gradcheck`` in float64, tests/test_loop_geometry.py).
    * Yaw/pitch/roll are in **degrees** as in VINS (``Utility::ypr2R`` / ``R2ypr``, spec §7.6):
      ``ypr_to_R(y, p, r) = Rz(y) @ Ry(p) @ Rx(r)``.
    * Quaternions are ``(..., 4)`` **w-first** ``(w, x, y, z)`` (Eigen's constructor order, VINS's
      ``loop_info`` and ``pose_graph.txt``); ``R_to_quat`` returns ``w >= 0``.
    * Rotation vectors (Rodrigues, OpenCV's ``rvec``): ``(..., 3)`` radians.
    * Poses in the pose graph are body-to-world ``(R_w_i, T_w_i)`` as in VINS.
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "R_to_quat",
    "R_to_ypr",
    "normalize_angle",
    "quat_to_R",
    "rodrigues",
    "rodrigues_inverse",
    "wrap_angle_once",
    "yaw_to_R",
    "ypr_to_R",
]

_DEG = math.pi / 180.0


def _rot_z(a: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(*a.shape, 3, 3)


def _rot_y(a: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(*a.shape, 3, 3)


def _rot_x(a: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(*a.shape, 3, 3)


def ypr_to_R(ypr: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` yaw, pitch, roll in degrees -> ``(..., 3, 3)`` ``Rz(y) Ry(p) Rx(r)``."""
    a = ypr * _DEG
    return _rot_z(a[..., 0]) @ _rot_y(a[..., 1]) @ _rot_x(a[..., 2])


def yaw_to_R(yaw: torch.Tensor) -> torch.Tensor:
    """``(...)`` yaw in degrees -> ``(..., 3, 3)`` rotation about z (``ypr2R(yaw, 0, 0)``)."""
    return _rot_z(yaw * _DEG)


def R_to_ypr(R: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` -> ``(..., 3)`` yaw, pitch, roll in degrees, VINS's ``R2ypr`` formulas.

    With columns ``n, o, a`` of R: ``y = atan2(n_y, n_x)``,
    ``p = atan2(-n_z, n_x cos y + n_y sin y)``, ``r = atan2(a_x sin y - a_y cos y, -o_x sin y + o_y cos y)``.
    """
    n, o, a = R[..., :, 0], R[..., :, 1], R[..., :, 2]
    y = torch.atan2(n[..., 1], n[..., 0])
    cy, sy = torch.cos(y), torch.sin(y)
    p = torch.atan2(-n[..., 2], n[..., 0] * cy + n[..., 1] * sy)
    r = torch.atan2(a[..., 0] * sy - a[..., 1] * cy, -o[..., 0] * sy + o[..., 1] * cy)
    return torch.stack([y, p, r], -1) / _DEG


def normalize_angle(a: torch.Tensor) -> torch.Tensor:
    """VINS's ``Utility::normalizeAngle`` (degrees): maps into [-180, 180), with +180 -> -180.

    ``a > 0: a - 360 floor((a + 180) / 360)``, else ``a + 360 floor((-a + 180) / 360)``.
    """
    return torch.where(a > 0, a - 360.0 * torch.floor((a + 180.0) / 360.0),
                       a + 360.0 * torch.floor((-a + 180.0) / 360.0))


def wrap_angle_once(a: torch.Tensor) -> torch.Tensor:
    """The Ceres functors' single-wrap ``NormalizeAngle`` (degrees): ``a > 180 -> a - 360``,
    ``a < -180 -> a + 360``, else unchanged (only one wrap; VINS's residual quirk)."""
    return torch.where(a > 180.0, a - 360.0, torch.where(a < -180.0, a + 360.0, a))


def quat_to_R(q: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` quaternion ``(w, x, y, z)`` (normalised here) -> ``(..., 3, 3)``."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def R_to_quat(R: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` -> ``(..., 4)`` unit quaternion ``(w, x, y, z)`` with ``w >= 0``.

    Shepperd's method: each of the four candidate formulas divides by the square root of its own
    pivot; the largest pivot is chosen per rotation so the division is well conditioned. The
    other branches are evaluated with a clamped pivot so they stay finite (``torch.where``
    differentiates every branch, and a NaN there would poison the gradient).
    """
    m = R
    t = torch.stack([
        1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2],
        1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
        1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
        1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
    ], -1)
    s = 2 * torch.sqrt(t.clamp_min(1e-12))  # (..., 4)
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s21, s02, s10 = m[..., 2, 1] + m[..., 1, 2], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1]
    cands = torch.stack([
        torch.stack([s[..., 0] / 4, d21 / s[..., 0], d02 / s[..., 0], d10 / s[..., 0]], -1),
        torch.stack([d21 / s[..., 1], s[..., 1] / 4, s10 / s[..., 1], s02 / s[..., 1]], -1),
        torch.stack([d02 / s[..., 2], s10 / s[..., 2], s[..., 2] / 4, s21 / s[..., 2]], -1),
        torch.stack([d10 / s[..., 3], s02 / s[..., 3], s21 / s[..., 3], s[..., 3] / 4], -1),
    ], -2)  # (..., 4 candidates, 4)
    k = t.argmax(-1)
    q = cands.gather(-2, k[..., None, None].expand(*k.shape, 1, 4)).squeeze(-2)
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0).to(q.dtype)
    return q / q.norm(dim=-1, keepdim=True)


def rodrigues(rvec: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` rotation vector (radians, OpenCV ``rvec``) -> ``(..., 3, 3)``.

    Uses ``sin(θ)/θ`` and ``(1 - cos θ)/θ²`` with a Taylor branch below θ = 1e-4 (float64) so the
    value and its gradient stay finite at θ = 0.
    """
    th2 = (rvec * rvec).sum(-1)
    small = th2 < 1e-8
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(th2s)
    a = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / th2s)
    x, y, z = rvec.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*rvec.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=rvec.dtype, device=rvec.device).expand_as(K)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rodrigues_inverse(R: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` -> ``(..., 3)`` rotation vector (radians), via the quaternion (stable near
    0 and pi): ``rvec = 2 atan2(|v|, w) v / |v|``."""
    q = R_to_quat(R)
    w, v = q[..., 0], q[..., 1:]
    n2 = (v * v).sum(-1)
    small = n2 < 1e-12
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    scale = torch.where(small, 2.0 / w.clamp_min(1e-12), 2.0 * torch.atan2(n, w) / n)
    return v * scale[..., None]
