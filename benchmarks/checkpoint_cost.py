"""What a ``track`` checkpoint costs (``pipelines/checkpoint.py``): milliseconds and bytes per
checkpoint at B streams, and the share of the run time at the default interval (500 frames or
60 s, whichever first).

    PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/checkpoint_cost.py --streams 1 16

The figures of 2026-12-03 are in ``benchmarks/results/checkpoint_cost.json`` (the lines it prints).

For each B: the sample (``torch_frontend/data/euroc_mini``, 24 frames) tracked as B streams, as
``track`` does (``RunRecorder``, default CPU path); then one checkpoint written as ``track``
writes it (tracker ``state_dict``, the recorder's counters, the chunk of outputs since the last
checkpoint, ``state.pt``), with the chunk's rows replicated to what ``DEFAULT_EVERY_FRAMES``
frames record (the sample has 24). The share: the checkpoint's time over the time between two
checkpoints, ``min(DEFAULT_EVERY_FRAMES * step time, DEFAULT_EVERY_SECONDS)``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torch_frontend.io import EurocSequence  # noqa: E402
from torch_frontend.outputs import RunRecorder  # noqa: E402
from torch_frontend.pipelines import checkpoint as ckpt  # noqa: E402
from torch_frontend.pipelines.prefetch import FrameStream  # noqa: E402
from torch_frontend.pipelines.track import tracked_batches  # noqa: E402
from torch_frontend.tracker import FeatureTracker  # noqa: E402

SAMPLE = REPO / "torch_frontend" / "data" / "euroc_mini"


def measure(B: int, repeat: int, tmp: Path) -> dict:
    import torch_frontend as tf

    cfg = tf.load_config(REPO / "configs" / "euroc.yaml")
    seqs = [EurocSequence(SAMPLE) for _ in range(B)]
    stream = FrameStream(seqs, size=(cfg.image_height, cfg.image_width))
    tracker = FeatureTracker(cfg, num_streams=B)
    steps = []
    with RunRecorder(tmp / f"out{B}", [f"s{b}" for b in range(B)], write_tracks=False, journal=True) as rec:
        for batch, frame, secs in tracked_batches(tracker, stream, torch.device("cpu")):
            t0 = time.perf_counter()
            rec.add(batch, frame)
            steps.append(time.perf_counter() - t0 + secs)
        n = len(steps)
        # the rows of DEFAULT_EVERY_FRAMES frames: the sample's, repeated
        copies = math.ceil(ckpt.DEFAULT_EVERY_FRAMES / n)
        rows, lengths, per_frame = list(rec._rows), list(rec._lengths), [list(p) for p in rec.per_frame]
        cp = ckpt.Checkpointer(rec.stage_path, {"bench": "1"}, every=1)
        times, sizes, state_bytes = [], [], []
        for _ in range(repeat):
            rec._rows, rec._lengths = rows * copies, lengths * copies
            rec.per_frame = [p * copies for p in per_frame]
            rec._marks = (0, 0, [0] * B)
            t0 = time.perf_counter()
            cp.save(cp.frames + 1, {"tracker": tracker.state_dict(), "recorder": rec.counters(), "times": {}},
                    rec.take_chunk())
            times.append(time.perf_counter() - t0)
            sizes.append(cp.bytes)
            state_bytes.append((cp.dir / "state.pt").stat().st_size)
        rec.abort()
    step = statistics.median(steps[2:])  # past the first frames (no tracking yet)
    ck = statistics.median(times)
    between = min(ckpt.DEFAULT_EVERY_FRAMES * step, ckpt.DEFAULT_EVERY_SECONDS)
    return {"streams": B, "step_ms": round(step * 1e3, 1), "checkpoint_ms": round(ck * 1e3, 1),
            "checkpoint_ms_all": [round(t * 1e3, 1) for t in times], "bytes": int(statistics.median(sizes)),
            "state_bytes": int(statistics.median(state_bytes)),
            "chunk_frames": n * copies, "share_at_default_interval": round(ck / (between + ck), 5)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--streams", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as d:
        for B in args.streams:
            print(json.dumps(measure(B, args.repeat, Path(d))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
