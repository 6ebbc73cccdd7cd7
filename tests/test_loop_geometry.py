"""Rotation helpers of the pose graph against OpenCV / numpy references."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torch_frontend.loop.geometry import (
    R_to_quat,
    R_to_ypr,
    normalize_angle,
    quat_to_R,
    rodrigues,
    rodrigues_inverse,
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
