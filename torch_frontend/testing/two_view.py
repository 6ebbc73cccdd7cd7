"""Two-view scenes with planted outliers and exact ground truth: the F-RANSAC test bed.

Convention:
    Points at 3..15 m in front of two 460-px pinholes (752x480, principal point (376, 240)), the
    second camera moved by a random small rotation and a ~0.4 m translation. Pixels ``(x, y)``,
    numpy float64. A fraction ``rate`` of the second-image points is replaced by uniform points at
    least 20 px from the true match and 5 px from its true epipolar lines in both images (real
    outliers, not near-inliers). Used by ``tests/test_ransac_lo.py`` and
    ``benchmarks/bench_fundamental_accuracy.py`` (the same seeds give the same scenes).
"""

from __future__ import annotations

from typing import Dict

import cv2
import numpy as np

__all__ = ["planted_scenes", "line_distances", "PINHOLE_K"]

#: the virtual pinhole of the scenes (VINS's 460-px FOCAL_LENGTH, a 752x480 image)
PINHOLE_K = np.array([[460.0, 0, 376.0], [0, 460.0, 240.0], [0, 0, 1.0]])
OUTLIER_MIN_MATCH_PX = 20.0  # a planted point is at least this far from the true match
OUTLIER_MIN_LINE_PX = 5.0  # ... and from the true epipolar lines in both images


def _skew(t):
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def line_distances(F: np.ndarray, a: np.ndarray, c: np.ndarray):
    """Distances (px) of ``a (n, 2)`` to its lines ``F^T c`` in image 1 and of ``c`` to ``F a`` in
    image 2 (rejectWithF's test is ``max(d1, d2) <= threshold``)."""
    h1, h2 = np.c_[a, np.ones(len(a))], np.c_[c, np.ones(len(c))]
    l2, l1 = h1 @ F.T, h2 @ F
    d = np.abs((h2 * l2).sum(1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return d / np.hypot(l1[:, 0], l1[:, 1]), d / np.hypot(l2[:, 0], l2[:, 1])


def planted_scenes(k: int, rate: float, seed: int, n: int = 150, noise: float = 0.3,
                   noisy_first: bool = True) -> Dict[str, np.ndarray]:
    """``k`` scenes of ``n`` matches: Gaussian noise ``noise`` px per coordinate in image 2 (and in
    image 1 unless ``noisy_first`` is False), ``rate`` of the matches planted outliers.

    Returns a dict of stacked arrays: ``p1, p2 (k, n, 2)`` the noisy, planted matches, ``g1, g2``
    their noise-free true positions, ``F (k, 3, 3)`` the true fundamental matrices and
    ``planted (k, n)`` bool."""
    rng = np.random.default_rng(seed)
    K = PINHOLE_K
    Ki = np.linalg.inv(K)
    names = ("p1", "p2", "g1", "g2", "F", "planted")
    out = {name: [] for name in names}
    for _ in range(k):
        z = rng.uniform(3, 15, n)
        X = np.stack([rng.uniform(-0.8, 0.8, n) * z, rng.uniform(-0.5, 0.5, n) * z, z], -1)
        R, _ = cv2.Rodrigues(rng.normal(0, 0.05, 3))
        t = rng.normal(0, 0.3, 3) + np.array([0.4, 0.0, 0.1])
        g1 = X @ K.T
        g1 = g1[:, :2] / g1[:, 2:]
        g2 = (X @ R.T + t) @ K.T
        g2 = g2[:, :2] / g2[:, 2:]
        F = Ki.T @ _skew(t) @ R @ Ki
        a = g1 + (rng.normal(0, noise, (n, 2)) if noisy_first else 0.0)
        c = g2 + rng.normal(0, noise, (n, 2))
        planted = np.zeros(n, bool)
        planted[rng.choice(n, int(round(rate * n)), replace=False)] = True
        for i in np.flatnonzero(planted):
            while True:
                q = rng.uniform([0, 0], [752, 480], (64, 2))
                d1, d2 = line_distances(F, np.repeat(g1[i : i + 1], 64, 0), q)
                good = (np.hypot(*(q - g2[i]).T) >= OUTLIER_MIN_MATCH_PX) & (np.minimum(d1, d2) >= OUTLIER_MIN_LINE_PX)
                if good.any():
                    c[i] = q[good.argmax()]
                    break
        for name, v in zip(names, (a, c, g1, g2, F, planted)):
            out[name].append(v)
    return {name: np.stack(v) for name, v in out.items()}
