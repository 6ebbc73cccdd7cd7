"""OpenCV oracle of the VINS-Mono / VINS-Fusion KLT front end (numpy + cv2 only, no torch).

``torch_frontend.testing.oracle``. A plain, sequential
re-implementation of the behaviour described in the behaviour spec (``docs/spec.md``; "spec §N"
below): the Mono ``feature_tracker`` node (``img_callback`` timing
logic + ``readImage``, spec §3), the VINS-Fusion tracker (spec §6) and the camodocal
``liftProjective`` of the PINHOLE / MEI / KANNALA_BRANDT models (spec §4). It is built only from
the spec and OpenCV calls; it is the *reference* the batched torch tracker is tested and
benchmarked against, so it favours readability and fidelity over speed (Python loops over points
are fine here).

Convention
----------
* Pixels ``(u, v)`` = (column x, row y), pixel centres at integer coordinates; images are
  ``(H, W)`` uint8. ``ROW x COL`` = ``image_height x image_width``.
* Point arrays are ``(N, 2)``; pixel positions and normalised coordinates are float32 like the
  C++ ``cv::Point2f`` vectors they mirror (lifts are computed in float64 from the float32 pixels,
  then stored as float32 exactly as the C++ does). Velocities are float32 (normalised units / s).
* ``cvRound`` is round-half-to-even (``np.rint``); the FREQ test uses C ``round`` (half away from
  zero), see :func:`c_round`.

Deliberate choices (see also the module-level notes in each class)
-----------------------------------------------------------------
* ``setMask`` ordering: VINS uses ``std::sort`` (unstable) on ``track_cnt`` descending. The oracle
  uses the STABLE rule ``sort by (-track_cnt, array index)``, the same rule the torch port uses, so
  the two can be compared feature by feature. It can differ from a real VINS run only in which of
  two equally old, closer-than-``min_dist`` features survives.
* ``findFundamentalMat`` is called through cv2, so OpenCV's own behaviour (LMedS for 8..14 points,
  RANSAC with its fixed RNG seed otherwise) is inherited, not re-implemented. If it returns no
  F/mask, all tracks are kept.

Modules: ``primitives`` (the constants of spec §2, VINS's roundings and the cv2 steps both trackers
share: LK, setMask, GFTT, velocities), ``camodocal`` (``liftProjective`` / ``spaceToPlane``),
``mono`` (``MonoTiming``, ``OracleMonoTracker``), ``fusion`` (``OracleFusionTracker``) and
``vins_config`` (config and camera YAML files through ``cv2.FileStorage``); every public name is
importable from the package. ``python -m torch_frontend.testing.oracle [VINS-Mono config]`` runs
the Mono oracle over the package's EuRoC sample frames and prints a table per frame.
"""

from __future__ import annotations

from .camodocal import lift_projective, space_to_plane
from .fusion import OracleFusionTracker
from .mono import MonoTiming, OracleMonoTracker
from .primitives import (  # noqa: F401 (the constants of spec §2: importable here, not in __all__)
    BORDER_SIZE,
    CLAHE_CLIP,
    CLAHE_GRID,
    F_CONFIDENCE,
    FLOW_BACK_MAX_PX,
    FOCAL_LENGTH,
    GFTT_QUALITY,
    LK_CRITERIA,
    LK_MAX_LEVEL,
    LK_WIN,
    PREDICTION_MIN_GOOD,
    RESTART_GAP_S,
    c_round,
    cv_round,
    in_border,
)
from .vins_config import camera_from_yaml, cfg_from_vins_yaml

__all__ = [
    "lift_projective",
    "space_to_plane",
    "c_round",
    "cv_round",
    "in_border",
    "MonoTiming",
    "OracleMonoTracker",
    "OracleFusionTracker",
    "run_oracle_sequence",
    "cfg_from_vins_yaml",
    "camera_from_yaml",
]


def run_oracle_sequence(frames: list, cfg: dict, mode: str = "mono") -> list:
    """Run a fresh oracle over ``frames``.

    mono: ``frames = [(t, img), ...]``; fusion: ``[(t, img0), ...]`` or ``[(t, img0, img1), ...]``.
    Returns one result dict per frame (see the tracker classes).
    """
    if mode == "mono":
        tr = OracleMonoTracker(cfg)
        return [tr.process(f[1], f[0]) for f in frames]
    if mode == "fusion":
        tr = OracleFusionTracker(cfg)
        return [tr.process(f[0], f[1], f[2] if len(f) > 2 else None) for f in frames]
    raise ValueError(f"run_oracle_sequence: mode must be 'mono' or 'fusion', got {mode!r}")
