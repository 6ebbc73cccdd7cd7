"""Loop closure on images + a VIO trajectory, without ROS: what ``torch-frontend loop`` and
``torch-frontend demo --loop`` run (``run_loop``).

Pipeline (one call, B input streams):

1. **Tracking**: the VINS front end (``FeatureTracker``, B streams in one batch) on the images.
2. **Keyframes**: VINS takes keyframes from its estimator; here they are picked from the
   front end's published frames whose time the given poses cover (see *Keyframe rule*). A
   keyframe's pose is the given body pose, interpolated (linear / slerp) at the image time.
3. **Triangulation**: each keyframe's points are the tracks (feature ids) it sees, triangulated
   from all their observations on published frames with the given poses (camera pose = body pose
   ∘ camera-to-body extrinsic), in batched ``triangulate_points`` calls (chunks of keyframes);
   only points that triangulate (``ok``) and lie in front of the keyframe camera are kept.
4. **Description**: FAST + BRIEF of the keyframes (``describe_keyframes``, batched).
5. **Vocabulary**: loaded (``--vocabulary``: the package's ``.npz``, VINS's ``brief_k10L6.bin``
   or a DBoW2 YAML) or trained on this run's keyframe descriptors (``--train-vocabulary``).
6. **Pose graph**: ``PoseGraph.add_keyframe`` per keyframe in time order (place recognition,
   verification, 4-DoF or 6-DoF optimisation). Several streams share one graph (VINS's
   multi-sequence map: stream b is sequence b + 1, added one after the other, merged into the
   first one's world by their first loop) or keep one graph each (``separate_graphs``).

Convention:
    * Poses are body-to-world ``(R_w_i, T_w_i)`` float64 (VINS), quaternions ``(w, x, y, z)``; the
      extrinsic ``(R_ic, t_ic)`` is camera-to-body (VINS's ``qic``, ``tic``): from the config's
      ``extrinsicRotation``/``extrinsicTranslation`` (VINS-Mono), ``body_T_cam0`` (VINS-Fusion) or
      an EuRoC ``sensor.yaml``'s ``T_BS``; identity when none is given.
    * Keyframe rule (per stream, on published frames whose time the poses cover and that have
      tracked features): the first such frame, then every frame whose body moved more than
      ``keyframe_distance`` metres or turned more than ``keyframe_angle`` degrees since the last
      keyframe; ``keyframe_every=k`` takes every k-th such frame instead.
    * Pose coverage: a frame is covered when its time lies between two poses at most
      ``max_pose_gap`` seconds apart (or on a pose). Uncovered frames are tracked but never
      keyframes (as VINS, whose estimator publishes nothing before it initialises); a stream with
      no covered frame at all is a ``DataError`` naming the poses file and both time spans.
    * Keyframes with 25 points or fewer (VINS needs > 25 matches) join the place database
      without querying it.
    * ATE (``ate_before`` = input VIO, ``ate_after`` = loop-corrected, metres): RMSE of keyframe
      positions after an SE(3) alignment to the ground truth interpolated at the keyframe times
      (``io.trajectory.ate_rmse``); with several streams the top-level values pool every
      keyframe's squared error (each stream aligned on its own); a shared map of several streams
      also gets ``ate_joint_before``/``ate_joint_after``: one alignment for all streams.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ..errors import ConfigError, DataError
from ..io.frames import Sequence as _FrameSequence
from ..io.frames import _Item

__all__ = [
    "ArraySequence",
    "LoopRecord",
    "LoopRun",
    "StreamRun",
    "DEMO_RENDER",
    "demo_config",
    "demo_loop",
    "demo_sequence",
    "extrinsic_from_config",
    "format_loop_summary",
    "load_vocabulary",
    "run_loop",
]

PathLike = Union[str, Path]
_F64 = torch.float64
MIN_POINTS_TO_QUERY = 25  # VINS accepts a loop only with > 25 matches: fewer points can never pass


# ----------------------------------------------------------------------------------------------
# results


@dataclass
class LoopRecord:
    """One verified loop candidate: the pose graph's ``LoopResult`` plus where it happened.

    ``graph``: graph number; ``stream``/``old_stream``: input streams of the current and old
    keyframes (-1 for a keyframe loaded with ``load_graph``); ``time``/``old_time``: seconds.
    """

    graph: int
    stream: int
    old_stream: int
    time: float
    old_time: float
    result: Any


@dataclass
class StreamRun:
    """One input stream of a run.

    ``vio``/``corrected``: ``io.trajectory.Trajectory`` of its keyframes (input VIO poses /
    loop-corrected poses in the pose-graph world); ``graph_indices``: the keyframes' indices in
    graph ``graph``; ``num_points``: 3-D points per keyframe; ``ground_truth``: the reference
    trajectory or None; ``ate_before``/``ate_after`` in metres or None.
    """

    name: str
    stream: int
    graph: int
    sequence: int
    frames: int = 0
    published: int = 0
    uncovered: int = 0
    keyframe_times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    graph_indices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    num_points: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    vio: Any = None
    corrected: Any = None
    ground_truth: Any = None
    ate_before: Optional[float] = None
    ate_after: Optional[float] = None


@dataclass
class LoopRun:
    """Everything a run produced: the pose graph(s), the streams, every verified loop candidate,
    the ``summary.json`` dict and, with ``keep_images``, the keyframe images
    ``{(graph, index): (H, W) uint8}``."""

    graphs: List[Any]
    streams: List[StreamRun]
    loops: List[LoopRecord]
    summary: Dict[str, Any]
    images: Optional[Dict[Tuple[int, int], np.ndarray]] = None
    out: Optional[Path] = None

    def keyframe(self, graph: int, index: int):
        """The ``KeyFrame`` with ``index`` in graph ``graph``."""
        return self.graphs[graph].keyframes[index]


# ----------------------------------------------------------------------------------------------
# inputs


class ArraySequence(_FrameSequence):
    """In-memory frames as an ``io`` sequence (the demo's rendered images).

    Args:
        images: ``(N, H, W)`` uint8 array (or a list of ``(H, W)`` arrays).
        times: ``(N,)`` seconds, increasing.
        name: for messages and outputs.
    """

    kind = "array"

    def __init__(self, images, times, name: str = "array"):
        super().__init__(name, False)
        self.images = [np.ascontiguousarray(np.asarray(im, dtype=np.uint8)) for im in images]
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        if t.shape[0] != len(self.images):
            raise ValueError(f"times: expected {len(self.images)} values (one per image), got {t.shape[0]}")
        self.stamps_ns = np.round(t * 1e9).astype(np.int64)

    def __len__(self) -> int:
        return len(self.images)

    def _items(self):
        for i, im in enumerate(self.images):
            yield _Item(i, int(self.stamps_ns[i]), f"{self.name}#{i}", lambda im=im: im)


def extrinsic_from_config(cfg) -> Tuple[torch.Tensor, torch.Tensor]:
    """Camera-to-body ``(R_ic (3, 3), t_ic (3,))`` float64 of a ``TrackerConfig`` (see the module
    docstring); identity / zero when the config gives none."""
    raw = getattr(cfg, "raw", None) or {}
    path = getattr(cfg, "path", None)
    if "extrinsicRotation" in raw or "extrinsicTranslation" in raw:
        R = np.asarray(raw.get("extrinsicRotation"), dtype=np.float64)
        t = np.asarray(raw.get("extrinsicTranslation"), dtype=np.float64)
        if R.shape != (3, 3):
            raise ConfigError(f"expected a 3x3 matrix, got shape {R.shape}", path, "extrinsicRotation")
        if t.size != 3:
            raise ConfigError(f"expected 3 numbers, got shape {t.shape}", path, "extrinsicTranslation")
        return torch.from_numpy(R.copy()), torch.from_numpy(t.reshape(3).copy())
    T = getattr(cfg, "body_T_cam0", None)
    if T is None and path and Path(path).name == "sensor.yaml":
        from ..io.fsyaml import read_opencv_yaml

        tbs = read_opencv_yaml(Path(path)).get("T_BS")
        if isinstance(tbs, dict) and len(tbs.get("data", [])) == 16:
            T = np.asarray(tbs["data"], dtype=np.float64).reshape(4, 4)
    if T is not None:
        T = np.asarray(T, dtype=np.float64)
        return torch.from_numpy(T[:3, :3].copy()), torch.from_numpy(T[:3, 3].copy())
    return torch.eye(3, dtype=_F64), torch.zeros(3, dtype=_F64)


def load_vocabulary(path: PathLike):
    """A ``Vocabulary`` from the package's ``.npz`` (``Vocabulary.save``), VINS's binary
    ``brief_k10L6.bin`` or a DBoW2 YAML, told apart by their content.

    Raises:
        DataError: a missing file, or one in none of these formats (one line naming the file).
    """
    from .vocabulary import Vocabulary

    p = Path(path)
    if not p.is_file():
        raise DataError(f"{p}: vocabulary file not found" if not p.exists() else f"{p}: not a file (expected a vocabulary)")
    with open(p, "rb") as fh:
        head = fh.read(16)
    try:
        if head.startswith(b"PK"):  # a zip: numpy .npz
            return Vocabulary.load(p)
        if head.lstrip().startswith((b"%YAML", b"vocabulary")) or p.suffix.lower() in (".yml", ".yaml"):
            return Vocabulary.load_dbow2_yaml(p)
        return Vocabulary.load_vins_bin(p)
    except (ConfigError, DataError, ValueError, KeyError, OSError) as exc:
        detail = str(exc)
        if detail.startswith(str(p)):
            detail = detail[len(str(p)):].lstrip(": ")
        raise DataError(f"{p}: not a vocabulary in a known format (the package's .npz, VINS's brief_k10L6.bin "
                        f"or a DBoW2 YAML): {detail}") from None


def _as_trajectory(x, what: str):
    from ..io.trajectory import Trajectory, read_trajectory

    if isinstance(x, Trajectory):
        return x
    if isinstance(x, tuple) and len(x) == 3:
        return Trajectory(*(torch.as_tensor(v, dtype=_F64) for v in x))
    traj = read_trajectory(x)
    if traj.time.shape[0] == 0:
        raise DataError(f"{x}: {what} file has no poses")
    return traj


def _covered(traj, times, max_gap: float) -> np.ndarray:
    """``(M,)`` bool numpy: the times ``interpolate`` accepts (``io.trajectory.covered``)."""
    from ..io.trajectory import covered

    return covered(traj, np.asarray(times, dtype=np.float64), max_gap).numpy()


def _listed_times(seq) -> Optional[np.ndarray]:
    """Seconds of every frame a sequence lists (None when it cannot tell without decoding)."""
    from ..io.multistream import ns_to_seconds

    if getattr(seq, "kind", "") == "bag":  # listing a bag reads every message
        return None
    try:
        return np.sort(ns_to_seconds(np.array([it.stamp_ns for it in seq._items()], dtype=np.int64)))
    except Exception:  # a reader that cannot list cheaply: the check after tracking still runs
        return None


def _span(t) -> str:
    t = np.asarray(t, dtype=np.float64)
    return "empty" if t.size == 0 else f"{t[0]:.3f} .. {t[-1]:.3f} s"


# ----------------------------------------------------------------------------------------------
# per-stream bookkeeping during tracking


class _StreamLog:
    """Published frames, their feature observations and the keyframe choice of one stream."""

    def __init__(self, name: str, traj, poses_name: str, max_gap: float, kf_distance: float,
                 kf_angle: float, kf_every: Optional[int]):
        self.name = name
        self.traj = traj
        self.poses_name = poses_name
        self.max_gap = max_gap
        self.kf_distance = kf_distance
        self.kf_cos = math.cos(math.radians(kf_angle) / 2.0)  # |q_w| of the relative rotation
        self.kf_every = kf_every
        self.frames = 0
        self.times: List[float] = []  # published frames
        self.covered: List[bool] = []
        self.obs: List[Tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []  # frame, ids, xy, uv
        self.kf_frames: List[int] = []
        self.kf_images: List[np.ndarray] = []
        self._last: Optional[Tuple[np.ndarray, np.ndarray]] = None  # t, q of the last keyframe
        self._candidates = 0

    def add(self, t: float, ids: np.ndarray, xy: np.ndarray, uv: np.ndarray, image: np.ndarray) -> None:
        f = len(self.times)
        self.times.append(t)
        cov = bool(_covered(self.traj, np.array([t]), self.max_gap)[0])
        self.covered.append(cov)
        if ids.size:
            self.obs.append((f, ids, xy, uv))
        if not cov or ids.size == 0:
            return
        from ..io.trajectory import interpolate

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


# ----------------------------------------------------------------------------------------------
# stages


def _triangulate_stream(log: _StreamLog, R_ic: torch.Tensor, t_ic: torch.Tensor, chunk: int, window: int):
    """Points of every keyframe of ``log``: list of ``(point_3d (N, 3), uv (N, 2), norm (N, 2),
    ids (N,))`` numpy arrays, plus the keyframe body poses ``(T (K, 3), R (K, 3, 3))``."""
    from ..io.trajectory import interpolate
    from .triangulate import camera_poses, triangulate_points

    times = np.asarray(log.times, dtype=np.float64)
    cov = np.asarray(log.covered, dtype=bool)
    F = times.size
    cov_idx = np.flatnonzero(cov)
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
    if log.obs:
        o_f = np.concatenate([np.full(o[1].size, o[0], dtype=np.int64) for o in log.obs])
        o_id = np.concatenate([o[1] for o in log.obs]).astype(np.int64)
        o_xy = np.concatenate([o[2] for o in log.obs]).astype(np.float64)
        o_uv = np.concatenate([o[3] for o in log.obs]).astype(np.float64)
        keep = cov[o_f]  # observations need a camera pose
        o_f, o_id, o_xy, o_uv = o_f[keep], o_id[keep], o_xy[keep], o_uv[keep]
    else:
        o_f = o_id = np.zeros(0, dtype=np.int64)
        o_xy = o_uv = np.zeros((0, 2))
    kf = np.asarray(log.kf_frames, dtype=np.int64)
    out: List[Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
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


def _describe(images: List[np.ndarray], points: List[tuple], camera, device, batch: int):
    """``describe_keyframes`` in batches of ``batch`` keyframes; returns per keyframe a dict of
    CPU tensors (keypoints, keypoints_norm, brief, window_brief)."""
    from .keyframe import describe_keyframes

    res = []
    for b0 in range(0, len(images), batch):
        imgs = torch.from_numpy(np.stack(images[b0:b0 + batch]))[:, None].to(device)
        pts = points[b0:b0 + batch]
        N = max(1, max(p[1].shape[0] for p in pts))
        uv = torch.zeros(len(pts), N, 2, dtype=torch.float32)
        valid = torch.zeros(len(pts), N, dtype=torch.bool)
        for i, p in enumerate(pts):  # keyframes of the batch, not points
            n = p[1].shape[0]
            uv[i, :n] = torch.from_numpy(p[1]).float()
            valid[i, :n] = True
        d = describe_keyframes(imgs, camera, uv.to(device), valid.to(device))
        d = {k: v.cpu() for k, v in d.items()}
        for i, p in enumerate(pts):
            kv = d["keypoints_valid"][i]
            res.append({"keypoints": d["keypoints"][i][kv].clone(),
                        "keypoints_norm": d["keypoints_norm"][i][kv].to(_F64).clone(),
                        "brief": d["brief"][i][kv].clone(),
                        "window_brief": d["window_brief"][i, : p[1].shape[0]].clone()})
    return res


def _make_keyframe(time: float, sequence: int, T, R, pts: tuple, desc: Dict[str, torch.Tensor]):
    from .keyframe import KeyFrame

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


def _ate(est, gt, max_gap: float) -> Tuple[Optional[float], int, float, Optional[Tuple[torch.Tensor, torch.Tensor]]]:
    """ATE of ``est`` against ``gt`` interpolated at ``est``'s times (covered ones): ``(rmse or
    None, pairs, sum of squared errors, (est positions, reference positions))``."""
    from ..io.trajectory import Trajectory, ate_rmse, interpolate

    t = est.time.numpy()
    cov = _covered(gt, t, max_gap)
    if int(cov.sum()) < 3:
        return None, 0, 0.0, None
    idx = torch.from_numpy(np.flatnonzero(cov))
    ref = interpolate(gt, t[cov], max_gap, "ground truth")
    sub = Trajectory(est.time[idx], est.t[idx], est.q[idx])
    e = ate_rmse(sub, ref, max_dt=1e-6)
    return e, int(cov.sum()), e * e * int(cov.sum()), (sub.t, ref.t)


def _joint_ate(pairs) -> float:
    """RMSE after ONE SE(3) alignment of every stream's positions (a shared map's common world)."""
    from ..io.trajectory import align_se3

    est = torch.cat([p[0] for p in pairs])
    ref = torch.cat([p[1] for p in pairs])
    R, t, _ = align_se3(est, ref)
    return float(((ref - (est @ R.T + t)) ** 2).sum(-1).mean().sqrt())


# ----------------------------------------------------------------------------------------------
# the run


def run_loop(
    config,
    sources: Sequence[Any],
    poses: Sequence[Any],
    out: Optional[PathLike] = None,
    *,
    vocabulary: Any = None,
    train_vocabulary: bool = False,
    vocabulary_k: int = 10,
    vocabulary_L: int = 4,
    vocabulary_sample: Optional[int] = 200,
    load_graph: Optional[PathLike] = None,
    ground_truth: Optional[Sequence[Any]] = None,
    separate_graphs: bool = False,
    mode: str = "4dof",
    device: Union[str, torch.device] = "cpu",
    tracker_mode: str = "mono",
    keyframe_distance: float = 0.2,
    keyframe_angle: float = 10.0,
    keyframe_every: Optional[int] = None,
    max_pose_gap: float = 0.5,
    R_ic=None,
    t_ic=None,
    pnp_backend: str = "torch",
    max_frames: Optional[int] = None,
    fps: Optional[float] = None,
    topic: Optional[str] = None,
    camera: str = "cam0",
    skip_bad_frames: bool = False,
    triangulation_chunk: int = 32,
    track_window: int = 40,
    describe_batch: int = 8,
    seed: int = 0,
    keep_images: bool = False,
    progress: Optional[bool] = None,
    write: bool = True,
    extra_summary: Optional[Dict[str, Any]] = None,
) -> LoopRun:
    """Loop-closure run on B image streams with their VIO poses (see the module docstring).

    Convention:
        ``sources``: one entry per stream, ``(kind, path)`` with kind ``euroc``/``images``/``bag``
        (as ``torch-frontend track``) or an ``io`` ``Sequence`` object (e.g. ``ArraySequence``).
        ``poses``: one per stream, a trajectory file (TUM, VINS csv, EuRoC ground truth; read by
        ``io.trajectory.read_trajectory``) or a ``Trajectory`` (body-to-world, seconds, wxyz).
        ``ground_truth``: None or one entry (file, ``Trajectory`` or None) per stream.
        Distances in metres, angles in degrees, times in seconds.

    Args:
        config: ``TrackerConfig``, a VINS config path, or None (``sensor.yaml`` of the first
            ``euroc`` input).
        out: output folder (``report.write_loop_outputs``); None or ``write=False``: write nothing.
        vocabulary: a ``Vocabulary`` or a vocabulary file (``load_vocabulary``).
        train_vocabulary: train one (k ``vocabulary_k``, depth ``vocabulary_L``) on this run's
            keyframe descriptors (a seeded random sample of at most ``vocabulary_sample`` per
            keyframe; None: all); exactly one of ``vocabulary`` / ``train_vocabulary``.
        load_graph: a saved pose graph (VINS format) loaded into every graph first.
        separate_graphs: one pose graph per stream instead of one shared map.
        mode: ``"4dof"`` (VIO with IMU) or ``"6dof"`` (without).
        tracker_mode: front end rules, ``"mono"`` or ``"fusion"``.
        keyframe_distance, keyframe_angle, keyframe_every: the keyframe rule.
        max_pose_gap: largest gap between two poses to interpolate across (s).
        R_ic, t_ic: camera-to-body extrinsic overriding the config's.
        keep_images: keep the keyframe images in ``LoopRun.images`` (for plots of matches).
        progress: tqdm bars on stderr (None: only on a terminal).

    Returns:
        the :class:`LoopRun` (its ``summary`` is also ``summary.json``).

    Raises:
        DataError: unreadable inputs, poses that cover none of a stream's images, a bad vocabulary
            file, ground truth that does not overlap, ...; ConfigError: a bad config;
            ValueError: bad arguments (counts of poses/ground truth, options).
    """
    from ..config import TrackerConfig, load_config
    from ..io import MultiStream, open_sequence
    from ..tracker import FeatureTracker
    from .geometry import R_to_quat
    from .pose_graph import PoseGraph
    from .vocabulary import Vocabulary

    t_start = _time.perf_counter()
    sources = list(sources)
    poses = list(poses)
    if not sources:
        raise ValueError("no input: give at least one --euroc DIR, --images DIR or --bag FILE")
    if len(poses) != len(sources):
        raise ValueError(f"--poses: expected one poses file per input ({len(sources)} inputs), got {len(poses)}")
    gts = [None] * len(sources) if ground_truth is None else list(ground_truth)
    if len(gts) != len(sources):
        raise ValueError(f"--ground-truth: expected one file per input ({len(sources)} inputs), got {len(gts)}")
    if (vocabulary is None) == (not train_vocabulary):
        raise ValueError("give a vocabulary (--vocabulary FILE) or --train-vocabulary" if vocabulary is None
                         else "give either --vocabulary or --train-vocabulary, not both")
    if mode not in ("4dof", "6dof"):
        raise ValueError(f"mode: expected '4dof' or '6dof', got {mode!r}")
    if keyframe_every is not None and keyframe_every < 1:
        raise ValueError(f"keyframe_every: expected >= 1, got {keyframe_every}")
    if not (keyframe_distance >= 0 and keyframe_angle >= 0 and max_pose_gap > 0):
        raise ValueError("keyframe_distance and keyframe_angle must be >= 0, max_pose_gap > 0")
    dev = torch.device(device)
    times: Dict[str, float] = {}

    # -- inputs (all checked before the long part)
    kinds = [s for s in sources if isinstance(s, tuple)]
    if isinstance(config, TrackerConfig):
        cfg = config
    elif config is not None:
        cfg = load_config(config)
    else:
        euroc = [p for k, p in kinds if k == "euroc"]
        if not euroc:
            raise ConfigError("no CONFIG given: a VINS config file is needed unless an --euroc folder provides sensor.yaml")
        from ..io.euroc import euroc_config

        cfg = euroc_config(euroc[0], camera)
    if cfg.camera is None:
        raise ConfigError("has no camera (an estimator-only config?); the tracker needs one", cfg.path)
    R_ic0, t_ic0 = extrinsic_from_config(cfg)
    R_ic = R_ic0 if R_ic is None else torch.as_tensor(R_ic, dtype=_F64).reshape(3, 3)
    t_ic = t_ic0 if t_ic is None else torch.as_tensor(t_ic, dtype=_F64).reshape(3)
    seqs = [s if isinstance(s, _FrameSequence) else
            open_sequence(s[0], s[1], camera=camera, fps=fps, topic=topic or cfg.image_topic or None,
                          skip_bad=skip_bad_frames) for s in sources]
    names = [f"{s.kind}:{s.name}" for s in seqs]
    trajs = [_as_trajectory(p, "poses") for p in poses]
    pose_names = [str(p) if not isinstance(p, tuple) else f"poses of {n}" for p, n in zip(poses, names)]
    gt_trajs = [None if g is None else _as_trajectory(g, "ground truth") for g in gts]
    voc = None
    t0 = _time.perf_counter()
    if vocabulary is not None:
        voc = vocabulary if isinstance(vocabulary, Vocabulary) else load_vocabulary(vocabulary)
    if load_graph is not None and not (Path(load_graph) / "pose_graph.txt").is_file():
        raise DataError(f"{load_graph}: no saved pose graph here (pose_graph.txt missing)")
    times["vocabulary_load"] = _time.perf_counter() - t0

    # poses that miss the images entirely fail now, not after tracking (the readers list their
    # stamps without decoding an image)
    for b, (sq, tr) in enumerate(zip(seqs, trajs)):
        st = _listed_times(sq)
        if st is not None and st.size and not _covered(tr, st, max_pose_gap).any():
            raise DataError(f"{pose_names[b]}: the poses ({_span(tr.time.numpy())}) do not cover the images of "
                            f"input {b + 1} {names[b]} ({_span(st)}, {st.size} images); are they this "
                            f"sequence's poses, with times in the same clock?")

    # -- 1-2. tracking and keyframe choice
    B = len(seqs)
    logs = [_StreamLog(names[b], trajs[b], pose_names[b], max_pose_gap, keyframe_distance, keyframe_angle,
                       keyframe_every) for b in range(B)]
    stream = MultiStream(seqs, size=(cfg.image_height, cfg.image_width), max_steps=max_frames)
    tracker = FeatureTracker(cfg, num_streams=B, device=dev, mode=tracker_mode)
    bar = _bar(progress, sum(len(s) if max_frames is None else min(len(s), max_frames) for s in seqs),
               "tracking", "frame")
    t0 = _time.perf_counter()
    try:
        for batch in stream:
            fr = tracker.track(batch.images.to(dev), batch.timestamps, active=batch.alive.to(dev))
            alive = batch.alive.numpy().astype(bool)
            pub = fr.published.cpu().numpy().astype(bool) & alive
            valid = fr.valid.cpu().numpy()
            ids = fr.ids.cpu().numpy()
            xy = fr.xy.detach().cpu().double().numpy()
            uv = fr.uv.detach().cpu().double().numpy()
            ts = fr.timestamps.cpu().double().numpy()
            for b in range(B):  # streams, not points
                if not alive[b]:
                    continue
                logs[b].frames += 1
                if pub[b]:
                    m = valid[b] & (ids[b] >= 0)
                    logs[b].add(float(ts[b]), ids[b][m], xy[b][m], uv[b][m], batch.raw[b])
            if bar is not None:
                bar.update(int(alive.sum()))
    finally:
        if bar is not None:
            bar.close()
    times["tracking"] = _time.perf_counter() - t0
    for b, log in enumerate(logs):
        if not any(log.covered):
            tr = log.traj.time.numpy()
            raise DataError(f"{log.poses_name}: the poses ({_span(tr)}) do not cover the images of input {b + 1} "
                            f"{log.name} ({_span(log.times)}, {len(log.times)} published frames); are they this "
                            f"sequence's poses, with times in the same clock?")
        if not log.kf_frames:
            raise DataError(f"{log.name}: no keyframe (no published frame with tracked features inside the poses' "
                            f"time span {_span(log.traj.time.numpy())})")

    # -- 3. triangulation
    t0 = _time.perf_counter()
    tri = [_triangulate_stream(log, R_ic, t_ic, triangulation_chunk, track_window) for log in logs]
    times["triangulation"] = _time.perf_counter() - t0

    # -- 4. description
    t0 = _time.perf_counter()
    cam_d = cfg.camera.to(device=dev, dtype=_F64)
    descs = [_describe(log.kf_images, tri[b][0], cam_d, dev, describe_batch) for b, log in enumerate(logs)]
    times["description"] = _time.perf_counter() - t0

    # -- 5. vocabulary
    voc_info: Dict[str, Any]
    if voc is None:
        t0 = _time.perf_counter()
        gen = torch.Generator().manual_seed(seed)
        allb = [d["brief"] for ds in descs for d in ds]
        # a seeded random sample of each keyframe's corners: k-medians time grows with the number
        # of descriptors, and a few hundred per image describe its words well enough
        if vocabulary_sample is not None:
            allb = [x[torch.randperm(x.shape[0], generator=gen)[:vocabulary_sample].sort().values]
                    for x in allb]
        K = max(1, max(x.shape[0] for x in allb))
        D = torch.zeros(len(allb), K, 4, dtype=torch.int64)
        V = torch.zeros(len(allb), K, dtype=torch.bool)
        for i, x in enumerate(allb):  # documents, not descriptors
            D[i, : x.shape[0]] = x
            V[i, : x.shape[0]] = True
        if not bool(V.any()):
            raise DataError("cannot train a vocabulary: the keyframes have no FAST corners (blank images?)")
        voc = Vocabulary.train(D, V, k=vocabulary_k, L=vocabulary_L, generator=gen)
        times["vocabulary"] = _time.perf_counter() - t0
        voc_info = {"source": "trained on this run", "documents": len(allb), "descriptors": int(V.sum())}
    else:
        times["vocabulary"] = times["vocabulary_load"]
        voc_info = {"source": str(getattr(voc, "source", None) or vocabulary)}
    voc_info.update({"k": int(voc.k), "L": int(voc.L), "words": int(voc.num_words)})
    times.pop("vocabulary_load", None)

    # -- 6. pose graph(s)
    n_graphs = B if separate_graphs else 1
    cam_cpu = cfg.camera.to(dtype=_F64)
    graphs = [PoseGraph(cam_cpu, voc, mode=mode, R_ic=R_ic, t_ic=t_ic, pnp_backend=pnp_backend,
                        generator=torch.Generator().manual_seed(seed)) for _ in range(n_graphs)]
    loaded = 0
    if load_graph is not None:
        for g in graphs:
            loaded = g.load(load_graph)
    streams: List[StreamRun] = []
    owner: Dict[Tuple[int, int], int] = {}  # (graph, index) -> stream
    loops: List[LoopRecord] = []
    images: Optional[Dict[Tuple[int, int], np.ndarray]] = {} if keep_images else None
    total_kf = sum(len(log.kf_frames) for log in logs)
    bar = _bar(progress, total_kf, "loop closure", "kf")
    t0 = _time.perf_counter()
    n_acc = 0
    few_points = 0
    try:
        for b, log in enumerate(logs):
            g = b if separate_graphs else 0
            graph = graphs[g]
            seq_id = 1 if separate_graphs else b + 1
            pts, Tk, Rk = tri[b]
            idx = []
            for k, f in enumerate(log.kf_frames):  # keyframes: one pose-graph step each
                kf = _make_keyframe(log.times[f], seq_id, Tk[k], Rk[k], pts[k], descs[b][k])
                query = kf.num_points > MIN_POINTS_TO_QUERY
                few_points += int(not query)
                res = graph.add_keyframe(kf, detect_loop=query)
                owner[(g, kf.index)] = b
                idx.append(kf.index)
                if images is not None:
                    images[(g, kf.index)] = log.kf_images[k]
                if res is not None:
                    old = graph.keyframes[res.old_index]
                    loops.append(LoopRecord(g, b, owner.get((g, res.old_index), -1), kf.time, old.time, res))
                    n_acc += int(res.accepted)
                if bar is not None:
                    bar.set_postfix(loops=n_acc, refresh=False)
                    bar.update(1)
            streams.append(StreamRun(name=log.name, stream=b, graph=g, sequence=seq_id, frames=log.frames,
                                     published=len(log.times), uncovered=int(len(log.covered) - sum(log.covered)),
                                     keyframe_times=np.array([log.times[f] for f in log.kf_frames]),
                                     graph_indices=np.array(idx, dtype=np.int64),
                                     num_points=np.array([p[0].shape[0] for p in pts], dtype=np.int64)))
    finally:
        if bar is not None:
            bar.close()
    t_graph = _time.perf_counter() - t0
    t_opt = sum(g.optimize_seconds for g in graphs)
    times["recognition_verification"] = t_graph - t_opt
    times["optimisation"] = t_opt
    for log in logs:  # the images live on in the keyframes' owners only when asked for
        log.kf_images = []

    # -- trajectories and ATE
    from ..io.trajectory import Trajectory

    sq_b = sq_a = 0.0
    n_pairs = 0
    joint_b: List[Any] = []
    joint_a: List[Any] = []
    for s in streams:
        kfs = [graphs[s.graph].keyframes[i] for i in s.graph_indices.tolist()]
        tt = torch.tensor([k.time for k in kfs], dtype=_F64)
        s.vio = Trajectory(tt, torch.stack([k.origin_vio_T for k in kfs]), R_to_quat(torch.stack([k.origin_vio_R for k in kfs])))
        s.corrected = Trajectory(tt.clone(), torch.stack([k.T_w_i for k in kfs]), R_to_quat(torch.stack([k.R_w_i for k in kfs])))
        gt = gt_trajs[s.stream]
        if gt is not None:
            s.ground_truth = gt
            eb, n, sb, pb = _ate(s.vio, gt, max_pose_gap)
            ea, _, sa, pa = _ate(s.corrected, gt, max_pose_gap)
            joint_b.append(pb)
            joint_a.append(pa)
            if eb is None:
                raise DataError(f"{gts[s.stream]}: the ground truth ({_span(gt.time.numpy())}) covers fewer than 3 "
                                f"keyframes of {s.name} ({_span(s.keyframe_times)})")
            s.ate_before, s.ate_after = eb, ea
            sq_b, sq_a, n_pairs = sq_b + sb, sq_a + sa, n_pairs + n

    # -- summary
    reasons: Dict[str, int] = {}
    for r in loops:
        if not r.result.accepted:
            reasons[r.result.reason] = reasons.get(r.result.reason, 0) + 1
    total = _time.perf_counter() - t_start
    times = {k: round(v, 6) for k, v in times.items()}
    summary: Dict[str, Any] = {
        "keyframes": total_kf,
        "keyframes_loaded": loaded * n_graphs,
        "keyframes_not_querying": few_points,
        "loop_candidates": len(loops),
        "loops_accepted": n_acc,
        "loops_rejected": len(loops) - n_acc,
        "rejected_by_reason": dict(sorted(reasons.items())),
    }
    if n_pairs:
        summary["ate_before"] = math.sqrt(sq_b / n_pairs)
        summary["ate_after"] = math.sqrt(sq_a / n_pairs)
        if not separate_graphs and B > 1 and len(joint_b) == B:
            # one alignment for all streams: "after" measures the merged map; "before" only means
            # something when the inputs' VIO poses share one world (e.g. one recording split in two)
            summary["ate_joint_before"] = _joint_ate(joint_b)
            summary["ate_joint_after"] = _joint_ate(joint_a)
    summary.update({
        "optimisations": sum(g.num_optimizations for g in graphs),
        "skipped_bad_frames": len(stream.skipped),
        "seconds": round(total, 6),
        "times": times,
        "keyframes_per_second": total_kf / t_graph if t_graph > 0 else 0.0,
        "streams": B,
        "graphs": n_graphs,
        "shared_map": not separate_graphs,
        "mode": mode,
        "tracker_mode": tracker_mode,
        "device": str(dev),
        "config": str(cfg.path),
        "extrinsic": {"R_ic": R_ic.tolist(), "t_ic": t_ic.tolist()},
        "keyframe_rule": ({"every": keyframe_every} if keyframe_every is not None else
                          {"distance_m": keyframe_distance, "angle_deg": keyframe_angle}),
        "vocabulary": voc_info,
        "load_graph": None if load_graph is None else str(load_graph),
        "per_stream": [{
            "name": s.name, "graph": s.graph, "sequence": s.sequence, "frames": s.frames, "published": s.published,
            "published_without_pose": s.uncovered, "keyframes": int(s.graph_indices.size),
            "mean_points": float(s.num_points.mean()) if s.num_points.size else 0.0,
            "loops_accepted": sum(1 for r in loops if r.stream == s.stream and r.result.accepted),
            "ate_before": s.ate_before, "ate_after": s.ate_after,
            "poses": pose_names[s.stream],
            "ground_truth": None if gts[s.stream] is None or isinstance(gts[s.stream], tuple) else str(gts[s.stream]),
        } for s in streams],
    })
    if extra_summary:
        summary.update(extra_summary)
    run = LoopRun(graphs, streams, loops, summary, images, None if out is None else Path(out))
    if write and out is not None:
        from .report import write_loop_outputs

        summary["out"] = str(Path(out))
        write_loop_outputs(out, run)
    return run


def _bar(progress: Optional[bool], total: int, desc: str, unit: str):
    if progress is False:
        return None
    import shutil
    import sys

    from tqdm import tqdm

    size = shutil.get_terminal_size((100, 20))  # a pty reporting 0 x 0 would hide the bar
    return tqdm(total=total, unit=unit, desc=desc, disable=None if progress is None else False, file=sys.stderr,
                ncols=min(120, size.columns), nrows=size.lines, leave=False)


def format_loop_summary(s: Dict[str, Any]) -> str:
    """The few lines ``loop`` / ``demo --loop`` print."""
    rej = ", ".join(f"{k} {v}" for k, v in s.get("rejected_by_reason", {}).items()) or "none"
    lines = [
        f"streams       {s['streams']}   graphs {s['graphs']} ({'shared map' if s['shared_map'] else 'separate'})"
        f"   mode {s['mode']}",
        f"keyframes     {s['keyframes']}   ({s['keyframes_not_querying']} with <= {MIN_POINTS_TO_QUERY} points "
        f"did not query)",
        f"loops         {s['loops_accepted']} accepted, {s['loops_rejected']} rejected ({rej})",
    ]
    if s.get("ate_before") is not None:
        lines.append(f"ATE           {s['ate_before']:.3f} m -> {s['ate_after']:.3f} m (SE(3)-aligned, keyframes"
                     f"{', per stream' if s['streams'] > 1 else ''})")
    if s.get("ate_joint_before") is not None:
        lines.append(f"ATE map       {s['ate_joint_before']:.3f} m -> {s['ate_joint_after']:.3f} m (one alignment "
                     f"for all streams)")
    t = s.get("times", {})
    lines.append("times         " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()))
    if "out" in s:
        lines.append(f"outputs       {s['out']}/ (vins_result_loop.csv, trajectory_loop.tum, trajectory_vio.tum, "
                     f"loops.csv, pose_graph/, summary.json, trajectory_top.png, place_recognition_scores.png)")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# the demo


#: the demo's render (``render_loop_sequence`` arguments): two laps of 64 keyframes, one frame
#: between keyframes for the tracker, and a VIO drift of 0.15 deg of yaw per keyframe plus 3 % of
#: the distance flown (about 20 deg and 0.5 m after two laps)
DEMO_RENDER = dict(laps=2, keyframes_per_lap=64, frames_per_keyframe=2, width=320, height=240,
                   yaw_bias_deg=0.15, trans_drift=0.03)


def demo_sequence(seed: int = 0, **render_kwargs):
    """The demo's ``SyntheticSequence`` (``DEMO_RENDER`` updated by ``render_kwargs``)."""
    from .synthetic import render_loop_sequence

    kw = dict(DEMO_RENDER)
    kw.update(render_kwargs)
    return render_loop_sequence(seed=seed, **kw)


def demo_config(seq):
    """A ``TrackerConfig`` for a ``SyntheticSequence``: its camera and size, 100 features 20 px
    apart, every frame published (``freq`` 100 Hz above the render's rate), no CLAHE."""
    from ..config import TrackerConfig

    H, W = int(seq.images.shape[-2]), int(seq.images.shape[-1])
    return TrackerConfig(path="demo (synthetic revisit sequence)", image_width=W, image_height=H,
                         camera=seq.camera, max_cnt=100, min_dist=20, freq=100, F_threshold=1.0, equalize=False)


def demo_loop(out: Optional[PathLike] = "out/demo_loop", *, two_sequences: bool = False,
              separate_graphs: bool = False, device: str = "cpu", progress: Optional[bool] = None,
              keep_images: bool = False, write: bool = True, seed: int = 0, sequence=None,
              run_kwargs: Optional[Dict[str, Any]] = None, **render_kwargs) -> LoopRun:
    """``torch-frontend demo --loop``: render the synthetic revisit sequence (``demo_sequence``:
    a room textured with the package's photo, two laps, exact poses, drifted VIO), run
    :func:`run_loop` on it with its drifted VIO poses as the input poses and its true poses as
    the ground truth, a vocabulary trained on the run, and write the outputs into ``out``.

    Args:
        two_sequences: the two laps become two input streams (sequences 1 and 2) that share one
            map (merged by their first loop) or, with ``separate_graphs``, keep one graph each.
        sequence: an already rendered ``SyntheticSequence`` (else ``demo_sequence``).
        run_kwargs: more :func:`run_loop` arguments.
        render_kwargs: override ``DEMO_RENDER`` (e.g. smaller ``width``/``height``).
    """
    from ..io.trajectory import Trajectory
    from .geometry import R_to_quat

    t0 = _time.perf_counter()
    seq = demo_sequence(seed, **render_kwargs) if sequence is None else sequence
    t_render = _time.perf_counter() - t0
    cfg = demo_config(seq)
    W, H = cfg.image_width, cfg.image_height
    times = np.asarray(seq.times.cpu(), dtype=np.float64)
    imgs = np.asarray(seq.images.cpu())

    def traj(T, R, sl):
        return Trajectory(torch.as_tensor(times[sl], dtype=_F64), torch.as_tensor(T, dtype=_F64).cpu()[sl],
                          R_to_quat(torch.as_tensor(R, dtype=_F64).cpu()[sl]))

    if two_sequences:
        n = len(times) // 2
        parts = [slice(0, n), slice(n, None)]
    else:
        parts = [slice(0, None)]
    sources = [ArraySequence(imgs[sl], times[sl], name=f"demo{'' if len(parts) == 1 else f'_lap{i + 1}'}")
               for i, sl in enumerate(parts)]
    poses = [traj(seq.T_vio, seq.R_vio, sl) for sl in parts]
    gts = [traj(seq.T_gt, seq.R_gt, sl) for sl in parts]
    extra = {"demo": {"render_seconds": round(t_render, 6), "frames": int(len(times)), "size": [W, H],
                      "two_sequences": bool(two_sequences)}}
    kw: Dict[str, Any] = dict(keyframe_distance=0.1, keyframe_angle=5.0, vocabulary_sample=150)
    # the render moves ~0.13 m and turns ~5.6 deg per rendered keyframe: about one keyframe per
    # rendered keyframe, 64 per lap, so that lap 2 lies more than VINS's 50 keyframes after lap 1
    kw.update(run_kwargs or {})
    return run_loop(cfg, sources, poses, out, train_vocabulary=True, ground_truth=gts, separate_graphs=separate_graphs,
                    device=device, R_ic=seq.R_ic.cpu(), t_ic=seq.t_ic.cpu(), progress=progress,
                    keep_images=keep_images, write=write, seed=seed, extra_summary=extra, **kw)
