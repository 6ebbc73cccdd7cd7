"""Tests of ``torch_frontend.polynomial.solve_cubic`` (the cubic of Lambda Twist P3P).

Oracle: ``numpy.roots`` (companion-matrix eigenvalues) on random cubics with three or one real
roots, and the exact roots of constructed quadratics, linear and constant polynomials.
"""

from __future__ import annotations

import numpy as np
import torch

from torch_frontend.polynomial import solve_cubic


def _real_roots(c: np.ndarray) -> np.ndarray:
    """numpy's real roots of one cubic (imaginary part below 1e-7 of the magnitude), sorted."""
    r = np.roots(c)
    return np.sort(r[np.abs(r.imag) <= 1e-7 * np.maximum(1.0, np.abs(r))].real)


def test_cubic_roots_match_numpy(device):
    """Three real roots come largest, middle, smallest; one real root in the first slot (the
    others not ok, 0); every root to 1e-9 of numpy's."""
    rng = np.random.default_rng(0)
    three = np.stack([np.poly(np.sort(rng.normal(size=3) * 10.0)) * rng.choice([-2.0, 0.5, 3.0]) for _ in range(400)])
    one = np.stack([np.poly([r, complex(u, v), complex(u, -v)]).real
                    for r, u, v in rng.normal(size=(400, 3)) * [5.0, 3.0, 1.0] + [0.0, 0.0, 0.5]])
    c = torch.from_numpy(np.concatenate([three, one])).to(device)
    roots, ok = solve_cubic(c)
    roots, ok = roots.cpu().numpy(), ok.cpu().numpy()
    assert ok[:400].all() and (np.diff(roots[:400], axis=1) <= 0).all()
    assert ok[400:, 0].all() and not ok[400:, 1:].any() and (roots[400:, 1:] == 0).all()
    for i in range(len(c)):
        ref = _real_roots(c[i].cpu().numpy())
        got = np.sort(roots[i][ok[i]])
        assert len(got) == len(ref) and np.allclose(got, ref, rtol=1e-9, atol=1e-9), (i, got, ref)


def test_lower_degrees_and_nothing(device):
    """A leading coefficient below 1e-12 of the largest: the quadratic's roots (two, one double
    reported twice, or none), the linear root, or no root for a constant; every lane finite, the
    slots that are not roots 0. Lanes of every kind in one batch (the fallback is evaluated on all
    lanes, no host check)."""
    c = torch.tensor([
        [0.0, 1.0, -3.0, 2.0],  # (x - 1)(x - 2)
        [0.0, 2.0, -4.0, 2.0],  # 2 (x - 1)^2: a double root
        [0.0, 1.0, 0.0, 1.0],  # x^2 + 1: no real root
        [0.0, 0.0, 4.0, -2.0],  # 4 x - 2
        [0.0, 0.0, 0.0, 5.0],  # constant
        [0.0, 0.0, 0.0, 0.0],
        [1.0, -6.0, 11.0, -6.0],  # (x - 1)(x - 2)(x - 3) in the same batch
        [1e-14, 1.0, -3.0, 2.0],  # (x - 1)(x - 2) with a negligible cubic term
    ], dtype=torch.float64, device=device)
    roots, ok = solve_cubic(c)
    assert torch.isfinite(roots).all() and (roots[~ok] == 0).all()
    roots, ok = roots.cpu(), ok.cpu()
    assert ok.tolist() == [[True, True, False], [True, True, False], [False, False, False],
                           [True, False, False], [False, False, False], [False, False, False],
                           [True, True, True], [True, True, False]]
    assert torch.allclose(roots[0, :2].sort().values, torch.tensor([1.0, 2.0], dtype=torch.float64))
    assert torch.equal(roots[1, :2], torch.ones(2, dtype=torch.float64))
    assert torch.allclose(roots[3, 0], torch.tensor(0.5, dtype=torch.float64))
    assert torch.allclose(roots[6], torch.tensor([3.0, 2.0, 1.0], dtype=torch.float64))
    assert torch.allclose(roots[7, :2].sort().values, torch.tensor([1.0, 2.0], dtype=torch.float64))


def test_batch_shapes_and_independence():
    """Any leading shape; a lane's roots do not depend on the other lanes (bit for bit)."""
    g = torch.Generator().manual_seed(5)
    c = torch.randn(6, 5, 4, dtype=torch.float64, generator=g)
    c[2, 3, 0] = 0.0  # a quadratic among cubics
    roots, ok = solve_cubic(c)
    assert roots.shape == ok.shape == (6, 5, 3)
    for i, j in ((0, 0), (2, 3), (5, 4)):
        r1, o1 = solve_cubic(c[i, j][None])
        assert torch.equal(r1[0], roots[i, j]) and torch.equal(o1[0], ok[i, j])
