"""The fused setMask (``torch_frontend::set_mask``, ``fused/mask_op.py``) against the tensor kernel
(``masks._distance_mask_impl``) and a cv2 reference (VINS's loop: a stable sort by track count,
``cv2.circle(mask, c, MIN_DIST, 0, FILLED)``), bit for bit: every kept slot and every mask pixel.

Convention:
    The real cases are the tracker's own setMask calls (``stages.set_mask``'s arguments, recorded)
    while it tracks the repo's sample sequence and ``../shared``'s V1_01 excerpt (skipped, saying so,
    when it is absent), each also with its slots shuffled (other ties), the VINS fisheye JPEG as the
    base mask (254 values, a cut-off disc) and several streams in one call.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend.fused.mask_op import disc_r2, disc_spans, set_mask_op
from torch_frontend.masks import _distance_mask_impl, distance_mask, fisheye_mask
from torch_frontend.testing.dispatch_count import OpCounter
from torch_frontend.tracker import FeatureTracker, stages

from .conftest import REPO, SHARED_DATA, load_gray, sample_frames, shared_data_or_skip

pytestmark = pytest.mark.usefixtures("single_thread")

CFG_PATH = REPO / "configs" / "euroc.yaml"


# ----------------------------------------------------------------------------------------- helpers
def _cv2_set_mask(pts: np.ndarray, cnt: np.ndarray, valid: np.ndarray, radius: int, base: np.ndarray):
    """VINS's setMask for one stream: ``(keep (N,) bool, mask (H, W) uint8)``."""
    m = base.copy()
    H, W = m.shape
    keep = np.zeros(len(pts), bool)
    for i in sorted((i for i in range(len(pts)) if valid[i]), key=lambda i: -int(cnt[i])):  # stable
        x, y = np.rint(pts[i].astype(np.float64))  # cvRound: half to even
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        x, y = int(x), int(y)
        if 0 <= x < W and 0 <= y < H and m[y, x] == 255:
            keep[i] = True
            cv2.circle(m, (x, y), int(radius), 0, -1)
    return keep, m


def _assert_all_equal(pts, cnt, valid, radius, base, what=""):
    """fused == tensor == cv2 on every stream: keep and every mask pixel. ``base``: ``(1 or B, H, W)``."""
    B = pts.shape[0]
    fk, fm = set_mask_op(pts, cnt, valid, base, float(radius))
    tk, tm = _distance_mask_impl(pts, cnt, valid, float(radius), base.expand(B, -1, -1).clone())[:2]
    assert torch.equal(fk, tk), f"{what}: keep differs from the tensor kernel"
    assert torch.equal(fm, tm), f"{what}: the mask differs from the tensor kernel at {int((fm != tm).sum())} px"
    for b in range(B):
        ck, cm = _cv2_set_mask(pts[b].numpy(), cnt[b].numpy(), valid[b].numpy(), radius,
                               base[b if base.shape[0] > 1 else 0].numpy())
        np.testing.assert_array_equal(fk[b].numpy(), ck, err_msg=f"{what} stream {b}: keep vs cv2")
        bad = int((fm[b].numpy() != cm).sum())
        assert bad == 0, f"{what} stream {b}: {bad} mask pixels differ from cv2"
    return fk, fm


def _record(monkeypatch, cfg, frames):
    """The tracker's setMask calls over ``frames`` (``(t, img)``): ``(pts, cnt, valid, radius)`` each
    (CPU tensors, the tracker's sorted slots)."""
    calls = []
    impl = stages._distance_mask_impl

    def spy(pts, pri, valid, radius, mask, **kw):
        calls.append((pts.detach().clone(), pri.clone(), valid.clone(), radius))
        return impl(pts, pri, valid, radius, mask, **kw)

    monkeypatch.setattr(stages, "_distance_mask_impl", spy)
    tr = FeatureTracker(cfg, num_streams=1)
    for t, img in frames:
        tr.track(torch.from_numpy(img)[None, None], [t])
    assert calls, "the tracker made no setMask call"
    return calls


def _check_calls(calls, base, name):
    """Every recorded call as it was, with its slots shuffled, and all of them as one batch."""
    rng = np.random.default_rng(5)
    kept = 0
    for k, (pts, cnt, valid, radius) in enumerate(calls):
        fk, _ = _assert_all_equal(pts, cnt, valid, radius, base, f"{name} call {k}")
        kept += int(fk.sum())
        perm = torch.from_numpy(rng.permutation(pts.shape[1]))
        _assert_all_equal(pts[:, perm], cnt[:, perm], valid[:, perm], radius, base, f"{name} call {k} shuffled")
    # one batch of every call: each stream's result is its own
    radius = calls[0][3]
    pts, cnt, valid = (torch.cat([c[i] for c in calls]) for i in range(3))
    fk, fm = set_mask_op(pts, cnt, valid, base, float(radius))
    for b, c in enumerate(calls):
        k1, m1 = set_mask_op(*c[:3], base, float(radius))
        assert torch.equal(fk[b], k1[0]) and torch.equal(fm[b], m1[0]), f"{name}: stream {b} of the batch"
    return kept


def _frames(paths):
    return [(int(p.stem) * 1e-9, load_gray(p)) for p in paths]


# ------------------------------------------------------------------------------------------- tests
def test_fused_set_mask_equals_cv2_on_the_sample(monkeypatch):
    """The tracker's setMask calls on the repo's EuRoC sample (cam0, 16 frames; MIN_DIST 30): every
    kept slot and pixel, with an all-255 base and with a fisheye base."""
    cfg = tf.load_config(CFG_PATH)
    calls = _record(monkeypatch, cfg, _frames(sample_frames("cam0")[:16]))
    assert len(calls) >= 6 and max(int(c[2].sum()) for c in calls) >= 100, [int(c[2].sum()) for c in calls]
    H, W = cfg.image_height, cfg.image_width
    kept = _check_calls(calls, torch.full((1, H, W), 255, dtype=torch.uint8), "sample")
    kept_fe = _check_calls(calls, fisheye_mask(H, W, radius=300)[None], "sample fisheye")
    assert kept > 0 and 0 < kept_fe < kept


def test_fused_set_mask_equals_cv2_on_shared_v1_01(monkeypatch):
    """The tracker's setMask calls on ``../shared``'s V1_01 cam0 (12 frames, every second one),
    MIN_DIST 25; the base masks: all 255 and VINS's ``fisheye_mask_752x480.jpg`` (soft edge)."""
    root = shared_data_or_skip("sequences", "euroc_v1_01_easy_micro", "mav0", "cam0", "data")
    cfg = dataclasses.replace(tf.load_config(CFG_PATH), min_dist=25)
    calls = _record(monkeypatch, cfg, _frames(sorted(root.glob("*.png"))[:24:2]))
    H, W = cfg.image_height, cfg.image_width
    _check_calls(calls, torch.full((1, H, W), 255, dtype=torch.uint8), "V1_01")
    jpg = SHARED_DATA / "vins_configs" / "vins_mono" / "fisheye_mask_752x480.jpg"
    if jpg.exists():
        base = torch.from_numpy(load_gray(jpg))[None]
        assert base.shape[-2:] == (H, W) and bool(((base > 0) & (base < 255)).any())
        _check_calls(calls, base, "V1_01 fisheye jpg")


def test_fused_set_mask_ties_borders_and_odd_inputs():
    """Ties everywhere, centres at .5 (half to even), on and just off every border, NaN / inf,
    invalid slots, int32 counts, float64 points, a per-stream base, radii 0, 1, 7.5 (a non-integer
    radius: ``dx² + dy² <= r²``) and larger than the image; B = 3 streams in one call equal one
    stream at a time."""
    rng = np.random.default_rng(11)
    B, N, H, W = 3, 90, 37, 53
    pts = rng.uniform(-2, [W + 1, H + 1], (B, N, 2))
    pts[:, :15] = np.round(pts[:, :15]) + 0.5
    edge = np.array([[0, 0], [-0.5, 3], [-0.51, 4], [W - 0.5, 5], [W - 0.51, 6], [10, H - 0.5], [11, -0.5],
                     [W - 1, H - 1], [np.nan, 3], [4, np.inf], [-np.inf, 2]])
    pts[:, 15:15 + len(edge)] = edge
    cnt = rng.integers(1, 4, (B, N))
    valid = rng.random((B, N)) > 0.15
    base = (rng.random((B, H, W)) > 0.03).astype(np.uint8) * 255
    base[1, :, :4] = 254
    for dt, it in ((torch.float32, torch.int64), (torch.float64, torch.int32)):
        p, c = torch.from_numpy(pts).to(dt), torch.from_numpy(cnt).to(it)
        v = torch.from_numpy(valid)
        for radius in (0, 1, 5, 30, 80):
            for bm in (torch.from_numpy(base), torch.from_numpy(base[:1])):
                fk, fm = _assert_all_equal(p, c, v, radius, bm, f"{dt} {it} r={radius}")
                for b in range(B):
                    k1, m1 = set_mask_op(p[b:b + 1], c[b:b + 1], v[b:b + 1], bm[b:b + 1] if bm.shape[0] > 1 else bm,
                                         float(radius))
                    assert torch.equal(k1[0], fk[b]) and torch.equal(m1[0], fm[b])
        fk, fm = set_mask_op(p, c, v, torch.from_numpy(base), 7.5)
        tk, tm = _distance_mask_impl(p, c, v, 7.5, torch.from_numpy(base).clone())[:2]
        assert torch.equal(fk, tk) and torch.equal(fm, tm)
    # empty: no features, no streams
    k, m = set_mask_op(torch.zeros(2, 0, 2), torch.zeros(2, 0, dtype=torch.long), torch.zeros(2, 0, dtype=torch.bool),
                       torch.full((1, 5, 6), 255, dtype=torch.uint8), 3.0)
    assert k.shape == (2, 0) and torch.equal(m, torch.full((2, 5, 6), 255, dtype=torch.uint8))


def test_disc_spans_are_cv2_circle():
    """The disc's rows (``disc_spans``) are ``cv2.circle``'s filled rows for radii 0..60."""
    for r in range(61):
        m = np.full((2 * r + 3, 2 * r + 3), 255, np.uint8)
        cv2.circle(m, (r + 1, r + 1), r, 0, -1)
        hw = disc_spans(disc_r2(r, 10 ** 4, 10 ** 4))
        assert len(hw) == r + 1
        for dy in range(-r - 1, r + 2):
            zeros = np.flatnonzero(m[r + 1 + dy] == 0) - (r + 1)
            want = np.arange(-hw[abs(dy)], hw[abs(dy)] + 1) if abs(dy) <= r else np.array([], int)
            np.testing.assert_array_equal(zeros, want, err_msg=f"r={r} dy={dy}")


def test_fused_set_mask_is_one_op_and_checks_its_arguments():
    """One op, no sync (``OpCounter``); the door runs it; clear errors."""
    pts = torch.tensor([[[10.0, 10.0], [12.0, 10.0], [40.0, 30.0]]])
    cnt = torch.tensor([[1, 3, 2]])
    valid = torch.ones(1, 3, dtype=torch.bool)
    base = torch.full((1, 48, 64), 255, dtype=torch.uint8)
    set_mask_op(pts, cnt, valid, base, 5.0)
    with OpCounter() as c:
        keep, mask = set_mask_op(pts, cnt, valid, base, 5.0)
    assert c.kernels == 1 and c.syncs == 0, c.summary()
    assert keep.tolist() == [[False, True, True]]
    with OpCounter() as c:
        res = _distance_mask_impl(pts, cnt, valid, 5.0, base, backend="fused")
    assert c.kernels == 1 and c.syncs == 0 and res.overflow is None, c.summary()
    with OpCounter() as c:
        res = _distance_mask_impl(pts, cnt, valid, 5.0, base, backend="fused", capturable=True)
    assert c.kernels == 2 and c.syncs == 0 and not res.overflow.any(), c.summary()  # the op + the zero overflow
    k2, m2 = distance_mask(pts, cnt, valid, 5, base[0], backend="tensor")
    assert torch.equal(k2, keep) and torch.equal(m2, mask)
    with pytest.raises(ValueError, match="priority"):
        set_mask_op(pts, cnt.float(), valid, base, 5.0)
    with pytest.raises(ValueError, match="base"):
        set_mask_op(pts, cnt, valid, base.expand(2, -1, -1), 5.0)
    with pytest.raises(ValueError, match="radius"):
        set_mask_op(pts, cnt, valid, base, -1.0)
    with pytest.raises(tf.errors.ConfigError, match="priority"):
        distance_mask(pts, cnt.float(), valid, 5, base[0], backend="fused")
    # float priorities: "auto" runs the tensor kernel
    k3, _ = distance_mask(pts, cnt.double(), valid, 5, base[0])
    assert torch.equal(k3, keep)


def test_tracker_runs_the_fused_set_mask(monkeypatch):
    """A tracker on the fused backend calls the op in its setMask stage, with one base mask for all
    streams (no copy), and gets the tensor kernel's bits there; a tensor tracker runs the tensor kernel."""
    calls = []
    real = stages._distance_mask_impl

    def spy(pts, pri, valid, radius, mask, **kw):
        calls.append((kw.get("backend"), mask.shape[0]))
        res = real(pts, pri, valid, radius, mask, **kw)
        if kw.get("backend") == "fused":
            ref = real(pts, pri, valid, radius, mask.expand(pts.shape[0], -1, -1).clone())
            assert torch.equal(res.keep, ref.keep) and torch.equal(res.mask, ref.mask)
        return res

    monkeypatch.setattr(stages, "_distance_mask_impl", spy)
    cfg = dataclasses.replace(tf.load_config(CFG_PATH), image_width=160, image_height=120, min_dist=12)
    frames = [(t, np.ascontiguousarray(img[100:220, 200:360])) for t, img in _frames(sample_frames("cam0")[:4])]
    for be in ("fused", "tensor"):
        tr = FeatureTracker(cfg, num_streams=2, lk_backend=be)
        for t, img in frames:
            tr.track(torch.from_numpy(np.stack([img, img[::-1].copy()]))[:, None], [t, t])
    assert ("fused", 1) in calls and ("tensor", 2) in calls, calls


def test_op_passes_opcheck_and_compiles_as_one_node():
    """``torch.library.opcheck`` (schema, fake, autograd registration, AOT dispatch) and
    ``torch.compile(fullgraph=True)`` of the door's fused path on the CPU (no graph break)."""
    from torch_frontend.fused import selfcheck

    c = selfcheck.case()
    pts = torch.cat((c["pts"], c["init"]), 1)
    cnt = (torch.arange(48).view(2, 24) * 7) % 4
    valid = torch.cat((c["valid"], c["valid"]), 1)
    base = torch.full((1, 72, 104), 255, dtype=torch.uint8)
    res = torch.library.opcheck(set_mask_op, (pts, cnt, valid, base, 17.0))
    assert all(v == "SUCCESS" for v in res.values()), res

    def fn(p, q, v, m):
        return _distance_mask_impl(p, q, v, 17.0, m, capturable=True, backend="fused")[:2]

    got = torch.compile(fn, backend="eager", fullgraph=True)(pts, cnt, valid, base)
    want = fn(pts, cnt, valid, base)
    assert all(torch.equal(x, y) for x, y in zip(got, want))


def test_threads_give_the_same_bits():
    """Stream groups on the thread pool (2 and 3 threads): each stream's bits are its own."""
    rng = np.random.default_rng(3)
    B, N, H, W = 5, 60, 48, 64
    pts = torch.from_numpy(rng.uniform(-1, [W, H], (B, N, 2)).astype(np.float32))
    cnt = torch.from_numpy(rng.integers(1, 4, (B, N)))
    valid = torch.from_numpy(rng.random((B, N)) > 0.1)
    base = torch.full((1, H, W), 255, dtype=torch.uint8)
    want = set_mask_op(pts, cnt, valid, base, 6.0)
    n = torch.get_num_threads()
    try:
        for t in (2, 3):
            torch.set_num_threads(t)
            got = set_mask_op(pts, cnt, valid, base, 6.0)
            assert all(torch.equal(a, b) for a, b in zip(got, want)), t
    finally:
        torch.set_num_threads(n)
