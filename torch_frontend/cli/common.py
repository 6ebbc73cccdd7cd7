"""What every part of the command line shares: exit codes, the package's sample paths, the
usage error, the process's rank and the thread policy."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from ..errors import ConfigError

PACKAGE_DIR = Path(__file__).resolve().parent.parent
SAMPLE_DIR = PACKAGE_DIR / "data" / "euroc_mini"

EXIT_DATA = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_TERMINATED = 143  # 128 + SIGTERM


def default_config_path() -> Path:
    """The EuRoC config: ``configs/euroc.yaml`` of a source checkout, else the packaged copy."""
    for p in (PACKAGE_DIR.parent / "configs" / "euroc.yaml", PACKAGE_DIR / "data" / "configs" / "euroc.yaml"):
        if p.is_file():
            return p
    raise ConfigError("cannot find configs/euroc.yaml (looked beside the package)")


class _UsageError(Exception):
    """Bad command-line combination (printed as one line, exit 2)."""


#: environment variables that set torch's intra-op threads: when the user sets one, the CLI leaves
#: the threads to it (torch reads them at start-up)
THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _thread_policy(threads: int | None):
    """torch's intra-op threads and OpenCV's for one command (``--threads``), restored after it.

    Default (``threads`` None): 1, unless the user set ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS``
    (then nothing is changed). One thread because the tracker's tensors are small (752x480
    images, ~150 points): extra threads only add synchronisation, and on a busy machine each of
    the tracker's many small ops then waits for a descheduled thread. Measured on this project's
    shared 2-core machine (``docs/cli.md#threads``): ``track`` on the sample frames, in the worst
    sitting, 0.3-1.6 frames/s with torch's default 2 threads and 8.5-14.3 with 1 (loaded by one
    busy core or not)."""
    import torch

    if threads is None and any(os.environ.get(v) for v in THREAD_ENV):
        yield
        return
    n = 1 if threads is None else int(threads)
    try:
        import cv2
    except ImportError:  # pragma: no cover - cv2 is a dependency
        cv2 = None
    saved = torch.get_num_threads(), (cv2.getNumThreads() if cv2 is not None else None)
    torch.set_num_threads(n)
    if cv2 is not None:
        cv2.setNumThreads(n)
    try:
        yield
    finally:
        torch.set_num_threads(saved[0])
        if cv2 is not None:
            cv2.setNumThreads(saved[1])



def _rank() -> int:
    """This process's rank under a launcher (0 without one)."""
    from ..distributed.env import dist_env

    try:
        return dist_env().rank
    except ValueError:  # a malformed RANK: let the command report it
        return 0
