"""Config loader: OpenCV FileStorage YAML, VINS-Mono and VINS-Fusion keys, ASL sensor.yaml, errors."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torch_frontend import ConfigError, load_camera, load_config
from torch_frontend.config import camera_from_sensor_yaml, config_from_sensor_yaml
from torch_frontend.opencv_yaml import read_opencv_yaml

from .conftest import REPO, SAMPLE, SHARED_DATA

CONFIGS = REPO / "configs"


def test_shipped_configs_all_load():
    files = sorted(CONFIGS.glob("*.yaml"))
    assert len(files) >= 6
    for f in files:
        raw = read_opencv_yaml(f)
        if "model_type" in raw and "max_cnt" not in raw:
            cam = load_camera(f)
            assert cam.width > 0 and cam.height > 0
        else:
            cfg = load_config(f)
            assert cfg.camera is not None, f
            assert cfg.max_cnt > 0 and cfg.min_dist > 0


def test_euroc_values():
    cfg = load_config(CONFIGS / "euroc.yaml")
    assert cfg.flavour == "mono"
    assert (cfg.image_width, cfg.image_height) == (752, 480)
    assert cfg.max_cnt == 150 and cfg.min_dist == 30 and cfg.freq == 10
    assert cfg.F_threshold == 1.0 and cfg.equalize and not cfg.fisheye
    cam = cfg.camera
    assert type(cam).__name__ == "PinholeCamera"
    p = cam.params_dict()
    assert p["fx"] == pytest.approx(461.6) and p["k1"] == pytest.approx(-0.2917)
    assert cfg.raw["extrinsicRotation"].shape == (3, 3)
    assert "extrinsicTranslation" in cfg.raw  # unknown keys are kept


def test_fusion_stereo_resolves_calibs():
    cfg = load_config(CONFIGS / "euroc_stereo_mei.yaml")
    assert cfg.flavour == "fusion" and cfg.num_of_cam == 2 and cfg.flow_back
    assert type(cfg.camera).__name__ == "MeiCamera" and type(cfg.camera1).__name__ == "MeiCamera"
    assert Path(cfg.cam0_calib).is_file() and Path(cfg.cam1_calib).is_file()
    assert cfg.body_T_cam0.shape == (4, 4) and cfg.body_T_cam1[3, 3] == 1.0
    mono = load_config(CONFIGS / "euroc_mono_mei.yaml")
    assert mono.num_of_cam == 1 and mono.camera1 is None


def test_kb_config():
    cfg = load_config(CONFIGS / "tum_vi.yaml")
    assert type(cfg.camera).__name__ == "KannalaBrandtCamera"
    assert cfg.fisheye and cfg.min_dist == 25


def _write(tmp_path, text, name="c.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


MINI = """%YAML:1.0
model_type: pinhole
camera_name: cam
image_width: 640
image_height: 480
distortion_parameters:
   k1: 1e-3
   k2: 0
   p1: 0
   p2: 0
projection_parameters:
   fx: 400.
   fy: 401
   cx: 320   # a comment
   cy: 240
max_cnt: 100
min_dist: 20
freq: 0
"""


def test_opencv_quirks(tmp_path):
    from torch_frontend.errors import ConfigWarning

    p = _write(tmp_path, MINI + "M: !!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: f\n   data: [1, 2, 3, 4e-1]\n")
    with pytest.warns(ConfigWarning, match="unknown key `M`"):  # not a VINS key: kept in raw, with a warning
        cfg = load_config(p)
    assert cfg.freq == 100  # freq 0 means 100 Hz (VINS-Mono)
    assert cfg.camera.params_dict()["k1"] == pytest.approx(1e-3)  # '1e-3' is a number, as in OpenCV
    m = cfg.raw["M"]
    assert m.dtype == np.float32 and m.shape == (2, 2) and m[1, 1] == pytest.approx(0.4)
    assert not cfg.equalize and not cfg.fisheye  # missing flags read as 0


def test_missing_file():
    with pytest.raises(ConfigError, match="nope.yaml.*not found"):
        load_config("/nonexistent/nope.yaml")


def test_missing_required_key(tmp_path):
    p = _write(tmp_path, MINI.replace("max_cnt: 100\n", ""))
    with pytest.raises(ConfigError, match=r"c\.yaml.*max_cnt"):
        load_config(p)


def test_wrong_type(tmp_path):
    p = _write(tmp_path, MINI.replace("min_dist: 20", 'min_dist: "far"'))
    with pytest.raises(ConfigError, match=r"min_dist.*integer"):
        load_config(p)


def test_unknown_model_type(tmp_path):
    p = _write(tmp_path, MINI.replace("model_type: pinhole", "model_type: fancy"))
    with pytest.raises(ConfigError, match=r"model_type.*fancy"):
        load_config(p)


def test_missing_camera_key(tmp_path):
    p = _write(tmp_path, MINI.replace("   fx: 400.\n", ""))
    with pytest.raises(ConfigError, match=r"fx"):
        load_config(p)


def test_missing_calib_file(tmp_path):
    p = _write(tmp_path, "%YAML:1.0\ncam0_calib: \"nothere.yaml\"\nimage_width: 10\nimage_height: 10\n"
               "max_cnt: 5\nmin_dist: 3\n")
    with pytest.raises(ConfigError, match=r"cam0_calib.*nothere\.yaml"):
        load_config(p)


def test_bad_yaml(tmp_path):
    p = _write(tmp_path, "%YAML:1.0\nkey: [unclosed\n")
    with pytest.raises(ConfigError, match=r"c\.yaml"):
        load_config(p)


def test_size_mismatch_warns(tmp_path):
    cam = (CONFIGS / "euroc_cam0_mei.yaml").read_text()
    _write(tmp_path, cam, "cam0.yaml")
    p = _write(tmp_path, "%YAML:1.0\ncam0_calib: \"cam0.yaml\"\nimage_width: 600\nimage_height: 600\n"
               "max_cnt: 5\nmin_dist: 3\n")
    with pytest.warns(UserWarning, match=r"600x600.*752x480.*cam0\.yaml"):
        cfg = load_config(p)
    assert cfg.camera is not None


def _vins_config_files(what: str):
    """Every YAML shipped with VINS-Mono and VINS-Fusion (../shared/data/vins_configs), at least 50;
    skips ``what`` with the reason when ../shared is not beside the repo."""
    root = SHARED_DATA / "vins_configs"
    if not root.exists():
        pytest.skip(f"../shared/data/vins_configs not found beside the repo ({root}); skipping {what}")
    files = sorted(root.rglob("*.yaml"))
    assert len(files) >= 50
    return files


def test_every_vins_config_loads():
    """Every YAML shipped with VINS-Mono and VINS-Fusion (../shared/data/vins_configs) loads."""
    files = _vins_config_files("the VINS-config sweep")
    root = SHARED_DATA / "vins_configs"
    n_cfg = n_cam = 0
    for f in files:
        raw = read_opencv_yaml(f)
        is_camera_file = "model_type" in raw and not any(k in raw for k in ("max_cnt", "imu_topic", "cam0_calib"))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if is_camera_file:
                cam = load_camera(f)
                assert cam.width > 0
                n_cam += 1
            else:
                cfg = load_config(f)
                n_cfg += 1
                if cfg.flavour == "estimator":
                    assert cfg.camera is None
                else:
                    assert cfg.camera is not None, f
        if f.name == "simulation_config.yaml" and "vins_fusion" in str(f):
            # 600x600 in the main config, 752x480 in the camera files
            assert any("disagrees" in str(w.message) for w in caught)
    assert n_cfg >= 20 and n_cam >= 20
    mono = load_config(root / "vins_mono" / "euroc" / "euroc_config.yaml")
    assert mono.camera.params_dict()["fx"] == pytest.approx(461.6)
    assert mono.max_cnt == 150 and mono.min_dist == 30 and mono.freq == 10
    tum = load_config(root / "vins_mono" / "tum" / "tum_config.yaml")
    assert tum.fisheye and type(tum.camera).__name__ == "KannalaBrandtCamera"
    sim = load_config(root / "vins_mono" / "simulation" / "simulation_config.yaml")
    assert sim.camera is None and sim.flavour == "estimator"


def test_sensor_yaml_camera_and_config(tmp_path):
    from torch_frontend.camera import PinholeCamera

    cam = camera_from_sensor_yaml(SAMPLE / "mav0" / "cam0" / "sensor.yaml")
    assert isinstance(cam, PinholeCamera)
    assert (cam.width, cam.height) == (752, 480)
    p = cam.params_dict()
    assert float(p["fx"]) == 458.654 and float(p["cy"]) == 248.375 and float(p["k1"]) == -0.28340811
    # the parameter mapping agrees with OpenCV's radial-tangential projection
    rng = np.random.default_rng(0)
    P = np.concatenate([rng.uniform(-0.6, 0.6, (50, 2)), np.ones((50, 1))], axis=1)
    K = np.array([[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1.0]])
    dist = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)
    got = cam.project(torch.from_numpy(P)).numpy()
    np.testing.assert_allclose(got, ref[:, 0], atol=1e-9)

    cfg = config_from_sensor_yaml(SAMPLE / "mav0" / "cam0" / "sensor.yaml")
    assert (cfg.image_width, cfg.image_height, cfg.max_cnt, cfg.min_dist, cfg.freq) == (752, 480, 150, 30, 10)
    assert cfg.equalize and cfg.camera is not None

    # TUM-VI: equidistant -> Kannala-Brandt; bad models are ConfigErrors naming the key
    y = tmp_path / "sensor.yaml"
    y.write_text("%YAML:1.0\nresolution: [512, 512]\nintrinsics: [190.9, 190.9, 254.9, 256.8]\n"
                 "camera_model: pinhole\ndistortion_model: equidistant\n"
                 "distortion_coefficients: [0.0034, 0.00071, -0.0021, 0.00020]\n")
    kb = camera_from_sensor_yaml(y)
    assert type(kb).__name__ == "KannalaBrandtCamera" and float(kb.params_dict()["k2"]) == 0.0034
    y.write_text("resolution: [512, 512]\nintrinsics: [1, 2, 3]\n")
    with pytest.raises(ConfigError, match="intrinsics"):
        camera_from_sensor_yaml(y)
    y.write_text("resolution: [512, 512]\nintrinsics: [1, 2, 3, 4]\ndistortion_model: weird\n"
                 "distortion_coefficients: [0, 0, 0, 0]\n")
    with pytest.raises(ConfigError, match="distortion_model"):
        camera_from_sensor_yaml(y)


def test_import_config_loads_neither_torch_nor_readers():
    """``torch_frontend.config`` (and the OpenCV-YAML reader below it) stay light: no torch, no
    dataset readers, no ROS-bag library, no OpenCV; reading a config file keeps it so."""
    code = (
        "import sys\n"
        "import torch_frontend.config as c\n"
        "c.read_opencv_yaml(sys.argv[1])\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'cv2', 'rosbags', 'kornia')\n"
        "             or m == 'torch_frontend.io' or m.startswith('torch_frontend.io.'))\n"
        "print(' '.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code, str(CONFIGS / "euroc.yaml")], capture_output=True,
                         text=True, cwd=REPO, check=True).stdout.split()
    assert out == [], f"import torch_frontend.config loaded: {out}"


# ----------------------------------------------------------------------------------------------
# key checks: near-misses warn, duplicates are errors, every shipped and VINS config is quiet


def test_near_miss_keys_warn_with_the_closest_known_key(tmp_path):
    from torch_frontend.errors import ConfigWarning

    p = _write(tmp_path, MINI + "equalise: 0\nF_treshold: 2\n")
    with pytest.warns(ConfigWarning) as caught:
        cfg = load_config(p)
    msgs = [str(w.message) for w in caught if issubclass(w.category, ConfigWarning)]
    assert f"unknown key `equalise` in {p}: did you mean `equalize`?" in msgs[0]
    assert f"unknown key `F_treshold` in {p}: did you mean `F_threshold`?" in msgs[1]
    assert len(msgs) == 2
    assert not cfg.equalize and cfg.F_threshold == 1.0  # ignored, as VINS would (the warning says so)
    p = _write(tmp_path, MINI + "Max_Cnt: 5\nwidget_colour: 3\n", "d.yaml")
    with pytest.warns(ConfigWarning) as caught:
        load_config(p)
    msgs = [str(w.message) for w in caught]
    assert "`Max_Cnt`" in msgs[0] and "did you mean `max_cnt`?" in msgs[0]
    assert "`widget_colour`" in msgs[1] and "not a key VINS" in msgs[1] and "did you mean" not in msgs[1]


def test_near_miss_in_a_camera_file_warns(tmp_path):
    from torch_frontend.errors import ConfigWarning

    cam = (CONFIGS / "euroc_cam0_mei.yaml").read_text()
    p = _write(tmp_path, cam + "camera_nmae: x\n", "cam0.yaml")
    with pytest.warns(ConfigWarning, match=r"`camera_nmae`.*did you mean `camera_name`"):
        load_camera(p)


def test_duplicated_key_is_an_error_naming_both_lines(tmp_path):
    # line 1 is %YAML:1.0; max_cnt is on line 16 of MINI and again on the last line
    p = _write(tmp_path, MINI + "max_cnt: 19\n")
    n = len(MINI.splitlines()) + 1
    first = MINI.splitlines().index("max_cnt: 100") + 1
    with pytest.raises(ConfigError) as info:
        load_config(p)
    msg = str(info.value)
    assert str(p) in msg and "max_cnt" in msg and f"line {first} and line {n}" in msg, msg
    # nested maps too (a camodocal parameter given twice)
    p = _write(tmp_path, MINI.replace("   fy: 401\n", "   fy: 401\n   fx: 399\n"), "n.yaml")
    with pytest.raises(ConfigError, match=r"n\.yaml.*'fx'.*line 12 and line 14"):
        load_config(p)


def _config_or_camera(f):
    raw = read_opencv_yaml(f)
    if "model_type" in raw and not any(k in raw for k in ("max_cnt", "imu_topic", "cam0_calib")):
        return load_camera(f)
    return load_config(f)


def _config_warnings(files):
    from torch_frontend.errors import ConfigWarning

    out = []
    for f in files:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _config_or_camera(f)
        out += [f"{f}: {w.message}" for w in caught if issubclass(w.category, ConfigWarning)]
    return out


def test_shipped_configs_load_without_key_warnings():
    files = sorted(CONFIGS.glob("*.yaml"))
    assert len(files) >= 6
    assert _config_warnings(files) == []


def test_vins_configs_load_without_key_warnings():
    """The estimator and pose-graph keys of VINS's own configs are known keys (ignored silently)."""
    files = _vins_config_files("the key sweep")
    assert _config_warnings(files) == []


def test_settings_line():
    cfg = load_config(CONFIGS / "euroc.yaml")
    line = cfg.settings_line()
    assert "\n" not in line
    for part in ("PINHOLE 752x480", "max_cnt 150", "min_dist 30", "freq 10 Hz", "equalize 1", "F_threshold 1",
                 "fisheye 0"):
        assert part in line, line
    assert "num_of_cam 2" in load_config(CONFIGS / "euroc_stereo_mei.yaml").settings_line()
