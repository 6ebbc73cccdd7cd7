"""Output sets are atomic as a whole, and nothing the library did not write is deleted (
items 1-2): ``track`` stopped by SIGINT, SIGTERM or SIGKILL in the middle of writing leaves its
``--out`` with the complete previous set, a rerun leaves the complete new set and no temporary;
foreign files in ``--out`` are refused, never deleted; ``loop``'s writer is atomic the same way;
stale temporaries of killed writers are removed, those of live ones kept.

The CLI runs that get a signal run in a child process whose ``numpy.savez_compressed`` (the
``features.npz`` writer, called after ``features.csv`` is written) writes its data, touches a
"ready" file and sleeps: the signal lands in the middle of writing the set, every time.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from tests._helpers import OUTPUTS, assert_one_error_line, make_asl, run_cli, small_config
from tests.conftest import REPO
from torch_frontend import _atomic
from torch_frontend._atomic import MARKER, OutputFolderError, StagedFolder, write_bytes_atomic
from torch_frontend.loop import report
from torch_frontend.loop.pose_graph import PoseGraph
from torch_frontend.trajectory import Trajectory

# the child: the CLI with a features.npz writer that stops in the middle of writing the set when
# TF_TEST_READY names a file; prints whether the signal handlers are back after main()
CHILD = textwrap.dedent("""
    import os, signal, sys, time
    import numpy as np
    ready = os.environ.get("TF_TEST_READY")
    if ready:
        real = np.savez_compressed
        def savez_compressed(*args, **kwargs):
            real(*args, **kwargs)
            open(ready, "w").close()
            time.sleep(300)
        np.savez_compressed = savez_compressed
    before = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    from torch_frontend.cli import main
    rc = main(sys.argv[1:])
    after = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    print("handlers restored" if after == before else f"handlers changed: {before} -> {after}")
    sys.exit(rc)
""")


def snapshot(folder: Path) -> dict:
    """``{relative path: bytes or "<dir>"}`` of everything under ``folder`` (hidden entries too)."""
    return {p.relative_to(folder).as_posix(): "<dir>" if p.is_dir() else p.read_bytes()
            for p in sorted(folder.rglob("*"))}


def temporaries(out: Path) -> list:
    """Hidden entries inside ``out`` and beside it (``.<out name>.*``)."""
    inside = [p for p in out.rglob(".*")] if out.is_dir() else []
    beside = [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]
    return sorted(inside + beside)


def track_argv(tmp_path: Path, seq: Path, out: Path, frames: int) -> list:
    return ["track", str(small_config(tmp_path)), "--euroc", str(seq), "--out", str(out),
            "--max-frames", str(frames), "--no-progress"]


def interrupted_child(argv: list, ready: Path, sig: int) -> subprocess.CompletedProcess:
    """Run the CLI in a child, send ``sig`` once it is in the middle of writing, wait for it."""
    env = {**os.environ, "TF_TEST_READY": str(ready), "PYTHONWARNINGS": "ignore",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", CHILD, *argv], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        t0 = time.monotonic()
        while not ready.exists():
            assert proc.poll() is None, f"the child ended before writing: {proc.communicate()}"
            assert time.monotonic() - t0 < 180, "the child never reached the writer"
            time.sleep(0.05)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


def assert_complete_new_set(out: Path, frames: int) -> None:
    for name in (*OUTPUTS, MARKER):
        assert (out / name).is_file(), name
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == frames
    rows = (out / "features.csv").read_text().splitlines()[1:]
    assert len(rows) == s["published_features"] == len(np.load(out / "features.npz")["id"])
    assert len(list((out / "tracks" / "stream0").glob("*.png"))) == s["published"]


@pytest.mark.parametrize("sig, code, words", [(signal.SIGINT, 130, "interrupted"),
                                              (signal.SIGTERM, 143, "interrupted (SIGTERM)")])
def test_signal_during_write_keeps_the_old_set(tmp_path, capsys, sig, code, words):
    """SIGINT / SIGTERM while ``track`` writes its set: one stderr line, exit 130 / 143, ``--out``
    byte-identical to the previous run's set, no temporary; the previous signal handlers are
    back after ``main``; a rerun writes the complete new set and leaves no temporary."""
    seq = make_asl(tmp_path / "a", n=5, small=True)
    out = tmp_path / "o"
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, out, 4))
    assert rc == 0, err
    old = snapshot(out)
    r = interrupted_child(track_argv(tmp_path, seq, out, 5), tmp_path / "ready", sig)
    assert r.returncode == code, r.stderr
    assert snapshot(out) == old  # the complete old set, nothing of the new one
    assert temporaries(out) == []
    assert_one_error_line(r.stderr, words, "no partial output")
    assert "handlers restored" in r.stdout
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, out, 5))
    assert rc == 0, err
    assert_complete_new_set(out, 5)
    assert temporaries(out) == []


def test_sigkill_during_write_keeps_the_old_set_and_rerun_cleans(tmp_path, capsys):
    """A run killed outright (SIGKILL: no handler runs) in the middle of writing: ``--out`` still
    holds the complete old set; its temporary folder beside ``--out`` is removed by the rerun."""
    seq = make_asl(tmp_path / "a", n=5, small=True)
    out = tmp_path / "o"
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, out, 4))
    assert rc == 0, err
    old = snapshot(out)
    r = interrupted_child(track_argv(tmp_path, seq, out, 5), tmp_path / "ready", signal.SIGKILL)
    assert r.returncode == -signal.SIGKILL
    assert snapshot(out) == old
    assert temporaries(out) != []  # the killed run's temporary folder (removed below)
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, out, 5))
    assert rc == 0, err
    assert_complete_new_set(out, 5)
    assert temporaries(out) == []


def test_track_refuses_foreign_files_in_out(tmp_path, capsys):
    """``--out`` holding a user's file (a fresh folder, or an earlier run's folder the user added
    to): exit 1, one line naming the folder and the file, nothing touched, no temporary."""
    seq = make_asl(tmp_path / "a", n=3, small=True)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, mine, 3))
    assert rc == 1
    assert_one_error_line(err, str(mine.resolve()), "notes.txt", "did not write")
    assert snapshot(mine) == {"notes.txt": b"keep me"} and temporaries(mine) == []
    out = tmp_path / "o"
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, out, 3))
    assert rc == 0, err
    (out / "tracks" / "stream0" / "my_drawing.png").write_bytes(b"mine")
    old = snapshot(out)
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, out, 2))
    assert rc == 1
    assert_one_error_line(err, "tracks/stream0/my_drawing.png", MARKER)
    assert snapshot(out) == old and temporaries(out) == []


def test_track_replaces_a_folder_written_before_the_marker(tmp_path, capsys):
    """An ``--out`` of an older version (no marker; its outputs and the temporaries its killed
    runs left, ``.tracks.*.tmp/`` and ``.features.npz.*.tmp``) is replaced by the new set, with
    no temporary left."""
    seq = make_asl(tmp_path / "a", n=3, small=True)
    out = tmp_path / "o"
    (out / "tracks" / "stream0").mkdir(parents=True)
    (out / "tracks" / "stream0" / "1403715273262142976.png").write_bytes(b"old")
    for name in OUTPUTS:
        (out / name).write_bytes(b"old")
    (out / ".tracks.k2j_x9a0.tmp" / "stream0").mkdir(parents=True)
    (out / ".tracks.k2j_x9a0.tmp" / "stream0" / "1.png").write_bytes(b"old")
    (out / ".features.npz.ab12cd34.tmp").write_bytes(b"half")
    rc, _, err = run_cli(capsys, *track_argv(tmp_path, seq, out, 3))
    assert rc == 0, err
    assert temporaries(out) == []
    assert_complete_new_set(out, 3)


# ----------------------------------------------------------------------------------------------
# loop's writer


def _loop_run(shift: float):
    """A small ``LoopRun``-like object: one stream, an empty pose graph, no loop."""
    t = torch.arange(4, dtype=torch.float64)
    traj = Trajectory(t, torch.stack([t + shift, t, t], 1), torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1).double())
    stream = SimpleNamespace(stream=0, graph=0, name="s0", corrected=traj, vio=traj, ground_truth=None)
    return SimpleNamespace(streams=[stream], graphs=[PoseGraph()], loops=[], summary={"shift": shift})


@pytest.fixture
def quick_plots(monkeypatch):
    monkeypatch.setattr(report, "plot_trajectories", lambda run: b"png of %g" % run.summary["shift"])
    monkeypatch.setattr(report, "plot_scores", lambda run: b"scores")


def test_loop_outputs_interrupted_keep_the_old_set(tmp_path, quick_plots, monkeypatch):
    """``write_loop_outputs`` interrupted after the trajectories, loops and pose graph are written:
    ``out`` holds the complete old set, no temporary is left; a rerun gives the new set."""
    out = tmp_path / "o"
    report.write_loop_outputs(out, _loop_run(0.0))
    old = snapshot(out)

    def interrupted(run):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(report, "plot_scores", interrupted)
        with pytest.raises(KeyboardInterrupt):
            report.write_loop_outputs(out, _loop_run(1.0))
    assert snapshot(out) == old
    assert temporaries(out) == []
    report.write_loop_outputs(out, _loop_run(1.0))
    assert json.loads((out / "summary.json").read_text())["shift"] == 1.0
    assert (out / "trajectory_top.png").read_bytes() == b"png of 1"
    assert temporaries(out) == []
    assert (out / MARKER).is_file() and (out / "pose_graph" / MARKER).is_file()


def test_loop_outputs_refuse_foreign_files(tmp_path, quick_plots):
    """A user's file in a loop ``out`` (at the top or in ``pose_graph/``): refused before the run
    (``check_out_folder``) and by the writer, nothing touched."""
    out = tmp_path / "o"
    report.write_loop_outputs(out, _loop_run(0.0))
    for where in ("notes.txt", "pose_graph/notes.txt"):
        (out / where).write_text("keep me")
        old = snapshot(out)
        with pytest.raises(OutputFolderError, match=where):
            report.write_loop_outputs(out, _loop_run(1.0))
        assert snapshot(out) == old and temporaries(out) == []
        with pytest.raises(OutputFolderError, match=where):
            report.check_out_folder(out)
        (out / where).unlink()
    report.write_loop_outputs(out, _loop_run(1.0))
    assert json.loads((out / "summary.json").read_text())["shift"] == 1.0


# ----------------------------------------------------------------------------------------------
# the building blocks


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_stale_file_temporaries_are_removed_live_ones_kept(tmp_path):
    """A single-file writer (the vocabulary, trajectories) killed mid-write leaves
    ``.<name>.tf<pid>-*.tmp``: the next write of that file removes it when its process is gone,
    keeps it while the process runs (a concurrent writer), and touches nothing else."""
    target = tmp_path / "voc.npz"
    stale = tmp_path / f".voc.npz.tf{_dead_pid()}-abcd1234.tmp"
    live = tmp_path / f".voc.npz.tf{os.getppid()}-efgh5678.tmp"
    other = tmp_path / ".voc.npz.notes.tmp"
    for p in (stale, live, other):
        p.write_bytes(b"x")
    write_bytes_atomic(target, b"new")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([target.name, live.name, other.name])


def test_staged_folder_swap_without_exchange_and_restore(tmp_path, monkeypatch):
    """Where ``renameat2(RENAME_EXCHANGE)`` is missing the swap is two renames; a run killed
    between them (the target gone, its ``.old`` backup left) gets the old contents back on the
    next write, which is then refused or done as usual."""
    monkeypatch.setattr(_atomic, "_exchange", lambda a, b: False)
    final = tmp_path / "g"
    for value in (b"1", b"2"):
        with StagedFolder(final, "test") as st:
            (st.path / "a.txt").write_bytes(value)
        assert (final / "a.txt").read_bytes() == value
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g"]
    for recreated in (False, True):  # the target gone, or an empty folder again (RunRecorder makes one)
        backup = tmp_path / f".g.tf{_dead_pid()}-abcd1234.old"
        final.rename(backup)
        if recreated:
            final.mkdir()
        st = StagedFolder(final, "test")  # cleans the stale temporaries of ``g`` first
        assert (final / "a.txt").read_bytes() == b"2" and not backup.exists()
        st.abort()
        assert sorted(p.name for p in tmp_path.iterdir()) == ["g"]


def test_marker_lists_what_was_written(tmp_path):
    final = tmp_path / "g"
    with StagedFolder(final, "test") as st:
        (st.path / "sub").mkdir()
        (st.path / "sub" / "b.txt").write_bytes(b"b")
        (st.path / "a.txt").write_bytes(b"a")
    m = json.loads((final / MARKER).read_text())
    assert m["written_by"] == "torch-frontend" and m["kind"] == "test"
    assert m["files"] == ["a.txt", "sub/b.txt"] and m["folders"] == ["sub"]
    # a file at the target is refused and stays
    f = tmp_path / "file"
    f.write_bytes(b"x")
    with pytest.raises(OutputFolderError, match="is a file"):
        StagedFolder(f, "test")
    assert f.read_bytes() == b"x" and sorted(p.name for p in tmp_path.iterdir()) == ["file", "g"]
