"""A synthetic flight: a camera flying over a real photo (a plane), with the exact homographies.

The tracker's test bed for sub-pixel truth (numpy + cv2 only, no torch): every frame is the photo
seen through a known homography, so where each tracked point should be is known exactly.

Convention:
    * ``H_k`` maps texture pixels to frame-``k`` pixels, ``(x, y, 1)`` homogeneous, pixel centres at
      integer coordinates in both images. The texture is the package photo (``package_photo``, the
      first EuRoC cam0 frame, 752x480).
    * Motion: ~2-3 px/frame translation, slow rotation (0.002 rad/frame) and zoom (+0.15 %/frame),
      mild perspective.
    * Rendering: 4x supersampled (bilinear ``warpPerspective``, reflected border) and area-averaged
      (``INTER_AREA``), so that interpolation blur does not bias sub-pixel positions; rounded to
      uint8. Deterministic (no randomness).
"""

from __future__ import annotations

from typing import List, Tuple

import cv2
import numpy as np

from ._photo import package_photo

__all__ = ["synthetic_flight"]

#: supersampling factor of the rendering (per axis)
SUPERSAMPLE = 4


def synthetic_flight(n_frames: int = 16, size: Tuple[int, int] = (400, 640)
                     ) -> Tuple[List[np.ndarray], List[np.ndarray]]:
    """Frames of a camera flying over the package photo, and the exact homographies.

    Args:
        n_frames: number of frames.
        size: ``(H, W)`` of every frame, pixels.

    Returns:
        ``frames``: ``n_frames`` ``(H, W)`` uint8 arrays; ``Hs``: ``n_frames`` ``(3, 3)`` float64
        homographies texture -> frame (see the module docstring).
    """
    tex = package_photo().astype(np.float32)
    H, W = size
    frames, Hs = [], []
    s = SUPERSAMPLE
    S = np.diag([s, s, 1.0])
    for k in range(n_frames):
        a = 0.002 * k
        sc = 1.0 + 0.0015 * k
        tx, ty = 40 + 2.5 * k, 30 + 1.5 * k
        c, si = np.cos(a) * sc, np.sin(a) * sc
        # frame point = A @ texture point (texture -> frame), mild perspective
        A = np.array([[c, -si, -tx], [si, c, -ty], [2e-6 * k, -1e-6 * k, 1.0]])
        big = cv2.warpPerspective(tex, S @ A, (W * s, H * s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        img = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
        # the supersampled pixel grid: frame pixel centre x maps to big pixel centre s*x + (s-1)/2
        C = np.array([[1.0 / s, 0, (1.0 / s - 1) / 2], [0, 1.0 / s, (1.0 / s - 1) / 2], [0, 0, 1]])
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
        Hs.append(C @ S @ A)
    return frames, Hs
