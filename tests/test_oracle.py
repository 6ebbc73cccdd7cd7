"""Tests of the numpy + cv2 VINS front-end oracle (``torch_frontend.testing.oracle``).

The oracle is the reference the torch tracker is compared with, so these tests pin the
behaviour of spec §3 (Mono node timing + readImage), §4 (camodocal lift) and §6 (Fusion tracker)
on synthetic clocks, analytic camera round trips and the repo's EuRoC sample frames.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from torch_frontend.testing import oracle as vo

from .conftest import load_gray, sample_frames, shared_data_or_skip

EUROC_CAM = {
    "model_type": "PINHOLE",
    "k1": -2.917e-01, "k2": 8.228e-02, "p1": 5.333e-05, "p2": -1.578e-04,
    "fx": 4.616e02, "fy": 4.603e02, "cx": 3.630e02, "cy": 2.481e02,
}
EUROC_MONO_CFG = {
    "max_cnt": 150, "min_dist": 30, "freq": 10, "F_threshold": 1.0, "equalize": 1, "fisheye": 0,
    "image_width": 752, "image_height": 480, "camera": EUROC_CAM,
}
# VINS-Fusion euroc/cam{0,1}_pinhole.yaml
FUSION_CAM0 = {
    "model_type": "PINHOLE",
    "k1": -2.9545645106987750e-01, "k2": 8.6623215640186171e-02,
    "p1": 2.0132892276082517e-06, "p2": 1.3924531371276508e-05,
    "fx": 4.6115862106007575e02, "fy": 4.5975286598073296e02,
    "cx": 3.6265929181685937e02, "cy": 2.4852105668448124e02,
}
FUSION_CAM1 = {
    "model_type": "PINHOLE",
    "k1": -2.9294124381930947e-01, "k2": 8.4798002331543665e-02,
    "p1": -2.9984646536002372e-04, "p2": 3.0028216325237329e-04,
    "fx": 4.6009781682258682e02, "fy": 4.5890983492218902e02,
    "cx": 3.7314916359808268e02, "cy": 2.5440734973672119e02,
}
CLA_KB = {  # VINS-Mono cla/cla_config.yaml
    "model_type": "KANNALA_BRANDT",
    "k2": -0.005740195474458931, "k3": 0.02878252863739417,
    "k4": -0.04010621197185408, "k5": 0.02008469575876223,
    "mu": 472.2863830700696, "mv": 470.83759684346785, "u0": 368.8316828103749, "v0": 232.23688706965652,
}
MEI_3DM = {  # VINS-Mono 3dm/3dm_config.yaml (gamma/u0/v0 rounded as in the file)
    "model_type": "MEI", "xi": 2.057, "k1": 7.145e-02, "k2": 5.059e-01, "p1": 4.727e-05, "p2": -5.492e-04,
    "gamma1": 1.115e03, "gamma2": 1.111e03, "u0": 3.688e02, "v0": 2.455e02,
}


def _grid(w, h, step):
    u, v = np.meshgrid(np.arange(0, w, step, dtype=np.float64), np.arange(0, h, step, dtype=np.float64))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def _stamp(path: Path) -> float:
    return int(path.stem) / 1e9  # EuRoC file names are ns


# ------------------------------------------------------------------------------------------
# timing rule (spec §3.2)
# ------------------------------------------------------------------------------------------
def _pub_pattern(stamps, freq=10):
    clock = vo.MonoTiming(freq)
    pubs, sent, tracked, restarts = [], [], [], []
    for k, t in enumerate(stamps):
        s = clock.step(t)
        if s["tracked"]:
            tracked.append(k)
        if s["restart"]:
            restarts.append(k)
        if s["pub_this_frame"]:
            pubs.append(k)
            if clock.published():
                sent.append(k)
    return pubs, sent, tracked, restarts


def test_c_round_is_half_away_from_zero():
    assert vo.c_round(12.5) == 13.0
    assert vo.c_round(2.5) == 3.0
    assert vo.c_round(12.49) == 12.0
    assert vo.c_round(0.49999999999999994) == 0.0  # floor(r + 0.5) would give 1 here
    assert vo.c_round(-2.5) == -3.0
    assert vo.c_round(math.inf) == math.inf


@pytest.mark.parametrize("t0", [0.0, 1403715273.262142976])
@pytest.mark.parametrize(
    "hz, expected",
    [
        (20, list(range(2, 61, 2))),  # every 2nd frame
        (30, list(range(3, 61, 3))),  # every 3rd frame
        (25, sorted([k for k in range(1, 61) if k % 5 in (3, 0)])),  # 3, 5, 8, 10, 13, 15, ...
    ],
)
def test_freq_rule_synthetic_clocks(t0, hz, expected):
    stamps = [t0 + k / hz for k in range(61)]
    pubs, sent, tracked, restarts = _pub_pattern(stamps)
    assert tracked == list(range(1, 61))  # frame 0 is the skipped first image
    assert restarts == []
    assert pubs == expected
    assert sent == expected[1:]  # the very first published frame is not sent (init_pub)


def test_freq_zero_means_100hz():
    stamps = [k / 20 for k in range(10)]
    pubs, *_ = _pub_pattern(stamps, freq=0)
    assert pubs == list(range(1, 10))  # 20 Hz camera is below FREQ=100: every tracked frame


def test_duplicate_stamp_after_reset_is_not_published():
    # 20 Hz: frame 2 publishes and resets first_image_time = t2; a duplicate of t2 has r = 1/0 = inf.
    stamps = [0.0, 0.05, 0.10, 0.10, 0.15, 0.20]
    pubs, _, tracked, _ = _pub_pattern(stamps)
    assert 3 in tracked and 3 not in pubs
    assert pubs == [2, 5]
    # duplicate of the first image: r = 1/0 = inf as well
    pubs, _, tracked, _ = _pub_pattern([0.0, 0.0, 0.05, 0.10])
    assert tracked == [1, 2, 3] and 1 not in pubs


def test_duplicate_stamp_can_publish_when_not_after_reset():
    # spec §3.2 step 4: a 5 Hz camera publishes without a reset (r=5), so a duplicate then has a
    # finite r = 2/0.2 = 10 -> published (and resets); "duplicate => inf" holds only right after a reset.
    pubs, *_ = _pub_pattern([0.0, 0.2, 0.2, 0.4])
    assert pubs == [1, 2, 3]


def test_gap_restart_drops_two_frames_and_resets_rate():
    stamps = [k * 0.05 for k in range(5)] + [2.2 + k * 0.05 for k in range(6)]
    pubs, sent, tracked, restarts = _pub_pattern(stamps)
    assert restarts == [5]  # 2.2 - 0.2 > 1 s
    assert 5 not in tracked and 6 not in tracked  # the restart frame and the next "first image"
    assert tracked == [1, 2, 3, 4, 7, 8, 9, 10]
    assert pubs == [2, 4, 8, 10]  # pub_count reset: frame 8 = 2nd frame after the new first image
    assert sent == [4, 8, 10]  # init_pub is not reset by a restart


def test_backwards_time_restarts():
    stamps = [0.0, 0.05, 0.10, 0.04, 0.09, 0.14, 0.19]
    pubs, _, tracked, restarts = _pub_pattern(stamps)
    assert restarts == [3]  # 0.04 < last_image_time 0.10
    assert tracked == [1, 2, 5, 6]  # 0.09 is the new (skipped) first image
    assert pubs == [2, 6]


def test_restart_keeps_tracker_state():
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.integers(0, 256, (120, 160), dtype=np.uint8), (0, 0), 2.0)
    base = cv2.normalize(base, None, 0, 255, cv2.NORM_MINMAX)
    cfg = dict(EUROC_MONO_CFG, image_width=160, image_height=120, max_cnt=40, min_dist=10,
               camera=dict(EUROC_CAM, cx=80.0, cy=60.0))
    tr = vo.OracleMonoTracker(cfg)
    stamps = [0.0, 0.05, 0.10, 0.15, 2.15, 2.20, 2.25]
    res = [tr.process(base, t) for t in stamps]
    assert [r["tracked"] for r in res] == [False, True, True, True, False, False, True]
    assert res[4]["restart"] and not res[5]["restart"]
    assert len(res[2]["ids"]) > 0 and res[2]["n_new"] == len(res[2]["ids"])
    # after the restart the same features continue (ids and counts not cleared) ...
    np.testing.assert_array_equal(res[6]["ids"], res[3]["ids"])
    np.testing.assert_array_equal(res[6]["track_cnt"], res[3]["track_cnt"] + 1)
    # ... and the velocity dt spans the gap (static image => zero velocity, finite)
    assert np.all(np.isfinite(res[6]["velocity"]))


# ------------------------------------------------------------------------------------------
# camera lift (spec §4)
# ------------------------------------------------------------------------------------------
def test_pinhole_lift_matches_cv2_mild_distortion():
    cam = dict(EUROC_CAM, k1=-0.05, k2=0.01)
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    D = np.array([cam["k1"], cam["k2"], cam["p1"], cam["p2"]])
    uv = _grid(752, 480, 4.0)
    P = vo.lift_projective(cam, uv)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    assert P.shape == (len(uv), 3) and np.all(P[:, 2] == 1.0)
    np.testing.assert_allclose(P[:, :2], ref, atol=1e-6, rtol=0)


def test_pinhole_lift_euroc_matches_cv2_where_converged_and_keeps_8_evaluations():
    cam = EUROC_CAM
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    D = np.array([cam["k1"], cam["k2"], cam["p1"], cam["p2"]])
    uv = _grid(752, 480, 4.0)
    P = vo.lift_projective(cam, uv)
    crit = (cv2.TERM_CRITERIA_COUNT, 200, 0.0)
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), K, D, None, None, crit).reshape(-1, 2)
    central = np.hypot(uv[:, 0] - cam["cx"], uv[:, 1] - cam["cy"]) < 200.0
    np.testing.assert_allclose(P[central, :2], ref[central], atol=1e-6, rtol=0)
    # Upstream quirk kept: 8 fixed-point evaluations do NOT converge in the EuRoC corners
    # (up to ~5e-4 normalised, ~0.13 px reprojection); the oracle follows camodocal, not the
    # converged inverse.
    assert np.abs(P[:, :2] - ref).max() > 1e-4
    corner = np.array([[0.0, 0.0]])
    assert np.abs(vo.lift_projective(cam, corner)[0, :2] - ref[0]).max() > 3e-5
    mdx, mdy = (0.0 - cam["cx"]) / cam["fx"], (0.0 - cam["cy"]) / cam["fy"]
    ux, uy = mdx, mdy
    for _ in range(8):  # m_u <- m_d - d(m_u), first evaluation at m_u = m_d
        r2 = ux * ux + uy * uy
        rad = cam["k1"] * r2 + cam["k2"] * r2 * r2
        dx = ux * rad + 2 * cam["p1"] * ux * uy + cam["p2"] * (r2 + 2 * ux * ux)
        dy = uy * rad + 2 * cam["p2"] * ux * uy + cam["p1"] * (r2 + 2 * uy * uy)
        ux, uy = mdx - dx, mdy - dy
    np.testing.assert_allclose(vo.lift_projective(cam, corner)[0, :2], [ux, uy], rtol=0, atol=1e-15)


def test_pinhole_no_distortion_shortcut():
    cam = dict(EUROC_CAM, k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    uv = _grid(752, 480, 16.0)
    P = vo.lift_projective(cam, uv)
    np.testing.assert_array_equal(P[:, 0], (uv[:, 0] - cam["cx"]) / cam["fx"])
    np.testing.assert_array_equal(P[:, 1], (uv[:, 1] - cam["cy"]) / cam["fy"])


def test_kannala_brandt_lift_round_trip_and_unit_norm():
    uv = _grid(752, 480, 8.0)
    P = vo.lift_projective(CLA_KB, uv)
    np.testing.assert_allclose(np.linalg.norm(P, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(vo.space_to_plane(CLA_KB, P), uv, atol=1e-8, rtol=0)
    # principal point -> optical axis (rho < 1e-10 => phi = 0, theta = 0)
    np.testing.assert_allclose(vo.lift_projective(CLA_KB, [[CLA_KB["u0"], CLA_KB["v0"]]]), [[0, 0, 1]], atol=1e-12)


def test_kannala_brandt_degree_quirk():
    rho = 0.7
    uv = np.array([[CLA_KB["u0"] + rho * CLA_KB["mu"], CLA_KB["v0"]]])
    # all four zero => degree 1 => theta = rho
    kb0 = dict(CLA_KB, k2=0.0, k3=0.0, k4=0.0, k5=0.0)
    np.testing.assert_allclose(vo.lift_projective(kb0, uv)[0], [math.sin(rho), 0, math.cos(rho)], atol=1e-12)
    # an interior zero (k3) drops the HIGHEST coefficient: degree 7 solves theta + k2 t^3 + k4 t^7
    kb = dict(CLA_KB, k3=0.0)
    theta = math.atan2(vo.lift_projective(kb, uv)[0, 0], vo.lift_projective(kb, uv)[0, 2])
    assert abs(theta + kb["k2"] * theta**3 + kb["k4"] * theta**7 - rho) < 1e-10
    assert abs(theta + kb["k2"] * theta**3 + kb["k4"] * theta**7 + kb["k5"] * theta**9 - rho) > 1e-6


def test_mei_lift_round_trip_and_xi_one_branch():
    uv = _grid(752, 480, 8.0)
    P = vo.lift_projective(MEI_3DM, uv)
    np.testing.assert_allclose(vo.space_to_plane(MEI_3DM, P), uv, atol=1e-6, rtol=0)
    mei1 = dict(MEI_3DM, xi=1.0, k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    P1 = vo.lift_projective(mei1, uv)
    mx = (uv[:, 0] - mei1["u0"]) / mei1["gamma1"]
    my = (uv[:, 1] - mei1["v0"]) / mei1["gamma2"]
    np.testing.assert_allclose(P1[:, 2], (1 - (mx * mx + my * my)) / 2, rtol=0, atol=1e-15)
    np.testing.assert_allclose(vo.space_to_plane(mei1, P1), uv, atol=1e-8, rtol=0)


# ------------------------------------------------------------------------------------------
# Mono tracker on the EuRoC sample (spec §3)
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mono_run():
    paths = sample_frames("cam0")
    assert len(paths) >= 20
    frames = [(_stamp(p), load_gray(p)) for p in paths]
    return frames, vo.run_oracle_sequence(frames, EUROC_MONO_CFG, mode="mono")


def test_mono_euroc_publish_pattern(mono_run):
    frames, res = mono_run
    n = len(res)
    assert [r["tracked"] for r in res] == [False] + [True] * (n - 1)
    assert [k for k, r in enumerate(res) if r["pub_this_frame"]] == list(range(2, n, 2))  # 20 Hz -> 10 Hz
    assert [k for k, r in enumerate(res) if r["sent"]] == list(range(4, n, 2))
    assert all(r["published"] == r["pub_this_frame"] for r in res)
    # detection only on PUB frames; the first PUB frame is the first detection
    assert all(r["n_new"] == 0 for r in res if not r["pub_this_frame"])
    assert len(res[1]["ids"]) == 0 and res[2]["n_new"] > 100


def test_mono_euroc_feature_invariants(mono_run):
    frames, res = mono_run
    min_d2 = EUROC_MONO_CFG["min_dist"] ** 2
    seen: set = set()
    max_id = -1
    for k, r in enumerate(res):
        if not r["tracked"]:
            continue
        ids, uv, cnt, vel = r["ids"], r["uv"], r["track_cnt"], r["velocity"]
        assert len(ids) <= 150
        assert len(np.unique(ids)) == len(ids) and np.all(ids >= 0)
        np.testing.assert_array_equal(r["published_mask"], cnt > 1)
        assert np.all(vo.in_border(uv, 480, 752))
        # ids: new ones are increasing, follow every previous id, and come after all tracks
        new = ~np.isin(ids, list(seen))
        np.testing.assert_array_equal(new, cnt == 1)
        if new.any():
            assert np.all(np.diff(ids[new]) > 0) and ids[new][0] > max_id
            assert np.all(np.flatnonzero(new) >= (cnt > 1).sum())
        seen |= set(ids.tolist())
        max_id = max(max_id, int(ids.max(initial=-1)))
        # velocity: zero for the first two observations (id still -1 at undistortion), then real
        assert np.all(vel[cnt <= 2] == 0)
        if (cnt >= 3).sum() > 20:
            assert np.mean(np.any(vel[cnt >= 3] != 0, axis=1)) > 0.9
        # xy = lift(uv) / z
        P = vo.lift_projective(EUROC_CAM, uv)
        np.testing.assert_allclose(r["xy"], P[:, :2] / P[:, 2:], atol=1e-6)
        if r["pub_this_frame"]:
            # setMask order: track_cnt non-increasing over the tracked part
            tracked = cnt > 1
            assert np.all(np.diff(cnt[tracked]) <= 0)
            # min-distance invariant: disc radius min_dist (d^2 <= r^2 painted) around rounded centres
            p = vo.cv_round(uv).astype(np.int64)
            d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
            np.fill_diagonal(d2, 10**9)
            old = cnt > 1
            assert np.all(d2[np.ix_(old, old)] > min_d2)  # kept tracks: outside each other's discs
            assert np.all(d2[np.ix_(old, ~old)] > min_d2)  # new corners: on mask != 0
            assert np.all(d2[np.ix_(~old, ~old)] >= min_d2)  # GFTT: d^2 >= minDistance^2
        else:
            # non-PUB frames keep the array order of the previous frame (only LK compaction)
            prev = res[k - 1]
            if prev["tracked"]:
                assert np.all(np.isin(ids, prev["ids"]))
                pos = {int(i): j for j, i in enumerate(prev["ids"])}
                assert np.all(np.diff([pos[int(i)] for i in ids]) > 0)
    assert max_id >= 149


def test_mono_velocity_is_displacement_over_dt(mono_run):
    frames, res = mono_run
    k = 6
    a, b = res[k - 1], res[k]
    dt = frames[k][0] - frames[k - 1][0]
    common, ia, ib = np.intersect1d(a["ids"], b["ids"], return_indices=True)
    m = b["track_cnt"][ib] >= 3
    assert m.sum() > 50
    expect = (b["xy"][ib] - a["xy"][ia]).astype(np.float64) / dt
    np.testing.assert_allclose(b["velocity"][ib][m], expect[m], rtol=1e-5, atol=1e-6)


def test_cfg_from_vins_yaml_euroc():
    path = shared_data_or_skip("vins_configs", "vins_mono", "euroc", "euroc_config.yaml")
    cfg = vo.cfg_from_vins_yaml(path)
    for key in ("max_cnt", "min_dist", "freq", "F_threshold", "equalize", "fisheye", "image_width", "image_height"):
        assert cfg[key] == EUROC_MONO_CFG[key], key
    for key, val in EUROC_CAM.items():
        assert cfg["camera"][key] == val, key


# ------------------------------------------------------------------------------------------
# Fusion tracker (spec §6)
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stereo_frames():
    left = sample_frames("cam0")[:6]
    right = sample_frames("cam1")[:6]
    assert len(right) == 6 and [p.name for p in left] == [p.name for p in right]
    return [(_stamp(a), load_gray(a), load_gray(b)) for a, b in zip(left, right)]


def test_fusion_stereo_shares_ids(stereo_frames):
    cfg = {"max_cnt": 150, "min_dist": 30, "flow_back": 1, "camera": FUSION_CAM0, "camera1": FUSION_CAM1}
    res = vo.run_oracle_sequence(stereo_frames, cfg, mode="fusion")
    assert len(res) == 6
    assert len(res[0]["ids"]) > 50 and np.all(res[0]["track_cnt"] == 1)  # no first-frame skip
    for r in res:
        ids, ids_r = r["ids"], r["ids_right"]
        assert len(ids) <= 150 and len(np.unique(ids)) == len(ids)
        assert len(ids_r) >= 10 and len(np.unique(ids_r)) == len(ids_r)
        assert np.all(np.isin(ids_r, ids))
        # right = left order subset; right points in border; positive disparity (right camera)
        pos = np.searchsorted(ids, ids_r, sorter=np.argsort(ids))
        assert np.all(np.diff(np.argsort(ids)[pos]) > 0)
        assert np.all(vo.in_border(r["uv_right"], 480, 752))
        left_uv = r["uv"][np.argsort(ids)[pos]]
        assert np.median(left_uv[:, 0] - r["uv_right"][:, 0]) > 0
        # feature map: left obs for every id, right obs exactly for ids_right
        fm = r["features"]
        assert list(fm) == sorted(int(i) for i in ids)
        assert {i for i, obs in fm.items() if len(obs) == 2} == {int(i) for i in ids_r}
        assert all(obs[0][0] == 0 and obs[0][1][2] == 1.0 for obs in fm.values())
    # velocity from the 2nd observation (ids exist at detection)
    r = res[1]
    assert np.all(r["velocity"][r["track_cnt"] == 1] == 0)
    assert np.mean(np.any(r["velocity"][r["track_cnt"] == 2] != 0, axis=1)) > 0.9
    # ids assigned at detection, increasing
    assert np.array_equal(res[0]["ids"], np.arange(len(res[0]["ids"])))


def test_fusion_prediction_and_remove(stereo_frames):
    cfg = {"max_cnt": 150, "min_dist": 30, "flow_back": 1, "camera": FUSION_CAM0}
    ref = vo.run_oracle_sequence([f[:2] for f in stereo_frames[:3]], cfg, mode="fusion")
    tr = vo.OracleFusionTracker(cfg)
    tr.process(stereo_frames[0][0], stereo_frames[0][1])
    tr.process(stereo_frames[1][0], stereo_frames[1][1])
    # predict with the reference tracker's frame-2 result; then drop a few ids
    pred = {int(i): tuple(p) for i, p in zip(ref[2]["ids"], ref[2]["uv"])}
    drop = tr.ids[:5].tolist()
    tr.remove(drop)
    tr.set_prediction(pred)
    r = tr.process(stereo_frames[2][0], stereo_frames[2][1])
    assert r["used_prediction"]
    assert not np.isin(drop, r["ids"]).any()
    assert len(r["ids_right"]) == 0  # mono config: no right camera
    # compare the tracks that existed before frame 2 (new ids differ: removal shifts detection)
    old_ref = ref[2]["ids"][ref[2]["track_cnt"] > 1]
    old = r["ids"][r["track_cnt"] > 1]
    common, ia, ib = np.intersect1d(old_ref, old, return_indices=True)
    ia = np.flatnonzero(ref[2]["track_cnt"] > 1)[ia]
    ib = np.flatnonzero(r["track_cnt"] > 1)[ib]
    assert len(common) > 100
    np.testing.assert_allclose(r["uv"][ib], ref[2]["uv"][ia], atol=0.1)


# ------------------------------------------------------------------------------------------
# paths the (nearly static) EuRoC sample does not exercise: LK loss / border, rejectWithF, fisheye
# ------------------------------------------------------------------------------------------
def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), 1.5)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)


def test_mono_shift_loses_border_points_and_tracks_the_rest():
    big = _texture(140, 200)
    cfg = dict(EUROC_MONO_CFG, image_width=160, image_height=120, max_cnt=60, min_dist=12, freq=0,
               equalize=0, camera=dict(EUROC_CAM, cx=80.0, cy=60.0))
    tr = vo.OracleMonoTracker(cfg)
    f0 = big[10:130, 20:180]
    f1 = big[10:130, 28:188]  # scene moves 8 px to the left
    r = [tr.process(f, t) for f, t in ((f0, 0.0), (f0, 0.05), (f1, 0.10))]
    assert r[1]["n_new"] > 20
    near_left = (r[1]["uv"][:, 0] < 7).sum()
    assert near_left > 0 and r[2]["n_lk_lost"] >= near_left
    common, ia, ib = np.intersect1d(r[1]["ids"], r[2]["ids"], return_indices=True)
    assert len(common) > 10
    shift = r[2]["uv"][ib] - r[1]["uv"][ia]
    assert np.median(np.abs(shift[:, 0] + 8.0)) < 0.05 and np.median(np.abs(shift[:, 1])) < 0.05
    assert np.all(vo.in_border(r[2]["uv"], 120, 160))


@pytest.mark.parametrize("n", [12, 40])  # 8..14 points: OpenCV switches to LMedS; >= 15: RANSAC
def test_reject_with_f_drops_outliers(n):
    rng = np.random.default_rng(n)
    tr = vo.OracleMonoTracker(EUROC_MONO_CFG)
    # a pure sideways translation in 3D: consistent epipolar geometry, plus 2 gross outliers
    X = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(3, 8, n)]
    cur = vo.space_to_plane(EUROC_CAM, X).astype(np.float32)
    forw = vo.space_to_plane(EUROC_CAM, X + [0.2, 0.05, 0.0]).astype(np.float32)
    forw[[0, 1]] += np.float32([[25.0, -30.0], [-20.0, 35.0]])
    keep = tr._reject_with_f(cur, forw)
    assert keep.shape == (n,) and not keep[0] and not keep[1]
    # LMedS (n < 15) uses sigma = max(0.001, 2.5*1.4826*(1+5/(n-7))*sqrt(median)): on near-perfect
    # data the threshold collapses and float32 noise can drop inliers; only the median half is sure.
    assert keep[2:].mean() >= (0.9 if n >= 15 else 0.5)


def test_mono_fisheye_mask_is_respected():
    mask_path = shared_data_or_skip("vins_configs", "vins_mono", "fisheye_mask_752x480.jpg")
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    assert mask.shape == (480, 752)
    cfg = dict(EUROC_MONO_CFG, fisheye=1, fisheye_mask=mask)
    frames = [(_stamp(p), load_gray(p)) for p in sample_frames("cam0")[:7]]
    res = vo.run_oracle_sequence(frames, cfg)
    for r in res:
        if r["pub_this_frame"]:
            p = vo.cv_round(r["uv"])
            vals = mask[p[:, 1], p[:, 0]]
            old = r["track_cnt"] > 1
            assert np.all(vals[old] == 255)  # kept tracks: exactly 255 (JPEG ring values count as masked)
            assert np.all(vals[~old] != 0)  # GFTT: any non-zero mask pixel is allowed
    assert sum(r["n_new"] for r in res) > 50
