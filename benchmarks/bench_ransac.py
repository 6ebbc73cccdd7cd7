"""Benchmark: batched fundamental-matrix RANSAC vs a loop of cv2.findFundamentalMat and of kornia's
RANSAC('fundamental').

* Batch rows: B = 1, 8, 64 problems of 150 correspondences each (synthetic non-planar scenes in
  VINS's 460-px virtual pinhole, 0.3 px noise, 25 % gross outliers by default), threshold 1 px,
  confidence 0.99; median ms over repeats (warm sample tables), per problem, ratio vs OpenCV.
* Tracker row (mimics ``FeatureTracker._track_mono``): 20 consecutive calls on B = 1 (and 8) streams,
  N = 150 slots of which 140..150 are valid (the count changes every call), float32 points,
  ``seed=0``, 10 % gross outliers by default; starts with empty sample-table caches, so the table
  generation for every new n is included. Reports the mean per call (median over repeats of the
  whole sequence).

Prints a markdown table and writes ``benchmarks/results/ransac.json`` (temp file + rename).

Run: ``.venv/bin/python benchmarks/bench_ransac.py [--device cpu] [--rate 0.25] [--repeats 5]``
"""

from __future__ import annotations

import argparse
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

from torch_frontend.ransac import find_fundamental  # noqa: E402
from torch_frontend.ransac.samples import _clear_sample_caches  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import sync, write_json_atomic  # noqa: E402


def make_problems(B: int, n: int = 150, rate: float = 0.25, noise: float = 0.3, seed: int = 0):
    rng = np.random.default_rng(seed)
    K = np.array([[460.0, 0, 376.0], [0, 460.0, 240.0], [0, 0, 1.0]])
    P1, P2 = [], []
    for _ in range(B):
        z = rng.uniform(3.0, 15.0, n)
        X = np.stack([rng.uniform(-0.8, 0.8, n) * z, rng.uniform(-0.5, 0.5, n) * z, z], -1)
        R, _ = cv2.Rodrigues(rng.normal(0, 0.05, 3))
        t = rng.normal(0, 0.3, 3) + np.array([0.4, 0.0, 0.1])
        x1 = X @ K.T
        x2 = (X @ R.T + t) @ K.T
        a = x1[:, :2] / x1[:, 2:] + rng.normal(0, noise, (n, 2))
        c = x2[:, :2] / x2[:, 2:] + rng.normal(0, noise, (n, 2))
        m = int(round(rate * n))
        idx = rng.choice(n, m, replace=False)
        c[idx] = rng.uniform([0, 0], [752, 480], (m, 2))
        P1.append(a.astype(np.float32))
        P2.append(c.astype(np.float32))
    return np.stack(P1), np.stack(P2)




def timeit(fn, repeats: int, device) -> float:
    fn()  # warm-up (sample tables, allocator)
    ts = []
    for _ in range(repeats):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts)


def kornia_ransac():
    try:
        from kornia.geometry.ransac import RANSAC

        return RANSAC("fundamental", inl_th=1.0, confidence=0.99, seed=0)
    except Exception as exc:  # API differs between kornia versions
        print(f"kornia RANSAC unavailable: {exc!r}", file=sys.stderr)
        return None


def batch_rows(args, device, kr) -> list:
    rows = []
    for B in [int(s) for s in args.sizes.split(",")]:
        P1, P2 = make_problems(B, rate=args.rate)
        p1 = torch.from_numpy(P1).to(device)
        p2 = torch.from_numpy(P2).to(device)

        def ours(p1=p1, p2=p2):
            return find_fundamental(p1, p2, threshold=1.0, confidence=0.99)

        def opencv(P1=P1, P2=P2):
            return [cv2.findFundamentalMat(a, c, cv2.FM_RANSAC, 1.0, 0.99) for a, c in zip(P1, P2)]

        t_ours = timeit(ours, args.repeats, device)
        t_cv = timeit(opencv, args.repeats, torch.device("cpu"))
        res = ours()
        cvm = opencv()
        agree = float(np.mean([np.mean(res.inliers[b].cpu().numpy() == cvm[b][1].ravel().astype(bool)) for b in range(B)]))
        t_kornia = None
        if kr is not None and not args.no_kornia:
            k1 = [torch.from_numpy(P1[b]).to(device) for b in range(B)]
            k2 = [torch.from_numpy(P2[b]).to(device) for b in range(B)]

            def kornia_loop(k1=k1, k2=k2):
                with torch.no_grad():
                    return [kr(a, c) for a, c in zip(k1, k2)]

            try:
                # kornia is slow on CPU: fewer repeats for the big batch
                t_kornia = timeit(kornia_loop, 1 if B > 8 else max(1, min(args.repeats, 3)), device)
            except Exception as exc:
                print(f"kornia RANSAC failed: {exc!r}", file=sys.stderr)
        rows.append(
            {
                "case": "batch",
                "B": B,
                "N": P1.shape[1],
                "outlier_rate": args.rate,
                "ours_ms": t_ours,
                "opencv_loop_ms": t_cv,
                "kornia_loop_ms": t_kornia,
                "ours_per_problem_ms": t_ours / B,
                "opencv_per_problem_ms": t_cv / B,
                "ours_vs_opencv": t_ours / t_cv,
                "ours_vs_kornia": None if t_kornia is None else t_ours / t_kornia,
                "mask_agreement_vs_opencv": agree,
                "mean_samples": float(res.num_iters.double().mean()),
            }
        )
    return rows


def tracker_rows(args, device) -> list:
    """20 consecutive calls as in FeatureTracker._track_mono: n valid of N = 150 slots changes every
    call, seed 0, float32; cold sample-table caches at the start."""
    rows = []
    for B in [int(s) for s in args.tracker_sizes.split(",")]:
        rng = np.random.default_rng(1)
        calls = []
        for i in range(args.tracker_calls):
            P1, P2 = make_problems(B, rate=args.tracker_rate, seed=100 + i)
            n = rng.integers(140, 151, B)
            valid = np.arange(150)[None, :] < n[:, None]
            P1 = np.where(valid[..., None], P1, np.nan).astype(np.float32)
            P2 = np.where(valid[..., None], P2, np.nan).astype(np.float32)
            calls.append((P1, P2, valid))
        torch_calls = [
            (torch.from_numpy(a).to(device), torch.from_numpy(c).to(device), torch.from_numpy(v).to(device))
            for a, c, v in calls
        ]
        find_fundamental(torch_calls[0][0][:, :20], torch_calls[0][1][:, :20], seed=12345)  # torch warm-up only
        means, firsts, cv_means, iters = [], [], [], []
        for _ in range(args.repeats):  # the whole sequence, each time from cold caches
            # the process-wide sample-table caches start empty, as in a fresh tracker
            _clear_sample_caches()
            ts = []
            for p1, p2, v in torch_calls:
                sync(device)
                t0 = time.perf_counter()
                res = find_fundamental(p1, p2, v, threshold=1.0, confidence=0.99, seed=0)
                sync(device)
                ts.append((time.perf_counter() - t0) * 1e3)
                iters.append(float(res.num_iters.double().mean()))
            means.append(statistics.mean(ts))
            firsts.append(ts[0])
            t0 = time.perf_counter()
            for P1, P2, valid in calls:
                for b in range(B):
                    cv2.findFundamentalMat(P1[b][valid[b]], P2[b][valid[b]], cv2.FM_RANSAC, 1.0, 0.99)
            cv_means.append((time.perf_counter() - t0) * 1e3 / len(calls))
        t_ours, t_cv = statistics.median(means), statistics.median(cv_means)
        agree = []
        for (P1, P2, valid), (p1, p2, v) in zip(calls, torch_calls):
            res = find_fundamental(p1, p2, v, threshold=1.0, confidence=0.99, seed=0)
            for b in range(B):
                m = cv2.findFundamentalMat(P1[b][valid[b]], P2[b][valid[b]], cv2.FM_RANSAC, 1.0, 0.99)[1].ravel().astype(bool)
                agree.append(float(np.mean(res.inliers[b][v[b]].cpu().numpy() == m)))
        rows.append(
            {
                "case": "tracker",
                "B": B,
                "N": 150,
                "outlier_rate": args.tracker_rate,
                "calls": args.tracker_calls,
                "ours_ms": t_ours,
                "ours_first_call_ms": statistics.median(firsts),
                "opencv_loop_ms": t_cv,
                "kornia_loop_ms": None,
                "ours_per_problem_ms": t_ours / B,
                "opencv_per_problem_ms": t_cv / B,
                "ours_vs_opencv": t_ours / t_cv,
                "ours_vs_kornia": None,
                "mask_agreement_vs_opencv": float(np.mean(agree)),
                "mean_samples": float(np.mean(iters)),
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--rate", type=float, default=0.25)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    ap.add_argument("--sizes", default="1,8,64")
    ap.add_argument("--tracker-sizes", default="1,8")
    ap.add_argument("--tracker-calls", type=int, default=20)
    ap.add_argument("--tracker-rate", type=float, default=0.10)
    ap.add_argument("--no-kornia", action="store_true")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "ransac.json"))
    args = ap.parse_args()
    device = torch.device(args.device)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    kr = None if args.no_kornia else kornia_ransac()
    rows = tracker_rows(args, device) + batch_rows(args, device, kr)
    print(f"\n### find_fundamental ({device.type}, torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"cv2 {cv2.__version__}, N = 150; batch rows {args.rate:.0%} outliers, median of {args.repeats}; tracker rows "
          f"{args.tracker_rate:.0%} outliers, n = 140..150 changing, mean of {args.tracker_calls} calls from cold caches, median of {args.repeats})\n")
    print("| case | B | ours ms | cv2 loop ms | kornia loop ms | ours ms / problem | cv2 ms / problem | ours / cv2 | "
          "ours / kornia | mask = cv2 | samples |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        kms = "n/a" if r["kornia_loop_ms"] is None else f"{r['kornia_loop_ms']:.1f}"
        kr_ = "n/a" if r["ours_vs_kornia"] is None else f"{r['ours_vs_kornia']:.2f}"
        print(
            f"| {r['case']} | {r['B']} | {r['ours_ms']:.2f} | {r['opencv_loop_ms']:.2f} | {kms} | "
            f"{r['ours_per_problem_ms']:.2f} | {r['opencv_per_problem_ms']:.2f} | {r['ours_vs_opencv']:.2f} | {kr_} | "
            f"{r['mask_agreement_vs_opencv']:.2%} | {r['mean_samples']:.0f} |"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "benchmark": "ransac",
        "device": device.type,
        "torch": torch.__version__,
        "opencv": cv2.__version__,
        "threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "rows": rows,
    }
    write_json_atomic(out, payload)
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
