"""Pipelines: what ``torch-frontend`` runs, as library functions with an options dataclass each.

* ``track``: :func:`run_track` (:class:`TrackOptions`): B sources as B streams of one batched
  ``FeatureTracker``, the outputs written by ``torch_frontend.outputs``.
* ``loop``: :func:`run_loop` (:class:`LoopOptions`): tracking -> keyframes -> triangulation ->
  FAST/BRIEF -> vocabulary -> VINS's pose graph -> outputs (``loop.report``); :func:`demo_loop` on
  a rendered revisiting sequence (``demo_sequence``). Its middle stages are ``loop_stages``.
* ``vocabulary``: :func:`run_vocabulary_train` (:class:`VocabularyOptions`) and
  :func:`load_vocabulary` (the package's ``.npz``, VINS's ``.bin``, DBoW2 YAML).
* ``config``: :func:`run_make_config` (``make_config``): a VINS config from Kalibr / camera_info
  calibration files (``torch_frontend.calibration``).
* shared: ``inputs`` (``resolve_configs``: one config per source, each ``euroc`` source's own
  ``sensor.yaml`` by default; ``open_inputs`` for ``(kind, path[, options])`` sources,
  ``ArraySequence``), ``rig`` (``read_rig``: a rig file's inputs and their configs), ``common`` (``InputOptions``, ``OptionError``, ``progress_bar``,
  ``pad_ragged``, ``resolve_device``), ``prefetch`` (:class:`FrameStream`: ``MultiStream``'s
  batches with the frames decoded in DataLoader workers, ``InputOptions.workers``).
* ``ros_node``: :func:`run_ros_node` (:class:`RosOptions`, :class:`RosCamera`): the live ROS 1
  node (``torch-frontend ros``), VINS-Mono's ``feature_tracker_node`` for one or more cameras.
* sharded over the ranks of a ``torch.distributed`` job (``torchrun``): ``sharded``
  (:func:`run_track_sharded`, :func:`run_loop_sharded`, :func:`run_vocabulary_train_sharded`;
  ``track.track_streams`` writes one output set per stream).

Bad options raise ``OptionError`` (a ``ValueError``) whose message starts with the option's name;
the CLI maps its flags to these names. Names are imported lazily.
"""

from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "InputOptions": "common",
    "OptionError": "common",
    "pad_ragged": "common",
    "progress_bar": "common",
    "resolve_device": "common",
    "ArraySequence": "inputs",
    "open_inputs": "inputs",
    "resolve_config": "inputs",
    "resolve_configs": "inputs",
    "read_rig": "rig",
    "TrackOptions": "track",
    "run_track": "track",
    "track_streams": "track",
    "FrameStream": "prefetch",
    "run_track_sharded": "sharded",
    "run_loop_sharded": "sharded",
    "run_vocabulary_train_sharded": "sharded",
    "LoopOptions": "loop",
    "LoopRecord": "loop",
    "LoopRun": "loop",
    "StreamRun": "loop",
    "demo_loop": "loop",
    "demo_options": "loop",
    "demo_sequence": "loop",
    "extrinsic_from_config": "loop",
    "run_loop": "loop",
    "run_make_config": "make_config",
    "RosCamera": "ros_node",
    "RosOptions": "ros_node",
    "run_ros_node": "ros_node",
    "VocabularyOptions": "vocabulary",
    "load_vocabulary": "vocabulary",
    "run_vocabulary_train": "vocabulary",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
