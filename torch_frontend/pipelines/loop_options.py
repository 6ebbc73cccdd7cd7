"""The options and results of loop closure (``pipelines.loop.run_loop``): :class:`LoopOptions`
and their checks, :class:`LoopRun` and its parts, and each stream's camera-to-body extrinsic
(:func:`extrinsic_from_config`, :func:`stream_extrinsics`).

Convention: see ``pipelines.loop`` (poses body-to-world, the extrinsic camera-to-body, VINS's
``qic``/``tic``; distances in metres, angles in degrees, times in seconds).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ..errors import ConfigError, ConfigWarning
from ..loop.world import UP_AXES
from .common import InputOptions, OptionError
from .track import TRACKER_MODES

__all__ = ["LoopOptions", "LoopRecord", "LoopRun", "MIN_POINTS_TO_QUERY", "PNP_BACKENDS", "POSE_GRAPH_MODES",
           "StreamRun", "extrinsic_from_config", "stream_extrinsics"]

PathLike = Union[str, Path]
_F64 = torch.float64
MIN_POINTS_TO_QUERY = 25  # VINS accepts a loop only with > 25 matches: fewer points can never pass
POSE_GRAPH_MODES = ("4dof", "6dof")
PNP_BACKENDS = ("torch", "opencv")


@dataclass
class LoopOptions(InputOptions):
    """Options of :func:`run_loop` (and the reader options of :class:`InputOptions`). Distances in
    metres, angles in degrees, times in seconds.

    Attributes:
        vocabulary: a ``Vocabulary`` or a vocabulary file (``vocabulary.load_vocabulary``).
        train_vocabulary: train one on this run's keyframe descriptors instead; exactly one of
            ``vocabulary`` / ``train_vocabulary``.
        vocabulary_k, vocabulary_L: branching factor and depth of a trained vocabulary.
        vocabulary_sample: a seeded random sample of at most this many descriptors per keyframe
            goes into training (k-medians time grows with their number; None: all).
        load_graph: a saved pose graph folder (VINS format) loaded into every graph first.
        separate_graphs: one pose graph per stream instead of one shared map.
        mode: pose graph: ``"4dof"`` (VIO with IMU: x, y, z, yaw about ``up``) or ``"6dof"``
            (without an IMU, e.g. KITTI).
        up: the poses' world axis pointing up (``loop.world.UP_AXES``; KITTI's camera-0 world:
            ``"-y"``): the poses are rotated into a z-up world for the pose graph and back for
            every output (``pose_graph/`` stays in the z-up world), the plots are drawn in the plane
            perpendicular to it, and poses whose motion is far from horizontal in it get a
            ``WorldFrameWarning`` naming the likely up axis.
        tracker_mode: front end rules, ``"mono"`` (VINS-Mono) or ``"fusion"`` (VINS-Fusion).
        keyframe_distance: new keyframe when the body moved more than this (m) ...
        keyframe_angle: ... or turned more than this (degrees) since the last keyframe.
        keyframe_every: instead, every k-th published frame with a pose (None: the rule above).
        max_pose_gap: largest gap between two poses to interpolate across (s).
        R_ic, t_ic: camera-to-body extrinsic ``(3, 3)`` / ``(3,)`` (m) overriding the config's.
        pnp_backend: loop verification PnP-RANSAC, ``"torch"`` or ``"opencv"``.
        triangulation_chunk: keyframes per batched triangulation call.
        track_window: published frames either side of a chunk whose observations triangulate it.
        describe_batch: keyframes per batched description call.
        seed: seed of vocabulary sampling/training and of the pose graph's RANSAC.
        keep_images: keep the keyframe images in ``LoopRun.images`` (for plots of matches).
        checkpoint_every: with ``out``, write a checkpoint (``pipelines.loop_checkpoint``, inside
            the run's staging folder) every this many frames while tracking and every this many
            keyframes while building the pose graph; None: every 500 or 60 s, whichever first;
            0: none.
        resume: continue the interrupted run of the same ``out`` from its last checkpoint
            (``checkpoint.ResumeError`` when it was another run: inputs, poses, config, options);
            no checkpoint to continue from: start from the first frame (a ``DataWarning`` says so).
    """

    vocabulary: Any = None
    train_vocabulary: bool = False
    vocabulary_k: int = 10
    vocabulary_L: int = 4
    vocabulary_sample: Optional[int] = 200
    load_graph: Optional[PathLike] = None
    separate_graphs: bool = False
    mode: str = "4dof"
    up: str = "+z"
    tracker_mode: str = "mono"
    keyframe_distance: float = 0.2
    keyframe_angle: float = 10.0
    keyframe_every: Optional[int] = None
    max_pose_gap: float = 0.5
    R_ic: Any = None
    t_ic: Any = None
    pnp_backend: str = "torch"
    triangulation_chunk: int = 32
    track_window: int = 40
    describe_batch: int = 8
    seed: int = 0
    keep_images: bool = False
    checkpoint_every: Optional[int] = None
    resume: bool = False

    def check(self) -> None:
        """Raise ``OptionError`` naming the first bad option."""
        super().check()
        if self.vocabulary is None and not self.train_vocabulary:
            raise OptionError("vocabulary", "vocabulary: none given: give a vocabulary (a Vocabulary or a file) "
                                            "or set train_vocabulary")
        if self.vocabulary is not None and self.train_vocabulary:
            raise OptionError("vocabulary", "vocabulary: give either a vocabulary or train_vocabulary, not both")
        choices = (("mode", POSE_GRAPH_MODES), ("tracker_mode", TRACKER_MODES), ("pnp_backend", PNP_BACKENDS),
                   ("up", UP_AXES))
        for name, allowed in choices:
            if getattr(self, name) not in allowed:
                raise OptionError(name, f"{name}: expected {' or '.join(map(repr, allowed))}, "
                                        f"got {getattr(self, name)!r}")
        for name in ("keyframe_every", "vocabulary_sample", "triangulation_chunk", "describe_batch"):
            v = getattr(self, name)
            if v is not None and v < 1:
                raise OptionError(name, f"{name}: expected >= 1, got {v}")
        for name in ("keyframe_distance", "keyframe_angle", "track_window"):
            if not getattr(self, name) >= 0:
                raise OptionError(name, f"{name}: expected >= 0, got {getattr(self, name)}")
        if not math.isfinite(self.keyframe_angle):  # its cosine is taken (inf: a math domain error)
            raise OptionError("keyframe_angle", f"keyframe_angle: expected a finite number of degrees, "
                                                f"got {self.keyframe_angle}")
        if not self.max_pose_gap > 0:
            raise OptionError("max_pose_gap", f"max_pose_gap: expected > 0, got {self.max_pose_gap}")
        if self.checkpoint_every is not None and (isinstance(self.checkpoint_every, bool)
                                                  or not isinstance(self.checkpoint_every, int)
                                                  or self.checkpoint_every < 0):
            raise OptionError("checkpoint_every", f"checkpoint_every: expected an integer >= 0 (frames; 0: no "
                                                  f"checkpoints), got {self.checkpoint_every!r}")


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

    ``vio``/``corrected``: ``trajectory.Trajectory`` of its keyframes (input VIO poses /
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


def extrinsic_from_config(cfg, warn: bool = True) -> Tuple[torch.Tensor, torch.Tensor]:
    """Camera-to-body ``(R_ic (3, 3), t_ic (3,))`` float64 of a ``TrackerConfig``: its
    ``extrinsicRotation``/``extrinsicTranslation`` (VINS-Mono), ``body_T_cam0`` (VINS-Fusion, a
    KITTI input's) or its ``sensor.yaml``'s ``T_BS``; identity / zero when the config gives none,
    with a ``ConfigWarning`` saying so (``warn``)."""
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
        from ..opencv_yaml import read_opencv_yaml

        tbs = read_opencv_yaml(Path(path)).get("T_BS")
        if isinstance(tbs, dict) and len(tbs.get("data", [])) == 16:
            T = np.asarray(tbs["data"], dtype=np.float64).reshape(4, 4)
    if T is not None:
        T = np.asarray(T, dtype=np.float64)
        return torch.from_numpy(T[:3, :3].copy()), torch.from_numpy(T[:3, 3].copy())
    if warn:
        warnings.warn(f"{path or 'the config'} gives no camera-to-body extrinsic (extrinsicRotation/"
                      f"extrinsicTranslation, body_T_cam0 or a sensor.yaml's T_BS): identity is used, i.e. the "
                      f"poses are taken as the camera's", ConfigWarning, stacklevel=2)
    return torch.eye(3, dtype=_F64), torch.zeros(3, dtype=_F64)


def stream_extrinsics(cfgs: Sequence[Any], opt: LoopOptions) -> Tuple[List[torch.Tensor], List[torch.Tensor]]:
    """Every stream's camera-to-body ``(R_ic (3, 3), t_ic (3,))`` float64: its config's
    (:func:`extrinsic_from_config`, read once per config) or ``opt.R_ic`` / ``opt.t_ic`` for all.

    Raises:
        OptionError: a shared map (``separate_graphs`` False) of streams whose configs give
            different extrinsics: VINS's pose graph has one ``qic``/``tic`` (loop verification
            maps both keyframes' cameras to their bodies with it), so such streams need one graph
            each.
    """
    per: Dict[int, Tuple[torch.Tensor, torch.Tensor]] = {}
    R_ics, t_ics = [], []
    for c in cfgs:
        if id(c) not in per:
            R, t = extrinsic_from_config(c, warn=opt.R_ic is None or opt.t_ic is None)
            R = R if opt.R_ic is None else torch.as_tensor(opt.R_ic, dtype=_F64).reshape(3, 3)
            t = t if opt.t_ic is None else torch.as_tensor(opt.t_ic, dtype=_F64).reshape(3)
            per[id(c)] = (R, t)
        R_ics.append(per[id(c)][0])
        t_ics.append(per[id(c)][1])
    if not opt.separate_graphs:
        for b in range(1, len(cfgs)):
            if not (torch.equal(R_ics[b], R_ics[0]) and torch.equal(t_ics[b], t_ics[0])):
                raise OptionError("separate_graphs", f"separate_graphs: needed for these inputs (one pose graph per "
                                  f"input): {cfgs[0].path} (input 1) and {cfgs[b].path} (input {b + 1}) give "
                                  f"different camera-to-body extrinsics, but a shared map has one (VINS's pose "
                                  f"graph: one qic/tic); or give configs with one extrinsic")
    return R_ics, t_ics
