"""The inputs of a pipeline: its config, and one ``io`` sequence per source.

Convention:
    A *source* is ``(kind, path)`` with kind ``euroc`` (ASL folder), ``images`` (image folder) or
    ``bag`` (ROS 1/2 bag), as ``io.open_sequence`` takes it, or an already open ``io.Sequence``
    (for instance an :class:`ArraySequence` of frames in memory). Source b is stream b of the
    batched tracker; its name in outputs is ``"<kind>:<name>"``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import ConfigError
from ..io.frames import Sequence as FrameSequence
from ..io.frames import _Item
from .common import InputOptions

__all__ = ["ArraySequence", "frames_to_read", "open_inputs", "resolve_config", "stream_names"]

Source = Union[Tuple[str, Any], FrameSequence]


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


def resolve_config(config: Any, sources: Sequence[Source] = (), camera: str = "cam0"):
    """The ``TrackerConfig`` of a run: ``config`` itself (a ``TrackerConfig``), the VINS config
    file it names, or, when None, the ``sensor.yaml`` of the first ``euroc`` source (VINS's EuRoC
    front-end settings for camera folder ``camera``).

    Raises:
        ConfigError: an unreadable config, no config and no ``euroc`` source, or a config without
            a camera (the tracker needs one).
    """
    from ..config import TrackerConfig, load_config

    if isinstance(config, TrackerConfig):
        cfg = config
    elif config is not None:
        cfg = load_config(Path(config))
    else:
        euroc = [s[1] for s in sources if isinstance(s, tuple) and s[0] == "euroc"]
        if not euroc:
            raise ConfigError("no config given: a VINS config file is needed unless a euroc source "
                              "provides sensor.yaml")
        from ..io.euroc import euroc_config

        cfg = euroc_config(euroc[0], camera)
    if cfg.camera is None:
        raise ConfigError("has no camera (an estimator-only config?); the tracker needs one", cfg.path)
    return cfg


def open_inputs(sources: Sequence[Source], cfg, options: InputOptions) -> List[FrameSequence]:
    """One ``io`` sequence per source, in order: ``(kind, path)`` opened by ``io.open_sequence``
    with the reader options of ``options`` (a bag's topic defaults to ``cfg.image_topic``), an
    ``io.Sequence`` as it is.

    Raises:
        DataError: a missing, unreadable or empty input, a bag without the topic.
    """
    from ..io import open_sequence

    topic = options.topic or cfg.image_topic or None
    return [s if isinstance(s, FrameSequence) else
            open_sequence(s[0], s[1], camera=options.camera, fps=options.fps, topic=topic,
                          skip_bad=options.skip_bad_frames)
            for s in sources]


def stream_names(seqs: Sequence[FrameSequence]) -> List[str]:
    """``"<kind>:<name>"`` of each stream (summaries, plots, messages)."""
    return [f"{s.kind}:{s.name}" for s in seqs]


def frames_to_read(seqs: Sequence[FrameSequence], max_frames: Optional[int]) -> int:
    """Stream-frames a run reads at most (the progress bar's total)."""
    return sum(len(s) if max_frames is None else min(len(s), max_frames) for s in seqs)
