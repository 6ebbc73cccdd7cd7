"""setMask as the tracker runs it: the fused op (``torch_frontend::set_mask``) against the tensor kernel.

The inputs are the tracker's own setMask calls (``stages.set_mask``'s arguments, recorded while it
tracks the repo's EuRoC sample, cam0, 752x480, MIN_DIST 30, up to 150 features), B streams per call
(B calls stacked). Each side is timed as the stage runs it, base mask included: the tensor kernel on
a fresh all-255 ``(B, H, W)`` mask (the stage's ``torch.full``), default and capturable paths; the
fused op on one cached ``(1, H, W)`` base. The two sides alternate (a shared machine's load hits both
alike); the same bits are asserted first. Prints a markdown table (median and min ms per call, ms per
stream, the ratio of medians fused / tensor).

Usage: ``python benchmarks/bench_mask.py [--B 1 16] [--repeat N] [--threads N]`` (1 thread, 30 repeats)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import torch_frontend as tf  # noqa: E402
from torch_frontend.masks import _distance_mask_impl  # noqa: E402
from torch_frontend.tracker import FeatureTracker, stages  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import apply_threads, time_pair  # noqa: E402

FRAMES = REPO / "torch_frontend" / "data" / "euroc_mini" / "mav0" / "cam0" / "data"


def record_calls(n_frames: int = 24):
    """The tracker's setMask calls on the sample: ``[(pts, cnt, valid, radius)]`` (one stream each)."""
    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    calls = []
    impl = stages._distance_mask_impl

    def spy(pts, pri, valid, radius, mask, **kw):
        calls.append((pts.detach().clone(), pri.clone(), valid.clone(), radius))
        return impl(pts, pri, valid, radius, mask, **kw)

    stages._distance_mask_impl = spy
    try:
        tr = FeatureTracker(cfg, num_streams=1)
        for p in sorted(FRAMES.glob("*.png"))[:n_frames]:
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            tr.track(torch.from_numpy(img)[None, None], [int(p.stem) * 1e-9])
    finally:
        stages._distance_mask_impl = impl
    return calls, (cfg.image_height, cfg.image_width)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--B", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    apply_threads(a.threads)
    calls, (H, W) = record_calls()
    full = calls[-1]  # a late call: a full table of tracks
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); setMask calls recorded: {len(calls)}, "
          f"features in the timed call: {int(full[2].sum())}, MIN_DIST {full[3]:g}, {W}x{H}\n")
    print("| B | path | fused median (min) ms | tensor median (min) ms | fused per stream ms | fused / tensor |")
    print("|---|---|---|---|---|---|")
    base1 = torch.full((1, H, W), 255, dtype=torch.uint8)
    r = float(full[3])
    for B in a.B:
        pts, cnt, valid = (full[i].expand(B, *full[i].shape[1:]).contiguous() for i in range(3))
        for cap in (False, True):
            def fused(pts=pts, cnt=cnt, valid=valid, cap=cap):
                return _distance_mask_impl(pts, cnt, valid, r, base1, capturable=cap, backend="fused")

            def tensor(pts=pts, cnt=cnt, valid=valid, cap=cap, B=B):
                m = torch.full((B, H, W), 255, dtype=torch.uint8)
                return _distance_mask_impl(pts, cnt, valid, r, m, capturable=cap)

            f, t = fused(), tensor()
            assert torch.equal(f.keep, t.keep) and torch.equal(f.mask, t.mask)
            (fm, fmin), (tm, tmin) = time_pair(fused, tensor, a.repeat, torch.device("cpu"))
            print(f"| {B} | {'capturable' if cap else 'default'} | {fm:.3f} ({fmin:.3f}) | {tm:.3f} ({tmin:.3f}) | "
                  f"{fm / B:.3f} | {fm / tm:.2f} |")


if __name__ == "__main__":
    main()
