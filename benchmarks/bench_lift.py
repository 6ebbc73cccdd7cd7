"""PINHOLE lift benchmark: the fused op (``torch_frontend::pinhole_lift``) vs the tensor lift, as the tracker calls them.

Cases: B = 1, 16 and 64 streams (``--batches``) of ``--points`` (default 150, VINS's max_cnt) float32
points over a 752x480 image, 90 % valid, EuRoC's PINHOLE camera (``configs/euroc.yaml``, 8
fixed-point evaluations). Each call is ``tracker.stages.lift_normalised`` with ``backend="fused"`` /
``"tensor"`` (the undistort stage's call; rejectWithF lifts twice as many points in one call). The
two are timed round-robin in one process on ``--threads`` intra-op threads (default 1), after a
warm-up; the outputs are checked bit for bit first.

Prints a markdown table (median µs per call and per stream-frame, the ratio of the medians) and
writes ``benchmarks/results/lift.json`` (temp + rename). Shared machine: noisy, compare ratios.

Usage: ``python benchmarks/bench_lift.py [--device cpu|cuda] [--repeat N] [--threads T] [--batches 1 16 64]``
"""

from __future__ import annotations

import platform
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import torch_frontend as tf  # noqa: E402
from torch_frontend.tracker.stages import lift_normalised  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, kernel_bench_parser, sync, write_json_atomic  # noqa: E402


def main(argv=None):
    ap = kernel_bench_parser(__doc__, "lift.json", repeat=200)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    ap.add_argument("--points", type=int, default=150)
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    device = torch.device(args.device)
    cam = tf.load_config(REPO / "configs" / "euroc.yaml").camera.to(device)
    rows = []
    for B in args.batches:
        g = torch.Generator().manual_seed(B)
        uv = (torch.rand((B, args.points, 2), generator=g) * torch.tensor([752.0, 480.0])).to(device)
        valid = (torch.rand((B, args.points), generator=g) < 0.9).to(device)
        a, b = (lift_normalised(cam, uv, valid, be) for be in ("fused", "tensor"))
        same = bool(torch.equal(a.view(torch.int32), b.view(torch.int32)))
        fns = {be: (lambda be=be, uv=uv, valid=valid: lift_normalised(cam, uv, valid, be)) for be in ("fused", "tensor")}
        times = {k: [] for k in fns}
        for f in fns.values():
            f()
        for _ in range(args.repeat):
            for k, f in fns.items():
                t0 = time.perf_counter()
                f()
                sync(device)
                times[k].append((time.perf_counter() - t0) * 1e6)
        row = {"B": B, "points": args.points, "bit_identical": same}
        for k, v in times.items():
            row[f"{k}_us"] = round(statistics.median(v), 1)
            row[f"{k}_min_us"] = round(min(v), 1)
            row[f"{k}_us_per_frame"] = round(statistics.median(v) / B, 2)
        row["fused_over_tensor"] = round(row["fused_us"] / row["tensor_us"], 3)
        rows.append(row)
    print("| B | fused µs/call | tensor µs/call | fused µs/stream-frame | tensor µs/stream-frame | fused/tensor | bits |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['B']} | {r['fused_us']:.1f} | {r['tensor_us']:.1f} | {r['fused_us_per_frame']:.2f} | "
              f"{r['tensor_us_per_frame']:.2f} | {r['fused_over_tensor']:.3f} | "
              f"{'same' if r['bit_identical'] else 'DIFFER'} |")
    meta = {"device": str(device), "threads": args.threads, "repeat": args.repeat, "torch": torch.__version__,
            "machine": platform.machine(), "python": platform.python_version(), "camera": "configs/euroc.yaml",
            "note": "medians of round-robin timings in one process; shared machine: noisy, compare ratios"}
    write_json_atomic(Path(args.out), {"meta": meta, "rows": rows})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
