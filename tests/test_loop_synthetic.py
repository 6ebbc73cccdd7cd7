"""The rendered revisiting sequence (torch_frontend.testing.synthetic): exact geometry, textures that
are what the renderer shows, VIO drift of the intended kind, revisit ground truth, and BRIEF
matching that works at the revisits only.

One module-scoped sequence (2 laps x 64 keyframes, 320x240: ~2-4 s to render on 1 thread); the
other tests render tiny images.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_frontend.geometry import R_to_ypr
from torch_frontend.loop.keyframe import match_brief
from torch_frontend.testing.synthetic import (
    default_textures,
    make_keyframes,
    make_room,
    render_loop_sequence,
)


@pytest.fixture(scope="module")
def seq():
    return render_loop_sequence(laps=2, keyframes_per_lap=64, width=320, height=240, seed=0)


@pytest.fixture(scope="module")
def pairs(seq):
    return seq.revisit_pairs(min_overlap=0.3, min_gap=50, step=32)


def _close(a, b, atol=1e-12):
    """Elementwise |a - b| <= atol (numpy; torch.testing's first call imports a lot)."""
    np.testing.assert_allclose(a.detach().cpu().numpy(), b.detach().cpu().numpy(), rtol=0, atol=atol)


def _cam_coords(seq, frame, X):
    R, c = seq.camera_pose(frame)
    return (X - c) @ R


# ------------------------------------------------------------------------------ geometry
def test_points_3d_reproject_exactly(seq):
    rng = np.random.default_rng(0)
    H, W = seq.images.shape[1:]
    for f in (0, 17, 93):
        uv = torch.from_numpy(rng.uniform([0, 0], [W - 1, H - 1], size=(200, 2)))
        X = seq.points_3d(f, uv)
        assert X.dtype == torch.float64 and torch.isfinite(X).all()
        Pc = _cam_coords(seq, f, X)
        assert (Pc[:, 2] > 0.3).all()
        err = (seq.camera.project(Pc) - uv).norm(dim=1)
        assert float(err.max()) < 1e-3
        # every point lies on the room's boundary (7 x 5 x 3 m box)
        Lx, Ly, Lz = 7.0, 5.0, 3.0
        gap = torch.stack([X[:, 0].abs() - Lx / 2, X[:, 1].abs() - Ly / 2, X[:, 2] - Lz, -X[:, 2]], 1).amax(1)
        assert float(gap.abs().max()) < 1e-9
        # the depth map is the camera z of the surface at integer pixels
        iu = torch.from_numpy(rng.integers(0, [W, H], size=(200, 2))).double()
        z = _cam_coords(seq, f, seq.points_3d(f, iu))[:, 2]
        d = seq.depth[f][iu[:, 1].long(), iu[:, 0].long()].double()
        assert float(((d - z) / z).abs().max()) < 1e-5


def _bilinear(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = tex.shape
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = x - x0, y - y0
    t = tex.astype(np.float64)
    return ((1 - fx) * (1 - fy) * t[y0, x0] + fx * (1 - fy) * t[y0, x0 + 1]
            + (1 - fx) * fy * t[y0 + 1, x0] + fx * fy * t[y0 + 1, x0 + 1])


def test_pixels_equal_texture_at_hit_point(seq):
    room = seq.room
    o, u, v, size = (a.numpy() for a in (room.origin, room.axis_u, room.axis_v, room.size))
    n = np.cross(u, v)
    H, W = seq.images.shape[1:]
    ys, xs = np.mgrid[0:H:3, 0:W:3]
    uv = torch.from_numpy(np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64))
    checked = set()
    for f in (0, 40, 77, 120):
        X = seq.points_3d(f, uv).numpy()
        on = np.abs(np.einsum("npk,pk->np", X[:, None, :] - o, n)) < 1e-7  # (pixels, planes)
        one = on.sum(1) == 1  # skip the few pixels on an edge between two planes
        assert one.mean() > 0.99
        p = on.argmax(1)[one]
        rel = X[one] - o[p]
        s = np.einsum("nk,nk->n", rel, u[p]) / size[p, 0]
        r = np.einsum("nk,nk->n", rel, v[p]) / size[p, 1]
        ref = np.empty(len(p))
        for k in np.unique(p):
            tex = room.textures[k].numpy()
            m = p == k
            ref[m] = _bilinear(tex, s[m] * (tex.shape[1] - 1), r[m] * (tex.shape[0] - 1))
            checked.add(int(k))
        img = seq.images[f].numpy()[uv[one, 1].long().numpy(), uv[one, 0].long().numpy()]
        # rounding to 8 bits (<= 0.5) plus float32 rendering (~1e-4 texel)
        assert np.abs(img - ref).max() <= 0.55
    assert checked >= {0, 1, 2, 3, 4}  # all walls and the floor were seen


def test_textures_and_extrinsic(seq):
    tex = default_textures()
    assert len(tex) == 6 and all(t.dtype == np.uint8 and t.shape in ((384, 752), (752, 384)) for t in tex)
    # distinct variants: no two textures are the same image
    flat = [t.ravel() for t in tex]
    assert all(not np.array_equal(flat[a], flat[b]) for a in range(6) for b in range(a))
    # the camera looks along body +x, image right = body -y, image down = body -z
    R_ic = seq.R_ic.numpy()
    np.testing.assert_array_equal(R_ic, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    assert 0 < float(seq.t_ic.norm()) < 0.1
    R_wc, T_wc = seq.camera_pose(torch.arange(5))
    _close(R_wc[:, :, 2], seq.R_gt[:5, :, 0])
    _close(T_wc, seq.T_gt[:5] + (seq.R_gt[:5] @ seq.t_ic))
    cam = seq.camera
    assert (cam.width, cam.height) == (320, 240) and float(cam.fx) == float(cam.fy) == 192.0


# ---------------------------------------------------------------------------------- drift
def _rel(R, T):
    Ra = R[:-1].transpose(1, 2)
    return Ra @ R[1:], (Ra @ (T[1:] - T[:-1])[..., None])[..., 0]


def _angle_deg(R):
    c = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.arccos(c))


@pytest.mark.parametrize("drift, fpk", [("4dof", 1), ("4dof", 3), ("6dof", 2), (None, 1)])
def test_vio_drift(drift, fpk):
    s = render_loop_sequence(width=16, height=16, drift=drift, frames_per_keyframe=fpk, seed=3)
    k = s.keyframe_frames
    Rg, Tg, Rv, Tv = s.R_gt[k], s.T_gt[k], s.R_vio[k], s.T_vio[k]
    # VIO = drift transform applied to the truth
    _close(Rv, s.R_drift[k] @ Rg)
    _close(Tv, (s.R_drift[k] @ Tg[..., None])[..., 0] + s.t_drift[k])
    assert torch.equal(s.T_vio[0], s.T_gt[0]) and torch.equal(s.R_vio[0], s.R_gt[0])
    # consecutive keyframes: the VIO relative motion is close to the true one
    rg, tg = _rel(Rg, Tg)
    rv, tv = _rel(Rv, Tv)
    rot_err = _angle_deg(rg.transpose(1, 2) @ rv)
    t_err = (tv - tg).norm(dim=1)
    assert float(rot_err.max()) < 0.5 and float(t_err.max()) < 0.01
    assert 0.1 < float(tg.norm(dim=1).mean()) < 0.2  # ~14 cm per keyframe
    yg, yv = R_to_ypr(Rg), R_to_ypr(Rv)
    pos_err = (Tv - Tg).norm(dim=1)
    if drift is None:
        assert torch.equal(Tv, Tg) and torch.equal(Rv, Rg)
        return
    # ... but it accumulates: several degrees of yaw and decimetres by the end of lap 2
    assert abs(float(yv[-1, 0] - yg[-1, 0])) > 2.0
    assert float(pos_err.max()) > 0.1
    pr = (yv - yg)[:, 1:].abs().max()
    if drift == "4dof":
        assert float(pr) < 1e-9  # pitch and roll exact (the IMU observes them)
    else:
        assert float(pr) > 0.2


def test_frames_and_times():
    s = render_loop_sequence(laps=1, keyframes_per_lap=8, frames_per_keyframe=3, width=16, height=16,
                             keyframe_dt=0.6)
    assert s.num_frames == 24 and s.num_keyframes == 8
    assert s.keyframe_frames.tolist() == list(range(0, 24, 3))
    assert s.is_keyframe.tolist() == [f % 3 == 0 for f in range(24)]
    np.testing.assert_allclose(s.times.numpy(), 1.0 + 0.2 * np.arange(24))
    np.testing.assert_allclose(s.phase.numpy(), 2 * np.pi * np.arange(24) / 24)
    assert s.lap.tolist() == [0] * 24
    assert s.images.shape == (24, 16, 16) and s.images.dtype == torch.uint8 and s.depth.dtype == torch.float32


# ------------------------------------------------------------------------------- revisits
def test_revisit_ground_truth(seq, pairs):
    assert pairs.dtype == torch.int64 and pairs.shape[1] == 2 and pairs.shape[0] > 100
    i, j = pairs[:, 0], pairs[:, 1]
    assert ((i - j) > 50).all()
    ph = seq.phase[seq.keyframe_frames]
    d = ph[i] - ph[j]
    wrapped = torch.remainder(d + math.pi, 2 * math.pi) - math.pi
    # a pair is the same place on a later pass: about one full turn apart, never half a lap
    assert float(d.min()) > math.pi and float(wrapped.abs().max()) < math.radians(60)
    # every keyframe of the second lap revisits something
    assert set(range(64, 128)) <= set(i.tolist())
    # the overlap measure: 1 with itself, high at a revisit, 0 on the opposite side of the room
    f = seq.keyframe_frames
    assert seq.overlaps(int(f[10]), int(f[10])) == 1.0
    assert seq.overlaps(int(f[74]), int(f[10])) > 0.7
    assert seq.overlaps(int(f[74]), int(f[42])) == 0.0


def _correct_matches(seq, a, b, ka, kb):
    idx, _, matched = match_brief(a.window_brief[None], b.brief[None])
    m, idx = matched[0], idx[0]
    Xa = seq.points_3d(int(seq.keyframe_frames[ka]), a.point_2d_uv[m].double())
    Xb = seq.points_3d(int(seq.keyframe_frames[kb]), b.keypoints[idx[m]].double())
    return int(m.sum()), int(((Xa - Xb).norm(dim=1) < 0.05).sum())


def test_brief_matching_at_revisits_only(seq, pairs):
    sel = [80, 16, 100, 36, 48, 4]
    kfs = dict(zip(sel, make_keyframes(seq, keyframes=sel)))
    gt = {tuple(p) for p in pairs.tolist()}
    for cur, old in ((80, 16), (100, 36)):
        assert (cur, old) in gt
        n, good = _correct_matches(seq, kfs[cur], kfs[old], cur, old)
        print(f"revisit {cur}->{old}: {n} BRIEF matches, {good} correct (3-D points within 5 cm)")
        assert good > 25
    for cur, old in ((80, 48), (100, 4)):
        assert (cur, old) not in gt
        n, good = _correct_matches(seq, kfs[cur], kfs[old], cur, old)
        print(f"elsewhere {cur}->{old}: {n} BRIEF matches, {good} correct")
        assert good < 5


# ------------------------------------------------------------------------------ keyframes
def test_make_keyframes_consistent(seq):
    sel = [0, 5, 70]
    kfs = make_keyframes(seq, max_points=100, min_dist=15, sequence=2, keyframes=sel)
    ids = torch.cat([k.point_id for k in kfs])
    assert len(set(ids.tolist())) == ids.numel()
    for k, kf in zip(sel, kfs):
        f = int(seq.keyframe_frames[k])
        assert kf.sequence == 2 and kf.time == float(seq.times[f])
        assert 40 <= kf.num_points <= 100 and kf.num_keypoints > 200
        assert torch.equal(kf.origin_vio_T, seq.T_vio[f]) and torch.equal(kf.origin_vio_R, seq.R_vio[f])
        # the window points are the exact surface points, in this keyframe's VIO world
        X = seq.points_3d(f, kf.point_2d_uv.double())
        _close(kf.point_3d, seq.to_vio(f, X))
        # ... consistent with the VIO pose: they project back onto their pixels
        R_wc = kf.origin_vio_R @ seq.R_ic
        T_wc = kf.origin_vio_T + kf.origin_vio_R @ seq.t_ic
        uv = seq.camera.project((kf.point_3d - T_wc) @ R_wc)
        assert float((uv - kf.point_2d_uv.double()).norm(dim=1).max()) < 1e-6
        xy = (kf.point_2d_uv.double() - torch.tensor([159.5, 119.5], dtype=torch.float64)) / 192.0
        _close(kf.point_2d_norm, xy)
        # pixel positions are the image's Shi-Tomasi corners (integers, at least min_dist apart)
        assert torch.equal(kf.point_2d_uv, kf.point_2d_uv.round())
        d = torch.cdist(kf.point_2d_uv, kf.point_2d_uv) + 1e3 * torch.eye(kf.num_points)
        assert float(d.min()) >= 15
    assert make_keyframes(seq, keyframes=[]) == []
    with pytest.raises(ValueError, match="keyframes"):
        make_keyframes(seq, keyframes=[128])


def test_deterministic():
    kw = dict(laps=2, keyframes_per_lap=6, width=64, height=48)
    a = render_loop_sequence(seed=7, **kw)
    b = render_loop_sequence(seed=7, **kw)
    c = render_loop_sequence(seed=8, **kw)
    assert torch.equal(a.images, b.images) and torch.equal(a.depth, b.depth)
    assert torch.equal(a.T_vio, b.T_vio) and torch.equal(a.R_vio, b.R_vio)
    assert torch.equal(a.images, c.images) and torch.equal(a.T_gt, c.T_gt)  # the drift is the only randomness
    assert not torch.equal(a.T_vio, c.T_vio)
    ka = make_keyframes(a, point_noise=0.01, keyframes=[1, 2])
    kb = make_keyframes(b, point_noise=0.01, keyframes=[1, 2])
    for x, y in zip(ka, kb):
        assert torch.equal(x.point_3d, y.point_3d) and torch.equal(x.brief, y.brief)
        assert torch.equal(x.window_brief, y.window_brief) and torch.equal(x.keypoints, y.keypoints)


def test_device_matches_cpu(device):
    kw = dict(laps=1, keyframes_per_lap=3, width=80, height=60)
    s = render_loop_sequence(device=device, **kw)
    ref = render_loop_sequence(**kw)
    assert s.images.device.type == device.type and s.T_vio.device.type == device.type
    diff = (s.images.cpu().int() - ref.images.int()).abs()
    assert int(diff.max()) <= 1 and float((diff > 0).float().mean()) < 0.01
    X = s.points_3d(1, torch.tensor([[10.5, 20.25]], device=device))
    _close(X.cpu(), ref.points_3d(1, torch.tensor([[10.5, 20.25]])))


def test_bad_arguments():
    with pytest.raises(ValueError, match="drift"):
        render_loop_sequence(width=16, height=16, drift="2dof")
    with pytest.raises(ValueError, match="laps"):
        render_loop_sequence(laps=0)
    with pytest.raises(ValueError, match="width"):
        render_loop_sequence(width=8)
    with pytest.raises(ValueError, match="textures"):
        make_room(textures=default_textures()[:5])
    with pytest.raises(ValueError, match=r"textures\[0\]"):
        make_room(textures=[np.zeros((4, 4), np.float32)] * 6)
    with pytest.raises(ValueError, match="size"):
        make_room(size=(1, 0, 1))


def test_room_cast_paths_agree():
    """The convex fast paths (inverse-depth argmax; one matmul per frame) equal the general ray /
    rectangle test for rays from inside the room."""
    from torch_frontend.testing.synthetic import Room

    room = make_room(textures=[np.full((4, 4), 10 * k, np.uint8) for k in range(6)])
    general = Room(room.origin, room.axis_u, room.axis_v, room.size, room.textures, convex=False)
    g = torch.Generator().manual_seed(0)
    c = (torch.rand(50, 1, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([6.0, 4.0, 2.0]) \
        + torch.tensor([0.0, 0.0, 1.5])
    d = torch.randn(50, 40, 3, generator=g, dtype=torch.float64)
    for a, b in zip(room.cast(c, d), general.cast(c, d)):
        _close(a, b, atol=1e-9)
    t, plane, st = room.cast(c, d)
    assert (plane >= 0).all() and torch.isfinite(t).all() and (t > 0).all()
    # shading: constant textures give the plane's value
    _close(room.shade(plane, st), 10.0 * plane.double(), atol=1e-5)
    # the pinhole fast path (float64 and float32) agrees with cast
    R = torch.linalg.qr(torch.randn(50, 3, 3, generator=g, dtype=torch.float64)).Q
    R = R * torch.linalg.det(R)[:, None, None]  # proper rotations
    xy1 = torch.cat([torch.randn(40, 2, generator=g, dtype=torch.float64) * 0.5, torch.ones(40, 1)], 1)
    ref = room.cast(c, xy1 @ R.transpose(1, 2))
    for dt, tol in ((torch.float64, 1e-9), (torch.float32, 1e-4)):
        tp, pp, sp = room.cast_pinhole(c[:, 0], R, xy1, dt)
        assert tp.dtype == dt and torch.equal(pp, ref[1])
        _close(tp.double(), ref[0], atol=tol * 10)
        _close(sp.double(), ref[2], atol=tol)
