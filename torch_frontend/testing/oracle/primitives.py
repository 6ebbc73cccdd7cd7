"""The oracle's shared pieces: the VINS constants (spec §2), VINS's two roundings (spec §5.5,
§3.2) and the cv2 steps both trackers call (pyramidal LK, ``setMask``, GFTT, velocities).

Convention: as the package (:mod:`torch_frontend.testing.oracle`): pixels ``(u, v)`` = (x, y),
point arrays ``(N, 2)`` float32, images ``(H, W)`` uint8.
"""

from __future__ import annotations

import math

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
