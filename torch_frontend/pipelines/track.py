"""The tracking pipeline (``torch-frontend track`` / ``demo``): B sources tracked as B streams of
one batched ``FeatureTracker``, the outputs written by ``outputs.RunRecorder``.

Convention:
    Sources are ``(kind, path[, options])`` or ``io`` sequences, each with its own config
    (``pipelines.inputs``: one config for all, or one per source; a source without one uses its
    own ``sensor.yaml``); streams of several sizes are tracked as one padded batch with their
    sizes (``io.multistream``). The outputs
    (``features.csv``, ``features.npz``, ``summary.json``, two plots, ``tracks/``) are described
    in ``torch_frontend.outputs``. Times in the summary are seconds of wall time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

from .common import InputOptions, OptionError, progress_bar, resolve_device
from .inputs import (
    Source,
    config_label,
    frames_to_read,
    open_inputs,
    resolve_configs,
    source_options,
    stream_config_entry,
    stream_names,
    stream_sizes,
)
from .prefetch import FrameStream

__all__ = ["DEMO_FLIGHT", "TrackOptions", "copy_imu", "demo_flight_inputs", "make_tracker", "run_track",
           "track_streams", "tracked_batches"]

TRACKER_MODES = ("mono", "fusion")

#: ``demo --flight``: ``testing.flight.synthetic_flight`` (a camera flying over the package photo,
#: ~2.5 px/frame across, slow rotation and zoom; the view stays on the photo for 32 frames of
#: 640x400) at 20 Hz, as EuRoC's cameras
DEMO_FLIGHT = dict(frames=32, size=(400, 640), rate=20.0)


@dataclass
class TrackOptions(InputOptions):
    """Options of :func:`run_track` (and the reader options of :class:`InputOptions`).

    Attributes:
        mode: the tracker's rules: ``"mono"`` (VINS-Mono feature_tracker) or ``"fusion"``
            (VINS-Fusion).
        write_tracks: draw the tracks of every published frame into ``tracks/``.
        bag: also write the feature tracker's ROS topics into this bag, a name inside ``out``
            (``features.bag``: ROS 1, ``features_db3``: ROS 2; one per stream, ``outputs.bag_names``;
            ``docs/ros.md``). None: no bag.
        bag_format: ``"ros1"`` / ``"ros2"``, overriding the name's form.
        bag_images: add ``/feature_tracker/feature_img``.
        bag_imu: copy each input's IMU into its bag (a bag's ``imu_topic``, a EuRoC ``imu0/data.csv``).
        checkpoint_every: write a checkpoint (``pipelines.checkpoint``, inside the run's staging
            folder) every this many frames (steps); None: every 500 frames or 60 s, whichever
            first; 0: none.
        resume: continue the interrupted run of the same ``out`` from its last checkpoint
            (``ResumeError`` when it was another run: inputs, config or options); no checkpoint
            to continue from: start from the first frame (with a ``DataWarning`` saying so).
        lk_backend: the tracker's pyramid and LK kernels (``FeatureTracker``'s ``lk_backend``:
            None / ``"auto"``, ``"fused"``, ``"tensor"``). The resolved one is part of a checkpoint's
            fingerprint and of the summary (a resume or a rank with other kernels would change bits).
    """

    mode: str = "mono"
    write_tracks: bool = True
    bag: str | None = None
    bag_format: str | None = None
    bag_images: bool = False
    bag_imu: bool = True
    checkpoint_every: Optional[int] = None
    resume: bool = False
    lk_backend: Optional[str] = None

    def check(self) -> None:
        """Raise ``OptionError`` naming the first bad option."""
        super().check()
        if self.checkpoint_every is not None and (not isinstance(self.checkpoint_every, int)
                                                  or self.checkpoint_every < 0):
            raise OptionError("checkpoint_every", f"checkpoint_every: expected an integer >= 0 (frames; 0: no "
                                                  f"checkpoints), got {self.checkpoint_every!r}")
        if self.mode not in TRACKER_MODES:
            raise OptionError("mode", f"mode: expected mono or fusion, got {self.mode!r}")
        from ..fused import BACKENDS

        if self.lk_backend is not None and self.lk_backend not in BACKENDS:
            raise OptionError("lk_backend", f"lk_backend: expected one of {', '.join(BACKENDS)}, got {self.lk_backend!r}")
        if self.bag_format not in (None, "ros1", "ros2"):
            raise OptionError("bag_format", f"bag_format: expected ros1 or ros2, got {self.bag_format!r}")
        if self.bag is not None:
            from ..outputs import bag_names

            try:
                bag_names(self.bag, 1)
            except ValueError as exc:
                raise OptionError("bag", str(exc)) from None

    def recorder_options(self) -> Dict[str, Any]:
        """The bag arguments of ``outputs.RunRecorder``."""
        return {"bag": self.bag, "bag_format": self.bag_format, "bag_images": self.bag_images}

    def output_options(self, device) -> Dict[str, Any]:
        """The options that change a run's outputs (a checkpoint's fingerprint; not ``workers``,
        ``progress`` nor the checkpoint interval), with the device's type."""
        from ..fused import resolve_backend

        keep = ("mode", "max_frames", "camera", "fps", "topic", "skip_bad_frames", "write_tracks", "bag",
                "bag_format", "bag_images", "bag_imu")
        return {**{k: getattr(self, k) for k in keep}, "device": device.type,
                "lk_backend": resolve_backend(self.lk_backend, device)}


def copy_imu(rec, cfg, sources, seqs, opt: TrackOptions, streams=None) -> None:
    """Copy the IMU of each input into the recorder's bags (``TrackOptions.bag_imu``), on its
    config's ``imu_topic`` (``cfg``: one config, or one per input); ``streams``: the inputs of the
    recorder's streams (default: all, in order)."""
    if opt.bag is None or not opt.bag_imu:
        return
    cfgs = list(cfg) if isinstance(cfg, (list, tuple)) else [cfg] * len(sources)
    for b, i in enumerate(range(len(sources)) if streams is None else streams):
        src = sources[i]
        topic = cfgs[i].imu_topic or "/imu0"
        kind, path = src[:2] if isinstance(src, tuple) else (getattr(seqs[i], "kind", ""), getattr(seqs[i], "path", None))
        if path is not None:
            rec.copy_imu(b, kind, path, topic)


def demo_flight_inputs(frames: int = DEMO_FLIGHT["frames"], size: Tuple[int, int] = DEMO_FLIGHT["size"],
                       rate: float = DEMO_FLIGHT["rate"]):
    """The config and source of ``demo --flight``: ``frames`` frames of ``size`` ``(H, W)`` of the
    synthetic flight at ``rate`` Hz (``DEMO_FLIGHT``), seen by an undistorted pinhole camera
    (focal 460 px, VINS-Mono's EuRoC front-end settings ``config.EUROC_FRONTEND``).

    Returns:
        ``(TrackerConfig, [ArraySequence])``, what :func:`run_track` takes.
    """
    import numpy as np

    from ..camera import PinholeCamera
    from ..config import EUROC_FRONTEND, TrackerConfig
    from ..testing.flight import synthetic_flight
    from .inputs import ArraySequence

    H, W = (int(x) for x in size)
    imgs, _ = synthetic_flight(n_frames=int(frames), size=(H, W))
    cam = PinholeCamera(0.0, 0.0, 0.0, 0.0, 460.0, 460.0, (W - 1) / 2, (H - 1) / 2, width=W, height=H,
                        camera_name="flight")
    cfg = TrackerConfig(path="demo (synthetic flight over the package photo)", image_width=W, image_height=H,
                        camera=cam, **EUROC_FRONTEND)
    return cfg, [ArraySequence(imgs, np.arange(len(imgs)) / float(rate), name="flight")]


def tracked_batches(tracker, stream, device, bar=None, start: int = 0) -> Iterator[Tuple[Any, Any, float]]:
    """Run ``tracker`` over ``stream`` (an ``io.MultiStream``): yields ``(batch, frame, seconds)``
    per step, ``seconds`` being the tracker call alone (synchronised on CUDA); ``bar`` (tqdm or
    None) advances by the alive streams after the caller has used the step. ``start``: the steps
    before it are read but not tracked (a resumed run: the tracker continues from a checkpoint)."""
    import torch

    cuda = device.type == "cuda"
    for batch in stream:
        if batch.step < start:
            if bar is not None:
                bar.update(int(batch.alive.sum()))
            continue
        t1 = time.perf_counter()
        # non_blocking: from FrameStream's pinned staging buffers the copy is asynchronous (the
        # tracker's kernels are queued behind it on the same stream)
        # a batch of mixed sizes is padded, with its sizes (io.multistream); one size: sizes None
        sizes = getattr(batch, "sizes", None)
        frame = tracker.track(batch.images.to(device, non_blocking=cuda), batch.timestamps,
                              active=batch.alive.to(device), **({} if sizes is None else {"sizes": sizes}))
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        yield batch, frame, time.perf_counter() - t1
        if bar is not None:
            bar.update(int(batch.alive.sum()))


def run_track(config, sources: Sequence[Source], out, options: TrackOptions | None = None) -> Dict[str, Any]:
    """Track ``sources`` as B streams and write the outputs into the folder ``out``.

    Args:
        config: a ``TrackerConfig`` or a VINS config path for every source, None (each ``euroc``
            source's own ``sensor.yaml``), or a list of one of these per source
            (``inputs.resolve_configs``): stream b is tracked with its own config.
        sources: ``[(kind, path)]`` (kind ``euroc``, ``bag``, ``images``; ``(kind, path, options)``
            with per-source reader options) or ``io`` sequences.
        out: output folder (created).
        options: :class:`TrackOptions` (default: all defaults).

    Returns:
        the summary dict, also written as ``summary.json``.

    Raises:
        OptionError: bad options or no source; ConfigError, DataError: bad config or inputs.
        ``KeyboardInterrupt`` passes through after the temporaries are removed.
    """
    from ..outputs import RunRecorder
    from . import checkpoint as ckpt

    opt = TrackOptions() if options is None else options
    sources = list(sources)
    if not sources:
        raise OptionError("sources", "sources: no input given (expected at least one (kind, path) or io Sequence)")
    opt.check()
    dev = resolve_device(opt.device)
    cfgs = resolve_configs(config, sources, opt.camera)
    seqs = open_inputs(sources, cfgs, opt)
    stream = FrameStream(seqs, size=stream_sizes(cfgs), max_steps=opt.max_frames,
                         workers=opt.workers, pin_memory=dev.type == "cuda")
    tracker = make_tracker(cfgs, dev, opt.mode, opt.lk_backend)
    fp = ckpt.fingerprint(cfgs, [ckpt.input_fingerprint(src, s) for src, s in zip(sources, seqs)],
                          opt.output_options(dev))
    resumed = ckpt.resume_point(out, fp) if opt.resume else None
    if opt.resume and resumed is None:
        import warnings

        from ..errors import DataWarning

        warnings.warn(f"--resume: no checkpoint of an interrupted run of {out} found: starting from the first frame",
                      DataWarning, stacklevel=2)
    steps = 0
    # the times of the interrupted run(s) before the checkpoint, added to this run's
    before = {"seconds": 0.0, "tracker_seconds": 0.0, "decode_seconds": 0.0, "input_wait_seconds": 0.0}
    with RunRecorder(out, stream_names(seqs), write_tracks=opt.write_tracks, **opt.recorder_options(),
                     adopt=None if resumed is None else resumed.stage,
                     journal=opt.checkpoint_every != 0) as rec:
        if resumed is not None:
            p = resumed.payload
            tracker.load_state_dict(p["tracker"])
            rec.restore(p["recorder"], resumed.chunks)
            steps = resumed.frames
            before = dict(p["times"])
            rec.keep_on_interrupt = True
        checkpoints = ckpt.Checkpointer(rec.stage_path, fp, opt.checkpoint_every, resumed)
        tracker_seconds = before["tracker_seconds"]
        t0 = time.perf_counter()
        with progress_bar(opt.progress, frames_to_read(seqs, opt.max_frames), "tracking", "frame") as bar:
            for batch, frame, step_seconds in tracked_batches(tracker, stream, dev, bar, start=steps):
                tracker_seconds += step_seconds
                rec.add(batch, frame)
                steps += 1
                ckpt.frame_hook(steps)
                if checkpoints.due(steps):
                    times = {"seconds": before["seconds"] + time.perf_counter() - t0,
                             "tracker_seconds": tracker_seconds,
                             "decode_seconds": before["decode_seconds"] + stream.decode_seconds,
                             "input_wait_seconds": before["input_wait_seconds"] + stream.wait_seconds}
                    checkpoints.save(steps, {"tracker": tracker.state_dict(), "recorder": rec.counters(),
                                             "times": times}, rec.take_chunk())
                    rec.keep_on_interrupt = True
        if dev.type == "cuda":
            import torch

            torch.cuda.synchronize(dev)
        seconds = before["seconds"] + time.perf_counter() - t0
        times = _input_times(stream, opt.workers)
        times["decode_seconds"] = round(before["decode_seconds"] + stream.decode_seconds, 6)
        times["input_wait_seconds"] = round(before["input_wait_seconds"] + stream.wait_seconds, 6)
        extra = {
            "steps": steps,
            "tracker_seconds": round(tracker_seconds, 6),
            **times,
            "config": config_label(cfgs),
            "mode": opt.mode,
            "device": str(dev),
            "lk_backend": tracker.lk_backend,
            "inputs": [_input_entry(src, s) for src, s in zip(sources, seqs)],
            "out": str(Path(out)),
        }
        summary = rec.summary(seconds, stream.skipped, extra=extra)
        for e, c in zip(summary["per_stream"], cfgs):  # each stream's config and camera
            e.update(stream_config_entry(c))
        copy_imu(rec, cfgs, sources, seqs, opt)
        rec.write(summary)
    return summary


def make_tracker(cfgs, device, mode: str, lk_backend: Optional[str] = None):
    """The batched ``FeatureTracker`` of B streams with these per-stream configs: one config
    object for every stream is the homogeneous tracker (as one config broadcast to B), others are
    per-stream configs (``FeatureTracker([cfg_0, ..., cfg_B-1])``; equal ones share a group)."""
    from ..tracker import FeatureTracker

    if all(c is cfgs[0] for c in cfgs):
        return FeatureTracker(cfgs[0], num_streams=len(cfgs), device=device, mode=mode, lk_backend=lk_backend)
    return FeatureTracker(list(cfgs), device=device, mode=mode, lk_backend=lk_backend)


def _input_times(stream, workers: int) -> Dict[str, Any]:
    """The summary's decode entries: ``workers``, ``decode_seconds`` (the readers' decoding, summed
    over the workers) and ``input_wait_seconds`` (the tracking loop waiting for frames)."""
    return {"workers": int(workers), "decode_seconds": round(stream.decode_seconds, 6),
            "input_wait_seconds": round(stream.wait_seconds, 6)}


def _stream_view(batch, frame, b: int):
    """Stream ``b`` of a ``MultiStream`` batch and of a ``FeatureFrame`` as a batch of one."""
    import dataclasses

    import torch

    images = batch.images[b:b + 1]
    sizes = getattr(batch, "sizes", None)
    if sizes is not None:  # a padded batch of mixed sizes: stream b's own (H, W), as its run alone sees it
        images = images[..., : int(sizes[b][0]), : int(sizes[b][1])]
    sub = type(batch)(step=batch.step, images=images, timestamps=batch.timestamps[b:b + 1],
                      stamps_ns=batch.stamps_ns[b:b + 1], alive=batch.alive[b:b + 1], sources=[batch.sources[b]],
                      raw=[batch.raw[b]])
    fields = {f.name: getattr(frame, f.name) for f in dataclasses.fields(frame)}
    one = type(frame)(**{k: v[b:b + 1] if isinstance(v, torch.Tensor) else v for k, v in fields.items()})
    return sub, one


def _on_cpu(frame):
    """A ``FeatureFrame`` with its tensors on the CPU."""
    import dataclasses

    import torch

    return type(frame)(**{f.name: (v.cpu() if isinstance(v, torch.Tensor) else v)
                          for f in dataclasses.fields(frame) for v in (getattr(frame, f.name),)})


def track_streams(config, sources: Sequence[Source], outs: Sequence[Any], options: TrackOptions | None = None,
                  *, extra: Dict[str, Any] | None = None, beat=None, stage=None) -> Dict[str, Any]:
    """Track ``sources`` as B streams of one batched tracker, as :func:`run_track`, but write each
    stream's outputs into its own folder ``outs[b]``: the output set one ``run_track`` of that
    source alone writes (the tracker treats every stream on its own, so its files are identical),
    committed as soon as the stream ends. Its ``summary.json`` has the one-stream run's entries
    (times are the batch's while the stream ran) and ``extra``.

    ``beat`` (a callable or None) is called once per step (``distributed.Job.beat``: heartbeats,
    and a way to stop the run by raising). Returns ``{"streams": [per stream: {"summary",
    "lengths" (track lengths, int64 numpy)}], "steps", "seconds", "tracker_seconds",
    "decode_seconds", "input_wait_seconds", "device"}``.

    ``stage`` (None, or a callable that takes the run's ``checkpoint.fingerprint`` and returns a
    ``pipelines.elastic.RankStage``: a sharded run's rank): the streams are staged in it, with
    checkpoints every ``options.checkpoint_every`` steps (default 500 or 60 s) and one as each
    stream ends (it is finished: a resumed run does not redo it); a resumed stage continues from
    its checkpoint (the finished streams' results from it, the others from its step).

    Raises:
        as :func:`run_track`; the streams already written stay, the others leave no output.
    """
    import contextlib

    from ..outputs import RunRecorder

    opt = TrackOptions() if options is None else options
    sources, outs = list(sources), list(outs)
    if len(outs) != len(sources):
        raise OptionError("outs", f"outs: expected one folder per source ({len(sources)}), got {len(outs)}")
    if not sources:
        raise OptionError("sources", "sources: no input given (expected at least one (kind, path) or io Sequence)")
    opt.check()
    dev = resolve_device(opt.device)
    cfgs = resolve_configs(config, sources, opt.camera)
    seqs = open_inputs(sources, cfgs, opt)
    names = stream_names(seqs)
    stream = FrameStream(seqs, size=stream_sizes(cfgs), max_steps=opt.max_frames,
                         workers=opt.workers, pin_memory=dev.type == "cuda")
    tracker = make_tracker(cfgs, dev, opt.mode, opt.lk_backend)
    B = len(seqs)
    results: List[Dict[str, Any] | None] = [None] * B
    steps = 0
    started = [False] * B
    # the times of the interrupted run(s) before the checkpoint, added to this run's
    before = {"seconds": 0.0, "tracker_seconds": 0.0, "decode_seconds": 0.0, "input_wait_seconds": 0.0}
    if stage is not None:
        from . import checkpoint as ckpt

        stage = stage(ckpt.fingerprint(cfgs, [ckpt.input_fingerprint(src, sq) for src, sq in zip(sources, seqs)],
                                       opt.output_options(dev)))
    resumed = None if stage is None else stage.resumed
    if resumed is not None:
        p = resumed.payload
        tracker.load_state_dict(p["tracker"])
        results = [p["finished"].get(b) for b in range(B)]
        started = list(p["started"])
        steps = resumed.frames
        before = dict(p["times"])
    tracker_seconds = before["tracker_seconds"]
    ended: List[int] = []  # streams finished since the last checkpoint
    checkpointed = stage is not None and stage.writer.enabled
    if resumed is not None:
        _commit_finished(stage, outs, results)
    t0 = time.perf_counter()

    def times_now() -> Dict[str, float]:
        return {"seconds": before["seconds"] + time.perf_counter() - t0, "tracker_seconds": tracker_seconds,
                "decode_seconds": before["decode_seconds"] + stream.decode_seconds,
                "input_wait_seconds": before["input_wait_seconds"] + stream.wait_seconds}

    def checkpoint(recs) -> None:
        live = {b: r for b, r in enumerate(recs) if r is not None and results[b] is None}
        stage.save(steps, {"tracker": tracker.state_dict(), "recorders": {b: r.counters() for b, r in live.items()},
                           "finished": {b: r for b, r in enumerate(results) if r is not None},
                           "started": list(started), "times": times_now()},
                   {b: r.take_chunk() for b, r in live.items()})
        for r in live.values():
            r.keep_on_interrupt = True
        # the streams this checkpoint records finished: their written sets swapped in now, not
        # before (RunRecorder.write(commit=False))
        if ended and ckpt.kill_point("ended", steps):  # the test hook: recorded finished, not swapped in
            ckpt.kill_now()
        for b in ended:
            recs[b].commit()
        ended.clear()

    def finish(b: int, rec) -> None:
        now = times_now()
        seconds = now["seconds"]
        skipped = [(0, src, why) for sb, src, why in stream.skipped if sb == b]
        times = _input_times(stream, opt.workers)
        times["decode_seconds"] = round(now["decode_seconds"], 6)
        times["input_wait_seconds"] = round(now["input_wait_seconds"], 6)
        info = {
            "steps": int(rec.frames[0]),
            "tracker_seconds": round(tracker_seconds, 6),
            **times,
            "config": config_label([cfgs[b]]),
            "mode": opt.mode,
            "device": str(dev),
            "lk_backend": tracker.lk_backend,
            "inputs": [_input_entry(sources[b], seqs[b])],
            "out": str(Path(outs[b])),
            **(extra or {}),
        }
        summary = rec.summary(seconds, skipped, extra=info)
        summary["per_stream"][0].update(stream_config_entry(cfgs[b]))
        copy_imu(rec, cfgs, sources, seqs, opt, streams=[b])
        # with checkpoints, swapped in by the next one, which records it finished
        rec.write(summary, commit=not checkpointed)
        results[b] = {"summary": summary, "lengths": rec.track_lengths()}
        ended.append(b)

    def recorder(b: int):
        if results[b] is not None:  # finished before the checkpoint this run continues from
            return None
        kw = {}
        if stage is not None:
            kw = {"adopt": stage.staging_of(Path(outs[b]).name), "journal": stage.writer.enabled}
        return RunRecorder(outs[b], [names[b]], write_tracks=opt.write_tracks, **opt.recorder_options(), **kw)

    with contextlib.ExitStack() as stack:
        recs = [recorder(b) for b in range(B)]
        for r in recs:
            if r is not None:
                stack.enter_context(r)
        if resumed is not None:
            chunks = resumed.chunks
            for b, r in enumerate(recs):
                if r is not None:
                    r.restore(resumed.payload["recorders"][b], [c[b] for c in chunks if b in c])
                    r.keep_on_interrupt = True
        with progress_bar(opt.progress, frames_to_read(seqs, opt.max_frames), "tracking", "frame") as bar:
            for batch, frame, step_seconds in tracked_batches(tracker, stream, dev, bar, start=steps):
                tracker_seconds += step_seconds
                if dev.type != "cpu":  # one copy per field, not one per stream
                    frame = _on_cpu(frame)
                alive = batch.alive.tolist()
                for b in range(B):
                    if alive[b]:
                        recs[b].add(*_stream_view(batch, frame, b))
                        started[b] = True
                    elif started[b] and results[b] is None:  # ended: its outputs are complete
                        finish(b, recs[b])
                steps += 1
                if beat is not None:
                    beat()
                if stage is not None:
                    from . import checkpoint as ckpt

                    ckpt.frame_hook(steps)
                    # one as a stream ends (after the whole step: every recorder has it), so
                    # that a resumed run does not redo it
                    if stage.writer.due(steps) or (ended and stage.writer.enabled):
                        checkpoint(recs)
        for b in range(B):
            if results[b] is None:
                finish(b, recs[b])
        if checkpointed and ended:
            checkpoint(recs)
    now = times_now()
    return {"streams": results, "steps": steps, "seconds": round(now["seconds"], 6),
            "tracker_seconds": round(tracker_seconds, 6), **_input_times(stream, opt.workers),
            "decode_seconds": round(now["decode_seconds"], 6), "input_wait_seconds": round(now["input_wait_seconds"], 6),
            "device": str(dev)}


def _commit_finished(stage, outs: Sequence[Any], results: Sequence[Any]) -> None:
    """A resumed rank's inputs that its checkpoint records finished but whose output set was not
    swapped in yet (the rank stopped between that checkpoint and the commit): the set is complete
    in the rank's staging folder (written before the checkpoint): swap it in now."""
    from .._atomic import StagedFolder
    from ..outputs import LEGACY_OUTPUTS

    for b, r in enumerate(results):
        staged = stage.path / Path(outs[b]).name
        if r is not None and staged.is_dir():
            StagedFolder(outs[b], "track", LEGACY_OUTPUTS, adopt=staged).commit()


def _input_entry(source: Source, seq) -> Dict[str, Any]:
    """The summary's ``inputs`` entry of one source."""
    kind, path = source[:2] if isinstance(source, tuple) else (seq.kind, seq.name)
    own = source_options(source)  # a rig entry's camera / topic / fps
    return {"kind": kind, "path": str(path), "frames_listed": len(seq), **own}
