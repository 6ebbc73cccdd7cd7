"""The ``torch-frontend`` command line: ``track``, ``demo``, ``loop`` and ``vocabulary train``.

This module does argparse and printing only: each command builds the options of a pipeline from
its flags, calls the pipeline (``torch_frontend.pipelines``), prints the summary and maps errors to
exit codes.

``torch-frontend track [CONFIG] (--euroc DIR | --bag PATH | --images DIR [--config FILE] | --rig FILE)...
--out DIR`` runs the VINS front end on one or more sequences at once (B streams in one batched
tracker, each with its own config: :func:`_paired_inputs`) and writes
``features.csv``, ``features.npz``, ``summary.json``, two plots and ``tracks/`` into ``--out``
(``pipelines.track.run_track``; see ``torch_frontend.outputs``). ``torch-frontend demo`` does the
same on the sample EuRoC frames shipped with the package.

``torch-frontend loop [CONFIG] (--euroc DIR | --images DIR | --bag FILE)... --poses FILE... --out DIR
(--vocabulary FILE | --train-vocabulary)`` runs loop closure (VINS's pose graph) on images plus
their VIO poses and writes the loop-corrected trajectory, the loops, the pose graph, a summary and
plots (``pipelines.loop.run_loop``, ``torch_frontend.loop.report``); ``torch-frontend demo --loop``
does the same on a rendered sequence that revisits places (``pipelines.loop.demo_loop``).
``torch-frontend vocabulary train`` is ``pipelines.vocabulary.run_vocabulary_train``.

Under ``torchrun`` (``torchrun --nproc-per-node N -m torch_frontend track|loop|vocabulary train
...``) every rank runs the command on its block of the inputs (``pipelines.sharded``): each rank on
``cuda:LOCAL_RANK`` when CUDA is present (``--device`` not given), rank 0 printing the merged
summary; ``--timeout`` bounds how long a rank may go without progress. ``--workers N`` decodes the
frames in DataLoader workers (``pipelines.prefetch``).

``track``, ``demo`` and ``loop`` run torch and OpenCV on one thread unless ``--threads N`` is given
or the user set ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` (:func:`_thread_policy`; the library
itself never changes the process's threads), and restore the previous counts afterwards.

User errors (missing or unreadable input, a bad config, a bag without the topic, an image of the
wrong size, an empty sequence, a bad option value) print one line ``torch-frontend: error: ...`` on
stderr and exit with a non-zero code: 2 for usage, option and config errors, 1 for data errors,
130 when interrupted (Ctrl-C, SIGINT), 143 on SIGTERM. A pipeline's ``OptionError`` names its
option; the line names the flag. Under ``torchrun`` an error every rank meets is printed by rank 0
only; a rank's own failure by that rank (``rank r (inputs): ...``) and by rank 0 (the job's line).

SIGINT and SIGTERM stop a command the same way (a ``KeyboardInterrupt``, while the command runs;
the previous handlers come back after it): the run removes its temporary folder, so ``--out``
keeps a complete set of outputs, the previous one, or the new one if the run had swapped it in
already (``torch_frontend.outputs``).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import signal
import sys
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

from .errors import ConfigError, DataError
from .pipelines.common import OptionError

PACKAGE_DIR = Path(__file__).resolve().parent
SAMPLE_DIR = PACKAGE_DIR / "data" / "euroc_mini"

EXIT_DATA = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_TERMINATED = 143  # 128 + SIGTERM

# option name of a pipeline -> the flag that sets it, per command (for OptionError messages)
_INPUT_FLAGS = {"max_frames": "--max-frames", "device": "--device", "fps": "--fps", "topic": "--topic",
                "camera": "--camera", "workers": "--workers"}
_TRACK_FLAGS = {**_INPUT_FLAGS, "mode": "--mode", "bag": "--write-bag", "bag_format": "--bag-format",
                "checkpoint_every": "--checkpoint-every", "resume": "--resume", "lk_backend": "--lk-backend"}
_DEMO_FLAGS = {"max_frames": "--max-frames", "device": "--device", "mode": "--mode", "tracker_mode": "--mode",
               "lk_backend": "--lk-backend"}
_LOOP_FLAGS = {
    **_INPUT_FLAGS, "poses": "--poses", "ground_truth": "--ground-truth", "vocabulary": "--vocabulary",
    "train_vocabulary": "--train-vocabulary", "vocabulary_k": "--train-k", "vocabulary_L": "--train-L",
    "load_graph": "--load-graph", "separate_graphs": "--separate-graphs", "mode": "--pose-graph",
    "tracker_mode": "--tracker-mode", "keyframe_distance": "--keyframe-distance",
    "keyframe_angle": "--keyframe-angle", "keyframe_every": "--keyframe-every", "max_pose_gap": "--max-pose-gap",
    "pnp_backend": "--pnp", "checkpoint_every": "--checkpoint-every", "resume": "--resume",
}
_VOCABULARY_FLAGS = {"out": "--out", "k": "--k", "L": "--L", "fast_threshold": "--fast-threshold",
                     "max_images": "--max-images", "max_keypoints": "--max-keypoints", "seed": "--seed",
                     "device": "--device"}


def default_config_path() -> Path:
    """The EuRoC config: ``configs/euroc.yaml`` of a source checkout, else the packaged copy."""
    for p in (PACKAGE_DIR.parent / "configs" / "euroc.yaml", PACKAGE_DIR / "data" / "configs" / "euroc.yaml"):
        if p.is_file():
            return p
    raise ConfigError("cannot find configs/euroc.yaml (looked beside the package)")


class _UsageError(Exception):
    """Bad command-line combination (printed as one line, exit 2)."""


#: environment variables that set torch's intra-op threads: when the user sets one, the CLI leaves
#: the threads to it (torch reads them at start-up)
THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _thread_policy(threads: int | None):
    """torch's intra-op threads and OpenCV's for one command (``--threads``), restored after it.

    Default (``threads`` None): 1, unless the user set ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS``
    (then nothing is changed). One thread because the tracker's tensors are small (752x480
    images, ~150 points): extra threads only add synchronisation, and on a busy machine each of
    the tracker's many small ops then waits for a descheduled thread. Measured on this project's
    shared 2-core machine (``docs/cli.md#threads``): ``track`` on the sample frames, in the worst
    sitting, 0.3-1.6 frames/s with torch's default 2 threads and 8.5-14.3 with 1 (loaded by one
    busy core or not)."""
    import torch

    if threads is None and any(os.environ.get(v) for v in THREAD_ENV):
        yield
        return
    n = 1 if threads is None else int(threads)
    try:
        import cv2
    except ImportError:  # pragma: no cover - cv2 is a dependency
        cv2 = None
    saved = torch.get_num_threads(), (cv2.getNumThreads() if cv2 is not None else None)
    torch.set_num_threads(n)
    if cv2 is not None:
        cv2.setNumThreads(n)
    try:
        yield
    finally:
        torch.set_num_threads(saved[0])
        if cv2 is not None:
            cv2.setNumThreads(saved[1])


# ----------------------------------------------------------------------------------------------
# printing


def format_summary(s: Dict[str, Any]) -> str:
    """The few lines ``track``/``demo`` print (``s``: the summary of ``run_track``)."""
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
    if "out" in s and dist:
        lines.append(f"outputs       {s['out']}/ (stream<b>/ per input: features.csv, features.npz, summary.json, "
                     f"plots, tracks/; index.json, summary.json)")
    elif "out" in s:
        lines.append(f"outputs       {s['out']}/ (features.csv, features.npz, summary.json, "
                     f"features_per_frame.png, track_length_hist.png, track_paths.png, tracks/)")
    return "\n".join(lines)


def format_loop_summary(s: Dict[str, Any]) -> str:
    """The few lines ``loop`` / ``demo --loop`` print (``s``: the summary of ``run_loop``)."""
    from .pipelines.loop import MIN_POINTS_TO_QUERY

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
    """A source as the command line names it (``--euroc DIR``)."""
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
    from .pipelines.rig import read_rig

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
                                  f"config (its 'config:' key); a --config applies to the --euroc/--bag/--images "
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
        if c is None and src[0] != "euroc":
            raise _UsageError(f"no CONFIG given for input {b + 1} ({_flag(src)}): a VINS config file is needed "
                              f"unless an --euroc folder provides sensor.yaml (give CONFIG, or --config FILE "
                              f"after this input)")


def _sharded() -> bool:
    """Whether a launcher (``torchrun``) started this process as a rank of a job."""
    from .distributed.env import launched

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
    from .pipelines.inputs import distinct_configs, resolve_configs

    opt.check()
    cfgs = resolve_configs(config, sources, opt.camera)
    groups = distinct_configs(cfgs)
    if _rank() == 0:
        for cfg, streams in groups:
            where = f" (stream{'s' if len(streams) > 1 else ''} {', '.join(map(str, streams))})" if len(groups) > 1 else ""
            print(cfg.settings_line() + where, flush=True)
    return cfgs[0] if len(groups) == 1 else cfgs


def _cmd_track(args: argparse.Namespace) -> int:
    from .pipelines.track import TrackOptions, run_track

    sources, config = _paired_inputs(args)
    _check_inputs(config, sources, "--euroc DIR, --bag PATH, --images DIR or --rig FILE")
    opt = TrackOptions(**_input_options(args), mode=args.mode, write_tracks=not args.no_tracks,
                       bag=args.write_bag, bag_format=args.bag_format, bag_images=args.bag_images,
                       bag_imu=not args.no_bag_imu, checkpoint_every=args.checkpoint_every, resume=args.resume,
                       lk_backend=args.lk_backend)
    config = _resolved_config(config, sources, opt)
    if _sharded():
        from .pipelines.sharded import run_track_sharded

        summary = run_track_sharded(config, sources, args.out, opt, timeout=args.timeout)
        if summary is not None:  # rank 0
            print(format_summary(summary))
        return 0
    print(format_summary(run_track(config, sources, args.out, opt)))
    return 0


def _cmd_loop(args: argparse.Namespace) -> int:
    from .pipelines.loop import LoopOptions, run_loop

    sources, config = _paired_inputs(args)
    _check_inputs(config, sources, "--euroc DIR, --images DIR, --bag FILE or --rig FILE")
    if args.vocabulary is None and not args.train_vocabulary:
        raise _UsageError("no vocabulary: give --vocabulary FILE (VINS's brief_k10L6.bin, or a .npz from "
                          "'torch-frontend vocabulary train') or --train-vocabulary")
    opt = LoopOptions(
        **_input_options(args), vocabulary=args.vocabulary, train_vocabulary=args.train_vocabulary,
        vocabulary_k=args.train_k, vocabulary_L=args.train_L, load_graph=args.load_graph,
        separate_graphs=args.separate_graphs, mode=args.pose_graph, tracker_mode=args.tracker_mode,
        keyframe_distance=args.keyframe_distance, keyframe_angle=args.keyframe_angle,
        keyframe_every=args.keyframe_every, max_pose_gap=args.max_pose_gap, pnp_backend=args.pnp,
        checkpoint_every=args.checkpoint_every, resume=args.resume,
    )
    config = _resolved_config(config, sources, opt)
    if _sharded():
        from .pipelines.sharded import run_loop_sharded

        summary = run_loop_sharded(config, sources, args.poses or [], args.out, opt,
                                   ground_truth=args.ground_truth, timeout=args.timeout)
        if summary is not None:  # rank 0
            print(format_loop_summary(summary))
        return 0
    run = run_loop(config, sources, args.poses or [], args.out, opt, ground_truth=args.ground_truth)
    print(format_loop_summary(run.summary))
    return 0


def _cmd_demo_loop(args: argparse.Namespace) -> int:
    from .pipelines.loop import demo_announcement, demo_loop, demo_options

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
    from .pipelines.track import DEMO_FLIGHT, TrackOptions, demo_flight_inputs, run_track

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
    print(format_summary(run_track(cfg, sources, out, opt)))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .config import load_config
    from .pipelines.track import TrackOptions, run_track

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
    print(format_summary(run_track(cfg, [("euroc", str(SAMPLE_DIR))], args.out, opt)))
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from .pipelines.compare import CompareOptions, format_compare, run_compare

    opt = CompareOptions(tolerance=args.tolerance, stream=args.stream, num_cameras=args.num_cameras)
    print(format_compare(run_compare(args.reference, args.run, args.out, opt)))
    return 0


def _cmd_vocabulary(args: argparse.Namespace) -> int:
    from .pipelines.vocabulary import VocabularyOptions, run_vocabulary_train

    if args.vocabulary_command != "train":
        raise _UsageError("vocabulary: expected a subcommand: train")
    opt = VocabularyOptions(k=args.k, L=args.L, fast_threshold=args.fast_threshold, max_images=args.max_images,
                            max_keypoints=args.max_keypoints, seed=args.seed, device=_device(args),
                            progress=_progress(args))
    if _sharded():
        from .pipelines.sharded import run_vocabulary_train_sharded

        s = run_vocabulary_train_sharded(args.images, args.out, opt, timeout=args.timeout)
        if s is None:  # not rank 0
            return 0
    else:
        s = run_vocabulary_train(args.images, args.out, opt)
    print(f"vocabulary    {s['words']} words (k={s['k']}, L={s['L']}) from {s['descriptors']} descriptors "
          f"of {s['images']} images in {s['seconds']:.2f} s -> {s['out']}")
    return 0


# ----------------------------------------------------------------------------------------------
# the parser


class _SourceAction(argparse.Action):
    """``--euroc/--bag/--images``, ``--config`` and ``--rig``: appended, in command-line order, as
    ``(kind, path)`` (kind ``config`` / ``rig`` for those two; :func:`_paired_inputs` pairs them)."""

    def __call__(self, parser, namespace, values, option_string=None):
        items = list(getattr(namespace, self.dest, None) or [])
        items.append((self.const, values))
        setattr(namespace, self.dest, items)


def _positive_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {s}")
    return v


def _frame_rate(s: str) -> float:
    v = _positive_float(s)
    if not math.isfinite(v):  # inf would put every frame at 0 s: the tracker would publish nothing
        raise argparse.ArgumentTypeError(f"must be a finite frame rate > 0 (Hz), got {s}")
    return v


def _non_negative_int(s: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {s}")
    return v


def _add_timeout(p: argparse.ArgumentParser) -> None:
    p.add_argument("--timeout", type=_positive_float, default=None, metavar="S",
                   help="under torchrun: seconds a rank may go without progress before the job fails "
                        "naming it, and the collectives' timeout (default: 1800)")


def _positive_int(s: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {s}")
    return v


def _add_run_options(p: argparse.ArgumentParser, out_default: str | None) -> None:
    p.add_argument("--out", type=Path, default=None if out_default is None else Path(out_default),
                   required=out_default is None, metavar="DIR",
                   help="output folder" + ("" if out_default is None else f" (default: {out_default})"))
    p.add_argument("--device", default=None,
                   help="cpu or cuda (default: cpu; under torchrun cuda:LOCAL_RANK when CUDA is present)")
    p.add_argument("--mode", choices=("mono", "fusion"), default="mono",
                   help="VINS-Mono feature_tracker or VINS-Fusion tracker rules (default: mono)")
    p.add_argument("--max-frames", type=_positive_int, default=None, metavar="N",
                   help="stop after N frames per stream")
    p.add_argument("--no-tracks", action="store_true", help="do not draw track images (tracks/)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--lk-backend", choices=("auto", "fused", "tensor"), default=None,
                   help="the pyramid's and the LK's kernels (default auto: the fused kernels on the CPU and CUDA, "
                        "OpenCV's bits; tensor: the tensor kernels; docs/kernels.md)")
    _add_threads(p)


def _add_threads(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=_positive_int, default=None, metavar="N",
                   help="torch and OpenCV threads (default: 1, or as OMP_NUM_THREADS says when it is set; "
                        "see docs/cli.md)")


def _add_input_options(p: argparse.ArgumentParser, title: str):
    """``--euroc/--bag/--images`` (repeatable, in order) and the reader options of ``track``/``loop``."""
    src = p.add_argument_group(title)
    src.add_argument("--euroc", dest="sources", action=_SourceAction, const="euroc", metavar="DIR",
                     help="EuRoC / TUM-VI ASL folder (mav0/cam0/data.csv + data/*.png)")
    src.add_argument("--bag", dest="sources", action=_SourceAction, const="bag", metavar="PATH",
                     help="ROS 1 .bag file or ROS 2 bag folder (sensor_msgs/Image or CompressedImage)")
    src.add_argument("--images", dest="sources", action=_SourceAction, const="images", metavar="DIR",
                     help="folder of images (timestamps from numeric names, or --fps)")
    src.add_argument("--config", dest="sources", action=_SourceAction, const="config", metavar="FILE",
                     help="VINS config of the input just before it (--euroc A --config a.yaml --euroc B "
                          "--config b.yaml: each stream its own camera, size and settings); inputs without "
                          "one use CONFIG, else an --euroc folder's own sensor.yaml. Before the first input "
                          "it is CONFIG (then no input may have its own --config)")
    src.add_argument("--rig", dest="sources", action=_SourceAction, const="rig", metavar="FILE",
                     help="YAML list of inputs, each with its config and camera folder: - {euroc: DIR, "
                          "config: FILE, camera: cam1} (also images: DIR, bag: PATH, topic: T, fps: F; paths "
                          "relative to FILE; docs/rigs.md)")
    p.add_argument("--fps", type=_frame_rate, default=None, metavar="F",
                   help="frame rate of --images folders (timestamps i/F)")
    p.add_argument("--topic", default=None, metavar="T",
                   help="image topic of --bag inputs (default: the config's image_topic)")
    p.add_argument("--camera", default="cam0", metavar="CAM",
                   help="camera folder of --euroc inputs (default: cam0)")
    p.add_argument("--skip-bad-frames", action="store_true",
                   help="skip unreadable/corrupt frames instead of stopping (counted in summary.json)")
    p.add_argument("--workers", type=_non_negative_int, default=0, metavar="N",
                   help="decode the frames in N DataLoader worker processes ahead of the tracker "
                        "(default: 0, in the tracking process)")
    _add_timeout(p)
    return src


def _add_track(sub) -> None:
    """``track``: inputs, run options."""
    track = sub.add_parser(
        "track",
        help="track one or more sequences (EuRoC/TUM-VI folders, ROS bags, image folders) and write results",
        description="Track one or more sequences as B streams of one batched tracker and write "
                    "features.csv, features.npz, summary.json, features_per_frame.png, "
                    "track_length_hist.png, track_paths.png and tracks/ into --out. Inputs may be repeated and mixed; "
                    "each is one stream with its own timestamps.",
        epilog="example: torch-frontend track configs/euroc.yaml --euroc MH_01_easy --euroc MH_02_easy "
               "--out out/mh --max-frames 200",
    )
    track.add_argument("config", nargs="?", type=Path, default=None, metavar="CONFIG",
                       help="VINS config YAML (VINS-Mono or VINS-Fusion) of every input without its own "
                            "--config; optional with --euroc, whose own sensor.yaml then gives each "
                            "folder's camera")
    _add_input_options(track, "inputs (repeatable, at least one)")
    _add_run_options(track, None)
    rb = track.add_argument_group("ROS bag output (docs/ros.md)")
    rb.add_argument("--write-bag", default=None, metavar="NAME",
                    help="also write VINS's feature_tracker topics into --out/NAME (NAME.bag: ROS 1, else a "
                         "ROS 2 folder; one per stream: NAME_stream<b>)")
    rb.add_argument("--bag-format", choices=("ros1", "ros2"), default=None,
                    help="bag format, instead of the name's form")
    rb.add_argument("--bag-images", action="store_true", help="add /feature_tracker/feature_img")
    rb.add_argument("--no-bag-imu", action="store_true",
                    help="do not copy the input's IMU (the config's imu_topic; EuRoC imu0/data.csv) into the bag")
    _add_checkpoint_options(track)
    track.set_defaults(func=_cmd_track, flags=_TRACK_FLAGS)


def _add_checkpoint_options(p: argparse.ArgumentParser) -> None:
    """``--checkpoint-every`` and ``--resume`` (``pipelines.checkpoint``)."""
    ck = p.add_argument_group("checkpoints and resuming (long runs; docs/cli.md#checkpoints)")
    ck.add_argument("--checkpoint-every", type=_non_negative_int, default=None, metavar="N",
                    help="write a checkpoint every N frames, inside the run's hidden staging folder beside --out "
                         "(default: every 500 frames or 60 s, whichever first; 0: none)")
    ck.add_argument("--resume", action="store_true",
                    help="continue the interrupted run of this --out (killed, preempted, Ctrl-C) from its last "
                         "checkpoint; the finished outputs equal an uninterrupted run's. Refused, naming what "
                         "differs, when the inputs, config or options differ; with no checkpoint to continue "
                         "from, the run starts from the first frame (a note says so)")


def _add_demo(sub) -> None:
    """``demo`` (and ``demo --loop``)."""
    demo = sub.add_parser(
        "demo",
        help="run on the sample data shipped with the package and print a summary",
        description="Track the 24 sample EuRoC cam0 frames shipped with the package "
                    "(torch_frontend/data/euroc_mini) with configs/euroc.yaml and write the outputs into --out.",
    )
    demo.add_argument("--config", type=Path, default=None, help="VINS config (default: configs/euroc.yaml)")
    _add_run_options(demo, "out/demo")
    demo.add_argument("--flight", action="store_true",
                      help="instead: track a synthetic flight over the package photo (32 frames, the camera "
                           "moving ~2.5 px/frame: tracks that move, see track_paths.png); writes into --out "
                           "(default: out/demo_flight)")
    dloop = demo.add_argument_group("loop closure demo")
    dloop.add_argument("--loop", action="store_true",
                       help="instead: render a synthetic sequence that revisits places (two laps, drifted VIO "
                            "poses, ground truth) and run 'loop' on it; writes the 'loop' outputs into --out "
                            "(default: out/demo_loop)")
    dloop.add_argument("--two-sequences", action="store_true",
                       help="with --loop: the two laps are two sequences (streams) that share one map")
    dloop.add_argument("--separate-graphs", action="store_true",
                       help="with --loop --two-sequences: one pose graph per sequence instead of a shared map")
    demo.set_defaults(func=_cmd_demo, flags=_DEMO_FLAGS)


def _add_loop(sub) -> None:
    """``loop``: inputs with their poses, vocabulary, pose graph and keyframe options."""
    loop = sub.add_parser(
        "loop",
        help="loop closure: images + a VIO trajectory -> loop-corrected trajectory (no ROS)",
        description="Track the images, take keyframes with the given VIO poses (3-D points triangulated "
                    "from the tracks), detect and verify loops (BRIEF bag of words, PnP) and optimise VINS's "
                    "pose graph. Writes vins_result_loop.csv, trajectory_loop.tum, trajectory_vio.tum, "
                    "loops.csv, pose_graph/, summary.json, trajectory_top.png and "
                    "place_recognition_scores.png into --out (per-stream files in stream<b>/ for several "
                    "inputs). Inputs may be repeated, each with its own --poses (same order).",
        epilog="example: torch-frontend loop configs/euroc.yaml --euroc MH_01_easy --poses "
               "vins_result_no_loop.csv --vocabulary brief_k10L6.bin --ground-truth "
               "MH_01_easy/mav0/state_groundtruth_estimate0/data.csv --out out/mh01_loop",
    )
    loop.add_argument("config", nargs="?", type=Path, default=None, metavar="CONFIG",
                      help="VINS config YAML (camera and camera-to-body extrinsic) of every input without its "
                           "own --config; optional with --euroc, whose own sensor.yaml then gives both (a shared "
                           "map needs one extrinsic: inputs with different ones need --separate-graphs)")
    lsrc = _add_input_options(loop, "inputs (repeatable, at least one; one --poses per input)")
    lsrc.add_argument("--poses", action="append", metavar="FILE",
                      help="VIO body poses of the input: VINS csv (vins_result_no_loop.csv), TUM, or EuRoC "
                           "ground truth (format detected)")
    lsrc.add_argument("--ground-truth", action="append", default=None, metavar="FILE",
                      help="reference trajectory of the input (any of the same formats): ATE before/after")
    voc = loop.add_mutually_exclusive_group()
    voc.add_argument("--vocabulary", type=Path, default=None, metavar="FILE",
                     help="BRIEF vocabulary: VINS's brief_k10L6.bin, a .npz from 'vocabulary train', or a "
                          "DBoW2 YAML")
    voc.add_argument("--train-vocabulary", action="store_true",
                     help="train the vocabulary on this run's keyframes (k --train-k, L --train-L)")
    loop.add_argument("--train-k", type=_positive_int, default=10, metavar="K",
                      help="with --train-vocabulary: branching factor (default: 10)")
    loop.add_argument("--train-L", type=_positive_int, default=4, metavar="L",
                      help="with --train-vocabulary: depth (default: 4)")
    loop.add_argument("--load-graph", type=Path, default=None, metavar="DIR",
                      help="start from a saved pose graph (VINS format, e.g. an earlier run's pose_graph/)")
    loop.add_argument("--separate-graphs", action="store_true",
                      help="one pose graph per input instead of one shared map (VINS's multi-sequence merge)")
    loop.add_argument("--pose-graph", choices=("4dof", "6dof"), default="4dof",
                      help="4dof: VIO with IMU (x, y, z, yaw), 6dof: without IMU (default: 4dof)")
    loop.add_argument("--keyframe-distance", type=float, default=0.2, metavar="M",
                      help="new keyframe when the body moved more than M metres ... (default: 0.2)")
    loop.add_argument("--keyframe-angle", type=float, default=10.0, metavar="DEG",
                      help="... or turned more than DEG degrees since the last keyframe (default: 10)")
    loop.add_argument("--keyframe-every", type=_positive_int, default=None, metavar="N",
                      help="instead: every N-th published frame with a pose")
    loop.add_argument("--max-pose-gap", type=_positive_float, default=0.5, metavar="S",
                      help="interpolate poses across gaps of at most S seconds (default: 0.5)")
    loop.add_argument("--pnp", choices=("torch", "opencv"), default="torch",
                      help="loop verification PnP-RANSAC backend (default: torch)")
    loop.add_argument("--tracker-mode", choices=("mono", "fusion"), default="mono",
                      help="front end rules: VINS-Mono or VINS-Fusion tracker (default: mono)")
    loop.add_argument("--max-frames", type=_positive_int, default=None, metavar="N",
                      help="stop after N frames per stream")
    loop.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    loop.add_argument("--device", default=None,
                      help="cpu or cuda (default: cpu; under torchrun cuda:LOCAL_RANK when CUDA is present)")
    loop.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_threads(loop)
    _add_checkpoint_options(loop)
    loop.set_defaults(func=_cmd_loop, flags=_LOOP_FLAGS)


def _add_compare(sub) -> None:
    """``compare``: a reference feature bag against a run."""
    cmp_ = sub.add_parser(
        "compare",
        help="compare a feature bag (e.g. recorded from VINS's feature_tracker_node) with a run",
        description="Per-frame agreement of RUN with the feature bag REFERENCE: frames matched by stamp, "
                    "tracks by first position, a feature agrees when the same track is within --tolerance "
                    "pixels. Writes compare.json, compare.txt and compare.png into --out (docs/ros.md).",
        epilog="example: torch-frontend compare features_vins.bag out/run --out out/compare",
    )
    cmp_.add_argument("reference", type=Path, metavar="REFERENCE", help="feature bag (.bag or ROS 2 folder)")
    cmp_.add_argument("run", type=Path, metavar="RUN",
                      help="a 'track' output folder (its feature bag, else features.npz) or a feature bag")
    cmp_.add_argument("--out", type=Path, default=Path("out/compare"), metavar="DIR",
                      help="report folder (default: out/compare)")
    cmp_.add_argument("--tolerance", type=_positive_float, default=0.1, metavar="PX",
                      help="pixels within which features agree (default: 0.1)")
    cmp_.add_argument("--stream", type=_non_negative_int, default=0, metavar="B",
                      help="stream of a multi-stream RUN (default: 0)")
    cmp_.add_argument("--num-cameras", type=int, choices=(1, 2), default=1,
                      help="id channel encoding: id * N + camera (default: 1, mono)")
    cmp_.set_defaults(func=_cmd_compare, flags={"tolerance": "--tolerance", "stream": "--stream",
                                                "num_cameras": "--num-cameras"})


def _add_vocabulary(sub) -> None:
    """``vocabulary train``."""
    vocab = sub.add_parser(
        "vocabulary",
        help="train a BRIEF bag-of-words vocabulary for loop closure",
        description="Bag-of-words vocabularies (DBoW2-style, VINS's brief_k10L6 layout) for loop closure.",
    )
    vsub = vocab.add_subparsers(dest="vocabulary_command", metavar="SUBCOMMAND")
    vtrain = vsub.add_parser(
        "train",
        help="train a vocabulary on FAST + BRIEF descriptors of images",
        description="Detect FAST corners and BRIEF descriptors (VINS's keyframe rules) in IMAGES and "
                    "train a k-ary, L-level vocabulary by hierarchical k-medians. FILE ending in .bin is "
                    "written in VINS's binary layout (brief_k10L6.bin), anything else in the package's "
                    ".npz format (Vocabulary.load).",
        epilog="example: torch-frontend vocabulary train MH_01/mav0/cam0/data --out voc.npz --max-images 500",
    )
    vtrain.add_argument("images", nargs="+", metavar="IMAGES",
                        help="image files and/or folders of images (sorted by name)")
    vtrain.add_argument("--out", type=Path, required=True, metavar="FILE",
                        help="vocabulary file (.bin: VINS binary; else .npz); its folder must exist")
    vtrain.add_argument("--k", type=int, default=10, help="branching factor (default: 10)")
    vtrain.add_argument("--L", type=int, default=6, help="depth levels (default: 6)")
    vtrain.add_argument("--fast-threshold", type=int, default=20, metavar="T",
                        help="FAST intensity threshold (default: 20, as VINS)")
    vtrain.add_argument("--max-images", type=_positive_int, default=None, metavar="N",
                        help="use N images evenly spaced over the sorted list")
    vtrain.add_argument("--max-keypoints", type=_positive_int, default=None, metavar="N",
                        help="keep the N strongest FAST corners per image (default: all)")
    vtrain.add_argument("--seed", type=int, default=0, help="k-medians seeding (default: 0)")
    vtrain.add_argument("--device", default=None,
                        help="cpu or cuda (default: cpu; under torchrun cuda:LOCAL_RANK when CUDA is present)")
    _add_timeout(vtrain)
    vtrain.add_argument("--no-progress", action="store_true", help="no progress bar")
    vocab.set_defaults(func=_cmd_vocabulary, flags=_VOCABULARY_FLAGS)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torch-frontend",
        description="Batched, differentiable VINS-Mono visual front end (KLT tracker) in PyTorch.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_track, _add_demo, _add_loop, _add_vocabulary, _add_compare):
        add(sub)
    return parser


def _error(msg: str) -> None:
    print(f"torch-frontend: error: {' '.join(str(msg).split())}", file=sys.stderr)


def _option_message(exc: OptionError, flags: Dict[str, str]) -> str:
    """``exc``'s message with its option name (which starts it) and every option named in backticks
    inside it (the library's style: "rerun without `resume`") replaced by the command's flags."""
    msg = str(exc)
    flag = flags.get(exc.option)
    msg = flag + msg[len(exc.option):] if flag and msg.startswith(exc.option) else msg
    # an option named inside the message (library style: in backticks) -> its flag
    return re.sub(r"`([a-z_]+)`", lambda m: flags.get(m.group(1), m.group(0)), msg)


def _os_error_message(exc: OSError, out) -> str:
    """One line for an ``OSError`` that reached the CLI: "cannot write" for the output folder
    ``out``, a file in it or a hidden temporary beside it (or when no file is named), "cannot read"
    for any other file (an input; the readers report their own files as ``DataError``)."""
    name = getattr(exc, "filename", None)
    verb = "write"
    if name is not None and out is not None:
        try:
            target, where = Path(out).resolve(), Path(str(name)).resolve()
            first = where.relative_to(target.parent).parts[:1] if target.parent in where.parents else ()
            if not first or not (first[0] == target.name or first[0].startswith(".")):
                verb = "read"
        except (OSError, RuntimeError, ValueError):  # a name that does not resolve: keep "write"
            pass
    return f"cannot {verb}{f' {name}' if name is not None else ''}: {exc.strerror or exc}"


class _Signalled(KeyboardInterrupt):
    """SIGINT or SIGTERM as a ``KeyboardInterrupt``: every writer cleans up as on Ctrl-C."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_signalled(signum, frame) -> None:
    raise _Signalled(signum)


@contextlib.contextmanager
def _interrupt_signals():
    """SIGINT and SIGTERM raise :class:`_Signalled` inside the block; the previous handlers come
    back after it. A signal ignored by whoever started us (``nohup``, a background job) stays
    ignored; outside the main thread nothing changes."""
    saved = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            prev = signal.getsignal(sig)
            if prev is signal.SIG_IGN:
                continue
            signal.signal(sig, _raise_signalled)
        except ValueError:  # not the main thread
            continue
        saved[sig] = signal.SIG_DFL if prev is None else prev
    try:
        yield
    finally:
        for sig, prev in saved.items():
            signal.signal(sig, prev)


@contextlib.contextmanager
def _config_warnings():
    """A config's ``ConfigWarning`` (an unknown key, "did you mean ...?") as one stderr line
    ``torch-frontend: warning: ...`` and an input's ``DataWarning`` (colour frames made grey) as
    ``torch-frontend: note: ...`` inside the block; other warnings as Python prints them."""
    import warnings

    from .errors import ConfigWarning, DataWarning

    shown = warnings.showwarning
    rank = _rank()

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, ConfigWarning):
            if rank == 0:  # under torchrun every rank reads the config: rank 0 says it once
                print(f"torch-frontend: warning: {message}", file=sys.stderr)
        elif issubclass(category, DataWarning):
            print(f"torch-frontend: note: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = shown


def _rank() -> int:
    """This process's rank under a launcher (0 without one)."""
    from .distributed.env import dist_env

    try:
        return dist_env().rank
    except ValueError:  # a malformed RANK: let the command report it
        return 0


def main(argv: List[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    from .distributed.job import JobAborted, RankFailure

    # Under torchrun every rank runs this: an error every rank meets (a bad option, config or
    # output folder) is printed by rank 0 only; a rank's own failure by that rank, rank 0 adding
    # the job's one-line report (pipelines.sharded).
    rank = _rank()

    def error(exc: BaseException, msg: str) -> None:
        if rank == 0 or getattr(exc, "rank_error", False):
            _error(msg if rank == 0 or msg.startswith("rank ") else f"rank {rank}: {msg}")

    try:
        threads = _thread_policy(args.threads) if hasattr(args, "threads") else contextlib.nullcontext()
        with _interrupt_signals(), threads, _config_warnings():
            return int(args.func(args) or 0)
    except (ConfigError, _UsageError) as exc:
        error(exc, str(exc))
        return EXIT_USAGE
    except OptionError as exc:
        error(exc, _option_message(exc, getattr(args, "flags", {})))
        return EXIT_USAGE
    except RankFailure as exc:
        error(exc, f"{exc}; no merged summary written")
        return exc.exit_code
    except DataError as exc:
        error(exc, str(exc))
        return EXIT_DATA
    except JobAborted as exc:
        if not exc.quiet:
            error(exc, str(exc))
        return EXIT_DATA
    except KeyboardInterrupt as exc:
        term = getattr(exc, "signum", signal.SIGINT) == signal.SIGTERM
        detail = getattr(exc, "detail", None)
        msg = (f"interrupted{' (SIGTERM)' if term else ''}: no partial output left (the output folder holds "
               f"its previous complete outputs, or this run's if it had finished writing them)")
        if getattr(exc, "resumable", False):
            msg = (f"interrupted{' (SIGTERM)' if term else ''}: the output folder holds its previous complete outputs; "
                   f"this run's last checkpoint is kept: rerun the same command with --resume to continue from it")
        if detail:  # a sharded run: who had not finished (torchrun stops every rank when one dies)
            msg = (f"interrupted{' (SIGTERM)' if term else ''}: {detail}; no merged summary written (complete "
                   f"per-input outputs stay)")
        error(exc, msg)
        return EXIT_TERMINATED if term else EXIT_INTERRUPTED
    except OSError as exc:  # e.g. --out is a file, a read-only folder, a full disk; an unreadable input
        error(exc, _os_error_message(exc, getattr(args, "out", None)))
        return EXIT_DATA


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
