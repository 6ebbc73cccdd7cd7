"""Helpers shared by the benchmark scripts (run as ``python benchmarks/bench_*.py``)."""

from __future__ import annotations

import argparse
import json
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
