"""Rotations for the whole package: matrices, quaternions, rotation vectors, yaw/pitch/roll.

Convention:
    * Rotations are ``(..., 3, 3)`` matrices; any leading batch shape; float32 or float64; every
      function is differentiable (``torch.autograd.gradcheck`` in float64, tests/test_geometry.py).
    * Quaternions are ``(..., 4)`` **w-first** ``(w, x, y, z)`` (Eigen's constructor order, VINS's
      ``loop_info`` and ``pose_graph.txt``, kornia's order), Hamilton product; ``R_to_quat`` and
      ``slerp`` return ``w >= 0``.
    * Rotation vectors (Rodrigues, OpenCV's ``rvec``): ``(..., 3)`` radians.
    * VINS's own conventions are thin named functions: yaw/pitch/roll in **degrees**
      (``Utility::ypr2R`` / ``R2ypr``, spec §7.6): ``ypr_to_R(y, p, r) = Rz(y) @ Ry(p) @ Rx(r)``;
      its two angle wraps (``normalize_angle``, ``wrap_angle_once``), also in degrees.
    * Poses of the pose graph and of trajectories are body-to-world ``(R_w_i, T_w_i)`` as in VINS.

kornia is used where its values and gradients are bit-identical to the hand-written forms the
package's outputs (pose graph, loop closure, trajectories) are produced with; tests/test_geometry.py
asserts the identity where kornia is used and measures the difference where it is not. Each
hand-written function says what kornia's counterpart gives (measured on 10^5 random inputs).
"""

from __future__ import annotations

import math

import torch
from kornia.geometry.conversions import vector_to_skew_symmetric_matrix

__all__ = [
    "R_to_quat",
    "R_to_ypr",
    "normalize_angle",
    "quat_conj",
    "quat_exp",
    "quat_mul",
    "quat_to_R",
    "rodrigues",
    "rodrigues_inverse",
    "skew",
    "slerp",
    "wrap_angle_once",
    "yaw_to_R",
    "ypr_to_R",
]

_DEG = math.pi / 180.0


# ----------------------------------------------------------------------------------------------
# matrices and rotation vectors


def skew(v: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` -> ``(..., 3, 3)`` cross-product matrix: ``skew(v) @ x = v × x``.

    kornia's ``vector_to_skew_symmetric_matrix`` (bit-identical values and gradients), which
    takes ``(3,)`` or ``(B, 3)`` only; the leading shape is flattened around it.
    """
    return vector_to_skew_symmetric_matrix(v.reshape(-1, 3)).reshape(*v.shape[:-1], 3, 3)


def rodrigues(rvec: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` rotation vector (radians, OpenCV ``rvec``) -> ``(..., 3, 3)``.

    ``I + sin(θ)/θ K + (1 - cos θ)/θ² K²`` with ``K = skew(rvec)``, and a Taylor branch below
    θ = 1e-4 so the value and its gradient stay finite at θ = 0.
    """
    # Hand-written: kornia's axis_angle_to_rotation_matrix expands the products per entry (and
    # switches to its series at θ = 1e-3); it differs from this form by up to 1.0e-15 (float64) /
    # 5.4e-7 (float32), which moves the PnP refinement and hence the loop outputs.
    th2 = (rvec * rvec).sum(-1)
    small = th2 < 1e-8
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(th2s)
    a = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / th2s)
    K = skew(rvec)
    eye = torch.eye(3, dtype=rvec.dtype, device=rvec.device).expand_as(K)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rodrigues_inverse(R: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` -> ``(..., 3)`` rotation vector (radians), via the quaternion (stable near
    0 and pi): ``rvec = 2 atan2(|v|, w) v / |v|``."""
    # Hand-written: kornia's rotation_matrix_to_axis_angle differs by up to 1.3e-15 (float64) /
    # 7.2e-7 (float32).
    q = R_to_quat(R)
    w, v = q[..., 0], q[..., 1:]
    n2 = (v * v).sum(-1)
    small = n2 < 1e-12
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    scale = torch.where(small, 2.0 / w.clamp_min(1e-12), 2.0 * torch.atan2(n, w) / n)
    return v * scale[..., None]


# ----------------------------------------------------------------------------------------------
# quaternions (w, x, y, z)


def quat_to_R(q: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` quaternion ``(w, x, y, z)`` (normalised here) -> ``(..., 3, 3)``."""
    # Hand-written: its values are bit-identical to kornia's quaternion_to_rotation_matrix
    # (tests/test_geometry.py), but kornia's backward accumulates the products in another order
    # and differs by up to 1.4e-14 (float64) / 7.6e-6 (float32), which would move the gradients of
    # optimize_6dof. (kornia also maps the zero quaternion to the identity; here it gives NaN.)
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
    # Hand-written: kornia's rotation_matrix_to_quaternion prefers the trace branch whenever the
    # trace is positive (not the largest pivot), keeps the sign and does not renormalise; after
    # w >= 0 it differs by up to 6.7e-16 (float64) / 3.6e-7 (float32).
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


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b`` of ``(..., 4)`` quaternions (w-first; broadcasts)."""
    # Hand-written: kornia's Quaternion.__mul__ (w_a w_b - v_a·v_b, w_a v_b + w_b v_a + v_a × v_b)
    # rounds differently: up to 3.6e-15 (float64) / 1.9e-6 (float32) on Gaussian inputs.
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` conjugate ``(w, -x, -y, -z)`` (the inverse of a unit quaternion)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_exp(d: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` -> ``(..., 4)`` ``exp((0, d)) = (cos|d|, sin|d| d/|d|)``: a rotation by ``2|d|``
    about ``d`` (Ceres's ``QuaternionParameterization`` step); ``d = 0`` gives the identity (no 0/0)."""
    # Hand-written: kornia's quaternion_log_to_exp (the same map, |d| computed as s |d / s| and
    # d sin|d| / |d| in the other order) differs by up to 9.4e-16 (float64) / 5.4e-7 (float32),
    # which moves optimize_6dof's iterates.
    n = d.norm(dim=-1, keepdim=True)
    small = n < 1e-12
    ns = torch.where(small, torch.ones_like(n), n)
    return torch.cat([torch.cos(n), torch.where(small, d, torch.sin(ns) / ns * d)], -1)


def slerp(q0: torch.Tensor, q1: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Shortest-arc spherical interpolation of ``(..., 4)`` unit quaternions at ``a (...)`` in [0, 1];
    returns ``(..., 4)`` unit quaternions with ``w >= 0``."""
    # Hand-written: kornia's Quaternion.slerp (q0 exp(a log(q0⁻¹ q1))) differs by up to 5.8e-16
    # (float64) / 2.7e-7 (float32), which moves interpolated poses (trajectory.interpolate).
    d = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(d < 0, -q1, q1)  # q and -q are the same rotation: take the short way
    d = d.abs().clamp(max=1.0)
    th = torch.acos(d)
    s = torch.sin(th)
    small = s < 1e-9
    s_safe = torch.where(small, torch.ones_like(s), s)
    a = a[..., None]
    w0 = torch.where(small, 1 - a, torch.sin((1 - a) * th) / s_safe)
    w1 = torch.where(small, a, torch.sin(a * th) / s_safe)
    out = w0 * q0 + w1 * q1
    out = out / out.norm(dim=-1, keepdim=True)
    return torch.where(out[..., :1] < 0, -out, out)


# ----------------------------------------------------------------------------------------------
# VINS's yaw/pitch/roll (degrees) and angle wraps; kornia's Euler angles are radians, roll first


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
