"""Compare two front ends' features (``torch-frontend compare``): a reference feature bag (VINS's own
``feature_tracker_node`` recorded, or ours) against a run of this front end.

Convention:
    *Frames* are matched by header stamp (ns). *Tracks* are matched by first position: a reference
    track (id) is mapped to the track of the other side that starts in the same frame (its first
    message) within ``tolerance`` pixels of it, the nearest one, each track used once. A reference
    feature *agrees* when its frame of the other side holds the mapped track within ``tolerance``
    pixels (u, v; Euclidean). Per-frame agreement = agreeing / reference features of the frame (a
    reference frame missing on the other side agrees on nothing); the overall figure is over all
    reference features. Camera 0 only (the id channel decoded with ``num_cameras``).

Outputs in ``out`` (one output set, ``_atomic.StagedFolder``): ``compare.json`` (the report),
``compare.txt`` (its text form), ``compare.png`` (per-frame agreement and feature counts).
"""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path
from typing import Any, Dict, List

import numpy as np

from .common import OptionError

__all__ = ["CompareOptions", "load_features", "compare_features", "run_compare", "format_compare"]


@dataclasses.dataclass
class CompareOptions:
    """Options of :func:`run_compare`.

    Attributes:
        tolerance: pixels (u, v) within which two features agree (default 0.1).
        stream: which stream of a multi-stream run (its ``features_stream<b>`` bag or npz rows).
        num_cameras: decoding of the id channel (1 mono, 2 stereo; ``io.feature_bag``).
        plots: write ``compare.png``.
    """

    tolerance: float = 0.1
    stream: int = 0
    num_cameras: int = 1
    plots: bool = True

    def check(self) -> None:
        if not self.tolerance > 0:
            raise OptionError("tolerance", f"tolerance: must be > 0 pixels, got {self.tolerance}")
        if self.stream < 0:
            raise OptionError("stream", f"stream: must be >= 0, got {self.stream}")
        if self.num_cameras not in (1, 2):
            raise OptionError("num_cameras", f"num_cameras: expected 1 or 2, got {self.num_cameras}")


def _is_bag(p: Path) -> bool:
    return (p.is_file() and p.suffix == ".bag") or (p.is_dir() and (p / "metadata.yaml").is_file())


def load_features(path, stream: int = 0, num_cameras: int = 1) -> List[Any]:
    """The feature frames of ``path`` as ``io.feature_bag.FeatureMessage``s (camera 0), in order:
    a feature bag, or a ``track`` output folder (its ``features.npz``, rows of ``stream``).

    Raises:
        DataError: nothing readable there.
    """
    from ..io.feature_bag import FeatureMessage, read_feature_bag
    from ..io.frames import DataError

    p = Path(path)
    if _is_bag(p):
        return [f for f in read_feature_bag(p, num_cameras=num_cameras).frames]
    npz = p / "features.npz"
    if not npz.is_file():
        raise DataError(f"{p}: neither a feature bag (.bag file or ROS 2 folder) nor a track output folder "
                        f"(no features.npz)")
    with np.load(npz) as z:
        c = {k: z[k] for k in ("stream", "stamp_ns", "id", "x", "y", "u", "v", "vx", "vy")}
    m = c["stream"] == stream
    c = {k: v[m] for k, v in c.items()}
    out = []
    order = np.argsort(c["stamp_ns"], kind="stable")  # rows keep their (slot) order within a frame
    c = {k: v[order] for k, v in c.items()}
    stamps, starts = np.unique(c["stamp_ns"], return_index=True)
    bounds = list(starts) + [len(c["stamp_ns"])]
    for i, s in enumerate(stamps):
        sl = slice(bounds[i], bounds[i + 1])
        n = bounds[i + 1] - bounds[i]
        out.append(FeatureMessage(stamp_ns=int(s), ids=c["id"][sl].astype(np.int64), camera=np.zeros(n, np.int64),
                                  xy=np.stack([c["x"][sl], c["y"][sl]], 1), uv=np.stack([c["u"][sl], c["v"][sl]], 1),
                                  velocity=np.stack([c["vx"][sl], c["vy"][sl]], 1)))
    return out


def _cam0(frames):
    return {f.stamp_ns: (f.ids[f.camera == 0], f.uv[f.camera == 0]) for f in frames}


def _first_seen(frames: Dict[int, tuple]) -> Dict[int, tuple]:
    """id -> (stamp of its first frame, its uv there)."""
    first: Dict[int, tuple] = {}
    for s in sorted(frames):
        ids, uv = frames[s]
        for j, i in enumerate(ids.tolist()):
            if i not in first:
                first[i] = (s, uv[j])
    return first


def compare_features(reference: List[Any], other: List[Any], tolerance: float = 0.1) -> Dict[str, Any]:
    """The agreement of ``other`` with ``reference`` (lists of ``FeatureMessage``; module docstring).

    Returns a dict: ``frames`` (reference frames), ``frames_missing`` (reference stamps absent from
    ``other``), ``frames_extra``, ``reference_features``, ``other_features`` (in the reference's
    frames), ``agreeing``, ``agreement`` (fraction), ``tracks_reference``, ``tracks_matched``,
    ``frames_full`` (frames at 100 %), ``per_frame`` (``[stamp_ns, reference features, other
    features, agreeing]``) and ``tolerance``.
    """
    ref, oth = _cam0(reference), _cam0(other)
    ref_first, oth_first = _first_seen(ref), _first_seen(oth)
    # tracks of `other` by the frame they start in
    starts: Dict[int, List[int]] = {}
    for i, (s, _uv) in oth_first.items():
        starts.setdefault(s, []).append(i)
    mapping: Dict[int, int] = {}
    used: set = set()
    for r in sorted(ref_first, key=lambda r: (ref_first[r][0], r)):
        s, uv = ref_first[r]
        cands = [i for i in starts.get(s, []) if i not in used]
        if not cands:
            continue
        d = np.array([np.linalg.norm(oth_first[i][1] - uv) for i in cands])
        k = int(np.argmin(d))
        if d[k] <= tolerance:
            mapping[r] = cands[k]
            used.add(cands[k])
    per_frame = []
    agreeing = n_ref = n_oth = 0
    for s in sorted(ref):
        ids, uv = ref[s]
        good = 0
        oids, ouv = oth.get(s, (np.zeros(0, np.int64), np.zeros((0, 2))))
        pos = {i: ouv[j] for j, i in enumerate(oids.tolist())}
        for j, r in enumerate(ids.tolist()):
            o = mapping.get(r)
            if o is not None and o in pos and np.linalg.norm(pos[o] - uv[j]) <= tolerance:
                good += 1
        per_frame.append([int(s), int(len(ids)), int(len(oids)), good])
        agreeing += good
        n_ref += len(ids)
        n_oth += len(oids)
    return {
        "frames": len(ref),
        "frames_missing": sorted(int(s) for s in set(ref) - set(oth)),
        "frames_extra": len(set(oth) - set(ref)),
        "reference_features": int(n_ref),
        "other_features": int(n_oth),
        "agreeing": int(agreeing),
        "agreement": float(agreeing / n_ref) if n_ref else 1.0,
        "tracks_reference": len(ref_first),
        "tracks_matched": len(mapping),
        "frames_full": int(sum(1 for p in per_frame if p[3] == p[1])),
        "tolerance": float(tolerance),
        "per_frame": per_frame,
    }


def format_compare(r: Dict[str, Any]) -> str:
    """The few lines ``torch-frontend compare`` prints."""
    pf = [p[3] / p[1] for p in r["per_frame"] if p[1]]
    lines = [
        f"reference     {r.get('reference', '?')}: {r['frames']} frames, {r['reference_features']} features, "
        f"{r['tracks_reference']} tracks",
        f"compared      {r.get('other', '?')}: {r['other_features']} features in those frames, "
        f"{len(r['frames_missing'])} frames missing, {r['frames_extra']} extra",
        f"tracks        {r['tracks_matched']} of {r['tracks_reference']} matched by first position "
        f"(within {r['tolerance']:g} px)",
        f"agreement     {100 * r['agreement']:.2f} % of the reference features ({r['agreeing']} of "
        f"{r['reference_features']}; same track within {r['tolerance']:g} px)",
        f"per frame     min {100 * min(pf) if pf else 100:.1f} %, mean {100 * np.mean(pf) if pf else 100:.1f} %, "
        f"{r['frames_full']} of {r['frames']} frames at 100 %",
    ]
    if "out" in r:
        lines.append(f"outputs       {r['out']}/ (compare.json, compare.txt, compare.png)")
    return "\n".join(lines)


def _plot(r: Dict[str, Any]) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    pf = r["per_frame"]
    k = np.arange(len(pf))
    ax1.plot(k, [100 * p[3] / p[1] if p[1] else 100 for p in pf], "o-", ms=3, lw=1)
    ax1.set_ylabel("agreement (%)")
    ax1.set_ylim(-2, 102)
    ax1.set_title(f"Agreement per frame ({100 * r['agreement']:.2f} % overall, {r['tolerance']:g} px)")
    ax1.grid(True, alpha=0.3)
    ax2.plot(k, [p[1] for p in pf], "-", label="reference")
    ax2.plot(k, [p[2] for p in pf], "--", label="compared")
    ax2.plot(k, [p[3] for p in pf], ":", label="agreeing")
    ax2.set_xlabel("reference frame")
    ax2.set_ylabel("features")
    ax2.legend(fontsize=8)
    ax2.grid(True, alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _run_stream(folder: Path, stream: int) -> Dict[str, Any]:
    """The ``name``, ``config`` and ``camera`` of stream ``stream`` of a ``track`` output folder (its
    ``summary.json``'s ``per_stream`` entry, or a sharded run's ``stream<b>/summary.json``); ``{}``
    when ``folder`` is not a run that names them (a bag, an older run)."""
    for summary, b in ((folder / "summary.json", stream), (folder / f"stream{stream}" / "summary.json", 0)):
        try:
            per = json.loads(summary.read_text(encoding="utf-8")).get("per_stream") or []
        except (OSError, ValueError, AttributeError):
            continue
        if b < len(per) and isinstance(per[b], dict) and "config" in per[b]:
            return {k: per[b][k] for k in ("name", "config", "camera") if k in per[b]}
    return {}


def run_compare(reference, other, out, options: CompareOptions | None = None) -> Dict[str, Any]:
    """Compare the feature bag ``reference`` with ``other`` (a bag or a ``track`` output folder) and
    write the report into the folder ``out`` (module docstring); returns the report (with
    ``other_stream``: the compared stream's name, config and camera, when ``other`` is a ``track``
    output folder whose summary names them).

    Raises:
        OptionError: bad options; DataError: unreadable inputs; OutputFolderError: ``out`` holds
        files the library did not write.
    """
    from .._atomic import StagedFolder

    opt = CompareOptions() if options is None else options
    opt.check()
    other_p = Path(other)
    if not _is_bag(other_p) and other_p.is_dir():
        bags = sorted(q for q in other_p.iterdir() if _is_bag(q) and f"_stream{opt.stream}" in q.name)
        whole = [q for q in other_p.iterdir() if _is_bag(q) and "_stream" not in q.name]
        pick = bags or (whole if opt.stream == 0 else [])
        if pick:
            other_p = pick[0]
    ref = load_features(reference, 0, opt.num_cameras)
    oth = load_features(other_p, opt.stream, opt.num_cameras)
    r = compare_features(ref, oth, opt.tolerance)
    r = {"reference": str(reference), "other": str(other_p), "out": str(out), **r}
    stream_info = _run_stream(Path(other), opt.stream)
    if stream_info:  # a track run: the compared stream's name, config and camera (per_stream)
        r["other_stream"] = stream_info
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    stage = StagedFolder(out, "compare")
    try:
        (stage.path / "compare.json").write_bytes((json.dumps(r, indent=1) + "\n").encode("utf-8"))
        (stage.path / "compare.txt").write_bytes((format_compare(r) + "\n").encode("utf-8"))
        if opt.plots:
            (stage.path / "compare.png").write_bytes(_plot(r))
        stage.commit()
    except BaseException:
        stage.abort()
        raise
    return r
