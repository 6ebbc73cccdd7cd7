"""Loop-closure keyframe features benchmark: torch-frontend vs OpenCV/numpy on 752x480 EuRoC frames,
1 and 16 keyframes per call.

Times ``fast`` (threshold 20, NMS; vs ``cv2.FastFeatureDetector``), ``brief`` (256 bits at every
FAST corner, ~900 per frame; vs ``cv2.GaussianBlur`` + a vectorised numpy BRIEF, OpenCV has no
BRIEF in its main module) and ``hamming`` + nearest neighbour (150 query descriptors, VINS's window features, against all FAST
descriptors of the keyframe: all distances, then the minimum per query as VINS's brute-force
``searchInAera``; vs ``cv2.batchDistance(NORM_HAMMING, K=1)`` on the uint8 view).
The baselines run image by image (no batch). Prints a markdown table (median and min ms per call,
ms per keyframe, ratio of medians torch / baseline: < 1 means torch is faster) and writes
``benchmarks/results/loop_features.json`` (temp file + rename). Torch and baseline calls
alternate, so load from other processes hits both alike; the min is the least disturbed run.

Usage: ``python benchmarks/bench_loop_features.py [--device cpu|cuda] [--repeat N] [--threads N]``
(default: 1 thread for torch and OpenCV, 5 repeats)
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

from torch_frontend.loop.features import brief, default_brief_pattern, fast, hamming  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, kernel_bench_parser, time_pair, write_json_atomic  # noqa: E402

FRAMES = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"
N_QUERY = 150






def _np_brief(img, pts, pattern):
    """OpenCV blur + vectorised numpy BRIEF of one image (the spec's rules), uint8 (K, 32)."""
    blur = cv2.GaussianBlur(img, (9, 9), 2, 2, borderType=cv2.BORDER_REFLECT_101)
    H, W = img.shape
    x1, y1, x2, y2 = (np.trunc(pts[:, None, j % 2] + pattern[j].astype(np.float32)).astype(np.int64)
                      for j in range(4))
    inside = (x1 >= 0) & (x1 < W) & (y1 >= 0) & (y1 < H) & (x2 >= 0) & (x2 < W) & (y2 >= 0) & (y2 < H)
    bits = (blur[np.clip(y1, 0, H - 1), np.clip(x1, 0, W - 1)] < blur[np.clip(y2, 0, H - 1), np.clip(x2, 0, W - 1)])
    return np.packbits(bits & inside, axis=1, bitorder="little")


def _cases(B, raw, kps_cv, det, pattern, device):
    """(name, torch fn, baseline fn) for B keyframes per call, and the mean keypoints per frame."""
    pat_np = pattern.numpy()
    x = torch.from_numpy(raw[:B]).to(device)
    pts, _, valid = fast(x)
    desc = brief(x, pts, valid, pattern)
    query = desc.roll(1, 0)[:, :N_QUERY].contiguous()  # another keyframe's first descriptors
    desc_cv = [_np_brief(raw[b], kps_cv[b], pat_np) for b in range(B)]
    query_cv = [desc_cv[(b - 1) % B][:N_QUERY] for b in range(B)]
    cases = [
        ("fast", lambda: fast(x), lambda: [det.detect(f) for f in raw[:B]]),
        ("brief", lambda: brief(x, pts, valid, pattern),
         lambda: [_np_brief(raw[b], kps_cv[b], pat_np) for b in range(B)]),
        (f"hamming {N_QUERY}xK + nearest", lambda: hamming(query, desc).min(dim=-1),
         lambda: [cv2.batchDistance(query_cv[b], desc_cv[b], cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)
                  for b in range(B)]),
    ]
    return cases, int(valid.sum()) / B


def main(argv=None):
    args = kernel_bench_parser(__doc__, "loop_features.json", repeat=5).parse_args(argv)
    device = torch.device(args.device)
    apply_threads(args.threads)

    paths = sorted(FRAMES.glob("*.png"))[:16]
    raw = np.stack([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths])
    H, W = raw.shape[1:]
    pattern = default_brief_pattern()
    det = cv2.FastFeatureDetector_create(20, True)
    kps_cv = [np.array([k.pt for k in det.detect(f)], np.float32) for f in raw]

    rows = []
    for B in (1, 16):
        cases, n_kp = _cases(B, raw, kps_cv, det, pattern, device)
        for name, ft, fc in cases:
            (t_torch, t_torch_min), (t_cv, t_cv_min) = time_pair(ft, fc, args.repeat, device)
            rows.append({"op": name, "B": B, "keypoints_per_frame": round(n_kp, 1),
                         "torch_ms": round(t_torch, 3), "torch_min_ms": round(t_torch_min, 3),
                         "torch_ms_per_image": round(t_torch / B, 3), "baseline_ms": round(t_cv, 3),
                         "baseline_min_ms": round(t_cv_min, 3), "ratio": round(t_torch / t_cv, 2)})

    print(f"\nLoop-closure features, {W}x{H}, device {device}, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads)\n")
    print("Baselines: fast = cv2.FastFeatureDetector; brief = cv2.GaussianBlur + numpy; "
          "hamming = cv2.batchDistance(NORM_HAMMING, K=1); all per image.\n")
    print("| op | B | kp / frame | torch ms (min) | torch ms / keyframe | baseline ms (min) | ratio torch/baseline |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['op']} | {r['B']} | {r['keypoints_per_frame']:.0f} | {r['torch_ms']:.2f} ({r['torch_min_ms']:.2f}) | "
              f"{r['torch_ms_per_image']:.2f} | {r['baseline_ms']:.2f} ({r['baseline_min_ms']:.2f}) | {r['ratio']:.2f} |")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": str(device), "torch": torch.__version__, "opencv": cv2.__version__,
            "torch_threads": torch.get_num_threads(), "opencv_threads": cv2.getNumThreads(),
            "machine": platform.machine(), "size": [W, H], "repeat": args.repeat, "n_query": N_QUERY,
            "note": "baselines per image: cv2 FAST; cv2.GaussianBlur + numpy BRIEF; cv2.batchDistance Hamming nearest (K=1)"}
    write_json_atomic(out, {"meta": meta, "rows": rows})
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
