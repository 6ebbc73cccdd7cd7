"""Place recognition on a rendered sequence that revisits places.

A camera flies the same closed loop twice over a "world" made of two real photos (an EuRoC frame
and the Middlebury Motorcycle image side by side). Poses are exact, so the ground-truth loops are
the earlier views whose footprint overlaps the current one. Keyframe descriptors are FAST (threshold
20) + BRIEF (VINS's rules), a vocabulary (k 10, L 5) is trained on the first lap's keyframes, and
VINS's ``detectLoop`` rule
(top 4, ``max_id = index − 50``, 0.05 / 0.015 thresholds, index > 50) runs on every keyframe.

The same pipeline is also built from ``cv2.FAST`` and a plain-numpy BRIEF, side by side.
Acceptance: detection precision ≥ 95 % at VINS's thresholds; recall is reported.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torch_frontend.loop.database import PlaceDatabase
from torch_frontend.loop.features import brief, default_brief_pattern, fast
from torch_frontend.loop.vocabulary import Vocabulary

from .conftest import TEST_DATA, load_gray, sample_frames

VIEW_W, VIEW_H = 240, 180
N_PER_LAP = 64


def _world():
    a = load_gray(sample_frames("cam0")[0])
    b = cv2.imread(str(TEST_DATA / "motorcycle" / "motorcycle_left.png"), cv2.IMREAD_GRAYSCALE)
    h = min(a.shape[0], b.shape[0])
    return np.concatenate([a[:h], b[:h]], axis=1)  # 480 x 1493


def _poses(lap: int):
    """Centre (x, y) in world pixels and in-plane angle (rad) of each keyframe of a lap; the second
    lap is the same loop, shifted by a few pixels and a slight rotation (a real revisit)."""
    t = np.arange(N_PER_LAP) / N_PER_LAP * 2 * np.pi
    cx = 746 + 560 * np.cos(t) + (6.0 if lap else 0.0)
    cy = 240 + 110 * np.sin(t) + (-4.0 if lap else 0.0)
    ang = 0.05 * np.sin(2 * t) + (0.03 if lap else 0.0)
    return np.stack([cx, cy, ang], 1)


def _render(world, pose):
    cx, cy, ang = pose
    c, s = np.cos(ang), np.sin(ang)
    # view pixel (u, v) -> world: R (u - W/2, v - H/2) + centre
    M = np.array([[c, -s, cx - c * VIEW_W / 2 + s * VIEW_H / 2], [s, c, cy - s * VIEW_W / 2 - c * VIEW_H / 2]])
    return cv2.warpAffine(world, M, (VIEW_W, VIEW_H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)


def _numpy_brief(img, pts, pattern):
    """Plain numpy BRIEF with VINS's rules (blur 9×9 σ=2, truncation, 0 outside)."""
    blur = cv2.GaussianBlur(img, (9, 9), 2, 2, borderType=cv2.BORDER_REFLECT_101).astype(np.int32)
    H, W = img.shape
    x1, y1, x2, y2 = pattern
    out = np.zeros((len(pts), 4), dtype=np.uint64)
    for j, (x, y) in enumerate(pts):
        ax = np.trunc(np.float32(x) + x1.astype(np.float32)).astype(int)
        ay = np.trunc(np.float32(y) + y1.astype(np.float32)).astype(int)
        bx = np.trunc(np.float32(x) + x2.astype(np.float32)).astype(int)
        by = np.trunc(np.float32(y) + y2.astype(np.float32)).astype(int)
        inside = (ax >= 0) & (ax < W) & (ay >= 0) & (ay < H) & (bx >= 0) & (bx < W) & (by >= 0) & (by < H)
        bits = np.zeros(len(x1), dtype=bool)
        bits[inside] = blur[ay[inside], ax[inside]] < blur[by[inside], bx[inside]]
        for i in np.flatnonzero(bits):
            out[j, i // 64] |= np.uint64(1) << np.uint64(i % 64)
    return out.view(np.int64)


def _torch_descriptors(views):
    imgs = torch.from_numpy(np.stack(views))[:, None]
    pts, _, valid = fast(imgs, threshold=20, nonmax=True)
    desc = brief(imgs, pts, valid)
    return desc, valid


def _cv_descriptors(views):
    pattern = default_brief_pattern().cpu().numpy()
    orb = cv2.FastFeatureDetector_create(20, True)
    per = []
    for v in views:
        kps = orb.detect(v)
        pts = np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2)
        per.append(_numpy_brief(v, pts, pattern))
    K = max(len(d) for d in per)
    desc = np.zeros((len(per), K, 4), dtype=np.int64)
    valid = np.zeros((len(per), K), dtype=bool)
    for i, d in enumerate(per):
        desc[i, :len(d)] = d
        valid[i, :len(d)] = True
    return torch.from_numpy(desc), torch.from_numpy(valid)


def _detect(desc, valid, poses):
    lap1 = slice(0, N_PER_LAP)
    voc = Vocabulary.train(desc[lap1], valid[lap1], k=10, L=5, generator=torch.Generator().manual_seed(0))
    db = PlaceDatabase(voc)
    bows = voc.transform(desc, valid)
    tp = fp = 0
    should = 0
    for i in range(desc.shape[0]):
        cand = db.detect_loop(type(bows)(bows.words[i:i + 1], bows.weights[i:i + 1]), i)
        # ground truth: an earlier view (id < i - 50, as VINS queries) whose footprint shares at
        # least a quarter of the view area with the current one
        if i > 50 and _overlap(poses[: i - 50], poses[i]).max() >= 0.25:
            should += 1
        if cand >= 0:
            ok = _overlap(poses[cand:cand + 1], poses[i])[0] >= 0.25
            tp += int(ok)
            fp += int(not ok)
    return tp, fp, should


def _overlap(others, pose):
    """Fraction of the view area shared with each of ``others`` (axis-aligned footprints; the
    in-plane rotations are ≤ 0.08 rad, which this ignores)."""
    dx = np.abs(others[:, 0] - pose[0])
    dy = np.abs(others[:, 1] - pose[1])
    return np.clip(VIEW_W - dx, 0, None) * np.clip(VIEW_H - dy, 0, None) / (VIEW_W * VIEW_H)


@pytest.mark.slow  # slow, and CI (make test-all) runs it: keeps make test within ~5 min
def test_revisit_loop_detection_precision():
    world = _world()
    poses = np.concatenate([_poses(0), _poses(1)])
    views = [_render(world, p) for p in poses]
    results = {}
    for name, (desc, valid) in (("torch", _torch_descriptors(views)), ("cv2+numpy", _cv_descriptors(views))):
        tp, fp, should = _detect(desc, valid, poses)
        precision = tp / max(tp + fp, 1)
        recall = tp / max(should, 1)
        results[name] = (precision, recall, tp, fp, should)
        print(f"{name:10s}: precision {precision:.3f} recall {recall:.3f} (tp {tp}, fp {fp}, "
              f"revisits {should}, mean keypoints {valid.sum(1).float().mean():.0f})")
    p, r, tp, fp, should = results["torch"]
    assert should >= 50
    assert tp > 0
    assert p >= 0.95
