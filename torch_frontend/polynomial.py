"""Real roots of polynomials, batched and branch-free (every lane finite, no host sync).

Convention:
    * Coefficients come highest degree first, in the last dimension: ``c[..., 0] x^3 + c[..., 1]
      x^2 + c[..., 2] x + c[..., 3]``; float64 recommended (the thresholds below are relative to
      float64 rounding).
    * Results have a fixed number of slots per polynomial (its degree), with an ``ok`` mask of
      which slots are real roots; slots that are not roots hold 0.
"""

from __future__ import annotations

import math

import torch

from ._cache import cached

__all__ = ["solve_cubic"]

#: a leading coefficient below this (relative to the largest one) makes the cubic a quadratic,
#: and so on down
_NEGLIGIBLE = 1e-12
#: Newton steps that polish every root on the original polynomial
_NEWTON_STEPS = 2


@cached(8)
def _phases(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """``2 pi k / 3``, k = 0, 1, 2: the trigonometric form's three roots (on ``device``, once)."""
    return (2.0 * math.pi * torch.arange(3, dtype=torch.float64) / 3.0).to(device, dtype)


def solve_cubic(c: torch.Tensor):
    """Real roots of ``c[..., 0] x^3 + c[..., 1] x^2 + c[..., 2] x + c[..., 3]`` (float64, batched).

    Args:
        c: ``(..., 4)`` coefficients, highest degree first.

    Returns:
        ``roots (..., 3)`` and ``ok (..., 3)`` bool (which slots are real roots; 0 elsewhere). Every
        lane stays finite (both branches of every ``torch.where`` are evaluated).

    Convention:
        * The coefficients are scaled by their largest magnitude; a leading coefficient below
          ``1e-12`` of it makes the polynomial a quadratic (two slots, the third not ok), a
          negligible quadratic term too a linear one (one slot), nothing left: no root.
        * Three real roots (discriminant <= 0, trigonometric form) come as largest, middle,
          smallest; one real root (Cardano) in the first slot. A double root is reported twice.
        * Every root is polished with two Newton steps on the (scaled) original cubic, kept only
          where the step is finite and small (cancellation when the leading coefficient is small
          but above the cut-off).
        * Not OpenCV's ``cv::solveCubic`` (other formulas, other order): the 7-point solver of
          ``torch_frontend.ransac`` has its own. Not ``kornia.geometry.solvers.solve_cubic``:
          measured (kornia 0.9.0) on 22 380 cubics of every kind its roots equal these in only
          12 % of rows (three-root rows in another order, max |diff| 2e-13), and it zero-pads
          instead of flagging which slots are real roots.
    """
    a, b, cc, d = c.unbind(-1)
    scale = c.abs().amax(-1).clamp_min(1e-300)
    a, b, cc, d = a / scale, b / scale, cc / scale, d / scale
    one = torch.ones_like(a)
    is_cubic = a.abs() > _NEGLIGIBLE
    a_s = torch.where(is_cubic, a, one)
    p, q, r = b / a_s, cc / a_s, d / a_s
    # depressed cubic t^3 + P t + Q, x = t - p/3
    P = q - p * p / 3.0
    Q = 2.0 * p ** 3 / 27.0 - p * q / 3.0 + r
    disc = (Q / 2.0) ** 2 + (P / 3.0) ** 3
    # one real root (disc > 0): Cardano
    sq = torch.sqrt(disc.clamp_min(0.0))
    u = -Q / 2.0 + sq
    v = -Q / 2.0 - sq
    t1 = torch.sign(u) * u.abs().pow(1.0 / 3.0) + torch.sign(v) * v.abs().pow(1.0 / 3.0)
    # three real roots (disc <= 0): trigonometric
    mneg = (-P / 3.0).clamp_min(0.0)
    m = 2.0 * torch.sqrt(mneg)
    pos = mneg > 0
    den = torch.where(pos, P * m, -one)
    arg = torch.where(pos, (3.0 * Q / den).clamp(-1.0, 1.0), torch.zeros_like(Q))
    theta = torch.acos(arg) / 3.0
    t3 = m[..., None] * torch.cos(theta[..., None] - _phases(c.device, c.dtype))
    one_root = (disc > 0)[..., None]
    roots = torch.where(one_root, t1[..., None], t3) - (p / 3.0)[..., None]
    ok = torch.cat([torch.ones_like(one_root), ~one_root, ~one_root], -1)
    # quadratic / linear fallback (OpenCV's solveCubic handles a == 0 the same way), evaluated on
    # every lane: a check for lanes that need it would be a host sync off the CPU
    is_quad = b.abs() > _NEGLIGIBLE
    b_s = torch.where(is_quad, b, one)
    qd = cc * cc - 4.0 * b * d
    sqd = torch.sqrt(qd.clamp_min(0.0))
    qr = torch.stack([(-cc + sqd) / (2.0 * b_s), (-cc - sqd) / (2.0 * b_s)], -1)
    c_s = torch.where(cc.abs() > _NEGLIGIBLE, cc, one)
    lin = -d / c_s
    quad_roots = torch.where(is_quad[..., None], qr, torch.stack([lin, lin], -1))
    quad_ok = torch.where(
        is_quad[..., None],
        (qd >= 0)[..., None].expand_as(qr),
        torch.stack([cc.abs() > _NEGLIGIBLE, torch.zeros_like(is_quad)], -1),
    )
    quad_roots = torch.cat([quad_roots, torch.zeros_like(quad_roots[..., :1])], -1)
    quad_ok = torch.cat([quad_ok, torch.zeros_like(quad_ok[..., :1])], -1)
    roots = torch.where(is_cubic[..., None], roots, quad_roots)
    ok = torch.where(is_cubic[..., None], ok, quad_ok)
    # Newton polish (guards against cancellation when |a| is small but above the cut-off)
    A, Bq, C, D = (t[..., None] for t in (a, b, cc, d))
    A3, B2 = 3.0 * A, 2.0 * Bq
    for _ in range(_NEWTON_STEPS):
        f = ((A * roots + Bq) * roots + C) * roots + D
        fp = (A3 * roots + B2) * roots + C
        big = fp.abs() > 1e-300
        step = torch.where(big, f / torch.where(big, fp, torch.ones_like(fp)), torch.zeros_like(f))
        new = roots - step
        roots = torch.where(torch.isfinite(new) & (step.abs() < 1e3 * (1.0 + roots.abs())), new, roots)
    ok = ok & torch.isfinite(roots)
    return torch.where(ok, roots, torch.zeros_like(roots)), ok
