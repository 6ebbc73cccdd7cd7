"""How the ranks of one sharded command finish together: each posts its outcome, a failure stops
the others early, a stalled rank is named after a timeout, and rank 0 reports.

Convention:
    The coordination goes through the job's key-value store (``torchrun``'s rendezvous store, hosted
    by the launcher, so it outlives a killed rank; an in-memory store for a single process without
    a launcher), under a prefix unique to the command: ``torch-frontend/<n>/<command>/<restart>``
    (``n`` counts the jobs this process started; every rank starts the same ones in the same
    order). Keys: ``proc/<r>`` (host, pid, inputs of rank ``r``), ``beat/<r>`` (a counter the
    rank's work loop raises at most once a second), and per phase of the job (``prepare``,
    ``work``, ...) ``<phase>/status/<r>`` (its outcome, JSON), ``<phase>/failed`` (how many
    ranks failed), ``<phase>/reported`` (rank 0 has reported).

    :meth:`Job.run` runs a rank's work. Outcomes: ``ok``; ``failed`` (an exception: the rank posts
    its message and bumps ``failed``); ``aborted`` (the work saw ``failed`` at a heartbeat and
    stopped: :class:`JobAborted`); ``interrupted`` (SIGINT/SIGTERM: ``torchrun`` stops every rank
    when one dies); ``stalled`` (posted by a waiting rank for a rank whose heartbeat did not move
    for ``timeout`` seconds) and ``died`` (posted for a rank on this host whose process is gone:
    found at once, without the timeout). After its outcome every rank waits for all the others'; then, when
    every rank succeeded, :meth:`Job.run` returns the work's result; otherwise rank 0 raises
    :class:`RankFailure` naming every failed rank with its inputs and message (the CLI prints it
    as its one error line), a failed rank re-raises its own exception with ``rank r (inputs):``
    put in front of a ``DataError``'s message, and the other ranks raise a quiet
    :class:`JobAborted`. An interrupted rank does not wait: it raises :class:`JobInterrupted`
    (a ``KeyboardInterrupt``) whose ``detail`` names the ranks that had not finished (and those
    found dead on this host) with their inputs.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import socket
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, TypeVar

from ..errors import DataError
from .env import DEFAULT_TIMEOUT, dist_env, init_process_group

__all__ = ["Job", "JobAborted", "JobInterrupted", "RankFailure"]

T = TypeVar("T")

#: heartbeats: at most one store round trip per this many seconds of work
BEAT_INTERVAL = 1.0
#: polling of the other ranks' outcomes: first and longest sleep (s)
POLL_FIRST, POLL_MAX = 0.02, 0.5
#: how long a failed job's ranks wait for each other (rank 0's report, the others' leaving) (s)
REPORT_WAIT = 60.0
_JOBS = itertools.count()


class RankFailure(DataError):
    """Some rank of a sharded command failed (rank 0's exception). ``statuses``: every rank's
    outcome (dicts: ``rank``, ``outcome``, ``message``, ``inputs``, ``exit``); ``exit_code``: the
    largest exit code a failed rank asked for (1: data, 2: usage)."""

    def __init__(self, message: str, statuses: Sequence[Dict[str, Any]], exit_code: int = 1):
        super().__init__(message)
        self.statuses = list(statuses)
        self.exit_code = int(exit_code)


class JobAborted(Exception):
    """This rank stopped because another one failed (``quiet``: the CLI prints nothing, rank 0 and
    the failed rank say what happened). The job goes on later (a restart, ``--resume``): what a
    rank checkpointed stays (``keeps_checkpoints``, read by ``outputs.RunRecorder``)."""

    keeps_checkpoints = True

    def __init__(self, message: str = "stopped: another rank failed", quiet: bool = False):
        super().__init__(message)
        self.quiet = quiet


class JobInterrupted(KeyboardInterrupt):
    """SIGINT/SIGTERM during a sharded command; ``detail`` names the unfinished ranks."""

    def __init__(self, signum: Optional[int], detail: str):
        super().__init__(detail)
        self.signum = signum
        self.detail = detail


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this host (a zombie, killed but not yet reaped, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            return fh.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True


class Job:
    """The ranks of one sharded command (module docstring).

    Args:
        command: what runs (``"track"``, ``"loop"``, ``"vocabulary"``): part of the store prefix.
        inputs: this rank's inputs as text (named in messages), e.g. ``"euroc:MH_01, euroc:MH_02"``.
        timeout: seconds a rank may go without a heartbeat before a waiting rank declares it
            stalled; also the process group's collective timeout.
        device: this rank's device (the process group's backend follows it).

    Attributes: ``env`` (:class:`DistEnv`), ``rank``, ``world_size``, ``store``, ``group`` (a
    gloo process group for Python objects, None for a single process without a launcher).
    """

    def __init__(self, command: str, inputs: str = "", timeout: float = DEFAULT_TIMEOUT, device=None):
        import torch.distributed as dist

        if not timeout > 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout}")
        self.command = command
        self.timeout = float(timeout)
        self.inputs = inputs
        self.t0 = time.perf_counter()
        self._owns_group = init_process_group(device, timeout)
        self.env = dist_env()
        self.rank, self.world_size = self.env.rank, self.env.world_size
        restart = os.environ.get("TORCHELASTIC_RESTART_COUNT", "0")
        prefix = f"torch-frontend/{next(_JOBS)}/{command}/{restart}"
        if dist.is_initialized():
            from torch.distributed import distributed_c10d as c10d

            base = c10d._get_default_store()
            backend = str(dist.get_backend())
            self.group = None if backend == "gloo" else dist.new_group(backend="gloo")
            self.distributed = True
        else:
            base = dist.HashStore()
            self.group = None
            self.distributed = False
        self.store = dist.PrefixStore(prefix, base)
        self._beats = 0
        self._last_beat = 0.0
        self._phase = "work"
        self.store.set(f"proc/{self.rank}", json.dumps({"host": socket.gethostname(), "pid": os.getpid(),
                                                        "inputs": inputs}))

    # -- during the work ---------------------------------------------------------------------
    def failed(self) -> bool:
        """Whether some rank has failed (one store round trip)."""
        return int(self.store.add(f"{self._phase}/failed", 0)) > 0

    def beat(self, force: bool = False) -> None:
        """Heartbeat from the work loop (cheap: one round trip per ``BEAT_INTERVAL``); raises
        :class:`JobAborted` when another rank has failed."""
        now = time.perf_counter()
        if not force and now - self._last_beat < BEAT_INTERVAL:
            return
        self._last_beat = now
        self._beats += 1
        self.store.add(f"beat/{self.rank}", 1)
        if self.failed():
            raise JobAborted()

    # -- outcomes ------------------------------------------------------------------------------
    def _post(self, outcome: str, message: str = "", exit_code: int = 0) -> None:
        st = {"rank": self.rank, "outcome": outcome, "message": message, "inputs": self.inputs, "exit": exit_code}
        self.store.set(f"{self._phase}/status/{self.rank}", json.dumps(st))
        if outcome != "ok":
            self.store.add(f"{self._phase}/failed", 1)

    def _status(self, r: int) -> Optional[Dict[str, Any]]:
        key = f"{self._phase}/status/{r}"
        if not self.store.check([key]):
            return None
        return json.loads(self.store.get(key))

    def _proc(self, r: int) -> Dict[str, Any]:
        key = f"proc/{r}"
        if not self.store.check([key]):
            return {}
        return json.loads(self.store.get(key))

    def wait_all(self) -> List[Dict[str, Any]]:
        """Every rank's outcome, waiting for those not posted yet; a rank whose heartbeat does not
        move for ``timeout`` s is posted ``stalled`` (which stops the others)."""
        statuses: Dict[int, Dict[str, Any]] = {}
        last: Dict[int, int] = {}
        seen: Dict[int, float] = {}
        host = socket.gethostname()
        sleep = POLL_FIRST
        while True:
            now = time.perf_counter()
            for r in range(self.world_size):
                if r in statuses:
                    continue
                st = self._status(r)
                if st is not None:
                    statuses[r] = st
                    continue
                proc = self._proc(r)
                b = int(self.store.add(f"beat/{r}", 0))
                why = None
                if proc.get("host") == host and proc.get("pid") and not _pid_alive(int(proc["pid"])):
                    why = ("died", f"its process {proc['pid']} ended without an outcome (killed?)")
                elif last.get(r) != b:
                    last[r], seen[r] = b, now
                elif now - seen[r] > self.timeout:
                    why = ("stalled", f"no progress for {self.timeout:g} s (hung, or slower than the job's timeout)")
                if why is not None:
                    st = {"rank": r, "outcome": why[0], "inputs": proc.get("inputs", ""), "exit": 1, "message": why[1]}
                    self.store.set(f"{self._phase}/status/{r}", json.dumps(st))
                    self.store.add(f"{self._phase}/failed", 1)
                    statuses[r] = st
            if len(statuses) == self.world_size:
                return [statuses[r] for r in range(self.world_size)]
            self.store.add(f"beat/{self.rank}", 1)  # waiting is progress too
            time.sleep(sleep)
            sleep = min(POLL_MAX, sleep * 2)

    @staticmethod
    def _name(st: Dict[str, Any]) -> str:
        inputs = st.get("inputs") or ""
        return f"rank {st['rank']}" + (f" ({inputs})" if inputs else " (no inputs)")

    def report(self, statuses: Sequence[Dict[str, Any]]) -> str:
        """One line: every failed or stalled rank with its inputs and message."""
        bad = [s for s in statuses if s["outcome"] in ("failed", "stalled", "died", "interrupted")]
        parts = [f"{self._name(s)} {s['outcome']}: {s['message']}" for s in bad]
        return f"{self.command} failed on {len(bad)} of {self.world_size} ranks: " + "; ".join(parts)

    def unfinished(self) -> str:
        """Ranks without an outcome (and those whose process is gone, on this host), for messages."""
        host = socket.gethostname()
        gone, running = [], []
        for r in range(self.world_size):
            if self._status(r) is not None:
                continue
            p = self._proc(r)
            name = self._name({"rank": r, "inputs": p.get("inputs", "")})
            if p.get("host") == host and p.get("pid") and not _pid_alive(int(p["pid"])):
                gone.append(name)
            else:
                running.append(name)
        parts = []
        if gone:
            parts.append("gone (killed?): " + ", ".join(gone))
        if running:
            parts.append("not finished: " + ", ".join(running))
        return "; ".join(parts) or "every rank had finished"

    def run(self, work: Callable[[], T], exit_code_of: Callable[[BaseException], int] = lambda exc: 1,
            phase: str = "work") -> T:
        """Run this rank's ``work`` and finish together with the other ranks (module docstring).
        ``exit_code_of`` maps a failure to the exit code it asks for; ``phase`` names the step (a
        job may run several, each with its own outcomes)."""
        self._phase = phase
        try:
            result = work()
        except JobAborted as exc:
            self._post("aborted", str(exc), 1)
            own: Optional[BaseException] = None
        except KeyboardInterrupt as exc:
            self._post("interrupted", "stopped by a signal", 130)
            detail = f"rank {self.rank}: {self.unfinished()}"
            raise JobInterrupted(getattr(exc, "signum", None), detail) from exc
        except BaseException as exc:
            self._post("failed", " ".join(str(exc).split()) or type(exc).__name__, exit_code_of(exc))
            own = exc
        else:
            self._post("ok")
            own = None
        try:
            statuses = self.wait_all()
        except KeyboardInterrupt as exc:
            raise JobInterrupted(getattr(exc, "signum", None), f"rank {self.rank}: {self.unfinished()}") from exc
        if all(s["outcome"] == "ok" for s in statuses):
            return result
        if self.rank == 0:
            self.store.set(f"{self._phase}/reported", "1")
            # the store may live in this process (no launcher agent): let the others read it first
            self._wait_keys([f"{self._phase}/left/{s['rank']}" for s in statuses
                             if s["rank"] != 0 and s["outcome"] not in ("died", "stalled")])
            code = max([int(s.get("exit", 1)) for s in statuses if s["outcome"] != "ok"] + [1])
            raise RankFailure(self.report(statuses), statuses, code)
        self._wait_keys([f"{self._phase}/reported"])
        self.store.set(f"{self._phase}/left/{self.rank}", "1")
        if own is None:
            raise JobAborted(quiet=True)
        if isinstance(own, DataError) and not isinstance(own, RankFailure):
            msg = f"{self._name({'rank': self.rank, 'inputs': self.inputs})}: {own}"
            try:
                err = type(own)(msg)
            except TypeError:  # a subclass with another signature
                err = DataError(msg)
            err.rank_error = True  # the CLI prints it on this rank (errors common to all ranks: rank 0 only)
            raise err from own
        with contextlib.suppress(AttributeError, TypeError):
            own.rank_error = True
        raise own

    def _wait_keys(self, keys: Sequence[str]) -> None:
        """Wait (at most ``REPORT_WAIT`` s, or ``timeout``) until every key is set."""
        t_end = time.perf_counter() + min(self.timeout, REPORT_WAIT)
        while keys and time.perf_counter() < t_end and not self.store.check(list(keys)):
            time.sleep(POLL_FIRST)

    # -- after a successful run ------------------------------------------------------------------
    def gather(self, obj: Any) -> Optional[List[Any]]:
        """``obj`` of every rank on rank 0 (in rank order), None on the others."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.world_size if self.rank == 0 else None
        dist.gather_object(obj, out, dst=0, group=self.group)
        # a sender's gather ends when its data is sent: meet, so that no rank destroys the group
        # (or exits) while rank 0 still receives (gloo may abort it then)
        dist.barrier(group=self.group)
        return out

    def broadcast(self, obj: Any = None) -> Any:
        """Rank 0's ``obj`` on every rank."""
        if not self.distributed:
            return obj
        import torch.distributed as dist

        box = [obj]
        dist.broadcast_object_list(box, src=0, group=self.group)
        return box[0]

    def all_gather(self, obj: Any) -> List[Any]:
        """``obj`` of every rank on every rank (rank order)."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out: List[Any] = [None] * self.world_size
        dist.all_gather_object(out, obj, group=self.group)
        return out

    def barrier(self) -> None:
        """Every rank reaches this point (a gloo barrier bounded by the collective timeout)."""
        if self.distributed:
            import torch.distributed as dist

            dist.barrier(group=self.group)

    def close(self) -> None:
        """Tear down the process group if this job initialised it (a caller's stays)."""
        import torch.distributed as dist

        if self._owns_group and dist.is_initialized():
            dist.destroy_process_group()
        self._owns_group = False

    def __enter__(self) -> Job:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()
        return False
