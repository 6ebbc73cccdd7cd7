"""Where this process stands in a ``torch.distributed`` job, and which inputs are its own.

Convention:
    ``torchrun`` (and most launchers) describe the job in the environment: ``RANK`` (0 ..
    ``WORLD_SIZE - 1``, unique over all nodes), ``WORLD_SIZE``, ``LOCAL_RANK`` (0 .. processes on
    this node - 1) and ``LOCAL_WORLD_SIZE``. An initialised default process group takes precedence
    for ``rank``/``world_size``. Without either, the process is rank 0 of a world of 1.

    Sharding is by input order in contiguous blocks: with ``n`` inputs and ``W`` ranks, rank ``r``
    gets inputs ``[r q + min(r, n mod W), ...)`` (``q = n // W``), the first ``n mod W`` ranks one
    more than the others (``numpy.array_split``'s rule). A rank's inputs are that rank's batch;
    ranks beyond ``n`` get none.
"""

from __future__ import annotations

import datetime
import os
import sys
from dataclasses import dataclass
from typing import Any, List, Optional, Sequence, TypeVar

__all__ = ["DistEnv", "dist_env", "init_process_group", "launched", "rank_device", "shard", "shard_indices"]

T = TypeVar("T")

#: the variables a launcher sets (``torchrun``: all four)
ENV_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE")
#: how long a collective may wait for its peers by default (s; torch's default for gloo)
DEFAULT_TIMEOUT = 1800.0


@dataclass(frozen=True)
class DistEnv:
    """Rank ``rank`` of ``world_size`` processes; ``local_rank`` of ``local_world_size`` on this
    node; ``launched``: the environment came from a launcher (or a process group)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    local_world_size: int = 1
    launched: bool = False

    @property
    def is_main(self) -> bool:
        """Rank 0: the rank that merges and prints."""
        return self.rank == 0


def _int_env(name: str, default: int) -> int:
    raw = os.environ.get(name)
    if raw is None or raw.strip() == "":
        return default
    try:
        return int(raw)
    except ValueError:
        raise ValueError(f"environment variable {name}={raw!r}: expected an integer") from None


def launched() -> bool:
    """Whether a launcher started this process as a rank (``RANK`` and ``WORLD_SIZE`` are set)."""
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ


def dist_env() -> DistEnv:
    """This process's :class:`DistEnv` (module docstring)."""
    rank = _int_env("RANK", 0)
    world = _int_env("WORLD_SIZE", 1)
    was_launched = launched()
    dist = sys.modules.get("torch.distributed")  # not imported: no process group (and no torch import here)
    if dist is not None and dist.is_available() and dist.is_initialized():
        rank, world, was_launched = dist.get_rank(), dist.get_world_size(), True
    local_world = _int_env("LOCAL_WORLD_SIZE", 1 if not was_launched else world)
    local = _int_env("LOCAL_RANK", rank % max(local_world, 1))
    if not (0 <= rank < world):
        raise ValueError(f"RANK {rank} is not in 0 .. WORLD_SIZE - 1 = {world - 1}")
    return DistEnv(rank, world, local, local_world, was_launched)


def shard_indices(n: int, rank: int, world_size: int) -> range:
    """Indices of the inputs of ``rank`` among ``n`` inputs on ``world_size`` ranks (contiguous,
    in input order, sizes differing by at most one; module docstring)."""
    if world_size < 1:
        raise ValueError(f"world_size must be >= 1, got {world_size}")
    if not 0 <= rank < world_size:
        raise ValueError(f"rank must be in 0 .. {world_size - 1}, got {rank}")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    q, rem = divmod(n, world_size)
    start = rank * q + min(rank, rem)
    return range(start, start + q + (1 if rank < rem else 0))


def shard(items: Sequence[T], rank: Optional[int] = None, world_size: Optional[int] = None) -> List[T]:
    """The items of ``rank`` (default: this process's) out of ``world_size`` (default: this job's),
    by :func:`shard_indices`."""
    if rank is None or world_size is None:
        e = dist_env()
        rank = e.rank if rank is None else rank
        world_size = e.world_size if world_size is None else world_size
    items = list(items)
    return [items[i] for i in shard_indices(len(items), rank, world_size)]


def rank_device(local_rank: Optional[int] = None, device: Any = None):
    """The ``torch.device`` a rank runs on: ``device`` when given with an index (``"cuda:1"``,
    ``"cpu"``), ``cuda:{local_rank}`` for ``"cuda"``; ``device=None``: ``cuda:{local_rank}`` when
    CUDA is present, else CPU. ``local_rank`` defaults to this process's."""
    import torch

    if local_rank is None:
        local_rank = dist_env().local_rank
    if device is None:
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    d = torch.device(str(device))
    if d.type == "cuda" and d.index is None:
        return torch.device(f"cuda:{local_rank}")
    return d


def init_process_group(device=None, timeout: float = DEFAULT_TIMEOUT) -> bool:
    """Initialise the default process group from the launcher's environment (``env://``), unless
    one exists or the world is a single process without a launcher; returns whether this call
    initialised it.

    The backend is gloo for a CPU ``device``, and ``cpu:gloo,cuda:nccl`` for CUDA (NCCL for CUDA
    tensors, gloo for CPU tensors and Python objects). ``timeout`` (s) bounds every collective.
    """
    import torch
    import torch.distributed as dist

    if dist.is_initialized() or not launched():
        return False
    dev = torch.device("cpu") if device is None else torch.device(str(device))
    backend = "cpu:gloo,cuda:nccl" if dev.type == "cuda" and dist.is_nccl_available() else "gloo"
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    td = datetime.timedelta(seconds=float(timeout))
    attempt = os.environ.get("TORCHELASTIC_RESTART_COUNT", "").strip()
    if attempt:
        # torch elastic keeps one store for every start of the worker group (the agent's, shared
        # across its restarts): the previous start's keys, its ranks' gloo addresses among them,
        # are still there, and a restarted rank may read a dead peer's address before the new
        # peer writes its own ("connection refused": 2 of the first 4 restarts tried here). The keys of
        # each start under their own prefix keep them apart.
        from torch.distributed.rendezvous import rendezvous

        store, rank, world = next(rendezvous("env://", timeout=td))
        dist.init_process_group(backend=backend, timeout=td, rank=rank, world_size=world,
                                store=dist.PrefixStore(f"torch-frontend/start-{attempt}", store))
        return True
    dist.init_process_group(backend=backend, timeout=td)
    return True
