"""camodocal ``OCAMCamera``: Scaramuzza's omnidirectional polynomial model (``scaramuzza``). Spec §4.4."""

from __future__ import annotations

from typing import Any

import torch

from .base import CameraModel, safe_norm2

POLY_SIZE = 5
INV_POLY_SIZE = 20


def _ascending_poly(coeffs: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``Σ c_i x^i`` summed in ascending order with a running power, as upstream does (not Horner),
    so the rounding matches camodocal's loop. ``coeffs (..., L)``: one camera's ``(L,)`` or a camera
    batch's ``(B, 1, ..., 1, L)`` (coefficient i is ``coeffs[..., i]``, broadcast against ``x``)."""
    acc = torch.zeros_like(x)
    xi = torch.ones_like(x)
    for i in range(coeffs.shape[-1]):
        acc = acc + xi * coeffs[..., i]
        xi = xi * x
    return acc


class ScaramuzzaCamera(CameraModel):
    """camodocal ``scaramuzza`` (``OCAMCamera``): ``poly (5,)``, ``inv_poly (20,)``, ``ac, ad, ae, cx, cy``.

    Convention (``C, D, E = ac, ad, ae``; ``inv_scale = 1/(C - D E)``):
        * ``lift(uv)``: ``xc = (u - cx, v - cy)``; ``xa = inv_scale (xc.x - D xc.y, -E xc.x + C xc.y)``;
          ``φ = ‖xa‖``; ``z = Σ poly[i] φ^i``; returns ``(xc.x, xc.y, -z)``. Upstream quirk, kept: x and
          y are the *uncorrected* offsets ``xc`` (Scaramuzza's reference uses ``xa``), so with a
          non-identity affine part ``project(lift(uv)) != uv``. With ``C = 1, D = E = 0`` it vanishes.
        * ``project(P)``: ``n = ‖(X, Y)‖``, ``θ = atan2(-Z, n)``, ``ρ = Σ inv_poly[i] θ^i``,
          ``xn = (X/n ρ, Y/n ρ)``, ``(u, v) = (C xn.x + D xn.y + cx, E xn.x + xn.y + cy)``.
          On the axis (``n = 0``) upstream divides by zero (NaN); we return ``(cx, cy)`` there so the
          lane stays finite (the direction is undefined, any finite value is as good).
    """

    model_type = "scaramuzza"
    param_names = ("poly", "inv_poly", "ac", "ad", "ae", "cx", "cy")
    vector_params = {"poly": POLY_SIZE, "inv_poly": INV_POLY_SIZE}

    @classmethod
    def _model_problems(cls, values):
        """``lift`` divides by the affine part's determinant ``ac - ad ae`` (> 0: invertible and not
        mirrored; OCamCalib's ``c ~ 1``, ``d, e ~ 0``), and ``poly[0]`` (OCamCalib's ``a0``, minus
        the focal length in pixels) must be < 0, else the centre pixel's ray does not look along +z."""
        (ac,), (ad,), (ae,) = values["ac"], values["ad"], values["ae"]
        problems = []
        if not ac - ad * ae > 0:
            problems.append(("ac", f"the affine part [[ac, ad], [ae, 1]] needs a determinant ac - ad*ae > 0, "
                                   f"got {ac!r} - {ad!r}*{ae!r} = {ac - ad * ae!r}"))
        if not values["poly"][0] < 0:
            problems.append(("poly[0]", f"must be < 0 (OCamCalib's a0: minus the focal length in pixels), "
                                        f"got {values['poly'][0]!r}"))
        return problems

    def __init__(
        self,
        poly: Any,
        inv_poly: Any,
        ac: Any,
        ad: Any,
        ae: Any,
        cx: Any,
        cy: Any,
        *,
        width: int = 0,
        height: int = 0,
        camera_name: str = "camera",
        dtype: torch.dtype = torch.float64,
        device: torch.device | None = None,
    ) -> None:
        super().__init__(
            dict(poly=poly, inv_poly=inv_poly, ac=ac, ad=ad, ae=ae, cx=cx, cy=cy),
            width=width,
            height=height,
            camera_name=camera_name,
            dtype=dtype,
            device=device,
        )

    def _lift_impl(self, uv, poly, inv_poly, ac, ad, ae, cx, cy):
        xcx = uv[..., 0] - cx
        xcy = uv[..., 1] - cy
        inv_scale = 1.0 / (ac - ad * ae)
        xax = inv_scale * (xcx - ad * xcy)
        xay = inv_scale * (-ae * xcx + ac * xcy)
        phi, _ = safe_norm2(xax, xay)  # finite gradient at the centre pixel
        z = _ascending_poly(poly, phi)
        return torch.stack((xcx, xcy, -z), dim=-1)

    def _project_impl(self, P, poly, inv_poly, ac, ad, ae, cx, cy):
        X, Y, Z = P[..., 0], P[..., 1], P[..., 2]
        n, nz = safe_norm2(X, Y)
        theta = torch.atan2(-Z, n)
        rho = _ascending_poly(inv_poly, theta)
        inv_n = torch.where(nz, 1.0 / torch.where(nz, n, torch.ones_like(n)), torch.zeros_like(n))
        xnx = X * inv_n * rho
        xny = Y * inv_n * rho
        return torch.stack((xnx * ac + xny * ad + cx, xnx * ae + xny + cy), dim=-1)
