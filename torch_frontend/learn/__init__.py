"""Training through the front end: ``nn.Module`` wrappers, tracking losses and a soft status.

See ``docs/differentiability.md`` for what is differentiable with respect to what, and how.
"""

from .._lazy import lazy_exports

_EXPORTS = {
    "tracking_loss": "losses",
    "homography_targets": "losses",
    "sample_flow": "losses",
    "soft_status": "status",
    "sample_windows": "status",
    "LucasKanade": "modules",
    "TrackerModule": "modules",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
