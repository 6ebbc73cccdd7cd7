"""Atomic file writes: a file goes to a hidden temporary name in the same folder and is renamed
over the final name (``os.replace``), so an interrupted or failed write leaves no partial file
under the final name. Used by every writer (run outputs, trajectories, the pose graph, the
vocabulary)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_path", "replace_dir", "write_bytes_atomic", "write_text_atomic"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _default_mode(tmp: Path, is_dir: bool = False) -> None:
    # mkstemp/mkdtemp create 0600/0700; give the final file the mode a plain open() would.
    os.chmod(tmp, (0o777 if is_dir else 0o666) & ~_umask())


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``, else delete it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_p = Path(tmp)
    try:
        yield tmp_p
        _default_mode(tmp_p)
        os.replace(tmp_p, path)
    except BaseException:
        tmp_p.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: Path, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def replace_dir(tmp_dir: Path, final: Path) -> None:
    """Move a finished temporary folder to ``final`` (an existing ``final`` is replaced)."""
    _default_mode(tmp_dir, is_dir=True)
    for sub in tmp_dir.rglob("*"):
        if sub.is_dir():
            _default_mode(sub, is_dir=True)
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.old-{os.getpid()}"
        if old.exists():
            shutil.rmtree(old)
        os.replace(final, old)
    os.replace(tmp_dir, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
