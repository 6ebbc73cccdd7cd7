"""camodocal ``EquidistantCamera``: Kannala-Brandt / equidistant fisheye (``KANNALA_BRANDT``). Spec §4.3."""

from __future__ import annotations

from typing import Any, Dict, Tuple

import torch

from .._autodiff import is_wrapper
from .base import CameraModel, check_iters, safe_norm2


def _poly_r(theta: torch.Tensor, k2, k3, k4, k5) -> torch.Tensor:
    """``r(θ) = θ + k2 θ³ + k3 θ⁵ + k4 θ⁷ + k5 θ⁹`` (camodocal's implicit k1 = 1)."""
    t2 = theta * theta
    t3 = t2 * theta
    t5 = t3 * t2
    t7 = t5 * t2
    t9 = t7 * t2
    return theta + k2 * t3 + k3 * t5 + k4 * t7 + k5 * t9


def _poly_dr(theta: torch.Tensor, k2, k3, k4, k5) -> torch.Tensor:
    s = theta * theta
    return 1 + s * (3 * k2 + s * (5 * k3 + s * (7 * k4 + s * (9 * k5))))


#: the odd powers of k2..k5 in r(θ)
_POWERS = (3, 5, 7, 9)


def effective_coefficients(k2, k3, k4, k5) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Upstream's degree-dropping quirk, as tensor ops (no host sync).

    camodocal sets the polynomial degree to ``9 - 2·(number of k2..k5 exactly 0)`` regardless of
    *which* are zero, so a zero ``k3`` drops the ``k5 θ⁹`` term. Terms above that degree are zeroed
    here. (If the surviving leading coefficient is itself 0 — e.g. only ``k4 == 0`` — upstream divides
    by it and its eigen-solver sees inf/NaN; we instead solve the polynomial with that zero term
    simply absent. Shipped calibrations have four non-zero coefficients, so none of this applies.)
    """
    ks = torch.stack((k2, k3, k4, k5))
    npow = 9 - 2 * (ks == 0).sum(0)
    # the powers 3, 5, 7, 9 compared one by one with Python numbers: a per-call tensor of them would
    # be a blocking host-to-device copy on CUDA
    keep = torch.stack([npow >= power for power in _POWERS])
    ks = torch.where(keep, ks, torch.zeros_like(ks))
    return ks[0], ks[1], ks[2], ks[3]


def critical_points(k2, k3, k4, k5) -> torch.Tensor:
    """Positive θ where ``r'(θ) = 0``, ascending, padded with +inf: shape ``(4,)``, float64, detached.

    ``r'(θ) = 1 + 3k2 s + 5k3 s² + 7k4 s³ + 9k5 s⁴`` with ``s = θ²``. With ``t = 1/s`` this is the
    *monic* quartic ``t⁴ + 3k2 t³ + 5k3 t² + 7k4 t + 9k5`` whatever coefficients are zero, so its
    companion matrix always exists. Between consecutive critical points ``r`` is monotone, which is
    what lets the per-pixel solver bracket the *smallest* root. Roots with a small imaginary part are
    kept on purpose: an extra split point inside a monotone interval is harmless, a missed one is not.
    """
    c = torch.stack((k2, k3, k4, k5)).detach().to(torch.float64)
    a = torch.stack((9 * c[3], 7 * c[2], 5 * c[1], 3 * c[0]))  # constant .. t³ coefficient
    comp = torch.zeros(4, 4, dtype=torch.float64, device=c.device)
    comp[1:, :3] = torch.eye(3, dtype=torch.float64, device=c.device)
    comp[:, 3] = -a
    t = torch.linalg.eigvals(comp)
    keep = (t.real > 0) & (t.imag.abs() <= 1e-6 * t.abs())
    tr = torch.where(keep, t.real, torch.zeros_like(t.real))
    theta = torch.where(keep, 1.0 / torch.sqrt(torch.where(keep, tr, torch.ones_like(tr))), torch.full_like(tr, float("inf")))
    return torch.sort(theta).values


def _root_bound(rho: torch.Tensor, k2, k3, k4, k5) -> torch.Tensor:
    """Fujiwara bound on the roots of ``r(θ) - ρ`` (all coefficient moduli, leading one non-zero):
    ``|θ| <= 2 max_i |a_i / a_n|^(1/(n - i))`` (the ``a_0`` term halved). Much tighter than Cauchy's
    ``1 + max|a_i/a_n|`` for small leading coefficients (``k5 ~ 1e-4`` gives ~8 instead of ~1e4), which
    keeps the last bracket short."""
    coeffs = [(3, k2), (5, k3), (7, k4), (9, k5)]
    deg = torch.ones_like(k2)
    lead = torch.ones_like(k2)
    for p, k in coeffs:
        deg = torch.where(k != 0, torch.full_like(deg, p), deg)
        lead = torch.where(k != 0, k, lead)
    lead = lead.abs()
    terms = []
    for i, a in [(0, 0.5 * rho), (1, torch.ones_like(k2))] + coeffs[:3]:
        e = deg - i
        ok = e > 0
        val = (a.abs() / lead) ** (1.0 / torch.where(ok, e, torch.ones_like(e)))
        terms.append(torch.where(ok, val, torch.zeros_like(val)))
    b = terms[0]
    for t in terms[1:]:
        b = torch.maximum(b, t)
    # a hair above the bound so that a root exactly on it still gives f(B) >= 0 after rounding
    return 2.0 * b * (1.0 + 1e-12) + 1e-300


def solve_theta(rho: torch.Tensor, k2, k3, k4, k5, iters: int = 50, crit=None) -> torch.Tensor:
    """Smallest non-negative root θ of ``r(θ) = ρ`` (upstream: smallest kept companion-matrix eigenvalue).

    Args:
        rho: ``(...)`` non-negative radii in normalised units.
        k2..k5: 0-d coefficients (already degree-reduced by ``effective_coefficients``).
        iters: safeguarded Newton iterations, a fixed count (no host sync). The shipped calibrations
            converge to 1e-14 rad in 5; random non-monotone polynomials needed up to ~40 (bisection
            fallbacks), so the default is 50.
        crit: ``critical_points(k2, k3, k4, k5)`` when the caller has it (a camera keeps it while
            its coefficients are unchanged: the eigen-solver waits for the device).

    Returns:
        ``(...)`` θ in radians; ``θ = ρ`` where no non-negative root exists (upstream's fallback).

    Method: the endpoints ``0 < c_1 < ... < c_m < B`` (critical points of ``r``, and a bound ``B`` on
    the roots of ``r(θ) - ρ`` from ``_root_bound``) cut ``[0, B]`` into intervals where ``f = r - ρ``
    is monotone.
    ``f(0) = -ρ < 0``, so the first endpoint with ``f >= 0`` closes the interval holding the smallest
    root, which is unique there. Newton from ``θ₀ = ρ`` clamped into that bracket, falling back to
    bisection whenever a step leaves the bracket, shrinks it. The loop runs on detached tensors; one
    final pair of Newton steps on the graph (:func:`newton_attach`) gives the exact implicit
    derivatives ``dθ/dρ = 1/r'(θ)``, ``dθ/dk_i = -θ^(2i-1)/r'(θ)`` and their exact second derivatives.
    """
    dt = rho.dtype
    kd = [k.detach() for k in (k2, k3, k4, k5)]
    crit = (critical_points(*kd) if crit is None else crit).to(device=rho.device, dtype=dt)
    r = rho.detach()
    bound = _root_bound(r, *kd)
    ends = torch.cat(
        (torch.zeros_like(r)[..., None], torch.minimum(crit, bound[..., None]), bound[..., None]), dim=-1
    )  # (..., 6), non-decreasing
    fe = _poly_r(ends, *kd) - r[..., None]
    pos = fe >= 0
    has = pos.any(dim=-1)
    j = torch.argmax(pos.to(torch.int8), dim=-1)  # first endpoint with f >= 0
    hi = torch.gather(ends, -1, j[..., None])[..., 0]
    lo = torch.gather(ends, -1, (j - 1).clamp(min=0)[..., None])[..., 0]
    theta = torch.minimum(torch.maximum(r, lo), hi)
    # Safeguarded Newton ("rtsafe"): a Newton step is taken only if it stays in the bracket and at
    # least halves the previous step, otherwise bisect; so the worst case is bisection speed (a
    # degree-9 polynomial far from its root would make plain Newton crawl by 8/9 per step).
    dx_old = hi - lo
    eps = torch.finfo(dt).eps
    c3, c5, c7, c9 = 3 * kd[0], 5 * kd[1], 7 * kd[2], 9 * kd[3]
    for _ in range(iters):
        # Horner in s = θ² (fewer ops than the power form; only the bracket logic sees these values)
        s = theta * theta
        f = theta * (1 + s * (kd[0] + s * (kd[1] + s * (kd[2] + s * kd[3])))) - r
        df = 1 + s * (c3 + s * (c5 + s * (c7 + s * c9)))
        lo = torch.where(f < 0, theta, lo)
        hi = torch.where(f > 0, theta, hi)
        step = f / torch.where(df != 0, df, torch.ones_like(df))
        newton = theta - step
        # a step at rounding level means converged: keep it (bisecting then would jump back out to
        # the middle of a bracket that Newton never needed to shrink from the far side)
        tiny = step.abs() <= 16 * eps * theta.abs()
        ok = (df > 0) & (newton >= lo) & (newton <= hi) & ((2 * step.abs() <= dx_old) | tiny)
        mid = 0.5 * (lo + hi)
        dx_old = torch.where(ok, step.abs(), 0.5 * (hi - lo))
        theta = torch.where(ok, newton, mid)
    theta = torch.where(has, theta, r)
    # ρ == 0: j == 0 and the root is θ = 0 (theta already 0 from the clamp; keep it exact).
    theta = torch.where(has & (j == 0), torch.zeros_like(theta), theta)
    # Implicit-function gradient: two Newton steps on the graph from the detached root. Where there
    # is no root upstream returns ρ itself, whose derivative is 1 w.r.t. ρ.
    return torch.where(has, newton_attach(theta, lambda t: _poly_r(t, k2, k3, k4, k5) - rho,
                                          lambda t: _poly_dr(t, k2, k3, k4, k5)), rho)


def newton_attach(root: torch.Tensor, f, df) -> torch.Tensor:
    """The detached scalar root ``root`` of ``f(θ) = 0`` with its exact first *and* second
    derivatives w.r.t. whatever ``f``/``df`` (``df = ∂f/∂θ``) depend on; the value is ``root`` bit for
    bit.

    ``N(θ) = θ - f(θ)/f'(θ)`` (Newton's map) has ``∂N/∂θ = 0`` at a root, so ``θ1 = N(root)`` with
    ``root`` detached carries the exact first derivative ``-f_x / f'`` (what one step gave before:
    exact to first order only, its second derivative missed the terms through ``θ(x)`` — 4.4 % to
    ~40 % off on Kannala-Brandt ``lift``); ``θ2 = N(θ1)`` with ``θ1`` on the graph carries the exact
    second derivative as well. The corrections are applied as ``c - c.detach()`` (exactly 0), so
    the forward value is untouched; ``f' = 0`` lanes get a zero correction (no NaN)."""
    def step(t):
        d = df(t)
        return -f(t) / torch.where(d != 0, d, torch.ones_like(d))

    c1 = step(root)
    t1 = root + (c1 - c1.detach())
    c2 = t1 + step(t1)
    return root + (c2 - c2.detach())


class KannalaBrandtCamera(CameraModel):
    """camodocal ``KANNALA_BRANDT`` (``EquidistantCamera``): parameters ``k2, k3, k4, k5, mu, mv, u0, v0``.

    ``r(θ) = θ + k2 θ³ + k3 θ⁵ + k4 θ⁷ + k5 θ⁹``; camodocal ``k2..k5`` are OpenCV-fisheye / Kalibr
    ``k1..k4``.

    Convention:
        * ``project(P)``: ``θ`` = angle from the optical axis, ``φ = atan2(Y, X)``,
          ``(u, v) = (mu r(θ) cos φ + u0, mv r(θ) sin φ + v0)``. Upstream computes
          ``θ = acos(Z/‖P‖)``; we use the equal ``atan2(‖(X, Y)‖, Z)``, which is accurate near the
          axis (acos loses half the digits there) and has a finite derivative at the pole.
          ``cos φ, sin φ`` are ``X/‖(X, Y)‖, Y/‖(X, Y)‖`` (1, 0 on the axis).
        * ``lift(uv)``: ``p = ((u - u0)/mu, (v - v0)/mv)``, ``ρ = ‖p‖``, ``φ = atan2(p.y, p.x)``
          (0 if ``ρ < 1e-10``), ``θ`` = smallest non-negative root of ``r(θ) = ρ`` (``solve_theta``:
          batched safeguarded Newton, equal to upstream's companion-matrix root to ~1e-15 rad on the
          shipped calibrations; degree-dropping quirk reproduced, see ``effective_coefficients``).
          Returns the **unit** vector ``(sin θ cos φ, sin θ sin φ, cos θ)``; ``z < 0`` beyond 90°.
    """

    model_type = "KANNALA_BRANDT"
    implicit_lift = True
    param_names = ("k2", "k3", "k4", "k5", "mu", "mv", "u0", "v0")
    positive_params = ("mu", "mv")

    def __init__(
        self,
        k2: Any,
        k3: Any,
        k4: Any,
        k5: Any,
        mu: Any,
        mv: Any,
        u0: Any,
        v0: Any,
        *,
        width: int = 0,
        height: int = 0,
        camera_name: str = "camera",
        solver_iters: int = 50,
        dtype: torch.dtype = torch.float64,
        device: torch.device | None = None,
    ) -> None:
        super().__init__(
            dict(k2=k2, k3=k3, k4=k4, k5=k5, mu=mu, mv=mv, u0=u0, v0=v0),
            width=width,
            height=height,
            camera_name=camera_name,
            dtype=dtype,
            device=device,
        )
        self.solver_iters = check_iters(solver_iters, "solver_iters")

    def _extra_repr_items(self) -> Dict[str, Any]:
        return {"solver_iters": self.solver_iters} if self.solver_iters != 50 else {}

    def _critical_points(self, raw, ks) -> torch.Tensor:
        """:func:`critical_points` of the effective coefficients ``ks`` of ``raw = (k2, k3, k4, k5)``,
        kept while ``raw`` is unchanged: the companion matrix's eigenvalues make CUDA wait for the
        device (``linalg.eigvals`` checks for errors on the host), so a tracker's per-frame lift
        would sync twice per step; with the memo it syncs once, on the first lift of a calibration.

        The key is each tensor's storage and in-place version counter (an optimiser step bumps it);
        the memo holds ``raw`` itself, so no other tensor can take a storage it keys on. Under
        ``torch.compile`` or a ``torch.func`` transform (wrappers own no storage) it computes afresh."""
        if torch.compiler.is_compiling() or any(is_wrapper(k) for k in raw):
            return critical_points(*ks)
        key = tuple((k.data_ptr(), k._version, k.dtype, k.device) for k in raw)
        memo = self.__dict__.get("_critical_memo")
        if memo is not None and memo[0] == key:
            return memo[2]
        crit = critical_points(*ks)
        self.__dict__["_critical_memo"] = (key, raw, crit)  # a plain attribute: not a buffer, not saved
        return crit

    def _project_impl(self, P, k2, k3, k4, k5, mu, mv, u0, v0):
        X, Y, Z = P[..., 0], P[..., 1], P[..., 2]
        n, nz = safe_norm2(X, Y)
        theta = torch.atan2(n, Z)
        rt = _poly_r(theta, k2, k3, k4, k5)
        n_safe = torch.where(nz, n, torch.ones_like(n))
        cphi = torch.where(nz, X / n_safe, torch.ones_like(n))
        sphi = torch.where(nz, Y / n_safe, torch.zeros_like(n))
        return torch.stack((mu * rt * cphi + u0, mv * rt * sphi + v0), dim=-1)

    def _lift_impl(self, uv, k2, k3, k4, k5, mu, mv, u0, v0, converged=False):  # converged already
        px = (uv[..., 0] - u0) / mu
        py = (uv[..., 1] - v0) / mv
        rho, _ = safe_norm2(px, py)
        far = ~(rho < 1e-10)  # NaN pixels stay NaN (through θ = ρ = NaN)
        # atan2(0, 0) has a NaN derivative in torch: feed it (1, 0) in the lanes where upstream sets φ = 0.
        phi = torch.atan2(torch.where(far, py, torch.zeros_like(py)), torch.where(far, px, torch.ones_like(px)))
        ks = effective_coefficients(k2, k3, k4, k5)
        theta = solve_theta(rho, *ks, iters=self.solver_iters, crit=self._critical_points((k2, k3, k4, k5), ks))
        st = torch.sin(theta)
        return torch.stack((st * torch.cos(phi), st * torch.sin(phi), torch.cos(theta)), dim=-1)
