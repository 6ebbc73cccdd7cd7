"""Benchmark: pose-graph optimisation (VINS optimize4DoF / loop_fusion optimize6DoF), 5 iterations,
per linear-solver option.

* Graph: a closed loop flown twice with yaw (+ roll/pitch for 6-DoF) drift in the vio poses, N
  keyframes, sequential edges to the previous 4 (VINS pattern), ``max(2, N // 50)`` loop edges
  between the two laps (true relative poses), node 0 fixed; N = 100, 1,000, 5,000.
* Solvers: ``banded`` (torch block cyclic reduction + Woodbury for the loop edges; pure torch),
  ``lapack_banded`` (scipy solveh_banded + the same Woodbury), ``splu`` (scipy.sparse SuperLU of
  the whole normal matrix), ``dense`` (torch Cholesky of the whole matrix; CUDA's default, skipped
  on CPU above ``--dense-max`` keyframes). ``auto`` is what the library picks.
* Reported: median ms of ``--repeat`` calls of ``optimize_4dof`` / ``optimize_6dof(iters=5)``
  (inputs prepared, no autograd), the final cost, and the peak resident-memory increase during one
  call (CUDA: ``max_memory_allocated``). On CPU the memory is the ``VmHWM`` increase of one call in a
  fresh process (it includes one-time library set-up, e.g. importing scipy).

Prints a markdown table and writes ``benchmarks/results/pose_graph.json`` (temp file + rename).

Run: ``.venv/bin/python benchmarks/bench_pose_graph.py [--device cpu] [--sizes 100,1000,5000]``
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torch_frontend.geometry import R_to_quat, R_to_ypr, ypr_to_R  # noqa: E402
from torch_frontend.loop import optimize as opt  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, apply_threads, sync, write_json_atomic  # noqa: E402


def drifting_loop(N, n_loops, yaw_drift=0.02, rp_drift=0.0, seed=0):
    """Two laps of a 20 m circle; vio = integrated relative motion + drift (as in the tests)."""
    rng = np.random.default_rng(seed)
    th = 4 * math.pi * np.arange(N) / N
    P = np.stack([20 * np.cos(th), 20 * np.sin(th), np.sin(3 * th)], -1)
    ypr = np.stack([np.degrees(th) + 90.0, 3 * np.sin(5 * th), 2 * np.cos(4 * th)], -1)
    R = ypr_to_R(torch.from_numpy(ypr)).numpy()
    Pv, Rv = P.copy(), R.copy()
    drift = np.stack([yaw_drift + rng.normal(0, 0.01, N), rp_drift * rng.normal(size=N),
                      rp_drift * rng.normal(size=N)], -1)
    Rd = ypr_to_R(torch.from_numpy(drift)).numpy()
    for k in range(1, N):
        Rv[k] = Rd[k] @ Rv[k - 1] @ (R[k - 1].T @ R[k])
        Pv[k] = Pv[k - 1] + Rv[k - 1] @ (R[k - 1].T @ (P[k] - P[k - 1]) + rng.normal(0, 0.01, 3))
    per = N // 2
    b = np.linspace(per + per // 10, N - 1, n_loops).astype(np.int64)
    a = b - per
    Pv, Rv, R_t = torch.from_numpy(Pv), torch.from_numpy(Rv), torch.from_numpy(R)
    si, sj = opt.sequential_edges(torch.zeros(N, dtype=torch.int64), 4)
    li, lj = torch.from_numpy(a), torch.from_numpy(b)
    i, j = torch.cat([si, li]), torch.cat([sj, lj])
    loop = torch.cat([torch.zeros(len(si), dtype=torch.bool), torch.ones(len(li), dtype=torch.bool)])
    fixed = torch.zeros(N, dtype=torch.bool)
    fixed[0] = True
    lt = torch.from_numpy(np.einsum("eji,ej->ei", R[a], P[b] - P[a]))
    tms, yms = opt.measurements_4dof(Pv, Rv, si, sj)
    e = R_to_ypr(Rv)
    four = (Pv, e[:, 0], e[:, 1], e[:, 2], i, j, torch.cat([tms, lt]),
            torch.cat([yms, torch.from_numpy(ypr[b, 0] - ypr[a, 0])]), loop, fixed)
    q = R_to_quat(Rv)
    tms6, qms6 = opt.measurements_6dof(Pv, q, si, sj)
    lq = opt._qmul(opt._qconj(R_to_quat(R_t[li])), R_to_quat(R_t[lj]))
    six = (Pv, q, i, j, torch.cat([tms6, lt]), torch.cat([qms6, lq]), loop, fixed)
    return four, six




def _peak_rss_subprocess(mode, N, solver, dtype):
    """Peak resident-memory increase of one call, measured in a fresh process (``VmHWM`` after
    building the inputs vs after one ``iters=5`` call; includes one-time library set-up). Not
    ``ru_maxrss``: Linux carries the parent's value into a forked/exec'd child."""
    import json
    import subprocess

    code = (
        "import sys, torch; torch.set_num_threads(1)\n"
        "def hwm():\n"
        "    return [int(x.split()[1]) for x in open('/proc/self/status') if x.startswith('VmHWM:')][0]\n"
        f"sys.path.insert(0, {str(Path(__file__).resolve().parent)!r}); sys.path.insert(0, {str(REPO)!r})\n"
        "from bench_pose_graph import drifting_loop; from torch_frontend.loop import optimize as opt\n"
        f"four, six = drifting_loop({N}, max(2, {N} // 50), **({{}} if {mode!r} == '4dof' else "
        "dict(yaw_drift=0.01, rp_drift=0.005)))\n"
        f"prob = [a.to(torch.{dtype}) if a.is_floating_point() else a for a in (four if {mode!r} == '4dof' else six)]\n"
        "b = hwm()\n"
        f"(opt.optimize_4dof if {mode!r} == '4dof' else opt.optimize_6dof)(*prob, iters=5, solver={solver!r})\n"
        "print((hwm() - b) / 1024)\n")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])
    except Exception as exc:  # noqa: BLE001 (a benchmark row without memory is still useful)
        print(f"memory measurement failed: {exc!r}", file=sys.stderr)
        return None


def run_case(fn, args, solver, repeat, device, mem_key=None):
    fn(*args, iters=5, solver=solver)  # warm-up
    ts = []
    for _ in range(repeat):
        sync(device)
        t0 = time.perf_counter()
        out = fn(*args, iters=5, solver=solver, return_info=True)
        sync(device)
        ts.append((time.perf_counter() - t0) * 1e3)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        fn(*args, iters=5, solver=solver)
        peak = torch.cuda.max_memory_allocated() - base
        peak = peak / 2 ** 20
    else:
        peak = None if mem_key is None else _peak_rss_subprocess(*mem_key)
    info = out[-1]
    return statistics.median(ts), info, peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="100,1000,5000")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: library default)")
    ap.add_argument("--dense-max", type=int, default=1000, help="largest N for the dense solver on CPU")
    ap.add_argument("--solvers", default="auto,banded,lapack_banded,splu,dense")
    ap.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    ap.add_argument("--no-mem", dest="mem", action="store_false",
                    help="skip the per-case peak-memory measurement (one fresh process per case on CPU)")
    ap.add_argument("--out", default=str(RESULTS / "pose_graph.json"))
    args = ap.parse_args()
    apply_threads(args.threads)
    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    have_scipy = importlib.util.find_spec("scipy") is not None
    rows = []
    for N in [int(s) for s in args.sizes.split(",")]:
        n_loops = max(2, N // 50)
        four, _ = drifting_loop(N, n_loops)
        _, six = drifting_loop(N, n_loops, yaw_drift=0.01, rp_drift=0.005)
        for mode, fn, prob in (("4dof", opt.optimize_4dof, four), ("6dof", opt.optimize_6dof, six)):
            prob = tuple(a.to(device, dtype) if a.is_floating_point() else a.to(device) for a in prob)
            for solver in args.solvers.split(","):
                if solver in ("lapack_banded", "splu") and not have_scipy:
                    continue
                if solver == "dense" and device.type == "cpu" and N > args.dense_max:
                    continue
                if solver in ("lapack_banded", "splu") and device.type != "cpu":
                    continue
                mem_key = (mode, N, solver, args.dtype) if args.mem else None
                ms, info, peak = run_case(fn, prob, solver, args.repeat, device, mem_key)
                rows.append(dict(mode=mode, N=N, loops=n_loops, edges=int(prob[-2].numel()),
                                 solver=solver, picked=info["solver"], ms=ms, iterations=info["iterations"],
                                 cost_initial=info["cost_initial"], cost_final=info["cost_final"],
                                 peak_mem_mb=peak))
                print(f"{mode} N={N} {solver}: {ms:.1f} ms", file=sys.stderr)
    print(f"\n### pose graph, 5 iterations ({device.type}, {args.dtype}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, median of {args.repeat})\n")
    print("| mode | N | loops | solver | ms | iterations | cost initial → final | peak mem MB |")
    print("|---|---:|---:|---|---:|---:|---|---:|")
    for r in rows:
        solver = r["solver"] if r["solver"] != "auto" else f"auto ({r['picked']})"
        mem = "n/a" if r["peak_mem_mb"] is None else f"{r['peak_mem_mb']:.1f}"
        print(f"| {r['mode']} | {r['N']} | {r['loops']} | {solver} | {r['ms']:.1f} | {r['iterations']} | "
              f"{r['cost_initial']:.4g} → {r['cost_final']:.4g} | {mem} |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out, dict(benchmark="pose_graph", device=device.type, dtype=args.dtype, torch=torch.__version__,
                                threads=torch.get_num_threads(), machine=platform.machine(), rows=rows))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
