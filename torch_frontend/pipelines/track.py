"""The tracking pipeline (``torch-frontend track`` / ``demo``): B sources tracked as B streams of
one batched ``FeatureTracker``, the outputs written by ``outputs.RunRecorder``.

Convention:
    Sources are ``(kind, path)`` or ``io`` sequences (``pipelines.inputs``); the outputs
    (``features.csv``, ``features.npz``, ``summary.json``, two plots, ``tracks/``) are described
    in ``torch_frontend.outputs``. Times in the summary are seconds of wall time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterator, Sequence, Tuple

from .common import InputOptions, OptionError, progress_bar, resolve_device
from .inputs import Source, frames_to_read, open_inputs, resolve_config, stream_names

__all__ = ["TrackOptions", "run_track", "tracked_batches"]

TRACKER_MODES = ("mono", "fusion")


@dataclass
class TrackOptions(InputOptions):
    """Options of :func:`run_track` (and the reader options of :class:`InputOptions`).

    Attributes:
        mode: the tracker's rules: ``"mono"`` (VINS-Mono feature_tracker) or ``"fusion"``
            (VINS-Fusion).
        write_tracks: draw the tracks of every published frame into ``tracks/``.
    """

    mode: str = "mono"
    write_tracks: bool = True

    def check(self) -> None:
        """Raise ``OptionError`` naming the first bad option."""
        super().check()
        if self.mode not in TRACKER_MODES:
            raise OptionError("mode", f"mode: expected mono or fusion, got {self.mode!r}")


def tracked_batches(tracker, stream, device, bar=None) -> Iterator[Tuple[Any, Any, float]]:
    """Run ``tracker`` over ``stream`` (an ``io.MultiStream``): yields ``(batch, frame, seconds)``
    per step, ``seconds`` being the tracker call alone (synchronised on CUDA); ``bar`` (tqdm or
    None) advances by the alive streams after the caller has used the step."""
    import torch

    for batch in stream:
        t1 = time.perf_counter()
        frame = tracker.track(batch.images.to(device), batch.timestamps, active=batch.alive.to(device))
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        yield batch, frame, time.perf_counter() - t1
        if bar is not None:
            bar.update(int(batch.alive.sum()))


def run_track(config, sources: Sequence[Source], out, options: TrackOptions | None = None) -> Dict[str, Any]:
    """Track ``sources`` as B streams and write the outputs into the folder ``out``.

    Args:
        config: a ``TrackerConfig``, a VINS config path, or None (``sensor.yaml`` of the first
            ``euroc`` source; see ``inputs.resolve_config``).
        sources: ``[(kind, path)]`` (kind ``euroc``, ``bag``, ``images``) or ``io`` sequences.
        out: output folder (created).
        options: :class:`TrackOptions` (default: all defaults).

    Returns:
        the summary dict, also written as ``summary.json``.

    Raises:
        OptionError: bad options or no source; ConfigError, DataError: bad config or inputs.
        ``KeyboardInterrupt`` passes through after the temporaries are removed.
    """
    from ..io import MultiStream
    from ..outputs import RunRecorder
    from ..tracker import FeatureTracker

    opt = TrackOptions() if options is None else options
    sources = list(sources)
    if not sources:
        raise OptionError("sources", "sources: no input given (expected at least one (kind, path) or io Sequence)")
    opt.check()
    dev = resolve_device(opt.device)
    cfg = resolve_config(config, sources, opt.camera)
    seqs = open_inputs(sources, cfg, opt)
    stream = MultiStream(seqs, size=(cfg.image_height, cfg.image_width), max_steps=opt.max_frames)
    tracker = FeatureTracker(cfg, num_streams=len(seqs), device=dev, mode=opt.mode)
    steps = 0
    tracker_seconds = 0.0
    with RunRecorder(out, stream_names(seqs), write_tracks=opt.write_tracks) as rec:
        t0 = time.perf_counter()
        with progress_bar(opt.progress, frames_to_read(seqs, opt.max_frames), "tracking", "frame") as bar:
            for batch, frame, step_seconds in tracked_batches(tracker, stream, dev, bar):
                tracker_seconds += step_seconds
                rec.add(batch, frame)
                steps += 1
        if dev.type == "cuda":
            import torch

            torch.cuda.synchronize(dev)
        seconds = time.perf_counter() - t0
        extra = {
            "steps": steps,
            "tracker_seconds": round(tracker_seconds, 6),
            "config": str(cfg.path),
            "mode": opt.mode,
            "device": str(dev),
            "inputs": [_input_entry(src, s) for src, s in zip(sources, seqs)],
            "out": str(Path(out)),
        }
        summary = rec.summary(seconds, stream.skipped, extra=extra)
        rec.write(summary)
    return summary


def _input_entry(source: Source, seq) -> Dict[str, Any]:
    """The summary's ``inputs`` entry of one source."""
    kind, path = source if isinstance(source, tuple) else (seq.kind, seq.name)
    return {"kind": kind, "path": str(path), "frames_listed": len(seq)}
