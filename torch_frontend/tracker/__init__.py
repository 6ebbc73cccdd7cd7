"""The VINS front end as one pure step over a feature table, and ``FeatureTracker`` around it.

Modules, in the order a frame goes through them:

* ``params``: :class:`TrackerParams`, every setting of the step (VINS keys and constants by name);
* ``table``: :class:`FeatureTable`, VINS's parallel feature arrays as one padded ``(B, K, ...)`` table;
* ``state``: :class:`TrackerState` (a registered pytree), what a step carries to the next;
* ``clock``: VINS-Mono's ``img_callback`` rules (skip, restart, publish);
* ``stages``: the stages named after VINS's (readImage's LK part, rejectWithF, setMask, addPoints,
  updateID, undistortedPoints, the stereo step, the estimator's hooks);
* ``track_step``: :func:`step`, the stages composed for mono and fusion;
* ``frame``: :class:`FeatureFrame`, what a step publishes;
* ``streams``: per-stream configs: streams of equal configs grouped, inputs split and frames merged;
* ``feature_tracker``: :class:`FeatureTracker`, the thin stateful wrapper.
"""

from .feature_tracker import FeatureTracker
from .frame import FeatureFrame
from .params import TrackerParams
from .state import ClockState, TrackerState
from .streams import GroupedState
from .table import FeatureTable
from .track_step import step

__all__ = ["FeatureTracker", "FeatureFrame", "FeatureTable", "TrackerParams", "TrackerState", "ClockState", "GroupedState", "step"]
