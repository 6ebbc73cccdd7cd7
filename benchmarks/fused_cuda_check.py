"""The fused kernels on a device against the CPU kernels, the tensor LK and OpenCV (``benchmarks/gpu.sh``
runs it first on a CUDA machine).

On real pairs of the repo's EuRoC sample (150 VINS corners, 1,000 weak corners and 300 random points
each, some outside the image; the stereo pairs too), per pair and in total:

* the run-time self-check (``fused/selfcheck.py``) on the device;
* the fused pyramid on the device == the CPU kernel's packed pyramid (every byte);
* the fused LK on the device (plain, with the forward-backward check) == the CPU kernel (every lane:
  positions, status, also of lanes with status 0) == cv2 (status; positions where tracked);
* the tensor LK on the device: lanes where it differs from cv2 (reported, not a failure).

Exit status 1 on any difference between the fused device kernels and the CPU kernels or cv2. Writes
``benchmarks/results/fused_<device>.json`` (temp + rename).

Usage: ``python benchmarks/fused_cuda_check.py [--device cuda] [--pairs 23]`` (``--device cpu`` runs the
same comparisons on the CPU: a smoke test of the script).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import RESULTS, write_json_atomic  # noqa: E402

from torch_frontend.fused import selfcheck  # noqa: E402
from torch_frontend.fused.ops import lk_op, pyramid_op  # noqa: E402
from torch_frontend.lk import track_lk  # noqa: E402

CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
SAMPLE = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0"


def _points(img, rng):
    h, w = img.shape
    c = cv2.goodFeaturesToTrack(img, 150, 0.01, 30).reshape(-1, 2)
    weak = cv2.goodFeaturesToTrack(img, 1000, 1e-4, 3).reshape(-1, 2)
    return np.concatenate([c, weak, rng.uniform([-40, -40], [w + 40, h + 40], (300, 2))]).astype(np.float32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--pairs", type=int, default=23)
    a = ap.parse_args(argv)
    dev = torch.device(a.device)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    report = {"device": str(dev), "name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
              "selfcheck": selfcheck.cuda_selfcheck(dev) if dev.type == "cuda" else None}
    print(f"self-check on {dev}: {report['selfcheck'] or 'the stored bits'}")
    cam0 = sorted((SAMPLE / "cam0" / "data").glob("*.png"))
    cam1 = sorted((SAMPLE / "cam1" / "data").glob("*.png"))
    imgs = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in cam0]
    pairs = [(imgs[k], imgs[k + 1]) for k in range(min(a.pairs, len(imgs) - 1))]
    pairs += [(cv2.imread(str(l), 0), cv2.imread(str(r), 0)) for l, r in zip(cam0, cam1)]
    rng = np.random.default_rng(0)
    tot = {"points": 0, "pyramid_bytes_differ": 0, "fused_vs_cpu": 0, "fused_vs_cv2": 0, "fb_vs_cpu": 0,
           "tensor_vs_cv2": 0}
    for A, Bimg in pairs:
        pts = _points(A, rng)
        x = torch.from_numpy(np.stack([A, Bimg]))  # (2, H, W)
        P_cpu, Q_cpu = pyramid_op(x[:1], 3, 22), pyramid_op(x[1:], 3, 22)
        P_dev, Q_dev = pyramid_op(x[:1].to(dev), 3, 22), pyramid_op(x[1:].to(dev), 3, 22)
        tot["pyramid_bytes_differ"] += int((P_dev.cpu() != P_cpu).sum() + (Q_dev.cpu() != Q_cpu).sum())
        p = torch.from_numpy(pts)[None]
        v = torch.ones(p.shape[:2], dtype=torch.bool)
        H, W = A.shape
        for fb in (-1, 1):
            args = (H, W, 22, 22, 3, 21, 21, 30, 0.01, 1e-4, fb, 0.5, True)
            cpu = lk_op(P_cpu, Q_cpu, p, v, None, *args)
            got = lk_op(P_dev, Q_dev, p.to(dev), v.to(dev), None, *args)
            bad = ~(got[0].cpu() == cpu[0]).all(-1) | (got[1].cpu() != cpu[1]) | (got[2].cpu() != cpu[2])
            tot["fused_vs_cpu" if fb < 0 else "fb_vs_cpu"] += int(bad.sum())
            if fb < 0:
                ref, st, _ = cv2.calcOpticalFlowPyrLK(A, Bimg, pts.reshape(-1, 1, 2), None, winSize=(21, 21),
                                                      maxLevel=3, criteria=CRIT)
                ref, st = ref.reshape(-1, 2), st.ravel().astype(bool)
                o, s = got[0][0].cpu().numpy(), got[1][0].cpu().numpy()
                tot["fused_vs_cv2"] += int(((s != st) | (s & st & np.any(o != ref, 1))).sum())
                to, ts = track_lk(torch.from_numpy(A)[None, None].to(dev), torch.from_numpy(Bimg)[None, None].to(dev),
                                  p.to(dev), lk_backend="tensor")
                to, ts = to[0].cpu().numpy(), ts[0].cpu().numpy()
                tot["tensor_vs_cv2"] += int(((ts != st) | (ts & st & np.any(to != ref, 1))).sum())
        tot["points"] += len(pts)
    report.update(tot, pairs=len(pairs), seconds=round(time.perf_counter() - t0, 1))
    print(report)
    write_json_atomic(RESULTS / f"fused_{dev.type}.json", report)
    ok = report["selfcheck"] is None and all(tot[k] == 0 for k in ("pyramid_bytes_differ", "fused_vs_cpu", "fused_vs_cv2",
                                                                     "fb_vs_cpu"))
    print("fused kernels on", dev, "==", "CPU kernels == cv2" if ok else "DIFFER (see above)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
