"""Loop-closure PnP-RANSAC benchmark: batched ``pnp_ransac`` (torch backend) vs a loop of
``cv2.solvePnPRansac`` called as VINS does (K = I, ITERATIVE, 100 iterations, 10/460, 0.99).

Synthetic problems as in tests/test_loop_pnp.py: a random pose, 100 world points at depth 2..10 m
in front of a 752 x 480, f = 460 camera, 1 px Gaussian noise, 30 % outliers (uniform in the
image). B = 1, 16, 64, 256 problems per call. Reports the median (and min) ms per call, ms per
problem, the ratio torch / OpenCV (< 1: torch faster), the inlier-flag agreement with OpenCV and
both rotation errors against the ground truth (median and max, degrees). Torch and OpenCV calls
alternate, so load from other processes hits both alike. Prints a markdown table and writes
``benchmarks/results/loop_pnp.json`` (temp file + rename).

Usage: ``python benchmarks/bench_loop_pnp.py [--device cpu|cuda] [--repeat N] [--threads N]
[--dtype float64|float32] [--sizes 1,16,64,256]`` (default: 1 thread, 5 repeats, float64)
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

from torch_frontend.loop.pnp import pnp_ransac  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, kernel_bench_parser, time_pair, write_json_atomic  # noqa: E402

THR = 10.0 / 460.0
W2, H2 = 376.0 / 460.0, 240.0 / 460.0


def make_problems(B, n=100, rate=0.3, noise_px=1.0, seed0=0):
    Xs, ps, Rs, ts = [], [], [], []
    for seed in range(seed0, seed0 + B):
        rng = np.random.default_rng(seed)
        R, _ = cv2.Rodrigues(rng.normal(0.0, 1.0, 3))
        t = rng.normal(0.0, 1.0, 3)
        z = rng.uniform(2.0, 10.0, n)
        uv = np.stack([rng.uniform(-W2, W2, n), rng.uniform(-H2, H2, n)], -1)
        X = (np.concatenate([uv * z[:, None], z[:, None]], -1) - t) @ R
        p = uv + rng.normal(0.0, noise_px / 460.0, (n, 2))
        m = int(round(rate * n))
        idx = rng.choice(n, m, replace=False)
        p[idx] = np.stack([rng.uniform(-W2, W2, m), rng.uniform(-H2, H2, m)], -1)
        Xs.append(X)
        ps.append(p)
        Rs.append(R)
        ts.append(t)
    return np.stack(Xs), np.stack(ps), np.stack(Rs), np.stack(ts)


def rot_err_deg(Ra, Rb):
    d = np.linalg.norm(np.asarray(Ra, np.float64) - Rb, axis=(-2, -1))
    return np.degrees(2.0 * np.arcsin(np.clip(d / np.sqrt(8.0), 0.0, 1.0)))






def cv_loop(X, p):
    out = []
    for b in range(len(X)):
        out.append(cv2.solvePnPRansac(X[b], p[b], np.eye(3), None, np.zeros((3, 1)), np.zeros((3, 1)),
                                      useExtrinsicGuess=False, iterationsCount=100, reprojectionError=THR,
                                      confidence=0.99, flags=cv2.SOLVEPNP_ITERATIVE))
    return out


def main(argv=None):
    ap = kernel_bench_parser(__doc__, "loop_pnp.json", repeat=5)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--sizes", default="1,16,64,256")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    apply_threads(args.threads)

    rows = []
    for B in [int(s) for s in args.sizes.split(",")]:
        X, p, R, t = make_problems(B)
        Xt = torch.from_numpy(X).to(device, dtype)
        pt = torch.from_numpy(p).to(device, dtype)

        def ft(Xt=Xt, pt=pt):
            return pnp_ransac(Xt, pt)

        def fc(X=X, p=p):
            return cv_loop(X, p)

        (t_med, t_min), (c_med, c_min) = time_pair(ft, fc, args.repeat, device)
        res = ft()
        cvr = fc()
        cv_inl = np.zeros((B, X.shape[1]), bool)
        cv_R = np.tile(np.eye(3), (B, 1, 1))
        for b, (ok, rvec, _tvec, idx) in enumerate(cvr):
            if ok and idx is not None:
                cv_inl[b, idx.ravel()] = True
                cv_R[b] = cv2.Rodrigues(rvec)[0]
        e_t = rot_err_deg(res.R.cpu().double().numpy(), R)
        e_c = rot_err_deg(cv_R, R)
        rows.append({
            "B": B, "N": X.shape[1], "torch_ms": round(t_med, 3), "torch_min_ms": round(t_min, 3),
            "torch_ms_per_problem": round(t_med / B, 4), "opencv_ms": round(c_med, 3),
            "opencv_min_ms": round(c_min, 3), "opencv_ms_per_problem": round(c_med / B, 4),
            "ratio": round(t_med / c_med, 3),
            "inlier_agreement": round(float((res.inliers.cpu().numpy() == cv_inl).mean()), 5),
            "torch_ok": int(res.ok.sum()), "opencv_ok": int(sum(bool(r[0]) for r in cvr)),
            "torch_rot_err_median_deg": round(float(np.median(e_t)), 5),
            "opencv_rot_err_median_deg": round(float(np.median(e_c)), 5),
            "torch_rot_err_max_deg": round(float(e_t.max()), 5),
            "opencv_rot_err_max_deg": round(float(e_c.max()), 5),
        })

    print(f"\nPnP-RANSAC, N = 100, 30 % outliers, 1 px noise, device {device}, {args.dtype}, torch "
          f"{torch.__version__} ({torch.get_num_threads()} threads), OpenCV {cv2.__version__} "
          f"({cv2.getNumThreads()} threads), median of {args.repeat}\n")
    print("| B | torch ms (min) | torch ms / problem | cv2 loop ms (min) | cv2 ms / problem | torch / cv2 | "
          "inliers = cv2 | ok torch / cv2 | rot err median torch / cv2 (deg) | rot err max torch / cv2 (deg) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['B']} | {r['torch_ms']:.2f} ({r['torch_min_ms']:.2f}) | {r['torch_ms_per_problem']:.3f} | "
              f"{r['opencv_ms']:.2f} ({r['opencv_min_ms']:.2f}) | {r['opencv_ms_per_problem']:.3f} | {r['ratio']:.2f} | "
              f"{r['inlier_agreement']:.2%} | {r['torch_ok']} / {r['opencv_ok']} | "
              f"{r['torch_rot_err_median_deg']:.4f} / {r['opencv_rot_err_median_deg']:.4f} | "
              f"{r['torch_rot_err_max_deg']:.4f} / {r['opencv_rot_err_max_deg']:.4f} |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": str(device), "dtype": args.dtype, "torch": torch.__version__, "opencv": cv2.__version__,
            "torch_threads": torch.get_num_threads(), "opencv_threads": cv2.getNumThreads(),
            "machine": platform.machine(), "repeat": args.repeat,
            "problem": "N=100, depth 2..10, f=460, 752x480, 1 px noise, 30 % outliers; threshold 10/460, "
                       "100 iterations, confidence 0.99",
            "opencv_call": "cv2.solvePnPRansac(K=I, ITERATIVE, useExtrinsicGuess=False) per problem"}
    write_json_atomic(out, {"meta": meta, "rows": rows})
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
