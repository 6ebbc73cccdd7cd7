"""Loop closure: VINS-Mono's ``pose_graph`` (and VINS-Fusion's ``loop_fusion``), batched.

Part 1, place recognition: ``fast``/``brief``/``hamming`` describe keyframes, ``Vocabulary`` turns
descriptors into bags of words (DBoW2), ``PlaceDatabase`` answers "have I been here before?" with
VINS's ``detectLoop`` rule.

Part 2, verification and the pose graph: ``KeyFrame`` and ``match_brief`` (VINS's
``searchByBRIEFDes``), ``pnp_ransac`` (batched P3P RANSAC + differentiable refinement, or
``cv2.solvePnPRansac``), ``PoseGraph`` (sequences, merge, drift, save/load in VINS's format) over
the pure optimisers ``optimize_4dof`` / ``optimize_6dof``; ``triangulate_points`` for keyframes
built from tracks and poses. The rendered revisiting test sequence (``render_loop_sequence``) is in
``torch_frontend.testing``.

Part 3, the outputs of a run: ``write_loop_outputs`` (``report``). The run itself (front end ->
keyframes -> place recognition -> pose graph -> outputs, as ``torch-frontend loop``) is
``torch_frontend.pipelines.loop.run_loop``, the demo ``pipelines.loop.demo_loop``.

Names are imported lazily, so ``import torch_frontend.loop`` stays cheap.
"""

from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "PlaceDatabase": "database",
    "brief": "features",
    "default_brief_pattern": "features",
    "fast": "features",
    "gaussian_blur_u8": "features",
    "hamming": "features",
    "load_brief_pattern": "features",
    "make_brief_pattern": "features",
    "BowVector": "vocabulary",
    "Vocabulary": "vocabulary",
    "bow_to_dense": "vocabulary",
    "KeyFrame": "keyframe",
    "describe_keyframes": "keyframe",
    "match_brief": "keyframe",
    "PnPResult": "pnp",
    "p3p": "pnp",
    "pnp_ransac": "pnp",
    "refine_pnp": "pnp",
    "LoopResult": "pose_graph",
    "PoseGraph": "pose_graph",
    "verify_loops": "pose_graph",
    "optimize_4dof": "optimize",
    "optimize_6dof": "optimize",
    "sequential_edges": "optimize",
    "measurements_4dof": "optimize",
    "measurements_6dof": "optimize",
    "camera_poses": "triangulate",
    "triangulate_points": "triangulate",
    "R_to_quat": ".geometry",
    "R_to_ypr": ".geometry",
    "normalize_angle": ".geometry",
    "quat_to_R": ".geometry",
    "rodrigues": ".geometry",
    "rodrigues_inverse": ".geometry",
    "wrap_angle_once": ".geometry",
    "yaw_to_R": ".geometry",
    "ypr_to_R": ".geometry",
    "write_loop_outputs": "report",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
