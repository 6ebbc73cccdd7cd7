"""OpenCV oracle of the VINS-Mono / VINS-Fusion KLT front end (numpy + cv2 only, no torch).

``torch_frontend.testing.oracle`` (formerly ``benchmarks/vins_oracle.py``). A plain, sequential
re-implementation of the behaviour described in the behaviour spec (``docs/spec.md``; "spec §N"
below): the Mono ``feature_tracker`` node (``img_callback`` timing
logic + ``readImage``, spec §3), the VINS-Fusion tracker (spec §6) and the camodocal
``liftProjective`` of the PINHOLE / MEI / KANNALA_BRANDT models (spec §4). It is built only from
the spec and OpenCV calls; it is the *reference* the batched torch tracker is tested and
benchmarked against, so it favours readability and fidelity over speed (Python loops over points
are fine here).

Convention
----------
* Pixels ``(u, v)`` = (column x, row y), pixel centres at integer coordinates; images are
  ``(H, W)`` uint8. ``ROW x COL`` = ``image_height x image_width``.
* Point arrays are ``(N, 2)``; pixel positions and normalised coordinates are float32 like the
  C++ ``cv::Point2f`` vectors they mirror (lifts are computed in float64 from the float32 pixels,
  then stored as float32 exactly as the C++ does). Velocities are float32 (normalised units / s).
* ``cvRound`` is round-half-to-even (``np.rint``); the FREQ test uses C ``round`` (half away from
  zero), see :func:`c_round`.

Deliberate choices (see also the module-level notes in each class)
-----------------------------------------------------------------
* ``setMask`` ordering: VINS uses ``std::sort`` (unstable) on ``track_cnt`` descending. The oracle
  uses the STABLE rule ``sort by (-track_cnt, array index)``, the same rule the torch port uses, so
  the two can be compared feature by feature. It can differ from a real VINS run only in which of
  two equally old, closer-than-``min_dist`` features survives.
* ``findFundamentalMat`` is called through cv2, so OpenCV's own behaviour (LMedS for 8..14 points,
  RANSAC with its fixed RNG seed otherwise) is inherited, not re-implemented. If it returns no
  F/mask, all tracks are kept.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

# --------------------------------------------------------------------------------------------
# Constants (spec §2)
# --------------------------------------------------------------------------------------------
FOCAL_LENGTH = 460.0  # virtual pinhole focal length of rejectWithF
BORDER_SIZE = 1
LK_WIN = (21, 21)
LK_MAX_LEVEL = 3
LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
GFTT_QUALITY = 0.01
CLAHE_CLIP = 3.0
CLAHE_GRID = (8, 8)
F_CONFIDENCE = 0.99
RESTART_GAP_S = 1.0
FLOW_BACK_MAX_PX = 0.5
PREDICTION_MIN_GOOD = 10

__all__ = [
    "lift_projective",
    "space_to_plane",
    "c_round",
    "cv_round",
    "in_border",
    "MonoTiming",
    "OracleMonoTracker",
    "OracleFusionTracker",
    "run_oracle_sequence",
    "cfg_from_vins_yaml",
    "camera_from_yaml",
]


# --------------------------------------------------------------------------------------------
# Rounding helpers (spec §5.5, §3.2)
# --------------------------------------------------------------------------------------------
def c_round(r: float) -> float:
    """C ``round``: half away from zero; ``inf`` stays ``inf``.

    For positive ``r`` this is ``floor(r + 0.5)`` except at ``0.49999999999999994`` where the
    addition itself rounds up; the exact form below avoids that corner. Python's ``round`` (banker's)
    must NOT be used: ``12.5`` has to become 13 (spec §3.2, 25 Hz example).
    """
    if not math.isfinite(r):
        return r
    a = abs(r)
    f = math.floor(a)
    out = f + 1.0 if (a - f) >= 0.5 else float(f)
    return math.copysign(out, r)


def cv_round(x: np.ndarray) -> np.ndarray:
    """``cvRound``: round half to even (default FPU mode), as int64."""
    return np.rint(np.asarray(x)).astype(np.int64)


def in_border(pts: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """``inBorder``: ``BORDER <= cvRound(x) < cols - BORDER`` and the same for y. pts (N, 2)."""
    pts = np.asarray(pts).reshape(-1, 2)
    ix = cv_round(pts[:, 0])
    iy = cv_round(pts[:, 1])
    return (BORDER_SIZE <= ix) & (ix < cols - BORDER_SIZE) & (BORDER_SIZE <= iy) & (iy < rows - BORDER_SIZE)


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


# --------------------------------------------------------------------------------------------
# Shared primitives
# --------------------------------------------------------------------------------------------
def _lk(prev_img, next_img, pts, guess=None, max_level=LK_MAX_LEVEL):
    """cv2 pyramidal LK; ``guess`` given -> OPTFLOW_USE_INITIAL_FLOW. Returns (pts (N,2) f32, status bool)."""
    p0 = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 1, 2)
    if guess is None:
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev_img, next_img, p0, None, winSize=LK_WIN,
                                              maxLevel=max_level, criteria=LK_CRITERIA)
    else:
        g = np.ascontiguousarray(guess, dtype=np.float32).reshape(-1, 1, 2).copy()
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev_img, next_img, p0, g, winSize=LK_WIN,
                                              maxLevel=max_level, criteria=LK_CRITERIA,
                                              flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    return nxt.reshape(-1, 2).astype(np.float32), st.reshape(-1).astype(bool)


def _stable_mask_order(track_cnt: np.ndarray) -> np.ndarray:
    """setMask order: track_cnt descending, ties by array index (STABLE; VINS's std::sort is not)."""
    return np.lexsort((np.arange(len(track_cnt)), -np.asarray(track_cnt, dtype=np.int64)))


def _set_mask(pts, ids, track_cnt, base_mask, min_dist):
    """spec §3.7: reorder by age, keep a feature iff mask[cvRound(p)] == 255, then paint a disc 0."""
    mask = base_mask.copy()
    keep_idx = []
    for i in _stable_mask_order(track_cnt):
        cx, cy = int(cv_round(pts[i, 0])), int(cv_round(pts[i, 1]))
        if mask[cy, cx] == 255:
            keep_idx.append(i)
            cv2.circle(mask, (cx, cy), int(min_dist), 0, -1)
    keep_idx = np.asarray(keep_idx, dtype=np.int64)
    return pts[keep_idx], ids[keep_idx], track_cnt[keep_idx], mask


def _gftt(img, n_max, min_dist, mask):
    """GFTT(quality 0.01, blockSize 3, Shi-Tomasi) -> (M, 2) float32 in response order."""
    if n_max <= 0:
        return np.zeros((0, 2), np.float32)
    c = cv2.goodFeaturesToTrack(img, maxCorners=int(n_max), qualityLevel=GFTT_QUALITY,
                                minDistance=float(min_dist), mask=mask)
    if c is None:
        return np.zeros((0, 2), np.float32)
    return c.reshape(-1, 2).astype(np.float32)


def _velocity(ids, un, prev_map, dt, skip_minus_one):
    """Velocity against ``prev_map`` (id -> float32 (2,)); zeros when prev_map is empty.

    float32 difference divided by the float64 ``dt`` then stored as float32 (C++ Point2f maths).
    A zero dt (duplicate stamp) gives inf/NaN exactly like the C++ division does.
    """
    vel = np.zeros((len(ids), 2), np.float32)
    if not prev_map:
        return vel
    with np.errstate(divide="ignore", invalid="ignore"):
        for i, fid in enumerate(ids):
            fid = int(fid)
            if skip_minus_one and fid == -1:
                continue
            prev = prev_map.get(fid)
            if prev is not None:
                diff = (un[i] - prev).astype(np.float64)  # float - float in float, then / double
                vel[i] = (diff / dt).astype(np.float32)
    return vel


def _as_gray_u8(img: np.ndarray, name: str) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"{name}: expected a (H, W) uint8 image, got shape {img.shape} dtype {img.dtype}")
    return np.ascontiguousarray(img)


# --------------------------------------------------------------------------------------------
# VINS-Mono: img_callback timing (spec §3.2)
# --------------------------------------------------------------------------------------------
class MonoTiming:
    """The ``img_callback`` state machine of the Mono node (first-image skip, restart, FREQ).

    ``step(t)`` returns ``{"tracked", "restart", "pub_this_frame"}`` for a new stamp; when
    ``tracked`` the caller runs readImage/updateID and then calls ``published()`` if
    ``pub_this_frame``, which returns whether the message is actually sent (``init_pub``).
    """

    def __init__(self, freq: int):
        self.freq = int(freq) if int(freq) != 0 else 100  # freq 0 => FREQ = 100
        self.first_image_flag = True
        self.first_image_time = 0.0
        self.last_image_time = 0.0
        self.pub_count = 1
        self.init_pub = False

    def step(self, t: float) -> dict:
        t = float(t)
        if self.first_image_flag:
            self.first_image_flag = False
            self.first_image_time = t
            self.last_image_time = t
            return {"tracked": False, "restart": False, "pub_this_frame": False}
        if t - self.last_image_time > RESTART_GAP_S or t < self.last_image_time:
            # restart: node state reset, tracker state NOT touched, init_pub NOT reset
            self.first_image_flag = True
            self.last_image_time = 0.0
            self.pub_count = 1
            return {"tracked": False, "restart": True, "pub_this_frame": False}
        self.last_image_time = t
        denom = t - self.first_image_time
        r = self.pub_count / denom if denom != 0.0 else math.inf  # duplicate stamp => +inf
        if c_round(r) <= self.freq:
            pub = True
            if abs(r - self.freq) < 0.01 * self.freq:
                self.first_image_time = t
                self.pub_count = 0
        else:
            pub = False
        return {"tracked": True, "restart": False, "pub_this_frame": pub}

    def published(self) -> bool:
        """After a PUB frame was tracked: pub_count += 1; returns whether the message is sent."""
        self.pub_count += 1
        if not self.init_pub:
            self.init_pub = True
            return False
        return True


# --------------------------------------------------------------------------------------------
# VINS-Mono tracker (spec §3.5 - §3.11)
# --------------------------------------------------------------------------------------------
class OracleMonoTracker:
    """VINS-Mono ``feature_tracker`` node: ``img_callback`` + ``readImage`` + ``updateID``.

    cfg keys: ``max_cnt, min_dist, freq, F_threshold, equalize, fisheye, image_width (COL),
    image_height (ROW), camera`` (flat camera dict, see :func:`lift_projective`) and optional
    ``fisheye_mask`` ((ROW, COL) uint8; required when ``fisheye`` is 1).

    ``process(img, t)`` returns, for ALL current features in array order (after updateID):
    ``ids`` int64 (N,), ``uv`` float32 (N, 2) (cur_pts), ``xy`` float32 (N, 2) (cur_un_pts),
    ``velocity`` float32 (N, 2), ``track_cnt`` int64 (N,), ``published_mask`` (track_cnt > 1: the
    points that go into the feature message), and flags ``tracked`` (readImage ran),
    ``restart`` (restart published on this stamp), ``pub_this_frame`` / ``published`` (PUB_THIS_FRAME),
    ``sent`` (the message was actually published: the first PUB frame is not, ``init_pub``),
    ``t`` and the step counts ``n_lk_lost, n_f_rejected, n_mask_pruned, n_new``. Skipped frames
    (first image, restart) return empty arrays.
    """

    def __init__(self, cfg: dict):
        self.max_cnt = int(cfg["max_cnt"])
        self.min_dist = int(cfg["min_dist"])
        self.F_threshold = float(cfg["F_threshold"])
        self.equalize = bool(int(cfg.get("equalize", 0)))
        self.fisheye = bool(int(cfg.get("fisheye", 0)))
        self.COL = int(cfg["image_width"])
        self.ROW = int(cfg["image_height"])
        self.camera = dict(cfg["camera"])
        self.timing = MonoTiming(int(cfg.get("freq", 0)))
        if self.fisheye:
            fm = cfg.get("fisheye_mask")
            if fm is None:
                raise ValueError("OracleMonoTracker: fisheye=1 needs cfg['fisheye_mask'] (ROW, COL) uint8")
            fm = _as_gray_u8(fm, "fisheye_mask")
            if fm.shape != (self.ROW, self.COL):
                raise ValueError(f"fisheye_mask: expected shape {(self.ROW, self.COL)}, got {fm.shape}")
            self.base_mask = fm.copy()
        else:
            self.base_mask = np.full((self.ROW, self.COL), 255, np.uint8)
        self._clahe = cv2.createCLAHE(clipLimit=CLAHE_CLIP, tileGridSize=CLAHE_GRID)
        # tracker state (never reset, not even on restart)
        self.cur_img: np.ndarray | None = None
        self.forw_img: np.ndarray | None = None
        self.cur_pts = np.zeros((0, 2), np.float32)
        self.ids = np.zeros((0,), np.int64)
        self.track_cnt = np.zeros((0,), np.int64)
        self.cur_un_pts = np.zeros((0, 2), np.float32)
        self.pts_velocity = np.zeros((0, 2), np.float32)
        self.prev_un_pts_map: dict = {}
        self.cur_time = 0.0
        self.prev_time = 0.0
        self.n_id = 0
        self.last_mask: np.ndarray | None = None  # the mask passed to GFTT on the last PUB frame

    # ---- readImage (spec §3.6) ----
    def read_image(self, img: np.ndarray, t: float, pub_this_frame: bool) -> dict:
        """One ``readImage`` call; returns per-step counts ``n_lk_lost`` (LK status 0 or out of
        border), ``n_f_rejected``, ``n_mask_pruned``, ``n_new``."""
        self.cur_time = float(t)
        if self.equalize:
            img = self._clahe.apply(img)
        if self.forw_img is None:
            self.cur_img = img
        self.forw_img = img

        cur_pts = self.cur_pts
        ids, track_cnt = self.ids, self.track_cnt
        stats = {"n_lk_lost": 0, "n_f_rejected": 0, "n_mask_pruned": 0, "n_new": 0}
        if len(cur_pts) > 0:
            forw_pts, status = _lk(self.cur_img, self.forw_img, cur_pts)
            status &= in_border(forw_pts, self.ROW, self.COL)
            stats["n_lk_lost"] = int((~status).sum())
            cur_pts, forw_pts = cur_pts[status], forw_pts[status]
            ids, track_cnt = ids[status], track_cnt[status]
        else:
            forw_pts = np.zeros((0, 2), np.float32)
        track_cnt = track_cnt + 1

        if pub_this_frame:
            # rejectWithF (spec §3.8)
            if len(forw_pts) >= 8:
                keep = self._reject_with_f(cur_pts, forw_pts)
                stats["n_f_rejected"] = int((~keep).sum())
                cur_pts, forw_pts = cur_pts[keep], forw_pts[keep]
                ids, track_cnt = ids[keep], track_cnt[keep]
            # setMask (spec §3.7): reorders/prunes forw_pts, ids, track_cnt only
            n_before = len(forw_pts)
            forw_pts, ids, track_cnt, mask = _set_mask(forw_pts, ids, track_cnt, self.base_mask, self.min_dist)
            stats["n_mask_pruned"] = n_before - len(forw_pts)
            self.last_mask = mask
            n_pts = _gftt(self.forw_img, self.max_cnt - len(forw_pts), self.min_dist, mask)
            n_new = len(n_pts)
            stats["n_new"] = n_new
            # addPoints
            forw_pts = np.concatenate([forw_pts, n_pts]).astype(np.float32)
            ids = np.concatenate([ids, np.full(n_new, -1, np.int64)])
            track_cnt = np.concatenate([track_cnt, np.ones(n_new, np.int64)])

        # shift
        self.cur_img = self.forw_img
        self.cur_pts, self.ids, self.track_cnt = forw_pts, ids, track_cnt
        self._undistorted_points()
        self.prev_time = self.cur_time
        return stats

    def _reject_with_f(self, cur_pts, forw_pts) -> np.ndarray:
        def virt(pts):
            P = lift_projective(self.camera, pts)
            return np.stack(
                [FOCAL_LENGTH * P[:, 0] / P[:, 2] + self.COL / 2.0,
                 FOCAL_LENGTH * P[:, 1] / P[:, 2] + self.ROW / 2.0], axis=1
            ).astype(np.float32)

        F, st = cv2.findFundamentalMat(virt(cur_pts), virt(forw_pts), cv2.FM_RANSAC,
                                       self.F_threshold, F_CONFIDENCE)
        if F is None or st is None or F.size == 0 or len(st) != len(cur_pts):
            return np.ones(len(cur_pts), bool)  # estimation failed: keep all (spec §3.8)
        return st.reshape(-1).astype(bool)

    def _undistorted_points(self):
        """spec §3.10: map keyed by id, new points share key -1 (only the first is stored)."""
        un = _normalised(self.camera, self.cur_pts)
        cur_map: dict = {}
        for i, fid in enumerate(self.ids):
            cur_map.setdefault(int(fid), un[i])  # std::map::insert keeps the first value
        dt = self.cur_time - self.prev_time
        self.pts_velocity = _velocity(self.ids, un, self.prev_un_pts_map, dt, skip_minus_one=True)
        self.cur_un_pts = un
        self.prev_un_pts_map = cur_map

    def update_id(self):
        """spec §3.9: assign n_id to every -1 in array order."""
        for i in range(len(self.ids)):
            if self.ids[i] == -1:
                self.ids[i] = self.n_id
                self.n_id += 1

    # ---- img_callback (spec §3.2) ----
    def process(self, img_u8: np.ndarray, t: float) -> dict:
        img_u8 = _as_gray_u8(img_u8, "process")
        H, W = img_u8.shape
        if H < self.ROW or W != self.COL:
            raise ValueError(f"process: expected an image of at least {self.ROW} rows and exactly "
                             f"{self.COL} columns, got {(H, W)}")
        step = self.timing.step(t)
        out = {"t": float(t), "tracked": step["tracked"], "restart": step["restart"],
               "pub_this_frame": step["pub_this_frame"], "published": step["pub_this_frame"],
               "sent": False, "n_new": 0, "n_lk_lost": 0, "n_f_rejected": 0, "n_mask_pruned": 0}
        if not step["tracked"]:
            out.update(_empty_arrays())
            return out
        out.update(self.read_image(img_u8[: self.ROW], float(t), step["pub_this_frame"]))
        self.update_id()
        if step["pub_this_frame"]:
            out["sent"] = self.timing.published()
        out.update({
            "ids": self.ids.copy(),
            "uv": self.cur_pts.copy(),
            "xy": self.cur_un_pts.copy(),
            "velocity": self.pts_velocity.copy(),
            "track_cnt": self.track_cnt.copy(),
            "published_mask": self.track_cnt > 1,
        })
        return out


def _empty_arrays() -> dict:
    return {"ids": np.zeros((0,), np.int64), "uv": np.zeros((0, 2), np.float32),
            "xy": np.zeros((0, 2), np.float32), "velocity": np.zeros((0, 2), np.float32),
            "track_cnt": np.zeros((0,), np.int64), "published_mask": np.zeros((0,), bool)}


# --------------------------------------------------------------------------------------------
# VINS-Fusion tracker (spec §6)
# --------------------------------------------------------------------------------------------
class OracleFusionTracker:
    """VINS-Fusion ``FeatureTracker::trackImage`` (spec §6.2).

    cfg keys: ``max_cnt, min_dist, flow_back`` (default 1), ``camera`` (cam0 flat dict), optional
    ``camera1`` (cam1; its presence = ``stereo_cam``). No CLAHE, no FREQ gating, no first-frame
    skip, no restart logic, no rejectWithF, full-255 mask, ids assigned at detection. Image size
    is the actual image size.

    ``process(t, img0, img1=None)`` returns left arrays ``ids, uv, xy, velocity, track_cnt`` (all
    features, new ones included), right arrays ``ids_right, uv_right, xy_right, velocity_right``,
    ``n_new``, ``used_prediction`` and ``features`` (= :meth:`to_vins_fusion`).
    """

    def __init__(self, cfg: dict):
        self.max_cnt = int(cfg["max_cnt"])
        self.min_dist = int(cfg["min_dist"])
        self.flow_back = bool(int(cfg.get("flow_back", 1)))
        self.camera = dict(cfg["camera"])
        self.camera1 = dict(cfg["camera1"]) if cfg.get("camera1") is not None else None
        self.stereo_cam = self.camera1 is not None
        self.prev_img: np.ndarray | None = None
        self.prev_pts = np.zeros((0, 2), np.float32)
        self.ids = np.zeros((0,), np.int64)
        self.track_cnt = np.zeros((0,), np.int64)
        self.cur_pts = np.zeros((0, 2), np.float32)
        self.cur_un_pts = np.zeros((0, 2), np.float32)
        self.pts_velocity = np.zeros((0, 2), np.float32)
        self.prev_un_pts_map: dict = {}
        self.ids_right = np.zeros((0,), np.int64)
        self.cur_right_pts = np.zeros((0, 2), np.float32)
        self.cur_un_right_pts = np.zeros((0, 2), np.float32)
        self.right_pts_velocity = np.zeros((0, 2), np.float32)
        self.prev_un_right_pts_map: dict = {}
        self.cur_time = 0.0
        self.prev_time = 0.0
        self.n_id = 0
        self._prediction: dict | None = None  # hasPrediction
        self.rows = 0
        self.cols = 0

    def set_prediction(self, pred: dict):
        """``setPrediction`` with pixels already projected: ``{id: (u, v)}``.

        Ids without a prediction fall back to their previous pixel. Consumed by the next
        ``process``. (The per-id lookup is done at process time, which equals VINS's set-time
        lookup because prev_pts/ids do not change in between except through :meth:`remove`.)
        """
        self._prediction = {int(k): (float(v[0]), float(v[1])) for k, v in pred.items()}

    def remove(self, ids) -> None:
        """``removeOutliers``: drop these ids from prev_pts/ids/track_cnt."""
        drop = {int(i) for i in ids}
        keep = np.array([int(i) not in drop for i in self.ids], dtype=bool)
        self.prev_pts, self.ids, self.track_cnt = self.prev_pts[keep], self.ids[keep], self.track_cnt[keep]

    def process(self, t: float, img0: np.ndarray, img1: np.ndarray | None = None) -> dict:
        cur_img = _as_gray_u8(img0, "process(img0)")
        self.cur_time = float(t)
        self.rows, self.cols = cur_img.shape
        prev_pts, ids, track_cnt = self.prev_pts, self.ids, self.track_cnt
        used_prediction = False
        cur_pts = np.zeros((0, 2), np.float32)
        if len(prev_pts) > 0:
            if self._prediction is not None:
                guess = np.array([self._prediction.get(int(i), tuple(prev_pts[k]))
                                  for k, i in enumerate(ids)], np.float32).reshape(-1, 2)
                cur_pts, status = _lk(self.prev_img, cur_img, prev_pts, guess=guess, max_level=1)
                used_prediction = True
                if int(status.sum()) < PREDICTION_MIN_GOOD:
                    cur_pts, status = _lk(self.prev_img, cur_img, prev_pts, max_level=3)
                    used_prediction = False
            else:
                cur_pts, status = _lk(self.prev_img, cur_img, prev_pts, max_level=3)
            if self.flow_back:
                rev, rstatus = _lk(cur_img, self.prev_img, cur_pts, guess=prev_pts, max_level=1)
                dist = np.hypot(*(prev_pts.astype(np.float64) - rev.astype(np.float64)).T)
                status = status & rstatus & (dist <= FLOW_BACK_MAX_PX)
            status &= in_border(cur_pts, self.rows, self.cols)
            prev_pts, cur_pts = prev_pts[status], cur_pts[status]
            ids, track_cnt = ids[status], track_cnt[status]
        track_cnt = track_cnt + 1

        # setMask (full 255 mask, actual size) + GFTT every frame, ids at detection
        base = np.full((self.rows, self.cols), 255, np.uint8)
        cur_pts, ids, track_cnt, mask = _set_mask(cur_pts, ids, track_cnt, base, self.min_dist)
        n_pts = _gftt(cur_img, self.max_cnt - len(cur_pts), self.min_dist, mask)
        n_new = len(n_pts)
        new_ids = np.arange(self.n_id, self.n_id + n_new, dtype=np.int64)
        self.n_id += n_new
        cur_pts = np.concatenate([cur_pts, n_pts]).astype(np.float32)
        ids = np.concatenate([ids, new_ids])
        track_cnt = np.concatenate([track_cnt, np.ones(n_new, np.int64)])

        # undistort + velocity (from the 2nd observation: ids exist at detection)
        cur_un_pts = _normalised(self.camera, cur_pts)
        cur_un_map = {int(i): cur_un_pts[k] for k, i in enumerate(ids)}
        velocity = _velocity(ids, cur_un_pts, self.prev_un_pts_map, self.cur_time - self.prev_time,
                             skip_minus_one=False)

        # stereo
        if img1 is not None and self.stereo_cam:
            right_img = _as_gray_u8(img1, "process(img1)")
            self.ids_right = np.zeros((0,), np.int64)
            self.cur_right_pts = np.zeros((0, 2), np.float32)
            self.cur_un_right_pts = np.zeros((0, 2), np.float32)
            self.right_pts_velocity = np.zeros((0, 2), np.float32)
            cur_un_right_map: dict = {}
            if len(cur_pts) > 0:
                right_pts, status = _lk(cur_img, right_img, cur_pts, max_level=3)
                if self.flow_back:
                    back, st_rl = _lk(right_img, cur_img, right_pts, max_level=3)
                    dist = np.hypot(*(cur_pts.astype(np.float64) - back.astype(np.float64)).T)
                    status = (status & st_rl & in_border(right_pts, self.rows, self.cols)
                              & (dist <= FLOW_BACK_MAX_PX))
                self.ids_right = ids[status].copy()
                self.cur_right_pts = right_pts[status]
                self.cur_un_right_pts = _normalised(self.camera1, self.cur_right_pts)
                cur_un_right_map = {int(i): self.cur_un_right_pts[k] for k, i in enumerate(self.ids_right)}
                self.right_pts_velocity = _velocity(self.ids_right, self.cur_un_right_pts,
                                                    self.prev_un_right_pts_map,
                                                    self.cur_time - self.prev_time, skip_minus_one=False)
            self.prev_un_right_pts_map = cur_un_right_map
        else:
            # no right image this frame: nothing to report for the right camera
            self.ids_right = np.zeros((0,), np.int64)
            self.cur_right_pts = np.zeros((0, 2), np.float32)
            self.cur_un_right_pts = np.zeros((0, 2), np.float32)
            self.right_pts_velocity = np.zeros((0, 2), np.float32)

        # shift
        self.prev_img = cur_img
        self.cur_pts = cur_pts
        self.prev_pts = cur_pts
        self.ids, self.track_cnt = ids, track_cnt
        self.cur_un_pts, self.pts_velocity = cur_un_pts, velocity
        self.prev_un_pts_map = cur_un_map
        self.prev_time = self.cur_time
        self._prediction = None

        return {
            "t": float(t),
            "tracked": True,
            "ids": ids.copy(),
            "uv": cur_pts.copy(),
            "xy": cur_un_pts.copy(),
            "velocity": velocity.copy(),
            "track_cnt": track_cnt.copy(),
            "ids_right": self.ids_right.copy(),
            "uv_right": self.cur_right_pts.copy(),
            "xy_right": self.cur_un_right_pts.copy(),
            "velocity_right": self.right_pts_velocity.copy(),
            "n_new": n_new,
            "used_prediction": used_prediction,
            "features": self.to_vins_fusion(),
        }

    def to_vins_fusion(self) -> dict:
        """``{id: [(cam, [x, y, 1, u, v, vx, vy]), ...]}`` ordered by id, left (0) before right (1)."""
        fm: dict = {}
        for k, i in enumerate(self.ids):
            fm.setdefault(int(i), []).append(
                (0, [float(self.cur_un_pts[k, 0]), float(self.cur_un_pts[k, 1]), 1.0,
                     float(self.cur_pts[k, 0]), float(self.cur_pts[k, 1]),
                     float(self.pts_velocity[k, 0]), float(self.pts_velocity[k, 1])]))
        for k, i in enumerate(self.ids_right):
            fm.setdefault(int(i), []).append(
                (1, [float(self.cur_un_right_pts[k, 0]), float(self.cur_un_right_pts[k, 1]), 1.0,
                     float(self.cur_right_pts[k, 0]), float(self.cur_right_pts[k, 1]),
                     float(self.right_pts_velocity[k, 0]), float(self.right_pts_velocity[k, 1])]))
        return dict(sorted(fm.items()))


# --------------------------------------------------------------------------------------------
# Runner and config loading
# --------------------------------------------------------------------------------------------
def run_oracle_sequence(frames: list, cfg: dict, mode: str = "mono") -> list:
    """Run a fresh oracle over ``frames``.

    mono: ``frames = [(t, img), ...]``; fusion: ``[(t, img0), ...]`` or ``[(t, img0, img1), ...]``.
    Returns one result dict per frame (see the tracker classes).
    """
    if mode == "mono":
        tr = OracleMonoTracker(cfg)
        return [tr.process(f[1], f[0]) for f in frames]
    if mode == "fusion":
        tr = OracleFusionTracker(cfg)
        return [tr.process(f[0], f[1], f[2] if len(f) > 2 else None) for f in frames]
    raise ValueError(f"run_oracle_sequence: mode must be 'mono' or 'fusion', got {mode!r}")


_CAMERA_KEYS = {
    "PINHOLE": ("k1", "k2", "p1", "p2", "fx", "fy", "cx", "cy"),
    "MEI": ("xi", "k1", "k2", "p1", "p2", "gamma1", "gamma2", "u0", "v0"),
    "KANNALA_BRANDT": ("k2", "k3", "k4", "k5", "mu", "mv", "u0", "v0"),
}
_CAMERA_BLOCKS = ("mirror_parameters", "distortion_parameters", "projection_parameters")


def _fs_real(node) -> float:
    # cv2.FileStorage: an absent node reads as 0 (spec §1.1 "missing keys are silent").
    return 0.0 if node.empty() or node.isNone() else float(node.real())


def _camera_from_fs(fs) -> dict:
    mt_node = fs.getNode("model_type")
    model = "MEI" if mt_node.empty() or mt_node.isNone() else mt_node.string()
    if model not in _CAMERA_KEYS:
        raise ValueError(
            f"camera: model_type {model!r} not supported by the oracle (expected exactly one of "
            f"{sorted(_CAMERA_KEYS)}; camodocal's readers are case-sensitive)"
        )
    cam = {"model_type": model}
    for key in _CAMERA_KEYS[model]:
        val = 0.0
        for blk in _CAMERA_BLOCKS:
            n = fs.getNode(blk)
            if not n.empty() and not n.isNone() and not n.getNode(key).empty():
                val = _fs_real(n.getNode(key))
                break
        cam[key] = val
    for key in ("image_width", "image_height"):
        cam[key] = int(_fs_real(fs.getNode(key)))
    return cam


def camera_from_yaml(path) -> dict:
    """Flat camodocal parameter dict from a camera YAML (or a Mono config holding the camera block)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise FileNotFoundError(f"camera_from_yaml: cannot open {path}")
    try:
        return _camera_from_fs(fs)
    finally:
        fs.release()


def cfg_from_vins_yaml(path) -> dict:
    """Oracle cfg from a VINS config, read with ``cv2.FileStorage``.

    VINS-Mono config (camera block inline): keys of :class:`OracleMonoTracker`; with
    ``fisheye: 1`` the mask ``<config dir>/../fisheye_mask.jpg`` is loaded (= VINS's fixed
    ``vins_folder/config/fisheye_mask.jpg``). VINS-Fusion config (``cam0_calib`` present): keys of
    :class:`OracleFusionTracker`, camera files resolved relative to the config's directory,
    ``camera1`` only when ``num_of_cam == 2``. ``mode`` tells which ("mono" / "fusion").
    """
    path = Path(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise FileNotFoundError(f"cfg_from_vins_yaml: cannot open {path}")
    try:
        def i(key):
            return int(_fs_real(fs.getNode(key)))

        def f(key):
            return _fs_real(fs.getNode(key))

        calib0 = fs.getNode("cam0_calib")
        if not calib0.empty() and not calib0.isNone():
            cfg = {
                "mode": "fusion",
                "max_cnt": i("max_cnt"),
                "min_dist": i("min_dist"),
                "flow_back": i("flow_back"),
                "F_threshold": f("F_threshold"),
                "image_width": i("image_width"),
                "image_height": i("image_height"),
                "num_of_cam": i("num_of_cam"),
                "camera": camera_from_yaml(path.parent / calib0.string()),
                "camera1": None,
            }
            if cfg["num_of_cam"] == 2:
                cfg["camera1"] = camera_from_yaml(path.parent / fs.getNode("cam1_calib").string())
            return cfg
        cfg = {
            "mode": "mono",
            "max_cnt": i("max_cnt"),
            "min_dist": i("min_dist"),
            "freq": i("freq"),
            "F_threshold": f("F_threshold"),
            "show_track": i("show_track"),
            "equalize": i("equalize"),
            "fisheye": i("fisheye"),
            "image_width": i("image_width"),
            "image_height": i("image_height"),
            "camera": _camera_from_fs(fs),
        }
    finally:
        fs.release()
    if cfg["fisheye"]:
        mpath = path.parent.parent / "fisheye_mask.jpg"
        mask = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise FileNotFoundError(f"cfg_from_vins_yaml: fisheye=1 but no mask at {mpath}")
        cfg["fisheye_mask"] = mask
    return cfg


if __name__ == "__main__":  # python -m torch_frontend.testing.oracle [VINS-Mono config]: the package's EuRoC sample
    import sys

    from ._photo import PHOTO_DIR

    cam0 = sorted(PHOTO_DIR.glob("*.png"))
    # default: the source checkout's EuRoC config (configs/ is not installed with the package)
    cfg_path = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[2] / "configs" / "euroc.yaml"
    cfg = cfg_from_vins_yaml(cfg_path)
    import time

    frames = [(int(p.stem) / 1e9, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in cam0]
    tr = OracleMonoTracker(cfg)
    print("| frame | tracked | pub | sent | N | msg (cnt>1) | lk lost | F rej | mask pruned | new | ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for k, (t, img) in enumerate(frames):
        t0 = time.perf_counter()
        r = tr.process(img, t)
        ms = 1e3 * (time.perf_counter() - t0)
        print(f"| {k} | {int(r['tracked'])} | {int(r['pub_this_frame'])} | {int(r['sent'])} | {len(r['ids'])} "
              f"| {int(r['published_mask'].sum())} | {r['n_lk_lost']} | {r['n_f_rejected']} "
              f"| {r['n_mask_pruned']} | {r['n_new']} | {ms:.1f} |")
