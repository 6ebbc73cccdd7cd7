"""Build a camera model from a camodocal camera YAML (or a VINS-Mono config holding the camera block).

Mirrors camodocal's ``CameraFactory::generateCameraFromYamlFile`` (spec §4.0, keys §1.6) with two
deliberate differences, both turning silent upstream failures into errors:

* upstream reads an absent key as 0 (and then divides by it); here a missing or non-numeric key
  raises ``ConfigError`` naming it, e.g. ``projection_parameters.fx``, and so does a value the model
  cannot work with (``CameraModel.param_problems``: not finite, a focal length <= 0, Scaramuzza's
  singular affine part), or an image size <= 0;
* upstream's per-model readers compare ``model_type`` case-sensitively and, on a mismatch such as
  ``pinhole``, silently leave every parameter 0; here any letter case selects the model and reads it.

As upstream, an absent ``model_type`` means ``MEI``.
"""

from __future__ import annotations

import math
import numbers
import os
from typing import Any, Dict, Mapping, Union

import torch

from ..errors import ConfigError
from ..opencv_yaml import read_opencv_yaml
from .base import CameraModel
from .kannala_brandt import KannalaBrandtCamera
from .mei import MeiCamera
from .pinhole import PinholeCamera, PinholeFullCamera
from .scaramuzza import INV_POLY_SIZE, POLY_SIZE, ScaramuzzaCamera

# lower-case model_type -> class
MODELS = {
    "pinhole": PinholeCamera,
    "pinhole_full": PinholeFullCamera,
    "mei": MeiCamera,
    "kannala_brandt": KannalaBrandtCamera,
    "scaramuzza": ScaramuzzaCamera,
}

# class -> [(yaml block, yaml key, parameter name)]
_LAYOUT = {
    PinholeCamera: [("distortion_parameters", k, k) for k in ("k1", "k2", "p1", "p2")]
    + [("projection_parameters", k, k) for k in ("fx", "fy", "cx", "cy")],
    PinholeFullCamera: [
        ("distortion_parameters", k, k) for k in ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
    ]
    + [("projection_parameters", k, k) for k in ("fx", "fy", "cx", "cy")],
    MeiCamera: [("mirror_parameters", "xi", "xi")]
    + [("distortion_parameters", k, k) for k in ("k1", "k2", "p1", "p2")]
    + [("projection_parameters", k, k) for k in ("gamma1", "gamma2", "u0", "v0")],
    KannalaBrandtCamera: [
        ("projection_parameters", k, k) for k in ("k2", "k3", "k4", "k5", "mu", "mv", "u0", "v0")
    ],
    ScaramuzzaCamera: [("affine_parameters", k, k) for k in ("ac", "ad", "ae", "cx", "cy")],
}


def _number(node: Mapping[str, Any], key: str, dotted: str, path) -> float:
    if key not in node:
        raise ConfigError("missing", path, dotted)
    v = node[key]
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise ConfigError(f"expected a number, got {type(v).__name__} {v!r}", path, dotted)
    return float(v)


def _block(node: Mapping[str, Any], key: str, path, hint: str = "") -> Mapping[str, Any]:
    if key not in node:
        raise ConfigError("missing" + hint, path, key)
    v = node[key]
    if not isinstance(v, Mapping):
        raise ConfigError(f"expected a map of parameters, got {type(v).__name__}", path, key)
    return v


def _int(node: Mapping[str, Any], key: str, path) -> int:
    if key not in node:
        raise ConfigError("missing", path, key)
    v = node[key]
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or float(v) != int(v):
        raise ConfigError(f"expected an integer, got {type(v).__name__} {v!r}", path, key)
    return int(v)


def _yaml_keys(cls) -> Dict[str, str]:
    """Parameter name (``param_problems``' spelling, ``poly[3]`` for a vector element) -> YAML key."""
    keys = {pname: f"{block_key}.{yaml_key}" for block_key, yaml_key, pname in _LAYOUT[cls]}
    if cls is ScaramuzzaCamera:
        for block_key, pname, size in (("poly_parameters", "poly", POLY_SIZE),
                                       ("inv_poly_parameters", "inv_poly", INV_POLY_SIZE)):
            keys.update({f"{pname}[{i}]": f"{block_key}.p{i}" for i in range(size)})
    return keys


def _check_params(cls, params: Mapping[str, Any], path, keys: Mapping[str, str]) -> None:
    """``ConfigError`` naming the file and key (``keys``: parameter name -> key) of the first of
    ``cls.param_problems(params)``."""
    problems = cls.param_problems(params)
    if problems:
        name, problem = problems[0]
        raise ConfigError(f"{problem} ({cls.model_type} camera)", path, keys.get(name, name))


def camera_from_config(
    node: Union[Mapping[str, Any], str, os.PathLike],
    path: Union[str, os.PathLike] | None = None,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | None = None,
) -> CameraModel:
    """Camera model from a parsed camodocal camera YAML / VINS-Mono config.

    Args:
        node: the dict ``torch_frontend.opencv_yaml.read_opencv_yaml(path)`` returns (top-level keys
            ``model_type``, ``camera_name``, ``image_width``, ``image_height`` and the nested parameter
            maps of §1.6), or a path, which is then read with ``read_opencv_yaml``.
        path: file the node came from; only used in error messages.
        dtype, device: of the model's parameters.

    Returns:
        ``PinholeCamera``, ``PinholeFullCamera``, ``MeiCamera``, ``KannalaBrandtCamera`` or
        ``ScaramuzzaCamera``. ``model_type`` is matched in any letter case; absent means ``MEI``
        (camodocal's default). ``camera_name`` is optional (default ``""`` as upstream reads it).

    Raises:
        ConfigError: naming the file and the key: a missing key (``projection_parameters.fx``), a
            value of the wrong type, a value the model cannot work with (not finite, a focal length
            <= 0: ``CameraModel.param_problems``), an image size <= 0, or an unknown ``model_type``
            (the message lists the known ones).
    """
    if isinstance(node, (str, os.PathLike)):
        path = node if path is None else path
        node = read_opencv_yaml(node)
    if not isinstance(node, Mapping):
        raise ConfigError(f"expected a mapping (parsed YAML), got {type(node).__name__}", path)

    hint = ""
    if "model_type" in node:
        mt = node["model_type"]
        if not isinstance(mt, str):
            raise ConfigError(f"expected a string, got {type(mt).__name__} {mt!r}", path, "model_type")
        key = mt.strip().lower()
        if key not in MODELS:
            known = ", ".join(c.model_type for c in MODELS.values())
            raise ConfigError(f"unknown camera model {mt!r}; known (any letter case): {known}", path, "model_type")
    else:
        key = "mei"  # camodocal: no model_type => MEI
        hint = " (no model_type, so the camodocal default MEI was assumed"
        if any(k in node for k in ("cam0_calib", "cam1_calib")):
            hint += "; this looks like a VINS-Fusion config: the camera is in the file named by cam0_calib"
        hint += ")"
    cls = MODELS[key]

    width = _int(node, "image_width", path)
    height = _int(node, "image_height", path)
    for key, v in (("image_width", width), ("image_height", height)):
        if v <= 0:
            raise ConfigError(f"must be a positive number of pixels, got {v}", path, key)
    name = node.get("camera_name", "")
    if not isinstance(name, str):
        name = str(name)

    params: Dict[str, Any] = {}
    for block_key, yaml_key, pname in _LAYOUT[cls]:
        block = _block(node, block_key, path, hint)
        params[pname] = _number(block, yaml_key, f"{block_key}.{yaml_key}", path)
    if cls is ScaramuzzaCamera:
        for block_key, pname, size in (("poly_parameters", "poly", POLY_SIZE), ("inv_poly_parameters", "inv_poly", INV_POLY_SIZE)):
            block = _block(node, block_key, path)
            params[pname] = [_number(block, f"p{i}", f"{block_key}.p{i}", path) for i in range(size)]
    _check_params(cls, params, path, _yaml_keys(cls))
    return cls(**params, width=width, height=height, camera_name=name, dtype=dtype, device=device)
