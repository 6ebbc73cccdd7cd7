"""Checkpoints and ``--resume`` of ``torch-frontend loop`` (``run_loop``), on the framework of
``pipelines.checkpoint`` (fingerprint, ``Checkpointer``, append-only chunks, adoption of a killed
run's staging folder).

Convention:
    A ``loop`` run with ``out`` stages its outputs from its start (``_atomic.StagedFolder`` beside
    ``out``, as ``track``); its checkpoints live in that folder's ``.checkpoint/`` and never reach
    ``out``. The run has three phases, and a checkpoint says which one it stopped in:

    * ``tracking``: every ``checkpoint_every`` frames (steps; default 500 frames or 60 s): the
      tracker's ``state_dict`` and the clocks (``state.pt``), and per stream what its
      ``KeyframeLog`` gained since the previous checkpoint (the chunk: published frames,
      observations, keyframe images, each written once);
    * ``prepared``: once, after tracking, triangulation, description and the vocabulary (the
      chunk: the logs' last part, the keyframes' points and descriptors, a trained vocabulary;
      ``state.pt``: the times and counts of the finished stages), so a resume never tracks again;
    * ``graphs``: while keyframes go into the pose graph(s), every ``checkpoint_every`` keyframes
      (or 60 s): the graphs' ``state_dict`` (``loop.state``; the chunk: the new keyframes' points
      and descriptors, ``state.pt``: everything else, poses, database, candidates, RANSAC
      generator), and where the stage stands.

    The counter given to ``Checkpointer.due`` is the frames tracked plus the keyframes added to
    the graphs (monotone across the phases). A resume rebuilds the phase's objects from the
    chunks and the state, and goes on: the outputs are those of a run that never stopped (timing
    fields aside: the times add the interrupted runs' to this one's).

    The fingerprint: the inputs (``checkpoint.input_fingerprint``), the poses, ground truth,
    vocabulary and ``load_graph`` files (path, size and SHA-256 of their contents; a
    ``Trajectory`` or ``Vocabulary`` object by its values), the config, and every option that
    changes the outputs (all but ``workers``, ``progress``, ``checkpoint_every``, ``resume``).

    Test hooks (``checkpoint.KILL_ENV``): ``frame:<k>`` / ``term:<k>`` (after tracking frame k),
    ``checkpoint:<n>`` (inside the n-th checkpoint this process writes), ``keyframe:<k>`` (after
    the k-th keyframe added to the graphs), ``written:<n>`` (a sharded run with separate graphs:
    after a rank wrote its n-th input and checkpointed it).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from . import checkpoint as ckpt

__all__ = ["LoopCheckpoints", "loop_fingerprint"]

#: LoopOptions fields left out of the fingerprint: they do not change the outputs
_NOT_OUTPUTS = ("workers", "progress", "checkpoint_every", "resume", "device")
_HASH_BLOCK = 1 << 20


def _file_digest(path) -> str:
    """``path (N bytes, sha256 ...)`` of a file; a folder (a saved pose graph): of each of its files."""
    p = Path(path)
    if p.is_dir():
        parts = [f"{q.relative_to(p)}: {_file_digest(q)}" for q in sorted(p.rglob("*")) if q.is_file()]
        return f"{os.path.abspath(p)} [{'; '.join(parts)}]"
    h = hashlib.sha256()
    try:
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(_HASH_BLOCK), b""):
                h.update(block)
        return f"{os.path.abspath(p)} ({p.stat().st_size} bytes, sha256 {h.hexdigest()[:16]})"
    except OSError:
        return f"{os.path.abspath(p)} (unreadable)"


def _value_digest(x: Any) -> str:
    """A file, a ``Trajectory``, a ``Vocabulary``, a tensor, a tuple of them or None, as a string."""
    import numpy as np
    import torch

    if x is None:
        return "None"
    if isinstance(x, (str, Path)):
        return _file_digest(x)
    if isinstance(x, torch.Tensor):
        t = x.detach().cpu().contiguous()
        return f"tensor {tuple(t.shape)} {t.dtype} sha256 {hashlib.sha256(t.numpy().tobytes()).hexdigest()[:16]}"
    if isinstance(x, np.ndarray):
        return _value_digest(torch.from_numpy(np.ascontiguousarray(x)))
    if isinstance(x, (tuple, list)):
        return "(" + ", ".join(_value_digest(v) for v in x) + ")"
    if hasattr(x, "state_dict"):  # a Vocabulary
        st = x.state_dict()
        return f"{type(x).__name__} " + _value_digest([v for k, v in sorted(st.items()) if isinstance(v, torch.Tensor)])
    if dataclasses.is_dataclass(x):  # a Trajectory
        return f"{type(x).__name__} " + _value_digest([getattr(x, f.name) for f in dataclasses.fields(x)])
    return repr(x)


def loop_fingerprint(cfg, sources: Sequence[Any], seqs: Sequence[Any], poses: Sequence[Any], gts: Sequence[Any],
                     opt, device) -> Dict[str, str]:
    """The run's ``checkpoint.fingerprint`` (module docstring)."""
    inputs = [ckpt.input_fingerprint(src, s) for src, s in zip(sources, seqs)]
    options: Dict[str, Any] = {}
    for i, (p, g) in enumerate(zip(poses, gts)):
        options[f"poses {i + 1}"] = _value_digest(p)
        options[f"ground truth {i + 1}"] = _value_digest(g)
    for f in dataclasses.fields(opt):
        if f.name in _NOT_OUTPUTS:
            continue
        v = getattr(opt, f.name)
        options[f.name] = v if isinstance(v, (bool, int, float, str, type(None))) else _value_digest(v)
    options["device"] = device.type
    from ..fused import resolve_backend

    options["lk_backend"] = resolve_backend(None, device)  # the tracker's kernels decide its bits
    return ckpt.fingerprint(cfg, inputs, options)


class LoopCheckpoints:
    """The staging folder and checkpoints of one ``run_loop`` with ``out`` (module docstring).

    Args:
        out: the output folder. fingerprint: :func:`loop_fingerprint`.
        every: ``LoopOptions.checkpoint_every``. resume: ``LoopOptions.resume``.

    Attributes: ``stage`` (the ``StagedFolder``; ``write_loop_outputs`` fills and commits it),
    ``resumed`` (the ``checkpoint.Checkpoint`` continued from, or None), ``phase`` (its phase, or
    None), ``before`` (the interrupted runs' seconds), ``writer`` (the ``Checkpointer``).

    As a context manager: on an exception the staging folder is removed, except on SIGINT/SIGTERM
    (``KeyboardInterrupt``) once a checkpoint is in it (kept for ``--resume``).
    """

    def __init__(self, out, fingerprint: Dict[str, str], every: Optional[int], resume: bool):
        from .._atomic import StagedFolder, make_folders, remove_empty_folders
        from ..loop.report import LEGACY_OUTPUTS

        out = Path(out)
        self.resumed = ckpt.resume_point(out, fingerprint) if resume else None
        if resume and self.resumed is None:
            from ..errors import DataWarning

            warnings.warn(f"--resume: no checkpoint of an interrupted run of {out} found: starting from the first "
                          f"frame", DataWarning, stacklevel=3)
        # the folders made here are removed again, while empty, when the run fails (__exit__)
        self._created = make_folders(out.parent)
        try:
            self.stage = StagedFolder(out, "loop", LEGACY_OUTPUTS,
                                      adopt=None if self.resumed is None else self.resumed.stage)
        except BaseException:
            remove_empty_folders(self._created)
            raise
        self.writer = ckpt.Checkpointer(self.stage.path, fingerprint, every, self.resumed)
        self.rank_stage = None
        self._start()

    @classmethod
    def of_rank(cls, rank_stage) -> LoopCheckpoints:
        """The checkpoints of one rank of a sharded ``loop`` (stages 1-4 of its inputs, and with
        separate graphs its finished inputs), in its ``elastic.RankStage``; no staging of ``out``
        (``stage`` is None)."""
        self = cls.__new__(cls)
        self.resumed, self.stage, self.writer, self.rank_stage = rank_stage.resumed, None, rank_stage.writer, rank_stage
        self._start()
        return self

    def _start(self) -> None:
        self.keep_on_interrupt = self.resumed is not None
        p = {} if self.resumed is None else self.resumed.payload
        self.phase: Optional[str] = p.get("phase")
        self.before: float = float(p.get("seconds", 0.0))
        self.t0 = time.perf_counter()
        # what the prepared checkpoint said (kept in every later one): times, counts
        self.prepared: Dict[str, Any] = dict(p.get("prepared") or {})
        #: each stream's ``KeyframeLog.mark()`` at the last checkpoint (its next chunk starts there)
        self.log_marks: Optional[List[Dict[str, int]]] = None

    # -- what the resumed checkpoint holds --------------------------------------------------------
    def chunks(self, phase: str) -> List[Dict[str, Any]]:
        """The resumed checkpoint's chunks of ``phase``, in order."""
        return [] if self.resumed is None else [c for c in self.resumed.chunks if c["phase"] == phase]

    @property
    def payload(self) -> Dict[str, Any]:
        return {} if self.resumed is None else self.resumed.payload

    @property
    def past_tracking(self) -> bool:
        """Whether the resumed checkpoint is past stages 1-4 (they come from it)."""
        return self.phase not in (None, "tracking")

    def seconds(self) -> float:
        """The run's seconds so far: the interrupted runs' and this one's."""
        return self.before + time.perf_counter() - self.t0

    # -- writing ----------------------------------------------------------------------------------
    def due(self, counter: int) -> bool:
        return self.writer.due(counter)

    def save(self, counter: int, phase: str, payload: Dict[str, Any], chunk: Dict[str, Any]) -> None:
        """Checkpoint ``counter`` of ``phase`` (module docstring): ``chunk`` appended, ``payload``
        as the state (with the phase, the seconds so far and the prepared stages' entries)."""
        self.writer.save(counter, {**payload, "phase": phase, "seconds": self.seconds(), "prepared": self.prepared},
                         {**chunk, "phase": phase})
        self.keep_on_interrupt = True
        if self.rank_stage is not None:
            self.rank_stage.keep = True

    @staticmethod
    def kill_point(event: str, n: int) -> None:
        """The test hook (``checkpoint.KILL_ENV``) at ``event`` number ``n``."""
        if ckpt.kill_point(event, n):
            ckpt.kill_now()

    @staticmethod
    def frame_hook(frames: int) -> None:
        """The test hook after tracking frame (step) ``frames`` (``checkpoint.frame_hook``)."""
        ckpt.frame_hook(frames)

    # -- the staging folder -----------------------------------------------------------------------
    def __enter__(self) -> LoopCheckpoints:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            return False
        if self.keep_on_interrupt and issubclass(exc_type, KeyboardInterrupt):
            exc.resumable = True  # the CLI's message: rerun with --resume
        else:
            self.stage.abort()
            from .._atomic import remove_empty_folders

            remove_empty_folders(getattr(self, "_created", ()))
        return False
