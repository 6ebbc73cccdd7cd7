"""A DDP training script in which every rank tracks its own streams.

    torchrun --nproc-per-node 2 docs/examples/ddp_track.py             # the sample's cam0 and cam1
    torchrun --nproc-per-node 4 docs/examples/ddp_track.py --euroc A --euroc B --euroc C --euroc D

Each rank takes its block of the sequences (``distributed.shard``: contiguous, in input order) as
the batch of its own ``FeatureTracker`` on ``cuda:{LOCAL_RANK}`` (CPU without CUDA), reads them
with the frames decoded ahead in a DataLoader worker (``FrameStream``, pinned memory on CUDA), and
trains a toy model on the tracked features (predict each feature's velocity from its position) with
``DistributedDataParallel``. The tracker reads no process-global state: seeding each rank
differently (as training scripts do for augmentation) does not change its features, so a
sequence gives the same tracks on whichever rank, in whichever batch, it lands.

Sequences differ in length (the sample's cam1 has 6 frames, cam0 24), so the ranks run different
numbers of steps: ``DistributedDataParallel.join()`` lets a rank that ran out of frames shadow the
others' gradient all-reduces until every rank is done. Every rank needs at least one sequence.
Run it with ``torchrun`` (it reads the launcher's environment).
"""

from __future__ import annotations

import argparse
import gc
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from torch_frontend import FeatureTracker, load_config
from torch_frontend.distributed import dist_env, init_process_group, rank_device, shard
from torch_frontend.io import euroc_config, open_sequence
from torch_frontend.pipelines.prefetch import FrameStream

SAMPLE = Path(__file__).resolve().parents[2] / "torch_frontend" / "data" / "euroc_mini"


def main(argv=None) -> float:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--euroc", action="append", help="EuRoC ASL folder (repeatable; default: the sample, cam0 and cam1)")
    ap.add_argument("--config", default=None, help="VINS config (default: the first input's sensor.yaml)")
    ap.add_argument("--steps", type=int, default=8, help="at most this many training steps (one tracker step each)")
    ap.add_argument("--workers", type=int, default=1, help="DataLoader workers decoding the frames")
    args = ap.parse_args(argv)

    env = dist_env()
    dev = rank_device(env.local_rank)  # cuda:{LOCAL_RANK}, or the CPU
    init_process_group(dev)  # gloo on the CPU; NCCL for CUDA tensors (and gloo for CPU ones)
    torch.manual_seed(1000 + env.rank)  # per-rank seeds: the model's, not the tracker's business

    inputs = [(p, "cam0") for p in args.euroc] if args.euroc else [(SAMPLE, "cam0"), (SAMPLE, "cam1")]
    mine = shard(inputs, env.rank, env.world_size)
    if not mine:
        raise SystemExit(f"rank {env.rank}: no sequence (give at least {env.world_size})")
    cfg = load_config(args.config) if args.config else euroc_config(inputs[0][0], "cam0")
    seqs = [open_sequence("euroc", p, camera=cam) for p, cam in mine]
    stream = FrameStream(seqs, size=(cfg.image_height, cfg.image_width), max_steps=args.steps,
                         workers=args.workers, pin_memory=dev.type == "cuda")
    tracker = FeatureTracker(cfg, num_streams=len(seqs), device=dev)

    model = torch.nn.Linear(2, 2).to(dev)
    ddp = DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)
    opt = torch.optim.SGD(ddp.parameters(), lr=1e-2)
    summed = torch.zeros(2, device=dev)  # (sum of losses, steps with published features)
    steps = 0
    with ddp.join():  # uneven inputs: ranks may run different numbers of steps
        for batch in stream:
            frame = tracker.track(batch.images.to(dev, non_blocking=True), batch.timestamps,
                                  active=batch.alive.to(dev))
            m = frame.valid & batch.alive.to(dev)[:, None]
            # forward and backward every step, with or without published features
            pred = ddp(torch.where(m[..., None], frame.xy, torch.zeros_like(frame.xy)).float())
            err = (pred - frame.velocity.detach().float()) ** 2
            loss = (err.sum(-1) * m).sum() / m.sum().clamp_min(1)
            opt.zero_grad()
            loss.backward()
            opt.step()
            steps += 1
            summed += torch.stack([loss.detach(), (m.sum() > 0).float()])
    print(f"rank {env.rank}: {len(mine)} sequences, {steps} steps, {int(summed[1])} with published features")
    dist.all_reduce(summed)
    mean = float(summed[0] / summed[1].clamp_min(1))
    if env.rank == 0:
        print(f"{env.world_size} ranks, {len(inputs)} sequences: mean loss {mean:.3e} over {int(summed[1])} steps")
    # The DDP wrapper goes before the group. Its C++ reducer holds the group, and a group freed from
    # there (when main's locals die, after destroy_process_group) runs gloo's destructor with the GIL
    # held: that joins gloo's worker threads, and a worker still dropping a finished collective's
    # tensor (whose Python object died first) waits for the GIL, a deadlock (one CI run hung so).
    # Freed here, the group's last owner is torch.distributed's registry, whose binding releases the
    # GIL while it destroys the group. gc: DDP's hooks make reference cycles.
    del ddp, opt
    gc.collect()
    # every rank reaches the teardown together: destroying a gloo group while a peer is already gone
    # can hang (pytorch/pytorch#75097)
    dist.barrier()
    dist.destroy_process_group()
    return mean


if __name__ == "__main__":
    main()
