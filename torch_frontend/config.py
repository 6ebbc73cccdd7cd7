"""VINS configuration files (``load_config``: VINS-Mono and VINS-Fusion; ``load_camera``) and ASL
``sensor.yaml`` camera files (``config_from_sensor_yaml``).

Convention:
    Keys keep their VINS names (``max_cnt``, ``min_dist``, ``F_threshold``, ...). Values are read
    as VINS reads them (spec §1): ``freq: 0`` means 100 Hz for VINS-Mono, a missing flag
    (``equalize``, ``fisheye``, ``flow_back``, ``show_track``) is 0. VINS-Fusion's ``cam0_calib`` /
    ``cam1_calib`` are resolved relative to the config file's folder. Every key of the file,
    known or not, is kept in ``TrackerConfig.raw``.

A VINS-Mono config (a camodocal block in the same file) must give ``image_width``,
``image_height``, ``max_cnt`` and ``min_dist``; a VINS-Fusion config (``cam0_calib``) must give
``image_width`` and ``image_height`` (``max_cnt``/``min_dist`` read as 0 when absent, as in VINS, and
``FeatureTracker`` then refuses the config by name). A config with neither (an estimator-only config such as VINS's simulation config)
loads with ``camera=None`` and the tracker keys left at their defaults.

Keys: the top-level keys of a config or camera file are checked against ``KNOWN_KEYS``: every key
VINS-Mono's and VINS-Fusion's nodes read (front end, estimator, pose graph, camodocal camera;
spec §1.2-§1.6), known or not to this front end, and ``F_method``. The keys the front end does not
use (``acc_n``, ``td``, ``output_path``, ...) are ignored silently, as VINS's other nodes read
them. Any other key is ignored with a ``ConfigWarning``: "unknown key `equalise` in <file>: did
you mean `equalize`?" for a near-miss of a known key (``difflib``, letter case ignored), "not a
key VINS reads" otherwise. A key given twice is a ``ConfigError`` naming both lines
(``opencv_yaml``). The keys inside the camera's parameter maps are checked by the camera models
(a missing one is an error).

Without a VINS config, an ASL (EuRoC / TUM-VI) camera's ``sensor.yaml`` (Kalibr format) gives the
camera: ``resolution: [W, H]``, ``intrinsics: [fu, fv, cu, cv]`` and ``distortion_model`` +
``distortion_coefficients``: ``radial-tangential`` ``[k1, k2, p1, p2]`` -> ``PinholeCamera``;
``equidistant`` ``[k1..k4]`` (TUM-VI) -> ``KannalaBrandtCamera`` with camodocal ``k2..k5 = k1..k4``
(``camera_from_sensor_yaml``). ``config_from_sensor_yaml`` wraps it in a ``TrackerConfig`` with
VINS-Mono's EuRoC front-end settings (``EUROC_FRONTEND``).

This module imports neither torch nor the dataset readers (``torch_frontend.io``): the camera
models (torch) are imported when a camera is built.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

import numpy as np

from .errors import ConfigError, ConfigWarning
from .opencv_yaml import read_opencv_yaml

PathLike = Union[str, Path]

# Keys that make a camodocal camera block in a VINS-Mono config.
_CAMERA_BLOCK_KEYS = ("model_type", "projection_parameters")
_REQUIRED = {
    # VINS-Mono's feature_tracker node reads these from the same file
    "mono": ("image_width", "image_height", "max_cnt", "min_dist"),
    # VINS-Fusion's estimator needs ROW/COL; its simulation config has no tracker keys (a data
    # generator publishes the features), so max_cnt/min_dist read as 0 there, as in VINS
    "fusion": ("image_width", "image_height"),
    "estimator": (),
}
# Every top-level key a VINS node reads (spec §1.2-§1.6; the union of the keys of every config
# VINS-Mono and VINS-Fusion ship), by what reads it. Keys outside these get a ConfigWarning.
FRONTEND_KEYS = frozenset({
    "image_topic", "imu_topic", "image0_topic", "image1_topic", "max_cnt", "min_dist", "freq",
    "F_threshold", "show_track", "equalize", "fisheye", "flow_back", "num_of_cam", "cam0_calib",
    "cam1_calib", "image_width", "image_height",
    "F_method",  # torch-frontend's own: rejectWithF's estimator
})
CAMERA_KEYS = frozenset({
    "model_type", "camera_name", "image_width", "image_height", "distortion_parameters",
    "projection_parameters", "mirror_parameters", "poly_parameters", "inv_poly_parameters", "affine_parameters",
})
POSE_GRAPH_KEYS = frozenset({
    "loop_closure", "pose_graph_save_path", "output_path", "save_image", "visualize_imu_forward",
    "visualize_camera_size", "load_previous_pose_graph", "fast_relocalization",
})
ESTIMATOR_KEYS = frozenset({
    "imu", "acc_n", "acc_w", "gyr_n", "gyr_w", "g_norm", "estimate_extrinsic", "ex_calib_result_path",
    "extrinsicRotation", "extrinsicTranslation", "body_T_cam0", "body_T_cam1", "estimate_td", "td",
    "rolling_shutter", "rolling_shutter_tr", "max_solver_time", "max_num_iterations", "keyframe_parallax",
    "multiple_thread",
})
KNOWN_KEYS = FRONTEND_KEYS | CAMERA_KEYS | POSE_GRAPH_KEYS | ESTIMATOR_KEYS
# difflib ratio above which an unknown key is taken for a typo of a known one ("equalise" ->
# "equalize" 0.88, "F_treshold" -> "F_threshold" 0.95, "max_count" -> "max_cnt" 0.88)
NEAR_MISS_RATIO = 0.75

# VINS-Mono's euroc_config.yaml front-end values, used when only a sensor.yaml is given.
EUROC_FRONTEND = dict(max_cnt=150, min_dist=30, freq=10, F_threshold=1.0, equalize=True, fisheye=False)
# ``F_method`` (not a VINS key): rejectWithF's estimator, ``torch_frontend.ransac``'s ``method``
F_METHODS = ("opencv", "lo")


@dataclasses.dataclass
class TrackerConfig:
    """Front-end settings from a VINS config file (VINS key names).

    Attributes:
        path: the config file.
        flavour: ``"mono"`` (camera block in the file) or ``"fusion"`` (``camN_calib`` files);
            ``"estimator"`` when the file has no camera at all.
        image_topic, imu_topic, image0_topic, image1_topic: the ROS topics as given (``""`` if absent).
        image_width, image_height: ``COL``, ``ROW`` in pixels.
        max_cnt: maximum number of tracked + new features per frame.
        min_dist: GFTT minimum distance and setMask disc radius (pixels).
        freq: publish rate in Hz (VINS-Mono rule: 0 in the file means 100).
        F_threshold: F-RANSAC threshold in virtual-pinhole pixels.
        F_method: F-RANSAC estimator (not a VINS key; default ``"opencv"``): ``"opencv"`` is VINS's
            (OpenCV's FM_RANSAC, exactly), ``"lo"`` LO-RANSAC (the same hypotheses and inlier
            test, locally optimised; keeps more good tracks), see ``ransac.find_fundamental``.
        show_track, equalize, fisheye, flow_back: VINS flags as bools.
        num_of_cam: 1 or 2 (VINS-Fusion); 1 for VINS-Mono.
        cam0_calib, cam1_calib: the resolved camera files of a VINS-Fusion config, else None.
        camera: the camodocal model of camera 0 (a ``torch_frontend.camera.CameraModel``), or None.
        camera1: camera 1 for stereo VINS-Fusion configs, else None.
        body_T_cam0, body_T_cam1: 4×4 float64 extrinsics when the file gives them (VINS-Fusion).
        origin: where the settings come from when not (only) from ``path`` (e.g. a KITTI
            sequence's: "KITTI calib.txt P0; VINS-Mono front-end defaults"); ``""`` for a file.
        raw: every key of the file as read (matrices as numpy arrays).
    """

    path: Optional[str] = None
    flavour: str = "mono"
    image_topic: str = ""
    imu_topic: str = ""
    image0_topic: str = ""
    image1_topic: str = ""
    image_width: int = 0
    image_height: int = 0
    max_cnt: int = 150
    min_dist: int = 30
    freq: int = 10
    F_threshold: float = 1.0
    F_method: str = "opencv"
    show_track: bool = False
    equalize: bool = False
    fisheye: bool = False
    flow_back: bool = False
    num_of_cam: int = 1
    cam0_calib: Optional[str] = None
    cam1_calib: Optional[str] = None
    camera: Any = None
    camera1: Any = None
    body_T_cam0: Optional[np.ndarray] = None
    body_T_cam1: Optional[np.ndarray] = None
    origin: str = ""
    raw: Dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)

    def __post_init__(self):
        if self.F_method not in F_METHODS:  # a config built by hand (load_config checks the file itself)
            raise ConfigError(f"expected one of {', '.join(map(repr, F_METHODS))}, got {self.F_method!r}",
                              self.path, "F_method")

    def settings_line(self) -> str:
        """One line of the settings that change what the tracker does (what ``track`` and
        ``loop`` print before they run): camera model and size, ``max_cnt``, ``min_dist``,
        ``freq``, ``equalize``, ``F_threshold``, ``fisheye`` (and ``flow_back``, ``num_of_cam``,
        ``F_method`` where they differ from VINS-Mono's)."""
        model = getattr(self.camera, "model_type", "no camera")
        extra = "".join([f", F_method {self.F_method}" if self.F_method != "opencv" else "",
                         ", flow_back 1" if self.flow_back else "",
                         f", num_of_cam {self.num_of_cam}" if self.num_of_cam != 1 else ""])
        origin = f" ({self.origin})" if self.origin else ""
        return (f"config        {self.path}{origin}: {model} {self.image_width}x{self.image_height}, max_cnt {self.max_cnt}, "
                f"min_dist {self.min_dist}, freq {self.freq} Hz, equalize {int(self.equalize)}, "
                f"F_threshold {self.F_threshold:g}, fisheye {int(self.fisheye)}{extra}")

    def summary(self) -> str:
        """A few human-readable lines (what ``make demo`` prints)."""
        lines = [
            f"config        {self.path} ({self.flavour})",
            f"image         {self.image_width} x {self.image_height}",
            f"max_cnt       {self.max_cnt}   min_dist {self.min_dist}   freq {self.freq} Hz"
            f"   F_threshold {self.F_threshold}" + (f"   F_method {self.F_method}" if self.F_method != "opencv" else ""),
            f"equalize      {int(self.equalize)}   fisheye {int(self.fisheye)}   flow_back {int(self.flow_back)}"
            f"   num_of_cam {self.num_of_cam}",
            f"camera        {self.camera!r}",
        ]
        if self.camera1 is not None:
            lines.append(f"camera1       {self.camera1!r}")
        return "\n".join(lines)


def _get_int(raw: Dict[str, Any], key: str, path: str, default: Optional[int]) -> Optional[int]:
    if key not in raw or raw[key] is None:
        return default
    v = raw[key]
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, float) and math.isfinite(v) and v == int(v):
        return int(v)
    raise ConfigError(f"expected an integer, got {v!r}", path, key)


def _get_float(raw: Dict[str, Any], key: str, path: str, default: Optional[float]) -> Optional[float]:
    if key not in raw or raw[key] is None:
        return default
    v = raw[key]
    if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
        if not math.isfinite(float(v)):
            raise ConfigError(f"expected a finite number, got {v!r}", path, key)
        return float(v)
    raise ConfigError(f"expected a number, got {v!r}", path, key)


def _get_str(raw: Dict[str, Any], key: str, path: str, default: str = "") -> str:
    if key not in raw or raw[key] is None:
        return default
    v = raw[key]
    if not isinstance(v, str):
        raise ConfigError(f"expected a string, got {v!r}", path, key)
    return v


def _get_matrix(raw: Dict[str, Any], key: str, path: str, shape) -> Optional[np.ndarray]:
    if key not in raw:
        return None
    v = raw[key]
    if not isinstance(v, np.ndarray):
        raise ConfigError(f"expected an !!opencv-matrix of shape {shape}, got {type(v).__name__}", path, key)
    if v.shape != tuple(shape):
        raise ConfigError(f"expected a matrix of shape {tuple(shape)}, got {v.shape}", path, key)
    return v.astype(np.float64)


def closest_known_key(key: str) -> Optional[str]:
    """The known key ``key`` is most likely a typo of (letter case ignored), or None when no known
    key is close (``NEAR_MISS_RATIO``)."""
    by_lower = {k.lower(): k for k in sorted(KNOWN_KEYS)}
    hit = difflib.get_close_matches(str(key).lower(), list(by_lower), n=1, cutoff=NEAR_MISS_RATIO)
    return by_lower[hit[0]] if hit else None


def check_keys(raw: Dict[str, Any], path: PathLike, *, stacklevel: int = 3) -> List[str]:
    """Warn (``ConfigWarning``) once per top-level key of ``raw`` that is not in ``KNOWN_KEYS``,
    naming the closest known key when there is one; returns those keys."""
    unknown = [k for k in raw if k not in KNOWN_KEYS]
    for k in unknown:
        near = closest_known_key(k)
        hint = (f"did you mean `{near}`? (the key is ignored)" if near is not None else
                "not a key VINS or torch-frontend reads (ignored)")
        warnings.warn(f"unknown key `{k}` in {path}: {hint}", ConfigWarning, stacklevel=stacklevel)
    return unknown


def load_camera(path: PathLike):
    """Load a camodocal camera YAML (``model_type`` PINHOLE, MEI, KANNALA_BRANDT, SCARAMUZZA,
    PINHOLE_FULL, any letter case) and return the camera model.

    Raises:
        ConfigError: the file is missing or unreadable, a key is missing or has the wrong type,
            or ``model_type`` is unknown; the message names the file and the key.
    """
    from .camera import camera_from_config

    raw = read_opencv_yaml(path)
    check_keys(raw, path)
    return camera_from_config(raw, path=str(path))


def _has_camera_block(raw: Dict[str, Any]) -> bool:
    return any(k in raw for k in _CAMERA_BLOCK_KEYS)


def _check_size(cfg: TrackerConfig, cam, cam_path: str) -> None:
    w, h = getattr(cam, "width", None), getattr(cam, "height", None)
    if cfg.image_width and cfg.image_height and w and h and (w, h) != (cfg.image_width, cfg.image_height):
        warnings.warn(
            f"image size {cfg.image_width}x{cfg.image_height} in {cfg.path} disagrees with "
            f"{w}x{h} in camera file {cam_path}",
            stacklevel=3,
        )


def load_config(path: PathLike) -> TrackerConfig:
    """Read a VINS-Mono or VINS-Fusion config file (OpenCV FileStorage YAML) into a ``TrackerConfig``.

    Args:
        path: the config YAML. VINS-Fusion's ``cam0_calib``/``cam1_calib`` are read relative to its
            folder.

    Returns:
        The config, with ``camera`` (and ``camera1`` for stereo) built from the camera block or
        calibration files, or ``camera=None`` for an estimator-only config.

    Warns:
        ConfigWarning: a key that is not in ``KNOWN_KEYS`` (ignored), naming the closest known key
            ("did you mean `equalize`?").

    Raises:
        ConfigError: a missing file, a key given twice (both lines named), a missing required key,
            a wrong type, an unknown ``model_type``, a negative ``freq`` or a camera value the model cannot work with
            (``fx: 0``: ``CameraModel.param_problems``); the message names the file, the key and
            what was expected.
    """
    from .camera import camera_from_config

    p = Path(path)
    raw = read_opencv_yaml(p)
    sp = str(p)
    check_keys(raw, sp)
    cfg = TrackerConfig(path=sp, raw=raw)

    has_block = _has_camera_block(raw)
    has_calib = "cam0_calib" in raw
    cfg.flavour = "fusion" if has_calib else ("mono" if has_block else "estimator")

    for key in _REQUIRED[cfg.flavour]:
        if key not in raw:
            raise ConfigError(f"required in a VINS-{cfg.flavour.capitalize()} config, but missing (expected an integer)",
                              sp, key)
    tracker_default = 0 if cfg.flavour == "fusion" else None

    cfg.image_topic = _get_str(raw, "image_topic", sp)
    cfg.imu_topic = _get_str(raw, "imu_topic", sp)
    cfg.image0_topic = _get_str(raw, "image0_topic", sp)
    cfg.image1_topic = _get_str(raw, "image1_topic", sp)
    cfg.image_width = _get_int(raw, "image_width", sp, 0)
    cfg.image_height = _get_int(raw, "image_height", sp, 0)
    cfg.max_cnt = _get_int(raw, "max_cnt", sp, 150 if tracker_default is None else tracker_default)
    cfg.min_dist = _get_int(raw, "min_dist", sp, 30 if tracker_default is None else tracker_default)
    freq = _get_int(raw, "freq", sp, 10)
    if freq < 0:  # VINS would publish nothing at all (no rate is <= a negative FREQ)
        raise ConfigError(f"must be a publish rate >= 0 in Hz (0 means 100, as in VINS-Mono), got {freq}", sp, "freq")
    cfg.freq = 100 if freq == 0 else freq  # VINS-Mono: FREQ 0 means 100 Hz
    cfg.F_threshold = _get_float(raw, "F_threshold", sp, 1.0)
    cfg.F_method = _get_str(raw, "F_method", sp, "opencv")
    if cfg.F_method not in F_METHODS:
        raise ConfigError(f"expected one of {', '.join(map(repr, F_METHODS))} (rejectWithF's estimator), got "
                          f"{cfg.F_method!r}", sp, "F_method")
    for flag in ("show_track", "equalize", "fisheye", "flow_back"):
        setattr(cfg, flag, bool(_get_int(raw, flag, sp, 0)))
    cfg.num_of_cam = _get_int(raw, "num_of_cam", sp, 1)
    if cfg.num_of_cam not in (1, 2):
        raise ConfigError(f"must be 1 or 2, got {cfg.num_of_cam}", sp, "num_of_cam")
    for key in _REQUIRED[cfg.flavour]:
        if getattr(cfg, key) <= 0:
            raise ConfigError(f"must be a positive integer, got {getattr(cfg, key)}", sp, key)
    cfg.body_T_cam0 = _get_matrix(raw, "body_T_cam0", sp, (4, 4))
    cfg.body_T_cam1 = _get_matrix(raw, "body_T_cam1", sp, (4, 4))

    if has_block and not has_calib:
        cfg.camera = camera_from_config(raw, path=sp)
        _check_size(cfg, cfg.camera, sp)
    if has_calib:
        calibs: List[str] = ["cam0_calib"] + (["cam1_calib"] if cfg.num_of_cam == 2 else [])
        for i, key in enumerate(calibs):
            name = _get_str(raw, key, sp)
            if not name:
                raise ConfigError("expected a camera calibration file name", sp, key)
            cam_path = (p.parent / name).resolve()
            if not cam_path.is_file():
                raise ConfigError(f"camera calibration file not found: {cam_path}", sp, key)
            cam = load_camera(cam_path)
            _check_size(cfg, cam, str(cam_path))
            setattr(cfg, key, str(cam_path))
            setattr(cfg, "camera" if i == 0 else "camera1", cam)
    return cfg


# ----------------------------------------------------------------------------------------------
# ASL sensor.yaml (Kalibr)


def _numbers(raw: Dict[str, Any], key: str, n: int, path: Path) -> List[float]:
    v = raw.get(key)
    try:
        vals = [float(x) for x in v]
    except TypeError:
        raise ConfigError(f"expected a list of {n} numbers, got {v!r}", path, key) from None
    except ValueError:
        raise ConfigError(f"expected numbers, got {v!r}", path, key) from None
    if len(vals) != n:
        raise ConfigError(f"expected {n} numbers, got {len(vals)}", path, key)
    return vals


def camera_from_sensor_yaml(path: PathLike):
    """Camera model of an ASL ``sensor.yaml`` (see the module docstring).

    Raises:
        ConfigError: missing file or key, wrong list length, unsupported camera or distortion model,
            a value the model cannot work with (not finite, a focal length <= 0, a size <= 0),
            naming the key and element (``intrinsics[0]``).
    """
    from .camera import KannalaBrandtCamera, PinholeCamera

    p = Path(path)
    raw = read_opencv_yaml(p)
    model = str(raw.get("camera_model", "pinhole")).lower()
    if model != "pinhole":
        raise ConfigError(f"unsupported camera_model {model!r} (expected 'pinhole')", p, "camera_model")
    res = _numbers(raw, "resolution", 2, p)
    if not all(math.isfinite(x) and x > 0 and x == int(x) for x in res):
        raise ConfigError(f"expected [width, height], positive integers, got {raw.get('resolution')!r}", p, "resolution")
    w, h = (int(x) for x in res)
    fu, fv, cu, cv = _numbers(raw, "intrinsics", 4, p)
    dist = str(raw.get("distortion_model", "radial-tangential")).lower()
    name = str(raw.get("comment", p.parent.name))
    if dist in ("radial-tangential", "radtan", "plumb_bob"):
        cls, names = PinholeCamera, ("k1", "k2", "p1", "p2", "fx", "fy", "cx", "cy")
    elif dist in ("equidistant", "fisheye"):
        # camodocal's k2..k5 are Kalibr's k1..k4 (the implicit k1 = 1)
        cls, names = KannalaBrandtCamera, ("k2", "k3", "k4", "k5", "mu", "mv", "u0", "v0")
    else:
        raise ConfigError(
            f"unsupported distortion_model {dist!r} (expected 'radial-tangential' or 'equidistant')", p,
            "distortion_model"
        )
    coeffs = _numbers(raw, "distortion_coefficients", 4, p)
    params = dict(zip(names, coeffs + [fu, fv, cu, cv]))
    # the sensor.yaml key (and element) of each camodocal parameter, for the error message
    keys = {n: f"distortion_coefficients[{i}]" for i, n in enumerate(names[:4])}
    keys.update({n: f"intrinsics[{i}]" for i, n in enumerate(names[4:])})
    problems = cls.param_problems(params)
    if problems:
        pname, problem = problems[0]
        raise ConfigError(problem, p, keys[pname])
    return cls(**params, width=w, height=h, camera_name=name)


def config_from_sensor_yaml(path: PathLike, **overrides) -> TrackerConfig:
    """A ``TrackerConfig`` from an ASL ``sensor.yaml``: its camera and size, and VINS-Mono's EuRoC
    front-end settings (``EUROC_FRONTEND``: ``max_cnt 150, min_dist 30, freq 10, F_threshold 1,
    equalize 1``) unless overridden by keyword (``TrackerConfig`` field names)."""
    cam = camera_from_sensor_yaml(path)
    settings = dict(EUROC_FRONTEND)
    settings.update(overrides)
    return TrackerConfig(
        path=str(path),
        flavour="mono",
        image_width=int(cam.width),
        image_height=int(cam.height),
        camera=cam,
        **settings,
    )


__all__ = [
    "EUROC_FRONTEND",
    "F_METHODS",
    "KNOWN_KEYS",
    "ConfigError",
    "ConfigWarning",
    "TrackerConfig",
    "check_keys",
    "closest_known_key",
    "camera_from_sensor_yaml",
    "config_from_sensor_yaml",
    "load_camera",
    "load_config",
]
