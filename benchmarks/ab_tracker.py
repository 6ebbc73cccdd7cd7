"""A/B timing of two torch_frontend source trees in one process (for performance work).

On a shared machine two benchmark runs minutes apart can differ by 1.5x; this loads the working
tree's ``torch_frontend`` and a reference copy (e.g. ``git worktree add /tmp/ref <commit>``) side by
side as two packages, builds one ``FeatureTracker`` each (mono, EuRoC config, the shipped 752x480
sample frames as B streams, as ``bench_pipeline.py``) and times them in alternating windows of
consecutive steps, so that both see the same machine load. Prints min and median ms per
stream-frame per tree and the ratio of the minima.

Two trees that both define the fused kernels' custom ops (``torch_frontend::lk``, ...) cannot both
register them in one process: the reference tree is loaded from a copy (under
``~/.cache/torch_frontend_ab``) whose op namespace is renamed ``tf_ab_ref::``. ``--ref same`` times the
working tree against itself, each side with its own ``FeatureTracker`` keyword arguments
(``--new-kwargs`` / ``--ref-kwargs``, JSON): an A/B of two settings (e.g. the fused and the tensor
kernels of one stage) in one tree.

Usage:
    python benchmarks/ab_tracker.py --ref /tmp/ref/torch_frontend [--batches 1 16 64] [--windows 8]
    python benchmarks/ab_tracker.py --ref same --ref-kwargs '{"lk_backend": "tensor"}'
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import importlib.util
import json
import os
import shutil
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


#: the op namespace of the working tree, and the one the reference copy's ops are renamed to
_OPS_NAMESPACE = "torch_frontend"
_REF_NAMESPACE = "tf_ab_ref"


def _renamed_ops_copy(path: Path) -> Path:
    """A copy of the package at ``path`` whose custom ops live in ``tf_ab_ref::`` (the ``.py`` sources
    with ``torch_frontend::`` and ``torch.ops.torch_frontend`` renamed), cached by content hash."""
    sources = sorted(p for p in path.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    digest = hashlib.sha256()
    for p in sources:
        digest.update(str(p.relative_to(path)).encode())
        digest.update(p.read_bytes())
    root = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "torch_frontend_ab"
    dest = root / digest.hexdigest()[:16] / "torch_frontend"
    if dest.is_dir():
        return dest
    tmp = dest.parent.with_name(dest.parent.name + f".tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    for p in sources:
        out = tmp / "torch_frontend" / p.relative_to(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        if p.suffix == ".py":
            text = p.read_text()
            text = text.replace(f"{_OPS_NAMESPACE}::", f"{_REF_NAMESPACE}::")
            text = text.replace(f"torch.ops.{_OPS_NAMESPACE}", f"torch.ops.{_REF_NAMESPACE}")
            out.write_text(text)
        else:
            shutil.copy2(p, out)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.rename(tmp, dest.parent)
    except OSError:  # another run made it first
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def compare(B: int, windows: int, trees: dict, kwargs: dict) -> dict:
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
        tr = mod.FeatureTracker(mod.load_config(REPO / "configs" / "euroc.yaml"), num_streams=B, **kwargs[key])
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ref", required=True,
                    help="the reference torch_frontend package directory, or 'same' (the working tree again)")
    ap.add_argument("--new-kwargs", type=json.loads, default={},
                    help="FeatureTracker keyword arguments of the working tree's tracker (JSON)")
    ap.add_argument("--ref-kwargs", type=json.loads, default={},
                    help="FeatureTracker keyword arguments of the reference's tracker (JSON)")
    ap.add_argument("--batches", type=int, nargs="*", default=[1, 16, 64])
    ap.add_argument("--windows", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    # numba's cache entries record the module that compiled them: the trees load here as ``tf_ab_new`` /
    # ``tf_ab_ref``, and entries written so beside the sources make a later plain ``import torch_frontend``
    # fail to load them (ModuleNotFoundError: tf_ab_new). Keep this process's numba cache apart.
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
                                                 / "torch_frontend_ab" / "numba"))
    import torch

    torch.set_num_threads(args.threads)
    new = _load("tf_ab_new", REPO / "torch_frontend")
    if args.ref == "same":
        ref = new
    else:
        ref_path = Path(args.ref).resolve()
        if not (ref_path / "__init__.py").is_file():
            raise SystemExit(f"--ref: {ref_path} is not a torch_frontend package directory (no __init__.py)")
        ref = _load("tf_ab_ref", _renamed_ops_copy(ref_path))
    trees = {"working tree": new, "reference": ref}
    kwargs = {"working tree": args.new_kwargs, "reference": args.ref_kwargs}
    print(f"working tree kwargs {args.new_kwargs}; reference {args.ref} kwargs {args.ref_kwargs}")
    print("| B | working tree min / median ms per stream-frame | reference min / median | ratio of minima |")
    print("|---|---|---|---|")
    for B in args.batches:
        t = compare(B, args.windows, trees, kwargs)
        new, ref = t["working tree"], t["reference"]
        print(f"| {B} | {new[0]:.1f} / {new[len(new) // 2]:.1f} | {ref[0]:.1f} / {ref[len(ref) // 2]:.1f} | "
              f"{new[0] / ref[0]:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
