"""Checkpoints of a long run and ``--resume``: what a pipeline (``track``, ``loop``) writes as it
goes so that a run killed at frame 9,000 continues from there, and finishes with the outputs an
uninterrupted run writes.

Convention:
    A run's outputs are staged in a hidden folder beside ``out`` (``_atomic.StagedFolder``). Its
    checkpoints live inside that staging folder, in ``.checkpoint/`` (never among the user's
    files; removed before the outputs are swapped in):

    * ``chunks/<n>.pkl``: the outputs recorded since the previous checkpoint, one pickled object
      per checkpoint (append-only: chunk ``n`` is written once, atomically, and never changed);
    * ``state.pt``: the latest checkpoint (``torch.save``, atomic: temp + rename): the format
      :data:`FORMAT_VERSION`, the run's :func:`fingerprint`, the frames done, how many chunks it
      covers, and the pipeline's payload (tracker ``state_dict``, counters, clocks, times).

    A chunk written by a checkpoint that was cut before its ``state.pt`` is not covered by any
    ``state.pt``: a resume ignores it, and the next checkpoint overwrites it.

    A run killed outright (SIGKILL, a power cut, a preempted machine) leaves its staging folder;
    ``SIGINT``/``SIGTERM`` keep it too once a checkpoint exists. :func:`resume_point` finds the one
    of ``out`` (a staging folder whose process is gone, holding a readable checkpoint; the newest),
    checks that the new run is the same run (the fingerprints: inputs, config contents, options
    that change outputs) and adopts it (renames it for this process). Without ``--resume`` the next
    run writing ``out`` removes it, as any stale temporary (``_atomic.clean_stale``).

    Test hook: the environment variable ``TORCH_FRONTEND_TEST_KILL_AT`` = ``frame:<k>`` makes the
    run SIGKILL itself once frame (step) ``k`` is recorded, ``checkpoint:<n>`` in the middle of
    writing its ``n``-th checkpoint (chunk written, ``state.pt`` half written), 1-based;
    ``term:<k>`` sends it SIGTERM once frame ``k`` is recorded; ``ended:<k>`` (a sharded ``track``)
    SIGKILLs it after the checkpoint of step ``k`` that records an input finished, before that
    input's output is swapped in.
"""

from __future__ import annotations

import dataclasses
import io
import os
import pickle
import shutil
import signal
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from .._atomic import CHECKPOINT_FOLDER
from .common import OptionError

__all__ = ["CHECKPOINT_FOLDER", "DEFAULT_EVERY_FRAMES", "DEFAULT_EVERY_SECONDS", "FORMAT_VERSION", "KILL_ENV",
           "Checkpoint", "Checkpointer", "ResumeError", "fingerprint", "fingerprint_difference",
           "frame_hook", "input_fingerprint", "kill_now", "kill_point", "load_checkpoint", "resume_point"]

_STATE = "state.pt"
_CHUNKS = "chunks"
#: the format of ``state.pt``; a checkpoint of another format is not resumed (a one-line refusal)
FORMAT_VERSION = 1
#: the default interval (``--checkpoint-every`` not given): this many frames or seconds, whichever first
DEFAULT_EVERY_FRAMES = 500
DEFAULT_EVERY_SECONDS = 60.0
#: the test hook (module docstring)
KILL_ENV = "TORCH_FRONTEND_TEST_KILL_AT"


class ResumeError(OptionError):
    """``--resume`` refused: the checkpoint is of another run (inputs, config, options) or of
    another format. The message is one line naming the first thing that differs."""

    def __init__(self, message: str):
        super().__init__("resume", message)


# ----------------------------------------------------------------------------------------------
# the run's fingerprint


def input_fingerprint(source, seq) -> str:
    """One input as a string: its kind, its absolute path (or the sequence's name) and the number
    of frames listed (a sequence that grew or was cut is another input)."""
    if isinstance(source, tuple):
        kind, path = source[:2]
        where = os.path.abspath(str(path))
        # a rig entry's reader options (camera folder, topic, fps) choose other frames
        opts = dict(source[2] or {}) if len(source) > 2 else {}
        if opts:
            where += " " + ", ".join(f"{k}={v!r}" for k, v in sorted(opts.items()))
    else:
        kind, where = getattr(seq, "kind", type(seq).__name__), str(getattr(seq, "name", ""))
    return f"{kind} {where} ({len(seq)} frames listed)"


def fingerprint(config, inputs: Sequence[str], options: Dict[str, Any]) -> Dict[str, str]:
    """What makes two runs the same run, as ``{field: exact value string}`` in the order a
    difference is reported: ``inputs`` (count), ``input <i>`` each (:func:`input_fingerprint`),
    ``config <key>`` (``tracker.checkpoint.config_fingerprint``: the settings, not the file's
    path), then ``options`` (only those that change the outputs: not workers, progress, threads,
    nor the checkpoint interval)."""
    from ..tracker.checkpoint import config_fingerprint

    fp: Dict[str, str] = {"inputs": str(len(inputs))}
    for i, s in enumerate(inputs):
        fp[f"input {i + 1}"] = str(s)
    for k, v in config_fingerprint(config).items():
        fp[f"config {k}"] = v
    for k, v in options.items():
        fp[k] = repr(v)
    return fp


def fingerprint_difference(saved: Dict[str, str], now: Dict[str, str]) -> Optional[str]:
    """The first field that differs, as ``"<field> differs (checkpoint: a; this run: b)"``, or None."""
    for k in list(now) + [k for k in saved if k not in now]:
        a, b = saved.get(k, "absent"), now.get(k, "absent")
        if a != b:
            return f"{k} differs (checkpoint: {a}; this run: {b})"
    return None


# ----------------------------------------------------------------------------------------------
# the test hook


def kill_point(event: str, n: int) -> bool:
    """Whether the test hook (``KILL_ENV``) asks to be killed at ``event`` number ``n``."""
    want = os.environ.get(KILL_ENV)
    return bool(want) and want == f"{event}:{n}"


def kill_now() -> None:  # pragma: no cover - the process ends here
    os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(60)


def frame_hook(frames: int) -> None:
    """The test hook after ``frames`` frames (steps) are recorded: ``frame:<k>`` SIGKILLs this
    process, ``term:<k>`` sends it SIGTERM (a preemption's first signal)."""
    if kill_point("frame", frames):
        kill_now()
    if kill_point("term", frames):
        os.kill(os.getpid(), signal.SIGTERM)


# ----------------------------------------------------------------------------------------------
# writing


def _atomic_write(path: Path, data: bytes, cut: bool = False) -> None:
    """``data`` into ``path`` by temp + rename (``_atomic.atomic_path``); ``cut``: the test hook's
    kill after half of it is written."""
    from .._atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            if cut:
                fh.write(data[: len(data) // 2])
                fh.flush()
                kill_now()
            fh.write(data)


class Checkpointer:
    """Writes a run's checkpoints into ``stage/.checkpoint`` (module docstring).

    Args:
        stage: the run's staging folder (``StagedFolder.path``).
        fingerprint: the run's :func:`fingerprint`.
        every: checkpoint every this many frames (steps); None: every
            ``DEFAULT_EVERY_FRAMES`` frames or ``DEFAULT_EVERY_SECONDS`` s, whichever first; 0: never.
        resumed: the :class:`Checkpoint` this run continues from (its chunk count and frames).

    :meth:`due` says whether a checkpoint is due after ``frames`` frames; :meth:`save` writes
    one: the outputs since the last one as a chunk, then ``state.pt``.
    """

    def __init__(self, stage: Path, fingerprint: Dict[str, str], every: Optional[int] = None,
                 resumed: Optional[Checkpoint] = None, clock=time.monotonic):
        self.dir = Path(stage) / CHECKPOINT_FOLDER
        self.fingerprint = dict(fingerprint)
        self.every = every
        self.clock = clock
        self.chunks = 0 if resumed is None else len(resumed.chunks)
        self.frames = 0 if resumed is None else resumed.frames
        self.written = 0  # checkpoints this process wrote
        self.seconds = 0.0  # spent writing them
        self.bytes = 0  # of the last one (state.pt and its chunk)
        self._last_time = clock()

    @property
    def enabled(self) -> bool:
        return self.every != 0

    def due(self, frames: int) -> bool:
        """Whether a checkpoint is due after ``frames`` frames (steps) done."""
        if not self.enabled or frames <= self.frames:
            return False
        if self.every is None:
            return (frames - self.frames >= DEFAULT_EVERY_FRAMES
                    or self.clock() - self._last_time >= DEFAULT_EVERY_SECONDS)
        return frames - self.frames >= self.every

    def save(self, frames: int, payload: Dict[str, Any], chunk: Any) -> None:
        """Write checkpoint ``frames`` (frames done): ``chunk`` (the outputs since the last one)
        as the next chunk, then ``state.pt`` with ``payload``."""
        t0 = time.perf_counter()
        n = self.written + 1
        chunk_bytes = pickle.dumps(chunk, protocol=pickle.HIGHEST_PROTOCOL)
        _atomic_write(self.dir / _CHUNKS / f"{self.chunks:06d}.pkl", chunk_bytes)
        import torch

        buf = io.BytesIO()
        torch.save({"version": FORMAT_VERSION, "fingerprint": self.fingerprint, "frames": int(frames),
                    "chunks": self.chunks + 1, "payload": payload}, buf)
        data = buf.getvalue()
        _atomic_write(self.dir / _STATE, data, cut=kill_point("checkpoint", n))
        self.chunks += 1
        self.frames = int(frames)
        self.written = n
        self.bytes = len(data) + len(chunk_bytes)
        self.seconds += time.perf_counter() - t0
        self._last_time = self.clock()

    def discard(self) -> None:
        """Remove the checkpoints (the run is complete: its outputs are about to be swapped in)."""
        shutil.rmtree(self.dir, ignore_errors=True)


# ----------------------------------------------------------------------------------------------
# reading and resuming


@dataclasses.dataclass
class Checkpoint:
    """A checkpoint read back: ``frames`` done, the pipeline's ``payload``, the ``chunks`` it
    covers (the unpickled objects, in order), the run's ``fingerprint`` and its ``stage`` folder."""

    frames: int
    payload: Dict[str, Any]
    chunks: List[Any]
    fingerprint: Dict[str, str]
    stage: Path


def load_checkpoint(stage: Path) -> Checkpoint:
    """Read ``stage``'s checkpoint. Raises ``FileNotFoundError`` when it has none, ``ResumeError``
    for another format, ``ValueError`` for a damaged one."""
    import torch

    d = Path(stage) / CHECKPOINT_FOLDER
    try:
        state = torch.load(d / _STATE, map_location="cpu", weights_only=False)
    except FileNotFoundError:
        raise
    except Exception as exc:  # a damaged file: not written by a finished save (cannot be: atomic)
        raise ValueError(f"{d / _STATE}: not a readable checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, dict) or state.get("version") != FORMAT_VERSION:
        v = state.get("version") if isinstance(state, dict) else None
        raise ResumeError(f"{d}: a checkpoint of format {v!r}, this torch-frontend resumes format {FORMAT_VERSION} "
                          f"only; rerun without `resume` to start over")
    chunks = []
    for i in range(int(state["chunks"])):
        with open(d / _CHUNKS / f"{i:06d}.pkl", "rb") as fh:
            chunks.append(pickle.load(fh))
    return Checkpoint(frames=int(state["frames"]), payload=state["payload"], chunks=chunks,
                      fingerprint=dict(state["fingerprint"]), stage=Path(stage))


def _checkpoint_time(stage: Path) -> float:
    try:
        return os.stat(Path(stage) / CHECKPOINT_FOLDER / _STATE).st_mtime
    except OSError:
        return -1.0


def resume_point(out, fingerprint: Dict[str, str]) -> Optional[Checkpoint]:
    """The checkpoint of an interrupted run of ``out`` to continue from, or None (no staging folder
    of a finished process holds one). The newest such folder is adopted (renamed for this process;
    ``Checkpoint.stage`` is its new path, for ``StagedFolder(..., adopt=)``); the others are left
    for ``clean_stale``.

    Raises:
        ResumeError: the checkpoint is of another run: one line naming the first field of the
            fingerprint that differs (or of another format).
    """
    from .._atomic import adopt_staging, stale_staging

    target = Path(os.path.realpath(out))
    found: List[Tuple[float, Path]] = [(t, p) for p in stale_staging(target) for t in (_checkpoint_time(p),) if t >= 0]
    for _, stage in sorted(found, key=lambda x: x[0], reverse=True):
        try:
            ck = load_checkpoint(stage)
        except (FileNotFoundError, ValueError, OSError, pickle.UnpicklingError, EOFError):
            continue  # a damaged one: the next older, or none
        diff = fingerprint_difference(ck.fingerprint, fingerprint)
        if diff is not None:
            raise ResumeError(f"resume: cannot continue the interrupted run of {out}: {diff}; rerun without "
                              f"`resume` to start over")
        ck.stage = adopt_staging(stage, target)
        return ck
    return None

