"""``torch-frontend config --from-kalibr / --from-camera-info`` (``torch_frontend.calibration``,
``pipelines.make_config``): the written config, loaded with the project's camera factory, projects
points as an independent implementation of the source model does (OpenCV for pinhole-radtan and
pinhole-equi, the unified-model formulas written out here for omni-radtan); the extrinsic is the
inverse of Kalibr's ``T_cam_imu``; the models camodocal lacks are refused by name; the written
config runs ``track`` on the sample and tracks as the sample's own ``sensor.yaml`` does."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
import torch
import yaml

from tests._helpers import assert_one_error_line, run_cli
from tests.conftest import SAMPLE
from torch_frontend.calibration import invert_rigid, read_camera_info, read_kalibr_camchain
from torch_frontend.config import load_config
from torch_frontend.errors import ConfigError
from torch_frontend.opencv_yaml import format_opencv_yaml, read_opencv_yaml
from torch_frontend.pipelines.common import OptionError
from torch_frontend.pipelines.make_config import run_make_config

# EuRoC cam0 (the sample's sensor.yaml) and its body <- camera extrinsic T_BS
EUROC_K = [458.654, 457.296, 367.215, 248.375]
EUROC_D = [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
T_BS = np.array([[0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
                 [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
                 [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
                 [0.0, 0.0, 0.0, 1.0]])
# TUM-VI cam0 (Kalibr pinhole-equi) and EuRoC cam0 as an omni-radtan calibration (VINS-Fusion's MEI values)
TUMVI_K = [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504]
TUMVI_D = [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182]
OMNI = [3.6313355285286337, 2138.7619122017772, 2131.5886210259278, 361.19856633263799, 248.27644773395667]
OMNI_D = [1.1757726639872075, 15.491281051140213, -8.1237172954550494e-04, 6.7297684030310243e-04]


def _cam(model="pinhole", dist="radtan", intr=EUROC_K, coeffs=EUROC_D, res=(752, 480), **extra):
    return dict(camera_model=model, distortion_model=dist, intrinsics=list(intr), distortion_coeffs=list(coeffs),
                resolution=list(res), rostopic="/cam0/image_raw", **extra)


def _write(path, doc):
    path.write_text(yaml.safe_dump(doc, default_flow_style=None))
    return path


def _points(seed=0, n=200, max_angle=0.9):
    """Points in front of the camera, up to ``max_angle`` rad off the axis, at 0.5-5 m."""
    g = np.random.default_rng(seed)
    th, ph = g.uniform(0, max_angle, n), g.uniform(-np.pi, np.pi, n)
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
    return d * g.uniform(0.5, 5.0, (n, 1))


def _project(cfg_path, P):
    cam = load_config(cfg_path).camera
    return cam.project(torch.from_numpy(P)).numpy()


def _K(k):
    return np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])


def test_pinhole_radtan_projects_as_opencv(tmp_path):
    chain = _write(tmp_path / "camchain.yaml", {"cam0": _cam()})
    s = run_make_config(tmp_path / "vins.yaml", kalibr=chain)
    assert s["flavour"] == "mono" and s["cameras"][0]["model_type"] == "PINHOLE" and s["extrinsic"] is None
    P = _points(max_angle=0.7)
    ref = cv2.projectPoints(P, np.zeros(3), np.zeros(3), _K(EUROC_K), np.array(EUROC_D))[0][:, 0]
    np.testing.assert_allclose(_project(tmp_path / "vins.yaml", P), ref, atol=1e-9, rtol=0)
    raw = read_opencv_yaml(tmp_path / "vins.yaml")
    # every tracker key at VINS-Mono's defaults; no extrinsic: VINS calibrates it
    assert {k: raw[k] for k in ("max_cnt", "min_dist", "freq", "F_threshold", "show_track", "equalize", "fisheye")} == \
        dict(max_cnt=150, min_dist=30, freq=10, F_threshold=1.0, show_track=1, equalize=1, fisheye=0)
    assert raw["estimate_extrinsic"] == 2 and "extrinsicRotation" not in raw and raw["image_topic"] == "/cam0/image_raw"


def test_pinhole_equi_projects_as_opencv_fisheye(tmp_path):
    chain = _write(tmp_path / "camchain.yaml", {"cam0": _cam(dist="equidistant", intr=TUMVI_K, coeffs=TUMVI_D,
                                                             res=(512, 512))})
    run_make_config(tmp_path / "tum.yaml", kalibr=chain)
    assert load_config(tmp_path / "tum.yaml").camera.model_type == "KANNALA_BRANDT"
    P = _points(1, max_angle=1.4)  # up to 80 degrees: a fisheye
    ref = cv2.fisheye.projectPoints(P[None], np.zeros(3), np.zeros(3), _K(TUMVI_K), np.array(TUMVI_D))[0][0]
    np.testing.assert_allclose(_project(tmp_path / "tum.yaml", P), ref, atol=1e-9, rtol=0)


def _omni_radtan(P, xi, fu, fv, pu, pv, k1, k2, p1, p2):
    """The unified (Mei) model as published (Mei & Rives 2007; Kalibr's omni-radtan): the point on
    the unit sphere, projected from xi behind its centre, radial-tangential distortion, intrinsics."""
    Xs = P / np.linalg.norm(P, axis=1, keepdims=True)
    z = Xs[:, 2] + xi
    x, y = Xs[:, 0] / z, Xs[:, 1] / z
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2
    xd = x + x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y + y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fu * xd + pu, fv * yd + pv], 1)


def test_omni_radtan_projects_as_the_unified_model(tmp_path):
    chain = _write(tmp_path / "camchain.yaml", {"cam0": _cam(model="omni", intr=OMNI, coeffs=OMNI_D)})
    run_make_config(tmp_path / "mei.yaml", kalibr=chain)
    cam = load_config(tmp_path / "mei.yaml").camera
    assert cam.model_type == "MEI" and float(cam.xi) == OMNI[0]
    P = _points(2, max_angle=0.5)
    np.testing.assert_allclose(_project(tmp_path / "mei.yaml", P), _omni_radtan(P, *OMNI, *OMNI_D), atol=1e-8, rtol=0)


def test_imucam_extrinsic_is_the_inverse_and_imu_noise(tmp_path):
    T_cam_imu = invert_rigid(T_BS)
    chain = _write(tmp_path / "camchain-imucam.yaml",
                   {"cam0": _cam(T_cam_imu=T_cam_imu.tolist(), timeshift_cam_imu=0.0025)})
    imu = _write(tmp_path / "imu.yaml", dict(accelerometer_noise_density=2.0e-3, accelerometer_random_walk=3.0e-3,
                                             gyroscope_noise_density=1.6968e-4, gyroscope_random_walk=1.9393e-5,
                                             rostopic="/imu0", update_rate=200.0))
    s = run_make_config(tmp_path / "vins.yaml", kalibr=chain, imu=imu)
    raw = read_opencv_yaml(tmp_path / "vins.yaml")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = raw["extrinsicRotation"], raw["extrinsicTranslation"][:, 0]
    np.testing.assert_allclose(T @ T_cam_imu, np.eye(4), atol=1e-12)  # body <- camera = T_cam_imu^-1
    np.testing.assert_allclose(T, T_BS, atol=1e-12)
    assert raw["estimate_extrinsic"] == 0 and raw["td"] == 0.0025 and s["extrinsic"].startswith("T_cam_imu")
    assert (raw["acc_n"], raw["acc_w"], raw["gyr_n"], raw["gyr_w"]) == (2.0e-3, 3.0e-3, 1.6968e-4, 1.9393e-5)
    assert raw["imu_topic"] == "/imu0"


def test_two_cameras_write_vins_fusion_layout(tmp_path):
    T1 = invert_rigid(T_BS)
    T_c1_c0 = np.eye(4)
    T_c1_c0[:3, 3] = [-0.11, 0.0004, -0.0009]
    chain = _write(tmp_path / "camchain-imucam.yaml", {
        "cam0": _cam(T_cam_imu=T1.tolist()),
        "cam1": _cam(model="omni", intr=OMNI, coeffs=OMNI_D, T_cam_imu=(T_c1_c0 @ T1).tolist(),
                     T_cn_cnm1=T_c1_c0.tolist())})
    s = run_make_config(tmp_path / "stereo.yaml", kalibr=chain)
    assert [p.split("/")[-1] for p in s["files"]] == ["stereo.yaml", "stereo_cam0.yaml", "stereo_cam1.yaml"]
    cfg = load_config(tmp_path / "stereo.yaml")
    assert cfg.flavour == "fusion" and cfg.num_of_cam == 2 and cfg.flow_back and cfg.raw["imu"] == 1
    assert (cfg.camera.model_type, cfg.camera1.model_type) == ("PINHOLE", "MEI")
    np.testing.assert_allclose(cfg.body_T_cam0, T_BS, atol=1e-12)
    np.testing.assert_allclose(cfg.body_T_cam1 @ T_c1_c0 @ T1, np.eye(4), atol=1e-12)
    # without an IMU: body = cam0, cam1 from T_cn_cnm1
    chain = _write(tmp_path / "camchain.yaml", {"cam0": _cam(), "cam1": _cam(T_cn_cnm1=T_c1_c0.tolist())})
    run_make_config(tmp_path / "noimu.yaml", kalibr=chain)
    cfg = load_config(tmp_path / "noimu.yaml")
    assert cfg.raw["imu"] == 0
    np.testing.assert_allclose(cfg.body_T_cam0, np.eye(4), atol=0)
    np.testing.assert_allclose(cfg.body_T_cam1 @ T_c1_c0, np.eye(4), atol=1e-12)


@pytest.mark.parametrize("cam, needles", [
    (_cam(model="ds", intr=[-0.2, 0.6, 350, 350, 376, 240], coeffs=[]), ["ds-", "double sphere", "cam0.camera_model"]),
    (_cam(model="eucm", intr=[0.6, 1.1, 350, 350, 376, 240], coeffs=[]), ["eucm", "extended unified"]),
    (_cam(dist="fov", coeffs=[0.9]), ["pinhole-fov", "field of view"]),
    (_cam(model="omni", dist="equidistant", intr=OMNI), ["omni-equidistant", "MEI"]),
    (_cam(intr=[0.0, 457.0, 367.0, 248.0]), ["cam0.intrinsics[0]", "> 0"]),
    (_cam(coeffs=[0.1, 0.2]), ["cam0.distortion_coeffs", "expected 4 numbers"]),
    (_cam(T_cam_imu=(2 * np.eye(4)).tolist()), ["cam0.T_cam_imu", "not a rigid transform"]),
])
def test_refused_calibrations_name_the_model_and_key(tmp_path, cam, needles):
    chain = _write(tmp_path / "camchain.yaml", {"cam0": cam})
    with pytest.raises(ConfigError) as e:
        read_kalibr_camchain(chain)
    for n in needles:
        assert n in str(e.value), (n, str(e.value))
    assert str(chain) in str(e.value)


def _camera_info(model="plumb_bob", D=(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0), K=EUROC_K):
    return dict(image_width=752, image_height=480, camera_name="narrow_stereo",
                camera_matrix=dict(rows=3, cols=3, data=_K(K).reshape(-1).tolist()), distortion_model=model,
                distortion_coefficients=dict(rows=1, cols=len(D), data=list(D)),
                rectification_matrix=dict(rows=3, cols=3, data=np.eye(3).reshape(-1).tolist()),
                projection_matrix=dict(rows=3, cols=4, data=np.eye(3, 4).reshape(-1).tolist()))


def test_camera_info(tmp_path):
    info = _write(tmp_path / "ost.yaml", _camera_info())
    run_make_config(tmp_path / "vins.yaml", camera_info=info)
    P = _points(3, max_angle=0.7)
    ref = cv2.projectPoints(P, np.zeros(3), np.zeros(3), _K(EUROC_K), np.array(EUROC_D))[0][:, 0]
    np.testing.assert_allclose(_project(tmp_path / "vins.yaml", P), ref, atol=1e-9, rtol=0)
    assert load_config(tmp_path / "vins.yaml").camera.camera_name == "narrow_stereo"
    fish = _write(tmp_path / "fish.yaml", _camera_info("equidistant", TUMVI_D, TUMVI_K))
    assert read_camera_info(fish).model_type == "KANNALA_BRANDT"
    for model, D, needles in (("plumb_bob", (-0.28, 0.07, 0.0, 0.0, 0.01), ["k3 = 0.01", "distortion_coefficients[4]"]),
                              ("rational_polynomial", (0.0,) * 8, ["'rational_polynomial'", "distortion_model"])):
        bad = _write(tmp_path / "bad.yaml", _camera_info(model, D))
        with pytest.raises(ConfigError) as e:
            read_camera_info(bad)
        for n in needles:
            assert n in str(e.value), (n, str(e.value))


def test_writer_reads_back_in_opencv(tmp_path):
    """``format_opencv_yaml``'s text means the same to ``cv2.FileStorage`` and to the project's reader."""
    m = np.arange(12.0).reshape(3, 4) / 7
    p = tmp_path / "w.yaml"
    p.write_text(format_opencv_yaml(["a comment", ("n", 3), ("x", 1e-5, "small"), ("s", "/cam0"), ("t", "PINHOLE"),
                                     ("m", m), ("d", {"fx": 461.5, "k1": -0.2917})], header=["head"]))
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    assert fs.getNode("n").real() == 3 and fs.getNode("x").real() == 1e-5 and fs.getNode("s").string() == "/cam0"
    assert fs.getNode("t").string() == "PINHOLE" and fs.getNode("d").getNode("k1").real() == -0.2917
    np.testing.assert_array_equal(fs.getNode("m").mat(), m)
    raw = read_opencv_yaml(p)
    np.testing.assert_array_equal(raw["m"], m)
    assert raw["x"] == 1e-5 and raw["d"] == {"fx": 461.5, "k1": -0.2917}
    with pytest.raises(ValueError, match="x: expected a finite number"):
        format_opencv_yaml([("x", float("nan"))])


def test_written_config_runs_track_as_the_sensor_yaml(tmp_path, capsys):
    """The round trip on the repo's sample: a camchain of its cam0 calibration -> ``config`` ->
    ``track``; the features equal those of ``track`` with the sample's own sensor.yaml (the same
    camera and VINS's front-end defaults). A second ``config`` replaces its own files, never a
    user's."""
    chain = _write(tmp_path / "camchain-imucam.yaml", {"cam0": _cam(T_cam_imu=invert_rigid(T_BS).tolist())})
    cfg = tmp_path / "cfg" / "vins.yaml"
    rc, stdout, err = run_cli(capsys, "config", "--from-kalibr", chain, "--out", cfg)
    assert rc == 0, err
    assert "VINS-Mono: cam0 PINHOLE 752x480" in stdout and "T_cam_imu" in stdout
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_config(cfg)  # no unknown key
    outs = []
    for argv in ([cfg], []):
        outs.append(tmp_path / f"run{len(outs)}")
        rc, _, err = run_cli(capsys, "track", *argv, "--euroc", SAMPLE, "--out", outs[-1], "--max-frames", 6,
                             "--no-tracks", "--no-progress")
        assert rc == 0, err
    a, b = (np.load(o / "features.npz") for o in outs)
    assert a["u"].size > 100
    for k in ("id", "u", "v", "x", "y", "stamp_ns"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    rc, _, err = run_cli(capsys, "config", "--from-kalibr", chain, "--out", cfg)  # its own file: replaced
    assert rc == 0, err
    mine = tmp_path / "mine.yaml"
    mine.write_text("%YAML:1.0\nmax_cnt: 10\n")
    rc, _, err = run_cli(capsys, "config", "--from-kalibr", chain, "--out", mine)
    assert rc == 2
    assert_one_error_line(err, "--out", str(mine), "not written by torch-frontend config")
    assert mine.read_text() == "%YAML:1.0\nmax_cnt: 10\n"
    rc, _, err = run_cli(capsys, "config", "--from-kalibr", tmp_path / "nope.yaml")
    assert rc == 2
    assert_one_error_line(err, "nope.yaml", "file not found")
    with pytest.raises(OptionError, match="^kalibr: give one calibration"):
        run_make_config(tmp_path / "x.yaml")
