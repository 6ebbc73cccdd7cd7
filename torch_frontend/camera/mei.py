"""camodocal ``CataCamera``: Mei's unified omnidirectional model (``MEI``). Spec §4.2."""

from __future__ import annotations

from typing import Any, Dict

import torch

from .base import (
    NAN,
    CameraModel,
    check_iters,
    radtan_distortion,
    radtan_undistort,
    radtan_undistort_converged,
)


class MeiCamera(CameraModel):
    """camodocal ``MEI``: parameters ``xi, k1, k2, p1, p2, gamma1, gamma2, u0, v0``.

    Convention:
        * ``project(P)``: ``z' = Z + xi ‖P‖``, ``p_u = (X/z', Y/z')``, ``p_d = p_u + d(p_u)``,
          ``(u, v) = (gamma1 p_d.x + u0, gamma2 p_d.y + v0)``.
        * ``lift(uv)``: ``m_d = ((u - u0)/gamma1, (v - v0)/gamma2)``, undistorted exactly like
          ``PinholeCamera`` (``undistort_iters`` = 8 evaluations); with ``ρ² = ‖m_u‖²`` returns
          ``(m_u.x, m_u.y, (1 - ρ²)/2)`` if ``xi == 1`` exactly, else
          ``(m_u.x, m_u.y, 1 - xi (ρ² + 1)/(xi + sqrt(1 + (1 - xi²) ρ²)))``. Not unit length; ``z``
          can be ``<= 0`` for rays beyond 90°.
        * Invalid lanes: for ``xi > 1`` and ``ρ² > 1/(xi² - 1)`` the square root is of a negative
          number and upstream returns NaN; so does ``lift`` (value parity), but the square root is
          evaluated on a safe argument there so the gradients of the *other* lanes stay finite.
    """

    model_type = "MEI"
    implicit_lift = True
    param_names = ("xi", "k1", "k2", "p1", "p2", "gamma1", "gamma2", "u0", "v0")
    positive_params = ("gamma1", "gamma2")
    # the unified model projects from a point xi behind the sphere's centre (xi = 0: a pinhole);
    # xi < 0 puts it in front, where xi + sqrt(...) in lift can vanish
    nonnegative_params = ("xi",)

    def __init__(
        self,
        xi: Any,
        k1: Any,
        k2: Any,
        p1: Any,
        p2: Any,
        gamma1: Any,
        gamma2: Any,
        u0: Any,
        v0: Any,
        *,
        width: int = 0,
        height: int = 0,
        camera_name: str = "camera",
        undistort_iters: int = 8,
        dtype: torch.dtype = torch.float64,
        device: torch.device | None = None,
    ) -> None:
        super().__init__(
            dict(xi=xi, k1=k1, k2=k2, p1=p1, p2=p2, gamma1=gamma1, gamma2=gamma2, u0=u0, v0=v0),
            width=width,
            height=height,
            camera_name=camera_name,
            dtype=dtype,
            device=device,
        )
        self.undistort_iters = check_iters(undistort_iters, "undistort_iters")

    def _extra_repr_items(self) -> Dict[str, Any]:
        return {"undistort_iters": self.undistort_iters} if self.undistort_iters != 8 else {}

    def _project_impl(self, P, xi, k1, k2, p1, p2, gamma1, gamma2, u0, v0):
        X, Y, Z = P[..., 0], P[..., 1], P[..., 2]
        zp = Z + xi * torch.sqrt(X * X + Y * Y + Z * Z)
        x = X / zp
        y = Y / zp
        dx, dy = radtan_distortion(x, y, k1, k2, p1, p2)
        return torch.stack((gamma1 * (x + dx) + u0, gamma2 * (y + dy) + v0), dim=-1)

    def _lift_impl(self, uv, xi, k1, k2, p1, p2, gamma1, gamma2, u0, v0, converged=False):
        mxd = (uv[..., 0] - u0) / gamma1
        myd = (uv[..., 1] - v0) / gamma2
        if converged:  # lift(..., jacobian="implicit")
            mxu, myu, _ = radtan_undistort_converged(mxd, myd, k1, k2, p1, p2)
        else:
            mxu, myu = radtan_undistort(mxd, myd, k1, k2, p1, p2, self.undistort_iters)
        rho2 = mxu * mxu + myu * myu
        arg = 1.0 + (1.0 - xi * xi) * rho2
        ok = arg >= 0
        # sqrt of a safe argument: torch.where differentiates both branches, and a NaN in the
        # unselected one would poison every gradient that flows through this op.
        root = torch.sqrt(torch.where(ok, arg, torch.ones_like(arg)))
        z_gen = 1.0 - xi * (rho2 + 1.0) / (xi + root)
        z_gen = torch.where(ok, z_gen, torch.full_like(z_gen, NAN))
        # xi == 1: upstream's special formula (1 - ρ²)/2 is algebraically the general one, so take its
        # value but the general formula's gradient (d/dxi of the constant branch would be 0).
        z_one = (1.0 - rho2) / 2.0
        z = torch.where(xi == 1, z_one.detach() + (z_gen - z_gen.detach()), z_gen)
        return torch.stack((mxu, myu, z), dim=-1)
