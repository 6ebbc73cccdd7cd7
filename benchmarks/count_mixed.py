"""Launches and host syncs per step of a mixed batch (per-stream configs) vs a homogeneous one, on the
simulated CUDA device of ``../shared/tools/cuda_sim`` (``count_step.py``'s counting, this script's
batches).

Usage (from the project root):
    .venv/bin/python benchmarks/count_mixed.py [--B 5 10] [--capturable] [--json out.json]

Batches: ``homogeneous`` = B EuRoC streams (``configs/euroc.yaml``); ``rig of B calibrations`` =
the same with every stream's own intrinsics (one group, a ``CameraBatch``); ``five configs`` = the repo's
and VINS's shipped configs cycled over the B streams (pinhole 752x480, Kannala-Brandt 512x512
fisheye, pinhole 640x480, MEI 752x480 equalize 0, Kannala-Brandt 752x480; the last four from
``../shared/data/vins_configs``), images given as one padded ``(B, 1, 512, 752)`` tensor with
``sizes``. Frames: the sample EuRoC frames, warped per stream (count_step's ``EurocFrames``),
cropped or padded to each stream's size.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TOOLS = REPO.parent / "shared" / "tools" / "cuda_sim"
SHIPPED = REPO.parent / "shared" / "data" / "vins_configs" / "vins_mono"
FIVE = (REPO / "configs" / "euroc.yaml", SHIPPED / "tum" / "tum_config.yaml",
        SHIPPED / "realsense" / "realsense_color_config.yaml", SHIPPED / "3dm" / "3dm_config.yaml",
        SHIPPED / "cla" / "cla_config.yaml")


def count(cfgs, B, warmup, steps, kw):
    import count_step
    import numpy as np
    import simcuda
    import torch
    from simcuda import LOG

    import torch_frontend as tf

    frames = count_step.EurocFrames(B)
    sizes = [(c.image_height, c.image_width) for c in cfgs]
    H, W = max(h for h, _ in sizes), max(w for _, w in sizes)
    mixed = len({id(c) for c in cfgs}) > 1
    snaps = []
    LOG.reset()
    with simcuda.SimCudaMode():
        trk = tf.FeatureTracker(cfgs, device="cuda", **kw)
        for k in range(warmup + steps):
            src = frames(k)
            img = np.zeros((B, 1, H, W), np.uint8)
            for b, (h, w) in enumerate(sizes):  # the padded batch: each stream's top-left h x w
                hh, ww = min(h, src.shape[2]), min(w, src.shape[3])
                img[b, 0, :hh, :ww] = src[b, 0, :hh, :ww]
            img = torch.from_numpy(img)
            t = count_step.stamps(B, k)
            LOG.reset()
            LOG.set_inputs(img, t)
            LOG.enabled = k >= warmup
            try:
                trk.track(img, t, sizes=sizes if mixed else None)
            finally:
                LOG.enabled = False
            if k >= warmup:
                snaps.append(count_step._snapshot())
    fig = count_step.figures(snaps, labelled=False, by="file")
    return dict(kernels_per_step=fig["kernels_per_step"], syncs_per_step=fig["syncs_per_step"],
                syncs_excl_input=fig["syncs_per_step_excl_input"], groups=len(trk.groups),
                sync_sites=fig["sync_sites"][:8])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--B", type=int, nargs="*", default=[5, 10])
    ap.add_argument("--capturable", action="store_true", help="capturable=True (the CUDA default)")
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--sites", action="store_true", help="print where the syncs are")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(TOOLS))
    import torch_frontend as tf

    missing = [str(p) for p in FIVE if not p.exists()]
    if missing:
        print(f"needs ../shared/data/vins_configs: missing {missing}", file=sys.stderr)
        return 2
    euroc = tf.load_config(FIVE[0])
    five = [tf.load_config(p) for p in FIVE]
    # a rig: B pinhole cameras of one size and VINS settings, each its own calibration (fx, cx varied)
    rig = []
    for b in range(max(args.B)):
        p = euroc.camera.params_dict()
        p.update(fx=p["fx"] * (1 + 0.01 * b), cx=p["cx"] + b)
        cam = type(euroc.camera).from_params(p, width=euroc.image_width, height=euroc.image_height)
        rig.append(dataclasses.replace(euroc, camera=cam))
    kw = {"capturable": True} if args.capturable else {"capturable": False}
    out = []
    alone = []
    for i, c in enumerate(five):  # each config's own homogeneous step: what the groups add up to
        r = dict(B=1, batch=f"config {i} alone ({Path(c.path).name})", **count([c], 1, args.warmup, args.steps, kw))
        alone.append(r)
        out.append(r)
        print(f"B=  1 {r['batch']:40s}: {r['kernels_per_step']:8.0f} kernels/step, {r['syncs_per_step']:.1f} syncs/step "
              f"({r['syncs_excl_input']:.1f} besides the input upload)", flush=True)
    print(f"      sum of the five alone: {sum(r['kernels_per_step'] for r in alone):8.0f} kernels/step")
    for B in args.B:
        batches = (("homogeneous", [euroc] * B), ("rig of B calibrations", rig[:B]),
                   ("five configs", [five[b % 5] for b in range(B)]))
        for label, cfgs in batches:
            r = dict(B=B, batch=label, **count(cfgs, B, args.warmup, args.steps, kw))
            out.append(r)
            if args.sites:
                for s in r["sync_sites"]:
                    print("    ", s)
            print(f"B={B:3d} {label:13s} groups {r['groups']}: {r['kernels_per_step']:8.0f} kernels/step, "
                  f"{r['syncs_per_step']:.1f} syncs/step ({r['syncs_excl_input']:.1f} besides the input upload)",
                  flush=True)
    if args.json:
        args.json.write_text(json.dumps(dict(capturable=args.capturable, rows=out), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
