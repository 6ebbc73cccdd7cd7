"""The VINS-Mono ``feature_tracker`` node of the oracle: the ``img_callback`` timing (spec §3.2,
:class:`MonoTiming`) and ``readImage`` + ``updateID`` (spec §3.5 - §3.11, :class:`OracleMonoTracker`).

Convention: as the package (:mod:`torch_frontend.testing.oracle`).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .camodocal import _normalised, lift_projective
from .primitives import (
    CLAHE_CLIP,
    CLAHE_GRID,
    F_CONFIDENCE,
    FOCAL_LENGTH,
    RESTART_GAP_S,
    _as_gray_u8,
    _gftt,
    _lk,
    _set_mask,
    _velocity,
    c_round,
    in_border,
)


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
