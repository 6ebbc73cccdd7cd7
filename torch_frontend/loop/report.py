"""Writers of a loop-closure run (``torch-frontend loop`` / ``demo --loop``): trajectories, loops,
the pose graph, ``summary.json`` and two plots, all written atomically into the output folder.

Convention:
    ``write_loop_outputs(out, run)`` takes the ``LoopRun`` of
    :func:`torch_frontend.pipelines.loop.run_loop` and writes, into ``out`` (created):

    * per stream (at the top of ``out`` for one stream, in ``out/stream<b>/`` for several):
      ``vins_result_loop.csv`` (VINS format, spec §7.11: ``time·1e9`` then ``P.x P.y P.z Q.w Q.x Q.y
      Q.z``, each followed by a comma), ``trajectory_loop.tum`` (loop-corrected keyframe poses) and
      ``trajectory_vio.tum`` (the input VIO poses at the same keyframes), TUM format
      ``timestamp tx ty tz qx qy qz qw`` (readable by evo). Poses are body-to-world; the
      loop-corrected ones are in the pose-graph world (that of the first sequence of a shared map).
    * ``loops.csv``: one row per verified loop candidate (accepted or not), see ``LOOP_COLUMNS``:
      keyframe indices in their graph (``current``, ``old``), their streams and times, the
      place-recognition ``score``, ``accepted`` (0/1), ``reason`` (``accepted``, ``few_matches``,
      ``pnp_failed``, ``few_inliers``, ``yaw``, ``translation``), ``matches``, ``inliers`` and the
      relative pose (current body in the old body frame: ``tx ty tz`` m, ``qw qx qy qz``,
      ``yaw_deg``; zeros / identity when PnP did not run).
    * the pose graph in VINS's format (``PoseGraph.save``): ``pose_graph/`` for one graph, or
      ``stream<b>/pose_graph/`` per stream with ``separate_graphs``.
    * ``summary.json`` (the ``run.summary`` dict; ``ate_before``/``ate_after`` in metres at the top
      level when ground truth was given).
    * ``trajectory_top.png``: top view before (VIO) and after loop closure, with the loop edges,
      in the plane perpendicular to the run's up axis (``summary["up"]``: x-y for ``+z``, x-z for
      KITTI's ``-y``; ``loop.world.plane_axes``); aligned to the ground truth (SE(3), Umeyama)
      when there is one.
      ``place_recognition_scores.png``: per keyframe, the best place-recognition score and the
      candidates (accepted / rejected).

    * ``written-by-torch-frontend.json``: the marker, the list of what the run wrote (and one in
      each ``pose_graph/``, which ``PoseGraph.save`` writes).

    The output set is written as a whole, as ``torch_frontend.outputs`` describes for ``track``:
    into a hidden temporary folder beside ``out``, swapped in for ``out`` in one step when
    complete (``_atomic.StagedFolder``), so ``out`` holds either the complete previous set or the
    complete new one; an interrupted or failed write removes its temporary folder. An ``out`` that
    holds files the library did not write is refused (``OutputFolderError``, checked by
    ``check_out_folder`` before the run and again before the swap); a folder written before the
    marker existed is replaced when it holds only the names above (``LEGACY_OUTPUTS``).
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from .._atomic import StagedFolder, check_replaceable, legacy_temporaries
from .pose_graph import POSE_GRAPH_FILES

__all__ = [
    "LEGACY_OUTPUTS",
    "LOOP_COLUMNS",
    "OUTPUT_FILES",
    "STREAM_FILES",
    "check_out_folder",
    "graph_dir",
    "loops_csv_text",
    "plot_scores",
    "plot_trajectories",
    "stream_dir",
    "write_loop_outputs",
]

LOOP_COLUMNS = ("graph", "current", "old", "current_stream", "old_stream", "current_time", "old_time",
                "score", "accepted", "reason", "matches", "inliers",
                "tx", "ty", "tz", "qw", "qx", "qy", "qz", "yaw_deg")

#: per-stream trajectory files and the run-level files every run writes
STREAM_FILES = ("vins_result_loop.csv", "trajectory_loop.tum", "trajectory_vio.tum")
OUTPUT_FILES = ("loops.csv", "summary.json", "trajectory_top.png", "place_recognition_scores.png")


def _names(names) -> str:
    return "(" + "|".join(re.escape(n) for n in names) + ")"


#: what an ``out`` folder written before the marker existed may hold to be replaced (``_atomic``):
#: the files above (per-stream ones at the top or in ``stream<b>/``), ``pose_graph/`` and the
#: temporaries older versions left
LEGACY_OUTPUTS = (
    _names(OUTPUT_FILES),
    r"stream\d+",
    r"(stream\d+/)?" + _names(STREAM_FILES),
    r"(stream\d+/)?pose_graph",
    *(r"(stream\d+/)?pose_graph/" + p for p in POSE_GRAPH_FILES),
    *(r"(stream\d+/)?" + p for p in legacy_temporaries(*STREAM_FILES, *OUTPUT_FILES, "pose_graph")),
)


def stream_dir(out: Path, stream: int, num_streams: int) -> Path:
    """Where a stream's trajectory files go: ``out`` for a single stream, else ``out/stream<b>``."""
    return Path(out) if num_streams == 1 else Path(out) / f"stream{stream}"


# ----------------------------------------------------------------------------------------------
# CSV


def _fmt(v: float) -> str:
    return f"{v:.9g}"


def loops_csv_text(loops: Sequence[Any]) -> str:
    """``loops.csv`` for ``LoopRun.loops`` (``LoopRecord``: ``graph``, ``stream``, ``old_stream``,
    ``time``, ``old_time`` and the pose graph's ``LoopResult`` as ``result``)."""
    lines = [",".join(LOOP_COLUMNS) + "\n"]
    for rec in loops:
        r = rec.result
        t = np.asarray(r.relative_t, dtype=np.float64).reshape(3)
        q = np.asarray(r.relative_q, dtype=np.float64).reshape(4)
        vals = [str(rec.graph), str(r.index), str(r.old_index), str(rec.stream), str(rec.old_stream),
                f"{rec.time:.9f}", f"{rec.old_time:.9f}", _fmt(r.score), str(int(bool(r.accepted))), r.reason,
                str(int(r.num_matches)), str(int(r.num_inliers)),
                *(_fmt(float(x)) for x in t), *(_fmt(float(x)) for x in q), _fmt(float(r.relative_yaw))]
        lines.append(",".join(vals) + "\n")
    return "".join(lines)


# ----------------------------------------------------------------------------------------------
# plots


def _figure(w: float, h: float):
    # Figure + the Agg canvas directly, no pyplot (as torch_frontend.outputs): no global backend
    # switch, no state leaking into a notebook's inline backend.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _pairs(traj, gt):
    """Associated ``(est (K, 3), ref (K, 3))`` positions of ``traj`` and ``gt``, or None."""
    if gt is None or traj.t.shape[0] < 3:
        return None
    from ..trajectory import associate

    ie, ir = associate(traj.time, gt.time)
    if ie.numel() < 3:
        return None
    return traj.t.double()[ie], gt.t.double()[ir]


def _alignments(run, key: str) -> Dict[int, Optional[tuple]]:
    """Per stream, the SE(3) ``(R, t)`` that moves its ``key`` (``"before"``: VIO, ``"after"``:
    corrected) positions onto the ground truth (Umeyama, as the ATE), or None without one. A shared
    map of several streams gets ONE alignment for all of them (its streams share one world)."""
    from ..trajectory import align_se3

    pairs = {s.stream: _pairs(s.vio if key == "before" else s.corrected, s.ground_truth) for s in run.streams}
    shared = len(run.graphs) == 1 and len(run.streams) > 1
    if shared and all(p is not None for p in pairs.values()):
        import torch

        R, t, _ = align_se3(torch.cat([p[0] for p in pairs.values()]), torch.cat([p[1] for p in pairs.values()]))
        return {k: (R.numpy(), t.numpy()) for k in pairs}
    out: Dict[int, Optional[tuple]] = {}
    for k, p in pairs.items():
        if p is None:
            out[k] = None
        else:
            R, t, _ = align_se3(p[0], p[1])
            out[k] = (R.numpy(), t.numpy())
    return out


def _apply(p: np.ndarray, Rt: Optional[tuple]) -> np.ndarray:
    return p if Rt is None else p @ Rt[0].T + Rt[1]


def _view(run) -> np.ndarray:
    """``(3, 3)``: world positions -> the plot's (horizontal, vertical, up) coordinates
    (``loop.world.to_z_up`` of the run's up axis)."""
    from .world import to_z_up

    return to_z_up(str(run.summary.get("up", "+z")))


def _keyframe_xy(run, align) -> Dict[str, Dict[tuple, np.ndarray]]:
    """``{"before"|"after": {(graph, index): xy}}`` of every keyframe, in the plotted frames."""
    pos: Dict[str, Dict[tuple, np.ndarray]] = {"before": {}, "after": {}}
    V = _view(run)
    for s in run.streams:
        for key, traj in (("before", s.vio), ("after", s.corrected)):
            p = _apply(np.asarray(traj.t, dtype=np.float64).reshape(-1, 3), align[key][s.stream]) @ V.T
            for k, gi in enumerate(np.asarray(s.graph_indices).tolist()):
                pos[key][(s.graph, int(gi))] = p[k, :2]
    return pos


def plot_trajectories(run) -> bytes:
    """PNG bytes of ``trajectory_top.png`` (see the module docstring)."""
    fig = _figure(12, 5.5)
    axes = [fig.add_subplot(1, 2, i + 1) for i in range(2)]
    align = {key: _alignments(run, key) for key in ("before", "after")}
    pos = _keyframe_xy(run, align)
    has_gt = any(s.ground_truth is not None for s in run.streams)
    colours = ["tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"]
    from .world import axis_name, plane_axes

    V = _view(run)
    labels = [f"{axis_name(a)} (m)" for a in plane_axes(str(run.summary.get("up", "+z")))]
    for ax, key, title in ((axes[0], "before", "before: VIO"), (axes[1], "after", "after: loop-corrected")):
        for s in run.streams:
            c = colours[s.stream % len(colours)]
            if s.ground_truth is not None:
                g = np.asarray(s.ground_truth.t, dtype=np.float64) @ V.T
                ax.plot(g[:, 0], g[:, 1], "-", color="0.55", lw=1.0,
                        label="ground truth" if s.stream == run.streams[0].stream else None)
            traj = s.vio if key == "before" else s.corrected
            p = _apply(np.asarray(traj.t, dtype=np.float64).reshape(-1, 3), align[key][s.stream]) @ V.T
            if p.shape[0]:
                ate = s.ate_before if key == "before" else s.ate_after
                lab = s.name + (f" (ATE {ate:.3f} m)" if ate is not None else "")
                ax.plot(p[:, 0], p[:, 1], ".-", color=c, lw=1.2, ms=3, label=lab)
                ax.plot(p[:1, 0], p[:1, 1], "o", color=c, ms=7, mfc="none")
        # loop edges: accepted in green on both panels, rejected candidates (thin red) before
        n_acc = n_rej = 0
        for rec in run.loops:
            a = pos[key].get((rec.graph, rec.result.index))
            b = pos[key].get((rec.graph, rec.result.old_index))
            if a is None or b is None:
                continue
            if rec.result.accepted:
                ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="tab:green", lw=1.6, alpha=0.8,
                        label="accepted loop" if n_acc == 0 else None)
                n_acc += 1
            elif key == "before":
                ax.plot([a[0], b[0]], [a[1], b[1]], ":", color="tab:red", lw=1.0, alpha=0.7,
                        label="rejected candidate" if n_rej == 0 else None)
                n_rej += 1
        ax.set_title(title + (" (aligned to ground truth)" if has_gt else ""))
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    s = run.summary
    if s.get("ate_joint_before") is not None:
        fig.suptitle(f"shared map: ATE (one alignment) {s['ate_joint_before']:.3f} m -> {s['ate_joint_after']:.3f} m, "
                     f"{s.get('loops_accepted', 0)} loops accepted")
    elif s.get("ate_before") is not None and s.get("ate_after") is not None:
        fig.suptitle(f"ATE {s['ate_before']:.3f} m -> {s['ate_after']:.3f} m, "
                     f"{s.get('loops_accepted', 0)} loops accepted")
    fig.tight_layout()
    return _png(fig)


def plot_scores(run) -> bytes:
    """PNG bytes of ``place_recognition_scores.png``: per graph, the best score of each keyframe's
    database query (0 while fewer than 50 keyframes are older), candidates marked."""
    n = len(run.graphs)
    fig = _figure(10, 2.2 + 2.3 * n)
    for g, graph in enumerate(run.graphs):
        ax = fig.add_subplot(n, 1, g + 1)
        sc = np.asarray(graph.scores, dtype=np.float64)
        x = np.arange(sc.size)
        # VINS queries the whole database while the keyframe index is <= 50 (DBoW2's max_id < 0
        # means "no limit") but never accepts a loop there: grey, to not read as revisits
        gap = int(getattr(graph, "min_loop_gap", 50))
        early = x <= gap
        if early.any():
            ax.plot(x[early], sc[early], "-", color="0.7", lw=1.0,
                    label=f"index <= {gap}: no loop possible (VINS)")
        if (~early).any():
            ax.plot(x[gap:], sc[gap:], "-", color="tab:blue", lw=1.0, label="best score")
        recs = [r for r in run.loops if r.graph == g]
        acc = [r.result for r in recs if r.result.accepted]
        rej = [r.result for r in recs if not r.result.accepted]
        if acc:
            ax.plot([r.index for r in acc], [r.score for r in acc], "o", color="tab:green", ms=5,
                    label=f"accepted loop ({len(acc)})")
        if rej:
            ax.plot([r.index for r in rej], [r.score for r in rej], "x", color="tab:red", ms=6,
                    label=f"rejected candidate ({len(rej)})")
        ax.axhline(0.05, color="0.5", ls="--", lw=0.8, label="VINS min. score 0.05")
        ax.set_xlabel("keyframe index")
        ax.set_ylabel("score")
        names = ", ".join(s.name for s in run.streams if s.graph == g)
        ax.set_title(f"Place recognition ({names})" if names else "Place recognition")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    return _png(fig)


# ----------------------------------------------------------------------------------------------
# everything


def _json_safe(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.ndarray):
        return _json_safe(v.tolist())
    if isinstance(v, Path):
        return str(v)
    return v


def check_out_folder(out) -> None:
    """Raise ``OutputFolderError`` when ``out`` may not be replaced by a run's outputs (it holds
    files the library did not write, or is a file); see the module docstring."""
    check_replaceable(Path(os.path.realpath(out)), LEGACY_OUTPUTS)


def write_loop_outputs(out, run, plots: bool = True, save_graph: bool = True, stage=None) -> List[Path]:
    """Write every output of ``run`` (a ``LoopRun``) and swap the set in for ``out`` (module
    docstring); returns the paths under ``out``. ``stage``: the run's ``StagedFolder`` of ``out``
    when it has one already (a checkpointed run's), filled and committed here."""
    from ..trajectory import write_tum, write_vins_csv

    t_all = time.perf_counter()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    written: List[Path] = []
    B = len(run.streams)
    own = stage is None
    if own:
        stage = StagedFolder(out, "loop", LEGACY_OUTPUTS)
    else:
        _clear_outputs(stage.path)
    try:
        tmp = stage.path
        for s in run.streams:
            d = stream_dir(tmp, s.stream, B)
            d.mkdir(parents=True, exist_ok=True)
            write_vins_csv(d / "vins_result_loop.csv", s.corrected)
            write_tum(d / "trajectory_loop.tum", s.corrected)
            write_tum(d / "trajectory_vio.tum", s.vio)
            written += [stream_dir(out, s.stream, B) / n for n in STREAM_FILES]
        (tmp / "loops.csv").write_bytes(loops_csv_text(run.loops).encode("utf-8"))
        written.append(out / "loops.csv")
        if save_graph:
            for g, graph in enumerate(run.graphs):
                d = graph_dir(tmp, g, run)
                d.parent.mkdir(parents=True, exist_ok=True)
                graph.save(d)
                written.append(graph_dir(out, g, run))
        if plots:
            for name, data in (("trajectory_top.png", plot_trajectories(run)),
                               ("place_recognition_scores.png", plot_scores(run))):
                (tmp / name).write_bytes(data)
                written.append(out / name)
        # summary.json last, with the time the outputs took (the plots dominate)
        times = run.summary.setdefault("times", {})
        if isinstance(times, dict):
            times["outputs"] = round(time.perf_counter() - t_all, 6)
        (tmp / "summary.json").write_bytes((json.dumps(_json_safe(run.summary), indent=2) + "\n").encode("utf-8"))
        written.append(out / "summary.json")
    except BaseException:
        if own:  # a checkpointed run's staging folder is its owner's to keep or remove
            stage.abort()
        raise
    stage.commit()
    return written


def _clear_outputs(stage: Path) -> None:
    """Remove what an interrupted writer left in a resumed run's staging folder (everything but
    its checkpoints: the outputs are written in one go, at the end)."""
    import shutil

    from .._atomic import CHECKPOINT_FOLDER

    for e in os.scandir(stage):
        if e.name == CHECKPOINT_FOLDER:
            continue
        if e.is_dir(follow_symlinks=False):
            shutil.rmtree(e.path)
        else:
            os.unlink(e.path)


def graph_dir(out: Path, graph: int, run) -> Path:
    """``pose_graph/`` of graph ``graph``: at the top for one graph, else in its stream's folder."""
    if len(run.graphs) == 1:
        return Path(out) / "pose_graph"
    owner: Optional[int] = next((s.stream for s in run.streams if s.graph == graph), graph)
    return stream_dir(out, owner, len(run.streams)) / "pose_graph"
