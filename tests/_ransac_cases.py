"""Shared cases of the RANSAC tests (``test_ransac.py``, ``test_ransac_capturable.py``,
``test_ransac_lo.py``, ``test_threads.py``): synthetic two-view scenes, planted outliers, cv2's
masks, constructed ties, OpenCV's sequential sample rule and cubics of every kind.

Convention: points are ``(n, 2)`` float64 numpy arrays in pixels of a 460-px pinhole (752 x 480);
cv2 is called on their float32 rounding, as the tracker's points are.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

FOCAL = 460.0


def _synthetic_scenes(k: int = 8, n: int = 150, noise: float = 0.15, seed: int = 3):
    """Random non-planar points (depth 3..15 m), two known poses, 460-px pinhole, Gaussian noise."""
    rng = np.random.default_rng(seed)
    K = np.array([[FOCAL, 0, 376.0], [0, FOCAL, 240.0], [0, 0, 1.0]])
    scenes = []
    for _ in range(k):
        z = rng.uniform(3.0, 15.0, n)
        X = np.stack([rng.uniform(-0.8, 0.8, n) * z, rng.uniform(-0.5, 0.5, n) * z, z], -1)
        R, _ = cv2.Rodrigues(rng.normal(0, 0.05, 3))
        t = rng.normal(0, 0.3, 3) + np.array([0.4, 0.0, 0.1])
        x1 = X @ K.T
        X2 = X @ R.T + t
        x2 = X2 @ K.T
        scenes.append(
            (
                x1[:, :2] / x1[:, 2:] + rng.normal(0, noise, (n, 2)),
                x2[:, :2] / x2[:, 2:] + rng.normal(0, noise, (n, 2)),
            )
        )
    return scenes


def _cv_mask(a, c):
    F, m = cv2.findFundamentalMat(a.astype(np.float32), c.astype(np.float32), cv2.FM_RANSAC, 1.0, 0.99)
    assert F is not None and m is not None
    return m.ravel().astype(bool)


def _reference_F(a: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Reference geometry of a clean pair: cv2's 8-point fit on cv2's RANSAC inliers."""
    m = _cv_mask(a, c)
    F, _ = cv2.findFundamentalMat(a[m], c[m], cv2.FM_8POINT)
    return F


def _line_dists(F, a, c):
    h1, h2 = np.c_[a, np.ones(len(a))], np.c_[c, np.ones(len(c))]
    l2, l1 = h1 @ F.T, h2 @ F
    d = np.abs((h2 * l2).sum(1))
    return d / np.hypot(l1[:, 0], l1[:, 1]), d / np.hypot(l2[:, 0], l2[:, 1])


def _plant(a: np.ndarray, c: np.ndarray, rate: float, rng, F_ref=None, col: int = 752, row: int = 480):
    """Replace ``rate`` of the second-image points by gross outliers: uniform random points >= 20 px
    from the true match and >= 5 px from the epipolar lines of the reference geometry in both
    images (a uniform point within ~1 px of its epipolar line is geometrically an inlier and no
    estimator can reject it)."""
    n = len(c)
    m = int(round(rate * n))
    idx = rng.choice(n, size=m, replace=False)
    out = c.copy()
    for i in idx:
        while True:
            q = rng.uniform([0, 0], [col, row], size=(64, 2))
            ok = np.hypot(*(q - c[i]).T) >= 20
            if F_ref is not None:
                d1, d2 = _line_dists(F_ref, np.repeat(a[i : i + 1], 64, 0), q)
                ok &= np.minimum(d1, d2) >= 5.0
            if ok.any():
                out[i] = q[ok.argmax()]
                break
    planted = np.zeros(n, bool)
    planted[idx] = True
    return out, planted


def _scatter(sets, N, rng, device="cpu"):
    """Point sets scattered over ``N`` slots (the rest NaN): p1, p2 (B, N, 2) float64, valid, slots."""
    B = len(sets)
    p1 = torch.full((B, N, 2), float("nan"), dtype=torch.float64)
    p2 = p1.clone()
    valid = torch.zeros(B, N, dtype=torch.bool)
    slots = []
    for b, (a, c) in enumerate(sets):
        s = np.sort(rng.choice(N, size=len(a), replace=False))
        p1[b, s] = torch.from_numpy(np.asarray(a, dtype=np.float64))
        p2[b, s] = torch.from_numpy(np.asarray(c, dtype=np.float64))
        valid[b, s] = True
        slots.append(s)
    return p1.to(device), p2.to(device), valid.to(device), slots


def _reference_subsets(state: int, n: int, num: int) -> np.ndarray:
    """OpenCV ``getSubset`` with ``cv::RNG(state)``, written out sequentially (the oracle of the
    vectorised, lazily grown sample tables)."""
    s, out = state, []
    while len(out) < num:
        cur: list = []
        while len(cur) < 7:
            s = (s & 0xFFFFFFFF) * 4164903690 + (s >> 32)
            v = (s & 0xFFFFFFFF) % n
            if v not in cur:
                cur.append(v)
        out.append(cur)
    return np.array(out, dtype=np.int64)


def _cubic_cases() -> np.ndarray:
    """Cubics of every kind ``cv::solveCubic`` tells apart: three distinct real roots, one real
    root, double and triple roots with representable values (where cv2 itself reports 1, 2 or 3
    roots, by rounding), ``c0 == 0`` (quadratics with two, one double or no real root; linear;
    nothing), a negligible ``c0`` (below eps * max |c|: a quadratic for OpenCV) and a tiny one (a
    cubic with a huge root)."""
    rng = np.random.default_rng(0)
    cases = []
    for _ in range(1000):
        cases.append(np.poly(rng.normal(size=3) * rng.choice([1e-3, 1.0, 1e3])) * rng.normal())
        cases.append(rng.normal(size=4) * rng.choice([1e-3, 1.0, 1e3], 4))
        s, d = rng.integers(-8, 9, 2) / rng.choice([1, 2, 4, 8], 2)
        cases.append(np.poly([s, d, d]) * rng.choice([1.0, -1.0, 0.5, 3.0]))
    for _ in range(200):
        q = rng.integers(-5, 6, 3) / rng.choice([1, 2, 4], 3)
        r = rng.integers(-5, 6) / 2
        cases += [np.r_[0.0, q], np.r_[0.0, 0.0, q[1:]], np.r_[0.0, np.poly([r, r])],
                  np.r_[rng.choice([1e-17, -1e-13, 1e-9]), rng.normal(size=3)]]
    cases += [np.zeros(4), np.array([0.0, 0, 0, 1]), np.array([1.0, -3, 3, -1]), np.array([2.0, 0, 0, 0])]
    return np.array(cases, dtype=np.float64)


def _unit(F: np.ndarray) -> np.ndarray:
    F = F / np.linalg.norm(F)
    return F * np.sign(F.flat[np.abs(F).argmax()])


def _epipolar_error(F, a, c):
    """OpenCV's computeError: max of the squared distances to the two epipolar lines."""
    h1, h2 = np.c_[a, np.ones(len(a))], np.c_[c, np.ones(len(c))]
    l2, l1 = h1 @ F.T, h2 @ F
    d = (h2 * l2).sum(1)
    return np.maximum(d**2 / (l1[:, 0] ** 2 + l1[:, 1] ** 2), d**2 / (l2[:, 0] ** 2 + l2[:, 1] ** 2))


def _tie_problem(seed: int, n_pencil: int = 60, n_each: int = 2, n_out: int = 16):
    """A constructed tie. Two random fundamental matrices ``Fa``, ``Fb`` (460-px pinhole, random
    small rotations and translations) span a pencil whose third rank-2 member is ``Fc``;
    ``n_pencil`` correspondences lie on both epipolar lines of ``Fa`` and ``Fb`` (``x2`` = their
    intersection), hence on every model of the pencil: any 7 of them give exactly ``Fa``, ``Fb``,
    ``Fc``. ``n_each`` more fit ``Fa`` only, ``n_each`` fit ``Fb`` only (>= 5 px from the other
    models' lines), ``n_out`` fit none. So ``Fa`` and ``Fb`` tie at ``n_pencil + n_each`` inliers
    with masks that differ in ``2 n_each`` labels, and when the first good sample is a pencil one
    (most seeds), the model kept is the first of the tied pair in the sample's model order.
    Returns float32 ``a, c`` and the inlier counts of ``Fa, Fb, Fc`` at 1 px."""
    rng = np.random.default_rng(seed)
    W, H = 752, 480
    K = np.array([[460.0, 0, 376.0], [0, 460.0, 240.0], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    Fs = []
    for _ in range(2):
        R, _ = cv2.Rodrigues(rng.normal(0, 0.1, 3))
        t = rng.normal(0, 1, 3)
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        Fs.append(Ki.T @ tx @ R @ Ki)
    Fa, Fb = Fs
    # det(x Fa + (1 - x) Fb) is a cubic in x with the roots 1 (Fa) and 0 (Fb); the third is Fc's
    xs = np.array([-1.0, 0.5, 2.0, 3.0])
    coef = np.polyfit(xs, [np.linalg.det(x * Fa + (1 - x) * Fb) for x in xs], 3)
    third = -coef[1] / coef[0] - 1.0  # sum of the roots = -c1 / c0
    Fc = third * Fa + (1 - third) * Fb
    models = (Fa, Fb, Fc)

    def inside(p):
        return (p[..., 0] > 5) & (p[..., 0] < W - 5) & (p[..., 1] > 5) & (p[..., 1] < H - 5)

    x1 = rng.uniform([0, 0], [W, H], (4000, 2))
    h1 = np.c_[x1, np.ones(len(x1))]
    x2h = np.cross(h1 @ Fa.T, h1 @ Fb.T)
    x2 = x2h[:, :2] / x2h[:, 2:]
    keep = inside(x2)
    assert keep.sum() >= n_pencil
    sets = [(x1[keep][:n_pencil], x2[keep][:n_pencil])]

    def pairs(k, fits):
        out = []
        while len(out) < k:
            p, q = rng.uniform([0, 0], [W, H]), rng.uniform([0, 0], [W, H])
            if fits is not None:  # move q onto the epipolar line of p
                line = fits @ np.r_[p, 1.0]
                q = np.array([q[0], -(line[0] * q[0] + line[2]) / line[1]])
                if not inside(q):
                    continue
            if all(_epipolar_error(G, p[None], q[None])[0] >= 25.0 for G in models if G is not fits):
                out.append((p, q))
        return np.array([p for p, _ in out]), np.array([q for _, q in out])

    sets += [pairs(n_each, Fa), pairs(n_each, Fb), pairs(n_out, None)]
    a = np.concatenate([s[0] for s in sets])
    c = np.concatenate([s[1] for s in sets])
    perm = rng.permutation(len(a))
    a, c = a[perm].astype(np.float32), c[perm].astype(np.float32)
    counts = [int((_epipolar_error(G, a.astype(np.float64), c.astype(np.float64)) <= 1.0).sum()) for G in models]
    return a, c, counts
