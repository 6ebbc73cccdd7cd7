"""Property tests (hypothesis) for the camodocal camera models: round trips on random valid
calibrations with small distortion, and the Kannala-Brandt root solver against numpy's
companion-matrix root on random (also non-monotone) polynomials."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_frontend.camera import KannalaBrandtCamera, MeiCamera, PinholeCamera, PinholeFullCamera
from torch_frontend.camera.kannala_brandt import _poly_dr, effective_coefficients, solve_theta

try:
    from tests.test_camera import np_kb_theta
except ImportError:  # pragma: no cover - other import modes
    from test_camera import np_kb_theta

SETTINGS = settings(max_examples=50, deadline=None, derandomize=True)
W, H = 640, 480


def _pixels(seed, n=64):
    rng = np.random.default_rng(seed)
    uv = np.stack((rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)), -1)
    uv[:4] = [[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]]  # corners are the hardest
    return torch.from_numpy(uv)


def _round_trip(cam, seed):
    uv = _pixels(seed)
    P = cam.lift(uv)
    ok = torch.isfinite(P).all(-1) & (P[..., 2] > 0)
    assert ok.any()
    err = (cam.project(P) - uv).norm(dim=-1)[ok]
    return err.max().item()


small = st.floats(-1.0, 1.0)
# non-zero, well scaled: exact zeros trigger upstream's degree-dropping quirk (lift then ignores some
# terms that project uses) and 1e-200-size coefficients overflow numpy's companion matrix
nonzero = st.one_of(st.floats(-1.0, -0.01), st.floats(0.01, 1.0))


@SETTINGS
@given(f=st.floats(300, 700), a=st.floats(0.98, 1.02), c=st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
       k1=st.floats(-0.1, 0.1), k2=st.floats(-0.02, 0.02), p=st.tuples(small, small), seed=st.integers(0, 2**31))
def test_pinhole_round_trip(f, a, c, k1, k2, p, seed):
    cam = PinholeCamera(k1, k2, 1e-3 * p[0], 1e-3 * p[1], f, a * f, W / 2 + c[0], H / 2 + c[1],
                        width=W, height=H, undistort_iters=64)
    assert _round_trip(cam, seed) < 1e-6


@SETTINGS
@given(f=st.floats(300, 600), xi=st.floats(0.3, 2.5), c=st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
       k1=st.floats(-0.1, 0.1), k2=st.floats(-0.02, 0.02), p=st.tuples(small, small), seed=st.integers(0, 2**31))
def test_mei_round_trip(f, xi, c, k1, k2, p, seed):
    g = f * (1 + xi)
    cam = MeiCamera(xi, k1, k2, 1e-3 * p[0], 1e-3 * p[1], g, g, W / 2 + c[0], H / 2 + c[1],
                    width=W, height=H, undistort_iters=64)
    assert _round_trip(cam, seed) < 1e-6


@SETTINGS
@given(f=st.floats(200, 400), ks=st.tuples(nonzero, nonzero, nonzero, nonzero), c=st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
       seed=st.integers(0, 2**31))
def test_kb_round_trip(f, ks, c, seed):
    k = [0.02 * ks[0], 0.005 * ks[1], 0.002 * ks[2], 0.0005 * ks[3]]
    cam = KannalaBrandtCamera(*k, f, f, W / 2 + c[0], H / 2 + c[1], width=W, height=H)
    uv = _pixels(seed)
    P = cam.lift(uv)
    assert torch.allclose(P.norm(dim=-1), torch.ones(len(P), dtype=torch.float64))  # unit rays, even beyond 90°
    # pixels beyond the maximum of r(θ) have no root (upstream falls back to θ = ρ): not invertible
    rho = ((uv - torch.tensor([W / 2 + c[0], H / 2 + c[1]], dtype=torch.float64)) / f).norm(dim=-1)
    theta = torch.atan2(P[:, :2].norm(dim=-1), P[:, 2])
    r = theta + k[0] * theta**3 + k[1] * theta**5 + k[2] * theta**7 + k[3] * theta**9
    ok = (r - rho).abs() < 1e-9
    assert ok[4:].float().mean() > 0.5
    assert (cam.project(P[ok]) - uv[ok]).norm(dim=-1).max().item() < 1e-6


@SETTINGS
@given(f=st.floats(450, 700), ks=st.tuples(small, small, small, small, small, small), p=st.tuples(small, small),
       seed=st.integers(0, 2**31))
def test_pinhole_full_round_trip(f, ks, p, seed):
    k = [0.1 * ks[0], 0.02 * ks[1], 0.002 * ks[2], 0.05 * ks[3], 0.01 * ks[4], 0.001 * ks[5]]
    cam = PinholeFullCamera(*k, 1e-3 * p[0], 1e-3 * p[1], f, f, W / 2, H / 2, width=W, height=H, undistort_iters=64)
    assert _round_trip(cam, seed) < 1e-6


@SETTINGS
@given(ks=st.tuples(nonzero, nonzero, nonzero, nonzero), zero=st.integers(-1, 3), seed=st.integers(0, 2**31))
def test_kb_solver_matches_companion(ks, zero, seed):
    """Random (often non-monotone) r(θ), ρ up to 3: same smallest non-negative root as camodocal's
    companion-matrix eigenvalues, degree-dropping quirk included (zero = index of a k set to 0)."""
    k = [0.5 * ks[0], 0.1 * ks[1], 0.02 * ks[2], 0.002 * ks[3]]
    if zero >= 0:
        k[zero] = 0.0
    npow = 9 - 2 * sum(x == 0 for x in k)
    if npow > 1 and k[(npow - 3) // 2] == 0:
        return  # upstream divides by a zero leading coefficient (documented deviation, tested elsewhere)
    rho = np.random.default_rng(seed).uniform(0, 3, 256)
    kt = [torch.tensor(x, dtype=torch.float64) for x in k]
    eff = effective_coefficients(*kt)
    got = solve_theta(torch.from_numpy(rho), *eff)
    ref = np_kb_theta(rho, *k)
    # Away from tangencies (r' ~ 0 at the root, where the root is ill-conditioned and numpy's 1e-10
    # imaginary-part filter decides) the two agree to 1e-9 rad.
    slope = _poly_dr(got, *eff).numpy()
    well = slope > 1e-3
    diff = np.abs(got.numpy() - ref)
    assert np.all(diff[well] <= 1e-9 * np.maximum(1.0, ref[well])), (k, diff[well].max())
