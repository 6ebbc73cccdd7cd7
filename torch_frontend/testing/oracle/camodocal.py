"""camodocal's ``liftProjective`` and ``spaceToPlane`` (spec §4) of the PINHOLE, MEI and
KANNALA_BRANDT models in numpy, as the oracle's undistortion.

Convention: camera parameters are a flat dict (``model_type`` and the camodocal parameter names,
see :func:`lift_projective`); pixels ``(N, 2)`` ``(u, v)``, rays ``(N, 3)``, computed in float64.
"""

from __future__ import annotations

import math

import numpy as np


# --------------------------------------------------------------------------------------------
# camodocal camera models (spec §4)
# --------------------------------------------------------------------------------------------
def _model(params: dict) -> str:
    # spec §4.0: an absent model_type means MEI.
    return str(params.get("model_type", "MEI") or "MEI")


def _rad_tan_d(x: np.ndarray, y: np.ndarray, k1: float, k2: float, p1: float, p2: float):
    """Radial-tangential displacement d(x, y) of spec §4.0 (OpenCV convention)."""
    mx2 = x * x
    my2 = y * y
    mxy = x * y
    r2 = mx2 + my2
    rad = k1 * r2 + k2 * r2 * r2
    dx = x * rad + 2.0 * p1 * mxy + p2 * (r2 + 2.0 * mx2)
    dy = y * rad + 2.0 * p2 * mxy + p1 * (r2 + 2.0 * my2)
    return dx, dy


def _undistort_recursive(mdx, mdy, k1, k2, p1, p2, n_eval: int = 8):
    """Fixed-point inversion: m_u <- m_d - d(m_d), then (n_eval-1) times m_u <- m_d - d(m_u)."""
    dx, dy = _rad_tan_d(mdx, mdy, k1, k2, p1, p2)
    mux, muy = mdx - dx, mdy - dy
    for _ in range(n_eval - 1):
        dx, dy = _rad_tan_d(mux, muy, k1, k2, p1, p2)
        mux, muy = mdx - dx, mdy - dy
    return mux, muy


def _kb_theta(rho: float, k: tuple) -> float:
    """Smallest non-negative real root of theta + k2 t^3 + k3 t^5 + k4 t^7 + k5 t^9 = rho.

    camodocal builds a companion matrix whose degree is ``9 - 2 * (#zeros among k2..k5)`` — zeros
    are counted wherever they are, so an interior zero drops the HIGHEST coefficient (quirk kept,
    spec §4.3). A zero leading coefficient then divides by zero: we return NaN (spec: "⇒ NaN").
    """
    k2, k3, k4, k5 = k
    coeffs = np.zeros(10)
    coeffs[0] = -rho
    coeffs[1] = 1.0
    coeffs[3] = k2
    coeffs[5] = k3
    coeffs[7] = k4
    coeffs[9] = k5
    npow = 9 - 2 * sum(1 for kk in k if kk == 0.0)
    if npow == 1:
        return rho
    lead = coeffs[npow]
    if lead == 0.0:
        return float("nan")
    comp = np.zeros((npow, npow))
    comp[np.arange(1, npow), np.arange(0, npow - 1)] = 1.0  # identity on the sub-diagonal
    comp[:, npow - 1] = -coeffs[:npow] / lead
    if not np.all(np.isfinite(comp)):
        return float("nan")
    roots = np.linalg.eigvals(comp)
    best = None
    for z in roots:
        if abs(z.imag) > 1e-10:
            continue
        re = z.real
        if re < -1e-10:
            continue
        if re < 0.0:  # (-1e-10, 0) clamps to 0
            re = 0.0
        if best is None or re < best:
            best = re
    return rho if best is None else float(best)


def lift_projective(params: dict, uv: np.ndarray) -> np.ndarray:
    """camodocal ``liftProjective`` (spec §4): pixels -> ray ``P`` (not normalised to z = 1).

    Args:
        params: flat dict, ``model_type`` one of ``PINHOLE`` (k1, k2, p1, p2, fx, fy, cx, cy),
            ``MEI`` (xi, k1, k2, p1, p2, gamma1, gamma2, u0, v0), ``KANNALA_BRANDT``
            (k2, k3, k4, k5, mu, mv, u0, v0). Absent ``model_type`` = MEI (camodocal default).
        uv: (N, 2) pixels (x, y); any float dtype, computed in float64.

    Returns:
        (N, 3) float64 rays. PINHOLE: ``(x, y, 1)``. MEI: ``(x, y, z(ρ²))`` (z may be <= 0 / NaN
        outside the valid field of view — kept, as upstream). KANNALA_BRANDT: unit vector.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    model = _model(params)
    u, v = uv[:, 0], uv[:, 1]
    if model == "PINHOLE":
        k1, k2, p1, p2 = (float(params[k]) for k in ("k1", "k2", "p1", "p2"))
        mdx = (u - float(params["cx"])) / float(params["fx"])
        mdy = (v - float(params["cy"])) / float(params["fy"])
        if k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0:
            mux, muy = mdx, mdy
        else:
            mux, muy = _undistort_recursive(mdx, mdy, k1, k2, p1, p2)
        return np.stack([mux, muy, np.ones_like(mux)], axis=1)
    if model == "MEI":
        xi = float(params["xi"])
        k1, k2, p1, p2 = (float(params[k]) for k in ("k1", "k2", "p1", "p2"))
        mdx = (u - float(params["u0"])) / float(params["gamma1"])
        mdy = (v - float(params["v0"])) / float(params["gamma2"])
        if k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0:
            mux, muy = mdx, mdy
        else:
            mux, muy = _undistort_recursive(mdx, mdy, k1, k2, p1, p2)
        rho2 = mux * mux + muy * muy
        if xi == 1.0:
            z = (1.0 - rho2) / 2.0
        else:
            with np.errstate(invalid="ignore"):
                z = 1.0 - xi * (rho2 + 1.0) / (xi + np.sqrt(1.0 + (1.0 - xi * xi) * rho2))
        return np.stack([mux, muy, z], axis=1)
    if model == "KANNALA_BRANDT":
        k = tuple(float(params[n]) for n in ("k2", "k3", "k4", "k5"))
        px = (u - float(params["u0"])) / float(params["mu"])
        py = (v - float(params["v0"])) / float(params["mv"])
        out = np.empty((uv.shape[0], 3))
        for i in range(uv.shape[0]):
            rho = math.hypot(px[i], py[i])
            phi = math.atan2(py[i], px[i]) if rho >= 1e-10 else 0.0
            theta = _kb_theta(rho, k)
            st = math.sin(theta)
            out[i] = (st * math.cos(phi), st * math.sin(phi), math.cos(theta))
        return out
    raise ValueError(
        f"lift_projective: unsupported model_type {model!r}; expected 'PINHOLE', 'MEI' or "
        "'KANNALA_BRANDT' (camodocal model readers compare case-sensitively)"
    )


def space_to_plane(params: dict, P: np.ndarray) -> np.ndarray:
    """camodocal ``spaceToPlane`` (spec §4): rays (N, 3) -> pixels (N, 2) float64."""
    P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    model = _model(params)
    if model in ("PINHOLE", "MEI"):
        k1, k2, p1, p2 = (float(params[k]) for k in ("k1", "k2", "p1", "p2"))
        if model == "PINHOLE":
            zp = Z
            f1, f2, c1, c2 = (float(params[k]) for k in ("fx", "fy", "cx", "cy"))
        else:
            zp = Z + float(params["xi"]) * np.linalg.norm(P, axis=1)
            f1, f2, c1, c2 = (float(params[k]) for k in ("gamma1", "gamma2", "u0", "v0"))
        x, y = X / zp, Y / zp
        if not (model == "PINHOLE" and k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0):
            dx, dy = _rad_tan_d(x, y, k1, k2, p1, p2)
            x, y = x + dx, y + dy
        return np.stack([f1 * x + c1, f2 * y + c2], axis=1)
    if model == "KANNALA_BRANDT":
        k2, k3, k4, k5 = (float(params[n]) for n in ("k2", "k3", "k4", "k5"))
        theta = np.arccos(np.clip(Z / np.linalg.norm(P, axis=1), -1.0, 1.0))
        phi = np.arctan2(Y, X)
        t2 = theta * theta
        r = theta * (1.0 + t2 * (k2 + t2 * (k3 + t2 * (k4 + t2 * k5))))
        return np.stack(
            [float(params["mu"]) * r * np.cos(phi) + float(params["u0"]),
             float(params["mv"]) * r * np.sin(phi) + float(params["v0"])],
            axis=1,
        )
    raise ValueError(f"space_to_plane: unsupported model_type {model!r}")


def _normalised(params: dict, pts: np.ndarray) -> np.ndarray:
    """C++ ``cv::Point2f(P.x / P.z, P.y / P.z)`` of the lifted float pixels -> (N, 2) float32."""
    if len(pts) == 0:
        return np.zeros((0, 2), np.float32)
    P = lift_projective(params, pts)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]], axis=1).astype(np.float32)
