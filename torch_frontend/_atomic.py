"""Atomic writes of single files and of whole output folders, and which folders the library may
replace. Used by every writer (run outputs, trajectories, the pose graph, the vocabulary).

Files: ``atomic_path`` / ``write_*_atomic`` write to a hidden temporary name beside the final
name and rename it over the final name (``os.replace``): an interrupted or failed write leaves
no partial file under the final name.

Folders: a :class:`StagedFolder` is a fresh hidden temporary folder beside its target; the writer
fills it and ``commit()`` writes the marker ``written-by-torch-frontend.json`` (the list of what
the library wrote) into it and swaps it in for the target in one step, so the target holds either
its complete old or its complete new contents, never a mix. On Linux the swap is one
``renameat2(RENAME_EXCHANGE)``; elsewhere (or on a file system without it) it is two renames with
SIGINT/SIGTERM deferred in between. A failed or interrupted writer removes its temporary folder.

Convention (what may be replaced):
    A folder is replaced only when it is absent, empty, or written by the library: it holds the
    marker and nothing the marker does not list (a sub-folder with a marker of its own is judged by
    that one), or, for a folder written before the marker existed, it has no marker and every
    entry matches the writer's ``legacy`` patterns (the names it writes, and the temporaries older
    versions left behind). Anything else, or a file at the target, raises
    :class:`OutputFolderError` naming the folder, the foreign entries and why; nothing is deleted,
    moved or written then. The check runs when the writer starts and again just before the swap.

    Temporaries are named ``.<name>.tf<pid>-<random>.tmp`` (``.old`` for the backup of a two-rename
    swap), ``<pid>`` being the writing process. Every new write of a target first removes those of
    its stale temporaries whose process no longer runs on this machine (a run killed by SIGKILL or
    a power cut); those of a live process (a concurrent writer) are left alone, and a backup left by
    a swap cut between its two renames is moved back when the target is missing (or an empty
    folder). Nothing else is ever removed, except the folders a failed run created itself
    (:func:`make_folders`), and those only while empty (:func:`remove_empty_folders`).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import signal
import stat
import sys
import tempfile
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Set, Tuple

from .errors import DataError

__all__ = [
    "CHECKPOINT_FOLDER",
    "MARKER",
    "OutputFolderError",
    "StagedFolder",
    "adopt_staging",
    "atomic_path",
    "check_replaceable",
    "clean_stale",
    "foreign_entries",
    "legacy_temporaries",
    "make_folders",
    "remove_empty_folders",
    "replace_dir",
    "stale_staging",
    "write_bytes_atomic",
    "write_text_atomic",
]

#: the file the library writes into every folder it owns (JSON: ``written_by``, ``kind``,
#: ``folders``, ``files``, paths relative to the folder, ``/``-separated)
MARKER = "written-by-torch-frontend.json"
_WRITTEN_BY = "torch-frontend"
#: a staging folder's private sub-folder (``pipelines.checkpoint``: a long run's checkpoints),
#: removed by :meth:`StagedFolder.commit` before the marker is written: never among the outputs
CHECKPOINT_FOLDER = ".checkpoint"
_TAG = "tf"  # temporaries: .<name>.tf<pid>-<random>.tmp|.old
# how many foreign entries an error names (the walk stops there: a big foreign tree costs nothing)
_SHOWN = 3


class OutputFolderError(DataError):
    """A folder the library was asked to replace holds something it did not write, or is a file."""


# ----------------------------------------------------------------------------------------------
# temporaries


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _default_mode(tmp: Path, is_dir: bool = False) -> None:
    # mkstemp/mkdtemp create 0600/0700; give the final file the mode a plain open() would.
    os.chmod(tmp, (0o777 if is_dir else 0o666) & ~_umask())


def _temp_prefix(name: str) -> str:
    return f".{name}.{_TAG}{os.getpid()}-"


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (True when it cannot be told)."""
    if os.name != "posix":  # os.kill would terminate it on Windows: never clean there
        return True
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it runs, as another user
        return True
    return True


def _absent_or_empty(p: Path) -> bool:
    if not os.path.lexists(p):
        return True
    if p.is_symlink() or not p.is_dir():
        return False
    with os.scandir(p) as it:
        return next(it, None) is None


def stale_staging(target: Path) -> List[Path]:
    """The staging folders (``.<name>.tf<pid>-<random>.tmp``, folders) of ``target`` whose process
    no longer runs on this machine: what a run killed outright left (``pipelines.checkpoint``
    resumes from one), and what :func:`clean_stale` would remove. Sorted by name."""
    target = Path(target)
    pattern = re.compile(rf"\.{re.escape(target.name)}\.{_TAG}(\d+)-[A-Za-z0-9_]+\.tmp")
    try:
        entries = [e for e in os.scandir(target.parent) if e.name.startswith(f".{target.name}.{_TAG}")]
    except OSError:
        return []
    found = []
    for e in sorted(entries, key=lambda e: e.name):
        m = pattern.fullmatch(e.name)
        if m is not None and not e.is_symlink() and e.is_dir() and not _pid_alive(int(m.group(1))):
            found.append(Path(e.path))
    return found


def adopt_staging(stale: Path, target: Path) -> Path:
    """Rename the stale staging folder ``stale`` of ``target`` to a fresh staging name of this
    process (so that :func:`clean_stale`, here or in a concurrent writer, leaves it alone); returns
    the new path, for ``StagedFolder(..., adopt=path)``."""
    target = Path(target)
    fresh = Path(tempfile.mkdtemp(prefix=_temp_prefix(target.name), suffix=".tmp", dir=target.parent))
    os.rmdir(fresh)  # the name is reserved; renaming onto an empty folder fails on Windows
    os.rename(stale, fresh)
    return fresh


def clean_stale(target: Path) -> List[Path]:
    """Remove the stale temporaries of ``target`` (see the module docstring); returns them."""
    target = Path(target)
    pattern = re.compile(rf"\.{re.escape(target.name)}\.{_TAG}(\d+)-[A-Za-z0-9_]+\.(tmp|old)")
    removed: List[Path] = []
    try:
        entries = [e for e in os.scandir(target.parent) if e.name.startswith(f".{target.name}.{_TAG}")]
    except OSError:
        return removed
    for e in sorted(entries, key=lambda e: e.name):
        m = pattern.fullmatch(e.name)
        if m is None or e.is_symlink() or _pid_alive(int(m.group(1))):
            continue
        p = Path(e.path)
        if m.group(2) == "old" and e.is_dir() and _absent_or_empty(target):
            if os.path.lexists(target):
                os.rmdir(target)
            os.rename(p, target)  # a swap cut between its two renames: the old contents come back
        elif e.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return removed


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``, else delete it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(path)
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path.name), suffix=".tmp", dir=path.parent)
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


def make_folders(path) -> List[Path]:
    """``mkdir -p path``; returns the folders it created, outermost first (empty when ``path``
    existed): what :func:`remove_empty_folders` may remove again after a failed run."""
    p = Path(os.path.abspath(path))
    missing: List[Path] = []
    while not os.path.lexists(p):
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    created: List[Path] = []
    for d in reversed(missing):
        try:
            d.mkdir()
        except FileExistsError:  # made meanwhile by someone else: not ours
            continue
        created.append(d)
    return created


def remove_empty_folders(created: Sequence[Path]) -> None:
    """Remove those of ``created`` (folders a run made, :func:`make_folders`) that are empty,
    innermost first; a folder that holds anything (whoever wrote it) stays, and nothing else is
    ever removed (``os.rmdir`` only removes empty folders)."""
    for d in reversed(list(created)):
        try:
            os.rmdir(d)
        except OSError:  # not empty, gone, or not ours to remove: left as it is
            return


def legacy_temporaries(*names: str) -> Tuple[str, ...]:
    """``legacy`` patterns of the temporaries versions before the marker left for ``names``:
    ``.<name>.<8 random>.tmp`` (a file, or a folder and its contents) and ``.<name>.old-<pid>``."""
    pats = []
    for n in names:
        pats.append(rf"\.{re.escape(n)}\.[a-z0-9_]{{8}}\.tmp(/.*)?")
        pats.append(rf"\.{re.escape(n)}\.old-\d+(/.*)?")
    return tuple(pats)


# ----------------------------------------------------------------------------------------------
# ownership


def _read_marker(folder: Path) -> Optional[Tuple[Set[str], Set[str]]]:
    """``(files, folders)`` of ``folder``'s marker, or None (no marker, or not a valid one)."""
    p = folder / MARKER
    if p.is_symlink() or not p.is_file():
        return None
    try:
        m = json.loads(p.read_text(encoding="utf-8"))
        if m.get("written_by") != _WRITTEN_BY:
            return None
        return {str(f) for f in m["files"]}, {str(f) for f in m["folders"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def foreign_entries(folder: Path, legacy: Sequence[str] = (), limit: int = _SHOWN) -> List[str]:
    """Up to ``limit`` entries of ``folder`` (paths relative to it, folders ending in ``/``) that
    the library did not write (module docstring); ``[]``: the folder may be replaced."""
    pats = [re.compile(p) for p in legacy]
    found: List[str] = []

    def walk(d: Path, shown: str, rel: str, marker: Optional[Tuple[Set[str], Set[str]]], top: bool) -> None:
        for e in sorted(os.scandir(d), key=lambda e: e.name):
            if len(found) >= limit:
                return
            r = rel + e.name
            is_dir = e.is_dir(follow_symlinks=False)
            if marker is not None:
                owned = (top and e.name == MARKER and not is_dir) or r in (marker[1] if is_dir else marker[0])
            else:
                owned = any(p.fullmatch(r) for p in pats)
            if not owned:
                found.append(shown + e.name + ("/" if is_dir else ""))
            elif is_dir:
                sub = _read_marker(Path(e.path))
                if sub is not None:  # a folder with its own marker answers for itself
                    walk(Path(e.path), shown + e.name + "/", "", sub, True)
                else:
                    walk(Path(e.path), shown + e.name + "/", r + "/", marker, False)

    walk(Path(folder), "", "", _read_marker(Path(folder)), True)
    return found


def check_replaceable(target: Path, legacy: Sequence[str] = ()) -> None:
    """Raise :class:`OutputFolderError` unless ``target`` is absent, an empty folder or a folder
    the library wrote (module docstring)."""
    target = Path(target)
    if not os.path.lexists(target):
        return
    if not target.is_dir():
        raise OutputFolderError(f"{target}: cannot write the outputs here: it is a file, not a folder "
                                f"(left as it is; choose another name)")
    if not os.access(target, os.W_OK):
        # the swap needs only the parent's permission: without this a protected folder (mode 0555)
        # would be replaced as a whole, which is not what protecting it asked for
        mode = stat.S_IMODE(os.stat(target).st_mode)
        raise OutputFolderError(f"{target}: not replaced: you cannot write into it (mode {mode:04o}); "
                                f"make it writable (chmod u+w) or choose another folder")
    foreign = foreign_entries(target, legacy, limit=_SHOWN + 1)
    if foreign:
        shown = ", ".join(foreign[:_SHOWN]) + (" and more" if len(foreign) > _SHOWN else "")
        why = (f"not listed in its {MARKER}" if _read_marker(target) is not None
               else f"no {MARKER} marker here, and not a name torch-frontend writes")
        raise OutputFolderError(f"{target}: not replaced: it holds files torch-frontend did not write: "
                                f"{shown} ({why}); move them away or choose another folder")


def _manifest(folder: Path, kind: str) -> str:
    """The marker's text for the finished ``folder`` (sorted, so equal contents give equal bytes)."""
    files: List[str] = []
    folders: List[str] = []

    def walk(d: Path, rel: str) -> None:
        for e in os.scandir(d):
            r = rel + e.name
            if e.is_dir(follow_symlinks=False):
                folders.append(r)
                if _read_marker(Path(e.path)) is None:  # else its own marker lists its contents
                    walk(Path(e.path), r + "/")
            elif rel or e.name != MARKER:
                files.append(r)

    walk(folder, "")
    m = {
        "written_by": _WRITTEN_BY,
        "kind": kind,
        "about": "this folder was written by torch-frontend as a whole; the next write replaces it as a "
                 "whole, and refuses to while it holds anything not listed here",
        "folders": sorted(folders),
        "files": sorted(files),
    }
    return json.dumps(m, indent=1) + "\n"


# ----------------------------------------------------------------------------------------------
# swapping folders


def _load_renameat2():
    """libc's ``renameat2`` (Linux), or None (looked up once, at import: a few microseconds)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_RENAMEAT2 = _load_renameat2()
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Swap the paths ``a`` and ``b`` in one step; False where the system cannot."""
    fn = _RENAMEAT2
    if fn is None:
        return False
    import ctypes

    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):  # kernel or file system without it
        return False
    raise OSError(err, os.strerror(err), str(b))


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """SIGINT/SIGTERM wait until the block is done (POSIX), so a swap is never cut in two."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _swap_in(new: Path, final: Path) -> Optional[Path]:
    """Put the folder ``new`` at ``final``; returns where the old contents went (None: none)."""
    try:
        os.rename(new, final)  # final absent or an empty folder: one rename
        return None
    except OSError as exc:
        if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY) or not final.is_dir():
            raise
    if _exchange(new, final):
        return new
    backup = Path(tempfile.mkdtemp(prefix=_temp_prefix(final.name), suffix=".old", dir=final.parent))
    os.rmdir(backup)  # the name is reserved; renaming onto an empty folder fails on Windows
    os.rename(final, backup)
    try:
        os.rename(new, final)
    except BaseException:
        os.rename(backup, final)
        raise
    return backup


def _set_modes(folder: Path) -> None:
    _default_mode(folder, is_dir=True)
    for sub in folder.rglob("*"):
        if sub.is_dir() and not sub.is_symlink():
            _default_mode(sub, is_dir=True)


def replace_dir(tmp_dir: Path, final: Path) -> None:
    """Move a finished temporary folder to ``final`` in one step (an existing folder ``final`` is
    replaced and removed, whatever it holds: the library's writers use :class:`StagedFolder`, which
    checks first). A file at ``final`` is refused (``OutputFolderError``)."""
    tmp_dir, final = Path(tmp_dir), Path(final)
    if os.path.lexists(final) and not final.is_dir():
        raise OutputFolderError(f"{final}: is a file, not a folder (left as it is)")
    _set_modes(tmp_dir)
    with _signals_deferred():
        old = _swap_in(tmp_dir, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


class StagedFolder:
    """A temporary folder beside ``target`` that replaces it as a whole on :meth:`commit`.

    Args:
        target: the folder to (re)write. Its parent must exist.
        kind: what the folder holds (``"track"``, ``"loop"``, ``"pose_graph"``: the marker's ``kind``).
        legacy: regular expressions (full match, ``/``-separated relative paths) of what this
            writer wrote before the marker existed (module docstring).
        adopt: an existing staging folder of ``target`` to fill instead of a new one (one that
            :func:`adopt_staging` renamed for this process: a resumed run's).

    Raises:
        OutputFolderError: ``target`` holds something the library did not write, is a file, or is
            a folder this user cannot write into (mode 0555: protected, so not replaced); checked
            here, before any work, and again in :meth:`commit`.

    ``path`` is the folder to fill. As a context manager: commits on success, removes the
    temporary folder on any exception (``KeyboardInterrupt`` included).
    """

    def __init__(self, target, kind: str, legacy: Sequence[str] = (), adopt: Optional[Path] = None):
        self.target = Path(os.path.realpath(target))  # a symlinked target: its folder is rewritten
        self.kind = kind
        self.legacy = tuple(legacy)
        check_replaceable(self.target, self.legacy)
        clean_stale(self.target)
        if adopt is not None:  # a resumed run fills the staging folder its interrupted run left
            self.path = Path(adopt)
        else:
            self.path = Path(tempfile.mkdtemp(prefix=_temp_prefix(self.target.name), suffix=".tmp",
                                              dir=self.target.parent))
        self._open = True

    def commit(self) -> Path:
        """Remove ``path``'s checkpoints (``CHECKPOINT_FOLDER``), write the marker into ``path`` and
        swap it in for the target; returns the target."""
        if not self._open:
            raise RuntimeError(f"{self.target}: StagedFolder already committed or aborted")
        try:
            shutil.rmtree(self.path / CHECKPOINT_FOLDER, ignore_errors=True)
            (self.path / MARKER).write_bytes(_manifest(self.path, self.kind).encode("utf-8"))
            _set_modes(self.path)
            with _signals_deferred():
                check_replaceable(self.target, self.legacy)
                old = _swap_in(self.path, self.target)
                self._open = False
                if old is not None:
                    shutil.rmtree(old, ignore_errors=True)
        except BaseException:
            self.abort()
            raise
        return self.target

    def abort(self) -> None:
        """Remove the temporary folder (the target is not touched)."""
        if self._open:
            self._open = False
            shutil.rmtree(self.path, ignore_errors=True)

    def __enter__(self) -> StagedFolder:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.commit()
        else:
            self.abort()
        return False
