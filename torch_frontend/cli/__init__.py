"""The ``torch-frontend`` command line: ``track``, ``demo``, ``loop``, ``vocabulary train``, ``compare``
and ``config``.

This module does argparse and printing only: each command builds the options of a pipeline from
its flags, calls the pipeline (``torch_frontend.pipelines``), prints the summary and maps errors to
exit codes.

``torch-frontend track [CONFIG] (--euroc DIR | --kitti SEQ | --bag PATH | --images DIR [--config FILE] | --rig FILE)...
--out DIR`` runs the VINS front end on one or more sequences at once (B streams in one batched
tracker, each with its own config: :func:`_paired_inputs`) and writes
``features.csv``, ``features.npz``, ``summary.json``, two plots and ``tracks/`` into ``--out``
(``pipelines.track.run_track``; see ``torch_frontend.outputs``). ``torch-frontend demo`` does the
same on the sample EuRoC frames shipped with the package.

``torch-frontend loop [CONFIG] (--euroc DIR | --kitti SEQ | --images DIR | --bag FILE)... --poses FILE... --out DIR
(--vocabulary FILE | --train-vocabulary)`` runs loop closure (VINS's pose graph) on images plus
their VIO poses and writes the loop-corrected trajectory, the loops, the pose graph, a summary and
plots (``pipelines.loop.run_loop``, ``torch_frontend.loop.report``); ``torch-frontend demo --loop``
does the same on a rendered sequence that revisits places (``pipelines.loop.demo_loop``).
``torch-frontend vocabulary train`` is ``pipelines.vocabulary.run_vocabulary_train``; ``torch-frontend
config --from-kalibr camchain.yaml [--imu imu.yaml] --out FILE`` (or ``--from-camera-info``) writes a
VINS config from calibration files (``pipelines.make_config``, ``torch_frontend.calibration``).

Under ``torchrun`` (``torchrun --nproc-per-node N -m torch_frontend track|loop|vocabulary train
...``) every rank runs the command on its block of the inputs (``pipelines.sharded``): each rank on
``cuda:LOCAL_RANK`` when CUDA is present (``--device`` not given), rank 0 printing the merged
summary; ``--timeout`` bounds how long a rank may go without progress. ``--workers N`` decodes the
frames in DataLoader workers (``pipelines.prefetch``).

``track``, ``demo`` and ``loop`` run torch and OpenCV on one thread unless ``--threads N`` is given
or the user set ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` (:func:`_thread_policy`; the library
itself never changes the process's threads), and restore the previous counts afterwards.

User errors (missing or unreadable input, a bad config, a bag without the topic, an image of the
wrong size, an empty sequence, a bad option value; a corrupt frame's line names ``--skip-bad-frames``)
print one line ``torch-frontend: error: ...`` on
stderr and exit with a non-zero code: 2 for usage, option and config errors, 1 for data errors,
130 when interrupted (Ctrl-C, SIGINT), 143 on SIGTERM. A pipeline's ``OptionError`` names its
option; the line names the flag. Under ``torchrun`` an error every rank meets is printed by rank 0
only; a rank's own failure by that rank (``rank r (inputs): ...``) and by rank 0 (the job's line).

SIGINT and SIGTERM stop a command the same way (a ``KeyboardInterrupt``, while the command runs;
the previous handlers come back after it): the run removes its temporary folder, so ``--out``
keeps a complete set of outputs, the previous one, or the new one if the run had swapped it in
already (``torch_frontend.outputs``).
"""

from __future__ import annotations

import contextlib
import re
import signal
import sys
from pathlib import Path
from typing import Dict, List

from ..errors import ConfigError, DataError
from ..pipelines.common import OptionError
from .commands import format_loop_summary, format_summary
from .common import (
    EXIT_DATA,
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    EXIT_USAGE,
    PACKAGE_DIR,
    SAMPLE_DIR,
    THREAD_ENV,
    _rank,
    _thread_policy,
    _UsageError,
    default_config_path,
)
from .parser import build_parser

__all__ = ["main", "build_parser", "default_config_path", "format_summary", "format_loop_summary", "PACKAGE_DIR",
           "SAMPLE_DIR", "THREAD_ENV", "EXIT_DATA", "EXIT_USAGE", "EXIT_INTERRUPTED", "EXIT_TERMINATED"]


def _error(msg: str) -> None:
    print(f"torch-frontend: error: {' '.join(str(msg).split())}", file=sys.stderr)


def _option_message(exc: OptionError, flags: Dict[str, str]) -> str:
    """``exc``'s message with its option name (which starts it) and every option named in backticks
    inside it (the library's style: "rerun without `resume`") replaced by the command's flags."""
    msg = str(exc)
    flag = flags.get(exc.option)
    msg = flag + msg[len(exc.option):] if flag and msg.startswith(exc.option) else msg
    return _flags_in(msg, flags)


def _flags_in(msg: str, flags: Dict[str, str]) -> str:
    """Every option named in ``msg`` in backticks (the library's style: "`skip_bad_frames` skips
    unreadable frames") replaced by the command's flag; other backticked words are kept."""
    return re.sub(r"`([a-z_]+)`", lambda m: flags.get(m.group(1), m.group(0)), msg)


def _os_error_message(exc: OSError, out) -> str:
    """One line for an ``OSError`` that reached the CLI: "cannot write" for the output folder
    ``out``, a file in it or a hidden temporary beside it (or when no file is named), "cannot read"
    for any other file (an input; the readers report their own files as ``DataError``)."""
    name = getattr(exc, "filename", None)
    verb = "write"
    if name is not None and out is not None:
        try:
            target, where = Path(out).resolve(), Path(str(name)).resolve()
            first = where.relative_to(target.parent).parts[:1] if target.parent in where.parents else ()
            if not first or not (first[0] == target.name or first[0].startswith(".")):
                verb = "read"
        except (OSError, RuntimeError, ValueError):  # a name that does not resolve: keep "write"
            pass
    return f"cannot {verb}{f' {name}' if name is not None else ''}: {exc.strerror or exc}"


class _Signalled(KeyboardInterrupt):
    """SIGINT or SIGTERM as a ``KeyboardInterrupt``: every writer cleans up as on Ctrl-C."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_signalled(signum, frame) -> None:
    raise _Signalled(signum)


@contextlib.contextmanager
def _interrupt_signals():
    """SIGINT and SIGTERM raise :class:`_Signalled` inside the block; the previous handlers come
    back after it. A signal ignored by whoever started us (``nohup``, a background job) stays
    ignored; outside the main thread nothing changes."""
    saved = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            prev = signal.getsignal(sig)
            if prev is signal.SIG_IGN:
                continue
            signal.signal(sig, _raise_signalled)
        except ValueError:  # not the main thread
            continue
        saved[sig] = signal.SIG_DFL if prev is None else prev
    try:
        yield
    finally:
        for sig, prev in saved.items():
            signal.signal(sig, prev)


@contextlib.contextmanager
def _config_warnings():
    """A config's ``ConfigWarning`` (an unknown key, "did you mean ...?") and the poses'
    ``WorldFrameWarning`` (loop closure's up axis) as one stderr line
    ``torch-frontend: warning: ...`` and an input's ``DataWarning`` (colour frames made grey) as
    ``torch-frontend: note: ...`` inside the block; other warnings as Python prints them."""
    import warnings

    from ..errors import ConfigWarning, DataWarning, WorldFrameWarning

    shown = warnings.showwarning
    rank = _rank()

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, (ConfigWarning, WorldFrameWarning)):
            # under torchrun every rank reads the config: rank 0 says it once; a rank's own poses: that rank
            if rank == 0 or issubclass(category, WorldFrameWarning):
                print(f"torch-frontend: warning: {message}", file=sys.stderr)
        elif issubclass(category, DataWarning):
            print(f"torch-frontend: note: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = shown


def main(argv: List[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    from ..distributed.job import JobAborted, RankFailure

    # Under torchrun every rank runs this: an error every rank meets (a bad option, config or
    # output folder) is printed by rank 0 only; a rank's own failure by that rank, rank 0 adding
    # the job's one-line report (pipelines.sharded).
    rank = _rank()

    def error(exc: BaseException, msg: str) -> None:
        if rank == 0 or getattr(exc, "rank_error", False):
            _error(msg if rank == 0 or msg.startswith("rank ") else f"rank {rank}: {msg}")

    try:
        threads = _thread_policy(args.threads) if hasattr(args, "threads") else contextlib.nullcontext()
        with _interrupt_signals(), threads, _config_warnings():
            return int(args.func(args) or 0)
    except (ConfigError, _UsageError) as exc:
        error(exc, str(exc))
        return EXIT_USAGE
    except OptionError as exc:
        error(exc, _option_message(exc, getattr(args, "flags", {})))
        return EXIT_USAGE
    except RankFailure as exc:
        error(exc, _flags_in(f"{exc}; no merged summary written", getattr(args, "flags", {})))
        return exc.exit_code
    except DataError as exc:  # an option named in backticks (`skip_bad_frames`, `fps`) -> its flag
        error(exc, _flags_in(str(exc), getattr(args, "flags", {})))
        return EXIT_DATA
    except JobAborted as exc:
        if not exc.quiet:
            error(exc, str(exc))
        return EXIT_DATA
    except KeyboardInterrupt as exc:
        term = getattr(exc, "signum", signal.SIGINT) == signal.SIGTERM
        detail = getattr(exc, "detail", None)
        msg = (f"interrupted{' (SIGTERM)' if term else ''}: no partial output left (the output folder holds "
               f"its previous complete outputs, or this run's if it had finished writing them)")
        if getattr(exc, "resumable", False):
            msg = (f"interrupted{' (SIGTERM)' if term else ''}: the output folder holds its previous complete outputs; "
                   f"this run's last checkpoint is kept: rerun the same command with --resume to continue from it")
        if detail:  # a sharded run: who had not finished (torchrun stops every rank when one dies)
            msg = (f"interrupted{' (SIGTERM)' if term else ''}: {detail}; no merged summary written (complete "
                   f"per-input outputs stay)")
        error(exc, msg)
        return EXIT_TERMINATED if term else EXIT_INTERRUPTED
    except OSError as exc:  # e.g. --out is a file, a read-only folder, a full disk; an unreadable input
        error(exc, _os_error_message(exc, getattr(args, "out", None)))
        return EXIT_DATA


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
