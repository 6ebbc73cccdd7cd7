"""``torch-frontend track --checkpoint-every N`` / ``--resume`` (``pipelines/checkpoint.py``): a run
SIGKILLed (or SIGTERMed) at a frame or in the middle of writing a checkpoint, then rerun with
``--resume``, finishes with every output file byte for byte an uninterrupted run's (the summary's
timing fields aside); a resume of another run is refused in one line naming what differs; and an
``--out`` the user cannot write into (mode 0555) is refused, not swapped.

The kills come from the test hook ``TORCH_FRONTEND_TEST_KILL_AT`` (``frame:<k>``: SIGKILL once
frame k is recorded; ``checkpoint:<n>``: SIGKILL half-way through writing checkpoint n; ``term:<k>``:
SIGTERM at frame k), deterministic where a timer would not be. Inputs: two streams of small crops
of the sample, the second ending early (7 of 12 frames), so that kills fall before, at and after
its end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests._helpers import assert_one_error_line, make_asl, run_cli, small_config
from tests.conftest import REPO, sample_frames

pytestmark = pytest.mark.usefixtures("single_thread")

EVERY = 3  # --checkpoint-every in the killed runs: checkpoints after frames 3, 6, 9
FRAMES_A, FRAMES_B = 12, 7
#: the summary's entries that are times (or the output path), not results
TIMING = ("seconds", "frames_per_second", "tracker_seconds", "decode_seconds", "input_wait_seconds", "out")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("resume_inputs")
    frames = sample_frames("cam0")
    a = make_asl(root / "a", small=True, frames=frames[:FRAMES_A])
    b = make_asl(root / "b", small=True, frames=frames[6:6 + FRAMES_B])  # ends early
    return small_config(root), a, b


def _args(inputs, out: Path, *extra) -> list:
    cfg, a, b = inputs
    return ["track", cfg, "--euroc", a, "--euroc", b, "--out", out, "--no-progress", *extra]


def _killed(inputs, out: Path, at: str, *extra, expect=-signal.SIGKILL) -> None:
    """Run ``track`` in a subprocess that the test hook kills at ``at``."""
    env = {**os.environ, "TORCH_FRONTEND_TEST_KILL_AT": at, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, "-m", "torch_frontend", *map(str, _args(inputs, out, *extra))], env=env,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == expect, f"expected the hook's kill ({expect}), got {p.returncode}: {p.stderr[-2000:]}"
    assert not (out / "summary.json").exists(), "a killed run must not leave outputs in --out"
    return p


def _staging(out: Path) -> list:
    return sorted(out.parent.glob(f".{out.name}.tf*.tmp"))


def _files(d: Path) -> dict:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def assert_same_outputs(ref: Path, got: Path) -> None:
    """Every file of ``got`` equals ``ref``'s byte for byte, ``summary.json`` but its ``TIMING``."""
    a, b = _files(ref), _files(got)
    assert sorted(a) == sorted(b), f"other files: {sorted(set(a) ^ set(b))}"
    for name in a:
        if name == "summary.json":
            sa, sb = json.loads(a[name]), json.loads(b[name])
            for s in (sa, sb):
                for k in TIMING:
                    s.pop(k, None)
            assert sa == sb, "summary.json differs beyond its timing fields"
        else:
            assert a[name] == b[name], f"{name} differs"


@pytest.fixture(scope="module")
def references(inputs, tmp_path_factory):
    """The uninterrupted runs (default checkpoint interval), per mode / bag variant, made on demand."""
    root = tmp_path_factory.mktemp("resume_refs")
    made = {}

    def get(*extra) -> Path:
        key = tuple(map(str, extra))
        if key not in made:
            out = root / f"ref{len(made)}"
            from torch_frontend.cli import main

            assert main([str(a) for a in _args(inputs, out, *extra)]) == 0
            made[key] = out
        return made[key]

    return get


def _resume(capsys, inputs, out: Path, *extra):
    rc, _, err = run_cli(capsys, *_args(inputs, out, "--checkpoint-every", EVERY, *extra, "--resume"))
    assert rc == 0, err
    return err


# ---------------------------------------------------------------------------------------------- kill, resume, compare


@pytest.mark.parametrize("at,extra", [
    pytest.param("frame:5", ("--write-bag", "features.bag"), id="mono-frame5-ros1bag"),
    pytest.param("checkpoint:2", ("--mode", "fusion"), id="fusion-mid-checkpoint2"),
    pytest.param("frame:9", (), id="mono-frame9-after-stream-b-ended", marks=pytest.mark.slow),
    pytest.param("frame:6", ("--mode", "fusion", "--write-bag", "features_db3"), id="fusion-frame6-at-checkpoint-ros2bag",
                 marks=pytest.mark.slow),
    pytest.param("checkpoint:3", ("--no-tracks",), id="mono-mid-checkpoint3-notracks", marks=pytest.mark.slow),
])
def test_resume_after_sigkill_is_byte_identical(capsys, inputs, references, tmp_path, at, extra):
    ref = references(*extra)
    out = tmp_path / "out"
    _killed(inputs, out, at, "--checkpoint-every", EVERY, *extra)
    assert len(_staging(out)) == 1, "the killed run's staging folder (with its checkpoint) stays beside --out"
    err = _resume(capsys, inputs, out, *extra)
    assert "no checkpoint" not in err
    assert_same_outputs(ref, out)
    assert not _staging(out), "nothing is left beside --out"
    assert not (out / ".checkpoint").exists()


def test_resume_of_another_run_is_refused_in_one_line(capsys, inputs, references, tmp_path):
    out = tmp_path / "out"
    _killed(inputs, out, "frame:4", "--checkpoint-every", EVERY)
    rc, _, err = run_cli(capsys, *_args(inputs, out, "--checkpoint-every", EVERY, "--max-frames", "10", "--resume"))
    assert rc == 2
    assert_one_error_line(err, "--resume", "max_frames differs", "checkpoint: None", "this run: 10", "without --resume")
    cfg, a, b = inputs
    rc, _, err = run_cli(capsys, "track", cfg, "--euroc", b, "--euroc", a, "--out", out, "--no-progress", "--resume")
    assert rc == 2
    assert_one_error_line(err, "input 1 differs")
    # the refusals changed nothing: the right command continues
    _resume(capsys, inputs, out)
    assert_same_outputs(references(), out)


@pytest.mark.slow  # covered by the faster cases (make test-all and CI run it)
def test_without_resume_the_run_starts_over(capsys, inputs, references, tmp_path):
    out = tmp_path / "out"
    _killed(inputs, out, "frame:7", "--checkpoint-every", EVERY)
    rc, _, err = run_cli(capsys, *_args(inputs, out))
    assert rc == 0, err
    assert not _staging(out), "the interrupted run's staging folder is removed, as any stale temporary"
    assert_same_outputs(references(), out)


def test_resume_with_no_checkpoint_starts_from_the_first_frame(capsys, inputs, references, tmp_path):
    out = tmp_path / "out"
    err = _resume(capsys, inputs, out)
    assert "note: --resume: no checkpoint of an interrupted run" in err and "starting from the first frame" in err
    assert_same_outputs(references(), out)


@pytest.mark.slow
@pytest.mark.parametrize("at", ["frame:2", "checkpoint:1"])
def test_killed_before_the_first_checkpoint_starts_over(capsys, inputs, references, tmp_path, at):
    out = tmp_path / "out"
    _killed(inputs, out, at, "--checkpoint-every", EVERY)
    err = _resume(capsys, inputs, out)
    assert "starting from the first frame" in err
    assert_same_outputs(references(), out)
    assert not _staging(out)


@pytest.mark.slow
def test_killed_twice(capsys, inputs, references, tmp_path):
    out = tmp_path / "out"
    _killed(inputs, out, "frame:4", "--checkpoint-every", EVERY)
    _killed(inputs, out, "frame:5", "--checkpoint-every", EVERY, "--resume")  # frame 5 of the resumed run: step 8
    _resume(capsys, inputs, out)
    assert_same_outputs(references(), out)


@pytest.mark.slow  # covered by the faster cases (make test-all and CI run it)
def test_sigterm_keeps_the_checkpoint_for_resume(capsys, inputs, references, tmp_path):
    out = tmp_path / "out"
    p = _killed(inputs, out, "term:7", "--checkpoint-every", EVERY, expect=143)
    assert "--resume" in p.stderr and "Traceback" not in p.stderr
    assert len(_staging(out)) == 1
    _resume(capsys, inputs, out)
    assert_same_outputs(references(), out)


def test_checkpoint_every_zero_writes_none(inputs, tmp_path):
    out = tmp_path / "out"
    p = _killed(inputs, out, "frame:7", "--checkpoint-every", "0")
    assert p.returncode == -signal.SIGKILL
    assert not any((s / ".checkpoint").exists() for s in _staging(out))


# ---------------------------------------------------------------------------------------------- a protected --out


def test_out_the_user_cannot_write_into_is_refused(capsys, inputs, tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    from torch_frontend._atomic import MARKER

    (out / MARKER).write_text(json.dumps({"written_by": "torch-frontend", "kind": "track", "folders": [],
                                          "files": ["keep.txt"]}))
    out.chmod(0o555)
    try:
        if os.geteuid() == 0:
            # root writes into a 0555 folder anyway (os.access says yes): emulate a user who cannot
            real = os.access
            monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == out and mode & os.W_OK
                                else real(p, mode, **kw))
        rc, _, err = run_cli(capsys, *_args(inputs, out, "--max-frames", "3"))
        assert rc == 1
        assert_one_error_line(err, str(out), "not replaced", "cannot write into it", "0555")
        assert (out / "keep.txt").read_text() == "mine" and sorted(p.name for p in out.iterdir()) == sorted([MARKER, "keep.txt"])
        assert not _staging(out)
    finally:
        out.chmod(0o755)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0,
                    reason="root can write into a 0555 folder (os.access is True): the test above emulates it")
def test_out_mode_0555_is_refused_for_real(capsys, inputs, tmp_path):  # pragma: no cover - non-root runs
    out = tmp_path / "out"
    out.mkdir()
    out.chmod(0o555)
    try:
        rc, _, err = run_cli(capsys, *_args(inputs, out, "--max-frames", "3"))
        assert rc == 1
        assert_one_error_line(err, "not replaced", "0555")
    finally:
        out.chmod(0o755)
