"""Helpers shared by the benchmark scripts (run as ``python benchmarks/bench_*.py``)."""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from torch_frontend.outputs import write_bytes_atomic

RESULTS = Path(__file__).resolve().parent / "results"


def write_atomic(path, data: bytes) -> Path:
    """Write ``data`` through a temp file and a rename: an interrupted benchmark never leaves a
    half-written result."""
    write_bytes_atomic(Path(path), data)
    return Path(path)


def write_json_atomic(path, obj) -> Path:
    """``json.dump(obj, indent=2)`` to ``path``, atomically."""
    return write_atomic(path, json.dumps(obj, indent=2).encode())


def kernel_bench_parser(doc: str, result_name: str, repeat: int) -> argparse.ArgumentParser:
    """The options every per-kernel benchmark takes: device, repeats, threads, output JSON."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=repeat)
    ap.add_argument("--threads", type=int, default=1,
                    help="intra-op threads for torch and OpenCV alike (0: library default; 1: a fair "
                         "single-core comparison, robust on a busy machine)")
    ap.add_argument("--out", default=str(RESULTS / result_name))
    return ap


def apply_threads(threads: int) -> None:
    """Give torch and OpenCV the same thread count (0 leaves the libraries' defaults)."""
    if threads > 0:
        import cv2
        import torch

        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)


def sync(device) -> None:
    """Wait for queued CUDA work, so that a timing covers it (no-op on CPU)."""
    if device.type == "cuda":
        import torch

        torch.cuda.synchronize()


def time_pair(ft, fc, repeat: int, device):
    """Alternating timings of the torch and the baseline (OpenCV) function, after one warm-up call
    of each (which also fills the kernels' per-size caches): ``((median, min), (median, min))`` ms."""
    ft()
    fc()
    sync(device)
    tt, tc = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        ft()
        sync(device)
        tt.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        fc()
        tc.append((time.perf_counter() - t0) * 1e3)
    return (statistics.median(tt), min(tt)), (statistics.median(tc), min(tc))
