"""The stages of the loop-closure pipeline between tracking and the pose graph: the keyframe rule,
triangulation of the keyframes' tracks, keyframe description, and ATE against ground truth.

Convention:
    Poses are body-to-world (VINS), float64, quaternions ``(w, x, y, z)``; camera poses are body
    pose ∘ camera-to-body extrinsic ``(R_ic, t_ic)``. Distances in metres, angles in degrees, times
    in seconds. Per-stream lists (frames, keyframes) are Python lists of numpy arrays; the loops
    run over keyframes or chunks of them, never over points.
"""

from __future__ import annotations

import math
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from ..errors import DataError

__all__ = ["KeyframeLog", "as_trajectory", "covered_mask", "describe_keyframe_images", "joint_ate",
           "keyframe_ate", "listed_times", "make_keyframe", "span", "triangulate_keyframes"]

_F64 = torch.float64
#: (point_3d (N, 3), uv (N, 2) pixels, xy (N, 2) normalised, ids (N,)) of one keyframe, numpy
KeyframePoints = Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


# ----------------------------------------------------------------------------------------------
# poses and times


def as_trajectory(x, what: str, times=None):
    """A ``Trajectory`` from a ``Trajectory``, a ``(time, t, q)`` tuple or a trajectory file
    (``trajectory.read_trajectory``: TUM, VINS csv, EuRoC ground truth, KITTI; ``times``: the
    seconds of a KITTI file's lines, its sequence's frames); ``what`` names it in errors. Raises
    ``DataError`` for a file without poses."""
    from ..trajectory import Trajectory, read_trajectory

    if isinstance(x, Trajectory):
        return x
    if isinstance(x, tuple) and len(x) == 3:
        return Trajectory(*(torch.as_tensor(v, dtype=_F64) for v in x))
    traj = read_trajectory(x, times=times)
    if traj.time.shape[0] == 0:
        raise DataError(f"{x}: {what} file has no poses")
    return traj


def covered_mask(traj, times, max_gap: float) -> np.ndarray:
    """``(M,)`` bool numpy: the ``times`` (s) that ``interpolate`` accepts, i.e. on a pose or
    between two poses at most ``max_gap`` s apart (``trajectory.covered``)."""
    from ..trajectory import covered

    return covered(traj, np.asarray(times, dtype=np.float64), max_gap).numpy()


def listed_times(seq) -> Optional[np.ndarray]:
    """Seconds of every frame a sequence lists (None when it cannot tell without decoding)."""
    from ..io.multistream import ns_to_seconds

    if getattr(seq, "kind", "") == "bag":  # listing a bag reads every message
        return None
    try:
        return np.sort(ns_to_seconds(np.array([it.stamp_ns for it in seq._items()], dtype=np.int64)))
    except Exception:  # a reader that cannot list cheaply: the check after tracking still runs
        return None


def span(t) -> str:
    """``"t0 .. t1 s"`` of sorted times (``"empty"``), for messages."""
    t = np.asarray(t, dtype=np.float64)
    return "empty" if t.size == 0 else f"{t[0]:.3f} .. {t[-1]:.3f} s"


# ----------------------------------------------------------------------------------------------
# keyframe choice during tracking


class KeyframeLog:
    """Published frames, their feature observations and the keyframe choice of one stream.

    Keyframe rule (on published frames whose time the poses ``traj`` cover, ``max_gap`` s, and
    that have tracked features): the first such frame, then every frame whose body moved more than
    ``keyframe_distance`` m or turned more than ``keyframe_angle`` degrees since the last keyframe;
    ``keyframe_every=k`` takes every k-th such frame instead. ``poses_name`` names the poses in
    errors.
    """

    def __init__(self, name: str, traj, poses_name: str, max_gap: float, keyframe_distance: float,
                 keyframe_angle: float, keyframe_every: Optional[int]):
        self.name = name
        self.traj = traj
        self.poses_name = poses_name
        self.max_gap = max_gap
        self.kf_distance = keyframe_distance
        self.kf_cos = math.cos(math.radians(keyframe_angle) / 2.0)  # |q_w| of the relative rotation
        self.kf_every = keyframe_every
        self.frames = 0
        self.times: List[float] = []  # published frames
        self.covered: List[bool] = []
        self.obs: List[Tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []  # frame, ids, xy, uv
        self.kf_frames: List[int] = []
        self.kf_images: List[np.ndarray] = []
        self._last: Optional[Tuple[np.ndarray, np.ndarray]] = None  # t, q of the last keyframe
        self._candidates = 0

    def add(self, t: float, ids: np.ndarray, xy: np.ndarray, uv: np.ndarray, image: np.ndarray) -> None:
        """One published frame at ``t`` s: its features' ``ids (N,)``, normalised ``xy (N, 2)``,
        pixel ``uv (N, 2)`` and its ``(H, W)`` uint8 image (kept if it becomes a keyframe)."""
        f = len(self.times)
        self.times.append(t)
        cov = bool(covered_mask(self.traj, np.array([t]), self.max_gap)[0])
        self.covered.append(cov)
        if ids.size:
            self.obs.append((f, ids, xy, uv))
        if not cov or ids.size == 0:
            return
        from ..trajectory import interpolate

        p = interpolate(self.traj, [t], self.max_gap, self.poses_name)
        pt, pq = p.t[0].numpy(), p.q[0].numpy()
        if self.kf_every is not None:
            take = self._candidates % self.kf_every == 0
        elif self._last is None:
            take = True
        else:
            lt, lq = self._last
            take = (np.linalg.norm(pt - lt) > self.kf_distance) or (abs(float(np.dot(pq, lq))) < self.kf_cos)
        self._candidates += 1
        if take:
            self.kf_frames.append(f)
            self.kf_images.append(np.array(image, dtype=np.uint8, copy=True))
            self._last = (pt, pq)

    # -- state (checkpoints) --------------------------------------------------------------------
    STATE_VERSION = 1

    def _settings(self) -> Dict[str, Any]:
        return {"name": self.name, "max_gap": float(self.max_gap), "keyframe_distance": float(self.kf_distance),
                "keyframe_cos": float(self.kf_cos), "keyframe_every": self.kf_every}

    def mark(self) -> Dict[str, int]:
        """Where the log stands (``state_dict(since=...)`` gives what was appended after it)."""
        return {"times": len(self.times), "obs": len(self.obs), "keyframes": len(self.kf_frames)}

    def state_dict(self, since: Optional[Dict[str, int]] = None) -> Dict[str, Any]:
        """The log as CPU tensors: its counters and last keyframe pose, and what was appended to
        its lists after the :meth:`mark` ``since`` (None: from the start), so that a checkpoint
        writes each published frame once (an append-only chunk; :meth:`load_state_dict` takes the
        chunks in order). Published frames: ``times (F,)`` float64, ``covered (F,)`` bool;
        observations: ``obs_frame``/``obs_n (O,)`` int64 (frame, feature count) and the features
        concatenated (``obs_ids``, ``obs_xy``, ``obs_uv``); keyframes: ``kf_frames (K,)`` int64
        and ``kf_images`` (K ``(H, W)`` uint8 tensors)."""
        from ..loop.state import pack_ragged

        m = since or {"times": 0, "obs": 0, "keyframes": 0}
        obs = self.obs[m["obs"]:]
        ids, n = pack_ragged([torch.from_numpy(o[1]) for o in obs], torch.zeros(0, dtype=torch.int64))
        xy, _ = pack_ragged([torch.from_numpy(o[2]) for o in obs], torch.zeros(0, 2, dtype=_F64))
        uv, _ = pack_ragged([torch.from_numpy(o[3]) for o in obs], torch.zeros(0, 2, dtype=_F64))
        return {"kind": "KeyframeLog", "version": self.STATE_VERSION, "settings": self._settings(),
                "start": dict(m), "frames": int(self.frames), "candidates": int(self._candidates),
                "last": None if self._last is None else [torch.from_numpy(np.array(v)) for v in self._last],
                "times": torch.tensor(self.times[m["times"]:], dtype=_F64),
                "covered": torch.tensor(self.covered[m["times"]:], dtype=torch.bool),
                "obs_frame": torch.tensor([o[0] for o in obs], dtype=torch.int64), "obs_n": n,
                "obs_ids": ids, "obs_xy": xy, "obs_uv": uv,
                "kf_frames": torch.tensor(self.kf_frames[m["keyframes"]:], dtype=torch.int64),
                "kf_images": [torch.from_numpy(im) for im in self.kf_images[m["keyframes"]:]]}

    def load_state_dict(self, state) -> None:
        """Restore one :meth:`state_dict` or a list of chunks (in the order they were written;
        each must start where the log stands). Raises ``StateError`` for another version, other
        keyframe settings or a chunk that does not follow."""
        from ..loop.state import StateError, check_same, check_state, split_ragged

        for st in (state if isinstance(state, (list, tuple)) else [state]):
            check_state(st, "KeyframeLog", self.STATE_VERSION, ("settings", "start", "times", "obs_n", "kf_frames"))
            here = self._settings()
            for key, v in st["settings"].items():
                check_same("KeyframeLog", key, v, here.get(key))
            if st["start"] != self.mark():
                raise StateError(f"KeyframeLog state of {self.name}: a chunk starting at {st['start']} does not "
                                 f"follow the log, which stands at {self.mark()} (a chunk is missing)")
            n = st["obs_n"]
            parts = [split_ragged(st[k], n) for k in ("obs_ids", "obs_xy", "obs_uv")]
            self.obs += [(int(f), i.numpy(), x.numpy(), u.numpy())
                         for f, i, x, u in zip(st["obs_frame"].tolist(), *parts)]
            self.times += st["times"].tolist()
            self.covered += [bool(c) for c in st["covered"].tolist()]
            self.kf_frames += [int(f) for f in st["kf_frames"].tolist()]
            self.kf_images += [im.numpy().copy() for im in st["kf_images"]]
            self.frames, self._candidates = int(st["frames"]), int(st["candidates"])
            self._last = None if st["last"] is None else (st["last"][0].numpy().copy(), st["last"][1].numpy().copy())


# ----------------------------------------------------------------------------------------------
# triangulation


def _frame_poses(log: KeyframeLog, R_ic: torch.Tensor, t_ic: torch.Tensor):
    """Camera ``(R_wc (F, 3, 3), t_wc (F, 3))`` and body ``(R_wb, T_wb)`` poses of every published
    frame (zeros for frames the poses do not cover), numpy float64."""
    from ..loop.triangulate import camera_poses
    from ..trajectory import interpolate

    times = np.asarray(log.times, dtype=np.float64)
    F = times.size
    cov_idx = np.flatnonzero(np.asarray(log.covered, dtype=bool))
    R_wc = np.zeros((F, 3, 3))
    t_wc = np.zeros((F, 3))
    R_wb = np.zeros((F, 3, 3))
    T_wb = np.zeros((F, 3))
    if cov_idx.size:
        p = interpolate(log.traj, times[cov_idx], log.max_gap, log.poses_name)
        Rb = p.R
        R_wb[cov_idx] = Rb.numpy()
        T_wb[cov_idx] = p.t.numpy()
        Rc, tc = camera_poses(Rb, p.t, R_ic, t_ic)
        R_wc[cov_idx] = Rc.numpy()
        t_wc[cov_idx] = tc.numpy()
    return R_wc, t_wc, R_wb, T_wb


def _observations(log: KeyframeLog):
    """Every observation on a covered frame as flat arrays ``(frame, id, xy, uv)``."""
    if not log.obs:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.zeros((0, 2)), np.zeros((0, 2))
    cov = np.asarray(log.covered, dtype=bool)
    o_f = np.concatenate([np.full(o[1].size, o[0], dtype=np.int64) for o in log.obs])
    o_id = np.concatenate([o[1] for o in log.obs]).astype(np.int64)
    o_xy = np.concatenate([o[2] for o in log.obs]).astype(np.float64)
    o_uv = np.concatenate([o[3] for o in log.obs]).astype(np.float64)
    keep = cov[o_f]  # observations need a camera pose
    return o_f[keep], o_id[keep], o_xy[keep], o_uv[keep]


def triangulate_keyframes(log: KeyframeLog, R_ic: torch.Tensor, t_ic: torch.Tensor, chunk: int, window: int
                          ) -> Tuple[List[KeyframePoints], np.ndarray, np.ndarray]:
    """Points of every keyframe of ``log``: the tracks it sees, triangulated from all their
    observations within ``window`` published frames of the chunk (``chunk`` keyframes per batched
    ``triangulate_points`` call); kept when they triangulate and lie in front of the keyframe
    camera. Returns ``(points per keyframe, T_wb (K, 3), R_wb (K, 3, 3))``."""
    from ..loop.triangulate import triangulate_points

    R_wc, t_wc, R_wb, T_wb = _frame_poses(log, R_ic, t_ic)
    o_f, o_id, o_xy, o_uv = _observations(log)
    kf = np.asarray(log.kf_frames, dtype=np.int64)
    out: List[KeyframePoints] = []
    for c0 in range(0, kf.size, chunk):  # chunks of keyframes, each one batched call
        ck = kf[c0:c0 + chunk]
        in_kf = np.isin(o_f, ck)
        tracks = np.unique(o_id[in_kf])
        sel = np.isin(o_id, tracks) & (o_f >= ck.min() - window) & (o_f <= ck.max() + window)
        sf, sid, sxy = o_f[sel], o_id[sel], o_xy[sel]
        frames, fcol = np.unique(sf, return_inverse=True)
        prow = np.searchsorted(tracks, sid)
        P, Fc = tracks.size, frames.size
        obs = np.zeros((P, Fc, 2))
        mask = np.zeros((P, Fc), dtype=bool)
        obs[prow, fcol] = sxy
        mask[prow, fcol] = True
        if P:
            X, ok = triangulate_points(torch.from_numpy(R_wc[frames]), torch.from_numpy(t_wc[frames]),
                                       torch.from_numpy(obs), torch.from_numpy(mask))
            X, ok = X.detach().cpu().double().numpy(), ok.cpu().numpy().astype(bool)
        else:
            X, ok = np.zeros((0, 3)), np.zeros(0, dtype=bool)
        for f in ck.tolist():  # keyframes of the chunk, not points
            rows = np.flatnonzero(o_f == f)
            pi = np.searchsorted(tracks, o_id[rows])
            Xk = X[pi] if pi.size else np.zeros((0, 3))
            # in front of the keyframe camera (triangulation may keep a point behind a far view)
            depth = ((Xk - t_wc[f]) @ R_wc[f])[:, 2] if pi.size else np.zeros(0)
            good = ok[pi] & (depth > 0) & np.isfinite(Xk).all(1) if pi.size else np.zeros(0, dtype=bool)
            rows = rows[good]
            out.append((Xk[good], o_uv[rows], o_xy[rows], o_id[rows]))
    return out, T_wb[kf], R_wb[kf]


# ----------------------------------------------------------------------------------------------
# description and keyframes


def describe_keyframe_images(images: List[np.ndarray], points: List[KeyframePoints], camera, device,
                             batch: int) -> List[Dict[str, torch.Tensor]]:
    """``loop.describe_keyframes`` of ``(H, W)`` uint8 keyframe images with their tracked points,
    ``batch`` keyframes per call on ``device``; per keyframe a dict of CPU tensors
    (``keypoints``, ``keypoints_norm`` float64, ``brief``, ``window_brief``)."""
    from ..loop.keyframe import describe_keyframes
    from .common import pad_ragged

    res = []
    for b0 in range(0, len(images), batch):
        imgs = torch.from_numpy(np.stack(images[b0:b0 + batch]))[:, None].to(device)
        pts = points[b0:b0 + batch]
        uv, valid = pad_ragged([torch.from_numpy(p[1]).float() for p in pts], min_length=1)
        d = describe_keyframes(imgs, camera, uv.to(device), valid.to(device))
        d = {k: v.cpu() for k, v in d.items()}
        for i, p in enumerate(pts):
            kv = d["keypoints_valid"][i]
            res.append({"keypoints": d["keypoints"][i][kv].clone(),
                        "keypoints_norm": d["keypoints_norm"][i][kv].to(_F64).clone(),
                        "brief": d["brief"][i][kv].clone(),
                        "window_brief": d["window_brief"][i, : p[1].shape[0]].clone()})
    return res


def make_keyframe(time: float, sequence: int, T, R, pts: KeyframePoints, desc: Dict[str, torch.Tensor]):
    """The pose graph's ``KeyFrame`` of one keyframe: VIO body pose ``(T (3,), R (3, 3))``, its
    triangulated points and its descriptors (from :func:`describe_keyframe_images`)."""
    from ..loop.keyframe import KeyFrame

    X, uv, xy, ids = pts
    return KeyFrame(
        time=float(time), sequence=int(sequence),
        origin_vio_T=torch.as_tensor(T, dtype=_F64).clone(), origin_vio_R=torch.as_tensor(R, dtype=_F64).clone(),
        point_3d=torch.from_numpy(np.ascontiguousarray(X, dtype=np.float64)),
        point_2d_uv=torch.from_numpy(np.ascontiguousarray(uv, dtype=np.float32)),
        point_2d_norm=torch.from_numpy(np.ascontiguousarray(xy, dtype=np.float64)),
        point_id=torch.from_numpy(np.ascontiguousarray(ids, dtype=np.int64)),
        window_brief=desc["window_brief"], keypoints=desc["keypoints"].float(),
        keypoints_norm=desc["keypoints_norm"], brief=desc["brief"],
    )


# ----------------------------------------------------------------------------------------------
# ATE


def keyframe_ate(est, gt, max_gap: float) -> Tuple[Optional[float], int, float, Optional[Tuple[Any, Any]]]:
    """ATE (m) of the trajectory ``est`` against ``gt`` interpolated at ``est``'s times (the
    covered ones, SE(3)-aligned): ``(rmse or None when fewer than 3 times are covered, pairs, sum
    of squared errors, (est positions, reference positions))``."""
    from ..trajectory import Trajectory, ate_rmse, interpolate

    t = est.time.numpy()
    cov = covered_mask(gt, t, max_gap)
    if int(cov.sum()) < 3:
        return None, 0, 0.0, None
    idx = torch.from_numpy(np.flatnonzero(cov))
    ref = interpolate(gt, t[cov], max_gap, "ground truth")
    sub = Trajectory(est.time[idx], est.t[idx], est.q[idx])
    e = ate_rmse(sub, ref, max_dt=1e-6)
    return e, int(cov.sum()), e * e * int(cov.sum()), (sub.t, ref.t)


def joint_ate(pairs) -> float:
    """RMSE (m) after ONE SE(3) alignment of every stream's positions (a shared map's world)."""
    from ..trajectory import align_se3

    est = torch.cat([p[0] for p in pairs])
    ref = torch.cat([p[1] for p in pairs])
    R, t, _ = align_se3(est, ref)
    return float(((ref - (est @ R.T + t)) ** 2).sum(-1).mean().sqrt())
