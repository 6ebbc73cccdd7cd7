"""camodocal camera models: parity with independent numpy references and cv2, round trips over every
shipped calibration's image, the Kannala-Brandt root solver against the companion-matrix root,
gradchecks, config parsing and input errors (spec §1.6, §4)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

try:  # pytest registers tests/conftest.py as ``tests.conftest`` (rootdir on sys.path)
    from tests.conftest import REPO, SHARED_DATA, shared_data_or_skip
except ImportError:  # pragma: no cover - other import modes
    from conftest import REPO, SHARED_DATA, shared_data_or_skip

from torch_frontend.camera import (
    CameraModel,
    KannalaBrandtCamera,
    MeiCamera,
    PinholeCamera,
    PinholeFullCamera,
    ScaramuzzaCamera,
    camera_from_config,
)
from torch_frontend.camera.kannala_brandt import effective_coefficients, solve_theta
from torch_frontend.errors import ConfigError
from torch_frontend.opencv_yaml import read_opencv_yaml

# ---------------------------------------------------------------------------------------------
# Calibrations built in the test (spec §1.3 EuRoC values; others copied from the shipped configs
# so that these tests never depend on ../shared).
BUILTIN = {
    "euroc_pinhole": ("PINHOLE", dict(k1=-2.917e-01, k2=8.228e-02, p1=5.333e-05, p2=-1.578e-04,
                                      fx=4.616e02, fy=4.603e02, cx=3.630e02, cy=2.481e02), 752, 480),
    "realsense_color": ("PINHOLE", dict(k1=0.09261550446502885, k2=-0.1808243882599568, p1=-0.0006548410037476597,
                                        p2=-0.0003582935155855742, fx=609.7055029679804, fy=609.0957967129472,
                                        cx=319.1666715228923, cy=235.58360480225772), 640, 480),
    "kitti_nodist": ("PINHOLE", dict(k1=0.0, k2=0.0, p1=0.0, p2=0.0, fx=718.856, fy=718.856, cx=607.1928,
                                     cy=185.2157), 1241, 376),
    "3dm_mei": ("MEI", dict(xi=2.057, k1=0.07145, k2=0.5059, p1=4.727e-05, p2=-0.0005492, gamma1=1115.0,
                            gamma2=1114.0, u0=367.2, v0=238.5), 752, 480),
    "euroc_cam0_mei": ("MEI", dict(xi=3.6313355285286337, k1=1.1757726639872075, k2=15.491281051140213,
                                   p1=-0.0008123717295455049, p2=0.0006729768403031024, gamma1=2138.7619122017772,
                                   gamma2=2131.5886210259278, u0=361.198566332638, v0=248.27644773395667), 752, 480),
    "euroc_cam1_mei": ("MEI", dict(xi=0.8126150589414611, k1=-0.34247886078397966, k2=0.17108792755973357,
                                   p1=-0.0006665314436490669, p2=0.0007231125584676709, gamma1=834.0624973543779,
                                   gamma2=831.4060676591695, u0=374.3200735524974, v0=254.22391621480082), 752, 480),
    "tum_kb": ("KANNALA_BRANDT", dict(k2=0.0034823894022493434, k3=0.0007150348452162257, k4=-0.0020532361418706202,
                                      k5=0.00020293673591811182, mu=190.97847715128717, mv=190.9733070521226,
                                      u0=254.93170605935475, v0=256.8974428996504), 512, 512),
    "cla_kb": ("KANNALA_BRANDT", dict(k2=-0.005740195474458931, k3=0.02878252863739417, k4=-0.04010621197185408,
                                      k5=0.02008469575876223, mu=472.2863830700696, mv=470.83759684346785,
                                      u0=368.8316828103749, v0=232.23688706965652), 752, 480),
    "realsense_fisheye_kb": ("KANNALA_BRANDT", dict(k2=0.01728035503519518, k3=-0.025505200860040985,
                                                    k4=0.022621441637715487, k5=-0.007335587171973111,
                                                    mu=277.237120544082, mv=276.99784668734617,
                                                    u0=336.2535687398587, v0=236.039247274539), 640, 480),
    "pinhole_full": ("PINHOLE_FULL", dict(k1=-0.28, k2=0.07, k3=-0.002, k4=0.01, k5=-0.003, k6=0.001,
                                          p1=2e-4, p2=-1e-4, fx=460.0, fy=459.0, cx=370.0, cy=250.0), 752, 480),
}
CLASSES = {"PINHOLE": PinholeCamera, "MEI": MeiCamera, "KANNALA_BRANDT": KannalaBrandtCamera,
           "PINHOLE_FULL": PinholeFullCamera}


def builtin(name, **kw):
    mt, p, w, h = BUILTIN[name]
    return CLASSES[mt](**p, width=w, height=h, **kw)


def _camera_files(root: Path):
    """Camera YAMLs (files with a model_type) under root, sorted."""
    out = []
    if root.exists():
        for f in sorted(root.rglob("*.yaml")):
            try:
                node = read_opencv_yaml(f)
            except ConfigError:
                continue
            if "model_type" in node:
                out.append(f)
    return out


SHARED_CONFIGS = SHARED_DATA / "vins_configs"
SHARED_FILES = _camera_files(SHARED_CONFIGS)
REPO_FILES = _camera_files(REPO / "configs")
FILE_IDS = [str(f.relative_to(SHARED_CONFIGS)) for f in SHARED_FILES]


def _file_params():
    if SHARED_FILES:
        return [pytest.param(f, id=i) for f, i in zip(SHARED_FILES, FILE_IDS)]
    return [pytest.param(None, id="shared-absent")]


def _repo_params():
    if REPO_FILES:
        return [pytest.param(f, id=f"repo:{f.name}") for f in REPO_FILES]
    return [pytest.param(None, id="repo-configs-absent")]


def shared_camera(f):
    if f is None:
        shared_data_or_skip("vins_configs")
        pytest.skip("no camodocal camera YAML under ../shared/data/vins_configs")
    return camera_from_config(read_opencv_yaml(f), f)


def repo_camera(f):
    if f is None:
        pytest.skip("no camera YAML in configs/ yet")
    return camera_from_config(read_opencv_yaml(f), f)


def grid(cam, nx=48, ny=36, dtype=torch.float64, device="cpu"):
    """Pixel grid over the whole image (borders included), (ny, nx, 2)."""
    u = torch.linspace(0, cam.width - 1, nx, dtype=dtype, device=device)
    v = torch.linspace(0, cam.height - 1, ny, dtype=dtype, device=device)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack((uu, vv), dim=-1)


# ---------------------------------------------------------------------------------------------
# Independent float64 numpy references (written from the spec's formulas).
def np_radtan(x, y, k1, k2, p1, p2):
    mx2, my2, mxy = x * x, y * y, x * y
    rho2 = mx2 + my2
    rad = k1 * rho2 + k2 * rho2 * rho2
    return (x * rad + 2.0 * p1 * mxy + p2 * (rho2 + 2.0 * mx2),
            y * rad + 2.0 * p2 * mxy + p1 * (rho2 + 2.0 * my2))


def np_fixed_point(mxd, myd, k1, k2, p1, p2, n=8):
    if k1 == 0 and k2 == 0 and p1 == 0 and p2 == 0:
        return mxd, myd
    dx, dy = np_radtan(mxd, myd, k1, k2, p1, p2)
    mxu, myu = mxd - dx, myd - dy
    for _ in range(n - 1):
        dx, dy = np_radtan(mxu, myu, k1, k2, p1, p2)
        mxu, myu = mxd - dx, myd - dy
    return mxu, myu


def np_pinhole_lift(uv, k1, k2, p1, p2, fx, fy, cx, cy, n=8):
    mxu, myu = np_fixed_point((uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy, k1, k2, p1, p2, n)
    return np.stack((mxu, myu, np.ones_like(mxu)), -1)


def np_mei_lift(uv, xi, k1, k2, p1, p2, gamma1, gamma2, u0, v0, n=8):
    mxu, myu = np_fixed_point((uv[..., 0] - u0) / gamma1, (uv[..., 1] - v0) / gamma2, k1, k2, p1, p2, n)
    rho2 = mxu * mxu + myu * myu
    if xi == 1:
        z = (1.0 - rho2) / 2.0
    else:
        with np.errstate(invalid="ignore"):
            z = 1.0 - xi * (rho2 + 1.0) / (xi + np.sqrt(1.0 + (1.0 - xi * xi) * rho2))
    return np.stack((mxu, myu, z), -1)


def np_mei_project(P, xi, k1, k2, p1, p2, gamma1, gamma2, u0, v0):
    zp = P[..., 2] + xi * np.linalg.norm(P, axis=-1)
    x, y = P[..., 0] / zp, P[..., 1] / zp
    dx, dy = np_radtan(x, y, k1, k2, p1, p2)
    return np.stack((gamma1 * (x + dx) + u0, gamma2 * (y + dy) + v0), -1)


def np_kb_theta(rho, k2, k3, k4, k5):
    """camodocal's companion-matrix root (spec §4.3), degree quirk included, vectorised over rho."""
    rho = np.asarray(rho, dtype=np.float64).reshape(-1)
    ks = [k2, k3, k4, k5]
    npow = 9 - 2 * sum(k == 0 for k in ks)
    if npow == 1:
        return rho.copy()
    c = np.zeros((rho.size, 10))
    c[:, 0] = -rho
    c[:, 1] = 1.0
    c[:, 3], c[:, 5], c[:, 7], c[:, 9] = k2, k3, k4, k5
    A = np.zeros((rho.size, npow, npow))
    A[:, 1:, :-1] = np.eye(npow - 1)
    A[:, :, -1] = -c[:, :npow] / c[:, npow:npow + 1]
    ev = np.linalg.eigvals(A)
    keep = (np.abs(ev.imag) <= 1e-10) & (ev.real >= -1e-10)
    re = np.where(ev.real < 0, 0.0, ev.real)
    th = np.where(keep, re, np.inf).min(axis=1)
    return np.where(np.isfinite(th), th, rho)


def np_kb_project(P, k2, k3, k4, k5, mu, mv, u0, v0):
    theta = np.arccos(P[..., 2] / np.linalg.norm(P, axis=-1))
    phi = np.arctan2(P[..., 1], P[..., 0])
    r = theta + k2 * theta**3 + k3 * theta**5 + k4 * theta**7 + k5 * theta**9
    return np.stack((mu * r * np.cos(phi) + u0, mv * r * np.sin(phi) + v0), -1)


def np_full_lift(uv, k1, k2, k3, k4, k5, k6, p1, p2, fx, fy, cx, cy, n=9):
    x0 = (uv[..., 0] - cx) / fx
    y0 = (uv[..., 1] - cy) / fy
    x, y = x0, y0
    for _ in range(n):
        r2 = x * x + y * y
        icdist = (1 + ((k6 * r2 + k5) * r2 + k4) * r2) / (1 + ((k3 * r2 + k2) * r2 + k1) * r2)
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x, y = (x0 - dx) * icdist, (y0 - dy) * icdist
    return np.stack((x, y, np.ones_like(x)), -1)


def np_scaramuzza_lift(uv, poly, inv_poly, ac, ad, ae, cx, cy):
    xc = uv[..., 0] - cx, uv[..., 1] - cy
    s = 1.0 / (ac - ad * ae)
    xa = s * (xc[0] - ad * xc[1]), s * (-ae * xc[0] + ac * xc[1])
    phi = np.hypot(*xa)
    z = sum(c * phi**i for i, c in enumerate(poly))
    return np.stack((xc[0], xc[1], -z), -1)


def np_scaramuzza_project(P, poly, inv_poly, ac, ad, ae, cx, cy):
    n = np.hypot(P[..., 0], P[..., 1])
    theta = np.arctan2(-P[..., 2], n)
    rho = sum(c * theta**i for i, c in enumerate(inv_poly))
    xn = P[..., 0] / n * rho, P[..., 1] / n * rho
    return np.stack((ac * xn[0] + ad * xn[1] + cx, ae * xn[0] + xn[1] + cy), -1)


def valid_ray(P):
    return torch.isfinite(P).all(-1) & (P[..., 2] > 0)


def converged(cam):
    """Same calibration with a converged fixed point (64 evaluations) for pinhole/MEI."""
    if isinstance(cam, (PinholeCamera, MeiCamera, PinholeFullCamera)):
        return type(cam).from_params(cam.params_dict(), width=cam.width, height=cam.height, undistort_iters=64)
    return cam


# ---------------------------------------------------------------------------------------------
# Round trips over every calibration's image grid.
def _round_trip_err(cam, dtype=torch.float64, device="cpu"):
    cam = converged(cam).to(device)
    uv = grid(cam, dtype=dtype, device=device)
    P = cam.lift(uv)
    ok = valid_ray(P)
    err = (cam.project(P) - uv).norm(dim=-1)
    assert ok.float().mean() > 0.5
    return err[ok].max().item(), P


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_round_trip_builtin(name, device, dtype):
    cam = builtin(name)
    err, P = _round_trip_err(cam, dtype, device)
    assert P.dtype == dtype and P.device.type == device.type
    tol = 1e-6 if dtype == torch.float64 else 5e-3
    assert err < tol, f"{name}: round trip {err:.3g} px"


@pytest.mark.parametrize("path", _file_params())
def test_round_trip_shared_configs(path):
    cam = shared_camera(path)
    err, _ = _round_trip_err(cam)
    assert err < 1e-6, f"{path}: round trip {err:.3g} px"


@pytest.mark.parametrize("path", _repo_params())
def test_round_trip_repo_configs(path):
    cam = repo_camera(path)
    err, _ = _round_trip_err(cam)
    assert err < 1e-6, f"{path}: round trip {err:.3g} px"


@pytest.mark.parametrize("path", _file_params())
def test_default_lift_matches_numpy_reference_shared(path):
    """With upstream's iteration counts, lift equals the numpy transcription of the spec exactly and
    the round trip reproduces upstream's own (unconverged) residual."""
    cam = shared_camera(path)
    uv = grid(cam)
    P = cam.lift(uv).numpy()
    p = cam.params_dict()
    if isinstance(cam, PinholeCamera):
        ref = np_pinhole_lift(uv.numpy(), **p)
    elif isinstance(cam, MeiCamera):
        ref = np_mei_lift(uv.numpy(), **p)
    else:
        theta = np_kb_theta(np.hypot((uv[..., 0].numpy() - p["u0"]) / p["mu"], (uv[..., 1].numpy() - p["v0"]) / p["mv"]),
                            p["k2"], p["k3"], p["k4"], p["k5"]).reshape(uv.shape[:-1])
        got = np.arctan2(np.hypot(P[..., 0], P[..., 1]), P[..., 2])  # θ of the unit ray (atan2: exact near 0)
        assert np.abs(got - theta).max() < 1e-9
        return
    assert np.abs(P - ref).max() <= 1e-12


# ---------------------------------------------------------------------------------------------
# Pinhole vs cv2 and the numpy fixed point.
def _K(fx, fy, cx, cy):
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


@pytest.mark.parametrize("name", ["euroc_pinhole", "realsense_color"])
def test_pinhole_project_vs_cv2(name):
    cam = builtin(name)
    p = cam.params_dict()
    rng = np.random.default_rng(0)
    P = np.concatenate((rng.uniform(-0.8, 0.8, (500, 2)), np.ones((500, 1))), -1) * rng.uniform(0.5, 20, (500, 1))
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), _K(p["fx"], p["fy"], p["cx"], p["cy"]),
                               np.array([p["k1"], p["k2"], p["p1"], p["p2"]]))
    got = cam.project(torch.from_numpy(P)).numpy()
    assert np.abs(got - ref[:, 0]).max() < 1e-6


@pytest.mark.parametrize("name", ["euroc_pinhole", "realsense_color", "kitti_nodist"])
def test_pinhole_lift_vs_fixed_point_and_cv2(name):
    cam = builtin(name)
    p = cam.params_dict()
    uv = grid(cam).reshape(-1, 2)
    got = cam.lift(uv).numpy()
    ref = np_pinhole_lift(uv.numpy(), **p)
    assert np.abs(got - ref).max() <= 1e-12  # the 8-evaluation fixed point, bit-level parity
    # cv2 with a converged iteration: the 8-step result differs from it by about the fixed point's
    # own residual |m_u + d(m_u) - m_d| (the inverse Jacobian of the distortion is ~1-2 here).
    cv = cv2.undistortPointsIter(uv.numpy()[:, None], _K(p["fx"], p["fy"], p["cx"], p["cy"]),
                                 np.array([p["k1"], p["k2"], p["p1"], p["p2"]]), np.eye(3), None,
                                 (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))[:, 0]
    mxd = (uv.numpy() - [p["cx"], p["cy"]]) / [p["fx"], p["fy"]]
    dx, dy = np_radtan(got[:, 0], got[:, 1], p["k1"], p["k2"], p["p1"], p["p2"])
    resid = np.hypot(got[:, 0] + dx - mxd[:, 0], got[:, 1] + dy - mxd[:, 1])
    diff = np.hypot(*(got[:, :2] - cv).T)
    assert np.all(diff <= 3 * resid + 1e-12)
    # and with a converged fixed point, lift equals cv2 to 1e-6 px
    conv = converged(cam).lift(uv).numpy()
    assert np.abs((conv[:, :2] - cv) * [p["fx"], p["fy"]]).max() < 1e-6


def test_pinhole_full_vs_cv2_and_numpy():
    cam = builtin("pinhole_full")
    p = cam.params_dict()
    D = np.array([p["k1"], p["k2"], p["p1"], p["p2"], p["k3"], p["k4"], p["k5"], p["k6"]])
    K = _K(p["fx"], p["fy"], p["cx"], p["cy"])
    rng = np.random.default_rng(1)
    P = np.concatenate((rng.uniform(-0.7, 0.7, (400, 2)), np.ones((400, 1))), -1)
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, D)
    assert np.abs(cam.project(torch.from_numpy(P)).numpy() - ref[:, 0]).max() < 1e-6
    uv = grid(cam).reshape(-1, 2)
    assert np.abs(cam.lift(uv).numpy() - np_full_lift(uv.numpy(), **p)).max() <= 1e-12
    cv = cv2.undistortPointsIter(uv.numpy()[:, None], K, D, np.eye(3), None,
                                 (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))[:, 0]
    conv = converged(cam).lift(uv).numpy()
    assert np.abs((conv[:, :2] - cv) * [p["fx"], p["fy"]]).max() < 1e-6


# ---------------------------------------------------------------------------------------------
# MEI vs numpy.
@pytest.mark.parametrize("name", ["3dm_mei", "euroc_cam0_mei", "euroc_cam1_mei"])
def test_mei_vs_numpy(name):
    cam = builtin(name)
    p = cam.params_dict()
    uv = grid(cam).reshape(-1, 2)
    got = cam.lift(uv).numpy()
    assert np.abs(got - np_mei_lift(uv.numpy(), **p)).max() <= 1e-12
    rng = np.random.default_rng(2)
    P = np.concatenate((rng.uniform(-0.5, 0.5, (300, 2)), np.ones((300, 1))), -1) * rng.uniform(0.5, 9, (300, 1))
    assert np.abs(cam.project(torch.from_numpy(P)).numpy() - np_mei_project(P, **p)).max() < 1e-9


def test_mei_xi_one_and_invalid_lanes():
    cam = MeiCamera(1.0, -0.1, 0.01, 0.0, 0.0, 400.0, 400.0, 320.0, 240.0, width=640, height=480)
    uv = grid(cam, 9, 7).reshape(-1, 2)
    P = cam.lift(uv)
    ref = np_mei_lift(uv.numpy(), **cam.params_dict())
    assert np.abs(P.numpy() - ref).max() <= 1e-15  # the (1 - rho²)/2 branch
    # xi > 1 beyond rho² = 1/(xi² - 1): upstream's sqrt is NaN; the value is NaN but gradients of the
    # other lanes stay finite.
    cam2 = MeiCamera(2.0, 0.0, 0.0, 0.0, 0.0, 100.0, 100.0, 0.0, 0.0).requires_grad_()
    uv2 = torch.tensor([[10.0, 0.0], [90.0, 0.0]], dtype=torch.float64, requires_grad=True)  # rho² .01, .81 > 1/3
    P2 = cam2.lift(uv2)
    assert torch.isfinite(P2[0]).all() and torch.isnan(P2[1, 2])
    P2[0].sum().backward()
    assert torch.isfinite(uv2.grad).all() and torch.isfinite(cam2.xi.grad)


# ---------------------------------------------------------------------------------------------
# Kannala-Brandt: cv2.fisheye parity and the root solver vs the companion matrix.
def _kb_file_params():
    files = [f for f in SHARED_FILES if read_opencv_yaml(f)["model_type"].upper() == "KANNALA_BRANDT"]
    if files:
        return [pytest.param(f, id=str(f.relative_to(SHARED_CONFIGS))) for f in files]
    return [pytest.param(None, id="shared-absent")]


@pytest.mark.parametrize("name", ["tum_kb", "cla_kb", "realsense_fisheye_kb"])
def test_kb_vs_cv2_fisheye(name):
    cam = builtin(name)
    p = cam.params_dict()
    K = _K(p["mu"], p["mv"], p["u0"], p["v0"])
    D = np.array([p["k2"], p["k3"], p["k4"], p["k5"]])
    rng = np.random.default_rng(3)
    P = np.concatenate((rng.uniform(-1.2, 1.2, (400, 2)), np.ones((400, 1))), -1)
    ref, _ = cv2.fisheye.projectPoints(P[:, None], np.zeros(3), np.zeros(3), K, D)
    assert np.abs(cam.project(torch.from_numpy(P)).numpy() - ref[:, 0]).max() < 1e-6
    uv = grid(cam).reshape(-1, 2)
    ray = cam.lift(uv)
    front = ray[:, 2].numpy() > 0.05  # cv2.fisheye works in x/z, meaningful in front of the camera
    cvn = cv2.fisheye.undistortPoints(uv.numpy()[:, None], K, D,
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15))[:, 0]
    ok = front & (np.abs(cvn) < 1e5).all(-1)
    assert ok.mean() > 0.5
    cv_ray = np.concatenate((cvn, np.ones((len(cvn), 1))), -1)
    cv_ray /= np.linalg.norm(cv_ray, axis=-1, keepdims=True)
    ang = np.arccos(np.clip((cv_ray * ray.numpy()).sum(-1), -1, 1))
    # angle x focal length ≈ pixels; acos of a dot product resolves ~1e-8 rad, so compare the
    # difference vector instead
    dvec = np.linalg.norm(cv_ray - ray.numpy(), axis=-1)
    assert (dvec[ok] * p["mu"]).max() < 1e-6, (ang[ok].max(), dvec[ok].max())


def _kb_solver_err(p, W, H):
    u, v = np.meshgrid(np.linspace(0, W - 1, 64), np.linspace(0, H - 1, 48))
    rho = np.hypot((u - p["u0"]) / p["mu"], (v - p["v0"]) / p["mv"]).ravel()
    ref = np_kb_theta(rho, p["k2"], p["k3"], p["k4"], p["k5"])
    ks = [torch.tensor(p[k], dtype=torch.float64) for k in ("k2", "k3", "k4", "k5")]
    got = solve_theta(torch.from_numpy(rho), *effective_coefficients(*ks)).numpy()
    return np.abs(got - ref).max()


@pytest.mark.parametrize("name", ["tum_kb", "cla_kb", "realsense_fisheye_kb"])
def test_kb_solver_vs_companion_builtin(name):
    _, p, W, H = BUILTIN[name]
    assert _kb_solver_err(p, W, H) <= 1e-9


@pytest.mark.parametrize("path", _kb_file_params())
def test_kb_solver_vs_companion_shared(path):
    cam = shared_camera(path)
    assert isinstance(cam, KannalaBrandtCamera)
    assert _kb_solver_err(cam.params_dict(), cam.width, cam.height) <= 1e-9


@pytest.mark.parametrize(
    "ks",
    [
        (-0.3, 0.02, 0.001, 1e-4),  # non-monotone r: a local max, the smallest root may jump to a far one
        (0.01, -0.3, 0.05, -0.002),  # r -> -inf: no root for large rho (fallback θ = ρ)
        (0.01, 0.0, 0.02, 0.003),  # degree quirk: k3 == 0 drops the k5 θ⁹ term
        (0.0, 0.0, 0.0, 0.0),  # npow == 1: θ = ρ
        (0.02, 0.0, 0.0, 0.001),  # two zeros: degree 5, θ⁵ term k3 == 0 => our truncation (see deviation)
    ],
)
def test_kb_solver_hard_cases(ks):
    rho = np.linspace(0, 4.0, 2001)
    k = [torch.tensor(x, dtype=torch.float64) for x in ks]
    got = solve_theta(torch.from_numpy(rho), *effective_coefficients(*k)).numpy()
    if ks == (0.02, 0.0, 0.0, 0.001):
        # upstream: degree 5 with leading coefficient k3 == 0 -> division by zero in its companion matrix.
        # We solve θ + 0.02 θ³ = ρ instead (the θ⁹ term is dropped by the quirk, the θ⁵ term is 0).
        ref = np_kb_theta(rho, 0.02, 0.0, 0.0, 0.0)
    else:
        ref = np_kb_theta(rho, *ks)
    assert np.abs(got - ref).max() <= 1e-9


def test_kb_axis_and_gradients_finite():
    cam = builtin("tum_kb").requires_grad_()
    uv = torch.tensor([[cam.u0.item(), cam.v0.item()], [10.0, 20.0]], dtype=torch.float64, requires_grad=True)
    P = cam.lift(uv)
    assert torch.allclose(P[0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    P.sum().backward()
    assert torch.isfinite(uv.grad).all() and all(torch.isfinite(q.grad).all() for q in cam.parameters())
    Q = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64, requires_grad=True)
    cam.project(Q).sum().backward()
    assert torch.isfinite(Q.grad).all()
    assert torch.allclose(cam.project(Q.detach()), torch.stack((cam.u0, cam.v0)).detach()[None])


# ---------------------------------------------------------------------------------------------
# Scaramuzza (no shipped config: calibrations made here).
def _ocam(ac=1.0, ad=0.0, ae=0.0):
    """A plausible OCAM calibration; inv_poly is a least-squares fit of the inverse of poly."""
    poly = np.array([-230.0, 0.0, 1.2e-3, -5e-7, 1e-9])
    phi = np.linspace(0.0, 420.0, 4000)
    theta = np.arctan2(sum(c * phi**i for i, c in enumerate(poly)), phi)  # project: atan2(-Z, n), Z = -poly(φ)
    deg = 16
    inv = np.polynomial.polynomial.polyfit(theta, phi, deg)
    inv_poly = np.zeros(20)
    inv_poly[: deg + 1] = inv
    fit = np.abs(np.polynomial.polynomial.polyval(theta, inv) - phi).max()
    cam = ScaramuzzaCamera(poly, inv_poly, ac, ad, ae, 400.5, 300.25, width=800, height=600)
    return cam, fit


def test_scaramuzza_round_trip_identity_affine():
    cam, fit = _ocam()
    assert fit < 1e-6
    uv = grid(cam).reshape(-1, 2)
    uv = uv[(uv - torch.tensor([400.5, 300.25], dtype=torch.float64)).norm(dim=-1) < 410]
    err = (cam.project(cam.lift(uv)) - uv).norm(dim=-1).max().item()
    assert err <= fit + 1e-9


def test_scaramuzza_quirk_and_numpy():
    cam, fit = _ocam(ac=1.02, ad=0.01, ae=-0.015)
    p = cam.params_dict()
    uv = grid(cam).reshape(-1, 2)
    uv = uv[(uv - torch.tensor([400.5, 300.25], dtype=torch.float64)).norm(dim=-1) < 380]
    P = cam.lift(uv)
    assert np.abs(P.numpy() - np_scaramuzza_lift(uv.numpy(), **p)).max() < 1e-9
    # the quirk: x, y are the *uncorrected* offsets from the centre
    assert torch.equal(P[:, :2], uv - torch.tensor([400.5, 300.25], dtype=torch.float64))
    assert np.abs(cam.project(P).numpy() - np_scaramuzza_project(P.numpy(), **p)).max() < 1e-9
    rt = (cam.project(P) - uv).norm(dim=-1).max().item()
    assert rt > 1.0  # so project(lift(uv)) != uv with a non-identity affine part ...
    # ... while the reference form (x, y = affine-corrected xa) does round-trip
    s = 1.0 / (p["ac"] - p["ad"] * p["ae"])
    xc = uv - torch.tensor([400.5, 300.25], dtype=torch.float64)
    xa = torch.stack((s * (xc[:, 0] - p["ad"] * xc[:, 1]), s * (-p["ae"] * xc[:, 0] + p["ac"] * xc[:, 1])), -1)
    P_ref = torch.cat((xa, P[:, 2:]), -1)
    assert (cam.project(P_ref) - uv).norm(dim=-1).max().item() < 2 * fit + 1e-9
    # on the axis upstream divides by zero; we return the centre
    assert torch.allclose(cam.project(torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)),
                          torch.tensor([400.5, 300.25], dtype=torch.float64))


# ---------------------------------------------------------------------------------------------
# Gradients.
def _all_cams():
    cams = {n: builtin(n) for n in ("euroc_pinhole", "kitti_nodist", "euroc_cam1_mei", "3dm_mei", "tum_kb",
                                    "realsense_fisheye_kb", "pinhole_full")}
    cams["mei_xi1"] = MeiCamera(1.0, -0.1, 0.01, 1e-3, -1e-3, 400.0, 400.0, 320.0, 240.0, width=640, height=480)
    cams["ocam"] = _ocam(ac=1.02, ad=0.01, ae=-0.015)[0]
    return cams


GRAD_CAMS = _all_cams()


@pytest.mark.parametrize("name", sorted(GRAD_CAMS))
def test_gradcheck_lift_and_project(name):
    cam = GRAD_CAMS[name]
    names = cam.param_names
    params = [getattr(cam, n).detach().clone().requires_grad_() for n in names]
    c = torch.tensor([cam.width / 2, cam.height / 2], dtype=torch.float64)
    uv = (c + torch.tensor([[0.0, 0.0], [37.3, -21.1], [-150.2, 90.7], [200.1, 160.3]], dtype=torch.float64))
    if name == "euroc_pinhole" or name == "kitti_nodist":
        uv[0] = c + 0.25  # the exact centre is fine too, but keep the fixed point away from trivial zeros
    uv.requires_grad_()

    def lift(uv, *ps):
        return cam._lift_impl(uv, **dict(zip(names, ps)))

    def project(P, *ps):
        return cam._project_impl(P, **dict(zip(names, ps)))

    assert torch.autograd.gradcheck(lift, (uv, *params), eps=1e-6, atol=1e-6, rtol=1e-5)
    P = cam.lift(uv.detach())
    if name == "ocam":
        P = P[1:]  # the centre pixel maps onto the axis, where the direction (and derivative) is undefined
    P = (P * torch.tensor([[1.3], [0.7], [2.0], [1.1]], dtype=torch.float64)[: len(P)]).requires_grad_()
    assert torch.autograd.gradcheck(project, (P, *params), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_public_api_gradients_reach_parameters():
    cam = builtin("euroc_pinhole")
    assert not any(p.requires_grad for p in cam.parameters())
    cam.requires_grad_()
    uv = torch.tensor([[100.0, 50.0], [700.0, 400.0]], dtype=torch.float32)  # float32 input, float64 params
    out = cam.lift(uv)
    assert out.dtype == torch.float32
    out.sum().backward()
    assert cam.k1.grad is not None and cam.k1.grad.dtype == torch.float64 and cam.k1.grad.abs() > 0
    # zero distortion: the no-distortion shortcut does not cut the coefficient gradients
    cam0 = builtin("kitti_nodist").requires_grad_()
    cam0.lift(torch.tensor([[10.0, 20.0]], dtype=torch.float64)).sum().backward()
    assert cam0.k1.grad.abs() > 0


# ---------------------------------------------------------------------------------------------
# Module behaviour: dtype/device, repr, params, undistort.
def test_module_to_dtype_device_and_repr(device):
    cam = builtin("euroc_cam1_mei")
    cam32 = builtin("euroc_cam1_mei").to(device=device, dtype=torch.float32)
    assert cam32.xi.dtype == torch.float32 and cam32.xi.device.type == device.type
    uv = grid(cam, 8, 6, torch.float32, device)
    a = cam32.lift(uv)
    b = cam.lift(uv.double().cpu())
    assert a.dtype == torch.float32 and torch.allclose(a.double().cpu(), b, atol=1e-5)
    # integer pixels are accepted and computed in the camera's dtype
    assert cam.lift(torch.tensor([[100, 200]])).dtype == torch.float64
    r = repr(cam)
    assert r.startswith("MeiCamera(") and "xi=0.8126150589414611" in r and "width=752" in r
    assert isinstance(cam, CameraModel) and cam.model_type == "MEI" and cam.camera_name == "camera"
    p = cam.params_dict()
    cam2 = MeiCamera.from_params(p, width=752, height=480)
    assert cam2.params_dict() == p
    # undistort = (x/z, y/z) of lift, leading dims preserved
    uvb = grid(cam, 5, 4).expand(3, 2, 4, 5, 2)
    und = cam.undistort(uvb)
    P = cam.lift(uvb)
    assert und.shape == (3, 2, 4, 5, 2) and torch.equal(und, P[..., :2] / P[..., 2:])
    assert torch.equal(cam.forward(P), cam.project(P))


def test_constructor_errors():
    with pytest.raises(ValueError, match="missing"):
        PinholeCamera.from_params({"k1": 0.0})
    with pytest.raises(ValueError, match=r"inv_poly: expected shape \(20,\)"):
        ScaramuzzaCamera(np.zeros(5), np.zeros(19), 1, 0, 0, 0, 0)
    with pytest.raises(ValueError, match="undistort_iters"):
        builtin("euroc_pinhole", undistort_iters=0)


@pytest.mark.parametrize("name", ["euroc_pinhole", "tum_kb"])
def test_shape_errors(name):
    cam = builtin(name)
    with pytest.raises(ValueError, match=r"uv: expected shape \(\*, 2\), got \(4, 3\)"):
        cam.lift(torch.zeros(4, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"P: expected shape \(\*, 3\), got \(5, 2\)"):
        cam.project(torch.zeros(5, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="uv: expected shape"):
        cam.undistort(torch.zeros(3, dtype=torch.float64))
    with pytest.raises(TypeError):
        cam.lift(np.zeros((2, 2)))


# ---------------------------------------------------------------------------------------------
# Config parsing.
def _node(mt="PINHOLE"):
    n = {"model_type": mt, "camera_name": "camera", "image_width": 752, "image_height": 480}
    if mt.upper() in ("PINHOLE", "MEI"):
        n["distortion_parameters"] = {"k1": -0.2917, "k2": 0.08228, "p1": 5.333e-05, "p2": -0.0001578}
    if mt.upper() == "PINHOLE":
        n["projection_parameters"] = {"fx": 461.6, "fy": 460.3, "cx": 363.0, "cy": 248.1}
    if mt.upper() == "MEI":
        n["mirror_parameters"] = {"xi": 2.0}
        n["projection_parameters"] = {"gamma1": 1100.0, "gamma2": 1100.0, "u0": 367.0, "v0": 238.0}
    if mt.upper() == "KANNALA_BRANDT":
        n["projection_parameters"] = dict(BUILTIN["tum_kb"][1])
    if mt.upper() == "PINHOLE_FULL":
        n["distortion_parameters"] = {k: BUILTIN["pinhole_full"][1][k] for k in
                                      ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")}
        n["projection_parameters"] = {"fx": 460.0, "fy": 459.0, "cx": 370.0, "cy": 250.0}
    if mt.lower() == "scaramuzza":
        n["poly_parameters"] = {f"p{i}": v for i, v in enumerate([-230.0, 0.0, 1.2e-3, -5e-7, 1e-9])}
        n["inv_poly_parameters"] = {f"p{i}": float(i) for i in range(20)}
        n["affine_parameters"] = {"ac": 1.0, "ad": 0.0, "ae": 0.0, "cx": 400.0, "cy": 300.0}
    return n


@pytest.mark.parametrize(
    "mt,cls",
    [("PINHOLE", PinholeCamera), ("pinhole", PinholeCamera), ("MEI", MeiCamera), ("Kannala_Brandt", KannalaBrandtCamera),
     ("scaramuzza", ScaramuzzaCamera), ("SCARAMUZZA", ScaramuzzaCamera), ("PINHOLE_FULL", PinholeFullCamera)],
)
def test_config_models(mt, cls):
    cam = camera_from_config(_node(mt))
    assert type(cam) is cls and cam.width == 752 and cam.height == 480 and cam.camera_name == "camera"
    if cls is ScaramuzzaCamera:
        assert cam.inv_poly.shape == (20,) and cam.inv_poly[19].item() == 19.0


def test_config_absent_model_type_is_mei():
    n = _node("MEI")
    del n["model_type"]
    assert isinstance(camera_from_config(n), MeiCamera)
    # a VINS-Fusion top-level config has no camera block: MEI is assumed and the error says why
    with pytest.raises(ConfigError, match="cam0_calib") as ei:
        camera_from_config({"image_width": 752, "image_height": 480, "cam0_calib": "cam0_mei.yaml"}, "x.yaml")
    assert ei.value.key == "mirror_parameters" and ei.value.path == "x.yaml"


def test_config_errors():
    n = _node()
    del n["projection_parameters"]["fx"]
    with pytest.raises(ConfigError, match=r"projection_parameters\.fx") as ei:
        camera_from_config(n, "/tmp/cam.yaml")
    assert ei.value.key == "projection_parameters.fx" and "/tmp/cam.yaml" in str(ei.value)
    n = _node()
    n["distortion_parameters"]["k2"] = "abc"
    with pytest.raises(ConfigError, match="expected a number") as ei:
        camera_from_config(n)
    assert ei.value.key == "distortion_parameters.k2"
    n = _node()
    n["distortion_parameters"] = 3.0
    with pytest.raises(ConfigError, match="map") as ei:
        camera_from_config(n)
    assert ei.value.key == "distortion_parameters"
    n = _node()
    del n["image_height"]
    with pytest.raises(ConfigError) as ei:
        camera_from_config(n)
    assert ei.value.key == "image_height"
    n = _node()
    n["image_width"] = 752.5
    with pytest.raises(ConfigError, match="integer"):
        camera_from_config(n)
    with pytest.raises(ConfigError, match="known.*PINHOLE.*MEI.*KANNALA_BRANDT.*scaramuzza") as ei:
        camera_from_config(_node("FOV"))
    assert ei.value.key == "model_type"
    n = _node("scaramuzza")
    del n["inv_poly_parameters"]["p19"]
    with pytest.raises(ConfigError) as ei:
        camera_from_config(n)
    assert ei.value.key == "inv_poly_parameters.p19"
    with pytest.raises(ConfigError):
        camera_from_config(["not", "a", "map"])


def test_config_from_path(tmp_path):
    f = tmp_path / "cam.yaml"
    f.write_text(
        "%YAML:1.0\n---\nmodel_type: KANNALA_BRANDT\ncamera_name: camera\nimage_width: 512\nimage_height: 512\n"
        "projection_parameters:\n   k2: 0.0034823894022493434\n   k3: 0.0007150348452162257\n"
        "   k4: -0.0020532361418706202\n   k5: 0.00020293673591811182\n   mu: 190.97847715128717\n"
        "   mv: 190.9733070521226\n   u0: 254.93170605935475\n   v0: 256.8974428996504\n"
    )
    cam = camera_from_config(f)
    assert isinstance(cam, KannalaBrandtCamera) and cam.params_dict() == BUILTIN["tum_kb"][1]
    cam2 = camera_from_config(read_opencv_yaml(f), f, dtype=torch.float32)
    assert cam2.mu.dtype == torch.float32


@pytest.mark.parametrize("path", _file_params())
def test_shared_configs_parse_like_builtin(path):
    """The in-test constants are the shipped values (so the built-in tests cover the real calibrations)."""
    cam = shared_camera(path)
    p = cam.params_dict()
    matches = [n for n, (_, q, w, h) in BUILTIN.items() if q == p and (w, h) == (cam.width, cam.height)]
    assert cam.model_type in ("PINHOLE", "MEI", "KANNALA_BRANDT") and math.isfinite(sum(p.values()))
    if path.name in ("tum_config.yaml", "cla_config.yaml", "3dm_config.yaml", "realsense_fisheye_config.yaml"):
        assert matches


@pytest.mark.parametrize("name", sorted(GRAD_CAMS))
def test_nan_propagates_and_empty_input(name):
    """A NaN pixel/point gives NaN (as upstream's arithmetic would), never a plausible finite ray; empty
    and un-batched inputs keep their shapes."""
    cam = GRAD_CAMS[name]
    P = cam.lift(torch.tensor([[float("nan"), 100.0], [120.0, 100.0]], dtype=torch.float64))
    assert torch.isnan(P[0]).any() and torch.isfinite(P[1]).all()
    uv = cam.project(torch.tensor([[float("nan"), 0.1, 1.0], [0.1, 0.1, -1.0 if name == "ocam" else 1.0]],
                                  dtype=torch.float64))
    assert torch.isnan(uv[0]).all() and torch.isfinite(uv[1]).all()
    assert cam.lift(torch.zeros(0, 2, dtype=torch.float64)).shape == (0, 3)
    assert cam.project(torch.zeros(2, 0, 3, dtype=torch.float64)).shape == (2, 0, 2)
    assert cam.lift(torch.tensor([120.0, 100.0], dtype=torch.float64)).shape == (3,)


@pytest.mark.parametrize("pshape", [(), (3, 1)], ids=["scalar_params", "per_stream_params"])
def test_stacked_radtan_undistort_equals_the_per_component_loop(pshape):
    """``radtan_undistort`` runs ``radtan_distortion``'s formula on stacked (x, y) (about half the
    kernels); every value equals the per-component loop's bit for bit, for scalar and per-stream
    coefficients (broadcast to ``(B, N)`` points), the zero-distortion shortcut included."""
    from torch_frontend.camera.base import radtan_distortion, radtan_undistort

    g = torch.Generator().manual_seed(7)
    x, y = (torch.rand(3, 50, generator=g, dtype=torch.float64) * 1.6 - 0.8 for _ in range(2))
    x[0, 0] = math.inf
    for ks in ((-0.28, 0.07, 2e-4, 1.8e-5), (0.0, 0.0, 0.0, 0.0)):
        k1, k2, p1, p2 = (torch.full(pshape, v, dtype=torch.float64) for v in ks)
        dx, dy = radtan_distortion(x, y, k1, k2, p1, p2)
        mx, my = x - dx, y - dy
        for _ in range(7):
            dx, dy = radtan_distortion(mx, my, k1, k2, p1, p2)
            mx, my = x - dx, y - dy
        zero = (k1 == 0) & (k2 == 0) & (p1 == 0) & (p2 == 0)
        mx = torch.where(zero & ~torch.isfinite(mx), x, mx)
        my = torch.where(zero & ~torch.isfinite(my), y, my)
        ux, uy = radtan_undistort(x, y, k1, k2, p1, p2, 8)
        assert ux.shape == uy.shape == (3, 50)
        # bit for bit, NaN where the loop made one (the inf point with distortion)
        torch.testing.assert_close(ux, mx, rtol=0, atol=0, equal_nan=True)
        torch.testing.assert_close(uy, my, rtol=0, atol=0, equal_nan=True)
        assert ux.isfinite().sum() >= 149, ks
