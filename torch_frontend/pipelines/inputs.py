"""The inputs of a pipeline: one config and one ``io`` sequence per source.

Convention:
    A *source* is ``(kind, path)`` with kind ``euroc`` (ASL folder), ``images`` (image folder),
    ``kitti`` (KITTI sequence) or ``bag`` (ROS 1/2 bag), as ``io.open_sequence`` takes it, ``(kind, path, options)`` with
    per-source reader options (a dict of ``camera``, ``topic``, ``fps``, overriding the run's
    ``InputOptions``; a rig file's entries, ``pipelines.rig``), or an already open
    ``io.Sequence`` (for instance an :class:`ArraySequence` of frames in memory). Source b is
    stream b of the batched tracker; its name in outputs is ``"<kind>:<name>"``.

    The *config* of a pipeline is one config for every source (a ``TrackerConfig`` or a VINS
    config path), None, or a list of one entry per source (each a ``TrackerConfig``, a path or
    None). A source without a config (None) uses its own ``sensor.yaml``: an ``euroc`` source's
    camera folder's (``io.euroc.euroc_config``: VINS-Mono's EuRoC front-end settings), never
    another source's; a ``kitti`` source's from its ``calib.txt`` (``io.kitti.kitti_config``:
    VINS-Mono's front-end defaults), and a config given for a ``kitti`` source gives its front-end
    keys only (the camera stays calib.txt's). :func:`resolve_configs` gives the B per-stream configs; each file is read
    once, so sources naming one file share one ``TrackerConfig`` (one stream group of the tracker).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import ConfigError
from ..io.frames import Sequence as FrameSequence
from ..io.frames import _Item
from .common import InputOptions, OptionError

__all__ = ["ArraySequence", "SOURCE_OPTIONS", "config_label", "distinct_configs", "frames_to_read", "open_inputs",
           "resolve_config", "resolve_configs", "source_name", "source_options", "stream_config_entry",
           "stream_names", "stream_sizes"]

Source = Union[Tuple[str, Any], Tuple[str, Any, Dict[str, Any]], FrameSequence]

#: per-source reader options a ``(kind, path, options)`` source may carry
SOURCE_OPTIONS = ("camera", "topic", "fps")


class ArraySequence(FrameSequence):
    """Frames in memory as an ``io`` sequence (the loop demo's rendered images).

    Args:
        images: ``(N, H, W)`` uint8 array (or a list of ``(H, W)`` arrays).
        times: ``(N,)`` seconds, increasing.
        name: for messages and outputs.
    """

    kind = "array"

    def __init__(self, images, times, name: str = "array"):
        super().__init__(name, False)
        self.images = [np.ascontiguousarray(np.asarray(im, dtype=np.uint8)) for im in images]
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        if t.shape[0] != len(self.images):
            raise ValueError(f"times: expected {len(self.images)} values (one per image), got {t.shape[0]}")
        self.stamps_ns = np.round(t * 1e9).astype(np.int64)

    def __len__(self) -> int:
        return len(self.images)

    def _items(self):
        for i, im in enumerate(self.images):
            yield _Item(i, int(self.stamps_ns[i]), f"{self.name}#{i}", lambda im=im: im)


def source_options(source: Source) -> Dict[str, Any]:
    """The per-source reader options of ``source`` (``{}`` for ``(kind, path)`` and sequences)."""
    if isinstance(source, tuple) and len(source) > 2 and source[2]:
        return dict(source[2])
    return {}


def source_name(source: Source) -> str:
    """``"<kind>:<path>"`` of a source (an open sequence: ``"<kind>:<name>"``), for messages."""
    if isinstance(source, tuple):
        return f"{source[0]}:{source[1]}"
    return f"{getattr(source, 'kind', 'sequence')}:{getattr(source, 'name', source)}"


def _own_config(source: Source, camera: str, index: int, cache: Dict[Any, Any]):
    """The config of a source given none: its own ``sensor.yaml`` (an ``euroc`` source, or an open
    sequence with a ``sensor_yaml``), read once per file."""
    from ..config import config_from_sensor_yaml

    if isinstance(source, tuple) and source[0] == "kitti":
        from ..io.kitti import kitti_config

        cam = source_options(source).get("camera") or camera
        key = ("kitti", str(Path(source[1]).resolve()), cam)
        if key not in cache:
            cache[key] = kitti_config(source[1], cam)
        return cache[key]
    if isinstance(source, tuple) and source[0] == "euroc":
        from ..io.euroc import euroc_config, find_camera_dir

        cam = source_options(source).get("camera") or camera
        key = ("sensor", str((find_camera_dir(source[1], cam) / "sensor.yaml").resolve()))
        if key not in cache:
            cache[key] = euroc_config(source[1], cam)
        return cache[key]
    yaml = getattr(source, "sensor_yaml", None)
    if not isinstance(source, tuple) and yaml is not None and Path(yaml).is_file():
        key = ("sensor", str(Path(yaml).resolve()))
        if key not in cache:
            cache[key] = config_from_sensor_yaml(yaml)
        return cache[key]
    raise ConfigError(f"no config given for input {index + 1} ({source_name(source)}): a VINS config file is "
                      f"needed unless a euroc source provides sensor.yaml or a kitti source calib.txt (give a "
                      f"config for every input, or one for this input)")


def _load(path: Path):
    """A config file: an ASL ``sensor.yaml`` (by its name: ``config_from_sensor_yaml``, VINS-Mono's
    EuRoC front-end settings, as for a source's own) or a VINS config (``load_config``)."""
    from ..config import config_from_sensor_yaml, load_config

    if path.name == "sensor.yaml" and path.is_file():
        return config_from_sensor_yaml(path)
    return load_config(path)


def _kitti_with(source: Source, base, camera: str, cache: Dict[Any, Any]):
    """A ``kitti`` source's config with ``base``'s front-end keys (``io.kitti.kitti_config``), once
    per (sequence, camera, config)."""
    from ..io.kitti import kitti_config

    cam = source_options(source).get("camera") or camera
    key = ("kitti", str(Path(source[1]).resolve()), cam, id(base))
    if key not in cache:
        cache[key] = (kitti_config(source[1], cam, base=base), base)  # base kept alive: its id stays unique
    return cache[key][0]


def resolve_configs(config: Any, sources: Sequence[Source] = (), camera: str = "cam0") -> List[Any]:
    """The ``TrackerConfig`` of every source, in order (module docstring): ``config`` one config
    for all (a ``TrackerConfig`` or a VINS config path), None (each ``euroc`` source's own
    ``sensor.yaml`` of camera folder ``camera``, or of its own ``camera`` option), or a list of
    one entry per source (``TrackerConfig``, path or None). A path named ``sensor.yaml`` is read
    as an ASL camera file (as a source's own); every file is read once. A ``kitti`` source's
    camera is always its ``calib.txt``'s; a config given for it sets the front-end keys.

    Raises:
        OptionError: a list whose length is not the number of sources.
        ConfigError: an unreadable config, a source without a config that has no ``sensor.yaml``
            (nor ``calib.txt``),
            or a config without a camera (the tracker needs one).
        DataError: an ``euroc`` source without its camera folder or ``sensor.yaml``; a ``kitti``
            source without its calibration or images.
    """
    from ..config import TrackerConfig

    sources = list(sources)
    if isinstance(config, (list, tuple)):
        if len(config) != len(sources):
            raise OptionError("config", f"config: expected one config per input ({len(sources)}), got {len(config)}")
        entries = list(config)
    else:
        entries = [config] * max(len(sources), 1)
    cache: Dict[Any, Any] = {}
    out = []
    for i, c in enumerate(entries):
        if isinstance(c, TrackerConfig):
            cfg = c
        elif c is not None:
            key = ("file", str(Path(c).resolve()))
            if key not in cache:
                cache[key] = _load(Path(c))
            cfg = cache[key]
        elif not sources:
            raise ConfigError("no config given: a VINS config file is needed unless a euroc source "
                              "provides sensor.yaml")
        else:
            cfg = _own_config(sources[i], camera, i, cache)
        if (sources and isinstance(sources[i], tuple) and sources[i][0] == "kitti" and c is not None
                and not cfg.origin.startswith("KITTI")):  # (a KITTI input's config already: as it is)
            cfg = _kitti_with(sources[i], cfg, camera, cache)
        if cfg.camera is None:
            raise ConfigError("has no camera (an estimator-only config?); the tracker needs one", cfg.path)
        out.append(cfg)
    return out


def resolve_config(config: Any, sources: Sequence[Source] = (), camera: str = "cam0"):
    """The one ``TrackerConfig`` of a run whose sources share it (:func:`resolve_configs`; a
    ``ConfigError`` when they do not, e.g. two ``euroc`` sources with different ``sensor.yaml``,
    which need :func:`resolve_configs`)."""
    cfgs = resolve_configs(config, sources, camera)
    if any(c is not cfgs[0] for c in cfgs[1:]):
        raise ConfigError(f"the inputs have different configs ({config_label(cfgs)}); use resolve_configs for "
                          f"one config per input")
    return cfgs[0]


def distinct_configs(cfgs: Sequence[Any]) -> List[Tuple[Any, List[int]]]:
    """``[(config, streams)]``: each distinct config object (first-use order) and its streams."""
    seen: Dict[int, Tuple[Any, List[int]]] = {}
    for b, c in enumerate(cfgs):
        seen.setdefault(id(c), (c, []))[1].append(b)
    return list(seen.values())


def config_label(cfgs: Sequence[Any]) -> str:
    """The summaries' ``config``: the path of the one config of every stream, or the distinct
    paths (first-use order) joined by ``"; "`` (each stream's is in ``per_stream``)."""
    return "; ".join(dict.fromkeys(str(c.path) for c in cfgs))


def stream_config_entry(cfg) -> Dict[str, Any]:
    """The ``config`` and ``camera`` entries of a stream in a summary's ``per_stream``: the config's
    path (a ``sensor.yaml`` when the input's own) and the camera's model, name and size (pixels)."""
    cam = cfg.camera
    return {"config": str(cfg.path),
            "camera": {"model": getattr(cam, "model_type", type(cam).__name__),
                       "name": getattr(cam, "camera_name", "") or "",
                       "width": int(cfg.image_width), "height": int(cfg.image_height)}}


def stream_sizes(cfgs: Sequence[Any]) -> List[Tuple[int, int]]:
    """``(H, W)`` of every stream's images (its config's ``image_height``, ``image_width``)."""
    return [(int(c.image_height), int(c.image_width)) for c in cfgs]


def open_inputs(sources: Sequence[Source], cfg, options: InputOptions) -> List[FrameSequence]:
    """One ``io`` sequence per source, in order: ``(kind, path[, options])`` opened by
    ``io.open_sequence`` with the reader options of ``options`` (overridden by the source's own:
    ``camera``, ``topic``, ``fps``); a bag's topic defaults to its config's ``image_topic``
    (``cfg``: one config, or one per source); an ``io.Sequence`` as it is.

    Raises:
        DataError: a missing, unreadable or empty input, a bag without the topic.
    """
    from ..io import open_sequence

    cfgs = list(cfg) if isinstance(cfg, (list, tuple)) else [cfg] * len(sources)
    out = []
    for s, c in zip(sources, cfgs):
        if isinstance(s, FrameSequence):
            out.append(s)
            continue
        own = source_options(s)
        topic = own.get("topic") or options.topic or c.image_topic or None
        out.append(open_sequence(s[0], s[1], camera=own.get("camera") or options.camera,
                                 fps=own.get("fps", options.fps), topic=topic, skip_bad=options.skip_bad_frames))
    return out


def stream_names(seqs: Sequence[FrameSequence]) -> List[str]:
    """``"<kind>:<name>"`` of each stream (summaries, plots, messages)."""
    return [f"{s.kind}:{s.name}" for s in seqs]


def frames_to_read(seqs: Sequence[FrameSequence], max_frames: Optional[int]) -> int:
    """Stream-frames a run reads at most (the progress bar's total)."""
    return sum(len(s) if max_frames is None else min(len(s), max_frames) for s in seqs)
