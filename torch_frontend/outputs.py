"""Writers of a tracking run: ``features.csv/.npz``, ``summary.json``, plots and track images.

Convention:
    ``RunRecorder.add(batch, frame)`` is called once per tracker step with the ``MultiStream``
    batch and the ``FeatureFrame``; only alive streams count. A *published feature* is a slot with
    ``frame.valid`` (what VINS would publish: mono ``track_cnt > 1`` on published frames).
    A track's length is the largest ``track_count`` its id reached (frames it was tracked in,
    published or not).

    Every output is written atomically: a file goes to a hidden temporary name in the same
    folder and is renamed over the final name (``os.replace``); ``tracks/`` is filled as a hidden
    temporary folder and renamed at the end (an older ``tracks/`` is replaced). An interrupted or
    failed run removes its temporaries and leaves no partial file under a final name.

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
      ``config``, ``mode``, ``device``, ``inputs``.
    * ``features_per_frame.png``, ``track_length_hist.png``: matplotlib (Agg) plots.
    * ``tracks/stream<b>/<stamp_ns>.png``: ``viz.draw_tracks`` per published frame per stream.
"""

from __future__ import annotations

import io
import json
import shutil
import tempfile
from pathlib import Path
from typing import Any, Dict, List, Sequence

import numpy as np

from ._atomic import atomic_path, replace_dir, write_bytes_atomic, write_text_atomic

CSV_COLUMNS = ("stream", "timestamp", "id", "x", "y", "u", "v", "vx", "vy", "track_count")


# ----------------------------------------------------------------------------------------------
# the recorder


class RunRecorder:
    """Collect per-step results of B streams and write the outputs of a run.

    Args:
        out: output folder (created).
        stream_names: one name per stream (for the summary and plots).
        write_tracks: draw and save track images (``tracks/``).

    Use as a context manager: leaving it with an exception removes the temporary ``tracks/``.
    """

    def __init__(self, out, stream_names: Sequence[str], write_tracks: bool = True):
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
        self._tmp_tracks: Path | None = None
        self.out.mkdir(parents=True, exist_ok=True)
        if self.write_tracks:
            self._tmp_tracks = Path(tempfile.mkdtemp(prefix=".tracks.", suffix=".tmp", dir=self.out))

    # -- context manager: clean temporaries on failure
    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self.abort()
        return False

    def abort(self) -> None:
        """Remove temporaries (nothing under a final name is touched)."""
        if self._tmp_tracks is not None and self._tmp_tracks.exists():
            shutil.rmtree(self._tmp_tracks, ignore_errors=True)
        self._tmp_tracks = None

    # -- per step
    def add(self, batch, frame) -> None:
        """Record one step: ``batch`` (``io.Batch``) and ``frame`` (``FeatureFrame``)."""
        alive = batch.alive.cpu().numpy().astype(bool)
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
        # track lengths: every feature in the table, its current count (max taken at the end)
        sb, sk = np.nonzero(present & (ids >= 0))
        if sb.size:
            self._lengths.append(np.stack([sb, ids[sb, sk], cnt[sb, sk]], axis=1).astype(np.int64))
        vb, vk = np.nonzero(valid)
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
        if self.write_tracks and self._tmp_tracks is not None:
            import cv2

            from .viz import draw_tracks

            for b in np.flatnonzero(published):
                img = draw_tracks(batch.raw[b], frame, int(b))
                d = self._tmp_tracks / f"stream{b}"
                d.mkdir(exist_ok=True)
                if not cv2.imwrite(str(d / f"{int(stamps[b])}.png"), img):
                    raise OSError(f"cannot write track image into {d}")
                self.track_images += 1

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
        """Length (largest ``track_count``) of every track (stream, id), as an int64 array."""
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
        s = {
            "streams": self.B,
            "frames": frames,
            "published": published,
            "published_features": int(cols_n),
            "mean_features": float(cols_n / published) if published else 0.0,
            "tracks": int(lengths.size),
            "mean_track_length": float(lengths.mean()) if lengths.size else 0.0,
            "median_track_length": float(np.median(lengths)) if lengths.size else 0.0,
            "seconds": round(float(seconds), 6),
            "frames_per_second": float(frames / seconds) if seconds > 0 else 0.0,
            "skipped_bad_frames": len(skipped),
            "skipped": [{"stream": int(b), "source": str(src), "reason": str(why)} for b, src, why in skipped],
            "track_images": self.track_images,
            "per_stream": per_stream,
        }
        if extra:
            s.update(extra)
        return s

    def write(self, summary: Dict[str, Any], plots: bool = True) -> List[Path]:
        """Write every output into ``out`` (atomically); returns the written paths."""
        written = []
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
        p = self.out / "features.csv"
        write_text_atomic(p, buf.getvalue())
        written.append(p)
        # features.npz (np.savez appends '.npz' to names without it: write to a file object)
        p = self.out / "features.npz"
        with atomic_path(p) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, **cols, stream_names=np.array(self.names))
        written.append(p)
        # summary.json
        p = self.out / "summary.json"
        write_text_atomic(p, json.dumps(summary, indent=2) + "\n")
        written.append(p)
        if plots:
            written += self._plots()
        if self.write_tracks and self._tmp_tracks is not None:
            replace_dir(self._tmp_tracks, self.out / "tracks")
            self._tmp_tracks = None
            written.append(self.out / "tracks")
        return written

    def _plots(self) -> List[Path]:
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
        out.append(self._save_fig(fig, "features_per_frame.png"))

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
        out.append(self._save_fig(fig, "track_length_hist.png"))
        return out

    def _save_fig(self, fig, name: str) -> Path:
        p = self.out / name
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        write_bytes_atomic(p, buf.getvalue())
        return p


__all__ = ["RunRecorder", "CSV_COLUMNS", "atomic_path", "write_text_atomic", "write_bytes_atomic", "replace_dir"]
