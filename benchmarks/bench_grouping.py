"""Stream grouping study on the CPU: CLAHE -> pyramid -> LK stage by stage (every stream's CLAHE,
then every stream's pyramid, then every stream's LK: what the tracker's step does) against group by
group (for each group of G streams the three kernels back to back, so that a stream's equalised
image and new pyramid are still in cache when the next kernel reads them).

The numba kernels themselves (``fused/_numba_*.py``, the ops' CPU bodies) on the sample's 752x480
frames, 150 GFTT corners per stream (VINS's 21x21 window, 3 levels, 30 iterations), the previous
frame's packed pyramid built beforehand (the tracker's state). Between timed runs a 64 MB buffer is
written (the rest of a step: detection, RANSAC, ... evict the caches). 1 thread; alternating order
runs per round; min and median ms per stream-frame; the grouped rows' ratio to stage order (minima).

Usage: python benchmarks/bench_grouping.py [--batches 1 16 64] [--groups 1 2 4 8] [--rounds 7]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--batches", type=int, nargs="*", default=[1, 16, 64])
    ap.add_argument("--groups", type=int, nargs="*", default=[1, 2, 4, 8])
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args(argv)
    import cv2
    import torch

    torch.set_num_threads(1)
    from bench_pipeline import _frames, _stream_frames

    from torch_frontend.fused._numba_clahe import clahe_streams
    from torch_frontend.fused._numba_lk import lk_streams
    from torch_frontend.fused._numba_pyramid import pyramid_streams
    from torch_frontend.fused.layout import lk_pad
    from torch_frontend.fused.ops import layout_arrays

    frames = _frames()
    H, W = frames[0].shape
    L, win, pad = 3, 21, lk_pad((21, 21))
    sizes, offs, org, pitch, total = layout_arrays(H, W, L, pad)
    flush = np.empty(64 << 20, dtype=np.uint8)
    print("| B | order | min / median ms per stream-frame | ratio to stage order (minima) |")
    print("|---|---|---|---|")
    for B in args.batches:
        prev_img, cur_img = (np.ascontiguousarray(np.stack(r)) for r in _stream_frames(frames, B, 2))
        clahe = cv2.createCLAHE(3.0, (8, 8))
        pts = np.zeros((B, 150, 2), np.float32)
        valid = np.zeros((B, 150), bool)
        for b in range(B):
            c = cv2.goodFeaturesToTrack(clahe.apply(prev_img[b]), 150, 0.01, 30)
            pts[b, :len(c)] = c[:, 0]
            valid[b, :len(c)] = True
        prev_eq = np.empty_like(prev_img)
        clahe_streams(prev_img, prev_eq, 3.0, 8, 8, 0, B)
        prev_pyr = np.empty((B, total), np.uint8)
        pyramid_streams(prev_eq, prev_pyr, sizes, offs, pad, 0, B)
        eq = np.empty_like(cur_img)
        pyr = np.empty((B, total), np.uint8)
        out = np.empty((B, 150, 2), np.float32)
        st = np.empty((B, 150), bool)
        cp = np.empty((B, 150), bool)
        noinit = np.zeros((1, 1, 2), np.float32)

        def run(G, B=B, cur_img=cur_img, eq=eq, pyr=pyr, prev_pyr=prev_pyr, pts=pts, valid=valid, noinit=noinit,
                out=out, st=st, cp=cp):
            for s0 in range(0, B, G):
                s1 = min(s0 + G, B)
                clahe_streams(cur_img, eq, 3.0, 8, 8, s0, s1)
                pyramid_streams(eq, pyr, sizes, offs, pad, s0, s1)
                lk_streams(prev_pyr, pyr, org, pitch, org, pitch, sizes, pts, valid, noinit, False, L, win, win, 30,
                           0.01, 1e-4, -1, 0.0, False, out, st, cp, s0, s1)
            return out.copy(), st.copy()

        orders = [("stage", B)] + [(f"G={g}", g) for g in args.groups if g < B]
        ref = run(B)
        for _, g in orders[1:]:
            o, s = run(g)
            assert np.array_equal(o.view(np.uint32), ref[0].view(np.uint32)) and np.array_equal(s, ref[1])
        times = {name: [] for name, _ in orders}
        for r in range(args.rounds):
            seq = orders if r % 2 == 0 else orders[::-1]
            for name, g in seq:
                flush[:] = r
                t0 = time.perf_counter()
                run(g)
                times[name].append((time.perf_counter() - t0) / B * 1e3)
        base = min(times["stage"])
        for name, _ in orders:
            t = sorted(times[name])
            print(f"| {B} | {name} | {t[0]:.2f} / {t[len(t) // 2]:.2f} | {t[0] / base:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
