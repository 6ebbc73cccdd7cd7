"""A/B timing of two torch_frontend source trees in one process (for performance work).

On a shared machine two benchmark runs minutes apart can differ by 1.5x; this loads the working
tree's ``torch_frontend`` and a reference copy (e.g. ``git worktree add /tmp/ref <commit>``) side by
side as two packages, builds one ``FeatureTracker`` each (mono, EuRoC config, the shipped 752x480
sample frames as B streams, as ``bench_pipeline.py``) and times them in alternating windows of
consecutive steps, so that both see the same machine load. Prints min and median ms per
stream-frame per tree and the ratio of the minima.

A same-tree A/B by tracker keywords: ``--ref same`` times this tree twice, the working-tree side
with ``--kwargs`` and the reference side with ``--ref-kwargs`` (``key=value`` pairs given to
``FeatureTracker``, e.g. ``--ref same --ref-kwargs corner_backend=tensor``: the fused detection
against the tensor one).

Usage:
    python benchmarks/ab_tracker.py --ref /tmp/ref/torch_frontend [--batches 1 16 64] [--windows 8]
    python benchmarks/ab_tracker.py --ref same [--kwargs k=v ...] --ref-kwargs k=v ... [--batches 1 16]
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


def _load(name: str, path: Path):
    init = path / "__init__.py"
    if not init.is_file():
        raise SystemExit(f"--ref: {path} is not a torch_frontend package directory (no __init__.py)")
    spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[str(path)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def compare(B: int, windows: int, trees: dict) -> dict:
    import numpy as np
    import torch

    sys.path.insert(0, str(HERE))
    from bench_pipeline import _frames, _stream_frames

    steps_per_window = 8 if B < 16 else 2  # even: VINS publishes every other step at these stamps
    n = 4 + windows * steps_per_window
    steps = _stream_frames(_frames(), B, n)
    batches = [torch.from_numpy(np.stack(row))[:, None] for row in steps]
    stamps = [1403715273.0 + 0.05 * k for k in range(n)]
    trackers = {}
    for key, mod in trees.items():
        mod, kwargs = mod if isinstance(mod, tuple) else (mod, {})
        tr = mod.FeatureTracker(mod.load_config(REPO / "configs" / "euroc.yaml"), num_streams=B, **kwargs)
        for k in range(4):
            tr.track(batches[k], [stamps[k]] * B)
        trackers[key] = tr
    times = {key: [] for key in trees}
    for w in range(windows):
        for key, tr in trackers.items():
            t0 = time.perf_counter()
            for k in range(4 + w * steps_per_window, 4 + (w + 1) * steps_per_window):
                tr.track(batches[k], [stamps[k]] * B)
            times[key].append((time.perf_counter() - t0) / (steps_per_window * B) * 1e3)
    return {key: sorted(v) for key, v in times.items()}


def _kwargs(pairs) -> dict:
    """``["k=v", ...]`` -> keywords (``v`` as a Python literal where it reads as one, else a string)."""
    import ast

    out = {}
    for p in pairs:
        k, sep, v = p.partition("=")
        if not sep:
            raise SystemExit(f"--kwargs / --ref-kwargs: expected key=value, got {p!r}")
        try:
            out[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            out[k] = v
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ref", type=Path, required=True,
                    help="the reference torch_frontend package directory, or 'same' (this tree, --ref-kwargs)")
    ap.add_argument("--kwargs", nargs="*", default=[], help="key=value FeatureTracker keywords of the working tree")
    ap.add_argument("--ref-kwargs", nargs="*", default=[], help="key=value FeatureTracker keywords of the reference")
    ap.add_argument("--batches", type=int, nargs="*", default=[1, 16, 64])
    ap.add_argument("--windows", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    new = _load("tf_ab_new", REPO / "torch_frontend")
    ref = new if str(args.ref) == "same" else _load("tf_ab_ref", args.ref)
    trees = {"working tree": (new, _kwargs(args.kwargs)), "reference": (ref, _kwargs(args.ref_kwargs))}
    print("| B | working tree min / median ms per stream-frame | reference min / median | ratio of minima |")
    print("|---|---|---|---|")
    for B in args.batches:
        t = compare(B, args.windows, trees)
        new, ref = t["working tree"], t["reference"]
        print(f"| {B} | {new[0]:.1f} / {new[len(new) // 2]:.1f} | {ref[0]:.1f} / {ref[len(ref) // 2]:.1f} | "
              f"{new[0] / ref[0]:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
