"""torch-frontend: the VINS-Mono visual front end (KLT feature tracker) as batched, differentiable
PyTorch/kornia tensor code.

Public names are imported lazily from their modules (one concept per module), so that
``import torch_frontend`` stays cheap and each kernel module can be used on its own.
"""

from __future__ import annotations

from ._lazy import lazy_exports

__version__ = "0.1.0"

# public name -> module that defines it
_EXPORTS = {
    # foundation
    "ConfigError": "errors",
    "DataError": "errors",
    "clear_caches": "_cache",
    "TrackerConfig": "config",
    "load_config": "config",
    "load_camera": "config",
    "camera_from_config": "camera",
    "CameraModel": "camera",
    "CameraBatch": "camera",
    "PinholeCamera": "camera",
    "PinholeFullCamera": "camera",
    "MeiCamera": "camera",
    "KannalaBrandtCamera": "camera",
    "ScaramuzzaCamera": "camera",
    # image stage
    "clahe": "equalize",
    "build_pyramid": "pyramid",
    "pyr_down": "pyramid",
    "scharr_gradients": "pyramid",
    "Pyramid": "pyramid",
    "min_eigen_response": "corners",
    "harris_response": "corners",
    "good_features_to_track": "corners",
    "distance_mask": "masks",
    "fisheye_mask": "masks",
    # tracking
    "track_lk": "lk",
    "find_fundamental": "ransac",
    "refit_fundamental": "ransac",
    "FundamentalResult": "ransac",
    "FeatureTracker": "tracker",
    "FeatureFrame": "tracker",
    "draw_tracks": "viz",
    # learning through the front end
    "LucasKanade": "learn",
    "TrackerModule": "learn",
    "tracking_loss": "learn",
    "soft_status": "learn",
}

__all__ = sorted(_EXPORTS) + ["__version__"]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
