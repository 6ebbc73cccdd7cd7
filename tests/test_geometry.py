"""Rotation helpers (torch_frontend.geometry) against OpenCV / numpy / kornia references."""

from __future__ import annotations

import cv2
import kornia.geometry.conversions as KC
import numpy as np
import pytest
import torch
from kornia.geometry.quaternion import Quaternion

from torch_frontend.geometry import (
    R_to_quat,
    R_to_ypr,
    normalize_angle,
    quat_conj,
    quat_exp,
    quat_mul,
    quat_to_R,
    rodrigues,
    rodrigues_inverse,
    skew,
    slerp,
    wrap_angle_once,
    yaw_to_R,
    ypr_to_R,
)


def _rvecs(n, dtype, device, scale=1.5):
    g = torch.Generator().manual_seed(3)
    r = torch.randn(n, 3, generator=g, dtype=torch.float64) * scale
    r[0] = 0.0  # identity
    r[1] = torch.tensor([np.pi - 1e-9, 0, 0])  # near pi
    return r.to(device=device, dtype=dtype)


def test_rodrigues_matches_opencv(device, dtype):
    rv = _rvecs(64, dtype, device)
    R = rodrigues(rv)
    ref = np.stack([cv2.Rodrigues(r)[0] for r in rv.double().cpu().numpy()])
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert np.abs(R.double().cpu().numpy() - ref).max() < tol
    back = rodrigues(rodrigues_inverse(R))
    assert (back - R).abs().max() < (1e-10 if dtype == torch.float64 else 1e-4)


def test_quaternion_and_ypr_round_trips(device):
    R = rodrigues(_rvecs(64, torch.float64, device))
    q = R_to_quat(R)
    assert bool((q[:, 0] >= 0).all())
    assert (quat_to_R(q) - R).abs().max() < 1e-12
    assert (ypr_to_R(R_to_ypr(R)) - R).abs().max() < 1e-12
    # yaw-only rotation
    yaw = torch.tensor([10.0, -170.0, 90.0], dtype=torch.float64, device=device)
    assert torch.allclose(R_to_ypr(yaw_to_R(yaw))[:, 0], yaw)
    # ypr2R = Rz Ry Rx with degrees, against a numpy construction
    y, p, r = np.deg2rad([30.0, -20.0, 10.0])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    got = ypr_to_R(torch.tensor([30.0, -20.0, 10.0], dtype=torch.float64)).numpy()
    assert np.abs(got - Rz @ Ry @ Rx).max() < 1e-15


@pytest.mark.parametrize("a,want", [(180.0, -180.0), (-180.0, 180.0), (190.0, -170.0), (725.0, 5.0), (-30.0, -30.0)])
def test_normalize_angle_vins(a, want):
    assert float(normalize_angle(torch.tensor(a, dtype=torch.float64))) == pytest.approx(want)


def test_wrap_angle_once_single_wrap():
    got = wrap_angle_once(torch.tensor([190.0, -190.0, -540.0, 45.0], dtype=torch.float64))
    assert got.tolist() == [-170.0, 170.0, -180.0, 45.0]


def test_gradcheck_rotation_helpers():
    rv = _rvecs(6, torch.float64, "cpu")[2:].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda r: R_to_quat(rodrigues(r)), (rv,))
    assert torch.autograd.gradcheck(lambda r: rodrigues_inverse(rodrigues(r)), (rv,))
    assert torch.autograd.gradcheck(lambda r: R_to_ypr(rodrigues(r)), (rv,))
    ypr = torch.tensor([[30.0, -20.0, 10.0], [-100.0, 5.0, 3.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(ypr_to_R, (ypr,))
    # finite gradient at the identity
    z = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    rodrigues(z).sum().backward()
    assert torch.isfinite(z.grad).all()


def _randn(shape, dtype, device, seed=0, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(*shape, generator=g, dtype=torch.float64) * scale).to(device=device, dtype=dtype)


def _unit(q):
    return q / q.norm(dim=-1, keepdim=True)


def _bits_equal(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and bool((a == b).all())


# --------------------------------------------------------------------------------------------
# where kornia is used: bit-identical values and gradients


@pytest.mark.parametrize("shape", [(1000, 3), (3,), (2, 5, 3), (0, 3)])
def test_skew_is_kornia_bit_identical(device, dtype, shape):
    v = _randn(shape, dtype, device, seed=1)
    S = skew(v)
    assert S.shape == (*shape[:-1], 3, 3)
    ref = KC.vector_to_skew_symmetric_matrix(v.reshape(-1, 3)).reshape(*shape[:-1], 3, 3)
    assert _bits_equal(S, ref)
    # the cross-product matrix: skew(v) @ x = v x x
    x = _randn(shape, dtype, device, seed=2)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert torch.allclose((S @ x[..., None])[..., 0], torch.linalg.cross(v, x, dim=-1), atol=tol)
    if v.numel():
        w = _randn((*shape[:-1], 3, 3), dtype, device, seed=3)
        a, b = v.clone().requires_grad_(), v.clone().requires_grad_()
        (skew(a) * w).sum().backward()
        (KC.vector_to_skew_symmetric_matrix(b.reshape(-1, 3)).reshape(*shape[:-1], 3, 3) * w).sum().backward()
        assert _bits_equal(a.grad, b.grad)


# --------------------------------------------------------------------------------------------
# where the hand-written form is kept: equal to kornia to rounding (not bitwise; see geometry.py)


def _kornia_quat_mul(a, b):
    return (Quaternion(a) * Quaternion(b)).data


def _kornia_slerp(q0, q1, t):
    out = Quaternion(q0).slerp(Quaternion(q1), t).data
    return torch.where(out[..., :1] < 0, -out, out)


def _kornia_R_to_quat(R):
    q = KC.rotation_matrix_to_quaternion(R)
    return torch.where(q[..., :1] < 0, -q, q)


def test_quat_to_R_values_are_kornias(device, dtype):
    """Values bit-identical to kornia (non-unit input too); gradients agree to rounding only, which is
    why the hand-written form stays (it keeps optimize_6dof's gradients as they were)."""
    q = _randn((4096, 4), dtype, device, seed=4, scale=2.0)
    assert _bits_equal(quat_to_R(q), KC.quaternion_to_rotation_matrix(q))
    w = _randn((4096, 3, 3), dtype, device, seed=5)
    a, b = q.clone().requires_grad_(), q.clone().requires_grad_()
    (quat_to_R(a) * w).sum().backward()
    (KC.quaternion_to_rotation_matrix(b) * w).sum().backward()
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    assert torch.allclose(a.grad, b.grad, rtol=0, atol=tol)


@pytest.mark.parametrize("name", ["rodrigues", "rodrigues_inverse", "R_to_quat", "quat_mul", "quat_exp", "slerp"])
def test_hand_written_agree_with_kornia(device, dtype, name):
    tol = 1e-13 if dtype == torch.float64 else 5e-6
    n = 4096
    if name == "rodrigues":
        for scale in (1.0, 1e-2, 1e-5):  # both series branches and the closed form
            r = _randn((n, 3), dtype, device, seed=6, scale=scale)
            assert (rodrigues(r) - KC.axis_angle_to_rotation_matrix(r)).abs().max() < tol
        return
    R = rodrigues(_randn((n, 3), dtype, device, seed=7))
    if name == "rodrigues_inverse":
        got, ref = rodrigues_inverse(R), KC.rotation_matrix_to_axis_angle(R)
    elif name == "R_to_quat":
        got, ref = R_to_quat(R), _kornia_R_to_quat(R)
    elif name == "quat_mul":
        a, b = _randn((n, 4), dtype, device, seed=8), _randn((n, 4), dtype, device, seed=9)
        got, ref = quat_mul(a, b), _kornia_quat_mul(a, b)
    elif name == "quat_exp":
        d = _randn((n, 3), dtype, device, seed=10)
        got, ref = quat_exp(d), KC.quaternion_log_to_exp(d, eps=1e-12)
    else:
        q0, q1 = _unit(_randn((n, 4), dtype, device, seed=11)), _unit(_randn((n, 4), dtype, device, seed=12))
        t = torch.rand(n, generator=torch.Generator().manual_seed(13), dtype=torch.float64).to(device, dtype)
        got, ref = slerp(q0, q1, t), _kornia_slerp(q0, q1, t)
    assert (got - ref).abs().max() < tol


# --------------------------------------------------------------------------------------------
# quaternion algebra


def _np_qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def test_quat_mul_conj_and_matrices(device, dtype):
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    a, b = _unit(_randn((64, 4), dtype, device, seed=14)), _unit(_randn((64, 4), dtype, device, seed=15))
    ab = quat_mul(a, b)
    ref = np.stack([_np_qmul(x, y) for x, y in zip(a.double().cpu().numpy(), b.double().cpu().numpy())])
    assert np.abs(ab.double().cpu().numpy() - ref).max() < tol
    # Hamilton convention: R(a b) = R(a) R(b); conj is the inverse of a unit quaternion
    assert (quat_to_R(ab) - quat_to_R(a) @ quat_to_R(b)).abs().max() < tol
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype, device=device)
    assert (quat_mul(a, quat_conj(a)) - ident).abs().max() < tol
    assert (quat_to_R(quat_conj(a)) - quat_to_R(a).mT).abs().max() < tol
    # broadcasting over a leading shape
    assert quat_mul(a[:1], b).shape == (64, 4)


def test_quat_exp_is_rotation_by_twice_the_vector(device, dtype):
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    d = _randn((64, 3), dtype, device, seed=16, scale=0.7)
    q = quat_exp(d)
    assert (q.norm(dim=-1) - 1).abs().max() < tol
    assert (quat_to_R(q) - rodrigues(2 * d)).abs().max() < tol
    zero = torch.zeros(2, 3, dtype=dtype, device=device)
    assert quat_exp(zero).tolist() == [[1.0, 0.0, 0.0, 0.0]] * 2


def test_slerp_endpoints_midpoint_and_short_way(device, dtype):
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    R0 = rodrigues(torch.tensor([0.0, 0.0, 0.0], dtype=dtype, device=device))
    q0 = R_to_quat(R0)
    q1 = R_to_quat(rodrigues(torch.tensor([0.0, 0.0, 1.2], dtype=dtype, device=device)))
    for a, want in ((0.0, 0.0), (0.5, 0.6), (1.0, 1.2)):
        q = slerp(q0, q1, torch.tensor(a, dtype=dtype, device=device))
        assert float(q[0]) >= 0
        assert (quat_to_R(q) - rodrigues(torch.tensor([0.0, 0.0, want], dtype=dtype, device=device))).abs().max() < tol
    # -q1 is the same rotation: the same (short-way) result
    half = torch.tensor(0.5, dtype=dtype, device=device)
    assert (slerp(q0, -q1, half) - slerp(q0, q1, half)).abs().max() < tol
    # equal endpoints: no 0/0
    assert torch.isfinite(slerp(q1, q1, half)).all() and (slerp(q1, q1, half) - q1).abs().max() < tol


def test_gradcheck_quaternion_helpers():
    f64 = torch.float64
    a = _unit(_randn((5, 4), f64, "cpu", seed=17)).requires_grad_()
    b = _unit(_randn((5, 4), f64, "cpu", seed=18)).requires_grad_()
    assert torch.autograd.gradcheck(quat_mul, (a, b))
    assert torch.autograd.gradcheck(lambda q: quat_to_R(quat_conj(q)), (a,))
    d = _randn((5, 3), f64, "cpu", seed=19).requires_grad_()
    assert torch.autograd.gradcheck(quat_exp, (d,))
    assert torch.autograd.gradcheck(skew, (d,))
    t = torch.rand(5, generator=torch.Generator().manual_seed(20), dtype=f64).requires_grad_()
    assert torch.autograd.gradcheck(slerp, (a, b, t))
    # finite gradient of the zero step
    z = torch.zeros(3, dtype=f64, requires_grad=True)
    quat_exp(z).sum().backward()
    assert torch.isfinite(z.grad).all()


def test_loop_package_names_are_the_geometry_functions():
    import torch_frontend.geometry as geometry
    from torch_frontend import loop

    for name in ("R_to_quat", "R_to_ypr", "normalize_angle", "quat_to_R", "rodrigues", "rodrigues_inverse",
                 "wrap_angle_once", "yaw_to_R", "ypr_to_R"):
        assert getattr(loop, name) is getattr(geometry, name), name
