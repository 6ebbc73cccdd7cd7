"""The parser: every command's flags (``build_parser``), and which flag sets which pipeline option
(for ``OptionError`` messages)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..loop.world import UP_AXES
from .commands import _cmd_compare, _cmd_config, _cmd_demo, _cmd_loop, _cmd_ros, _cmd_track, _cmd_vocabulary

# option name of a pipeline -> the flag that sets it, per command (for OptionError messages)
_INPUT_FLAGS = {"max_frames": "--max-frames", "device": "--device", "fps": "--fps", "topic": "--topic",
                "camera": "--camera", "workers": "--workers", "skip_bad_frames": "--skip-bad-frames"}
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
    "pnp_backend": "--pnp", "checkpoint_every": "--checkpoint-every", "resume": "--resume", "up": "--up",
}
_ROS_FLAGS = {"device": "--device", "lk_backend": "--lk-backend", "queue_size": "--queue-size",
              "sync_wait": "--sync-wait", "max_frames": "--max-frames", "cameras": "CONFIG"}
_CONFIG_FLAGS = {"kalibr": "--from-kalibr", "camera_info": "--from-camera-info", "imu": "--imu", "out": "--out"}
_VOCABULARY_FLAGS = {"out": "--out", "k": "--k", "L": "--L", "fast_threshold": "--fast-threshold",
                     "max_images": "--max-images", "max_keypoints": "--max-keypoints", "seed": "--seed",
                     "device": "--device"}



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
    src.add_argument("--kitti", dest="sources", action=_SourceAction, const="kitti", metavar="SEQ",
                     help="KITTI odometry sequence (sequences/NN: image_0/, calib.txt, times.txt) or raw drive "
                          "(*_sync: image_00/, calib_cam_to_cam.txt); no config needed: the camera from P0 "
                          "(--camera cam1..cam3: P1..P3), VINS-Mono's front-end defaults, which a --config "
                          "after it replaces (its front-end keys; docs/datasets.md)")
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
                   help="camera folder of --euroc inputs, camera of --kitti inputs (default: cam0)")
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
                            "folder's camera, and with --kitti (calib.txt)")
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
                           "own --config; optional with --euroc, whose own sensor.yaml then gives both, and with "
                           "--kitti (calib.txt; body = camera 0) (a shared "
                           "map needs one extrinsic: inputs with different ones need --separate-graphs)")
    lsrc = _add_input_options(loop, "inputs (repeatable, at least one; one --poses per input)")
    lsrc.add_argument("--poses", action="append", metavar="FILE",
                      help="VIO body poses of the input: VINS csv (vins_result_no_loop.csv), TUM, EuRoC "
                           "ground truth or KITTI (poses/NN.txt: line k at the input's image k; format detected)")
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
    loop.add_argument("--pose-graph", choices=("4dof", "6dof"), default=None,
                      help="4dof: VIO with IMU (x, y, z, yaw about --up), 6dof: without IMU (default: 4dof; "
                           "6dof when an input is --kitti, which has no IMU)")
    loop.add_argument("--up", choices=UP_AXES, default=None,
                      help="the poses' world axis that points up (against gravity): the 4dof graph's yaw axis and "
                           "the plots' viewing axis (default: +z; -y when every input is --kitti, whose camera-0 "
                           "world has y down)")
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


def _non_negative_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (v >= 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {s}")
    return v


def _add_ros(sub) -> None:
    """``ros``: the live ROS 1 node (``pipelines.ros_node``)."""
    ros = sub.add_parser(
        "ros",
        help="live ROS 1 node: VINS-Mono's feature_tracker_node for one or more cameras (docs/ros.md)",
        description="Subscribe to each camera's image topic and publish VINS's feature, feature_img and restart "
                    "topics live (the master from ROS_MASTER_URI). One CONFIG: /feature_tracker/feature, "
                    "/feature_tracker/feature_img, /feature_tracker/restart, as VINS-Mono's node; several: one "
                    "batched tracker, each camera's topics under its image topic's namespace "
                    "(/cam0/image_raw -> /cam0/feature_tracker/feature). Runs until Ctrl-C or SIGTERM (exit 0) "
                    "and prints a summary (frames, drops, latency). ROS remapping arguments (name:=value, "
                    "__ns:=NS, __name:=NAME) go to rospy.",
        epilog="example: torch-frontend ros configs/euroc.yaml   (beside rosrun vins_estimator ...; "
               "two cameras: torch-frontend ros a.yaml@/cam0/image_raw a.yaml@/cam1/image_raw)",
    )
    ros.add_argument("configs", nargs="+", metavar="CONFIG",
                     help="VINS-Mono config of a camera, subscribed to its image_topic; CONFIG@TOPIC: to TOPIC "
                          "instead (one config for several cameras)")
    ros.add_argument("--device", default=None, help="cpu or cuda (default: cpu)")
    ros.add_argument("--lk-backend", choices=("auto", "fused", "tensor"), default=None,
                     help="the pyramid's and the LK's kernels (default auto; docs/kernels.md)")
    ros.add_argument("--queue-size", type=_positive_int, default=4, metavar="N",
                     help="frames queued per camera at most; a frame arriving at a full queue drops the oldest "
                          "(default: 4)")
    ros.add_argument("--sync-wait", type=_non_negative_float, default=0.0, metavar="MS",
                     help="with several cameras: a step waits up to MS milliseconds for every camera to have a "
                          "frame (default: 0, step with the cameras that have one)")
    ros.add_argument("--latency", action="store_true",
                     help="publish each frame's latency on <prefix>/latency (std_msgs/Float64MultiArray: stamp_sec, "
                          "stamp_nsec, latency_ms, median_ms, p95_ms, max_ms, dropped, sent, restarted)")
    ros.add_argument("--summary", type=Path, default=None, metavar="FILE",
                     help="also write the exit summary as JSON into FILE")
    ros.add_argument("--max-frames", type=_positive_int, default=None, metavar="N",
                     help="stop after N tracked frames in all (default: until stopped)")
    _add_threads(ros)
    ros.set_defaults(func=_cmd_ros, flags=_ROS_FLAGS)


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


def _add_config(sub) -> None:
    """``config``: a VINS config from calibration files."""
    cfg = sub.add_parser(
        "config",
        help="write a VINS config from a Kalibr camchain or a ROS camera_info YAML",
        description="Write a VINS config from calibration files: one camera gives a VINS-Mono config, two a "
                    "VINS-Fusion config (FILE and FILE_cam0.yaml, FILE_cam1.yaml beside it). Kalibr pinhole-radtan "
                    "-> PINHOLE, pinhole-equi -> KANNALA_BRANDT, omni-radtan -> MEI (ds, eucm and fov have no "
                    "camodocal model: refused); camchain-imucam.yaml's T_cam_imu becomes VINS's body <- camera "
                    "extrinsic; camera_info: plumb_bob (k3 = 0) -> PINHOLE, equidistant -> KANNALA_BRANDT. Every "
                    "other key at VINS's defaults. A file that exists is replaced only when this command wrote it.",
        epilog="example: torch-frontend config --from-kalibr camchain-imucam.yaml --imu imu.yaml --out my_vins.yaml",
    )
    src = cfg.add_mutually_exclusive_group(required=True)
    src.add_argument("--from-kalibr", type=Path, default=None, metavar="CAMCHAIN",
                     help="Kalibr's camchain.yaml or camchain-imucam.yaml (1 or 2 cameras)")
    src.add_argument("--from-camera-info", type=Path, default=None, metavar="YAML",
                     help="a ROS camera_calibration camera_info YAML (ost.yaml; one camera)")
    cfg.add_argument("--imu", type=Path, default=None, metavar="IMU_YAML",
                     help="Kalibr's imu.yaml: the IMU noise (acc_n, gyr_n, acc_w, gyr_w) and imu_topic "
                          "(default: VINS's EuRoC values)")
    cfg.add_argument("--out", type=Path, default=Path("vins_config.yaml"), metavar="FILE",
                     help="the config file to write (default: vins_config.yaml)")
    cfg.set_defaults(func=_cmd_config, flags=_CONFIG_FLAGS)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torch-frontend",
        description="Batched, differentiable VINS-Mono visual front end (KLT tracker) in PyTorch.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_track, _add_demo, _add_loop, _add_vocabulary, _add_compare, _add_ros, _add_config):
        add(sub)
    return parser
