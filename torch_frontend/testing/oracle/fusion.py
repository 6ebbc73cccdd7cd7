"""The VINS-Fusion tracker of the oracle: ``FeatureTracker::trackImage`` (spec §6), mono or
stereo, with flow-back and predictions.

Convention: as the package (:mod:`torch_frontend.testing.oracle`).
"""

from __future__ import annotations

import numpy as np

from .camodocal import _normalised
from .primitives import (
    FLOW_BACK_MAX_PX,
    PREDICTION_MIN_GOOD,
    _as_gray_u8,
    _gftt,
    _lk,
    _set_mask,
    _velocity,
    in_border,
)


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
