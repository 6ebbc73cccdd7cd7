"""Image-stage benchmark: torch-frontend vs OpenCV on 752x480 EuRoC frames, B = 1 and 8.

Times ``clahe``, ``min_eigen_response``, ``good_features_to_track`` (150 corners, quality 0.01,
min distance 30), ``distance_mask`` (VINS setMask, 150 tracked points, radius 30) and
``build_pyramid(img, 3)``. OpenCV runs the same work image by image (it has no
batch); the setMask baseline is the sequential loop with ``cv2.circle`` as VINS does it, in
Python. Prints a markdown table (median and min ms per call, ms per image, ratio of medians
torch / OpenCV: < 1 means torch is faster) and writes ``benchmarks/results/image.json`` (temp
file + rename). Torch and OpenCV calls alternate, so load from other processes on a shared
machine hits both sides alike; the min is the least disturbed run.

Usage: ``python benchmarks/bench_image.py [--device cpu|cuda] [--repeat N] [--threads N]``
(default: 1 thread for torch and OpenCV, 15 repeats)
"""

from __future__ import annotations

import platform
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torch_frontend.corners import good_features_to_track, min_eigen_response  # noqa: E402
from torch_frontend.equalize import clahe  # noqa: E402
from torch_frontend.masks import distance_mask  # noqa: E402
from torch_frontend.pyramid import build_pyramid  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, kernel_bench_parser, time_pair, write_json_atomic  # noqa: E402

FRAMES = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"






def _setmask_cv(pts, cnt, r, H, W):
    m = np.full((H, W), 255, np.uint8)
    order = sorted(range(len(pts)), key=lambda i: -cnt[i])
    for i in order:
        x, y = int(round(float(pts[i][0]))), int(round(float(pts[i][1])))
        if 0 <= x < W and 0 <= y < H and m[y, x] == 255:
            cv2.circle(m, (x, y), r, 0, -1)
    return m


def _cases(B, raw, eq, tracked, cnts, cl, device):
    """(name, torch fn, OpenCV fn) for batch size B."""
    H, W = raw.shape[1:]
    x_raw = torch.from_numpy(raw[:B])[:, None].to(device)
    x_eq = torch.from_numpy(eq[:B])[:, None].to(device)
    pts = torch.from_numpy(np.stack(tracked[:B])).to(device)
    cnt = torch.from_numpy(cnts[:B]).to(device)
    cases = [
        ("clahe", lambda: clahe(x_raw), lambda: [cl.apply(f) for f in raw[:B]]),
        ("min_eigen_response", lambda: min_eigen_response(x_eq),
         lambda: [cv2.cornerMinEigenVal(f, 3, 3) for f in eq[:B]]),
        ("good_features_to_track", lambda: good_features_to_track(x_eq, 150, 0.01, 30),
         lambda: [cv2.goodFeaturesToTrack(f, 150, 0.01, 30) for f in eq[:B]]),
        ("distance_mask", lambda: distance_mask(pts, cnt, None, 30, height=H, width=W),
         lambda: [_setmask_cv(tracked[b], cnts[b], 30, H, W) for b in range(B)]),
        ("build_pyramid(3)", lambda: build_pyramid(x_eq, 3),
         lambda: [cv2.buildOpticalFlowPyramid(f, (21, 21), 3) for f in eq[:B]]),
    ]
    return cases


def main(argv=None):
    args = kernel_bench_parser(__doc__, "image.json", repeat=15).parse_args(argv)
    device = torch.device(args.device)
    apply_threads(args.threads)

    paths = sorted(FRAMES.glob("*.png"))[:8]
    raw = np.stack([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths])
    cl = cv2.createCLAHE(3.0, (8, 8))
    eq = np.stack([cl.apply(f) for f in raw])
    H, W = raw.shape[1:]
    rng = np.random.default_rng(0)
    tracked = [cv2.goodFeaturesToTrack(f, 150, 0.01, 20)[:, 0] + rng.normal(0, 2, (150, 2)).astype(np.float32)
               for f in eq]
    cnts = rng.integers(1, 10, (8, 150))

    rows = []
    for B in (1, 8):
        cases = _cases(B, raw, eq, tracked, cnts, cl, device)
        for name, ft, fc in cases:
            (t_torch, t_torch_min), (t_cv, t_cv_min) = time_pair(ft, fc, args.repeat, device)
            rows.append({"op": name, "B": B, "torch_ms": round(t_torch, 3), "torch_min_ms": round(t_torch_min, 3),
                         "torch_ms_per_image": round(t_torch / B, 3), "opencv_ms": round(t_cv, 3),
                         "opencv_min_ms": round(t_cv_min, 3), "ratio": round(t_torch / t_cv, 2)})

    print(f"\nImage stage, 752x480, device {device}, torch {torch.__version__} ({torch.get_num_threads()} threads), "
          f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads)\n")
    print("| op | B | torch ms (min) | torch ms / image | OpenCV ms (min) | ratio torch/OpenCV |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['op']} | {r['B']} | {r['torch_ms']:.2f} ({r['torch_min_ms']:.2f}) | "
              f"{r['torch_ms_per_image']:.2f} | {r['opencv_ms']:.2f} ({r['opencv_min_ms']:.2f}) | {r['ratio']:.2f} |")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": str(device), "torch": torch.__version__, "opencv": cv2.__version__,
            "torch_threads": torch.get_num_threads(), "opencv_threads": cv2.getNumThreads(),
            "machine": platform.machine(), "size": [W, H], "repeat": args.repeat,
            "note": "OpenCV per image in a Python loop; setMask baseline is a Python loop with cv2.circle"}
    write_json_atomic(out, {"meta": meta, "rows": rows})
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
