"""Loop closure on images + a VIO trajectory, without ROS (``torch-frontend loop``, ``demo --loop``):
:func:`run_loop`. Its options and results are in ``loop_options`` (:class:`LoopOptions`,
:class:`LoopRun`, the extrinsics), its middle stages in ``loop_stages``, its checkpoints in
``loop_checkpoint``, the demo on a rendered revisiting sequence in ``loop_demo``
(:func:`demo_loop`); the names of all of them are importable from here.

Pipeline (one call, B input streams):

1. **Tracking**: the VINS front end (``FeatureTracker``, B streams in one batch) on the images.
2. **Keyframes**: VINS takes keyframes from its estimator; here they are picked from the front
   end's published frames whose time the given poses cover (``loop_stages.KeyframeLog``). A
   keyframe's pose is the given body pose, interpolated (linear / slerp) at the image time.
3. **Triangulation**: each keyframe's points are the tracks (feature ids) it sees, triangulated
   from their observations on published frames with the given poses (camera pose = body pose ∘
   camera-to-body extrinsic), in batched ``triangulate_points`` calls (chunks of keyframes); only
   points that triangulate and lie in front of the keyframe camera are kept.
4. **Description**: FAST + BRIEF of the keyframes (``describe_keyframes``, batched).
5. **Vocabulary**: loaded (``LoopOptions.vocabulary``: a ``Vocabulary``, the package's ``.npz``,
   VINS's ``brief_k10L6.bin`` or a DBoW2 YAML) or trained on this run's keyframe descriptors
   (``LoopOptions.train_vocabulary``).
6. **Pose graph**: ``PoseGraph.add_keyframe`` per keyframe in time order (place recognition,
   verification, 4-DoF or 6-DoF optimisation). Several streams share one graph (VINS's
   multi-sequence map: stream b is sequence b + 1, added one after the other, merged into the
   first one's world by their first loop) or keep one graph each (``separate_graphs``).

Convention:
    * Poses are body-to-world ``(R_w_i, T_w_i)`` float64 (VINS), quaternions ``(w, x, y, z)``; the
      extrinsic ``(R_ic, t_ic)`` is camera-to-body (VINS's ``qic``, ``tic``): from the config's
      ``extrinsicRotation``/``extrinsicTranslation`` (VINS-Mono), ``body_T_cam0`` (VINS-Fusion) or
      an EuRoC ``sensor.yaml``'s ``T_BS``; identity when none is given (a ``ConfigWarning`` says so).
    * World frame: the poses' world has ``LoopOptions.up`` pointing up (default ``+z``, VINS's);
      another up axis (KITTI's camera-0 world: ``-y``) is rotated into a z-up world for the pose
      graph and back for the trajectories and ATE (``loop.world``); poses whose motion is far from
      horizontal in it get a ``WorldFrameWarning`` naming the likely up axis.
    * Pose coverage: a frame is covered when its time lies between two poses at most
      ``max_pose_gap`` seconds apart (or on a pose). Uncovered frames are tracked but never
      keyframes (as VINS, whose estimator publishes nothing before it initialises); a stream with
      no covered frame at all is a ``DataError`` naming the poses and both time spans.
    * Keyframes with ``MIN_POINTS_TO_QUERY`` points or fewer (VINS needs more matches) join the
      place database without querying it.
    * ATE (``ate_before`` = input VIO, ``ate_after`` = loop-corrected, metres): RMSE of keyframe
      positions after an SE(3) alignment to the ground truth interpolated at the keyframe times
      (``trajectory.ate_rmse``); with several streams the top-level values pool every keyframe's
      squared error (each stream aligned on its own); a shared map of several streams also gets
      ``ate_joint_before``/``ate_joint_after``: one alignment for all streams.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ..errors import DataError
from ..loop.world import into_z_up, warn_if_not_horizontal
from .common import OptionError, pad_ragged, progress_bar, resolve_device
from .inputs import (
    ArraySequence,  # noqa: F401  (re-exported: the demo's and users' frames in memory)
    Source,
    config_label,
    frames_to_read,
    open_inputs,
    resolve_configs,
    stream_config_entry,
    stream_names,
    stream_sizes,
)
from .loop_options import (
    MIN_POINTS_TO_QUERY,
    PNP_BACKENDS,
    POSE_GRAPH_MODES,
    LoopOptions,
    LoopRecord,
    LoopRun,
    StreamRun,
    extrinsic_from_config,
    stream_extrinsics,
)
from .loop_stages import (
    KeyframeLog,
    as_trajectory,
    covered_mask,
    describe_keyframe_images,
    joint_ate,
    keyframe_ate,
    listed_times,
    make_keyframe,
    span,
    triangulate_keyframes,
)
from .track import make_tracker, tracked_batches

__all__ = [
    "LoopOptions",
    "LoopRecord",
    "LoopRun",
    "MIN_POINTS_TO_QUERY",
    "PNP_BACKENDS",
    "POSE_GRAPH_MODES",
    "StreamRun",
    "extrinsic_from_config",
    "run_loop",
    "stream_extrinsics",
]

PathLike = Union[str, Path]
_F64 = torch.float64
#: the demo's names, importable from here too (``loop_demo`` imports :func:`run_loop` from this
#: module, so they are looked up on first use rather than imported at the top)
_DEMO_NAMES = ("DEMO_OPTIONS", "DEMO_RENDER", "demo_announcement", "demo_config", "demo_loop", "demo_options",
               "demo_sequence")


def __getattr__(name: str):
    if name in _DEMO_NAMES:
        import importlib

        value = getattr(importlib.import_module(".loop_demo", __package__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ += list(_DEMO_NAMES)


# ----------------------------------------------------------------------------------------------
# the run


@dataclass
class _Inputs:
    """What :func:`run_loop` opened and checked before the long part (one entry per stream: its
    config, camera-to-body extrinsic, sequence, ...)."""

    cfgs: List[Any]
    device: torch.device
    R_ics: List[torch.Tensor]
    t_ics: List[torch.Tensor]
    seqs: List[Any]
    names: List[str]
    trajs: List[Any]
    pose_names: List[str]
    gts: List[Any]  # as given (files, trajectories or None)
    gt_trajs: List[Any]
    vocabulary: Any  # loaded, or None: trained on the run


@dataclass
class _Graphs:
    """The pose-graph stage's results and counts."""

    graphs: List[Any]
    streams: List[StreamRun]
    loops: List[LoopRecord]
    images: Optional[Dict[Tuple[int, int], np.ndarray]]
    keyframes: int
    loaded: int
    not_querying: int
    accepted: int
    seconds: float


def run_loop(config, sources: Sequence[Source], poses: Sequence[Any], out: Optional[PathLike] = None,
             options: Optional[LoopOptions] = None, *, ground_truth: Optional[Sequence[Any]] = None,
             extra_summary: Optional[Dict[str, Any]] = None) -> LoopRun:
    """Loop-closure run on B image streams with their VIO poses (see the module docstring).

    Args:
        config: a ``TrackerConfig`` or a VINS config path for every source, None (each ``euroc``
            source's own ``sensor.yaml``), or a list of one of these per source
            (``inputs.resolve_configs``): each stream is tracked, triangulated (its extrinsic) and
            described (its camera) with its own config; a shared map needs one extrinsic
            (:func:`stream_extrinsics`).
        sources: one per stream, ``(kind, path)`` with kind ``euroc``/``images``/``bag`` or an
            ``io`` sequence (e.g. ``ArraySequence``).
        poses: one per stream, a trajectory file (TUM, VINS csv, EuRoC ground truth; read by
            ``trajectory.read_trajectory``) or a ``Trajectory`` (body-to-world, seconds, wxyz).
        out: output folder (``loop.report.write_loop_outputs``); None: write nothing.
        options: :class:`LoopOptions` (the defaults need a vocabulary: set ``vocabulary`` or
            ``train_vocabulary``).
        ground_truth: None or one entry (file, ``Trajectory`` or None) per stream: ATE before/after.
        extra_summary: entries added to the summary (the demo's render).

    Returns:
        the :class:`LoopRun` (its ``summary`` is also ``summary.json``).

    Raises:
        OptionError: bad options or argument counts; DataError: unreadable inputs, poses that
            cover none of a stream's images, a bad vocabulary file, ground truth that does not
            overlap, ...; ConfigError: a bad config.
    """
    t_start = _time.perf_counter()
    opt = LoopOptions() if options is None else options
    sources, poses = list(sources), list(poses)
    gts = [None] * len(sources) if ground_truth is None else list(ground_truth)
    _check_arguments(sources, poses, gts, opt)
    if out is not None:  # an --out holding foreign files is refused before the run, not after it
        from ..loop.report import check_out_folder

        check_out_folder(out)
    times: Dict[str, float] = {}
    inp = _open_inputs(config, sources, poses, gts, opt, times)
    if out is None:
        prep = _prepare_streams(inp, opt, times)
        return _finish(inp, prep, opt, times, t_start, out, extra_summary)
    from .loop_checkpoint import LoopCheckpoints, loop_fingerprint

    fp = loop_fingerprint(inp.cfgs, sources, inp.seqs, poses, gts, opt, inp.device)
    with LoopCheckpoints(out, fp, opt.checkpoint_every, opt.resume) as ck:
        prep = _prepare_streams(inp, opt, times, ck=ck)
        return _finish(inp, prep, opt, times, t_start - ck.before, out, extra_summary, ck=ck)


@dataclass
class _Prepared:
    """Stages 1-4 of every stream (what the vocabulary and pose-graph stages take): the keyframe
    logs, skipped bad frames, triangulated points and keyframe descriptors, and the input
    pipeline's times."""

    logs: List[KeyframeLog]
    skipped: int
    tri: List[Any]
    descs: List[Any]
    input_times: Dict[str, Any]
    skipped_per_stream: List[int] = field(default_factory=list)


def _prepare_streams(inp: _Inputs, opt: LoopOptions, times: Dict[str, float], beat=None, ck=None) -> _Prepared:
    """Stages 1-4: tracking (B streams in one batch), keyframes, triangulation, description. Each
    stream's results are its own (the stages treat streams independently). ``beat``: called per
    tracker step (a sharded run's heartbeat). ``ck``: the run's ``LoopCheckpoints`` (or None):
    tracking checkpoints, and a resume past tracking takes stages 1-4 from its checkpoint."""
    if ck is not None and ck.past_tracking:
        return _prepared_from_checkpoint(inp, opt, times, ck)
    logs, skipped, input_times, per_stream = _track(inp, opt, times, beat, ck)
    t0 = _time.perf_counter()
    tri = [triangulate_keyframes(log, inp.R_ics[b], inp.t_ics[b], opt.triangulation_chunk, opt.track_window)
           for b, log in enumerate(logs)]
    times["triangulation"] = _time.perf_counter() - t0
    t0 = _time.perf_counter()
    cams: Dict[int, Any] = {}  # each stream's camera (one copy per distinct camera)
    descs = []
    for b, log in enumerate(logs):
        cam = inp.cfgs[b].camera
        if id(cam) not in cams:
            cams[id(cam)] = cam.to(device=inp.device, dtype=_F64)
        descs.append(describe_keyframe_images(log.kf_images, tri[b][0], cams[id(cam)], inp.device,
                                              opt.describe_batch))
    times["description"] = _time.perf_counter() - t0
    return _Prepared(logs, skipped, tri, descs, input_times, per_stream)


def _prepared_from_checkpoint(inp: _Inputs, opt: LoopOptions, times: Dict[str, float], ck) -> _Prepared:
    """Stages 1-4 of a run resumed past them: the logs from every chunk, the points and
    descriptors from the prepared chunk, the times and counts from its state."""
    logs = _new_logs(inp, opt)
    for b, log in enumerate(logs):
        log.load_state_dict([c["logs"][b] for c in ck.chunks("tracking") + ck.chunks("prepared")])
    chunk = ck.chunks("prepared")[0]
    p = ck.prepared
    times.clear()
    times.update(p["times"])
    return _Prepared(logs, int(p["skipped"]), chunk["tri"], chunk["descs"], dict(p["input_times"]),
                     list(p["skipped_per_stream"]))


def _new_logs(inp: _Inputs, opt: LoopOptions) -> List[KeyframeLog]:
    return [KeyframeLog(inp.names[b], inp.trajs[b], inp.pose_names[b], opt.max_pose_gap, opt.keyframe_distance,
                        opt.keyframe_angle, opt.keyframe_every) for b in range(len(inp.seqs))]


def _finish(inp: _Inputs, prep: _Prepared, opt: LoopOptions, times: Dict[str, float], t_start: float,
            out: Optional[PathLike], extra_summary: Optional[Dict[str, Any]] = None,
            vocabulary: Optional[Tuple[Any, Dict[str, Any], float]] = None, ck=None) -> LoopRun:
    """Stages 5-6 and the outputs: vocabulary (``vocabulary``: an already trained one, its
    summary entry and training seconds), pose graphs, trajectories and ATE, the summary, ``out``
    (None: nothing). ``ck``: the run's ``LoopCheckpoints`` (or None): the prepared checkpoint
    after the vocabulary, the pose-graph stage's checkpoints, a resume of either; ``out`` is
    written into its staging folder."""
    logs, tri, descs = prep.logs, prep.tri, prep.descs
    if ck is not None and ck.past_tracking:
        voc, voc_info = _resumed_vocabulary(inp, ck)
    elif vocabulary is None:
        voc, voc_info = _vocabulary(inp.vocabulary, descs, opt, times)
    else:
        voc, voc_info = vocabulary[0], dict(vocabulary[1])
        times.pop("vocabulary_load", None)
        times["vocabulary"] = vocabulary[2]
    if ck is None:
        gr = _pose_graphs(inp, logs, tri, descs, voc, opt)
    else:
        gr = _checkpointed_graphs(inp, prep, voc, voc_info, opt, times, ck)
    t_opt = sum(g.optimize_seconds for g in gr.graphs)
    times["recognition_verification"] = gr.seconds - t_opt
    times["optimisation"] = t_opt
    for log in logs:  # the images live on in the keyframes' owners only when asked for
        log.kf_images = []
    ate = _trajectories_and_ate(inp, gr, opt)
    summary = _summary(inp, opt, gr, ate, voc_info, times, prep.skipped, _time.perf_counter() - t_start)
    summary.update(prep.input_times)
    if extra_summary:
        summary.update(extra_summary)
    run = LoopRun(gr.graphs, gr.streams, gr.loops, summary, gr.images, None if out is None else Path(out))
    if out is not None:
        from ..loop.report import write_loop_outputs

        summary["out"] = str(Path(out))
        write_loop_outputs(out, run, stage=None if ck is None else ck.stage)
    return run


def save_prepared(ck, prep: _Prepared, times: Dict[str, float], extra: Dict[str, Any], vocabulary=None) -> None:
    """The prepared checkpoint (``pipelines.loop_checkpoint``): stages 1-4 (and ``vocabulary``, a
    trained one's ``state_dict``) done; ``extra``: entries kept with the times and counts."""
    steps = int(ck.writer.frames)
    ck.prepared = {"times": dict(times), "skipped": prep.skipped, "input_times": dict(prep.input_times),
                   "skipped_per_stream": list(prep.skipped_per_stream), "steps": steps, **extra}
    if ck.writer.enabled:
        marks = ck.log_marks or [None] * len(prep.logs)
        ck.save(steps, "prepared", {}, {"logs": [log.state_dict(since=m) for log, m in zip(prep.logs, marks)],
                                        "tri": prep.tri, "descs": prep.descs, "vocabulary": vocabulary})


def _resumed_vocabulary(inp: _Inputs, ck):
    """The vocabulary of a run resumed past stage 5: the trained one from the prepared chunk, or
    the given one (loaded again: the fingerprint holds its file's contents)."""
    from ..loop.vocabulary import Vocabulary

    chunk = ck.chunks("prepared")[0]
    info = dict(ck.prepared["vocabulary_info"])
    if chunk["vocabulary"] is not None:
        return Vocabulary.from_state_dict(chunk["vocabulary"]), info
    return inp.vocabulary, info


def _checkpointed_graphs(inp: _Inputs, prep: _Prepared, voc, voc_info, opt: LoopOptions, times: Dict[str, float],
                         ck) -> _Graphs:
    """Stage 6 with checkpoints (``pipelines.loop_checkpoint``): first the prepared checkpoint (a
    fresh run, or one resumed while tracking), then one per ``checkpoint_every`` keyframes; a run
    resumed in this stage restores it from its checkpoint."""
    if not ck.past_tracking:
        save_prepared(ck, prep, times, {"vocabulary_info": dict(voc_info)},
                      voc.state_dict() if inp.vocabulary is None else None)
    steps = int(ck.prepared["steps"])
    stage = _GraphStage(inp, prep.logs, prep.tri, prep.descs, voc, opt, load_graph=ck.phase != "graphs")
    if ck.phase == "graphs":
        chunks = ck.chunks("graphs")
        stage.restore_parts(ck.payload["graph"], [c["keyframes"] for c in chunks])

    def after_step():
        ck.kill_point("keyframe", stage.done)
        if ck.due(steps + stage.done):
            payload, static = stage.checkpoint_parts()
            ck.save(steps + stage.done, "graphs", {"graph": payload}, {"keyframes": static})

    with progress_bar(opt.progress, stage.gr.keyframes, "loop closure", "kf") as bar:
        return stage.run(bar, after_step)


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'s' if n != 1 else ''}"


def _check_arguments(sources: List[Any], poses: List[Any], gts: List[Any], opt: LoopOptions) -> None:
    if not sources:
        raise OptionError("sources", "sources: no input given (expected at least one (kind, path) or io Sequence)")
    n = len(sources)
    if len(poses) != n:
        raise OptionError("poses", f"poses: expected one poses file per input, in the same order "
                                   f"({_plural(n, 'input')}), got {len(poses)}")
    if len(gts) != n:
        raise OptionError("ground_truth", f"ground_truth: expected one file per input, in the same order "
                                          f"({_plural(n, 'input')}), got {len(gts)}")
    opt.check()


def _open_inputs(config, sources, poses, gts, opt: LoopOptions, times: Dict[str, float],
                 load_vocabulary: bool = True) -> _Inputs:
    """Config, extrinsic, sequences, poses, ground truth and vocabulary (unless
    ``load_vocabulary`` is False), all checked before the long part; poses that miss a stream's
    images entirely fail here, not after tracking."""
    from ..loop.vocabulary import Vocabulary
    from .vocabulary import load_vocabulary as _load_vocabulary

    dev = resolve_device(opt.device)
    cfgs = resolve_configs(config, sources, opt.camera)
    R_ics, t_ics = stream_extrinsics(cfgs, opt)
    seqs = open_inputs(sources, cfgs, opt)
    names = stream_names(seqs)
    listed = [listed_times(sq) for sq in seqs]  # a KITTI poses file's line k is at image k's time
    trajs = [as_trajectory(p, "poses", times=st) for p, st in zip(poses, listed)]
    pose_names = [str(p) if not isinstance(p, tuple) else f"poses of {n}" for p, n in zip(poses, names)]
    gt_trajs = [None if g is None else as_trajectory(g, "ground truth", times=st) for g, st in zip(gts, listed)]
    for name, tr in zip(pose_names, trajs):  # a WorldFrameWarning for poses far from horizontal
        warn_if_not_horizontal(tr, opt.up, opt.mode, name)
    trajs = [into_z_up(tr, opt.up) for tr in trajs]  # the pose graph's z-up world
    voc = None
    t0 = _time.perf_counter()
    if opt.vocabulary is not None and load_vocabulary:
        voc = opt.vocabulary if isinstance(opt.vocabulary, Vocabulary) else _load_vocabulary(opt.vocabulary)
    if opt.load_graph is not None and not (Path(opt.load_graph) / "pose_graph.txt").is_file():
        raise DataError(f"{opt.load_graph}: no saved pose graph here (pose_graph.txt missing)")
    times["vocabulary_load"] = _time.perf_counter() - t0
    # the readers list their stamps without decoding an image
    for b, (st, tr) in enumerate(zip(listed, trajs)):
        if st is not None and st.size and not covered_mask(tr, st, opt.max_pose_gap).any():
            raise DataError(f"{pose_names[b]}: the poses ({span(tr.time.numpy())}) do not cover the images of "
                            f"input {b + 1} {names[b]} ({span(st)}, {st.size} images); are they this "
                            f"sequence's poses, with times in the same clock?")
    return _Inputs(cfgs, dev, R_ics, t_ics, seqs, names, trajs, pose_names, gts, gt_trajs, voc)


def _track(inp: _Inputs, opt: LoopOptions, times: Dict[str, float], beat=None, ck=None
           ) -> Tuple[List[KeyframeLog], int, Dict[str, Any], List[int]]:
    """Stages 1-2: track every stream and pick its keyframes; returns the logs, the number of
    skipped bad frames, the input pipeline's times (``workers``, ``decode_seconds``,
    ``input_wait_seconds``) and the skipped frames per stream. ``ck``: the run's
    ``LoopCheckpoints`` (tracking checkpoints; a resumed run continues from its checkpoint)."""
    from .prefetch import FrameStream

    B = len(inp.seqs)
    logs = _new_logs(inp, opt)
    stream = FrameStream(inp.seqs, size=stream_sizes(inp.cfgs), max_steps=opt.max_frames,
                         workers=opt.workers, pin_memory=inp.device.type == "cuda")
    tracker = make_tracker(inp.cfgs, inp.device, opt.tracker_mode)
    start = 0
    before = {"tracking": 0.0, "decode_seconds": 0.0, "input_wait_seconds": 0.0}  # the interrupted runs'
    if ck is not None and ck.phase == "tracking":
        tracker.load_state_dict(ck.payload["tracker"])
        chunks = ck.chunks("tracking")
        for b, log in enumerate(logs):
            log.load_state_dict([c["logs"][b] for c in chunks])
        start = ck.resumed.frames
        before = dict(ck.payload["times"])
    if ck is not None:
        ck.log_marks = [log.mark() for log in logs]

    def clocks(t0):
        return {"tracking": before["tracking"] + _time.perf_counter() - t0,
                "decode_seconds": before["decode_seconds"] + stream.decode_seconds,
                "input_wait_seconds": before["input_wait_seconds"] + stream.wait_seconds}

    with progress_bar(opt.progress, frames_to_read(inp.seqs, opt.max_frames), "tracking", "frame") as bar:
        t0 = _time.perf_counter()
        for batch, fr, _ in tracked_batches(tracker, stream, inp.device, bar, start=start):
            alive = batch.alive.numpy().astype(bool)
            pub = fr.published.cpu().numpy().astype(bool) & alive
            valid = fr.valid.cpu().numpy()
            ids = fr.ids.cpu().numpy()
            xy = fr.xy.detach().cpu().double().numpy()
            uv = fr.uv.detach().cpu().double().numpy()
            ts = fr.timestamps.cpu().double().numpy()
            for b in np.flatnonzero(alive).tolist():  # streams, not points
                logs[b].frames += 1
                if pub[b]:
                    m = valid[b] & (ids[b] >= 0)
                    logs[b].add(float(ts[b]), ids[b][m], xy[b][m], uv[b][m], batch.raw[b])
            if beat is not None:
                beat()
            if ck is not None:
                steps = batch.step + 1
                ck.frame_hook(steps)
                if ck.due(steps):
                    chunk = {"logs": [log.state_dict(since=m) for log, m in zip(logs, ck.log_marks)]}
                    ck.save(steps, "tracking", {"tracker": tracker.state_dict(), "times": clocks(t0)}, chunk)
                    ck.log_marks = [log.mark() for log in logs]
    end = clocks(t0)
    times["tracking"] = end["tracking"]
    for b, log in enumerate(logs):
        if not any(log.covered):
            raise DataError(f"{log.poses_name}: the poses ({span(log.traj.time.numpy())}) do not cover the images "
                            f"of input {b + 1} {log.name} ({span(log.times)}, {len(log.times)} published frames); "
                            f"are they this sequence's poses, with times in the same clock?")
        if not log.kf_frames:
            raise DataError(f"{log.name}: no keyframe (no published frame with tracked features inside the poses' "
                            f"time span {span(log.traj.time.numpy())})")
    input_times = {"workers": int(opt.workers), "decode_seconds": round(end["decode_seconds"], 6),
                   "input_wait_seconds": round(end["input_wait_seconds"], 6)}
    per_stream = [sum(1 for k in stream.skipped if k[0] == b) for b in range(B)]
    return logs, len(stream.skipped), input_times, per_stream


def _vocabulary(voc, descs: List[List[Dict[str, torch.Tensor]]], opt: LoopOptions, times: Dict[str, float]):
    """Stage 5: the given vocabulary, or one trained on the keyframes' BRIEF descriptors; returns
    it and the summary's ``vocabulary`` entry."""
    from ..loop.vocabulary import Vocabulary

    if voc is None:
        t0 = _time.perf_counter()
        gen = torch.Generator().manual_seed(opt.seed)
        allb = [d["brief"] for ds in descs for d in ds]
        # a seeded random sample of each keyframe's corners: k-medians time grows with the number
        # of descriptors, and a few hundred per image describe its words well enough
        if opt.vocabulary_sample is not None:
            allb = [x[torch.randperm(x.shape[0], generator=gen)[:opt.vocabulary_sample].sort().values]
                    for x in allb]
        D, V = pad_ragged(allb, min_length=1)  # documents (keyframes) x descriptors
        if not bool(V.any()):
            raise DataError("cannot train a vocabulary: the keyframes have no FAST corners (blank images?)")
        voc = Vocabulary.train(D, V, k=opt.vocabulary_k, L=opt.vocabulary_L, generator=gen)
        times["vocabulary"] = _time.perf_counter() - t0
        info: Dict[str, Any] = {"source": "trained on this run", "documents": len(allb), "descriptors": int(V.sum())}
    else:
        times["vocabulary"] = times["vocabulary_load"]
        info = {"source": str(getattr(voc, "source", None) or opt.vocabulary)}
    info.update({"k": int(voc.k), "L": int(voc.L), "words": int(voc.num_words)})
    times.pop("vocabulary_load", None)
    return voc, info


class _GraphStage:
    """Stage 6, resumable: every keyframe into its pose graph, in time order (one stream after the
    other), one :meth:`step` per keyframe; :meth:`state_dict` / :meth:`load_state_dict` stop it
    after any step and go on bit for bit (a checkpoint of ``loop``)."""

    STATE_VERSION = 1

    def __init__(self, inp: _Inputs, logs: List[KeyframeLog], tri, descs, voc, opt: LoopOptions,
                 load_graph: bool = True):
        from ..loop.pose_graph import PoseGraph

        self.inp, self.logs, self.tri, self.descs, self.opt = inp, logs, tri, descs, opt
        B = len(logs)
        n_graphs = B if opt.separate_graphs else 1
        # graph g: stream g's camera and extrinsic (separate graphs), or the shared map's one extrinsic
        # (stream_extrinsics checked they agree) with stream 0's camera (the graph keeps it for users)
        self.graphs = [PoseGraph(inp.cfgs[g].camera.to(dtype=_F64), voc, mode=opt.mode, R_ic=inp.R_ics[g],
                                 t_ic=inp.t_ics[g], pnp_backend=opt.pnp_backend,
                                 generator=torch.Generator().manual_seed(opt.seed))
                       for g in range(n_graphs)]
        loaded = 0
        if opt.load_graph is not None and load_graph:
            for g in self.graphs:
                loaded = g.load(opt.load_graph)
        self.gr = _Graphs(self.graphs, [], [], {} if opt.keep_images else None,
                          sum(len(log.kf_frames) for log in logs), loaded, 0, 0, 0.0)
        self.owner: Dict[Tuple[int, int], int] = {}  # (graph, index) -> stream
        self.b, self.k = 0, 0  # the next keyframe: stream b's k-th
        self.idx: List[int] = []  # graph indices of stream b's keyframes so far
        self.saved = [0] * n_graphs  # keyframes of each graph in earlier checkpoint chunks
        self.positions: List[int] = []  # of each gr.loops record's result in its graph's loops

    @property
    def done(self) -> int:
        """Keyframes added so far (of this run's, not the loaded ones)."""
        return sum(len(log.kf_frames) for log in self.logs[:self.b]) + self.k

    def step(self) -> bool:
        """Add the next keyframe (closing its stream when it was the last); False when none is left."""
        opt, gr = self.opt, self.gr
        while self.b < len(self.logs) and self.k >= len(self.logs[self.b].kf_frames):
            self._close_stream()
        if self.b >= len(self.logs):
            return False
        b, k, log = self.b, self.k, self.logs[self.b]
        g = b if opt.separate_graphs else 0
        seq_id = 1 if opt.separate_graphs else b + 1
        pts, Tk, Rk = self.tri[b]
        kf = make_keyframe(log.times[log.kf_frames[k]], seq_id, Tk[k], Rk[k], pts[k], self.descs[b][k])
        query = kf.num_points > MIN_POINTS_TO_QUERY
        gr.not_querying += int(not query)
        res = self.graphs[g].add_keyframe(kf, detect_loop=query)
        self.owner[(g, kf.index)] = b
        self.idx.append(kf.index)
        if gr.images is not None:
            gr.images[(g, kf.index)] = log.kf_images[k]
        if res is not None:
            old = self.graphs[g].keyframes[res.old_index]
            gr.loops.append(LoopRecord(g, b, self.owner.get((g, res.old_index), -1), kf.time, old.time, res))
            self.positions.append(len(self.graphs[g].loops) - 1)
            gr.accepted += int(res.accepted)
        self.k += 1
        if self.k >= len(log.kf_frames):
            self._close_stream()
        return True

    def _close_stream(self) -> None:
        b, log, opt = self.b, self.logs[self.b], self.opt
        pts = self.tri[b][0]
        self.gr.streams.append(StreamRun(
            name=log.name, stream=b, graph=b if opt.separate_graphs else 0, sequence=1 if opt.separate_graphs else b + 1,
            frames=log.frames, published=len(log.times), uncovered=int(len(log.covered) - sum(log.covered)),
            keyframe_times=np.array([log.times[f] for f in log.kf_frames]),
            graph_indices=np.array(self.idx, dtype=np.int64),
            num_points=np.array([p[0].shape[0] for p in pts], dtype=np.int64)))
        self.b, self.k, self.idx = b + 1, 0, []

    def run(self, bar=None, after_step=None) -> _Graphs:
        """Every keyframe left; ``after_step()`` (or None) is called after each (a checkpoint's
        chance). Returns the stage's results (``seconds``: this run's and the earlier runs')."""
        t0 = _time.perf_counter() - self.gr.seconds
        if bar is not None and self.done:
            bar.update(self.done)
        while self.step():
            if bar is not None:
                bar.set_postfix(loops=self.gr.accepted, refresh=False)
                bar.update(1)
            self.gr.seconds = _time.perf_counter() - t0
            if after_step is not None:
                after_step()
        self.gr.seconds = _time.perf_counter() - t0
        return self.gr

    def state_dict(self, append: bool = False) -> Dict[str, Any]:
        """The stage's state (``loop.state``): each graph's ``PoseGraph.state_dict`` (with
        ``append``: its keyframes' points and descriptors only since the previous call's, a
        chunk to keep with the earlier ones), where the stage stands, the candidates' owners and
        the counts."""
        since = self.saved if append else [0] * len(self.graphs)
        graphs = [g.state_dict(since=s) for g, s in zip(self.graphs, since)]
        self.saved = [len(g.keyframes) for g in self.graphs]
        gr = self.gr
        # a candidate is its graph's LoopResult: found again by its position there
        records = [[r.graph, r.stream, r.old_stream, pos] for r, pos in zip(gr.loops, self.positions)]
        return {"kind": "LoopGraphStage", "version": self.STATE_VERSION, "graphs": graphs, "b": self.b,
                "k": self.k, "idx": list(self.idx), "owner": [[g, i, b] for (g, i), b in self.owner.items()],
                "records": records, "streams_closed": len(gr.streams), "loaded": gr.loaded,
                "not_querying": gr.not_querying, "accepted": gr.accepted, "seconds": gr.seconds}

    def checkpoint_parts(self):
        """:meth:`state_dict` (``append``) split for a checkpoint: ``(state, chunk)``, the chunk
        holding the graphs' new keyframes' points and descriptors (written once, append-only),
        the state everything else (rewritten each time)."""
        from ..loop.keyframe import KEYFRAME_STATIC_KEYS

        st = self.state_dict(append=True)
        static = []
        for g in st["graphs"]:
            kst = g["keyframes"]
            static.append({k: kst[k] for k in KEYFRAME_STATIC_KEYS})
            g["keyframes"] = {k: v for k, v in kst.items() if k not in KEYFRAME_STATIC_KEYS}
        return st, static

    def restore_parts(self, state, chunks) -> None:
        """Restore :meth:`checkpoint_parts`' last ``state`` and every ``chunk`` so far, in order."""
        states = []
        for static in chunks:  # one stage state per chunk: its keyframes, the rest of the last state
            graphs = [{**g, "keyframes": {**g["keyframes"], **static[n]}} for n, g in enumerate(state["graphs"])]
            states.append({**state, "graphs": graphs})
        self.load_state_dict(states)

    def load_state_dict(self, states) -> None:
        """Restore :meth:`state_dict` (or its chunks in order: the last gives all but the
        graphs' keyframe chunks). ``StateError`` for a state of another version or graphs."""
        from ..loop.state import StateError, check_state

        chunks = list(states) if isinstance(states, (list, tuple)) else [states]
        for c in chunks:
            check_state(c, "LoopGraphStage", self.STATE_VERSION, ("graphs", "b", "k", "records"))
            if len(c["graphs"]) != len(self.graphs):
                raise StateError(f"LoopGraphStage state: {len(c['graphs'])} pose graphs, this run has "
                                 f"{len(self.graphs)}")
        st = chunks[-1]
        for n, g in enumerate(self.graphs):
            g.load_state_dict([c["graphs"][n] for c in chunks])
        self.saved = [len(g.keyframes) for g in self.graphs]
        gr = self.gr
        gr.loaded, gr.not_querying, gr.accepted, gr.seconds = (int(st["loaded"]), int(st["not_querying"]),
                                                                int(st["accepted"]), float(st["seconds"]))
        self.owner = {(int(g), int(i)): int(b) for g, i, b in st["owner"]}
        gr.loops, self.positions = [], [int(r[3]) for r in st["records"]]
        for g, b, ob, pos in st["records"]:
            res = self.graphs[g].loops[pos]
            cur, old = self.graphs[g].keyframes[res.index], self.graphs[g].keyframes[res.old_index]
            gr.loops.append(LoopRecord(int(g), int(b), int(ob), cur.time, old.time, res))
        # the closed streams and the current one's keyframes so far, from the restored owners
        self.b, self.k, self.idx = 0, 0, []
        gr.streams = []
        idx_of: Dict[int, List[Tuple[int, int]]] = {}  # stream -> its (graph, index) in adding order
        for (g, i), b in sorted(self.owner.items()):
            idx_of.setdefault(b, []).append((g, i))
        for b in range(int(st["streams_closed"])):
            self.idx = [i for _, i in idx_of.get(b, [])]
            self._close_stream()
        self.k, self.idx = int(st["k"]), [int(i) for i in st["idx"]]
        if gr.images is not None:
            for b, keys in idx_of.items():
                for pos, key in enumerate(keys):
                    gr.images[key] = self.logs[b].kf_images[pos]


def _pose_graphs(inp: _Inputs, logs: List[KeyframeLog], tri, descs, voc, opt: LoopOptions) -> _Graphs:
    """Stage 6: every keyframe into its pose graph, in time order (one stream after the other)."""
    stage = _GraphStage(inp, logs, tri, descs, voc, opt)
    with progress_bar(opt.progress, stage.gr.keyframes, "loop closure", "kf") as bar:
        return stage.run(bar)


def _trajectories_and_ate(inp: _Inputs, gr: _Graphs, opt: LoopOptions) -> Dict[str, float]:
    """Each stream's keyframe trajectories (VIO and corrected) and ATE; returns the summary's
    pooled ATE entries (empty without ground truth)."""
    from ..geometry import R_to_quat
    from ..loop.world import from_z_up
    from ..trajectory import Trajectory

    sq_b = sq_a = 0.0
    n_pairs = 0
    joint_b: List[Any] = []
    joint_a: List[Any] = []
    for s in gr.streams:
        kfs = [gr.graphs[s.graph].keyframes[i] for i in s.graph_indices.tolist()]
        tt = torch.tensor([k.time for k in kfs], dtype=_F64)
        s.vio = Trajectory(tt, torch.stack([k.origin_vio_T for k in kfs]),
                           R_to_quat(torch.stack([k.origin_vio_R for k in kfs])))
        s.corrected = Trajectory(tt.clone(), torch.stack([k.T_w_i for k in kfs]),
                                 R_to_quat(torch.stack([k.R_w_i for k in kfs])))
        s.vio, s.corrected = from_z_up(s.vio, opt.up), from_z_up(s.corrected, opt.up)  # the poses' own world
        gt = inp.gt_trajs[s.stream]
        if gt is None:
            continue
        s.ground_truth = gt
        eb, n, sb, pb = keyframe_ate(s.vio, gt, opt.max_pose_gap)
        ea, _, sa, pa = keyframe_ate(s.corrected, gt, opt.max_pose_gap)
        joint_b.append(pb)
        joint_a.append(pa)
        if eb is None:
            raise DataError(f"{inp.gts[s.stream]}: the ground truth ({span(gt.time.numpy())}) covers fewer than 3 "
                            f"keyframes of {s.name} ({span(s.keyframe_times)})")
        s.ate_before, s.ate_after = eb, ea
        sq_b, sq_a, n_pairs = sq_b + sb, sq_a + sa, n_pairs + n
    ate: Dict[str, float] = {}
    if n_pairs:
        ate["ate_before"] = math.sqrt(sq_b / n_pairs)
        ate["ate_after"] = math.sqrt(sq_a / n_pairs)
        B = len(gr.streams)
        if not opt.separate_graphs and B > 1 and len(joint_b) == B:
            # one alignment for all streams: "after" measures the merged map; "before" only means
            # something when the inputs' VIO poses share one world (e.g. one recording split in two)
            ate["ate_joint_before"] = joint_ate(joint_b)
            ate["ate_joint_after"] = joint_ate(joint_a)
    return ate


def _summary(inp: _Inputs, opt: LoopOptions, gr: _Graphs, ate: Dict[str, float], voc_info: Dict[str, Any],
             times: Dict[str, float], skipped: int, seconds: float) -> Dict[str, Any]:
    """The ``summary.json`` dict (its key order is part of the output format)."""
    reasons: Dict[str, int] = {}
    for r in gr.loops:
        if not r.result.accepted:
            reasons[r.result.reason] = reasons.get(r.result.reason, 0) + 1
    n_graphs = len(gr.graphs)
    summary: Dict[str, Any] = {
        "keyframes": gr.keyframes,
        "keyframes_loaded": gr.loaded * n_graphs,
        "keyframes_not_querying": gr.not_querying,
        "loop_candidates": len(gr.loops),
        "loops_accepted": gr.accepted,
        "loops_rejected": len(gr.loops) - gr.accepted,
        "rejected_by_reason": dict(sorted(reasons.items())),
        **ate,
        "optimisations": sum(g.num_optimizations for g in gr.graphs),
        "skipped_bad_frames": skipped,
        "seconds": round(seconds, 6),
        "times": {k: round(v, 6) for k, v in times.items()},
        "keyframes_per_second": gr.keyframes / gr.seconds if gr.seconds > 0 else 0.0,
        "streams": len(gr.streams),
        "graphs": n_graphs,
        "shared_map": not opt.separate_graphs,
        "mode": opt.mode,
        "up": opt.up,
        "tracker_mode": opt.tracker_mode,
        "device": str(inp.device),
        "config": config_label(inp.cfgs),
        "extrinsic": {"R_ic": inp.R_ics[0].tolist(), "t_ic": inp.t_ics[0].tolist()},
        "keyframe_rule": ({"every": opt.keyframe_every} if opt.keyframe_every is not None else
                          {"distance_m": opt.keyframe_distance, "angle_deg": opt.keyframe_angle}),
        "vocabulary": voc_info,
        "load_graph": None if opt.load_graph is None else str(opt.load_graph),
        "per_stream": [_stream_summary(inp, gr, s) for s in gr.streams],
    }
    return summary


def _stream_summary(inp: _Inputs, gr: _Graphs, s: StreamRun) -> Dict[str, Any]:
    gt = inp.gts[s.stream]
    return {
        "name": s.name, "graph": s.graph, "sequence": s.sequence, "frames": s.frames, "published": s.published,
        "published_without_pose": s.uncovered, "keyframes": int(s.graph_indices.size),
        "mean_points": float(s.num_points.mean()) if s.num_points.size else 0.0,
        "loops_accepted": sum(1 for r in gr.loops if r.stream == s.stream and r.result.accepted),
        "ate_before": s.ate_before, "ate_after": s.ate_after,
        "poses": inp.pose_names[s.stream],
        "ground_truth": None if gt is None or isinstance(gt, tuple) else str(gt),
        **stream_config_entry(inp.cfgs[s.stream]),
        "extrinsic": {"R_ic": inp.R_ics[s.stream].tolist(), "t_ic": inp.t_ics[s.stream].tolist()},
    }
