"""How long ``FeatureTracker.compile()`` of the capturable mono step takes before a user sees frames.

A mono EuRoC tracker (``configs/euroc.yaml``, one stream, ``capturable=True``) on the CPU is
compiled (inductor) and tracks the repo's first sample frames at 20 Hz; each step's wall time is
printed, with whether its frame equals a plain eager capturable tracker's bit for bit. The first
three steps compile what the run needs (the first frame, track only, publish: mono's three step
variants); later steps run compiled. Inductor keeps what it compiled on disk
(``TORCHINDUCTOR_CACHE_DIR``): a fresh folder is used unless ``--warm-cache``, so the figure is a
first run's.

    .venv/bin/python benchmarks/compile_time.py [--regions | --whole] [--frames 6] [--warm-cache]

``--regions`` (the CPU's default: the step's parts compiled once each, shared by the variants) or
``--whole`` (one graph per variant, the CUDA default). Writes
``benchmarks/results/compile_time_{regions,whole}.json``. Measured on this 2-core machine,
2026-12-06 (every mono stage fused): regions 20.7 + 2.2 + 23.8 s (46.7 s in all; 2026-12-05, before: 214 + 4 + 59 s), whole 245 + 197 + 296 s (739 s); identical frames for the first three
steps, then last-bit drift (inductor reorders float reductions).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FIELDS = ("ids", "uv", "xy", "velocity", "valid", "track_count", "published")
#: the first sample frame's time (s) and the EuRoC camera's period
T0, PERIOD = 1403715273.262142976, 0.05


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--regions", dest="regions", action="store_true", default=True,
                   help="compile the step's parts once for every variant (default)")
    g.add_argument("--whole", dest="regions", action="store_false", help="compile each variant's whole step")
    ap.add_argument("--frames", type=int, default=6, help="steps to run (default 6)")
    ap.add_argument("--warm-cache", action="store_true", help="keep inductor's on-disk cache (default: a fresh one)")
    args = ap.parse_args(argv)
    if not args.warm_cache:  # before torch reads it
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="tf-inductor-")
    sys.path.insert(0, str(REPO))
    import cv2
    import torch

    import torch_frontend as tf

    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    paths = sorted((REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data").glob("*.png"))
    if len(paths) < args.frames:
        print(f"compile_time.py: {len(paths)} sample frames, asked for {args.frames}", file=sys.stderr)
        return 2
    ref = tf.FeatureTracker(cfg, capturable=True)
    tr = tf.FeatureTracker(cfg, capturable=True)
    tr.compile(regions=args.regions)
    total = 0.0
    times, same_list = [], []
    print(f"compile({'regions' if args.regions else 'whole'}), inductor cache: "
          f"{'warm' if args.warm_cache else 'fresh'}, {torch.get_num_threads()} threads")
    for i, p in enumerate(paths[: args.frames]):
        x = torch.from_numpy(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))[None, None]
        t = [T0 + PERIOD * i]
        t0 = time.perf_counter()
        out = tr.track(x, t)
        dt = time.perf_counter() - t0
        total += dt
        r = ref.track(x, t)
        same = all(torch.equal(getattr(r, f), getattr(out, f)) for f in FIELDS)
        times.append(dt)
        same_list.append(same)
        print(f"step {i}: {dt:7.1f} s  {'identical to eager' if same else 'differs from eager (last bits)'}")
    c = tr._compiled
    if c.failed is not None:
        print(f"the compiled step failed and fell back to eager: {c.failed}")
        return 1
    print(f"variants: {sorted(p.name for p in c.variants if p is not None)}"
          + (f"; parts: {sorted(c.regions.parts)}" if c.regions is not None else ""))
    print(f"total: {total:.1f} s")
    import json
    import platform

    res = {"mode": "regions" if args.regions else "whole", "inductor_cache": "warm" if args.warm_cache else "fresh",
           "threads": torch.get_num_threads(), "torch": torch.__version__, "machine": platform.processor() or
           platform.machine(), "cpus": os.cpu_count(), "steps_s": [round(x, 1) for x in times], "same": same_list,
           "total_s": round(total, 1)}
    out = REPO / "benchmarks" / "results" / f"compile_time_{res['mode']}.json"
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(res, indent=1) + "\n")
    os.replace(tmp, out)
    print(f"wrote {out.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
