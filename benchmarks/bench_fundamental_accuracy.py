"""Benchmark (issue 22): F-RANSAC accuracy against exact ground truth, and the tracker end to end
with ``F_method="opencv"`` vs ``"lo"``.

Inputs (exact ground truth):
* **planted**: 128 two-view problems per outlier rate (0, 10, 25, 40 %): 150 matches of random
  points at 3..15 m seen by two 460-px pinholes (752x480), Gaussian noise 0.3 px per coordinate in
  both images; the planted outliers replace the second-image point by a uniform one >= 20 px from
  the true match and >= 5 px from the true epipolar lines in both images (a uniform point within
  ~1 px of its line is geometrically an inlier). One more set, "10 %, noise in image 2 only",
  shows what the 1 px test allows when only one image is noisy.
* **flight**: tracker-like inputs from ``torch_frontend.testing.flight.synthetic_flight`` (33
  frames, 400x640, exact homographies): Shi-Tomasi corners of frame k (150, quality 0.01, 30 px
  apart, as VINS) tracked by ``cv2.calcOpticalFlowPyrLK`` (21x21, 3 levels) into frame k + s, s in
  {1, 2, 4, 8} (117 pairs), ground truth ``x2* = H_{k+s} H_k^-1 x1``; then the same outlier rates
  planted (>= 20 px from the true match; a planar scene has no unique F, so no line rule).
  True inliers: not planted and within 1 px of the truth; true outliers: planted or > 3 px off
  (LK failures); tracks in between count in neither.

Columns:
* inlier recall: share of the true inliers the method's mask keeps; outlier recall: share of the
  true outliers it rejects (its own mask and inlier test: cv2's USAC and kornia threshold the
  Sampson distance, OpenCV's FM_RANSAC and this library ``max(d1, d2)``, the point-to-epipolar-line
  distances in both images).
* recall @1px: inlier recall of the returned F under one common test, ``max(d1, d2) <= 1 px``
  (rejectWithF's), so that the F's are compared, not the tests.
* F error: for every true inlier, ``max(d1, d2)`` of its *noise-free* correspondence under the
  estimated F, px; median and 90th percentile over all true inliers of all problems.
* ms/problem at B = 1 (single calls) and B = 32 (one call per 32 problems): CPU, 1 thread for
  torch and OpenCV; cv2 and kornia solve one problem per call (no B = 32 figure).
* Rows: ``gt`` (the ground-truth F under the 1 px test: the ceiling of any estimator with this
  test), ``opencv`` / ``lo`` (``find_fundamental(method=...)``, default path), the same with
  ``capturable=True`` (overflow: share of problems beyond the fixed budgets), cv2
  ``findFundamentalMat`` FM_RANSAC / USAC_MAGSAC / USAC_ACCURATE (threshold 1, confidence 0.99),
  kornia ``RANSAC("fundamental", inl_th=1)``.

End to end: ``FeatureTracker`` (EuRoC config; the flight at 640x400) on the flight (clean, and with
Gaussian image noise of 8 grey levels), ``torch_frontend/data/euroc_mini`` and
``../shared/data/sequences/euroc_v1_01_easy_micro`` (cam0), ``F_method`` "opencv" vs "lo":
features per published frame, mean track length (the longest count of every published track),
tracks rejected by rejectWithF, and (flight) the ground-truth reprojection error of every
observation of a track (``|H_k H_k0^-1 uv_0 - uv_k|``, k0 its first frame).

Writes ``benchmarks/results/fundamental_accuracy.{json,md}`` (temp file + rename).
Run: ``.venv/bin/python benchmarks/bench_fundamental_accuracy.py [--problems 128] [--no-e2e]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import torch_frontend as tf  # noqa: E402
from torch_frontend import ransac  # noqa: E402
from torch_frontend.testing.flight import reprojection_errors, synthetic_flight  # noqa: E402
from torch_frontend.testing.two_view import line_distances  # noqa: E402
from torch_frontend.testing.two_view import planted_scenes as two_view_scenes  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, write_atomic, write_json_atomic  # noqa: E402

RATES = (0.0, 0.10, 0.25, 0.40)
THRESHOLD, CONFIDENCE = 1.0, 0.99
SHARED_MICRO = REPO.parent / "shared" / "data" / "sequences" / "euroc_v1_01_easy_micro"


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------
_line_dists = line_distances


def _opencv_error(F, a, c):
    return np.maximum(*_line_dists(F, a, c))


def planted_scenes(B, rate, seed, n=150, noise=0.3, noisy_first=True):
    """Problem dicts: p1, p2 (noisy, outliers planted), g1, g2 (noise-free), F, inlier/outlier masks
    (``torch_frontend.testing.two_view.planted_scenes``)."""
    s = two_view_scenes(B, rate, seed, n=n, noise=noise, noisy_first=noisy_first)
    return [dict(p1=s["p1"][b], p2=s["p2"][b], g1=s["g1"][b], g2=s["g2"][b], F=s["F"][b],
                 inlier=~s["planted"][b], outlier=s["planted"][b]) for b in range(B)]


def flight_problems(rate, seed, frames, Hs, steps=(1, 2, 4, 8)):
    """Tracker-like problems from the flight (see the module docstring), ``rate`` planted."""
    rng = np.random.default_rng(seed)
    lk = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
    H_, W_ = frames[0].shape
    out = []
    for s in steps:
        for k in range(len(frames) - s):
            pts = cv2.goodFeaturesToTrack(frames[k], 150, 0.01, 30)
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(frames[k], frames[k + s], pts, None, **lk)
            a, c = pts[:, 0].astype(np.float64), nxt[:, 0].astype(np.float64)
            keep = (st.ravel() == 1) & (c[:, 0] >= 0) & (c[:, 0] < W_) & (c[:, 1] >= 0) & (c[:, 1] < H_)
            a, c = a[keep], c[keep]
            Hk = Hs[k + s] @ np.linalg.inv(Hs[k])
            g = np.c_[a, np.ones(len(a))] @ Hk.T
            g = g[:, :2] / g[:, 2:]
            err = np.hypot(*(c - g).T)
            n = len(a)
            planted = np.zeros(n, bool)
            planted[rng.choice(n, int(round(rate * n)), replace=False)] = True
            for i in np.flatnonzero(planted):
                while True:
                    q = rng.uniform([0, 0], [W_, H_], 2)
                    if np.hypot(*(q - g[i])) >= 20:
                        c[i] = q
                        break
            out.append(dict(p1=a, p2=c, g1=a, g2=g, F=None, inlier=~planted & (err <= 1.0),
                            outlier=planted | (err > 3.0)))
    return out


def _pad(problems, N=150):
    """(B, N, 2) float64 p1, p2 and valid: N = 150 slots (the tracker's max_cnt; every problem has
    at most that many matches), so that the capturable path's tables are built once."""
    B = len(problems)
    p1 = torch.zeros(B, N, 2, dtype=torch.float64)
    p2 = torch.zeros(B, N, 2, dtype=torch.float64)
    valid = torch.zeros(B, N, dtype=torch.bool)
    for b, p in enumerate(problems):
        n = len(p["p1"])
        p1[b, :n], p2[b, :n], valid[b, :n] = torch.from_numpy(p["p1"]), torch.from_numpy(p["p2"]), True
    return p1, p2, valid


# ----------------------------------------------------------------------------------------------
# estimators: each returns per problem (F (3, 3) or None, mask (n,) bool) and ms per problem
# ----------------------------------------------------------------------------------------------
def _torch_estimator(method, capturable):
    def run_batch(problems):
        p1, p2, valid = _pad(problems)
        r = ransac.find_fundamental(p1, p2, valid, THRESHOLD, CONFIDENCE, method=method, capturable=capturable)
        res = []
        for b, p in enumerate(problems):
            n = len(p["p1"])
            res.append((r.F[b].numpy() if bool(r.ok[b]) else None, r.inliers[b, :n].numpy(), bool(r.overflow[b])))
        return res

    return run_batch


def _cv2_estimator(flag):
    def run_batch(problems):
        res = []
        for p in problems:
            F, m = cv2.findFundamentalMat(p["p1"].astype(np.float32), p["p2"].astype(np.float32), flag, THRESHOLD,
                                          CONFIDENCE)
            ok = F is not None and m is not None and F.shape[0] >= 3
            res.append((F[:3] if ok else None, m.ravel().astype(bool) if ok else np.zeros(len(p["p1"]), bool), False))
        return res

    return run_batch


def _kornia_estimator():
    from kornia.geometry.ransac import RANSAC

    est = RANSAC(model_type="fundamental", inl_th=THRESHOLD, confidence=CONFIDENCE, seed=0)

    def run_batch(problems):
        res = []
        for p in problems:
            F, m = est(torch.from_numpy(p["p1"]), torch.from_numpy(p["p2"]))
            F = F.double().numpy()
            res.append((F if np.abs(F).sum() > 0 else None, m.numpy().astype(bool), False))
        return res

    return run_batch


def estimators():
    rows = {
        "opencv": (_torch_estimator("opencv", False), True),
        "lo": (_torch_estimator("lo", False), True),
        "opencv (capturable)": (_torch_estimator("opencv", True), True),
        "lo (capturable)": (_torch_estimator("lo", True), True),
        "cv2 FM_RANSAC": (_cv2_estimator(cv2.FM_RANSAC), False),
    }
    for name in ("USAC_MAGSAC", "USAC_ACCURATE"):
        if hasattr(cv2, name):
            rows[f"cv2 {name}"] = (_cv2_estimator(getattr(cv2, name)), False)
    try:
        rows["kornia RANSAC"] = (_kornia_estimator(), False)
    except ImportError:  # pragma: no cover
        pass
    return rows


def _timed(fn, problems):
    t = time.perf_counter()
    out = fn(problems)
    return out, (time.perf_counter() - t) * 1e3 / max(len(problems), 1)


def evaluate(problems, results):
    """Recalls, recall @1px and F error over all problems (see the module docstring)."""
    kept_in = n_in = rej_out = n_out = kept_1px = 0
    errs, overflow = [], 0
    for p, (F, m, over) in zip(problems, results):
        inl, outl = p["inlier"], p["outlier"]
        n_in += inl.sum()
        n_out += outl.sum()
        kept_in += (m & inl).sum()
        rej_out += (~m & outl).sum()
        overflow += over
        if F is None:
            errs.append(np.full(inl.sum(), np.inf))
            continue
        kept_1px += (_opencv_error(F, p["p1"][inl], p["p2"][inl]) <= THRESHOLD).sum()
        errs.append(_opencv_error(F, p["g1"][inl], p["g2"][inl]))
    e = np.concatenate(errs)
    return dict(inlier_recall=float(kept_in / n_in), outlier_recall=float(rej_out / n_out) if n_out else None,
                recall_1px=float(kept_1px / n_in), err_median=float(np.median(e)), err_p90=float(np.quantile(e, 0.9)),
                overflow=float(overflow / len(problems)), problems=len(problems), true_inliers=int(n_in),
                true_outliers=int(n_out))


def accuracy(sets, timing_problems):
    rows = []
    ests = estimators()
    for set_name, problems in sets:
        if problems[0]["F"] is not None:  # the ceiling: the true F under the 1 px test
            gt = [(p["F"], _opencv_error(p["F"], p["p1"], p["p2"]) <= THRESHOLD, False) for p in problems]
            rows.append(dict(set=set_name, method="gt", **evaluate(problems, gt), ms_b1=None, ms_b32=None))
        for name, (fn, batched) in ests.items():
            fn(problems[:1])  # warm-up (B = 1 and 32): sample tables, device constants, imports
            fn(problems[:32])
            res, ms32 = [], []
            step = 32 if batched else len(problems)
            for i in range(0, len(problems), step):
                out, ms = _timed(fn, problems[i : i + step])
                res += out
                ms32.append(ms)
            ms_b1 = float(np.mean([_timed(fn, [p])[1] for p in problems[:timing_problems]]))
            row = dict(set=set_name, method=name, **evaluate(problems, res), ms_b1=ms_b1,
                       ms_b32=float(np.mean(ms32)) if batched else None)
            rows.append(row)
            print(f"{set_name:28s} {name:22s} recall {row['inlier_recall']:.4f} out {row['outlier_recall'] or 0:.4f} "
                  f"@1px {row['recall_1px']:.4f} err {row['err_median']:.4f}/{row['err_p90']:.3f} "
                  f"ms {ms_b1:.2f}/{row['ms_b32'] or 0:.2f} overflow {row['overflow']:.2f}", flush=True)
    return rows


# ----------------------------------------------------------------------------------------------
# end to end
# ----------------------------------------------------------------------------------------------
def run_tracker(method, frames, cfg, Hs=None, dt=0.05):
    """One FeatureTracker pass with ``F_method = method``: the tracker's figures (module docstring)."""
    from torch_frontend.tracker import FeatureTracker, TrackerParams, stages

    wired = "F_method" in {f.name for f in dataclasses.fields(TrackerParams)}
    orig = stages._find_fundamental_impl
    rejected = [0]

    def impl(*args, **kw):
        if not wired:  # the tracker does not pass F_method yet: pass it here (this script only)
            kw["method"] = method
        res = orig(*args, **kw)
        rejected[0] += int((args[2] & ~res.inliers & res.ok[:, None]).sum())
        return res

    stages._find_fundamental_impl = impl
    try:
        tr = FeatureTracker(cfg, num_streams=1)
        if wired:
            tr.params = dataclasses.replace(tr.params, F_method=method)
        t = time.perf_counter()
        out = [tr.track(torch.from_numpy(f)[None, None], [1.0 + dt * k]) for k, f in enumerate(frames)]
        wall = time.perf_counter() - t
    finally:
        stages._find_fundamental_impl = orig
    best, feats = {}, []
    for f in out:
        if not bool(f.published[0]):
            continue
        v = f.valid[0].numpy()
        feats.append(int(v.sum()))
        for i, c in zip(f.ids[0].numpy()[v].tolist(), f.track_count[0].numpy()[v].tolist()):
            best[i] = max(best.get(i, 0), c)
    row = dict(frames=len(frames), published=len(feats), features_per_frame=float(np.mean(feats)),
               mean_track_length=float(np.mean(list(best.values()))), tracks=len(best), rejected_by_F=rejected[0],
               ms_per_frame=wall * 1e3 / len(frames))
    if Hs is not None:
        e = reprojection_errors([(f.ids[0].numpy()[f.present[0].numpy()], f.uv[0].numpy()[f.present[0].numpy()])
                                 for f in out], Hs)
        row.update(gt_err_median=float(np.median(e)), gt_err_p90=float(np.quantile(e, 0.9)), observations=len(e))
    return row


def end_to_end(flight_frames, Hs):
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    fcfg = dataclasses.replace(cfg, image_width=flight_frames[0].shape[1], image_height=flight_frames[0].shape[0])
    rng = np.random.default_rng(8)
    noisy = [np.clip(f + rng.normal(0, 8.0, f.shape), 0, 255).astype(np.uint8) for f in flight_frames]
    seqs = [("flight", flight_frames, fcfg, Hs), ("flight + image noise 8", noisy, fcfg, Hs)]
    for name, root in (("euroc_mini", REPO / "torch_frontend" / "data" / "euroc_mini"), ("euroc_v1_01_easy_micro", SHARED_MICRO)):
        files = sorted((root / "mav0" / "cam0" / "data").glob("*.png"))
        if files:
            seqs.append((name, [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files], cfg, None))
        else:
            print(f"skipped {name}: no frames under {root}")
    rows = []
    for name, frames, c, H in seqs:
        for method in ("opencv", "lo"):
            row = dict(sequence=name, F_method=method, **run_tracker(method, frames, c, H))
            rows.append(row)
            print(name, method, {k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()
                                 if k not in ("sequence", "F_method")}, flush=True)
    return rows


# ----------------------------------------------------------------------------------------------
# report
# ----------------------------------------------------------------------------------------------
def _f(x, fmt="{:.4f}"):
    return "—" if x is None else fmt.format(x)


def summary_rows(rows):
    """Per family (planted at 0.3 px both images / flight) and method: recalls averaged over the
    four rates (outlier recall over 10..40 %), F error pooled (median of the per-rate medians, p90
    of the per-rate p90s: the sets have the same sizes), ms at 25 %."""
    out = []
    for fam in ("planted", "flight"):
        sets = [r for r in rows if r["set"].startswith(fam) and "image 2 only" not in r["set"]]
        for m in dict.fromkeys(r["method"] for r in sets):
            rs = [r for r in sets if r["method"] == m]
            at25 = [r for r in rs if "25 %" in r["set"]]
            out.append(dict(family=fam, method=m,
                            inlier_recall=float(np.mean([r["inlier_recall"] for r in rs])),
                            outlier_recall=float(np.mean([r["outlier_recall"] for r in rs if not r["set"].endswith(" 0 %")])),
                            recall_1px=float(np.mean([r["recall_1px"] for r in rs])),
                            err_median=float(np.median([r["err_median"] for r in rs])),
                            err_p90=float(np.median([r["err_p90"] for r in rs])),
                            err_median_worst=float(max(r["err_median"] for r in rs)),
                            ms_b1=at25[0]["ms_b1"] if at25 else None, ms_b32=at25[0]["ms_b32"] if at25 else None))
    return out


def markdown(meta, rows, summ, e2e):
    L = ["# F-RANSAC accuracy against ground truth (`bench_fundamental_accuracy.py`)", "",
         f"Machine: {meta['machine']}; torch {meta['torch']}, OpenCV {meta['cv2']}, kornia {meta['kornia']}; "
         f"1 thread. Threshold {THRESHOLD} px, confidence {CONFIDENCE}.", "",
         "Definitions: see the script's docstring (inlier/outlier recall: the method's own mask; recall @1px: "
         "the returned F under rejectWithF's test `max(d1, d2) <= 1 px`; F error: `max(d1, d2)` of the "
         "noise-free correspondences of the true inliers under the estimated F, px).", "",
         "## Summary (recalls averaged over 0/10/25/40 %, outlier recall over 10..40 %; F error: median of the "
         "per-rate medians / p90s, worst rate's median; ms at 25 %)", "",
         "| inputs | method | inlier recall | outlier recall | recall @1px | F error median | F error p90 | worst median | ms B=1 | ms B=32 |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for r in summ:
        L.append(f"| {r['family']} | {r['method']} | {_f(r['inlier_recall'])} | {_f(r['outlier_recall'])} | "
                 f"{_f(r['recall_1px'])} | {_f(r['err_median'], '{:.3f}')} | {_f(r['err_p90'], '{:.3f}')} | "
                 f"{_f(r['err_median_worst'], '{:.3f}')} | {_f(r['ms_b1'], '{:.2f}')} | {_f(r['ms_b32'], '{:.2f}')} |")
    L += ["", "## Every set", "",
          "| set | method | inlier recall | outlier recall | recall @1px | F error median | F error p90 | ms B=1 | ms B=32 | overflow |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['set']} | {r['method']} | {_f(r['inlier_recall'])} | {_f(r['outlier_recall'])} | "
                 f"{_f(r['recall_1px'])} | {_f(r['err_median'], '{:.3f}')} | {_f(r['err_p90'], '{:.3f}')} | "
                 f"{_f(r['ms_b1'], '{:.2f}')} | {_f(r['ms_b32'], '{:.2f}')} | {_f(r['overflow'], '{:.2f}')} |")
    if e2e:
        L += ["", "## End to end: FeatureTracker, F_method \"opencv\" vs \"lo\"", "",
              "| sequence | F_method | published frames | features / frame | mean track length | tracks | rejected by F | GT error median px | GT error p90 px | ms / frame |",
              "|---|---|---|---|---|---|---|---|---|---|"]
        for r in e2e:
            L.append(f"| {r['sequence']} | {r['F_method']} | {r['published']} | {r['features_per_frame']:.1f} | "
                     f"{r['mean_track_length']:.2f} | {r['tracks']} | {r['rejected_by_F']} | "
                     f"{_f(r.get('gt_err_median'), '{:.3f}')} | {_f(r.get('gt_err_p90'), '{:.3f}')} | {r['ms_per_frame']:.1f} |")
    return "\n".join(L) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", type=int, default=128, help="planted problems per outlier rate")
    ap.add_argument("--timing-problems", type=int, default=16, help="single calls timed per set (B = 1)")
    ap.add_argument("--flight-frames", type=int, default=33)
    ap.add_argument("--no-e2e", action="store_true")
    ap.add_argument("--out", default=str(RESULTS / "fundamental_accuracy.json"))
    ap.add_argument("--report-only", action="store_true", help="rewrite the summary and the .md from --out's rows")
    args = ap.parse_args()
    out = Path(args.out)
    if args.report_only:
        d = json.loads(out.read_text())
        d["summary"] = summary_rows(d["accuracy"])
        write_json_atomic(out, d)
        write_atomic(out.with_suffix(".md"), markdown(d["meta"], d["accuracy"], d["summary"], d["end_to_end"]).encode())
        return
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    import kornia

    meta = dict(machine=f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread",
                torch=torch.__version__, cv2=cv2.__version__, kornia=kornia.__version__, python=platform.python_version(),
                problems=args.problems, flight_frames=args.flight_frames)
    frames, Hs = synthetic_flight(n_frames=args.flight_frames)
    sets = []
    for rate in RATES:
        sets.append((f"planted {int(rate * 100)} %", planted_scenes(args.problems, rate, seed=1000 + int(rate * 100))))
    sets.append(("planted 10 %, noise in image 2 only", planted_scenes(args.problems, 0.10, seed=2010, noisy_first=False)))
    for rate in RATES:
        sets.append((f"flight {int(rate * 100)} %", flight_problems(rate, 3000 + int(rate * 100), frames, Hs)))
    rows = accuracy(sets, args.timing_problems)
    summ = summary_rows(rows)
    e2e = [] if args.no_e2e else end_to_end(frames, Hs)
    write_json_atomic(out, dict(meta=meta, accuracy=rows, summary=summ, end_to_end=e2e))
    write_atomic(out.with_suffix(".md"), markdown(meta, rows, summ, e2e).encode())
    print(f"wrote {out} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
