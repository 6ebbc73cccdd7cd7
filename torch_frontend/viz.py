"""Track images with VINS's colouring (spec §3.12, §6.6)."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

WINDOW_SIZE = 20  # track count at which the colour saturates to red


def _to_bgr(image) -> np.ndarray:
    img = image
    if isinstance(img, torch.Tensor):
        img = img.detach().cpu()
        if img.dim() == 3 and img.shape[0] == 1:
            img = img[0]
        img = img.round().clamp(0, 255).to(torch.uint8).numpy() if img.is_floating_point() else img.numpy()
    img = np.asarray(img)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 3:
        return img.astype(np.uint8).copy()
    raise ValueError(f"image: expected (H, W), (1, H, W) or (H, W, 3), got {img.shape}")


def draw_tracks(image, frame, b: int = 0, right_image=None, arrows: Optional[bool] = None) -> np.ndarray:
    """Draw stream ``b`` of a ``FeatureFrame`` on its (raw, non-equalised) grey image.

    Every feature of the table is a circle of radius 2, thickness 2, coloured in BGR
    ``(255 (1 - len), 0, 255 len)`` with ``len = min(1, track_count / 20)``: blue = new, red = tracked
    for 20 frames or more. For VINS-Fusion frames (``frame.prev_uv`` set) green arrows go from each
    feature to its previous position; with ``right_image`` the right view is drawn beside the left
    one with green circles at the right observations.

    Args:
        image: ``(H, W)`` / ``(1, H, W)`` grey tensor or array, or ``(H, W, 3)`` BGR.
        frame: the ``FeatureFrame`` returned by ``FeatureTracker.track``.
        b: stream index.

    Returns:
        ``(H, W, 3)`` uint8 BGR image (``(H, 2W, 3)`` with ``right_image``), ready for ``cv2.imwrite``.
    """
    import cv2

    if not 0 <= b < frame.batch_size:
        raise ValueError(f"b: expected 0 <= b < {frame.batch_size}, got {b}")
    left = _to_bgr(image)
    W = left.shape[1]
    canvas = left if right_image is None else np.concatenate([left, _to_bgr(right_image)], axis=1)
    present = frame.present[b].cpu().numpy()
    uv = frame.uv[b].detach().cpu().double().numpy()
    cnt = frame.track_count[b].cpu().numpy()
    for j in np.flatnonzero(present):
        ln = min(1.0, cnt[j] / WINDOW_SIZE)
        colour = (int(round(255 * (1 - ln))), 0, int(round(255 * ln)))
        cv2.circle(canvas, (int(np.rint(uv[j, 0])), int(np.rint(uv[j, 1]))), 2, colour, 2)
    draw_arrows = frame.prev_uv is not None if arrows is None else arrows
    if draw_arrows and frame.prev_uv is not None:
        prev = frame.prev_uv[b].detach().cpu().double().numpy()
        pv = frame.prev_valid[b].cpu().numpy()
        for j in np.flatnonzero(present & pv):
            p = (int(np.rint(uv[j, 0])), int(np.rint(uv[j, 1])))
            q = (int(np.rint(prev[j, 0])), int(np.rint(prev[j, 1])))
            cv2.arrowedLine(canvas, p, q, (0, 255, 0), 1, 8, 0, 0.2)
    if right_image is not None and frame.right_valid is not None:
        ruv = frame.right_uv[b].detach().cpu().double().numpy()
        for j in np.flatnonzero(frame.right_valid[b].cpu().numpy()):
            cv2.circle(canvas, (int(np.rint(ruv[j, 0])) + W, int(np.rint(ruv[j, 1]))), 2, (0, 255, 0), 2)
    return canvas


__all__ = ["draw_tracks"]
