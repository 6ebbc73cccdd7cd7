"""Sharded runs that survive a killed rank: each rank's checkpoints in the job's staging area, and
the resume that ``torchrun --max-restarts K`` (torch elastic) needs.

Convention:
    torch elastic's agent (``torch.distributed.elastic.agent.server.api``, torch 2.13) watches its
    workers; when one fails (exits non-zero or is killed) it stops every worker of the group
    (SIGTERM, then SIGKILL), rendezvous again and starts them all again with
    ``TORCHELASTIC_RESTART_COUNT`` raised by one, as long as restarts are left. Every rank, not only
    the killed one, starts its command from the beginning, with the same arguments.

    So a sharded command resumes by itself when ``TORCHELASTIC_RESTART_COUNT`` > 0 (as if
    ``--resume`` were given; :func:`resuming`), and every rank keeps what it did in **its staging
    folder**: a hidden folder beside ``out`` named as ``_atomic``'s temporaries of the target
    ``<out>.rank<r>`` (``.<out name>.rank<r>.tf<pid>-<random>.tmp``; never swapped in: it is the
    rank's private part of the job's staging area). It holds the rank's checkpoints
    (``pipelines.checkpoint``: ``.checkpoint/``) and the staging folders of the rank's unfinished
    per-input outputs (``stream<b>/``, renamed to ``out/stream<b>`` when the input is complete and
    the checkpoint that records it finished is saved: a rank stopped before that checkpoint redoes
    the input from the previous one, and the track images of the frames before it are only here).
    The checkpoints say which of the rank's inputs are finished (with their results for the merged
    summary), so a restarted rank redoes none of them and continues the others from the last
    checkpoint. A restarted rank finds its folder as ``--resume`` finds a killed run's
    (``checkpoint.resume_point``: the folder of a process that is gone, holding a checkpoint of
    the same job: inputs, config, options, world size and rank) and adopts it.

    The folder is removed when the job is complete (after rank 0 wrote the merged summary); a
    failed job leaves it for the next run: with ``--resume`` (or a restart) it continues, without
    it the next run removes it (a stale temporary).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Dict, Optional

from . import checkpoint as ckpt

__all__ = ["RESTART_ENV", "RankStage", "restart_count", "resuming"]

#: set by torch elastic in every worker: how many times the worker group was restarted
RESTART_ENV = "TORCHELASTIC_RESTART_COUNT"


def restart_count() -> int:
    """``TORCHELASTIC_RESTART_COUNT`` (0 outside torch elastic, or at the first start)."""
    raw = os.environ.get(RESTART_ENV, "").strip()
    try:
        return int(raw) if raw else 0
    except ValueError:
        return 0


def resuming(resume: bool) -> bool:
    """Whether a sharded command continues from its checkpoints: ``--resume``, or a restart."""
    return bool(resume) or restart_count() > 0


class RankStage:
    """One rank's staging folder of a sharded job (module docstring).

    Args:
        out: the job's output folder. rank: this rank.
        fingerprint: the job's ``checkpoint.fingerprint`` (with the world size and the rank).
        every: the checkpoint interval (``checkpoint.Checkpointer``; 0: no checkpoints).
        resume: continue from this rank's checkpoint (:func:`resuming`).

    Attributes: ``path`` (the folder), ``resumed`` (the ``checkpoint.Checkpoint`` or None),
    ``writer`` (the ``Checkpointer``), ``keep`` (leave the folder when the work stops with an
    exception: set once a checkpoint is in it).
    """

    def __init__(self, out, rank: int, fingerprint: Dict[str, str], every: Optional[int], resume: bool):
        from .._atomic import StagedFolder

        out = Path(os.path.realpath(out))
        target = out.parent / f"{out.name}.rank{int(rank)}"
        self.resumed = ckpt.resume_point(target, fingerprint) if resume else None
        if resume and self.resumed is None and restart_count() == 0:
            from ..errors import DataWarning

            warnings.warn(f"--resume: no checkpoint of an interrupted run of {out} found for rank {rank}: "
                          f"starting from the first frame", DataWarning, stacklevel=3)
        # a StagedFolder of the (never written) target: it removes the stale folders of earlier
        # jobs (not the adopted one, renamed for this process) and is never committed
        self._stage = StagedFolder(target, "rank", adopt=None if self.resumed is None else self.resumed.stage)
        if self.resumed is not None:
            from ..errors import DataWarning

            done = self.resumed.payload.get("finished") or {}
            why = f"restart {restart_count()} of the job" if restart_count() else "--resume"
            warnings.warn(f"rank {rank}: {why}: resuming from its checkpoint at step {self.resumed.frames}"
                          f"{f' ({len(done)} of its inputs finished)' if done else ''}", DataWarning, stacklevel=3)
        self.path = self._stage.path
        self.writer = ckpt.Checkpointer(self.path, fingerprint, every, self.resumed)
        self.keep = self.resumed is not None

    @property
    def payload(self) -> Dict[str, Any]:
        return {} if self.resumed is None else self.resumed.payload

    def staging_of(self, name: str) -> Path:
        """The staging folder of the rank's output ``name`` (``stream<b>``) inside this one."""
        p = self.path / name
        p.mkdir(exist_ok=True)
        return p

    def save(self, counter: int, payload: Dict[str, Any], chunk: Any) -> None:
        self.writer.save(counter, payload, chunk)
        self.keep = True

    def close(self) -> None:
        """Remove the folder (the job is complete)."""
        self._stage.abort()

    def stop(self, exc: Optional[BaseException]) -> None:
        """The rank's work stopped with ``exc``: keep the folder when a checkpoint is in it and the
        job may go on (interrupted, aborted because another rank failed, killed and restarted),
        else remove it."""
        from ..distributed import JobAborted

        if self.keep and isinstance(exc, (KeyboardInterrupt, JobAborted)):
            return
        self.close()
