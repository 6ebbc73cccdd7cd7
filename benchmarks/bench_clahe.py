"""CLAHE benchmark: the fused op (``torch_frontend::clahe``) vs the tensor CLAHE vs ``cv2.createCLAHE(3.0, (8, 8)).apply``.

Cases: B = 1 and 16 streams (``--batches``) of different 752x480 EuRoC frames (the sample sequence's
cam0, reused cyclically), VINS's CLAHE (clip 3.0, 8x8 tiles), uint8 in and out. OpenCV has no batch:
it runs the B images one after the other. The three are timed round-robin in one process (the same
machine load for each), on ``--threads`` intra-op threads (default 1) for torch and OpenCV alike,
after one warm-up call of each. The fused and tensor calls are the tracker's kernel call
(``equalize._clahe_impl`` with ``backend="fused"`` / ``"tensor"``: no input checks or layout work).

Prints a markdown table (median ms per call and per stream-frame, min ms, ratios of the medians: < 1
means the first is faster) and writes ``benchmarks/results/clahe.json`` (temp + rename). Numbers on
a shared machine are noisy: compare ratios from one run.

Usage: ``python benchmarks/bench_clahe.py [--device cpu|cuda] [--repeat N] [--threads T] [--batches 1 16]``
"""

from __future__ import annotations

import platform
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torch_frontend.equalize import _clahe_impl  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, kernel_bench_parser, sync, write_json_atomic  # noqa: E402

FRAMES = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"
CLIP, GRID = 3.0, (8, 8)


def _time_round_robin(fns: dict, repeat: int, device) -> dict:
    """``{name: (median ms, min ms)}`` of each function, called in turn ``repeat`` times after a warm-up."""
    for f in fns.values():
        f()
    sync(device)
    times = {k: [] for k in fns}
    for _ in range(repeat):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            sync(device)
            times[k].append((time.perf_counter() - t0) * 1e3)
    return {k: (statistics.median(v), min(v)) for k, v in times.items()}


def main(argv=None):
    ap = kernel_bench_parser(__doc__, "clahe.json", repeat=15)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    device = torch.device(args.device)
    frames = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(FRAMES.glob("*.png"))]
    clahe = cv2.createCLAHE(CLIP, GRID)
    rows = []
    for B in args.batches:
        imgs = np.stack([frames[b % len(frames)] for b in range(B)])
        x = torch.from_numpy(imgs).to(device)
        out_f = _clahe_impl(x, CLIP, *GRID, backend="fused").image
        out_t = _clahe_impl(x, CLIP, *GRID, backend="tensor").image
        ref = np.stack([clahe.apply(i) for i in imgs])
        same = bool(np.array_equal(out_f.cpu().numpy(), ref) and np.array_equal(out_t.cpu().numpy(), ref))
        fns = {
            "fused": lambda x=x: _clahe_impl(x, CLIP, *GRID, backend="fused"),
            "tensor": lambda x=x: _clahe_impl(x, CLIP, *GRID, backend="tensor"),
            "cv2": lambda imgs=imgs: [clahe.apply(i) for i in imgs],
        }
        t = _time_round_robin(fns, args.repeat, device)
        row = {"B": B, "bit_identical": same}
        for k, (med, mn) in t.items():
            row[f"{k}_ms"] = round(med, 3)
            row[f"{k}_min_ms"] = round(mn, 3)
            row[f"{k}_ms_per_frame"] = round(med / B, 3)
        row["fused_over_cv2"] = round(t["fused"][0] / t["cv2"][0], 3)
        row["tensor_over_cv2"] = round(t["tensor"][0] / t["cv2"][0], 3)
        row["fused_over_tensor"] = round(t["fused"][0] / t["tensor"][0], 3)
        rows.append(row)
    print("| B | fused ms/frame | tensor ms/frame | cv2 ms/frame | fused/cv2 | tensor/cv2 | fused/tensor | bits |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['B']} | {r['fused_ms_per_frame']:.3f} | {r['tensor_ms_per_frame']:.3f} | "
              f"{r['cv2_ms_per_frame']:.3f} | {r['fused_over_cv2']:.2f} | {r['tensor_over_cv2']:.2f} | "
              f"{r['fused_over_tensor']:.3f} | {'same' if r['bit_identical'] else 'DIFFER'} |")
    meta = {"device": str(device), "threads": args.threads, "repeat": args.repeat, "torch": torch.__version__,
            "opencv": cv2.__version__, "machine": platform.machine(), "python": platform.python_version(),
            "size": "752x480", "clip": CLIP, "grid": list(GRID),
            "note": "medians of round-robin timings in one process; shared machine: noisy, compare ratios"}
    write_json_atomic(Path(args.out), {"meta": meta, "rows": rows})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
