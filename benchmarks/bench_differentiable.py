"""Benchmark: the cost of training through the whole tracker, ``FeatureTracker(...,
differentiable=True)`` against the 8-bit path, in one process.

Input: the repo's EuRoC sample (``torch_frontend/data/euroc_mini``, cam0, 752x480, EuRoC config:
CLAHE on, 150 features). B streams are the sequence started at B different frames (so their
images differ). Per B, per frame (means over the frames after the first ``WARM`` ones):

* ``8bit``: the default step on uint8 images (forward only);
* ``diff fwd``: ``differentiable=True`` on float images that require a gradient, forward only;
* ``diff fwd+bwd``: windows of ``k`` frames (BPTT through the state; ``state.detach()`` between
  windows), the loss ``tracking_loss(uv, present, target=uv.detach() + 0.25) + |velocity|^2`` of
  every frame, one backward per window: seconds per frame;
* ``saved MiB``: the largest sum of tensors autograd saved for backward during one window
  (``torch.autograd.graph.saved_tensors_hooks``; storage bytes, views counted once), CPU.

Both LK gradient modes are timed (``implicit``, the default, and ``unrolled``). The outputs of
the differentiable step equal the 8-bit step's (checked on every frame here too).
"""

from __future__ import annotations

import argparse
import json
import time

import torch
from _common import RESULTS, apply_threads, write_atomic, write_json_atomic

import torch_frontend as tf
from torch_frontend.cli import SAMPLE_DIR, default_config_path
from torch_frontend.io import EurocSequence
from torch_frontend.learn import tracking_loss

WARM = 2  # frames before timing (first image, first detection)


class SavedBytes:
    """Peak bytes of the tensors saved for backward while active (unique storages)."""

    def __init__(self):
        self.live, self.peak = {}, 0

    def pack(self, t):
        key = t.untyped_storage().data_ptr()
        self.live[key] = t.untyped_storage().nbytes()
        self.peak = max(self.peak, sum(self.live.values()))
        return t

    def hooks(self):
        return torch.autograd.graph.saved_tensors_hooks(self.pack, lambda t: t)


def _batches(frames, B, n):
    """``n`` (timestamps (B,), images (B, 1, H, W) uint8): stream b starts at frame b."""
    out = []
    for k in range(n):
        imgs = torch.cat([frames[k + b][1] for b in range(B)])
        out.append((torch.tensor([frames[k][0]] * B, dtype=torch.float64), imgs))
    return out


def _time_forward(tracker, batches, as_float):
    state, times = tracker.initial_state(), []
    frames_out = []
    for k, (t, u8) in enumerate(batches):
        x = u8.float().requires_grad_() if as_float else u8
        t0 = time.perf_counter()
        state, fr = tracker.step(state, x, t)
        if k >= WARM:
            times.append(time.perf_counter() - t0)
        state = state.detach() if as_float else state
        frames_out.append(fr)
    return sum(times) / len(times), frames_out


def _time_training(tracker, batches, window):
    state = tracker.initial_state()
    for t, u8 in batches[:WARM]:
        state, _ = tracker.step(state, u8.float(), t)
    rest = batches[WARM:]
    per_frame, peak = [], 0
    for w0 in range(0, len(rest) - window + 1, window):
        state = state.detach()
        saved = SavedBytes()
        t0 = time.perf_counter()
        with saved.hooks():
            loss = 0.0
            for t, u8 in rest[w0:w0 + window]:
                x = u8.float().requires_grad_()
                state, fr = tracker.step(state, x, t)
                loss = loss + tracking_loss(fr.uv, fr.present, target=fr.uv.detach() + 0.25) + fr.velocity.square().sum()
        loss.backward()
        per_frame.append((time.perf_counter() - t0) / window)
        peak = max(peak, saved.peak)
    return sum(per_frame) / len(per_frame), peak / 2**20


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--frames", type=int, default=14, help="frames per stream (the sample has 20)")
    ap.add_argument("--window", type=int, default=3, help="BPTT window (frames)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out-name", default="differentiable")
    args = ap.parse_args(argv)
    apply_threads(args.threads)
    seq = [(f.timestamp, torch.from_numpy(f.image)[None, None]) for f in EurocSequence(SAMPLE_DIR)]
    cfg = default_config_path()
    rows = []
    for B in args.batch:
        n = min(args.frames, len(seq) - B + 1)
        batches = _batches(seq, B, n)
        base = tf.FeatureTracker(cfg, B)
        t8, f8 = _time_forward(base, batches, as_float=False)
        row = dict(B=B, frames=n, ms_8bit=1e3 * t8)
        for mode in ("implicit", "unrolled"):
            dif = tf.FeatureTracker(cfg, B, differentiable=True, grad_mode=mode)
            tf_, fd = _time_forward(dif, batches, as_float=True)
            same = all(torch.equal(a.uv, b.uv.detach()) and torch.equal(a.ids, b.ids) for a, b in zip(f8, fd))
            tt, mib = _time_training(dif, batches, args.window)
            row.update({f"ms_fwd_{mode}": 1e3 * tf_, f"ms_train_{mode}": 1e3 * tt, f"saved_mib_{mode}": mib,
                        f"same_{mode}": same})
        rows.append(row)
        print(json.dumps(row))
    res = dict(benchmark="differentiable", threads=args.threads, window=args.window, torch=torch.__version__,
               input="torch_frontend/data/euroc_mini cam0 (EuRoC config, CLAHE on)", rows=rows)
    write_json_atomic(RESULTS / f"{args.out_name}.json", res)
    lines = ["# Training through the tracker (`benchmarks/bench_differentiable.py`)", "",
             f"EuRoC sample, cam0, 1 torch thread, BPTT window {args.window} frames; ms per frame "
             f"(all B streams); saved = peak MiB saved for backward in one window.", "",
             "| B | 8-bit step | diff fwd (implicit) | diff fwd+bwd (implicit) | saved MiB (implicit) | "
             "diff fwd+bwd (unrolled) | saved MiB (unrolled) | outputs equal |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['B']} | {r['ms_8bit']:.1f} | {r['ms_fwd_implicit']:.1f} | {r['ms_train_implicit']:.1f} | "
                     f"{r['saved_mib_implicit']:.0f} | {r['ms_train_unrolled']:.1f} | {r['saved_mib_unrolled']:.0f} | "
                     f"{r['same_implicit'] and r['same_unrolled']} |")
    write_atomic(RESULTS / f"{args.out_name}.md", ("\n".join(lines) + "\n").encode())


if __name__ == "__main__":
    main()
