"""camodocal ``PinholeCamera`` (radial-tangential k1, k2, p1, p2) and ``PinholeFullCamera`` (OpenCV
rational model k1..k6, p1, p2; VINS-Fusion only). Spec §4.1 and §4.5."""

from __future__ import annotations

from typing import Any, Dict

import torch

from .base import CameraModel, check_iters, radtan_distortion, radtan_undistort, radtan_undistort_converged


class PinholeCamera(CameraModel):
    """camodocal ``PINHOLE``: radial-tangential distortion, parameters ``k1, k2, p1, p2, fx, fy, cx, cy``.

    Convention:
        * ``project(P)``: ``p_u = (X/Z, Y/Z)``, ``p_d = p_u + d(p_u)`` (spec §4.0 displacement),
          ``(u, v) = (fx p_d.x + cx, fy p_d.y + cy)``. Points with ``Z = 0`` give inf/NaN as upstream.
        * ``lift(uv)``: ``m_d = ((u - cx)/fx, (v - cy)/fy)``, then ``undistort_iters`` (upstream: 8)
          evaluations of the fixed point ``m_u <- m_d - d(m_u)`` starting at ``m_u = m_d``; returns
          ``(m_u.x, m_u.y, 1)``. With 8 evaluations ``project(lift(uv))`` is *not* ``uv`` far from the
          centre (up to ~0.13 px at the EuRoC corners); pass ``undistort_iters=64`` for a converged
          inverse (round trip < 1e-9 px on every shipped calibration).
    """

    model_type = "PINHOLE"
    implicit_lift = True
    param_names = ("k1", "k2", "p1", "p2", "fx", "fy", "cx", "cy")
    positive_params = ("fx", "fy")

    def __init__(
        self,
        k1: Any,
        k2: Any,
        p1: Any,
        p2: Any,
        fx: Any,
        fy: Any,
        cx: Any,
        cy: Any,
        *,
        width: int = 0,
        height: int = 0,
        camera_name: str = "camera",
        undistort_iters: int = 8,
        dtype: torch.dtype = torch.float64,
        device: torch.device | None = None,
    ) -> None:
        super().__init__(
            dict(k1=k1, k2=k2, p1=p1, p2=p2, fx=fx, fy=fy, cx=cx, cy=cy),
            width=width,
            height=height,
            camera_name=camera_name,
            dtype=dtype,
            device=device,
        )
        self.undistort_iters = check_iters(undistort_iters, "undistort_iters")

    def _extra_repr_items(self) -> Dict[str, Any]:
        return {"undistort_iters": self.undistort_iters} if self.undistort_iters != 8 else {}

    def _project_impl(self, P, k1, k2, p1, p2, fx, fy, cx, cy):
        x = P[..., 0] / P[..., 2]
        y = P[..., 1] / P[..., 2]
        dx, dy = radtan_distortion(x, y, k1, k2, p1, p2)
        return torch.stack((fx * (x + dx) + cx, fy * (y + dy) + cy), dim=-1)

    def _lift_impl(self, uv, k1, k2, p1, p2, fx, fy, cx, cy, converged=False):
        mxd = (uv[..., 0] - cx) / fx
        myd = (uv[..., 1] - cy) / fy
        if converged:  # lift(..., jacobian="implicit")
            mxu, myu, _ = radtan_undistort_converged(mxd, myd, k1, k2, p1, p2)
        else:
            mxu, myu = radtan_undistort(mxd, myd, k1, k2, p1, p2, self.undistort_iters)
        return torch.stack((mxu, myu, torch.ones_like(mxu)), dim=-1)


class PinholeFullCamera(CameraModel):
    """camodocal ``PINHOLE_FULL`` (VINS-Fusion): OpenCV rational model, ``k1..k6, p1, p2, fx, fy, cx, cy``.

    Convention:
        * ``project(P)``: ``x = X/Z``, ``y = Y/Z``, ``r² = x² + y²``,
          ``x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶)/(1 + k4 r² + k5 r⁴ + k6 r⁶) + 2 p1 x y + p2 (r² + 2x²)``,
          ``y_d = y (...)/(...) + p1 (r² + 2y²) + 2 p2 x y``; ``(u, v) = (fx x_d + cx, fy y_d + cy)``.
        * ``lift(uv)``: OpenCV ``undistortPoints`` iteration ``x <- (x0 - Δx)·icdist`` from ``x = x0``,
          ``icdist = (1 + ((k6 r² + k5) r² + k4) r²)/(1 + ((k3 r² + k2) r² + k1) r²)``. Upstream's stop
          test never fires, so it always makes **9** updates (``undistort_iters``); returns ``(x, y, 1)``.
    """

    model_type = "PINHOLE_FULL"
    param_names = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "fx", "fy", "cx", "cy")
    positive_params = ("fx", "fy")

    def __init__(
        self,
        k1: Any,
        k2: Any,
        k3: Any,
        k4: Any,
        k5: Any,
        k6: Any,
        p1: Any,
        p2: Any,
        fx: Any,
        fy: Any,
        cx: Any,
        cy: Any,
        *,
        width: int = 0,
        height: int = 0,
        camera_name: str = "camera",
        undistort_iters: int = 9,
        dtype: torch.dtype = torch.float64,
        device: torch.device | None = None,
    ) -> None:
        super().__init__(
            dict(k1=k1, k2=k2, k3=k3, k4=k4, k5=k5, k6=k6, p1=p1, p2=p2, fx=fx, fy=fy, cx=cx, cy=cy),
            width=width,
            height=height,
            camera_name=camera_name,
            dtype=dtype,
            device=device,
        )
        self.undistort_iters = check_iters(undistort_iters, "undistort_iters")

    def _extra_repr_items(self) -> Dict[str, Any]:
        return {"undistort_iters": self.undistort_iters} if self.undistort_iters != 9 else {}

    def _project_impl(self, P, k1, k2, k3, k4, k5, k6, p1, p2, fx, fy, cx, cy):
        x = P[..., 0] / P[..., 2]
        y = P[..., 1] / P[..., 2]
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        a1 = 2 * x * y
        xd = x * radial + p1 * a1 + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * a1
        return torch.stack((fx * xd + cx, fy * yd + cy), dim=-1)

    def _lift_impl(self, uv, k1, k2, k3, k4, k5, k6, p1, p2, fx, fy, cx, cy):
        x0 = (uv[..., 0] - cx) / fx
        y0 = (uv[..., 1] - cy) / fy
        x, y = x0, y0
        for _ in range(self.undistort_iters):
            r2 = x * x + y * y
            icdist = (1 + ((k6 * r2 + k5) * r2 + k4) * r2) / (1 + ((k3 * r2 + k2) * r2 + k1) * r2)
            delta_x = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            delta_y = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (x0 - delta_x) * icdist
            y = (y0 - delta_y) * icdist
        return torch.stack((x, y, torch.ones_like(x)), dim=-1)
