"""The ``torch-frontend`` command line: ``track``, ``demo`` and ``vocabulary train``.

``torch-frontend track [CONFIG] (--euroc DIR | --bag PATH | --images DIR)... --out DIR`` runs the
VINS front end on one or more sequences at once (B streams in one batched tracker) and writes
``features.csv``, ``features.npz``, ``summary.json``, two plots and ``tracks/`` into ``--out``
(see ``torch_frontend.outputs``). ``torch-frontend demo`` does the same on the sample EuRoC frames
shipped with the package.

``torch-frontend loop [CONFIG] (--euroc DIR | --images DIR | --bag FILE)... --poses FILE... --out DIR
(--vocabulary FILE | --train-vocabulary)`` runs loop closure (VINS's pose graph) on images plus
their VIO poses and writes the loop-corrected trajectory, the loops, the pose graph, a summary and
plots (``torch_frontend.loop.run``, ``torch_frontend.loop.report``); ``torch-frontend demo --loop``
does the same on a rendered sequence that revisits places.

User errors (missing or unreadable input, a bad config, a bag without the topic, an image of the
wrong size, an empty sequence) print one line ``torch-frontend: error: ...`` on stderr and exit
with a non-zero code: 2 for usage and config errors, 1 for data errors, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

from .errors import ConfigError
from .io.frames import DataError

PACKAGE_DIR = Path(__file__).resolve().parent
SAMPLE_DIR = PACKAGE_DIR / "data" / "euroc_mini"

EXIT_DATA = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def default_config_path() -> Path:
    """The EuRoC config: ``configs/euroc.yaml`` of a source checkout, else the packaged copy."""
    for p in (PACKAGE_DIR.parent / "configs" / "euroc.yaml", PACKAGE_DIR / "data" / "configs" / "euroc.yaml"):
        if p.is_file():
            return p
    raise ConfigError("cannot find configs/euroc.yaml (looked beside the package)")


class _UsageError(Exception):
    """Bad command-line combination (printed as one line, exit 2)."""


# ----------------------------------------------------------------------------------------------
# the run


def _resolve_device(device: str):
    import torch

    if device.startswith("cuda") and not torch.cuda.is_available():
        raise _UsageError(f"--device {device}: CUDA is not available on this machine (use --device cpu)")
    try:
        return torch.device(device)
    except RuntimeError:
        raise _UsageError(f"--device: expected cpu or cuda, got {device!r}") from None


def resolve_config(config: Path | None, sources: Sequence[Tuple[str, str]], camera: str = "cam0"):
    """The ``TrackerConfig`` of a run: ``config`` if given, else the ``sensor.yaml`` of the first
    ``--euroc`` input (VINS's EuRoC front-end settings)."""
    from .config import load_config

    if config is not None:
        cfg = load_config(config)
    else:
        euroc = [p for k, p in sources if k == "euroc"]
        if not euroc:
            raise _UsageError("no CONFIG given: a VINS config file is needed unless an --euroc folder "
                              "provides sensor.yaml")
        from .io.euroc import euroc_config

        cfg = euroc_config(euroc[0], camera)
    if cfg.camera is None:
        raise ConfigError("has no camera (an estimator-only config?); the tracker needs one", cfg.path)
    return cfg


def run_track(
    config,
    sources: Sequence[Tuple[str, str]],
    out,
    *,
    device: str = "cpu",
    mode: str = "mono",
    max_frames: int | None = None,
    fps: float | None = None,
    topic: str | None = None,
    camera: str = "cam0",
    skip_bad_frames: bool = False,
    write_tracks: bool = True,
    progress: bool | None = None,
) -> Dict[str, Any]:
    """Track ``sources`` (``[(kind, path)]``, kind in ``euroc``, ``bag``, ``images``) as B streams
    and write the outputs into ``out``. Returns the summary dict (also in ``summary.json``).

    Args:
        config: a ``TrackerConfig``, a config path, or None (``sensor.yaml`` of the first --euroc).
        max_frames: at most this many steps (frames per stream).
        progress: tqdm bar on stderr (None: only on a terminal).

    Raises:
        DataError, ConfigError: user errors; ``KeyboardInterrupt`` passes through after cleanup.
    """
    import torch

    from .config import TrackerConfig
    from .io import MultiStream, open_sequence
    from .outputs import RunRecorder

    if not sources:
        raise _UsageError("no input: give at least one --euroc DIR, --bag PATH or --images DIR")
    if max_frames is not None and max_frames < 1:
        raise _UsageError(f"--max-frames must be >= 1, got {max_frames}")
    if mode not in ("mono", "fusion"):
        raise _UsageError(f"--mode: expected mono or fusion, got {mode!r}")
    dev = _resolve_device(device)
    cfg = config if isinstance(config, TrackerConfig) else resolve_config(
        None if config is None else Path(config), sources, camera)
    seqs = [
        open_sequence(kind, path, camera=camera, fps=fps, topic=topic or cfg.image_topic or None,
                      skip_bad=skip_bad_frames)
        for kind, path in sources
    ]
    stream = MultiStream(seqs, size=(cfg.image_height, cfg.image_width), max_steps=max_frames)

    from .tracker import FeatureTracker

    tracker = FeatureTracker(cfg, num_streams=len(seqs), device=dev, mode=mode)
    names = [f"{s.kind}:{s.name}" for s in seqs]
    total = sum(len(s) if max_frames is None else min(len(s), max_frames) for s in seqs)
    bar = None
    if progress is not False:
        from tqdm import tqdm

        # a pty that reports a 0 x 0 size makes tqdm hide the bar: fall back to 100 x 20
        size = shutil.get_terminal_size((100, 20))
        bar = tqdm(total=total, unit="frame", desc="tracking", disable=None if progress is None else False,
                   file=sys.stderr, ncols=min(120, size.columns), nrows=size.lines, leave=False)
    steps = 0
    tracker_seconds = 0.0
    with RunRecorder(out, names, write_tracks=write_tracks) as rec:
        t0 = time.perf_counter()
        try:
            for batch in stream:
                t1 = time.perf_counter()
                frame = tracker.track(batch.images.to(dev), batch.timestamps, active=batch.alive.to(dev))
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                tracker_seconds += time.perf_counter() - t1
                rec.add(batch, frame)
                steps += 1
                if bar is not None:
                    bar.update(int(batch.alive.sum()))
        finally:
            if bar is not None:
                bar.close()
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        seconds = time.perf_counter() - t0
        summary = rec.summary(
            seconds,
            stream.skipped,
            extra={
                "steps": steps,
                "tracker_seconds": round(tracker_seconds, 6),
                "config": str(cfg.path),
                "mode": mode,
                "device": str(dev),
                "inputs": [{"kind": k, "path": str(p), "frames_listed": len(s)} for (k, p), s in zip(sources, seqs)],
                "out": str(Path(out)),
            },
        )
        rec.write(summary)
    return summary


def format_summary(s: Dict[str, Any]) -> str:
    """The few lines ``track``/``demo`` print."""
    lines = [
        f"streams       {s['streams']}   frames {s['frames']}   steps {s.get('steps', '?')}   "
        f"published frames {s['published']}",
        f"features      {s['published_features']} published, {s['mean_features']:.1f} per published frame",
        f"tracks        {s['tracks']}   mean length {s['mean_track_length']:.2f}   "
        f"median {s['median_track_length']:g} frames",
        f"speed         {s['frames_per_second']:.1f} frames/s ({s['seconds']:.2f} s on {s.get('device', '?')}, "
        f"mode {s.get('mode', '?')})",
        f"skipped       {s['skipped_bad_frames']} bad frames",
    ]
    for k in s.get("skipped", [])[:5]:
        lines.append(f"              stream {k['stream']}: {k['reason']}")
    if "out" in s:
        lines.append(f"outputs       {s['out']}/ (features.csv, features.npz, summary.json, "
                     f"features_per_frame.png, track_length_hist.png, tracks/)")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# commands


def _cmd_track(args: argparse.Namespace) -> int:
    summary = run_track(
        args.config, args.sources or [], args.out, device=args.device, mode=args.mode,
        max_frames=args.max_frames, fps=args.fps, topic=args.topic, camera=args.camera,
        skip_bad_frames=args.skip_bad_frames, write_tracks=not args.no_tracks,
        progress=False if args.no_progress else None,
    )
    print(format_summary(summary))
    return 0


def _cmd_loop(args: argparse.Namespace) -> int:
    from .loop.run import format_loop_summary, run_loop

    sources = args.sources or []
    poses = args.poses or []
    gts = args.ground_truth
    if not sources:
        raise _UsageError("no input: give at least one --euroc DIR, --images DIR or --bag FILE")
    if len(poses) != len(sources):
        raise _UsageError(f"--poses: expected one poses file per input, in the same order ({len(sources)} "
                          f"input{'s' if len(sources) != 1 else ''}), got {len(poses)}")
    if gts is not None and len(gts) != len(sources):
        raise _UsageError(f"--ground-truth: expected one file per input, in the same order ({len(sources)} "
                          f"input{'s' if len(sources) != 1 else ''}), got {len(gts)}")
    if args.vocabulary is None and not args.train_vocabulary:
        raise _UsageError("no vocabulary: give --vocabulary FILE (VINS's brief_k10L6.bin, or a .npz from "
                          "'torch-frontend vocabulary train') or --train-vocabulary")
    if args.max_frames is not None and args.max_frames < 1:
        raise _UsageError(f"--max-frames must be >= 1, got {args.max_frames}")
    dev = _resolve_device(args.device)
    run = run_loop(
        args.config, sources, poses, args.out, vocabulary=args.vocabulary, train_vocabulary=args.train_vocabulary,
        vocabulary_k=args.train_k, vocabulary_L=args.train_L, load_graph=args.load_graph, ground_truth=gts,
        separate_graphs=args.separate_graphs, mode=args.pose_graph, device=dev, tracker_mode=args.tracker_mode,
        keyframe_distance=args.keyframe_distance, keyframe_angle=args.keyframe_angle,
        keyframe_every=args.keyframe_every, max_pose_gap=args.max_pose_gap, pnp_backend=args.pnp,
        max_frames=args.max_frames, fps=args.fps, topic=args.topic, camera=args.camera,
        skip_bad_frames=args.skip_bad_frames, progress=False if args.no_progress else None,
    )
    print(format_loop_summary(run.summary))
    return 0


def _cmd_demo_loop(args: argparse.Namespace) -> int:
    import torch

    from .loop.run import DEMO_RENDER, demo_loop, format_loop_summary

    # One intra-op thread: the demo's tensors are small (320x240 images, ~100 points), so extra
    # threads only add synchronisation, and on a busy machine each of the tracker's many small ops
    # then waits for a descheduled thread (measured: > 10 min instead of ~40 s with 2 threads
    # while another process kept one of 2 cores busy).
    torch.set_num_threads(1)
    out = Path("out/demo_loop") if args.out == Path("out/demo") else args.out
    print(f"demo          synthetic revisit sequence: {DEMO_RENDER['laps']} laps x {DEMO_RENDER['keyframes_per_lap']} "
          f"keyframes, {DEMO_RENDER['width']}x{DEMO_RENDER['height']}, drifted VIO poses, ground truth")
    run = demo_loop(out, two_sequences=args.two_sequences, separate_graphs=args.separate_graphs,
                    device=str(_resolve_device(args.device)), progress=False if args.no_progress else None,
                    run_kwargs={"tracker_mode": args.mode})
    print(format_loop_summary(run.summary))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .config import load_config

    if args.loop:
        return _cmd_demo_loop(args)
    if args.two_sequences or args.separate_graphs:
        raise _UsageError("--two-sequences and --separate-graphs go with --loop")
    cfg = load_config(args.config or default_config_path())
    print(cfg.summary())
    print(f"\nsample        {SAMPLE_DIR} (cam0)")
    summary = run_track(
        cfg, [("euroc", str(SAMPLE_DIR))], args.out, device=args.device, mode=args.mode,
        max_frames=args.max_frames, write_tracks=not args.no_tracks,
        progress=False if args.no_progress else None,
    )
    print(format_summary(summary))
    return 0


def _vocabulary_images(inputs: Sequence[str]) -> List[Path]:
    """The image files of ``vocabulary train``: files as given, folders' images sorted by name."""
    from .io.frames import IMAGE_SUFFIXES

    files: List[Path] = []
    for raw in inputs:
        p = Path(raw)
        if p.is_dir():
            found = sorted(f for f in p.iterdir()
                           if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith("."))
            if not found:
                raise DataError(f"{p}: no images in folder (looked for {'/'.join(x[1:] for x in IMAGE_SUFFIXES)})")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise DataError(f"{p}: no such image file or folder")
    return files


def run_vocabulary_train(
    images: Sequence[str],
    out,
    *,
    k: int = 10,
    L: int = 6,
    fast_threshold: int = 20,
    max_images: int | None = None,
    max_keypoints: int | None = None,
    seed: int = 0,
    device: str = "cpu",
    progress: bool | None = None,
    chunk: int = 8,
) -> Dict[str, Any]:
    """Train a BRIEF vocabulary (``loop.Vocabulary``) on FAST + BRIEF descriptors of ``images``
    (files and/or folders) and save it to ``out`` (``.bin``: VINS's binary layout, else the
    package's ``.npz`` format), atomically. Returns a summary dict.

    Images of one size are described in chunks of ``chunk`` through ``loop.fast`` / ``loop.brief``;
    ``max_images`` keeps that many evenly spaced images of the sorted list; ``max_keypoints`` keeps
    the strongest FAST corners per image (default: all, as VINS).
    """
    import numpy as np
    import torch

    from .io.frames import read_image
    from .loop import Vocabulary, brief, fast

    if k < 2:
        raise _UsageError(f"--k must be >= 2, got {k}")
    if L < 1:
        raise _UsageError(f"--L must be >= 1, got {L}")
    out = Path(out)
    if out.is_dir():
        raise _UsageError(f"--out {out}: is a folder, expected a vocabulary file name")
    if not out.parent.is_dir():
        raise _UsageError(f"--out {out}: folder {out.parent} does not exist")
    dev = _resolve_device(device)
    files = _vocabulary_images(images)
    if max_images is not None and max_images < len(files):
        files = [files[int(i)] for i in np.linspace(0, len(files) - 1, max_images).round().astype(int)]

    bar = None
    if progress is not False:
        from tqdm import tqdm

        size = shutil.get_terminal_size((100, 20))
        bar = tqdm(total=len(files), unit="image", desc="describing", disable=None if progress is None else False,
                   file=sys.stderr, ncols=min(120, size.columns), nrows=size.lines, leave=False)
    t0 = time.perf_counter()
    descs: List[torch.Tensor] = []  # per image (K_i, 4) int64, valid descriptors only

    def describe(batch: List[np.ndarray]) -> None:
        img = torch.from_numpy(np.stack(batch)).to(dev)  # (b, H, W) uint8
        pts, _, valid = fast(img, threshold=fast_threshold, max_points=max_keypoints)
        d = brief(img, pts, valid)
        for b in range(d.shape[0]):
            descs.append(d[b][valid[b]])
        if bar is not None:
            bar.update(len(batch))

    try:
        pending: List[np.ndarray] = []
        for f in files:
            im = read_image(f)
            if pending and (im.shape != pending[0].shape or len(pending) >= chunk):
                describe(pending)
                pending = []
            pending.append(im)
        if pending:
            describe(pending)
    finally:
        if bar is not None:
            bar.close()
    n_desc = sum(int(d.shape[0]) for d in descs)
    if n_desc == 0:
        raise DataError(f"no FAST corners (threshold {fast_threshold}) in any of the {len(files)} images")
    Kmax = max(int(d.shape[0]) for d in descs)
    D = len(descs)
    desc = torch.zeros(D, Kmax, 4, dtype=torch.int64, device=dev)
    valid = torch.zeros(D, Kmax, dtype=torch.bool, device=dev)
    for i, d in enumerate(descs):
        desc[i, :d.shape[0]] = d
        valid[i, :d.shape[0]] = True
    t_desc = time.perf_counter() - t0
    gen = torch.Generator(device=dev).manual_seed(int(seed))
    # Vocabulary.train reports its levels on stdout: only alongside a visible progress bar
    verbose = bar is not None and not bar.disable
    voc = Vocabulary.train(desc, valid, k=k, L=L, generator=gen, progress=verbose)
    if out.suffix.lower() == ".bin":
        voc.save_vins_bin(out)
    else:
        voc.save(out)
    seconds = time.perf_counter() - t0
    return {"images": D, "descriptors": n_desc, "words": int(voc.num_words), "nodes": int(voc.num_nodes),
            "k": k, "L": L, "seconds": round(seconds, 3), "describe_seconds": round(t_desc, 3),
            "out": str(out), "device": str(dev)}


def _cmd_vocabulary(args: argparse.Namespace) -> int:
    if args.vocabulary_command != "train":
        raise _UsageError("vocabulary: expected a subcommand: train")
    s = run_vocabulary_train(
        args.images, args.out, k=args.k, L=args.L, fast_threshold=args.fast_threshold,
        max_images=args.max_images, max_keypoints=args.max_keypoints, seed=args.seed, device=args.device,
        progress=False if args.no_progress else None,
    )
    print(f"vocabulary    {s['words']} words (k={s['k']}, L={s['L']}) from {s['descriptors']} descriptors "
          f"of {s['images']} images in {s['seconds']:.2f} s -> {s['out']}")
    return 0


class _SourceAction(argparse.Action):
    """``--euroc/--bag/--images``: appended, in command-line order, as ``(kind, path)``."""

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
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--mode", choices=("mono", "fusion"), default="mono",
                   help="VINS-Mono feature_tracker or VINS-Fusion tracker rules (default: mono)")
    p.add_argument("--max-frames", type=_positive_int, default=None, metavar="N",
                   help="stop after N frames per stream")
    p.add_argument("--no-tracks", action="store_true", help="do not draw track images (tracks/)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_input_options(p: argparse.ArgumentParser, title: str):
    """``--euroc/--bag/--images`` (repeatable, in order) and the reader options of ``track``/``loop``."""
    src = p.add_argument_group(title)
    src.add_argument("--euroc", dest="sources", action=_SourceAction, const="euroc", metavar="DIR",
                     help="EuRoC / TUM-VI ASL folder (mav0/cam0/data.csv + data/*.png)")
    src.add_argument("--bag", dest="sources", action=_SourceAction, const="bag", metavar="PATH",
                     help="ROS 1 .bag file or ROS 2 bag folder (sensor_msgs/Image or CompressedImage)")
    src.add_argument("--images", dest="sources", action=_SourceAction, const="images", metavar="DIR",
                     help="folder of images (timestamps from numeric names, or --fps)")
    p.add_argument("--fps", type=_positive_float, default=None, metavar="F",
                   help="frame rate of --images folders (timestamps i/F)")
    p.add_argument("--topic", default=None, metavar="T",
                   help="image topic of --bag inputs (default: the config's image_topic)")
    p.add_argument("--camera", default="cam0", metavar="CAM",
                   help="camera folder of --euroc inputs (default: cam0)")
    p.add_argument("--skip-bad-frames", action="store_true",
                   help="skip unreadable/corrupt frames instead of stopping (counted in summary.json)")
    return src


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torch-frontend",
        description="Batched, differentiable VINS-Mono visual front end (KLT tracker) in PyTorch.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    track = sub.add_parser(
        "track",
        help="track one or more sequences (EuRoC/TUM-VI folders, ROS bags, image folders) and write results",
        description="Track one or more sequences as B streams of one batched tracker and write "
                    "features.csv, features.npz, summary.json, features_per_frame.png, "
                    "track_length_hist.png and tracks/ into --out. Inputs may be repeated and mixed; "
                    "each is one stream with its own timestamps.",
        epilog="example: torch-frontend track configs/euroc.yaml --euroc MH_01_easy --euroc MH_02_easy "
               "--out out/mh --max-frames 200",
    )
    track.add_argument("config", nargs="?", type=Path, default=None, metavar="CONFIG",
                       help="VINS config YAML (VINS-Mono or VINS-Fusion); optional with --euroc, whose "
                            "sensor.yaml then gives the camera")
    _add_input_options(track, "inputs (repeatable, at least one)")
    _add_run_options(track, None)
    track.set_defaults(func=_cmd_track)

    demo = sub.add_parser(
        "demo",
        help="run on the sample data shipped with the package and print a summary",
        description="Track the 24 sample EuRoC cam0 frames shipped with the package "
                    f"({SAMPLE_DIR}) with configs/euroc.yaml and write the outputs into --out.",
    )
    demo.add_argument("--config", type=Path, default=None, help="VINS config (default: configs/euroc.yaml)")
    _add_run_options(demo, "out/demo")
    dloop = demo.add_argument_group("loop closure demo")
    dloop.add_argument("--loop", action="store_true",
                       help="instead: render a synthetic sequence that revisits places (two laps, drifted VIO "
                            "poses, ground truth) and run 'loop' on it; writes the 'loop' outputs into --out "
                            "(default: out/demo_loop)")
    dloop.add_argument("--two-sequences", action="store_true",
                       help="with --loop: the two laps are two sequences (streams) that share one map")
    dloop.add_argument("--separate-graphs", action="store_true",
                       help="with --loop --two-sequences: one pose graph per sequence instead of a shared map")
    demo.set_defaults(func=_cmd_demo)

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
                      help="VINS config YAML (camera and camera-to-body extrinsic); optional with --euroc, "
                           "whose sensor.yaml then gives both")
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
    loop.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    loop.add_argument("--no-progress", action="store_true", help="no progress bar")
    loop.set_defaults(func=_cmd_loop)

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
    vtrain.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    vtrain.add_argument("--no-progress", action="store_true", help="no progress bar")
    vocab.set_defaults(func=_cmd_vocabulary)
    return parser


def _error(msg: str) -> None:
    print(f"torch-frontend: error: {' '.join(str(msg).split())}", file=sys.stderr)


def main(argv: List[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args) or 0)
    except (ConfigError, _UsageError) as exc:
        _error(str(exc))
        return EXIT_USAGE
    except DataError as exc:
        _error(str(exc))
        return EXIT_DATA
    except KeyboardInterrupt:
        _error("interrupted (no partial file left in the output folder)")
        return EXIT_INTERRUPTED
    except OSError as exc:  # e.g. --out is a file, a read-only folder, a full disk
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        _error(f"cannot write{where}: {exc.strerror or exc}")
        return EXIT_DATA


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
