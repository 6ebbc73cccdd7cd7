"""References and test beds: what torch-frontend is tested against, shipped so that you can test
your own code (or a modified kernel) the same way.

* ``oracle``: the OpenCV oracle pipeline, a plain sequential numpy + cv2 re-implementation of the
  VINS-Mono / VINS-Fusion KLT front end (``OracleMonoTracker``, ``OracleFusionTracker``,
  ``run_oracle_sequence``; camodocal's ``lift_projective``), built only from cv2/numpy calls: the
  reference the batched tracker is compared with feature by feature.
* ``synthetic``: a rendered room sequence that revisits its places, with exact depth and poses and
  drifting VIO poses (``render_loop_sequence``, ``SyntheticSequence``; ``make_keyframes`` hands its
  keyframes over as a VIO would): the pose graph's test bed and ``torch-frontend demo --loop``.
* ``flight``: a camera flying over a real photo with the exact homographies
  (``synthetic_flight``, ``fly_over`` / ``Flight``): the tracker's sub-pixel ground truth; and the
  image degradations of notebook 05 (``Degradation``, ``degrade``: blur, gamma, exposure,
  vignetting, noise).
* ``two_view``: two-view scenes with planted outliers and exact F (``planted_scenes``): the F-RANSAC
  test bed.
* ``dispatch_count``: ``OpCounter``, the kernels, views and host syncs of any tensor code as a GPU
  would see them.

Not imported by ``import torch_frontend``; names are imported lazily from their modules.
"""

from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "OracleFusionTracker": "oracle",
    "OracleMonoTracker": "oracle",
    "cfg_from_vins_yaml": "oracle",
    "lift_projective": "oracle",
    "run_oracle_sequence": "oracle",
    "Room": "synthetic",
    "SyntheticSequence": "synthetic",
    "default_textures": "synthetic",
    "make_keyframes": "synthetic",
    "make_room": "synthetic",
    "render_loop_sequence": "synthetic",
    "synthetic_flight": "flight",
    "reprojection_errors": "flight",
    "fly_over": "flight",
    "Flight": "flight",
    "Degradation": "flight",
    "degrade": "flight",
    "planted_scenes": "two_view",
    "line_distances": "two_view",
    "OpCounter": "dispatch_count",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
