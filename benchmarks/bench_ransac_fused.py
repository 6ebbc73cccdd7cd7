"""Benchmark: F-RANSAC with the fused scoring op (``torch_frontend::ransac_score``) against the tensor
scoring and a loop of ``cv2.findFundamentalMat(FM_RANSAC, 1.0, 0.99)``, in one process, alternating.

* Problems as the tracker's: ``B`` streams of 150 slots, 140..150 valid (float32 virtual-pinhole
  pixels, synthetic non-planar scenes, 0.3 px noise, ``--rate`` gross outliers, default 10 %), OpenCV's
  seed; B = 1 and 16. The default (eager) path for both backends, and the capturable path.
* Median and min ms per call over ``--repeat`` alternating rounds, per stream-frame, ratios to cv2.
  The masks of the three are compared (they are equal).

Noisy on a shared machine: read the ratios. Writes ``benchmarks/results/ransac_fused.json``.

Run: ``.venv/bin/python benchmarks/bench_ransac_fused.py [--repeat 15] [--threads 1] [--rate 0.1]``
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
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import apply_threads, kernel_bench_parser, write_json_atomic  # noqa: E402
from bench_ransac import make_problems  # noqa: E402

from torch_frontend.ransac import find_fundamental  # noqa: E402


def _inputs(B: int, rate: float, seed: int = 0):
    a, c = make_problems(B, 150, rate, seed=seed)
    rng = np.random.default_rng(seed + 1)
    ns = rng.integers(140, 151, B)
    valid = torch.zeros(B, 150, dtype=torch.bool)
    for b, n in enumerate(ns):
        valid[b, :n] = True
    return torch.from_numpy(a), torch.from_numpy(c), valid, ns


def _calls(p1, p2, valid, ns):
    """The timed calls on one batch: name -> function."""
    a, c = p1.numpy(), p2.numpy()
    return {
        "fused": lambda: find_fundamental(p1, p2, valid, backend="fused"),
        "tensor": lambda: find_fundamental(p1, p2, valid, backend="tensor"),
        "fused_capturable": lambda: find_fundamental(p1, p2, valid, backend="fused", capturable=True),
        "tensor_capturable": lambda: find_fundamental(p1, p2, valid, backend="tensor", capturable=True),
        "cv2": lambda: [cv2.findFundamentalMat(a[b, :n], c[b, :n], cv2.FM_RANSAC, 1.0, 0.99)
                        for b, n in enumerate(ns)],
    }


def main() -> None:
    ap = kernel_bench_parser(__doc__, "ransac_fused.json", 15)
    ap.add_argument("--rate", type=float, default=0.1)
    ap.add_argument("--B", type=int, nargs="+", default=[1, 16])
    args = ap.parse_args()
    apply_threads(args.threads)
    rows = []
    for B in args.B:
        p1, p2, valid, ns = _inputs(B, args.rate)
        fns = _calls(p1, p2, valid, ns)
        outs = {k: f() for k, f in fns.items()}  # warm-up (tables, kernels) and the masks
        cvm = [m.ravel().astype(bool) for _, m in outs["cv2"]]
        same = {k: all(np.array_equal(outs[k].inliers[b, :n].numpy(), cvm[b]) for b, n in enumerate(ns))
                for k in fns if k != "cv2"}
        ts = {k: [] for k in fns}
        for _ in range(args.repeat):
            for k, f in fns.items():
                t0 = time.perf_counter()
                f()
                ts[k].append((time.perf_counter() - t0) * 1e3)
        med = {k: statistics.median(v) for k, v in ts.items()}
        row = {"B": B, "ms_per_call_median": med, "ms_per_call_min": {k: min(v) for k, v in ts.items()},
               "ms_per_stream_frame": {k: v / B for k, v in med.items()},
               "ratio_to_cv2": {k: med[k] / med["cv2"] for k in fns},
               "masks_equal_cv2": same}
        rows.append(row)
        print(f"B={B:3d} " + "  ".join(f"{k} {med[k] / B:.3f} ms ({med[k] / med['cv2']:.2f}x)" for k in fns)
              + f"  masks==cv2 {same}", flush=True)
    write_json_atomic(args.out, {"benchmark": "bench_ransac_fused", "threads": args.threads, "rate": args.rate,
                                 "repeat": args.repeat, "torch": torch.__version__, "cv2": cv2.__version__,
                                 "machine": platform.machine(), "note": "shared 2-core machine: noisy, read ratios",
                                 "rows": rows})


if __name__ == "__main__":
    main()
