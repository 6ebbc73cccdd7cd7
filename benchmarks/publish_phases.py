"""Modelled GPU cost of the capturable mono step when the streams publish out of phase.

``../shared/tools/cuda_sim/roofline.py`` plays every stream with the same 20 Hz stamps, so the
streams publish together (an in-phase rig: every step is track-only or every-stream). Independent
sequences are rarely in phase: here a share of the streams gets its second image 0.1 s after the
first (one 20 Hz frame later), which moves their publish steps by one frame, so about that share
publishes on the steps the others do not. The step then runs rejectWithF, setMask and GFTT on a
sub-batch of the publishing streams (``tracker.clock.publish_plan``). Prints per measured step the
host's plan, kernels, MB moved and the modelled H100 CUDA-graph time, then the means.

    .venv/bin/python benchmarks/publish_phases.py --B 4 16 [--shifted 0.5] [--steps 4] [--warmup 3]
        [--compare]

Frames, config and the roofline model are the tool's (imported); ``--compare`` checks the outputs
against a plain CPU tracker on the same stamps.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
TOOLS = REPO.parent / "shared" / "tools" / "cuda_sim"


def shifted_stamps(shifted: float, hz: float = 20.0):
    """``stamps(B, k)`` for the tools: the first ``round(shifted * B)`` streams (every other one when
    ``shifted`` is 0.5) skip 0.1 s after their first image, the others run at ``hz`` from 0."""

    def stamps(B, k):
        t = torch.full((B,), k / hz, dtype=torch.float64)
        n = round(shifted * B)
        idx = torch.arange(1, B, 2)[:n] if abs(shifted - 0.5) < 1e-9 else torch.arange(n)
        if k >= 1:
            t[idx] += 1.0 / hz
        return t

    return stamps


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--B", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--shifted", type=float, default=0.5, help="share of the streams one frame out of phase")
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--compare", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    sys.path.insert(0, str(TOOLS))
    import count_step
    import roofline

    from torch_frontend.tracker import feature_tracker as ftm

    count_step.stamps = shifted_stamps(args.shifted)
    plans = []
    real_plan = ftm.FeatureTracker._plan

    def spy(self, *a):
        plan, host = real_plan(self, *a)
        plans.append(plan.name)
        return plan, host

    ftm.FeatureTracker._plan = spy
    cfg = count_step.default_config()
    print(f"torch_frontend from {Path(ftm.__file__).parents[1]}; {args.shifted:.0%} of the streams one frame "
          f"out of phase; {args.warmup} warm-up + {args.steps} measured steps")
    for B in args.B:
        plans.clear()
        rec, snaps, _, diffs = roofline.measure(cfg, B, count_step.EurocFrames(B), {"capturable": True},
                                                warmup=args.warmup, steps=args.steps, compare_outputs=args.compare)
        fig = roofline.summarise(rec, snaps, B)
        names = plans[args.warmup:args.warmup + args.steps]
        print(f"== B={B}")
        print("   step  plan     kernels    MB/step  MB/stream  H100 graph ms")
        tot = [0.0, 0.0, 0.0]
        for k, (name, step) in enumerate(zip(names, rec.steps)):
            s = step["totals"]
            mb = (s["read"] + s["write"]) / 1e6
            tot = [tot[0] + s["kernels"], tot[1] + mb, tot[2] + s["H100:graph"] * 1e3]
            print(f"   {args.warmup + k:4d}  {name:6s}  {s['kernels']:7,d}  {mb:9.1f}  {mb / B:9.1f}  {s['H100:graph'] * 1e3:13.2f}")
        n = max(len(rec.steps), 1)
        print(f"   mean          {tot[0] / n:7,.0f}  {tot[1] / n:9.1f}  {tot[1] / n / B:9.1f}  {tot[2] / n:13.2f}")
        print(f"   host syncs per step besides the input upload: {fig['totals']['syncs_excl_input']:.1f}")
        print("   mean MB per stream by stage: " + ", ".join(
            f"{row} {(r.get('read', 0) + r.get('write', 0)) / 1e6 / B:.1f}" for row, r in fig["rows"].items()))
        if diffs is not None:
            print("   outputs vs a plain CPU tracker: " + ("identical" if not diffs else "; ".join(diffs)))


if __name__ == "__main__":
    main()
