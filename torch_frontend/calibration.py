"""VINS configs from calibration files: Kalibr's ``camchain.yaml`` / ``camchain-imucam.yaml`` (and
its IMU ``imu.yaml``) and ROS ``camera_calibration``'s ``camera_info`` YAML, read and converted
to VINS-Mono / VINS-Fusion YAML text (``vins_config_files``). Pure: reads files, returns text;
``pipelines.make_config`` writes them (``torch-frontend config``).

Camera models (Kalibr ``camera_model`` + ``distortion_model`` -> camodocal ``model_type``):

=========================  ===================  ==========================================================
Kalibr                     camodocal            parameters
=========================  ===================  ==========================================================
``pinhole`` + ``radtan``   ``PINHOLE``          ``intrinsics [fu, fv, pu, pv]`` -> ``fx, fy, cx, cy``;
                                                ``distortion_coeffs [k1, k2, r1, r2]`` -> ``k1, k2, p1, p2``
``pinhole`` + ``equidistant``  ``KANNALA_BRANDT``  ``mu, mv, u0, v0``; ``[k1..k4]`` -> ``k2..k5`` (camodocal's
                                                implicit k1 = 1, spec §4.3)
``omni`` + ``radtan``      ``MEI``              ``intrinsics [xi, fu, fv, pu, pv]`` -> ``xi, gamma1, gamma2, u0,
                                                v0``; ``k1, k2, p1, p2`` as pinhole
``pinhole|omni`` + ``none``  ``PINHOLE`` / ``MEI``  zero distortion
=========================  ===================  ==========================================================

Kalibr's ``ds`` (double sphere), ``eucm`` (extended unified) and the ``fov`` distortion have no
camodocal model (VINS cannot read them), nor has ``omni`` + ``equidistant``: a ``ConfigError``
names the model and the camera. ``camera_info`` (``camera_matrix`` K, ``distortion_model``,
``distortion_coefficients`` D): ``plumb_bob`` ``[k1, k2, p1, p2, k3]`` -> ``PINHOLE`` (``k3`` must
be 0: camodocal's pinhole has no ``k3``), ``equidistant`` ``[k1..k4]`` -> ``KANNALA_BRANDT``;
``rational_polynomial`` and a skewed K are refused by name.

Extrinsics (VINS's convention: body <- camera, ``extrinsicRotation`` / ``extrinsicTranslation``
for VINS-Mono, ``body_T_cam0`` / ``body_T_cam1`` for VINS-Fusion): Kalibr's ``T_cam_imu`` maps IMU
coordinates into the camera's, so VINS's ``T_imu_cam`` is its inverse ``[R^T, -R^T t]``. A
two-camera ``camchain.yaml`` without an IMU gives ``body_T_cam0 = I`` and ``body_T_cam1`` the
inverse of cam1's ``T_cn_cnm1`` (cam1 <- cam0). ``timeshift_cam_imu`` (``t_imu = t_cam + shift``)
is VINS's ``td``. Kalibr's ``imu.yaml``: ``accelerometer_noise_density`` -> ``acc_n``,
``accelerometer_random_walk`` -> ``acc_w``, ``gyroscope_noise_density`` -> ``gyr_n``,
``gyroscope_random_walk`` -> ``gyr_w`` (as given: Kalibr's continuous-time densities, which VINS
users often inflate), ``rostopic`` -> ``imu_topic``.

Output: one camera: a VINS-Mono config (the camera block in the file); two: VINS-Fusion's layout,
the main file and one camodocal file per camera (``<stem>_cam0.yaml``, named by ``cam0_calib``),
``imu: 1`` with ``T_cam_imu``, else 0. Every other key at VINS's shipped EuRoC values: the front end
``EUROC_FRONTEND`` (``max_cnt 150, min_dist 30, freq 10, F_threshold 1, equalize 1, fisheye 0``;
Fusion: ``flow_back 1``, no ``equalize``/``fisheye``), the estimator, loop-closure and IMU-noise
defaults; ``estimate_extrinsic 0`` with a Kalibr extrinsic, else 2 (VINS-Mono calibrates it).

Errors: ``ConfigError`` naming the file, the key (``cam0.distortion_model``) and what was
expected, for a missing or malformed key, a model camodocal lacks, a ``T_cam_imu`` that is not a
rigid transform, or values the camera model refuses (``CameraModel.param_problems``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import numpy as np

from .config import EUROC_FRONTEND
from .errors import ConfigError
from .opencv_yaml import format_opencv_yaml, read_opencv_yaml

PathLike = Union[str, Path]

#: the first header line of every file written here: a file that starts with it may be replaced
#: by a new ``torch-frontend config`` (``pipelines.make_config``), any other is not
WRITTEN_BY = "written by torch-frontend config"

# camodocal parameter names per model, in the file's order: (block, names)
_LAYOUT = {
    "PINHOLE": [("distortion_parameters", ("k1", "k2", "p1", "p2")),
                ("projection_parameters", ("fx", "fy", "cx", "cy"))],
    "KANNALA_BRANDT": [("projection_parameters", ("k2", "k3", "k4", "k5", "mu", "mv", "u0", "v0"))],
    "MEI": [("mirror_parameters", ("xi",)), ("distortion_parameters", ("k1", "k2", "p1", "p2")),
            ("projection_parameters", ("gamma1", "gamma2", "u0", "v0"))],
}
# Kalibr's models camodocal has no equivalent of (named in the error)
_NO_CAMODOCAL = {"ds": "double sphere", "eucm": "extended unified (EUCM)", "fov": "field of view (FOV)"}
_SUPPORTED = "pinhole-radtan, pinhole-equi, omni-radtan (or pinhole/omni with distortion none)"
# VINS's shipped values of the keys the calibration does not give (VINS-Mono's and VINS-Fusion's EuRoC configs)
MONO_IMU_NOISE = dict(acc_n=0.08, gyr_n=0.004, acc_w=0.00004, gyr_w=2.0e-6, g_norm=9.81007)
FUSION_IMU_NOISE = dict(acc_n=0.1, gyr_n=0.01, acc_w=0.001, gyr_w=0.0001, g_norm=9.81007)
#: VINS-Fusion's front-end keys at its shipped EuRoC values
FUSION_FRONTEND = dict(max_cnt=150, min_dist=30, freq=10, F_threshold=1.0, show_track=1, flow_back=1)
OUTPUT_PATH = "~/output/"


@dataclasses.dataclass
class CameraCalibration:
    """One camera as camodocal describes it, with what the calibration says around it.

    Attributes:
        name: the camera's name (``cam0``; ``camera_name`` of a camera_info file).
        model_type: ``PINHOLE``, ``KANNALA_BRANDT`` or ``MEI``.
        params: camodocal parameter name -> value (pixels for focal lengths and centre).
        width, height: image size in pixels.
        topic: the image topic (Kalibr's ``rostopic``), ``""`` if none.
        T_imu_cam: 4x4 float64, VINS's body (IMU) <- camera, from ``T_cam_imu``; None without one.
        T_cam_prev: 4x4 float64, Kalibr's ``T_cn_cnm1`` (this camera <- the previous one); None.
        td: ``timeshift_cam_imu`` in seconds (VINS's ``td``), None when absent.
        source: the file and camera (for messages), e.g. ``camchain.yaml cam1``.
    """

    name: str
    model_type: str
    params: Dict[str, float]
    width: int
    height: int
    topic: str = ""
    T_imu_cam: Optional[np.ndarray] = None
    T_cam_prev: Optional[np.ndarray] = None
    td: Optional[float] = None
    source: str = ""

    def camera_block(self) -> List[tuple]:
        """The camodocal keys of this camera as ``opencv_yaml.format_opencv_yaml`` entries."""
        out: List[tuple] = [("model_type", self.model_type), ("camera_name", self.name),
                            ("image_width", self.width), ("image_height", self.height)]
        for block, names in _LAYOUT[self.model_type]:
            out.append((block, {n: self.params[n] for n in names}))
        return out


@dataclasses.dataclass
class ImuNoise:
    """VINS's IMU keys from Kalibr's ``imu.yaml`` (continuous-time densities, as given)."""

    acc_n: float
    gyr_n: float
    acc_w: float
    gyr_w: float
    topic: str = ""
    source: str = ""


# ----------------------------------------------------------------------------------------------
# reading


def _numbers(node: Mapping[str, Any], key: str, n: Union[int, Sequence[int]], path: Path, where: str) -> List[float]:
    """``node[key]`` as a list of ``n`` finite numbers (``n``: a length or the allowed lengths)."""
    full = f"{where}.{key}" if where else key
    if key not in node:
        raise ConfigError("missing", path, full)
    v = node[key]
    ns = (n,) if isinstance(n, int) else tuple(n)
    try:
        vals = [float(x) for x in v]
    except (TypeError, ValueError):
        raise ConfigError(f"expected a list of {' or '.join(map(str, ns))} numbers, got {v!r}", path, full) from None
    if len(vals) not in ns:
        raise ConfigError(f"expected {' or '.join(map(str, ns))} numbers, got {len(vals)}", path, full)
    bad = [i for i, x in enumerate(vals) if not math.isfinite(x)]
    if bad:
        raise ConfigError(f"element {bad[0]} is not a finite number ({vals[bad[0]]!r})", path, full)
    return vals


def _text(node: Mapping[str, Any], key: str, path: Path, where: str, default: Optional[str] = None) -> str:
    full = f"{where}.{key}" if where else key
    if key not in node or node[key] is None:
        if default is not None:
            return default
        raise ConfigError("missing", path, full)
    return str(node[key]).strip()


def _size(node: Mapping[str, Any], path: Path, where: str, keys=("resolution",)) -> tuple:
    w, h = _numbers(node, keys[0], 2, path, where)
    if not (w > 0 and h > 0 and w == int(w) and h == int(h)):
        raise ConfigError(f"expected [width, height], positive integers, got {node[keys[0]]!r}", path,
                          f"{where}.{keys[0]}")
    return int(w), int(h)


def _rigid(node: Mapping[str, Any], key: str, path: Path, where: str) -> np.ndarray:
    """A 4x4 rigid transform (Kalibr writes a list of 4 rows): rotation orthonormal with det +1
    to 1e-6, last row ``[0, 0, 0, 1]``."""
    full = f"{where}.{key}"
    v = node[key]
    try:
        T = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"expected a 4x4 matrix (4 rows of 4 numbers), got {v!r}", path, full) from None
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ConfigError(f"expected a 4x4 matrix of finite numbers (4 rows of 4), got shape {T.shape}", path, full)
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > 1e-6 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 0:
        raise ConfigError(f"not a rigid transform: the rotation part must be orthonormal with det +1 (|R^T R - I| "
                          f"= {err:.2g}) and the last row [0, 0, 0, 1], got {T.tolist()}", path, full)
    return T


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """The inverse of a 4x4 rigid transform: ``[R^T, -R^T t; 0 0 0 1]``."""
    T = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _check_params(model_type: str, params: Dict[str, float], path: Path, keys: Mapping[str, str]) -> None:
    """The camera model's own rules (``CameraModel.param_problems``: focal lengths > 0, xi >= 0,
    ...), the first problem as a ``ConfigError`` naming the source key."""
    from .camera.factory import MODELS

    problems = MODELS[model_type.lower()].param_problems(params)
    if problems:
        name, why = problems[0]
        raise ConfigError(why, path, keys.get(name, name))


def _kalibr_camera(node: Any, name: str, path: Path) -> CameraCalibration:
    if not isinstance(node, Mapping):
        raise ConfigError(f"expected a camera (a map with camera_model, intrinsics, ...), got {node!r}", path, name)
    model = _text(node, "camera_model", path, name).lower()
    dist = _text(node, "distortion_model", path, name, default="none").lower()
    dist = {"radial-tangential": "radtan", "equi": "equidistant", "fisheye": "equidistant"}.get(dist, dist)
    label = f"{model}-{dist}"
    for bad, long in _NO_CAMODOCAL.items():
        if bad in (model, dist):
            key = "camera_model" if bad == model else "distortion_model"
            raise ConfigError(f"{label}: Kalibr's {long} model has no camodocal equivalent, so VINS cannot read it; "
                              f"VINS's cameras come from {_SUPPORTED} (recalibrate with one of those)", path,
                              f"{name}.{key}")
    if model not in ("pinhole", "omni"):
        raise ConfigError(f"unknown Kalibr camera model {model!r} (expected pinhole or omni)", path,
                          f"{name}.camera_model")
    if dist not in ("radtan", "equidistant", "none"):
        raise ConfigError(f"unknown Kalibr distortion model {dist!r} (expected radtan, equidistant or none)", path,
                          f"{name}.distortion_model")
    if model == "omni" and dist == "equidistant":
        raise ConfigError(f"{label}: camodocal's MEI model has radial-tangential distortion only; VINS's cameras "
                          f"come from {_SUPPORTED}", path, f"{name}.distortion_model")
    w, h = _size(node, path, name)
    intr = _numbers(node, "intrinsics", 5 if model == "omni" else 4, path, name)
    if dist == "none":  # coefficients absent, empty or zeros
        coeffs = _numbers(node, "distortion_coeffs", range(5), path, name) if "distortion_coeffs" in node else []
        if any(c != 0 for c in coeffs):
            raise ConfigError(f"distortion_model none with non-zero coefficients {coeffs}", path,
                              f"{name}.distortion_coeffs")
        coeffs = [0.0, 0.0, 0.0, 0.0]
    else:
        coeffs = _numbers(node, "distortion_coeffs", 4, path, name)
    ik, dk = f"{name}.intrinsics", f"{name}.distortion_coeffs"
    if dist == "equidistant":
        mt, names = "KANNALA_BRANDT", ("k2", "k3", "k4", "k5")
        proj = dict(zip(("mu", "mv", "u0", "v0"), intr))
        keys = {n: f"{ik}[{i}]" for i, n in enumerate(("mu", "mv", "u0", "v0"))}
    elif model == "omni":
        mt, names = "MEI", ("k1", "k2", "p1", "p2")
        proj = dict(zip(("xi", "gamma1", "gamma2", "u0", "v0"), intr))
        keys = {n: f"{ik}[{i}]" for i, n in enumerate(("xi", "gamma1", "gamma2", "u0", "v0"))}
    else:
        mt, names = "PINHOLE", ("k1", "k2", "p1", "p2")
        proj = dict(zip(("fx", "fy", "cx", "cy"), intr))
        keys = {n: f"{ik}[{i}]" for i, n in enumerate(("fx", "fy", "cx", "cy"))}
    params = {**dict(zip(names, coeffs)), **proj}
    keys.update({n: f"{dk}[{i}]" for i, n in enumerate(names)})
    _check_params(mt, params, path, keys)
    cam = CameraCalibration(name=name, model_type=mt, params=params, width=w, height=h,
                            topic=_text(node, "rostopic", path, name, default=""), source=f"{path} {name}")
    if "T_cam_imu" in node:
        cam.T_imu_cam = invert_rigid(_rigid(node, "T_cam_imu", path, name))
    if "T_cn_cnm1" in node:
        cam.T_cam_prev = _rigid(node, "T_cn_cnm1", path, name)
    if "timeshift_cam_imu" in node:
        cam.td = _numbers({"t": [node["timeshift_cam_imu"]]}, "t", 1, path, name)[0]
    return cam


def read_kalibr_camchain(path: PathLike) -> List[CameraCalibration]:
    """The cameras of a Kalibr ``camchain.yaml`` / ``camchain-imucam.yaml`` (``cam0``, ``cam1``, ...
    in order), converted to camodocal models (module docstring).

    Raises:
        ConfigError: the file is missing or not YAML, has no ``cam0``, a camera key is missing or
            malformed, a model camodocal lacks (naming it), or a value the model refuses.
    """
    p = Path(path)
    raw = read_opencv_yaml(p)
    names = sorted((k for k in raw if isinstance(k, str) and k.startswith("cam") and k[3:].isdigit()),
                   key=lambda k: int(k[3:]))
    if not names or names[0] != "cam0":
        raise ConfigError(f"not a Kalibr camchain: expected cameras cam0, cam1, ... at the top level, got keys "
                          f"{sorted(map(str, raw))}", p, "cam0")
    for i, n in enumerate(names):
        if n != f"cam{i}":
            raise ConfigError(f"cameras must be numbered cam0, cam1, ... without gaps, got {names}", p, n)
    cams = [_kalibr_camera(raw[n], n, p) for n in names]
    with_imu = [c.T_imu_cam is not None for c in cams]
    if any(with_imu) and not all(with_imu):
        n = names[with_imu.index(False)]
        raise ConfigError("T_cam_imu is given for some cameras only (a camchain-imucam.yaml has it for every "
                          "camera)", p, f"{n}.T_cam_imu")
    return cams


def read_kalibr_imu(path: PathLike) -> ImuNoise:
    """VINS's IMU noise keys from Kalibr's ``imu.yaml`` (flat, or under ``imu0:`` as Kalibr's
    results file writes it).

    Raises:
        ConfigError: a missing file or key, or a value that is not a finite number > 0.
    """
    p = Path(path)
    raw = read_opencv_yaml(p)
    node, where = (raw["imu0"], "imu0") if isinstance(raw.get("imu0"), Mapping) else (raw, "")
    vals = {}
    for vins, kalibr in (("acc_n", "accelerometer_noise_density"), ("acc_w", "accelerometer_random_walk"),
                         ("gyr_n", "gyroscope_noise_density"), ("gyr_w", "gyroscope_random_walk")):
        v = _numbers({kalibr: [node[kalibr]]} if kalibr in node else {}, kalibr, 1, p, where)[0]
        if not v > 0:
            raise ConfigError(f"expected a noise density > 0, got {v!r}", p, f"{where}.{kalibr}" if where else kalibr)
        vals[vins] = v
    return ImuNoise(**vals, topic=_text(node, "rostopic", p, where, default=""), source=str(p))


def _flat_matrix(raw: Mapping[str, Any], key: str, path: Path, n: Optional[int] = None) -> List[float]:
    """A camera_info matrix (``{rows, cols, data}``, or an ``!!opencv-matrix``) as its flat data
    (``n`` numbers when given)."""
    if key not in raw:
        raise ConfigError("missing", path, key)
    v = raw[key]
    if isinstance(v, np.ndarray):
        v = {"data": v.reshape(-1).tolist()}
    if not isinstance(v, Mapping) or "data" not in v:
        raise ConfigError(f"expected a matrix {{rows, cols, data}}, got {v!r}", path, key)
    data = v["data"] if isinstance(v["data"], list) else [v["data"]]
    return _numbers({"data": data}, "data", n if n is not None else range(len(data) + 1), path, key)


def read_camera_info(path: PathLike) -> CameraCalibration:
    """The camera of a ROS ``camera_calibration`` camera_info YAML (``image_width``,
    ``image_height``, ``camera_name``, ``camera_matrix``, ``distortion_model``,
    ``distortion_coefficients``): ``plumb_bob`` -> ``PINHOLE`` (``k3`` = 0 only), ``equidistant``
    -> ``KANNALA_BRANDT``.

    Raises:
        ConfigError: a missing or malformed key, a skewed ``camera_matrix``, ``plumb_bob`` with
            ``k3 != 0``, or another distortion model (``rational_polynomial``: camodocal's pinhole
            has no k3..k6), naming it.
    """
    p = Path(path)
    raw = read_opencv_yaml(p)
    w, h = (_numbers({k: [raw[k]]} if k in raw else {}, k, 1, p, "")[0] for k in ("image_width", "image_height"))
    for k, v in (("image_width", w), ("image_height", h)):
        if not (v > 0 and v == int(v)):
            raise ConfigError(f"expected a positive integer (pixels), got {v!r}", p, k)
    w, h = int(w), int(h)
    K = np.asarray(_flat_matrix(raw, "camera_matrix", p, 9)).reshape(3, 3)
    if K[0, 1] != 0 or np.abs(K[2] - [0, 0, 1]).max() > 0 or K[1, 0] != 0:
        raise ConfigError(f"expected [fx, 0, cx, 0, fy, cy, 0, 0, 1] (camodocal has no skew), got {K.reshape(-1).tolist()}",
                          p, "camera_matrix")
    dist = _text(raw, "distortion_model", p, "").lower()
    D = _flat_matrix(raw, "distortion_coefficients", p)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if dist == "plumb_bob":
        if len(D) not in (4, 5):
            raise ConfigError(f"plumb_bob: expected 5 coefficients [k1, k2, p1, p2, k3], got {len(D)}", p,
                              "distortion_coefficients")
        if len(D) == 5 and D[4] != 0:
            raise ConfigError(f"plumb_bob with k3 = {D[4]!r}: camodocal's PINHOLE model has k1, k2, p1, p2 only, so "
                              f"VINS cannot use k3 (recalibrate with k3 fixed to 0, e.g. camera_calibration's "
                              f"--fix-k3)", p, "distortion_coefficients[4]")
        mt = "PINHOLE"
        params = dict(zip(("k1", "k2", "p1", "p2"), D[:4]), fx=fx, fy=fy, cx=cx, cy=cy)
        keys = {n: f"distortion_coefficients[{i}]" for i, n in enumerate(("k1", "k2", "p1", "p2"))}
    elif dist in ("equidistant", "fisheye"):
        if len(D) != 4:
            raise ConfigError(f"equidistant: expected 4 coefficients [k1, k2, k3, k4], got {len(D)}", p,
                              "distortion_coefficients")
        mt = "KANNALA_BRANDT"
        params = dict(zip(("k2", "k3", "k4", "k5"), D), mu=fx, mv=fy, u0=cx, v0=cy)
        keys = {n: f"distortion_coefficients[{i}]" for i, n in enumerate(("k2", "k3", "k4", "k5"))}
    else:
        raise ConfigError(f"distortion model {dist!r}: camodocal (VINS's cameras) reads plumb_bob with k3 = 0 "
                          f"(PINHOLE) or equidistant (KANNALA_BRANDT) only", p, "distortion_model")
    keys.update({"fx": "camera_matrix[0]", "fy": "camera_matrix[4]", "cx": "camera_matrix[2]",
                 "cy": "camera_matrix[5]", "mu": "camera_matrix[0]", "mv": "camera_matrix[4]",
                 "u0": "camera_matrix[2]", "v0": "camera_matrix[5]"})
    _check_params(mt, params, p, keys)
    return CameraCalibration(name=_text(raw, "camera_name", p, "", default="camera") or "camera", model_type=mt,
                             params={k: float(v) for k, v in params.items()}, width=w, height=h, source=str(p))


# ----------------------------------------------------------------------------------------------
# writing


def _header(sources: Sequence[str]) -> List[str]:
    return [f"{WRITTEN_BY} from {', '.join(sources)}",
            "(torch_frontend.calibration; every key not in the calibration at VINS's shipped EuRoC values)"]


def _imu_entries(imu: Optional[ImuNoise], defaults: Dict[str, float]) -> List[Any]:
    src = f"from {Path(imu.source).name}" if imu is not None else "VINS's EuRoC values: give --imu imu.yaml"
    vals = defaults if imu is None else {**defaults, "acc_n": imu.acc_n, "gyr_n": imu.gyr_n, "acc_w": imu.acc_w,
                                         "gyr_w": imu.gyr_w}
    return ["", f"imu parameters ({src})",
            ("acc_n", vals["acc_n"], "accelerometer noise density"),
            ("gyr_n", vals["gyr_n"], "gyroscope noise density"),
            ("acc_w", vals["acc_w"], "accelerometer bias random walk"),
            ("gyr_w", vals["gyr_w"], "gyroscope bias random walk"),
            ("g_norm", vals["g_norm"], "gravity magnitude (m/s^2)")]


def _td(cams: Sequence[CameraCalibration]) -> float:
    return float(cams[0].td) if cams[0].td is not None else 0.0


def _mono(cam: CameraCalibration, imu: Optional[ImuNoise], sources: Sequence[str]) -> str:
    e: List[Any] = ["common parameters",
                    ("imu_topic", imu.topic if imu is not None and imu.topic else "/imu0"),
                    ("image_topic", cam.topic or "/cam0/image_raw"),
                    ("output_path", OUTPUT_PATH), "", "camera calibration (camodocal)"]
    e += cam.camera_block()
    e += ["", "extrinsic: body (IMU) <- camera"]
    if cam.T_imu_cam is not None:
        e += [("estimate_extrinsic", 0, "0: trust the extrinsic below (Kalibr's T_cam_imu, inverted)"),
              ("extrinsicRotation", cam.T_imu_cam[:3, :3]), ("extrinsicTranslation", cam.T_imu_cam[:3, 3:4])]
    else:
        e += [("estimate_extrinsic", 2, "2: no extrinsic in the calibration, VINS calibrates it (rotate at the start)")]
    f = EUROC_FRONTEND
    e += ["", "feature tracker (VINS-Mono's defaults)", ("max_cnt", f["max_cnt"]), ("min_dist", f["min_dist"]),
          ("freq", f["freq"]), ("F_threshold", float(f["F_threshold"])), ("show_track", 1),
          ("equalize", int(f["equalize"])),
          ("fisheye", int(f["fisheye"]), "1: VINS masks the image with its fisheye_mask.jpg (512x512 for TUM-VI)")]
    e += ["", "optimization", ("max_solver_time", 0.04), ("max_num_iterations", 8), ("keyframe_parallax", 10.0)]
    e += _imu_entries(imu, MONO_IMU_NOISE)
    e += ["", "loop closure", ("loop_closure", 1), ("load_previous_pose_graph", 0), ("fast_relocalization", 0),
          ("pose_graph_save_path", OUTPUT_PATH + "pose_graph/")]
    e += ["", "time offset: image clock + td = IMU clock (Kalibr's timeshift_cam_imu)", ("estimate_td", 0),
          ("td", _td([cam])), "", "rolling shutter", ("rolling_shutter", 0), ("rolling_shutter_tr", 0),
          "", "visualization", ("save_image", 1), ("visualize_imu_forward", 0), ("visualize_camera_size", 0.4)]
    return format_opencv_yaml(e, _header(sources))


def _fusion(cams: Sequence[CameraCalibration], imu: Optional[ImuNoise], sources: Sequence[str],
            calib_names: Sequence[str]) -> str:
    with_imu = cams[0].T_imu_cam is not None
    if with_imu:
        body = [c.T_imu_cam for c in cams]
        how = "Kalibr's T_cam_imu, inverted"
    else:  # no IMU: the body is cam0; cam1 <- cam0 is cam1's T_cn_cnm1
        if cams[1].T_cam_prev is None:
            raise ConfigError("two cameras without T_cam_imu need cam1's T_cn_cnm1 (cam1 <- cam0) for the stereo "
                              "extrinsic", cams[1].source.rsplit(" ", 1)[0], f"{cams[1].name}.T_cn_cnm1")
        body = [np.eye(4), invert_rigid(cams[1].T_cam_prev)]
        how = "no IMU: body = cam0, cam1 from Kalibr's T_cn_cnm1, inverted"
    e: List[Any] = ["common parameters", ("imu", int(with_imu)), ("num_of_cam", len(cams)),
                    ("imu_topic", imu.topic if imu is not None and imu.topic else ("/imu0" if with_imu else ""))]
    e += [(f"image{i}_topic", c.topic or f"/cam{i}/image_raw") for i, c in enumerate(cams)]
    e += [("output_path", OUTPUT_PATH), ""]
    e += [(f"cam{i}_calib", n) for i, n in enumerate(calib_names)]
    e += [("image_width", cams[0].width), ("image_height", cams[0].height)]
    e += ["", f"extrinsics: body <- camera ({how})", ("estimate_extrinsic", 0)]
    e += [(f"body_T_cam{i}", T) for i, T in enumerate(body)]
    e += ["", "multiple thread support", ("multiple_thread", 1)]
    e += ["", "feature tracker (VINS-Fusion's defaults)"] + list(FUSION_FRONTEND.items())
    e += ["", "optimization", ("max_solver_time", 0.04), ("max_num_iterations", 8), ("keyframe_parallax", 10.0)]
    e += _imu_entries(imu, FUSION_IMU_NOISE)
    e += ["", "time offset: image clock + td = IMU clock (Kalibr's timeshift_cam_imu)", ("estimate_td", 0),
          ("td", _td(cams))]
    e += ["", "loop closure", ("load_previous_pose_graph", 0), ("pose_graph_save_path", OUTPUT_PATH + "pose_graph/"),
          ("save_image", 1)]
    return format_opencv_yaml(e, _header(sources))


def vins_config_files(cameras: Sequence[CameraCalibration], out_name: str, imu: Optional[ImuNoise] = None,
                      sources: Sequence[str] = ()) -> Dict[str, str]:
    """The files of the VINS config for ``cameras``: ``{file name: text}``, the main file
    ``out_name`` first. One camera: a VINS-Mono config; two: VINS-Fusion's main file and
    ``<stem>_cam0.yaml``, ``<stem>_cam1.yaml`` (module docstring).

    Raises:
        ConfigError: no camera or more than two (VINS takes 1 or 2), or two cameras of different
            sizes (VINS-Fusion has one ``image_width`` / ``image_height``), naming the source.
    """
    cams = list(cameras)
    src = cams[0].source.rsplit(" ", 1)[0] if cams else None
    if not 1 <= len(cams) <= 2:
        raise ConfigError(f"{len(cams)} cameras: VINS takes 1 (VINS-Mono) or 2 (VINS-Fusion stereo)", src)
    sources = list(sources) or [Path(src).name]
    if len(cams) == 1:
        return {out_name: _mono(cams[0], imu, sources)}
    if (cams[0].width, cams[0].height) != (cams[1].width, cams[1].height):
        raise ConfigError(f"cam0 is {cams[0].width}x{cams[0].height}, cam1 {cams[1].width}x{cams[1].height}: "
                          f"VINS-Fusion takes one image size for both cameras", src, "cam1.resolution")
    stem = Path(out_name).stem
    names = [f"{stem}_{c.name}.yaml" for c in cams]
    files = {out_name: _fusion(cams, imu, sources, names)}
    for c, n in zip(cams, names):
        files[n] = format_opencv_yaml(c.camera_block(), _header(sources))
    return files


__all__ = [
    "CameraCalibration",
    "ImuNoise",
    "WRITTEN_BY",
    "invert_rigid",
    "read_camera_info",
    "read_kalibr_camchain",
    "read_kalibr_imu",
    "vins_config_files",
]
