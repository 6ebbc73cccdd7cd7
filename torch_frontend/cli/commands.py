"""The commands: each builds a pipeline's options from its flags, runs the pipeline and prints its
summary (``format_summary``, ``format_loop_summary``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

from .common import SAMPLE_DIR, _rank, _UsageError, default_config_path

# ----------------------------------------------------------------------------------------------
# printing


def format_summary(s: Dict[str, Any], tracks: bool = True) -> str:
    """The few lines ``track``/``demo`` print (``s``: the summary of ``run_track``; ``tracks``:
    whether the run drew ``tracks/``, i.e. not ``--no-tracks``)."""
    lines = [
        f"streams       {s['streams']}   frames {s['frames']}   steps {s.get('steps', '?')}   "
        f"published frames {s['published']}",
        f"features      {s['published_features']} published, {s['mean_features']:.1f} per published frame",
        f"tracks        {s['tracks']}   mean length {s['mean_track_length']:.2f}   "
        f"median {s['median_track_length']:g} frames",
        f"speed         {s['frames_per_second']:.1f} frames/s ({s['seconds']:.2f} s on {s.get('device', '?')}, "
        f"mode {s.get('mode', '?')}, {s.get('lk_backend', '?')} LK)",
        f"skipped       {s['skipped_bad_frames']} bad frames",
    ]
    for k in s.get("skipped", [])[:5]:
        lines.append(f"              stream {k['stream']}: {k['reason']}")
    if "decode_seconds" in s:
        lines.append(f"input         decoding {s['decode_seconds']:.2f} s ({s.get('workers', 0)} workers), "
                     f"waited {s['input_wait_seconds']:.2f} s for frames, tracker {s.get('tracker_seconds', 0):.2f} s")
    dist = s.get("distributed")
    if dist:
        lines.append(f"ranks         {dist['world_size']} ({dist['backend']}): "
                     + ", ".join(f"rank {r['rank']} {len(r['streams'])} streams" for r in dist["ranks"]))
    t = ", tracks/" if tracks else ""
    if "out" in s and dist:
        lines.append(f"outputs       {s['out']}/ (stream<b>/ per input: features.csv, features.npz, summary.json, "
                     f"plots{t}; index.json, summary.json)")
    elif "out" in s:
        lines.append(f"outputs       {s['out']}/ (features.csv, features.npz, summary.json, "
                     f"features_per_frame.png, track_length_hist.png, track_paths.png{t})")
    return "\n".join(lines)


def format_loop_summary(s: Dict[str, Any]) -> str:
    """The few lines ``loop`` / ``demo --loop`` print (``s``: the summary of ``run_loop``)."""
    from ..pipelines.loop import MIN_POINTS_TO_QUERY

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
    dist = s.get("distributed")
    if dist:
        lines.append(f"ranks         {dist['world_size']} ({dist['backend']}): "
                     + ", ".join(f"rank {r['rank']} {len(r['streams'])} streams" for r in dist["ranks"]))
    if "out" in s and dist and not s["shared_map"]:
        lines.append(f"outputs       {s['out']}/ (stream<b>/ per input: the loop outputs of that input; "
                     f"index.json, summary.json)")
    elif "out" in s:
        lines.append(f"outputs       {s['out']}/ (vins_result_loop.csv, trajectory_loop.tum, trajectory_vio.tum, "
                     f"loops.csv, pose_graph/, summary.json, trajectory_top.png, place_recognition_scores.png)")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# commands


def _progress(args: argparse.Namespace):
    return False if args.no_progress else None


def _flag(source) -> str:
    """A source as the command line names it (``--euroc DIR``, ``--kitti SEQ``)."""
    return f"--{source[0]} {source[1]}"


def _paired_inputs(args: argparse.Namespace) -> Tuple[List[Tuple], Any]:
    """The inputs of ``track``/``loop`` and their configs, from the one ordered list that
    ``--euroc/--bag/--images``, ``--config`` and ``--rig`` append to (``_SourceAction``), and the
    positional CONFIG. Returns ``(sources, config)``: ``config`` is the pipelines' (one config for
    every input, None, or one entry per input: its own, else CONFIG's, else None, its own
    ``sensor.yaml``).

    Rules (the ``--config`` help): a ``--config`` applies to the input just before it; one before
    the first input is CONFIG (every input without its own), and then no input may have its own
    ``--config`` (that order reads as "config before its input", which is not the rule); a rig
    file's entries name theirs (``config:``). Misuse is a usage error."""
    from ..pipelines.rig import read_rig

    sources: List[Tuple] = []
    own: List[Any] = []  # per input: its --config / rig config, or None
    from_flag: List[bool] = []  # the input's config came from a --config (not a rig entry)
    common, leading = args.config, None
    last = None  # what the previous item was: None, "input" or the rig file
    for kind, value in args.sources or []:
        if kind == "config":
            if last is None:
                if common is not None or leading is not None:
                    raise _UsageError(f"--config {value}: a config for every input is given twice "
                                      f"({common or leading} and {value}); give one")
                leading = Path(value)
            elif last != "input":
                raise _UsageError(f"--config {value} after --rig {last}: a rig file's inputs name their own "
                                  f"config (its 'config:' key); a --config applies to the --euroc/--kitti/--bag/--images "
                                  f"input just before it")
            elif own[-1] is not None:
                raise _UsageError(f"--config {value}: input {len(sources)} ({_flag(sources[-1])}) already has "
                                  f"--config {own[-1]}; give one --config after each input")
            else:
                own[-1] = Path(value)
                from_flag[-1] = True
            continue
        if kind == "rig":
            rs, rc = read_rig(value)
            sources += rs
            own += rc
            from_flag += [False] * len(rs)
            last = str(value)
            continue
        sources.append((kind, value))
        own.append(None)
        from_flag.append(False)
        last = "input"
    if leading is not None:
        if any(from_flag):
            b = from_flag.index(True)
            raise _UsageError(f"--config {leading} before the first input, and --config {own[b]} after input "
                              f"{b + 1} ({_flag(sources[b])}): a --config applies to the input just before it, "
                              f"so the first one has no input; give each input's --config after it (and one "
                              f"config for the others as CONFIG)")
        common = leading
    if all(c is None for c in own):
        return sources, common
    return sources, [common if c is None else c for c in own]


def _check_inputs(config, sources: Sequence[Tuple], kinds: str) -> None:
    """The usage errors of ``track``/``loop`` inputs, in the command line's words (``config``: as
    :func:`_paired_inputs` returns it)."""
    if not sources:
        raise _UsageError(f"no input: give at least one {kinds}")
    per = list(config) if isinstance(config, list) else [config] * len(sources)
    for b, (src, c) in enumerate(zip(sources, per)):
        if c is None and src[0] not in ("euroc", "kitti"):
            raise _UsageError(f"no CONFIG given for input {b + 1} ({_flag(src)}): a VINS config file is needed "
                              f"unless an --euroc folder provides sensor.yaml or a --kitti sequence calib.txt "
                              f"(give CONFIG, or --config FILE after this input)")


def _sharded() -> bool:
    """Whether a launcher (``torchrun``) started this process as a rank of a job."""
    from ..distributed.env import launched

    return launched()


def _device(args: argparse.Namespace):
    """``--device``; not given: CPU for one process, each rank's own device under ``torchrun``
    (``cuda:{LOCAL_RANK}`` when CUDA is present)."""
    return args.device if args.device is not None or _sharded() else "cpu"


def _input_options(args: argparse.Namespace) -> Dict[str, Any]:
    """``InputOptions`` fields from the reader flags of ``track``/``loop``."""
    return dict(device=_device(args), max_frames=args.max_frames, camera=args.camera, fps=args.fps,
                topic=args.topic, skip_bad_frames=args.skip_bad_frames, progress=_progress(args),
                workers=args.workers)


def _resolved_config(config, sources, opt):
    """The run's config (after the options are checked, so that a bad option is still the first
    error): one ``TrackerConfig`` for every input, or a list of one per input
    (``pipelines.inputs.resolve_configs``), the settings printed on one line per distinct config,
    with its streams when there are several (rank 0 under ``torchrun``)."""
    from ..pipelines.inputs import distinct_configs, resolve_configs

    opt.check()
    cfgs = resolve_configs(config, sources, opt.camera)
    groups = distinct_configs(cfgs)
    if _rank() == 0:
        for cfg, streams in groups:
            where = f" (stream{'s' if len(streams) > 1 else ''} {', '.join(map(str, streams))})" if len(groups) > 1 else ""
            print(cfg.settings_line() + where, flush=True)
    return cfgs[0] if len(groups) == 1 else cfgs


def _cmd_track(args: argparse.Namespace) -> int:
    from ..pipelines.track import TrackOptions, run_track

    sources, config = _paired_inputs(args)
    _check_inputs(config, sources, "--euroc DIR, --kitti SEQ, --bag PATH, --images DIR or --rig FILE")
    opt = TrackOptions(**_input_options(args), mode=args.mode, write_tracks=not args.no_tracks,
                       bag=args.write_bag, bag_format=args.bag_format, bag_images=args.bag_images,
                       bag_imu=not args.no_bag_imu, checkpoint_every=args.checkpoint_every, resume=args.resume,
                       lk_backend=args.lk_backend)
    config = _resolved_config(config, sources, opt)
    if _sharded():
        from ..pipelines.sharded import run_track_sharded

        summary = run_track_sharded(config, sources, args.out, opt, timeout=args.timeout)
        if summary is not None:  # rank 0
            print(format_summary(summary, tracks=not args.no_tracks))
        return 0
    print(format_summary(run_track(config, sources, args.out, opt), tracks=not args.no_tracks))
    return 0


def _world_defaults(args: argparse.Namespace, sources: Sequence[Tuple]) -> Tuple[str, str, str]:
    """``(pose graph mode, up axis, why)`` of ``loop``: ``--pose-graph`` / ``--up`` as given, else
    6dof when an input is ``--kitti`` (no IMU, as VINS-Fusion with ``imu: 0``) and ``-y`` when
    every input is (KITTI's camera-0 world: y down), else 4dof and ``+z``; ``why`` says which
    default came from ``--kitti`` (empty when none did)."""
    kitti = [s[0] == "kitti" for s in sources]
    mode = args.pose_graph or ("6dof" if any(kitti) else "4dof")
    up = args.up or ("-y" if kitti and all(kitti) else "+z")
    why = [w for w, derived in (("--kitti: no IMU, 6dof", args.pose_graph is None and any(kitti)),
                                ("--kitti: camera-0 world, y down", args.up is None and kitti and all(kitti)))
           if derived]
    return mode, up, "; ".join(why)


def _cmd_loop(args: argparse.Namespace) -> int:
    from ..pipelines.loop import LoopOptions, run_loop

    sources, config = _paired_inputs(args)
    _check_inputs(config, sources, "--euroc DIR, --kitti SEQ, --images DIR, --bag FILE or --rig FILE")
    if args.vocabulary is None and not args.train_vocabulary:
        raise _UsageError("no vocabulary: give --vocabulary FILE (VINS's brief_k10L6.bin, or a .npz from "
                          "'torch-frontend vocabulary train') or --train-vocabulary")
    mode, up, why = _world_defaults(args, sources)
    opt = LoopOptions(
        **_input_options(args), vocabulary=args.vocabulary, train_vocabulary=args.train_vocabulary,
        vocabulary_k=args.train_k, vocabulary_L=args.train_L, load_graph=args.load_graph,
        separate_graphs=args.separate_graphs, mode=mode, up=up, tracker_mode=args.tracker_mode,
        keyframe_distance=args.keyframe_distance, keyframe_angle=args.keyframe_angle,
        keyframe_every=args.keyframe_every, max_pose_gap=args.max_pose_gap, pnp_backend=args.pnp,
        checkpoint_every=args.checkpoint_every, resume=args.resume,
    )
    config = _resolved_config(config, sources, opt)
    if _rank() == 0:
        print(f"pose graph    {mode}, up {up}" + (f" ({why})" if why else ""), flush=True)
    if _sharded():
        from ..pipelines.sharded import run_loop_sharded

        summary = run_loop_sharded(config, sources, args.poses or [], args.out, opt,
                                   ground_truth=args.ground_truth, timeout=args.timeout)
        if summary is not None:  # rank 0
            print(format_loop_summary(summary))
        return 0
    run = run_loop(config, sources, args.poses or [], args.out, opt, ground_truth=args.ground_truth)
    print(format_loop_summary(run.summary))
    return 0


def _cmd_demo_loop(args: argparse.Namespace) -> int:
    from ..pipelines.loop import demo_announcement, demo_loop, demo_options

    # one intra-op thread by default, as every command (_thread_policy; measured here: > 10 min
    # instead of ~40 s with 2 threads while another process kept one of 2 cores busy)
    out = Path("out/demo_loop") if args.out == Path("out/demo") else args.out
    opt = demo_options(separate_graphs=args.separate_graphs, device=args.device or "cpu", progress=_progress(args),
                       tracker_mode=args.mode, max_frames=args.max_frames)
    print(f"demo          {demo_announcement(opt)}")
    run = demo_loop(out, opt, two_sequences=args.two_sequences)
    print(format_loop_summary(run.summary))
    return 0


def _cmd_demo_flight(args: argparse.Namespace) -> int:
    from ..pipelines.track import DEMO_FLIGHT, TrackOptions, demo_flight_inputs, run_track

    if args.config is not None:
        raise _UsageError("--config does not go with --flight (the flight has its own camera)")
    out = Path("out/demo_flight") if args.out == Path("out/demo") else args.out
    H, W = DEMO_FLIGHT["size"]
    print(f"demo          synthetic flight over the package photo: {DEMO_FLIGHT['frames']} frames {W}x{H} at "
          f"{DEMO_FLIGHT['rate']:g} Hz, ~2.5 px/frame across, turning and zooming slowly")
    cfg, sources = demo_flight_inputs()
    print(cfg.settings_line())
    opt = TrackOptions(device=args.device or "cpu", mode=args.mode, max_frames=args.max_frames,
                       write_tracks=not args.no_tracks, progress=_progress(args), lk_backend=args.lk_backend)
    print(format_summary(run_track(cfg, sources, out, opt), tracks=not args.no_tracks))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..pipelines.track import TrackOptions, run_track

    if args.loop and args.flight:
        raise _UsageError("--loop and --flight are two demos: give one")
    if args.loop:
        return _cmd_demo_loop(args)
    if args.two_sequences or args.separate_graphs:
        raise _UsageError("--two-sequences and --separate-graphs go with --loop")
    if args.flight:
        return _cmd_demo_flight(args)
    cfg = load_config(args.config or default_config_path())
    print(cfg.summary())
    print(f"\nsample        {SAMPLE_DIR} (cam0)")
    opt = TrackOptions(device=args.device or "cpu", mode=args.mode, max_frames=args.max_frames,
                       write_tracks=not args.no_tracks, progress=_progress(args), lk_backend=args.lk_backend)
    print(format_summary(run_track(cfg, [("euroc", str(SAMPLE_DIR))], args.out, opt), tracks=not args.no_tracks))
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from ..pipelines.compare import CompareOptions, format_compare, run_compare

    opt = CompareOptions(tolerance=args.tolerance, stream=args.stream, num_cameras=args.num_cameras)
    print(format_compare(run_compare(args.reference, args.run, args.out, opt)))
    return 0


def _cmd_vocabulary(args: argparse.Namespace) -> int:
    from ..pipelines.vocabulary import VocabularyOptions, run_vocabulary_train

    if args.vocabulary_command != "train":
        raise _UsageError("vocabulary: expected a subcommand: train")
    opt = VocabularyOptions(k=args.k, L=args.L, fast_threshold=args.fast_threshold, max_images=args.max_images,
                            max_keypoints=args.max_keypoints, seed=args.seed, device=_device(args),
                            progress=_progress(args))
    if _sharded():
        from ..pipelines.sharded import run_vocabulary_train_sharded

        s = run_vocabulary_train_sharded(args.images, args.out, opt, timeout=args.timeout)
        if s is None:  # not rank 0
            return 0
    else:
        s = run_vocabulary_train(args.images, args.out, opt)
    print(f"vocabulary    {s['words']} words (k={s['k']}, L={s['L']}) from {s['descriptors']} descriptors "
          f"of {s['images']} images in {s['seconds']:.2f} s -> {s['out']}")
    return 0


def format_ros_summary(s: Dict[str, Any]) -> str:
    """The lines ``ros`` prints on exit (``s``: the summary of ``pipelines.ros_node.run_ros_node``)."""

    def lat(d: Dict[str, Any]) -> str:
        if not d["n"]:
            return "none"
        return f"median {d['median']:.1f} ms, p95 {d['p95']:.1f} ms, max {d['max']:.1f} ms ({d['n']} frames)"

    lines = [f"cameras       {len(s['cameras'])}   steps {s['steps']}   cameras per step "
             f"{s['cameras_per_step'] if s['cameras_per_step'] is not None else '-'}   ({s['seconds']:.1f} s on "
             f"{s['device']}, {s['lk_backend']} LK)",
             f"frames        received {s['received']}, tracked {s['tracked']}, dropped {s['dropped']} (queue "
             f"{s['queue_size']} per camera, the newest kept; sync wait {s['sync_wait_ms']:g} ms)",
             f"latency       image received -> feature published: {lat(s['latency_ms'])}"]
    for c in s["cameras"]:
        lines.append(f"  {c['topic']} -> {c['outputs']}: {c['received']} received, {c['tracked']} tracked, "
                     f"{c['dropped']} dropped, {c['feature_messages']} feature messages, {c['restarts']} restarts")
    return "\n".join(lines)


def _cmd_ros(args: argparse.Namespace) -> int:
    """``ros``: configs and rospy's remapping arguments (``name:=value``) from the positionals."""
    from ..pipelines.ros_node import RosCamera, RosOptions, run_ros_node

    remap = [a for a in args.configs if ":=" in a]
    cams = []
    for a in args.configs:
        if ":=" in a:
            continue
        path, topic = a, None
        if "@" in a and not Path(a).is_file():
            path, topic = a.rsplit("@", 1)
            if not topic:
                raise _UsageError(f"{a}: expected CONFIG@TOPIC, got an empty topic")
        cams.append(RosCamera(Path(path), topic))
    if not cams:
        raise _UsageError("no CONFIG given (only remapping arguments: " + " ".join(remap) + ")")
    for c in cams:
        if not c.config.is_file():
            raise _UsageError(f"config file not found: {c.config}")
    opt = RosOptions(device=_device(args), lk_backend=args.lk_backend, queue_size=args.queue_size,
                     sync_wait=args.sync_wait / 1e3, latency=args.latency,
                     summary=None if args.summary is None else str(args.summary), remap=remap,
                     max_frames=args.max_frames)

    def ready(node) -> None:
        seen = []
        for cfg in node.cfgs:  # the settings of each distinct config, as track prints them
            if not any(cfg is c for c in seen):
                seen.append(cfg)
                print(cfg.settings_line(), flush=True)
        names = ", ".join(f"{t} -> {node.rospy.names.resolve_name(p + 'feature')}"
                          for t, p in zip(node.topics, node.prefixes))
        import rosgraph

        print(f"ros           node {node.rospy.get_name()} (master {rosgraph.get_master_uri()}): {names}", flush=True)

    print(format_ros_summary(run_ros_node(cams, opt, ready=ready)))
    return 0


def _cmd_config(args: argparse.Namespace) -> int:
    from ..pipelines.make_config import format_make_config, run_make_config

    print(format_make_config(run_make_config(args.out, kalibr=args.from_kalibr, camera_info=args.from_camera_info,
                                             imu=args.imu)))
    return 0
