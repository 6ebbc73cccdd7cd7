"""Modelled GPU figures of the capturable step, before -> after, as ``benchmarks/results/roofline.md``.

The figures come from ``../shared/tools/cuda_sim/roofline.py`` (a simulated CUDA device that records
the bytes and FLOPs of every kernel of a tracker step and models its time on an H100/H200, eager and
CUDA graph; see that tool's README). They are *modelled*, not measured: a real GPU run
(``benchmarks/gpu.sh``) puts its measured times beside them.

    # 1. the figures of a tree (run from that tree's root; the tool imports the package from PYTHONPATH)
    PYTHONPATH=$PWD .venv/bin/python benchmarks/roofline_report.py run --B 1 16 64 256 --out after.json
    # 2. the report from two runs (before: an older tree's run of step 1)
    .venv/bin/python benchmarks/roofline_report.py render --before before.json --after after.json
    # 3. on a GPU (benchmarks/gpu.sh): measured bench_pipeline.py times beside the modelled ones
    .venv/bin/python benchmarks/roofline_report.py beside --measured benchmarks/results/pipeline_cuda.json \
        --modelled modelled.json --out benchmarks/results/pipeline_cuda_vs_model.md

``run`` passes ``--tracker-kwargs '{"capturable": true}'`` and an even number of measured steps (the
mono clock publishes every other EuRoC frame, so the means cover published and unpublished steps
alike). Several ``--json`` files of one tree (e.g. B = 256 run apart for memory) can be given to
``render`` as ``--after a.json b.json``: their B's are merged.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO.parent / "shared" / "tools" / "cuda_sim" / "roofline.py"
OUT = REPO / "benchmarks" / "results" / "roofline.md"
#: the device and mode the tables report (the issue's targets are H100 graph-mode figures)
DEVICE = "H100"
#: OpenCV's time per frame on one core (ms), as the tool's OPENCV_MS
OPENCV_MS = 6.0
#: measured steps after the warm-up: even, so published and unpublished steps weigh alike
STEPS, WARMUP = 4, 8
MB, GB, GIB = 1e6, 1e9, 2.0 ** 30


def run(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(prog="roofline_report.py run")
    ap.add_argument("--B", type=int, nargs="+", default=[1, 16, 64, 256])
    ap.add_argument("--tool", default=str(TOOL), help="roofline.py (default: ../shared/tools/cuda_sim/roofline.py)")
    ap.add_argument("--steps", type=int, default=STEPS)
    ap.add_argument("--warmup", type=int, default=WARMUP)
    ap.add_argument("--out", required=True, help="JSON to write")
    ap.add_argument("--keep-inplace-cycle", action="store_true",
                    help="run the tool as it is (its peak memory then keeps every in-place op's target alive "
                         "until Python's next garbage collection; see _tool)")
    a = ap.parse_args(argv)
    if not Path(a.tool).is_file():
        print(f"roofline_report.py: {a.tool} not found (the cuda_sim tools live in ../shared/tools/cuda_sim)",
              file=sys.stderr)
        return 2
    tool = [a.tool] if a.keep_inplace_cycle else [str(Path(__file__).resolve()), "_tool", a.tool]
    cmd = [sys.executable, *tool, "--B", *map(str, a.B), "--steps", str(a.steps), "--warmup", str(a.warmup),
           "--tracker-kwargs", '{"capturable": true}', "--json", a.out]
    env = dict(os.environ, PYTHONPATH=os.environ.get("PYTHONPATH", str(Path.cwd())))
    return subprocess.call(cmd, env=env)


def _write_atomic(path, data: bytes) -> None:
    """The benchmarks' temp + rename writer (``_common.write_atomic``): whole or not at all."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import write_atomic

    write_atomic(path, data)


def _load(paths: List[str]) -> Dict[int, dict]:
    res: Dict[int, dict] = {}
    for p in paths:
        with open(p) as f:
            d = json.load(f)
        for b, fig in d["results"].items():
            res[int(b)] = dict(fig, warmup=d.get("warmup"))
    return res


def _summary_row(fig: dict) -> Dict[str, float]:
    t, B = fig["totals"], fig["B"]
    graph_ms = t[f"{DEVICE}:graph"] * 1e3
    return dict(kernels=t["kernels"], gb=(t["read"] + t["write"]) / GB, mb_stream=(t["read"] + t["write"]) / MB / B,
                graph_ms=graph_ms, frame_ms=graph_ms / B, x_opencv=OPENCV_MS / (graph_ms / B),
                eager_ms=t[f"{DEVICE}:eager"] * 1e3, peak_gib=t["peak_live_bytes"] / GIB)


def _stages(fig: dict) -> Dict[str, Dict[str, float]]:
    B = fig["B"]
    return {name: dict(kernels=r["calls"], mb_stream=(r["read"] + r["write"]) / MB / B,
                       graph_ms=r[f"{DEVICE}:graph"] * 1e3)
            for name, r in fig["rows"].items()}


def _arrow(a, b, fmt: str) -> str:
    if a is None:
        return format(b, fmt)
    if b is None:
        return format(a, fmt) + " → –"
    return f"{format(a, fmt)} → {format(b, fmt)}"


def render(argv: List[str]) -> int:
    ap = argparse.ArgumentParser(prog="roofline_report.py render")
    ap.add_argument("--before", nargs="+", required=True)
    ap.add_argument("--after", nargs="+", required=True)
    ap.add_argument("--before-label", default="before")
    ap.add_argument("--after-label", default="after")
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args(argv)
    before, after = _load(a.before), _load(a.after)
    Bs = sorted(set(before) | set(after))
    runs = sorted({(f.get("steps"), f.get("warmup")) for f in after.values()}, key=str)
    means = "; ".join(f"{st} steps after {wu} warm-up steps" for st, wu in runs)
    lines = [
        "# Modelled GPU figures of the capturable step (roofline.py)",
        "",
        "**Modelled, not measured**: `../shared/tools/cuda_sim/roofline.py` runs a mono EuRoC step",
        "(`configs/euroc.yaml`, the package's sample frames with a moving warp per stream) on a simulated CUDA",
        "device, records the bytes and FLOPs of every kernel, and models each as `max(launch floor, bytes /",
        "bandwidth, FLOPs / peak)`; the figures below are the " + DEVICE + " in CUDA-graph mode (2.5 µs per node),",
        f"means per step ({a.after_label}: {means}; an even count weighs published and unpublished steps alike). "
        "`benchmarks/gpu.sh` on a real GPU",
        "prints measured times beside the same model. Made by",
        "`benchmarks/roofline_report.py` (its docstring has the commands).",
        "",
        f"Columns: kernels per step; GB moved per step (read + written); MB per stream per step; {DEVICE} graph",
        "ms per step and per stream-frame; speed against OpenCV on one core (6 ms per frame); the peak of live",
        "device memory (the simulated tensors' storages, each freed at its last reference as on a GPU: `run`",
        "drops the tool's hold on in-place ops' inputs, see `_tool`; a real run reserves more).",
        "The step's GPU targets, where each stands and the floor of tensor ops that stops it:",
        "[docs/benchmarks.md](../../docs/benchmarks.md#the-gpu-step-modelled-targets-and-the-floors-of-tensor-ops).",
        "",
        f"{a.before_label} → {a.after_label}:",
        "",
        "| B | kernels | GB / step | MB / stream | ms / step | ms / stream-frame | × OpenCV | peak GiB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for B in Bs:
        s0 = _summary_row(before[B]) if B in before else {}
        s1 = _summary_row(after[B]) if B in after else {}
        g = lambda k, fmt, s0=s0, s1=s1: _arrow(s0.get(k), s1.get(k), fmt)  # noqa: E731
        lines.append(f"| {B} | {g('kernels', ',.0f')} | {g('gb', '.2f')} | {g('mb_stream', ',.0f')} | "
                     f"{g('graph_ms', '.2f')} | {g('frame_ms', '.3f')} | {g('x_opencv', '.1f')} | {g('peak_gib', '.2f')} |")
    fused = [(B, after[B]["totals"]) for B in Bs if B in after and after[B]["totals"].get("fused_kernels")]
    if fused:
        lines += ["", f"**Lower bounds.** The {a.after_label} step's fused custom ops (`torch_frontend::pyramid`, `::lk`,",
                  "`::clahe`, `::good_features`, `::set_mask`, `::ransac_score`, `::pinhole_lift`: one kernel each",
                  "on the simulated device, docs/kernels.md) are modelled as their inputs read and outputs written",
                  "once, with no compute and no latency (the tool's rule for custom ops): a **lower bound** of their",
                  "time, and so of every figure that includes them, until a GPU measures them (`benchmarks/gpu.sh`).",
                  "On a real GPU some are several launches: CLAHE and setMask two Triton kernels each, detection",
                  "two Triton kernels plus its capturable tensor selection (about 508 launches on a detecting step,",
                  "inside the op's CUDA implementation), the LK one to three. Their share, per step:", "",
                  "| B | fused kernels | MB | graph ms (of the step's) |", "|---|---|---|---|"]
        for B, t in fused:
            lines.append(f"| {B} | {t['fused_kernels']:,.0f} | {t['fused_bytes'] / MB:,.1f} | "
                         f"{t.get(f'{DEVICE}:graph:fused', 0) * 1e3:.3f} (of {t[f'{DEVICE}:graph'] * 1e3:.2f}) |")
    for B in Bs:
        st0 = _stages(before[B]) if B in before else {}
        st1 = _stages(after[B]) if B in after else {}
        names = sorted(set(st0) | set(st1), key=lambda n: -(st0.get(n) or st1.get(n))["mb_stream"])
        lines += ["", f"## B = {B}, per stage ({a.before_label} → {a.after_label})", "",
                  "| stage | kernels | MB / stream | graph ms / step |", "|---|---|---|---|"]
        for n in names:
            r0, r1 = st0.get(n, {}), st1.get(n, {})
            lines.append(f"| {n} | {_arrow(r0.get('kernels'), r1.get('kernels'), ',.0f')} | "
                         f"{_arrow(r0.get('mb_stream'), r1.get('mb_stream'), ',.1f')} | "
                         f"{_arrow(r0.get('graph_ms'), r1.get('graph_ms'), '.2f')} |")
        big = after.get(B, before.get(B))["biggest_tensor"]
        if big:
            lines.append(f"\nLargest tensor ({a.after_label if B in after else a.before_label}): "
                         f"{big[0] / MB:,.1f} MB, {big[1][4]}{list(big[1][3])} from `{big[1][1]}` at `{big[1][2]}`.")
    text = "\n".join(lines) + "\n"
    _write_atomic(a.out, text.encode())
    print(text)
    print(f"written {a.out}")
    return 0


def beside(argv: List[str]) -> int:
    """Measured (``bench_pipeline.py --device cuda`` JSON) beside modelled (``run``'s JSON), per B."""
    ap = argparse.ArgumentParser(prog="roofline_report.py beside")
    ap.add_argument("--measured", required=True, help="bench_pipeline.py's JSON (benchmarks/gpu.sh: pipeline_cuda.json)")
    ap.add_argument("--modelled", nargs="+", required=True, help="run's JSON")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    with open(a.measured) as f:
        measured = json.load(f)
    model = _load(a.modelled)
    lines = ["# Measured beside modelled (capturable step, ms per step)", "",
             f"Measured: `{Path(a.measured).name}` ({measured.get('machine', '?')}). Modelled: roofline.py "
             "(simulated device; eager = 5 µs per op, graph = 2.5 µs per node; see roofline.md).", "",
             "| B | compiled | measured ms / step | H100 eager | H100 graph | H200 eager | H200 graph |",
             "|---|---|---|---|---|---|---|"]
    for r in measured.get("rows", []):
        if r.get("device") != "cuda" or "torch_ms_per_step" not in r:
            continue
        t = model.get(int(r["B"]), {}).get("totals")
        m = (lambda k, t=t: f"{t[k] * 1e3:.2f}" if t else "–")  # noqa: E731
        lines.append(f"| {r['B']} | {'yes' if r.get('compiled') else 'no'} | {r['torch_ms_per_step']:.2f} | "
                     f"{m('H100:eager')} | {m('H100:graph')} | {m('H200:eager')} | {m('H200:graph')} |")
    _write_atomic(a.out, ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))
    return 0


#: the one line of ``simcuda._handle`` that :func:`_tool` rewrites
_HANDLE_RETURN = "    return wrap(out)\n"


def _tool(argv: List[str]) -> int:
    """``_tool ROOFLINE_PY ARGS...``: roofline.py with one fix to its live-memory figure.

    ``simcuda._handle`` wraps an op's results with a nested function that calls itself (a
    reference cycle) and whose closure holds ``orig``, the in-place or ``out=`` op's input
    tensors: every tensor an op modified in place stays alive until Python's cyclic garbage
    collector runs, which a real CUDA tensor does not (its storage is freed at its last
    reference). With image-sized in-place updates in a step, the tool's peak overstates the real
    one (4e4701b, B = 64: 2.98 GiB as is, 2.34 with the fix). The fix drops ``orig`` when
    ``_handle`` returns; kernels, bytes and times are unchanged (they do not depend on it)."""
    if not argv:
        print("usage: roofline_report.py _tool ROOFLINE_PY [roofline.py arguments]", file=sys.stderr)
        return 2
    import inspect

    tool = Path(argv[0]).resolve()
    sys.path.insert(0, str(tool.parent))
    import simcuda  # the tool's own modules, from its folder

    src = inspect.getsource(simcuda._handle)
    if src.count(_HANDLE_RETURN) != 1:
        print(f"roofline_report.py: {tool.parent / 'simcuda.py'} changed (no single {_HANDLE_RETURN.strip()!r}); "
              "run with --keep-inplace-cycle", file=sys.stderr)
        return 2
    src = src.replace(_HANDLE_RETURN, "    try:\n        return wrap(out)\n    finally:\n        orig = None\n")
    exec(compile(src, simcuda.__file__, "exec"), simcuda.__dict__)
    import roofline

    sys.argv = [str(tool)] + argv[1:]
    return roofline.main(argv[1:]) or 0


COMMANDS = {"run": run, "render": render, "beside": beside, "_tool": _tool}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        print(__doc__)
        return 2
    return COMMANDS[argv[0]](argv[1:])


if __name__ == "__main__":
    sys.exit(main())
