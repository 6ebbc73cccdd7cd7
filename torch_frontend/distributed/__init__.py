"""Many processes, GPUs and nodes with ``torch.distributed``: sharding inputs over ranks, the
coordination of a sharded run, and the vocabulary's k-medians over ranks.

* ``env``: :class:`DistEnv` / :func:`dist_env` (rank, world size, local rank from ``torchrun``'s
  environment or an initialised process group), :func:`launched`, :func:`shard_indices` /
  :func:`shard` (deterministic contiguous blocks by input order), :func:`rank_device`
  (``cuda:{LOCAL_RANK}`` when CUDA is present, else CPU) and :func:`init_process_group` (gloo on
  CPU, NCCL for CUDA tensors plus gloo for CPU ones, with a timeout).
* ``job``: :class:`Job`, how the ranks of one sharded command tell each other that they finished or
  failed (the rendezvous store of ``torchrun``), with heartbeats so that a stalled rank is named
  after a timeout; :class:`RankFailure`, :class:`JobAborted`.
* ``kmedians``: :func:`train_vocabulary`, ``loop.Vocabulary.train`` with the descriptors spread
  over ranks: the same vocabulary as one process with the same seed, bit for bit.

Library use under DDP (each rank of a training script tracks its own streams)::

    from torch_frontend.distributed import dist_env, rank_device, shard
    env = dist_env()                                    # after torch.distributed.init_process_group
    mine = shard(all_sequences, env.rank, env.world_size)
    tracker = FeatureTracker(cfg, num_streams=len(mine), device=rank_device(env.local_rank))

The tracker keeps no process-global state that results depend on (no global RNG, caches keyed by
device/dtype/size only), so a stream gives the same features on any rank, in any batch.
Names are imported lazily (``import torch_frontend.distributed`` does not import torch).
"""

from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "DistEnv": "env",
    "dist_env": "env",
    "init_process_group": "env",
    "launched": "env",
    "rank_device": "env",
    "shard": "env",
    "shard_indices": "env",
    "Job": "job",
    "JobAborted": "job",
    "RankFailure": "job",
    "train_vocabulary": "kmedians",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
