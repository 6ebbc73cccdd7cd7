"""The package's own photo: the first EuRoC cam0 frame of ``torch_frontend/data/euroc_mini``
(752x480, grey), the texture of both synthetic scenes (``synthetic``'s room, ``flight``'s plane)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import ConfigError

PHOTO_DIR = Path(__file__).resolve().parents[1] / "data" / "euroc_mini" / "mav0" / "cam0" / "data"


def package_photo() -> np.ndarray:
    """``(480, 752)`` uint8: the first (by name = timestamp) PNG of ``PHOTO_DIR``."""
    frames = sorted(PHOTO_DIR.glob("*.png"))
    if not frames:
        raise ConfigError("package photo missing (torch_frontend/data/euroc_mini)", path=PHOTO_DIR)
    img = cv2.imread(str(frames[0]), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ConfigError("cannot read the package photo", path=frames[0])
    return img
