"""Detection benchmark: ``goodFeaturesToTrack`` as VINS calls it, the fused op against the tensor path and
``cv2.goodFeaturesToTrack``, on 752x480 EuRoC frames (CLAHE 3.0 / 8x8 as VINS-Mono equalises).

Cases: B = 1 and 16 streams (the sample's frames reused cyclically), ``max_corners`` 150, quality
0.01, MIN_DIST 30, block 3:

* ``unmasked``: a first frame (no mask, 150 corners);
* ``masked``: the steady state: setMask's mask (255 with filled discs of radius 30 around 110 tracked
  features, here cv2's strongest corners of the frame jittered by a few pixels) and
  ``max_corners = 150 - 110 = 40``;
* ``fisheye``: a first frame under a fisheye-style mask (a disc of radius 260 px at the centre: 43 %
  of the frame masked, in wide margins), 150 corners.

OpenCV has no batch: it runs the B frames one after the other. Every library on ``--threads`` threads
(default 1); the three are timed alternately in one process (the same machine load for all). Prints
a markdown table (median and min ms per call, per stream-frame, ratio to OpenCV of the medians) and
writes ``benchmarks/results/corners.json`` (temp + rename). Numbers on a shared machine are noisy:
compare ratios within one run.

Usage: ``python benchmarks/bench_corners.py [--repeat N] [--threads T]``
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

from torch_frontend.corners import _good_features_impl  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, kernel_bench_parser, write_json_atomic  # noqa: E402

FRAMES = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"
MAX_CNT, MIN_DIST, QUALITY, TRACKED = 150, 30, 0.01, 110


def _setmask(img: np.ndarray, rng) -> np.ndarray:
    """setMask's mask for ``TRACKED`` features near cv2's strongest corners (jittered)."""
    c = cv2.goodFeaturesToTrack(img, TRACKED, QUALITY, MIN_DIST).reshape(-1, 2)
    c = c + rng.integers(-3, 4, c.shape)
    m = np.full(img.shape, 255, np.uint8)
    for x, y in c:
        cv2.circle(m, (int(x), int(y)), MIN_DIST, 0, -1)
    return m


def _time3(fns, repeat):
    """Alternating timings of each function (after one warm-up call each): [(median, min)] ms."""
    for f in fns:
        f()
    ts = [[] for _ in fns]
    for _ in range(repeat):
        for f, t in zip(fns, ts):
            t0 = time.perf_counter()
            f()
            t.append((time.perf_counter() - t0) * 1e3)
    return [(statistics.median(t), min(t)) for t in ts]


def main(argv=None):
    ap = kernel_bench_parser(__doc__, "corners.json", repeat=15)
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    clahe = cv2.createCLAHE(3.0, (8, 8))
    frames = [clahe.apply(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in sorted(FRAMES.glob("*.png"))]
    rng = np.random.default_rng(0)
    masks = [_setmask(f, rng) for f in frames]
    rows = []
    fish = np.zeros(frames[0].shape, np.uint8)
    cv2.circle(fish, (frames[0].shape[1] // 2, frames[0].shape[0] // 2), 260, 255, -1)
    for case in ("unmasked", "masked", "fisheye"):
        for B in (1, 16):
            idx = [b % len(frames) for b in range(B)]
            x = torch.from_numpy(np.stack([frames[i] for i in idx]))[:, None]
            n = MAX_CNT - TRACKED if case == "masked" else MAX_CNT
            mc = torch.full((B,), n)
            cmask = {"unmasked": [None] * len(frames), "masked": masks, "fisheye": [fish] * len(frames)}[case]
            m = None if case == "unmasked" else torch.from_numpy(np.stack([cmask[i] for i in idx]) != 0)
            # the outputs agree (the tests hold every corner; here a guard on what is timed)
            a = _good_features_impl(x, mc, QUALITY, float(MIN_DIST), m, False, 3, 0.04, None, backend="fused")
            b = _good_features_impl(x, mc, QUALITY, float(MIN_DIST), m, False, 3, 0.04, None, backend="tensor")
            assert torch.equal(a.pts, b.pts) and torch.equal(a.valid, b.valid)

            def run(be, x=x, mc=mc, m=m):
                return lambda: _good_features_impl(x, mc, QUALITY, float(MIN_DIST), m, False, 3, 0.04, None,
                                                   backend=be)

            def cv(idx=idx, cmask=cmask, n=n):
                for i in idx:
                    cv2.goodFeaturesToTrack(frames[i], n, QUALITY, MIN_DIST, mask=cmask[i])

            (f_med, f_min), (t_med, t_min), (c_med, c_min) = _time3([run("fused"), run("tensor"), cv], args.repeat)
            row = {"case": case, "B": B, "max_corners": n, "fused_ms": round(f_med, 3), "fused_min_ms": round(f_min, 3),
                   "tensor_ms": round(t_med, 3), "tensor_min_ms": round(t_min, 3), "opencv_ms": round(c_med, 3),
                   "opencv_min_ms": round(c_min, 3), "fused_over_opencv": round(f_med / c_med, 3),
                   "fused_over_tensor": round(f_med / t_med, 3),
                   "masked_share": None if m is None else round(1 - float(m.float().mean()), 3)}
            rows.append(row)
            print(row, flush=True)
    print(f"\ngoodFeaturesToTrack, 752x480 CLAHE frames, quality {QUALITY}, MIN_DIST {MIN_DIST}, torch "
          f"{torch.__version__} ({torch.get_num_threads()} threads), OpenCV {cv2.__version__} "
          f"({cv2.getNumThreads()} threads)\n")
    print("| case | B | fused ms / stream-frame | tensor | OpenCV | fused / OpenCV | fused / tensor |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        B = r["B"]
        print(f"| {r['case']} | {B} | {r['fused_ms'] / B:.3f} | {r['tensor_ms'] / B:.3f} | {r['opencv_ms'] / B:.3f} | "
              f"{r['fused_over_opencv']:.2f} | {r['fused_over_tensor']:.2f} |")
    meta = {"torch": torch.__version__, "opencv": cv2.__version__, "torch_threads": torch.get_num_threads(),
            "opencv_threads": cv2.getNumThreads(), "machine": platform.machine(), "size": [752, 480],
            "repeat": args.repeat,
            "note": "medians of alternating timings in one process (fused, tensor, OpenCV); OpenCV runs the B frames "
                    "sequentially; 'masked': setMask's mask of 110 tracked features, 40 new corners; 'fisheye': a centred "
                    "disc of radius 260 px, 150 corners; a shared, "
                    "busy machine: ratios within one run, not absolute times"}
    write_json_atomic(Path(args.out), {"meta": meta, "rows": rows})
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
