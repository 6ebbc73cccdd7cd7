"""Full front end (FeatureTracker, mono mode, EuRoC config, 752×480) vs the OpenCV oracle pipeline.

Both run in the same process on the same frames. For each row: milliseconds per stream-frame for
torch-frontend (B streams in one tracker) and for OpenCV (a loop of B single-stream oracle trackers,
``torch_frontend.testing.oracle``), the ratio, peak memory, and torch's per-stage breakdown.

Each configuration runs in its own subprocess so that peak RSS belongs to it alone, and torch and
OpenCV get the same thread count (``torch.set_num_threads`` / ``cv2.setNumThreads``).

Usage:
    python benchmarks/bench_pipeline.py              # the standard table (B 1, 4, 16, 64; threads 1, 2)
    python benchmarks/bench_pipeline.py --quick      # B 1 and 4, threads 1 (a smoke run)
    python benchmarks/bench_pipeline.py --compile    # also torch.compile rows (B 1 and 16, 1 thread)
    python benchmarks/bench_pipeline.py --profile 16 # where the time goes at B = 16, 1 thread:
                                                     # results/pipeline_profile.md (torch.profiler
                                                     # ops and cProfile functions)
    python benchmarks/bench_pipeline.py --rig        # per-stream configs: a mixed batch of equal-size
                                                     # configs and a mixed-size one vs a homogeneous
                                                     # batch of the same B, in one process, 1 thread:
                                                     # results/pipeline_rig.{json,md}

Writes ``benchmarks/results/pipeline.json`` and ``benchmarks/results/pipeline.md`` (temp + rename),
and a scaling plot ``benchmarks/results/pipeline_scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
SAMPLE = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"

#: per stream-frame against the OpenCV pipeline: B = 1 at most 1.5x, B >= 16 at most 0.8x (CPU, 1 thread);
#: B = 64 on a GPU at least 50x faster than OpenCV on one core
TARGETS = {"cpu_b1": 1.5, "cpu_b16plus": 0.8, "gpu_b64_speedup": 50.0}


def _frames():
    import cv2

    files = sorted(SAMPLE.glob("*.png"))
    return [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]


def _stream_frames(frames, B, n_steps):
    """Frame k of stream b: sample frame (k + 3 b) mod 24 walked forwards then backwards (a real,
    slowly moving sequence per stream, different per stream)."""
    n = len(frames)
    period = 2 * (n - 1)
    out = []
    for k in range(n_steps):
        row = []
        for b in range(B):
            i = (k + 3 * b) % period
            row.append(frames[i if i < n else period - i])
        out.append(row)
    return out


def run_one(B: int, threads: int, device: str, compiled: bool, n_warm: int, n_meas: int, skip_cv: bool,
            repeats: int = 3, capturable: bool | None = None) -> dict:
    """One configuration, in this process. Returns a dict of measurements.

    Each side is timed over ``repeats`` windows of ``n_meas`` consecutive steps (an even count: VINS
    publishes every other frame at these stamps, so a window holds both kinds of step), torch and
    OpenCV windows alternating, and the fastest window counts, as ``timeit`` does: on a shared
    machine the slower windows measure the neighbours, not the code."""
    import resource

    import cv2
    import numpy as np
    import torch

    import torch_frontend as tf
    from torch_frontend.testing import oracle

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    frames = _frames()
    n_total = n_warm + repeats * n_meas
    steps = _stream_frames(frames, B, n_total)
    stamps = [1403715273.0 + 0.05 * k for k in range(n_total)]
    windows = [range(n_warm + r * n_meas, n_warm + (r + 1) * n_meas) for r in range(repeats)]
    dev = torch.device(device)
    tr = tf.FeatureTracker(cfg, num_streams=B, device=dev, capturable=capturable)
    if compiled:
        tr.compile()
    batches = [torch.from_numpy(np.stack(row))[:, None].to(dev) for row in steps]
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    for k in range(n_warm):
        tr.track(batches[k], [stamps[k]] * B)
    sync()
    warm_state = tr.state  # a value: the counted steps below replay the first window from here
    orcs = None
    if not skip_cv:
        cfg_cv = {
            "max_cnt": cfg.max_cnt, "min_dist": cfg.min_dist, "freq": cfg.freq, "F_threshold": cfg.F_threshold,
            "equalize": int(cfg.equalize), "fisheye": 0, "image_width": cfg.image_width,
            "image_height": cfg.image_height,
            "camera": {"model_type": cfg.camera.model_type, **cfg.camera.params_dict()},
        }
        orcs = [oracle.OracleMonoTracker(cfg_cv) for _ in range(B)]
        for k in range(n_warm):
            for b in range(B):
                orcs[b].process(steps[k][b], stamps[k])
    # windows alternate between the two sides, so that both see the same machine weather
    t_torch, stages, t_cv = float("inf"), {}, float("inf")
    for win in windows:
        tr.enable_stage_times()
        t0 = time.perf_counter()
        for k in win:
            tr.track(batches[k], [stamps[k]] * B)
        sync()
        t = time.perf_counter() - t0
        if t < t_torch:
            t_torch, stages = t, {k: v / (n_meas * B) * 1e3 for k, v in (tr.stage_times or {}).items()}
        if orcs is not None:
            t0 = time.perf_counter()
            for k in win:
                for b in range(B):
                    orcs[b].process(steps[k][b], stamps[k])
            t_cv = min(t_cv, time.perf_counter() - t0)
    counts = launch_counts(tr, warm_state, batches[n_warm:n_warm + n_meas], stamps[n_warm:n_warm + n_meas], B)
    res = {
        "B": B, "threads": threads, "device": device, "compiled": compiled, "capturable": tr.capturable,
        "steps_per_window": n_meas, "windows": repeats, **counts,
        "torch_ms_per_stream_frame": t_torch / (n_meas * B) * 1e3,
        "torch_ms_per_step": t_torch / n_meas * 1e3,
        "stages_ms_per_stream_frame": stages,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    if dev.type == "cuda":
        res["cuda_max_allocated_mib"] = torch.cuda.max_memory_allocated() / 2**20
    if orcs is not None:
        res["opencv_ms_per_stream_frame"] = t_cv / (n_meas * B) * 1e3
        res["ratio"] = res["torch_ms_per_stream_frame"] / res["opencv_ms_per_stream_frame"]
    return res


def launch_counts(tr, state, batches, stamps, B) -> dict:
    """Kernels, views and host syncs per step (means over ``len(batches)`` steps, an even count: a
    published and an unpublished step each), counted with ``torch_frontend.testing.dispatch_count``
    from ``state`` with the pure step (what the same ops launch and wait for on CUDA), including the
    door's checks and the upload of the step's own images and timestamps. Not counted for compiled rows (the compiled
    graph does not dispatch op by op)."""
    from torch_frontend.testing.dispatch_count import OpCounter

    if tr._compiled is not None:
        return {}
    totals = dict(kernels=0, views=0, syncs=0)
    for img, t in zip(batches, stamps):
        with OpCounter() as c:
            state, _ = tr.step(state, img, [t] * B)
        for k in totals:
            totals[k] += getattr(c, k)
    return {f"{k}_per_step": v / len(batches) for k, v in totals.items()}


def profile(B: int, n_meas: int = 6) -> str:
    """Markdown: the tracker at ``B`` streams, 1 thread, CPU — the top aten ops by self time
    (``torch.profiler``) and the top torch_frontend functions by own time (``cProfile``), each as a
    share of the measured steps."""
    import cProfile
    import pstats

    import numpy as np
    import torch
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as tprofile

    import torch_frontend as tf

    torch.set_num_threads(1)
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    steps = _stream_frames(_frames(), B, 4 + 2 * n_meas)
    stamps = [1403715273.0 + 0.05 * k for k in range(len(steps))]
    batches = [torch.from_numpy(np.stack(row))[:, None] for row in steps]
    tr = tf.FeatureTracker(cfg, num_streams=B)
    for k in range(4):
        tr.track(batches[k], [stamps[k]] * B)
    with tprofile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        for k in range(4, 4 + n_meas):
            tr.track(batches[k], [stamps[k]] * B)
        wall = time.perf_counter() - t0
    ev = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in ev) or 1.0
    lines = [f"Profile: B = {B}, 1 thread, {n_meas} steps, {wall / (n_meas * B) * 1e3:.1f} ms/stream-frame "
             f"under torch.profiler. Machine: {machine_description()}", "",
             "| aten op | self CPU share | calls per step | mean µs per call |", "|---|---|---|---|"]
    for e in ev[:15]:
        lines.append(f"| {e.key} | {e.self_cpu_time_total / total:.1%} | {e.count / n_meas:.1f} | "
                     f"{e.self_cpu_time_total / max(e.count, 1):.1f} |")
    pr = cProfile.Profile()
    pr.enable()
    for k in range(4 + n_meas, 4 + 2 * n_meas):
        tr.track(batches[k], [stamps[k]] * B)
    pr.disable()
    st = pstats.Stats(pr)
    # own time of each torch_frontend function, plus the builtins (torch ops) it calls directly:
    # where the kernels' time lands in our code
    own: dict = {}
    for key, (_, _, tt, _, callers) in st.stats.items():
        if "torch_frontend" in key[0]:
            own[key] = own.get(key, 0.0) + tt
        elif key[0] == "~":
            for caller, (_, _, _, cct) in callers.items():
                if "torch_frontend" in caller[0]:
                    own[caller] = own.get(caller, 0.0) + cct
    tot = st.total_tt or 1.0
    lines += ["", "| torch_frontend function (cProfile) | own time share, with the torch ops it calls |"
              " calls per step |", "|---|---|---|"]
    for key, t in sorted(own.items(), key=lambda kv: kv[1], reverse=True)[:15]:
        lines.append(f"| {Path(key[0]).name}:{key[1]} {key[2]} | {t / tot:.1%} | {st.stats[key][1] / n_meas:.1f} |")
    return "\n".join(lines) + "\n"


#: ``--rig``: the mixed batches, as ``(label, configs)`` cycled over the B streams. Equal size: four
#: 752x480 configs of two models and other VINS keys and intrinsics; mixed size: EuRoC and TUM-VI
RIG_BATCHES = ("equal-size mixed (pinhole, MEI, other fx, other max_cnt/min_dist)", "mixed sizes (752x480, 512x512)")


def _rig_configs():
    import dataclasses

    import torch

    import torch_frontend as tf

    euroc = tf.load_config(REPO / "configs" / "euroc.yaml")
    mei = tf.load_config(REPO / "configs" / "euroc_mono_mei.yaml")
    other_fx = dataclasses.replace(euroc, camera=type(euroc.camera).from_params(
        {**euroc.camera.params_dict(), "fx": euroc.camera.params_dict()["fx"] * 1.02},
        width=euroc.image_width, height=euroc.image_height))
    other_keys = dataclasses.replace(euroc, max_cnt=120, min_dist=25)
    tum = tf.load_config(REPO / "configs" / "tum_vi.yaml")
    del torch
    return euroc, {RIG_BATCHES[0]: [euroc, mei, other_fx, other_keys], RIG_BATCHES[1]: [euroc, tum]}


def rig(batches=(4, 8, 16), n_warm: int = 4, n_meas: int = 4, repeats: int = 5) -> dict:
    """CPU ms per stream-frame of a homogeneous batch (B EuRoC streams) and of the mixed batches of
    :data:`RIG_BATCHES` at the same B, 1 thread, in this process: windows of ``n_meas`` steps
    alternate between the batches, the fastest window of each counts (as :func:`run_one`)."""
    import cv2
    import numpy as np
    import torch

    import torch_frontend as tf

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    euroc, mixes = _rig_configs()
    frames = _frames()
    rows = []
    for B in batches:
        n_total = n_warm + repeats * n_meas
        steps = _stream_frames(frames, B, n_total)
        stamps = [1403715273.0 + 0.05 * k for k in range(n_total)]
        runs = {"homogeneous": (tf.FeatureTracker(euroc, num_streams=B), None)}
        for label, cfgs in mixes.items():
            per = [cfgs[b % len(cfgs)] for b in range(B)]
            runs[label] = (tf.FeatureTracker(per), per)

        def inputs(per, k, steps=steps):
            if per is None:
                return torch.from_numpy(np.stack(steps[k]))[:, None]
            # each stream at its config's size: the sample frame resized (TUM-VI's 512x512)
            return [torch.from_numpy(im if (im.shape[1], im.shape[0]) == (c.image_width, c.image_height) else
                                     cv2.resize(im, (c.image_width, c.image_height), interpolation=cv2.INTER_AREA))
                    for im, c in zip(steps[k], per)]

        batches_in = {lab: [inputs(per, k) for k in range(n_total)] for lab, (_, per) in runs.items()}
        for lab, (tr, _) in runs.items():
            for k in range(n_warm):
                tr.track(batches_in[lab][k], [stamps[k]] * B)
        best = {lab: float("inf") for lab in runs}
        for r in range(repeats):
            win = range(n_warm + r * n_meas, n_warm + (r + 1) * n_meas)
            for lab, (tr, _) in runs.items():
                t0 = time.perf_counter()
                for k in win:
                    tr.track(batches_in[lab][k], [stamps[k]] * B)
                best[lab] = min(best[lab], time.perf_counter() - t0)
        ms = {lab: t / (n_meas * B) * 1e3 for lab, t in best.items()}
        row = {"B": B, "ms_per_stream_frame": ms, "groups": {lab: len(tr.groups) for lab, (tr, _) in runs.items()},
               "ratio_vs_homogeneous": {lab: ms[lab] / ms["homogeneous"] for lab in ms if lab != "homogeneous"}}
        rows.append(row)
        print(f"  B={B}: " + ", ".join(f"{lab}: {v:.2f} ms ({len(runs[lab][0].groups)} groups)" for lab, v in ms.items()),
              flush=True)
    return {"machine": machine_description(), "threads": 1, "rows": rows}


def rig_markdown(res) -> str:
    lines = [f"Machine: {res['machine']}; 1 thread; the fastest of 5 windows of 4 steps, the batches' windows "
             "alternating in one process (`python benchmarks/bench_pipeline.py --rig`).", "",
             "| B | homogeneous ms/stream-frame | " + " | ".join(f"{lab}: ms (groups), × homogeneous" for lab in RIG_BATCHES)
             + " |", "|---|---|" + "---|" * len(RIG_BATCHES)]
    for r in res["rows"]:
        ms = r["ms_per_stream_frame"]
        cells = [f"{ms[lab]:.2f} ({r['groups'][lab]}), {r['ratio_vs_homogeneous'][lab]:.2f}×" for lab in RIG_BATCHES]
        lines.append(f"| {r['B']} | {ms['homogeneous']:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _target(row) -> str:
    if "ratio" not in row:
        return ""
    if row["device"] == "cuda":
        if row["B"] != 64:
            return ""
        ok = 1.0 / row["ratio"] >= TARGETS["gpu_b64_speedup"]
        return f"{'met' if ok else 'missed'} (≥ {TARGETS['gpu_b64_speedup']:.0f}× OpenCV)"
    if row["B"] == 1:
        return f"{'met' if row['ratio'] <= TARGETS['cpu_b1'] else 'missed'} (≤ {TARGETS['cpu_b1']}×)"
    if row["B"] >= 16:
        return f"{'met' if row['ratio'] <= TARGETS['cpu_b16plus'] else 'missed'} (≤ {TARGETS['cpu_b16plus']}×)"
    return "(no target)"


def markdown(rows, machine: str) -> str:
    lines = [
        f"Machine: {machine}",
        "",
        "Each side: the fastest of 5 (B = 64: 3) windows of consecutive steps after 4 warm-up steps, the two"
        " sides' windows alternating (peak RSS includes the OpenCV trackers).",
        "",
        "| device | B | threads | mode | torch ms/stream-frame | OpenCV ms/stream-frame | ratio | target | peak RSS MiB |"
        " stages ms/stream-frame (front = clahe + pyramid + lk on the CPU, clahe, pyramid, lk, ransac, mask, detection, undistort) |"
        " kernels / views / syncs per step |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['device']} | {r['B']} | {r['threads']} | {'compile' if r['compiled'] else 'eager'} |"
                         f" failed: {r['error']} | | | | | |")
            continue
        st = r["stages_ms_per_stream_frame"]
        stages = ", ".join(f"{st.get(k, 0.0):.1f}" for k in
                           ("front", "clahe", "pyramid", "lk", "ransac", "mask", "detection", "undistort"))
        cv = f"{r['opencv_ms_per_stream_frame']:.2f}" if "opencv_ms_per_stream_frame" in r else "-"
        ratio = f"{r['ratio']:.2f}" if "ratio" in r else "-"
        counts = (f"{r['kernels_per_step']:.0f} / {r['views_per_step']:.0f} / {r['syncs_per_step']:.1f}"
                  if "kernels_per_step" in r else "-")
        lines.append(
            f"| {r['device']} | {r['B']} | {r['threads']} | {_mode(r)} | "
            f"{r['torch_ms_per_stream_frame']:.2f} | {cv} | {ratio} | {_target(r)} | {r['peak_rss_mib']:.0f} | {stages} |"
            f" {counts} |"
        )
    lines += ["", "Mode: eager = the default path of the device (CPU: tuned, early exits; CUDA: capturable),"
              " capturable = `capturable=True` (shape-static, no host syncs: the CUDA path, here measured on the"
              " CPU), compile = `FeatureTracker.compile()`. Kernels / views / syncs: aten ops per step counted with"
              " `torch_frontend.testing.dispatch_count.OpCounter` (the launches and host waits the same ops cost on"
              " a GPU), from the input checks on: the step's two uploads (images, timestamps) are in the sync count."]
    return "\n".join(lines) + "\n"


def _mode(r) -> str:
    m = "compile" if r["compiled"] else "eager"
    if r.get("capturable") and r["device"] == "cpu":
        m += ", capturable"
    return m


def plot(rows, path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    for dev in sorted({r["device"] for r in rows}):
        for th in sorted({r["threads"] for r in rows}):
            sel = [r for r in rows if r["device"] == dev and r["threads"] == th and not r["compiled"] and "error" not in r]
            if not sel:
                continue
            ax.plot([r["B"] for r in sel], [r["torch_ms_per_stream_frame"] for r in sel], "o-",
                    label=f"torch-frontend {dev}, {th} thr")
            cvs = [r for r in sel if "opencv_ms_per_stream_frame" in r]
            if cvs and dev == "cpu":
                ax.plot([r["B"] for r in cvs], [r["opencv_ms_per_stream_frame"] for r in cvs], "s--",
                        label=f"OpenCV loop, {th} thr")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("streams B")
    ax.set_ylabel("ms per stream-frame")
    ax.set_title("VINS front end: time per stream-frame vs batch size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".png")
    os.close(fd)
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)


def machine_description() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = f", GPU {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    return f"{cpu}, {os.cpu_count()} cores{gpu}; torch {torch.__version__}, Python {platform.python_version()}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="B 1 and 4, 1 thread only")
    ap.add_argument("--compile", action="store_true", help="add torch.compile rows")
    ap.add_argument("--capturable", action="store_true",
                    help="add CPU rows with capturable=True (the CUDA code path's launch and sync counts)")
    ap.add_argument("--batches", type=int, nargs="*", default=None)
    ap.add_argument("--threads", type=int, nargs="*", default=None)
    ap.add_argument("--device", nargs="*", default=None)
    ap.add_argument("--profile", type=int, default=None, metavar="B",
                    help="profile the tracker at B streams (1 thread) instead of the table")
    ap.add_argument("--out-name", default="pipeline",
                    help="results/<name>.json and .md (default pipeline; benchmarks/gpu.sh: pipeline_cuda)")
    ap.add_argument("--rig", action="store_true",
                    help="per-stream configs: mixed batches vs a homogeneous one (results/pipeline_rig.*)")
    ap.add_argument("--one", type=str, default=None, help=argparse.SUPPRESS)  # internal: run one config
    args = ap.parse_args(argv)
    if args.rig:
        res = rig(tuple(args.batches or (4, 8, 16)))
        md = rig_markdown(res)
        print(md)
        sys.path.insert(0, str(HERE))
        from _common import write_atomic, write_json_atomic

        RESULTS.mkdir(parents=True, exist_ok=True)
        write_json_atomic(RESULTS / "pipeline_rig.json", res)
        write_atomic(RESULTS / "pipeline_rig.md", md.encode())
        return 0
    if args.profile is not None:
        md = profile(args.profile)
        print(md)
        sys.path.insert(0, str(HERE))
        from _common import write_atomic

        RESULTS.mkdir(parents=True, exist_ok=True)
        write_atomic(RESULTS / "pipeline_profile.md", md.encode())
        return 0

    if args.one:
        spec = json.loads(args.one)
        try:
            res = run_one(**spec)
        except Exception as exc:  # reported in the table, not fatal for the whole benchmark
            res = {**{k: spec[k] for k in ("B", "threads", "device", "compiled")}, "error": f"{type(exc).__name__}: {exc}"}
        print("RESULT " + json.dumps(res))
        return 0

    import torch

    batches = args.batches or ([1, 4] if args.quick else [1, 4, 16, 64])
    threads = args.threads or ([1] if args.quick else [1, 2])
    devices = args.device or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    modes = [(False, None)] + ([(True, None)] if args.compile else []) + ([(False, True)] if args.capturable else [])
    rows = []
    for dev in devices:
        for th in threads if dev == "cpu" else [threads[0]]:
            for compiled, capturable in modes:
                # compile rows: compiling costs ~1 min per process on CPU, so only threads 1 and two sizes;
                # capturable rows are for their counts (and the CPU time of the CUDA path): 1 thread
                if (compiled or capturable) and (th != threads[0]):
                    continue
                if capturable and dev != "cpu":
                    continue  # the device's default already is the capturable path
                # compile and capturable rows at two sizes (capturable: the launch counts do not depend on B)
                for B in ([b for b in batches if b in (1, 16)] or batches[:1]) if compiled or capturable else batches:
                    n_meas = max(2, min(8, 64 // B)) if dev == "cpu" else 8  # even: see run_one
                    spec = dict(B=B, threads=th, device=dev, compiled=compiled, n_warm=4, n_meas=n_meas,
                                skip_cv=(dev != "cpu" and B not in (1, 64)) or bool(capturable),
                                repeats=5 if B <= 16 else 3, capturable=capturable)
                    t0 = time.time()
                    out = subprocess.run([sys.executable, __file__, "--one", json.dumps(spec)],
                                         capture_output=True, text=True, timeout=900)
                    line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
                    if not line:
                        res = {**{k: spec[k] for k in ("B", "threads", "device", "compiled")},
                               "error": (out.stderr.strip().splitlines() or ["no output"])[-1]}
                    else:
                        res = json.loads(line[-1][7:])
                    rows.append(res)
                    print(f"  {dev} B={B} threads={th} {'compile' if compiled else 'eager'}"
                          f"{', capturable' if capturable else ''}: "
                          + (res.get("error") or f"{res['torch_ms_per_stream_frame']:.2f} ms/stream-frame"
                             + (f", OpenCV {res['opencv_ms_per_stream_frame']:.2f}, ratio {res['ratio']:.2f}"
                                if "ratio" in res else ""))
                          + f"  [{time.time() - t0:.0f} s]", flush=True)
    machine = machine_description()
    md = markdown(rows, machine)
    print()
    print(md)
    RESULTS.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(HERE))
    from _common import write_atomic, write_json_atomic

    write_json_atomic(RESULTS / f"{args.out_name}.json", {"machine": machine, "targets": TARGETS, "rows": rows})
    write_atomic(RESULTS / f"{args.out_name}.md", md.encode())
    plot(rows, RESULTS / f"{args.out_name}_scaling.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
