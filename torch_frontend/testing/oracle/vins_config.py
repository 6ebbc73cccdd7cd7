"""VINS config files and camodocal camera files for the oracle, read with ``cv2.FileStorage`` as
VINS reads them (absent keys read as 0, spec §1.1): :func:`cfg_from_vins_yaml` (the trackers' cfg
dicts) and :func:`camera_from_yaml` (the flat camera dict of :func:`.camodocal.lift_projective`).
"""

from __future__ import annotations

from pathlib import Path

import cv2

_CAMERA_KEYS = {
    "PINHOLE": ("k1", "k2", "p1", "p2", "fx", "fy", "cx", "cy"),
    "MEI": ("xi", "k1", "k2", "p1", "p2", "gamma1", "gamma2", "u0", "v0"),
    "KANNALA_BRANDT": ("k2", "k3", "k4", "k5", "mu", "mv", "u0", "v0"),
}
_CAMERA_BLOCKS = ("mirror_parameters", "distortion_parameters", "projection_parameters")


def _fs_real(node) -> float:
    # cv2.FileStorage: an absent node reads as 0 (spec §1.1 "missing keys are silent").
    return 0.0 if node.empty() or node.isNone() else float(node.real())


def _camera_from_fs(fs) -> dict:
    mt_node = fs.getNode("model_type")
    model = "MEI" if mt_node.empty() or mt_node.isNone() else mt_node.string()
    if model not in _CAMERA_KEYS:
        raise ValueError(
            f"camera: model_type {model!r} not supported by the oracle (expected exactly one of "
            f"{sorted(_CAMERA_KEYS)}; camodocal's readers are case-sensitive)"
        )
    cam = {"model_type": model}
    for key in _CAMERA_KEYS[model]:
        val = 0.0
        for blk in _CAMERA_BLOCKS:
            n = fs.getNode(blk)
            if not n.empty() and not n.isNone() and not n.getNode(key).empty():
                val = _fs_real(n.getNode(key))
                break
        cam[key] = val
    for key in ("image_width", "image_height"):
        cam[key] = int(_fs_real(fs.getNode(key)))
    return cam


def camera_from_yaml(path) -> dict:
    """Flat camodocal parameter dict from a camera YAML (or a Mono config holding the camera block)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise FileNotFoundError(f"camera_from_yaml: cannot open {path}")
    try:
        return _camera_from_fs(fs)
    finally:
        fs.release()


def cfg_from_vins_yaml(path) -> dict:
    """Oracle cfg from a VINS config, read with ``cv2.FileStorage``.

    VINS-Mono config (camera block inline): keys of :class:`OracleMonoTracker`; with
    ``fisheye: 1`` the mask ``<config dir>/../fisheye_mask.jpg`` is loaded (= VINS's fixed
    ``vins_folder/config/fisheye_mask.jpg``). VINS-Fusion config (``cam0_calib`` present): keys of
    :class:`OracleFusionTracker`, camera files resolved relative to the config's directory,
    ``camera1`` only when ``num_of_cam == 2``. ``mode`` tells which ("mono" / "fusion").
    """
    path = Path(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise FileNotFoundError(f"cfg_from_vins_yaml: cannot open {path}")
    try:
        def i(key):
            return int(_fs_real(fs.getNode(key)))

        def f(key):
            return _fs_real(fs.getNode(key))

        calib0 = fs.getNode("cam0_calib")
        if not calib0.empty() and not calib0.isNone():
            cfg = {
                "mode": "fusion",
                "max_cnt": i("max_cnt"),
                "min_dist": i("min_dist"),
                "flow_back": i("flow_back"),
                "F_threshold": f("F_threshold"),
                "image_width": i("image_width"),
                "image_height": i("image_height"),
                "num_of_cam": i("num_of_cam"),
                "camera": camera_from_yaml(path.parent / calib0.string()),
                "camera1": None,
            }
            if cfg["num_of_cam"] == 2:
                cfg["camera1"] = camera_from_yaml(path.parent / fs.getNode("cam1_calib").string())
            return cfg
        cfg = {
            "mode": "mono",
            "max_cnt": i("max_cnt"),
            "min_dist": i("min_dist"),
            "freq": i("freq"),
            "F_threshold": f("F_threshold"),
            "show_track": i("show_track"),
            "equalize": i("equalize"),
            "fisheye": i("fisheye"),
            "image_width": i("image_width"),
            "image_height": i("image_height"),
            "camera": _camera_from_fs(fs),
        }
    finally:
        fs.release()
    if cfg["fisheye"]:
        mpath = path.parent.parent / "fisheye_mask.jpg"
        mask = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise FileNotFoundError(f"cfg_from_vins_yaml: fisheye=1 but no mask at {mpath}")
        cfg["fisheye_mask"] = mask
    return cfg
