"""Benchmark: what ``loop --checkpoint-every`` costs (``pipelines.loop_checkpoint``): ms and bytes
per checkpoint, by phase, and the run time with and without checkpoints.

* Inputs: the demo's revisit render (``pipelines.loop.demo_sequence``), ``--laps`` laps of
  ``--keyframes-per-lap`` keyframes, one frame between keyframes, ``--size`` pixels; B = ``--streams``
  copies of it as B streams of one run (one shared map), drifted VIO poses, a trained vocabulary,
  a keyframe every 2 published frames.
* Runs: a warm-up (6 frames, no outputs), then ``run_loop`` with ``out`` three times: no checkpoints (``checkpoint_every=0``), the default
  interval (500 frames or 60 s: on a short run only the prepared checkpoint), and every
  ``--every`` frames / keyframes. Each checkpoint is timed inside ``Checkpointer.save`` (pickling
  the chunk, ``torch.save`` of the state, two atomic writes) and sized (``state.pt`` + its chunk).

Prints a markdown table and writes ``benchmarks/results/loop_checkpoint_b<B>.json`` (temp file +
rename).

Run: ``.venv/bin/python benchmarks/bench_loop_checkpoint.py [--streams 1] [--every 16]``; the
figures in ``docs/loop_closure.md``: ``--streams 1`` and ``--streams 16 --keyframes-per-lap 8 --every 4``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import torch  # noqa: E402
from _common import RESULTS, write_json_atomic  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--streams", type=int, default=1)
    ap.add_argument("--laps", type=int, default=2)
    ap.add_argument("--keyframes-per-lap", type=int, default=24)
    ap.add_argument("--size", default="160x120", help="WxH of the render")
    ap.add_argument("--every", type=int, default=16, help="checkpoint interval of the third run (frames)")
    ap.add_argument("--out", default=None, help="result JSON (default: benchmarks/results/loop_checkpoint_b<B>.json)")
    args = ap.parse_args(argv)
    if args.out is None:
        args.out = str(RESULTS / f"loop_checkpoint_b{args.streams}.json")
    torch.set_num_threads(1)

    from torch_frontend.geometry import R_to_quat
    from torch_frontend.pipelines import checkpoint as ckpt
    from torch_frontend.pipelines import loop as L
    from torch_frontend.pipelines.inputs import ArraySequence
    from torch_frontend.trajectory import Trajectory

    W, H = (int(v) for v in args.size.split("x"))
    seq = L.demo_sequence(laps=args.laps, keyframes_per_lap=args.keyframes_per_lap, frames_per_keyframe=1,
                          width=W, height=H)
    cfg = L.demo_config(seq)
    times = seq.times.double()
    imgs = seq.images.numpy()
    vio = Trajectory(times, seq.T_vio.double(), R_to_quat(seq.R_vio.double()))
    B = args.streams
    sources = [ArraySequence(imgs, times.numpy(), name=f"render{b}") for b in range(B)]

    records = []
    real_save = ckpt.Checkpointer.save

    def timed_save(self, frames, payload, chunk):
        t0 = time.perf_counter()
        real_save(self, frames, payload, chunk)
        records.append({"phase": payload.get("phase"), "ms": 1e3 * (time.perf_counter() - t0), "bytes": self.bytes})

    ckpt.Checkpointer.save = timed_save
    # a warm-up run (a few frames, no outputs): the first run of a process pays one-time set-up
    L.run_loop(cfg, sources, [vio] * B, None, L.LoopOptions(train_vocabulary=True, keyframe_every=2, progress=False,
                                                            max_frames=6, R_ic=seq.R_ic, t_ic=seq.t_ic))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, every in (("none", 0), ("default", None), (f"every {args.every}", args.every)):
            records.clear()
            opt = L.LoopOptions(train_vocabulary=True, keyframe_every=2, progress=False, checkpoint_every=every,
                                R_ic=seq.R_ic, t_ic=seq.t_ic)
            t0 = time.perf_counter()
            run = L.run_loop(cfg, sources, [vio] * B, Path(tmp) / label.replace(" ", "_"), opt)
            seconds = time.perf_counter() - t0
            by_phase = {}
            for r in records:
                by_phase.setdefault(r["phase"], []).append(r)
            rows.append({"run": label, "seconds": round(seconds, 3), "keyframes": run.summary["keyframes"],
                         "frames": B * len(times), "checkpoints": len(records),
                         "checkpoint_seconds": round(sum(r["ms"] for r in records) / 1e3, 3),
                         "phases": {p: {"n": len(rs), "median_ms": round(statistics.median(r["ms"] for r in rs), 2),
                                        "median_bytes": int(statistics.median(r["bytes"] for r in rs))}
                                    for p, rs in by_phase.items()}})
    ckpt.Checkpointer.save = real_save
    base = rows[0]["seconds"]
    print(f"B = {B}, {len(times)} frames {W}x{H} per stream, {rows[0]['keyframes']} keyframes\n")
    print("| run | seconds | checkpoints | in checkpoints (s) | share | per phase: n, median ms, median bytes |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        share = 100.0 * r["checkpoint_seconds"] / r["seconds"] if r["seconds"] else 0.0
        ph = "; ".join(f"{p} {v['n']} x {v['median_ms']:.1f} ms, {v['median_bytes'] / 1e3:.0f} kB"
                       for p, v in r["phases"].items()) or "-"
        print(f"| {r['run']} | {r['seconds']:.2f} | {r['checkpoints']} | {r['checkpoint_seconds']:.3f} | "
              f"{share:.1f} % | {ph} |")
    print(f"\n(the run without checkpoints: {base:.2f} s)")
    write_json_atomic(args.out, {"streams": B, "size": [W, H], "frames_per_stream": len(times), "runs": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
