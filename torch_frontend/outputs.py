"""Writers of a tracking run: ``features.csv/.npz``, ``summary.json``, plots and track images.

Convention:
    ``RunRecorder.add(batch, frame)`` is called once per tracker step with the ``MultiStream``
    batch and the ``FeatureFrame``; only alive streams count. A *published feature* is a slot with
    ``frame.valid`` (what VINS would publish: mono ``track_cnt > 1`` on published frames).
    A *track* is an id that was published at least once; its length is the largest
    ``track_count`` it was published with (VINS's ``track_cnt``: the frames it was tracked in,
    published or not). Features detected and lost between two published frames never reached
    VINS and are not tracks (the summary's ``tracks``, mean and median lengths, the histogram).

    The output set is written as a whole: a run fills a hidden temporary folder beside ``out``
    (``.<out>.tf<pid>-<random>.tmp``, created when the recorder is, ``tracks/`` growing in it during
    the run) and :meth:`RunRecorder.write` swaps it in for ``out`` in one step
    (``_atomic.StagedFolder``), so ``out`` holds either the complete previous set or the complete
    new one: a run without ``tracks/`` leaves none, an interrupted or failed run (SIGINT, SIGTERM
    from the CLI, an error) removes its temporary folder and leaves ``out`` as it was. The set
    includes ``written-by-torch-frontend.json``, the list of what the run wrote. Temporaries of
    earlier runs that were killed outright (SIGKILL) are removed by the next run writing ``out``.

    Foreign files: a run never deletes what the library did not write. It refuses, before
    tracking, an ``out`` that holds anything else (``OutputFolderError``, a ``DataError`` naming
    the folder and the files; the CLI prints it and exits 1): ``out`` must be absent, empty, a
    folder of an earlier run (its marker lists everything in it), or a folder written before the
    marker existed that holds only the names below and those versions' temporaries
    (``LEGACY_OUTPUTS``). The temporary folder needs ``out``'s parent to be writable.

Outputs in ``out``:
    * ``features.csv``: ``stream, timestamp, id, x, y, u, v, vx, vy, track_count``, one row per
      published feature; ``timestamp`` in seconds with 9 decimals (exact from the ns stamp),
      ``x, y`` normalised undistorted, ``u, v`` pixels, ``vx, vy`` normalised units / s.
    * ``features.npz``: the same columns as arrays (``timestamp`` float64 s, ``stamp_ns`` int64).
    * ``summary.json``: ``frames`` (stream-frames read), ``published`` (published stream-frames),
      ``published_features``, ``mean_features`` (per published frame), ``tracks``,
      ``mean_track_length``/``median_track_length`` (frames), ``seconds`` and ``frames_per_second``
      (whole loop: reading, tracking, recording; ``tracker_seconds``: the tracker calls alone),
      ``skipped_bad_frames`` and ``skipped`` (stream, source, reason), ``per_stream``, and the run's
      ``config``, ``mode``, ``device``, ``inputs`` (the pipelines add each stream's ``config`` and
      ``camera`` to its ``per_stream`` entry: ``pipelines.inputs.stream_config_entry``).
    * ``features_per_frame.png``, ``track_length_hist.png``, ``track_paths.png``: matplotlib (Agg)
      plots; ``track_paths.png`` draws each published track's path in the image (``u, v`` of its
      published frames; the first 4 streams), coloured by length (a colour bar per panel: published
      frames, blue short, red long): dots for a still camera, lines that follow the motion for a
      moving one.
    * ``tracks/stream<b>/<stamp_ns>.png``: ``viz.draw_tracks`` per published frame per stream
      (``stamp_ns`` zero-padded to 19 digits, so the names sort in time order).
    * with ``bag``: the feature bag(s) (``features.bag`` / a ROS 2 folder; ``io.feature_bag``).
    * ``written-by-torch-frontend.json``: the marker (``_atomic.MARKER``).
"""

from __future__ import annotations

import io
import json
import os
import re
from pathlib import Path
from typing import Any, Dict, List, Sequence

import numpy as np

from ._atomic import (
    OutputFolderError,
    StagedFolder,
    atomic_path,
    legacy_temporaries,
    make_folders,
    remove_empty_folders,
    replace_dir,
    write_bytes_atomic,
    write_text_atomic,
)

CSV_COLUMNS = ("stream", "timestamp", "id", "x", "y", "u", "v", "vx", "vy", "track_count")
#: the files of a run (besides ``tracks/`` and the marker)
OUTPUT_FILES = ("features.csv", "features.npz", "summary.json", "features_per_frame.png", "track_length_hist.png",
                "track_paths.png")
#: what an ``out`` folder written before the marker existed may hold to be replaced (``_atomic``)
LEGACY_OUTPUTS = (
    "(" + "|".join(re.escape(n) for n in OUTPUT_FILES) + ")",
    r"tracks(/stream\d+(/\d+\.png)?)?",
    *legacy_temporaries(*OUTPUT_FILES, "tracks"),
)


# ----------------------------------------------------------------------------------------------
# the recorder


def _remove(p: Path) -> None:
    """Remove the file or folder ``p`` if it exists."""
    import shutil

    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif os.path.lexists(p):
        p.unlink()


def run_counts(streams: int, frames: int, published: int, published_features: int, lengths, seconds: float,
               skipped: List[Dict[str, Any]], track_images: int) -> Dict[str, Any]:
    """The counts that open ``summary.json`` (one process, or the merge of a sharded run's inputs):
    totals, means over published frames and tracks (``lengths``: track lengths, a numpy array), rates,
    and the skipped frames (``skipped``: ``{"stream", "source", "reason"}`` dicts)."""
    return {
        "streams": int(streams),
        "frames": frames,
        "published": published,
        "published_features": published_features,
        "mean_features": float(published_features / published) if published else 0.0,
        "tracks": int(lengths.size),
        "mean_track_length": float(lengths.mean()) if lengths.size else 0.0,
        "median_track_length": float(np.median(lengths)) if lengths.size else 0.0,
        "seconds": round(float(seconds), 6),
        "frames_per_second": float(frames / seconds) if seconds > 0 else 0.0,
        "skipped_bad_frames": len(skipped),
        "skipped": skipped,
        "track_images": track_images,
    }


def bag_names(name: str, streams: int, fmt: str | None = None) -> List[str]:
    """The feature bags of a run of ``streams`` streams in ``out``: ``name`` itself for one stream,
    else ``<stem>_stream<b><suffix>`` (``features.bag`` -> ``features_stream0.bag``, a ROS 2 folder
    ``features_db3`` -> ``features_db3_stream0``). ``name`` must be a plain name (no folder); a
    ROS 1 bag (``fmt="ros1"``) gets the ``.bag`` its readers need."""
    p = Path(str(name).rstrip("/"))
    if fmt == "ros1" and p.suffix != ".bag":
        p = Path(p.name + ".bag")
    if p.name != str(p) or p.name in ("", ".", ".."):
        raise ValueError(f"bag: expected a name inside the output folder (no '/'), got {name!r}")
    if p.name in OUTPUT_FILES or p.name == "tracks":
        raise ValueError(f"bag: {name!r} is the name of another output")
    if streams == 1:
        return [p.name]
    return [f"{p.stem}_stream{b}{p.suffix}" for b in range(streams)]


def feature_message(frame, b: int, stamp_ns: int):
    """Stream b of a ``FeatureFrame`` as an ``io.feature_bag.FeatureMessage``: the published
    features (``frame.valid``) in slot order (VINS-Mono's array order); with right observations
    (VINS-Fusion stereo) ordered by id, camera 0 before camera 1."""
    from .io.feature_bag import FeatureMessage

    sel = np.flatnonzero(frame.valid[b].cpu().numpy())
    ids = frame.ids[b].cpu().numpy()[sel].astype(np.int64)

    def rows(t):
        return t[b].detach().cpu().double().numpy()[sel]

    xy, uv, vel = rows(frame.xy), rows(frame.uv), rows(frame.velocity)
    cam = np.zeros(len(sel), dtype=np.int64)
    if frame.right_valid is not None:
        rv = frame.right_valid[b].cpu().numpy()[sel].astype(bool)
        ids = np.concatenate([ids, ids[rv]])
        cam = np.concatenate([cam, np.ones(int(rv.sum()), dtype=np.int64)])
        xy = np.concatenate([xy, rows(frame.right_xy)[rv]])
        uv = np.concatenate([uv, rows(frame.right_uv)[rv]])
        vel = np.concatenate([vel, rows(frame.right_velocity)[rv]])
        order = np.lexsort((cam, ids))
        ids, cam, xy, uv, vel = ids[order], cam[order], xy[order], uv[order], vel[order]
    return FeatureMessage(stamp_ns=int(stamp_ns), ids=ids, camera=cam, xy=xy, uv=uv, velocity=vel)


class RunRecorder:
    """Collect per-step results of B streams and write the outputs of a run.

    Args:
        out: output folder (created; see the module docstring for what it may already hold).
        stream_names: one name per stream (for the summary and plots).
        write_tracks: draw and save track images (``tracks/``).
        bag: write the feature tracker's topics into this bag inside ``out`` (one per stream,
            :func:`bag_names`; ``io.feature_bag``, ``docs/ros.md``), part of the output set.
        bag_format: ``"ros1"`` or ``"ros2"`` (default: ``.bag`` names ROS 1, others ROS 2).
        bag_images: add ``/feature_tracker/feature_img`` to the bags.
        adopt: the staging folder of an interrupted run to continue in (``pipelines.checkpoint``;
            then :meth:`restore` the recorder's state from its checkpoint).
        journal: keep what was recorded since the last :meth:`take_chunk` (a checkpointed run).

    Raises:
        OutputFolderError: ``out`` holds files the library did not write (nothing is touched).
        OSError: ``out`` cannot be created (a file there, no permission).

    Use as a context manager: leaving it with an exception removes the temporary folder.
    """

    def __init__(self, out, stream_names: Sequence[str], write_tracks: bool = True, bag: str | None = None,
                 bag_format: str | None = None, bag_images: bool = False, adopt: Path | None = None,
                 journal: bool = False):
        self.out = Path(out)
        self.names = list(stream_names)
        self.B = len(self.names)
        self.write_tracks = bool(write_tracks)
        self._rows: List[Dict[str, np.ndarray]] = []
        self._lengths: List[np.ndarray] = []  # (M, 3) int64: stream, id, track_count
        self.frames = np.zeros(self.B, dtype=np.int64)
        self.published = np.zeros(self.B, dtype=np.int64)
        self.per_frame: List[List[tuple]] = [[] for _ in range(self.B)]  # (step, t, present, published or -1)
        self.track_images = 0
        self._size: tuple | None = None  # (H, W) of the frames, pixels (track_paths.png's axes)
        self._tmp_tracks: Path | None = None
        self._pending: List[str] | None = None  # the names written by write(commit=False)
        self.journal = bool(journal)
        #: leave the staging folder on SIGINT/SIGTERM (set once a checkpoint is in it)
        self.keep_on_interrupt = False
        self._marks = (0, 0, [0] * self.B)  # _rows, _lengths, per_frame entries already in chunks
        # created first, so that a file at ``out`` or a read-only place fails before the run; a
        # file at ``out`` is StagedFolder's "is a file, not a folder" (mkdir's would be "File exists")
        # (the folders made here are removed again, while empty, when the run fails: abort)
        self._created = make_folders(self.out)
        try:
            self._stage: StagedFolder | None = StagedFolder(self.out, "track", LEGACY_OUTPUTS, adopt=adopt)
        except BaseException:
            remove_empty_folders(self._created)
            raise
        if self.write_tracks:
            self._tmp_tracks = self._stage.path / "tracks"
            self._tmp_tracks.mkdir(exist_ok=adopt is not None)
        self.bag_names = bag_names(bag, self.B, bag_format) if bag else []
        self._bags: List[Any] = []
        self.bag_images = bool(bag_images)
        if self.bag_names:
            from .io.feature_bag import FeatureBagWriter

            try:
                for name in self.bag_names:
                    if adopt is not None:  # the interrupted run's bag: rewritten from its journal (restore)
                        _remove(self._stage.path / name)
                    self._bags.append(FeatureBagWriter(self._stage.path / name, bag_format, images=bag_images))
                    if self.journal:
                        self._bags[-1].journal = []
            except BaseException:
                self.abort()
                raise

    # -- context manager: clean temporaries on failure
    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            if self._pending is not None:  # written with commit=False and never committed
                self.commit()
        else:
            self._stop(exc)
        return False

    def _stop(self, exc: BaseException) -> None:
        """The run stopped with ``exc``: remove the staging folder, or keep it when ``exc`` stops a
        checkpointed run that goes on later (:meth:`_resumable`)."""
        if not self._resumable(exc):
            self.abort()
            return
        # SIGINT / SIGTERM (a preemption), or a sharded job stopped by another rank, after a
        # checkpoint: the staging folder stays, for --resume or the job's restart (the next run
        # without it removes it as a stale temporary)
        self._stage = None
        self._bags = []
        self._tmp_tracks = None
        if isinstance(exc, KeyboardInterrupt):
            exc.resumable = True  # the CLI's message: rerun with --resume

    def _resumable(self, exc: BaseException) -> bool:
        """Whether ``exc`` stops a checkpointed run that goes on later (its staging folder stays):
        an interrupt, or an exception whose class says ``keeps_checkpoints = True``:
        ``distributed.JobAborted`` (another rank of the job failed; a restart or ``--resume``
        continues from this rank's checkpoint, ``pipelines.elastic``; a class attribute, as this
        layer does not import ``distributed``)."""
        if not self.keep_on_interrupt:
            return False
        return isinstance(exc, KeyboardInterrupt) or bool(getattr(type(exc), "keeps_checkpoints", False))

    def abort(self) -> None:
        """Remove the temporary folder (``out`` is not touched, unless this recorder created it:
        then it is removed while empty, with the parents it created)."""
        for w in self._bags:
            w.abort()
        self._bags = []
        if self._stage is not None:
            self._stage.abort()
            remove_empty_folders(self._created)
        self._stage = None
        self._tmp_tracks = None
        self._pending = None

    @property
    def stage_path(self) -> Path | None:
        """The staging folder being filled (None once written or aborted)."""
        return None if self._stage is None else self._stage.path

    # -- checkpoints (pipelines.checkpoint): the counters, and what was recorded since the last chunk
    def counters(self) -> Dict[str, Any]:
        """The recorder's counters as plain values (a checkpoint's; the rows are in the chunks)."""
        return {"frames": self.frames.tolist(), "published": self.published.tolist(),
                "track_images": int(self.track_images), "size": self._size,
                "bags": [w.header_state() for w in self._bags]}

    def take_chunk(self) -> Dict[str, Any]:
        """What was recorded since the last call (rows, track lengths, per-frame counts, bag
        messages), concatenated: the next append-only chunk of a checkpoint."""
        r0, l0, p0 = self._marks
        rows = self._rows[r0:]
        chunk = {
            "rows": {k: np.concatenate([r[k] for r in rows]) for k in rows[0]} if rows else None,
            "lengths": np.concatenate(self._lengths[l0:]) if len(self._lengths) > l0 else None,
            "per_frame": [pf[p0[b]:] for b, pf in enumerate(self.per_frame)],
            "bags": [list(w.journal or ()) for w in self._bags],
        }
        for w in self._bags:
            if w.journal is not None:
                w.journal.clear()
        # one entry per chunk from now on (equal columns: np.concatenate of the pieces is the same)
        if rows:
            self._rows[r0:] = [chunk["rows"]]
        if chunk["lengths"] is not None:
            self._lengths[l0:] = [chunk["lengths"]]
        self._marks = (len(self._rows), len(self._lengths), [len(pf) for pf in self.per_frame])
        return chunk

    def restore(self, counters: Dict[str, Any], chunks: Sequence[Dict[str, Any]]) -> None:
        """Continue from a checkpoint: its :meth:`counters` and every chunk (:meth:`take_chunk`) it
        covers, in order. The track images of the checkpointed frames are in the adopted staging
        folder already; the bags are written again from the chunks' messages."""
        self._rows = [c["rows"] for c in chunks if c["rows"] is not None]
        self._lengths = [c["lengths"] for c in chunks if c["lengths"] is not None]
        self.per_frame = [[e for c in chunks for e in c["per_frame"][b]] for b in range(self.B)]
        self.frames = np.asarray(counters["frames"], dtype=np.int64)
        self.published = np.asarray(counters["published"], dtype=np.int64)
        self.track_images = int(counters["track_images"])
        self._size = None if counters["size"] is None else tuple(counters["size"])
        for b, w in enumerate(self._bags):
            w.replay([m for c in chunks for m in c["bags"][b]], counters["bags"][b])
        self._marks = (len(self._rows), len(self._lengths), [len(pf) for pf in self.per_frame])

    # -- per step
    def add(self, batch, frame) -> None:
        """Record one step: ``batch`` (``io.Batch``) and ``frame`` (``FeatureFrame``)."""
        alive = batch.alive.cpu().numpy().astype(bool)
        self._size = tuple(int(x) for x in batch.images.shape[-2:])
        valid = frame.valid.cpu().numpy() & alive[:, None]
        present = frame.present.cpu().numpy() & alive[:, None]
        published = frame.published.cpu().numpy().astype(bool) & alive
        ids = frame.ids.cpu().numpy()
        cnt = frame.track_count.cpu().numpy()
        stamps = np.asarray(batch.stamps_ns, dtype=np.int64)
        self.frames += alive
        self.published += published
        for b in np.flatnonzero(alive):
            n_pub = int(valid[b].sum()) if published[b] else -1
            self.per_frame[b].append((batch.step, int(stamps[b]), int(present[b].sum()), n_pub))
        vb, vk = np.nonzero(valid)
        # track lengths: every published feature, its count then (max taken at the end); a feature
        # that was detected and lost between two published frames never reached VINS: not a track
        if vb.size:
            self._lengths.append(np.stack([vb, ids[vb, vk], cnt[vb, vk]], axis=1).astype(np.int64))
        if vb.size:
            xy = frame.xy.detach().cpu().double().numpy()
            uv = frame.uv.detach().cpu().double().numpy()
            vel = frame.velocity.detach().cpu().double().numpy()
            self._rows.append({
                "stream": vb.astype(np.int32),
                "stamp_ns": stamps[vb],
                "id": ids[vb, vk].astype(np.int64),
                "x": xy[vb, vk, 0], "y": xy[vb, vk, 1],
                "u": uv[vb, vk, 0], "v": uv[vb, vk, 1],
                "vx": vel[vb, vk, 0], "vy": vel[vb, vk, 1],
                "track_count": cnt[vb, vk].astype(np.int64),
            })
        if self._bags:
            self._add_to_bags(batch, frame, alive, published, stamps)
        if self.write_tracks and self._tmp_tracks is not None:
            import cv2

            from .viz import draw_tracks

            for b in np.flatnonzero(published):
                img = draw_tracks(batch.raw[b], frame, int(b))
                d = self._tmp_tracks / f"stream{b}"
                d.mkdir(exist_ok=True)
                # zero-padded nanoseconds (19 digits, as EuRoC names them): names sort in time order
                if not cv2.imwrite(str(d / f"{int(stamps[b]):019d}.png"), img):
                    raise OSError(f"cannot write track image into {d}")
                self.track_images += 1

    def _add_to_bags(self, batch, frame, alive, published, stamps) -> None:
        """The feature tracker's topics of this step, stream b into bag b (``io.feature_bag``)."""
        restarted = frame.restarted.cpu().numpy().astype(bool)
        sent = frame.sent.cpu().numpy().astype(bool)
        for b in np.flatnonzero(alive):
            w = self._bags[b]
            if restarted[b]:
                w.write_restart(int(stamps[b]))
            if sent[b]:
                w.write_features(feature_message(frame, int(b), int(stamps[b])))
            if self.bag_images and published[b]:
                from .viz import draw_tracks

                w.write_image(int(stamps[b]), draw_tracks(batch.raw[b], frame, int(b)))

    def copy_imu(self, b: int, kind: str, path, topic: str) -> int:
        """Copy the IMU of stream b's input into its bag: a bag's ``topic`` as recorded, or a EuRoC
        folder's ``mav0/imu0/data.csv`` as ``sensor_msgs/Imu`` on ``topic``; returns the message
        count (0: no bag, or no IMU in the input)."""
        if not self._bags:
            return 0
        w = self._bags[b]
        if kind == "bag":
            return w.copy_topic(path, topic)
        if kind == "euroc":
            csv = Path(path) / "mav0" / "imu0" / "data.csv"
            return w.write_euroc_imu(csv, topic) if csv.is_file() else 0
        return 0

    # -- results
    def columns(self) -> Dict[str, np.ndarray]:
        """All published features as column arrays (``CSV_COLUMNS`` + ``stamp_ns``)."""
        keys = ("stream", "stamp_ns", "id", "x", "y", "u", "v", "vx", "vy", "track_count")
        if not self._rows:
            dt = dict(stream=np.int32, stamp_ns=np.int64, id=np.int64, track_count=np.int64)
            cols = {k: np.zeros(0, dtype=dt.get(k, np.float64)) for k in keys}
        else:
            cols = {k: np.concatenate([r[k] for r in self._rows]) for k in keys}
        from .io.multistream import ns_to_seconds

        cols["timestamp"] = ns_to_seconds(cols["stamp_ns"])
        return cols

    def track_lengths(self) -> np.ndarray:
        """Length (largest published ``track_count``) of every published track (stream, id), as an
        int64 array (features that were never published are not counted)."""
        if not self._lengths:
            return np.zeros(0, dtype=np.int64)
        a = np.concatenate(self._lengths)
        order = np.lexsort((-a[:, 2], a[:, 1], a[:, 0]))  # per (stream, id): largest count first
        a = a[order]
        first = np.ones(len(a), dtype=bool)
        first[1:] = (a[1:, 0] != a[:-1, 0]) | (a[1:, 1] != a[:-1, 1])
        return a[first, 2]

    def summary(self, seconds: float, skipped: Sequence[tuple] = (), extra: Dict[str, Any] | None = None
                ) -> Dict[str, Any]:
        """The ``summary.json`` content. ``seconds``: wall time of the tracking loop."""
        cols_n = sum(len(r["id"]) for r in self._rows)
        lengths = self.track_lengths()
        frames = int(self.frames.sum())
        published = int(self.published.sum())
        per_stream = []
        for b in range(self.B):
            pf = self.per_frame[b]
            pub = [p[3] for p in pf if p[3] >= 0]
            per_stream.append({
                "name": self.names[b],
                "frames": int(self.frames[b]),
                "published": int(self.published[b]),
                "mean_features": float(np.mean(pub)) if pub else 0.0,
            })
        s = run_counts(self.B, frames, published, int(cols_n), lengths, seconds,
                       [{"stream": int(b), "source": str(src), "reason": str(why)} for b, src, why in skipped],
                       self.track_images)
        s["per_stream"] = per_stream
        if extra:
            s.update(extra)
        return s

    def write(self, summary: Dict[str, Any], plots: bool = True, commit: bool = True) -> List[Path]:
        """Write every output and swap the set in for ``out`` (module docstring); returns the
        paths under ``out``. Any failure leaves ``out`` as it was and removes the temporaries
        (those of a checkpointed run stay on an interrupt: :meth:`__exit__`).

        ``commit=False`` writes the whole set into the staging folder and stops there:
        :meth:`commit` swaps it in later. A sharded run commits a finished input only after the
        checkpoint that records it finished: before it, a resumed run redoes the input from the
        previous checkpoint and needs the track images of the frames before it, which are in the
        staging folder only."""
        if self._stage is None or self._pending is not None:
            raise RuntimeError(f"{self.out}: the outputs of this RunRecorder were written or aborted already")
        try:
            for w in self._bags:
                w.close()
            names = self._write_set(self._stage.path, summary, plots) + list(self.bag_names)
            self._bags = []
            self._pending = names
            if commit:
                self.commit()
        except BaseException as exc:
            self._stop(exc)
            raise
        return [self.out / n for n in names]

    def commit(self) -> List[Path]:
        """Swap the set written by ``write(..., commit=False)`` in for ``out``; returns the paths
        under ``out``."""
        if self._stage is None or self._pending is None:
            raise RuntimeError(f"{self.out}: nothing written to commit (write(commit=False) first)")
        try:
            self._stage.commit()
        except BaseException:
            self.abort()
            raise
        names, self._pending = self._pending, None
        self._stage = None
        self._tmp_tracks = None
        return [self.out / n for n in names]

    def _write_set(self, d: Path, summary: Dict[str, Any], plots: bool) -> List[str]:
        """Write the outputs into the temporary folder ``d``; returns their names."""
        names = []
        cols = self.columns()
        # features.csv
        buf = io.StringIO()
        buf.write(",".join(CSV_COLUMNS) + "\n")
        for i in range(len(cols["id"])):
            ns = int(cols["stamp_ns"][i])
            buf.write(
                f"{cols['stream'][i]},{ns // 1_000_000_000}.{ns % 1_000_000_000:09d},{cols['id'][i]},"
                f"{cols['x'][i]:.9g},{cols['y'][i]:.9g},{cols['u'][i]:.6f},{cols['v'][i]:.6f},"
                f"{cols['vx'][i]:.9g},{cols['vy'][i]:.9g},{cols['track_count'][i]}\n"
            )
        (d / "features.csv").write_bytes(buf.getvalue().encode("utf-8"))
        names.append("features.csv")
        # features.npz (np.savez appends '.npz' to names without it: write to a file object)
        with open(d / "features.npz", "wb") as fh:
            np.savez_compressed(fh, **cols, stream_names=np.array(self.names))
        names.append("features.npz")
        (d / "summary.json").write_bytes((json.dumps(summary, indent=2) + "\n").encode("utf-8"))
        names.append("summary.json")
        if plots:
            names += self._plots(d)
        if self.write_tracks:
            names.append("tracks")
        return names

    def _plots(self, d: Path) -> List[str]:
        # Figure + the Agg canvas directly, no pyplot: no global backend switch, no GUI, no state
        # leaking into a notebook's inline backend.
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        out = []
        fig = Figure(figsize=(8, 4), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        for b in range(self.B):
            pf = self.per_frame[b]
            if not pf:
                continue
            steps = [p[0] for p in pf]
            ax.plot(steps, [p[2] for p in pf], "-", lw=1, alpha=0.6, label=f"{self.names[b]}: in table")
            pub = [(p[0], p[3]) for p in pf if p[3] >= 0]
            if pub:
                ax.plot([q[0] for q in pub], [q[1] for q in pub], "o", ms=4, label=f"{self.names[b]}: published")
        ax.set_xlabel("frame")
        ax.set_ylabel("features")
        ax.set_title("Features per frame")
        ax.grid(True, alpha=0.3)
        if self.B <= 8:
            ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        out.append(self._save_fig(fig, d, "features_per_frame.png"))

        lengths = self.track_lengths()
        fig = Figure(figsize=(6, 4), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        if lengths.size:
            hi = int(lengths.max())
            ax.hist(lengths, bins=np.arange(0.5, hi + 1.5, 1.0 if hi <= 60 else max(1.0, hi / 60)),
                    color="tab:blue", edgecolor="white")
            ax.axvline(float(np.median(lengths)), color="tab:red", ls="--",
                       label=f"median {np.median(lengths):g}")
            ax.legend(fontsize=8)
        ax.set_xlabel("track length (frames)")
        ax.set_ylabel("tracks")
        ax.set_title(f"Track lengths ({lengths.size} tracks)")
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        out.append(self._save_fig(fig, d, "track_length_hist.png"))
        out.append(self._track_paths(d))
        return out

    #: streams drawn in ``track_paths.png``
    PATH_PANELS = 4

    def _track_paths(self, d: Path) -> str:
        """``track_paths.png``: the published tracks' paths in the image, per stream."""
        from matplotlib import colormaps
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.cm import ScalarMappable
        from matplotlib.collections import LineCollection
        from matplotlib.colors import Normalize
        from matplotlib.figure import Figure
        from mpl_toolkits.axes_grid1 import make_axes_locatable

        cmap = colormaps["coolwarm"]  # blue: short tracks, red: long ones (as the track images)
        cols = self.columns()
        n = max(1, min(self.B, self.PATH_PANELS))
        fig = Figure(figsize=(5.5 * n, 4.2), dpi=100)
        FigureCanvasAgg(fig)
        for b in range(n):
            ax = fig.add_subplot(1, n, b + 1)
            m = cols["stream"] == b
            ids, stamp = cols["id"][m], cols["stamp_ns"][m]
            uv = np.stack([cols["u"][m], cols["v"][m]], axis=1)
            order = np.lexsort((stamp, ids))  # per track, in time order
            ids, uv = ids[order], uv[order]
            cuts = np.flatnonzero(ids[1:] != ids[:-1]) + 1
            paths = np.split(uv, cuts) if ids.size else []
            lengths = np.array([len(p) for p in paths], dtype=np.float64)
            hi = max(2.0, float(lengths.max())) if paths else 2.0
            if paths:
                ax.add_collection(LineCollection(paths, colors=cmap(lengths / hi), linewidths=1.0))
                ends = np.stack([p[-1] for p in paths])
                ax.scatter(ends[:, 0], ends[:, 1], s=4, c=cmap(lengths / hi))
            # the colour scale: a track's length in published frames (0 .. the longest, at least 2)
            cax = make_axes_locatable(ax).append_axes("right", size="4%", pad=0.08)  # as tall as the image
            bar = fig.colorbar(ScalarMappable(norm=Normalize(0.0, hi), cmap=cmap), cax=cax)
            bar.set_label("track length (published frames)", fontsize=8)
            h, w = self._size if self._size is not None else (1, 1)
            ax.set_xlim(0, w)
            ax.set_ylim(h, 0)  # image rows down
            ax.set_aspect("equal")
            moved = float(np.median([np.linalg.norm(p[-1] - p[0]) for p in paths])) if paths else 0.0
            ax.set_title(f"{self.names[b]}: {len(paths)} tracks, median path {moved:.1f} px", fontsize=9)
            ax.set_xlabel("u (px)")
            ax.set_ylabel("v (px)")
        fig.tight_layout()
        return self._save_fig(fig, d, "track_paths.png")

    def _save_fig(self, fig, d: Path, name: str) -> str:
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        (d / name).write_bytes(buf.getvalue())
        return name


__all__ = ["RunRecorder", "bag_names", "feature_message", "CSV_COLUMNS", "OUTPUT_FILES", "LEGACY_OUTPUTS", "OutputFolderError", "atomic_path",
           "write_text_atomic", "write_bytes_atomic", "replace_dir"]
