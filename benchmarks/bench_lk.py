"""Pyramidal LK benchmark: ``track_lk`` vs ``cv2.calcOpticalFlowPyrLK`` on 752x480 EuRoC frames.

Cases: N = 150 and 1000 points (``goodFeaturesToTrack`` corners of the previous frame), B = 1, 8, 16,
64 streams (consecutive-frame pairs of the sample sequence, reused cyclically), win 21, maxLevel 3,
30 iterations / eps 0.01, uint8 input (OpenCV's fixed-point path). OpenCV has no batch: it runs the
B pairs one after the other. Both libraries on ``--threads`` intra-op threads (default 1), timed
alternately in one process (``_common.time_pair``: the same machine load for both).

Row groups (``mode``):

* ``vins``: **the tracker's call** (and the acceptance bar): ``build_pyramid(next)`` +
  ``track_lk(prev_pyramid, next_pyramid)`` (the previous frame's pyramid is the tracker's state)
  against ``calcOpticalFlowPyrLK(prev, next, pts)`` as VINS calls it (OpenCV builds both pyramids
  and the previous one's derivatives inside). ``lk`` = ``fused`` (the default backend) or
  ``tensor``.
* ``images``: ``track_lk(prev_image, next_image, pts)`` (both pyramids built inside the call) vs the
  same cv2 call.
* ``build``: ``build_pyramid`` (4 levels, padded for the LK, no derivatives) vs
  ``cv2.buildOpticalFlowPyramid`` (4 levels, ``withDerivatives=False``: the same work).
* ``compile`` (``--compile``): the tensor LK with ``compile_step=True``.

Prints a markdown table (median ms per call and per stream-frame, min ms, ratio torch / OpenCV of
the medians: < 1 means torch is faster) and writes ``benchmarks/results/lk.json`` (temp + rename).
``--quick`` skips B = 64 and the tensor LK's larger cases. Runtime: ~2 min on 2 cores (the tensor
LK's rows dominate).

Usage: ``python benchmarks/bench_lk.py [--device cpu|cuda] [--repeat N] [--threads T] [--compile] [--quick]``
"""

from __future__ import annotations

import platform
import sys
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
from _common import apply_threads, kernel_bench_parser, time_pair, write_json_atomic  # noqa: E402

FRAMES = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


def _inputs(frames, pts_by_n, n, B, device):
    npairs = len(frames) - 1
    idx = [b % npairs for b in range(B)]
    prev = torch.from_numpy(np.stack([frames[i] for i in idx]))[:, None].to(device)
    nxt = torch.from_numpy(np.stack([frames[i + 1] for i in idx]))[:, None].to(device)
    pts = torch.from_numpy(np.stack([pts_by_n[n][i] for i in idx])).to(device)
    return idx, prev, nxt, pts


def main(argv=None):
    ap = kernel_bench_parser(__doc__, "lk.json", repeat=9)
    ap.add_argument("--compile", action="store_true", help="also time torch.compile of the tensor LK's step (slow)")
    ap.add_argument("--quick", action="store_true", help="skip B=64 and the tensor LK's larger cases")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    apply_threads(args.threads)

    frames = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(FRAMES.glob("*.png"))]
    pts_by_n = {}
    for n in (150, 1000):
        per = []
        for i in range(len(frames) - 1):
            c = cv2.goodFeaturesToTrack(frames[i], n, 0.001, 5).reshape(-1, 2)
            c = np.concatenate([c, c[: n - len(c)] + 0.5]) if len(c) < n else c  # pad to exactly n
            per.append(np.ascontiguousarray(c[:n].astype(np.float32)))
        pts_by_n[n] = per

    def cv_calls(idx, n):
        def run():
            for i in idx:
                cv2.calcOpticalFlowPyrLK(frames[i], frames[i + 1], pts_by_n[n][i], None, winSize=(21, 21), maxLevel=3,
                                         criteria=CRIT)
        return run

    rows, notes = [], []

    def record(mode, lk, n, B, ft, fc):
        row = {"mode": mode, "lk": lk, "N": n, "B": B}
        try:
            (t_med, t_min), (c_med, c_min) = time_pair(ft, fc, args.repeat, device)
            row.update(torch_ms=round(t_med, 3), torch_min_ms=round(t_min, 3), opencv_ms=round(c_med, 3),
                       opencv_min_ms=round(c_min, 3), ratio=round(t_med / c_med, 3))
        except Exception as e:  # noqa: BLE001 - e.g. a compile failure at the first call
            row.update(torch_ms=None, ratio=None, error=f"{type(e).__name__}: {str(e).splitlines()[0][:200]}")
            notes.append(f"{mode} {lk} N={n} B={B}: {row['error']}")
            traceback.print_exc()
        rows.append(row)
        print(row, flush=True)

    batches = (1, 8, 16) + (() if args.quick else (64,))
    # the tracker's call: next pyramid + LK on the kept previous pyramid, vs VINS's cv2 call
    for lk in ("fused", "tensor"):
        for B in (1, 16):
            idx, prev, nxt, pts = _inputs(frames, pts_by_n, 150, B, device)
            valid = torch.ones(pts.shape[:2], dtype=torch.bool, device=device)
            pa = build_pyramid(prev, 3, with_gradients=False, backend=lk)

            def ours(pa=pa, nxt=nxt, pts=pts, valid=valid, lk=lk):
                pb = build_pyramid(nxt, 3, with_gradients=False, backend=lk)
                return track_lk(pa, pb, pts, valid, lk_backend=lk)

            record("vins", lk, 150, B, ours, cv_calls(idx, 150))
    # images in, both pyramids inside
    for lk in ("fused", "tensor"):
        for n in (150, 1000):
            for B in batches:
                if lk == "tensor" and (B == 64 or (args.quick and (n == 1000 or B > 1))):
                    continue
                idx, prev, nxt, pts = _inputs(frames, pts_by_n, n, B, device)
                record("images", lk, n, B,
                       lambda prev=prev, nxt=nxt, pts=pts, lk=lk: track_lk(prev, nxt, pts, lk_backend=lk),
                       cv_calls(idx, n))
    if args.compile:
        for B in (1, 8):
            idx, prev, nxt, pts = _inputs(frames, pts_by_n, 150, B, device)
            record("compile", "tensor", 150, B,
                   lambda prev=prev, nxt=nxt, pts=pts: track_lk(prev, nxt, pts, lk_backend="tensor", compile_step=True),
                   cv_calls(idx, 150))
    # the pyramid alone
    for lk in ("fused", "tensor"):
        for B in (1, 16):
            idx, _, nxt, _ = _inputs(frames, pts_by_n, 150, B, device)

            def build(nxt=nxt, lk=lk):
                p = build_pyramid(nxt, 3, with_gradients=False, backend=lk)
                return p if lk == "fused" else [p.padded(level, 22, 22) for level in range(4)]

            def cv_build(idx=idx):
                for i in idx:
                    cv2.buildOpticalFlowPyramid(frames[i + 1], (21, 21), 3, withDerivatives=False)

            record("build", lk, 0, B, build, cv_build)

    print(f"\nPyramidal LK, 752x480, win 21, maxLevel 3, device {device}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads)\n")
    print("| mode | LK | N | B | torch ms | OpenCV ms | ratio torch/OpenCV | torch ms / stream-frame |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        t = "fail" if r["torch_ms"] is None else f"{r['torch_ms']:.2f}"
        ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}"
        per = "-" if r["torch_ms"] is None else f"{r['torch_ms'] / r['B']:.2f}"
        print(f"| {r['mode']} | {r['lk']} | {r['N']} | {r['B']} | {t} | {r.get('opencv_ms', 0):.2f} | {ratio} | {per} |")
    for note in notes:
        print(f"\nnote: {note}")

    meta = {"device": str(device), "torch": torch.__version__, "opencv": cv2.__version__,
            "torch_threads": torch.get_num_threads(), "opencv_threads": cv2.getNumThreads(),
            "machine": platform.machine(), "size": [752, 480], "repeat": args.repeat,
            "params": {"win_size": 21, "max_level": 3, "max_iters": 30, "eps": 0.01, "input": "uint8"},
            "note": "medians of alternating timings in one process; OpenCV runs the B pairs sequentially; 'vins' "
                    "rows: build_pyramid(next) + track_lk on the kept previous pyramid vs calcOpticalFlowPyrLK "
                    "(which builds both pyramids); 'images' rows: both pyramids inside the call; 'build' rows: "
                    "one 4-level pyramid per stream, padded for the LK (OpenCV: withDerivatives=False)",
            "notes": notes}
    write_json_atomic(Path(args.out), {"meta": meta, "rows": rows})
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
