"""Pyramidal LK benchmark: ``track_lk`` vs ``cv2.calcOpticalFlowPyrLK`` on 752x480 EuRoC frames.

Cases: N = 150 and 1000 points (``goodFeaturesToTrack`` corners of the previous frame), B = 1, 8, 64
streams (consecutive-frame pairs of the sample sequence, reused cyclically), win 21, maxLevel 3,
30 iterations / eps 0.01, uint8 input (fixed-point emulation, OpenCV's default path). Both sides
build their pyramids inside the call. OpenCV has no batch: it runs the B pairs one after the
other. ``torch`` runs eager (and, with ``--compile``, with ``torch.compile`` of the per-iteration
kernel, ``track_lk(..., compile_step=True)``; a compile failure is caught and reported in the table).
Two extra row groups: ``pyr`` = LK on pyramids built beforehand (how the tracker calls it: the
previous frame's pyramid and its padded levels are kept, the next one's levels are padded inside
the call; OpenCV's column is its usual call, which builds them, as its Python binding takes no
pyramids), and ``build`` = ``build_pyramid`` (4 levels, padded by win + 1 as the LK reads them; no
derivatives: the LK takes them from its windows) vs ``cv2.buildOpticalFlowPyramid`` (4 levels,
with derivatives).

Prints a markdown table (median ms, ratio torch / OpenCV: < 1 means torch is faster) and writes
``benchmarks/results/lk.json`` (temp file + rename). Runtime: a few minutes on 2 cores
(``--quick`` skips B = 64 with N = 1000). Both libraries use ``--threads`` intra-op threads
(default 1).

Usage: ``python benchmarks/bench_lk.py [--device cpu|cuda] [--repeat N] [--threads T] [--compile] [--quick]``
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torch_frontend.lk import track_lk  # noqa: E402
from torch_frontend.pyramid import build_pyramid  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, kernel_bench_parser, sync, write_json_atomic  # noqa: E402

FRAMES = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)




def _time(fn, repeat, device, budget_s=20.0):
    """Median ms over ``repeat`` runs after one warm-up; fewer runs when a call is slow."""
    t0 = time.perf_counter()
    fn()  # warm-up (and compilation)
    sync(device)
    first = time.perf_counter() - t0
    n = max(1, min(repeat, int(budget_s / max(first, 1e-6))))
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        sync(device)
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts), n


def main(argv=None):
    ap = kernel_bench_parser(__doc__, "lk.json", repeat=5)
    ap.add_argument("--compile", action="store_true", help="also time torch.compile of the step kernel (slow)")
    ap.add_argument("--no-compile", action="store_true", help=argparse.SUPPRESS)  # old flag: the default now
    ap.add_argument("--quick", action="store_true", help="skip B=64 x N=1000")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    apply_threads(args.threads)

    paths = sorted(FRAMES.glob("*.png"))
    frames = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths]
    npairs = len(frames) - 1
    pts_by_n = {}
    for n in (150, 1000):
        per = []
        for i in range(npairs):
            c = cv2.goodFeaturesToTrack(frames[i], n, 0.001, 5).reshape(-1, 2)
            c = np.concatenate([c, c[: n - len(c)] + 0.5]) if len(c) < n else c  # pad to exactly n
            per.append(c[:n].astype(np.float32))
        pts_by_n[n] = per

    modes = ["eager"] + (["compile"] if args.compile and not args.no_compile else [])
    rows, notes = [], []
    for mode in modes:
        kw = dict(compile_step=mode == "compile")  # per call: the compiled iteration kernel
        for n in (150, 1000):
            for B in (1, 8, 64):
                if args.quick and B == 64 and n == 1000:
                    continue
                idx = [b % npairs for b in range(B)]
                prev = torch.from_numpy(np.stack([frames[i] for i in idx]))[:, None].to(device)
                nxt = torch.from_numpy(np.stack([frames[i + 1] for i in idx]))[:, None].to(device)
                pts = torch.from_numpy(np.stack([pts_by_n[n][i] for i in idx])).to(device)

                def run_cv(idx=idx, n=n):
                    for i in idx:
                        cv2.calcOpticalFlowPyrLK(frames[i], frames[i + 1], pts_by_n[n][i], None, winSize=(21, 21),
                                                 maxLevel=3, criteria=CRIT)

                row = {"mode": mode, "N": n, "B": B}
                try:
                    t_torch, reps = _time(lambda prev=prev, nxt=nxt, pts=pts, kw=kw: track_lk(prev, nxt, pts, **kw),
                                          args.repeat, device)
                    row.update(torch_ms=round(t_torch, 2), torch_reps=reps)
                except Exception as e:  # noqa: BLE001 - e.g. a compile failure at first call
                    row.update(torch_ms=None, error=f"{type(e).__name__}: {str(e).splitlines()[0][:200]}")
                    notes.append(f"{mode} N={n} B={B}: {row['error']}")
                    traceback.print_exc()
                t_cv, _ = _time(run_cv, args.repeat, torch.device("cpu"))
                row["opencv_ms"] = round(t_cv, 2)
                row["ratio"] = None if row["torch_ms"] is None else round(row["torch_ms"] / t_cv, 2)
                rows.append(row)
                print(row, flush=True)

    # tracker-style calls (pyramids built beforehand) and the pyramid build itself, N = 150
    n = 150
    for B in (1, 8):
        idx = [b % npairs for b in range(B)]
        prev = torch.from_numpy(np.stack([frames[i] for i in idx]))[:, None].to(device)
        nxt = torch.from_numpy(np.stack([frames[i + 1] for i in idx]))[:, None].to(device)
        pts = torch.from_numpy(np.stack([pts_by_n[n][i] for i in idx])).to(device)
        pa, pb = build_pyramid(prev, 3), build_pyramid(nxt, 3)
        def run_cv_pyr(idx=idx):  # the Python binding takes no pyramids: OpenCV builds them inside
            for i in idx:
                cv2.calcOpticalFlowPyrLK(frames[i], frames[i + 1], pts_by_n[n][i], None, winSize=(21, 21),
                                         maxLevel=3, criteria=CRIT)

        def run_cv_build(idx=idx):
            for i in idx:
                cv2.buildOpticalFlowPyramid(frames[i + 1], (21, 21), 3)

        def run_pyr(pa=pa, pb=pb, pts=pts):
            pb._padded.clear()  # as in the tracker: the previous pyramid's padded levels are kept, the next's are new
            return track_lk(pa, pb, pts)

        def run_build(nxt=nxt):  # what the tracker builds per frame: 4 levels, padded for LK (win 21)
            p = build_pyramid(nxt, 3, with_gradients=False)
            return [p.padded(level, 22, 22) for level in range(4)]

        for mode, f_t, f_cv in (("pyr", run_pyr, run_cv_pyr), ("build", run_build, run_cv_build)):
            t_torch, reps = _time(f_t, args.repeat, device)
            t_cv, _ = _time(f_cv, args.repeat, torch.device("cpu"))
            row = {"mode": mode, "N": n if mode == "pyr" else 0, "B": B, "torch_ms": round(t_torch, 2),
                   "torch_reps": reps, "opencv_ms": round(t_cv, 2), "ratio": round(t_torch / t_cv, 2)}
            rows.append(row)
            print(row, flush=True)

    print(f"\nPyramidal LK, 752x480, win 21, maxLevel 3, device {device}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads)\n")
    print("| mode | N | B | torch ms | OpenCV ms | ratio torch/OpenCV | torch ms / stream |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        t = "fail" if r["torch_ms"] is None else f"{r['torch_ms']:.1f}"
        ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}"
        per = "-" if r["torch_ms"] is None else f"{r['torch_ms'] / r['B']:.1f}"
        print(f"| {r['mode']} | {r['N']} | {r['B']} | {t} | {r['opencv_ms']:.1f} | {ratio} | {per} |")
    for note in notes:
        print(f"\nnote: {note}")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": str(device), "torch": torch.__version__, "opencv": cv2.__version__,
            "torch_threads": torch.get_num_threads(), "opencv_threads": cv2.getNumThreads(),
            "machine": platform.machine(), "size": [752, 480], "repeat": args.repeat,
            "params": {"win_size": 21, "max_level": 3, "max_iters": 30, "eps": 0.01, "input": "uint8"},
            "note": "OpenCV runs the B pairs sequentially; eager/compile rows build both pyramids inside the "
                    "call; 'pyr' rows track on pyramids built beforehand (the next one padded inside the call); "
                    "'build' rows build one 4-level pyramid per stream (torch: padded levels, no derivatives, "
                    "as the tracker; OpenCV: with derivatives)",
            "notes": notes}
    write_json_atomic(out, {"meta": meta, "rows": rows})
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
