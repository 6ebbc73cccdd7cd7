"""``torchrun --max-restarts 1`` with a rank SIGKILLed once (the checkpoint test hook, armed at the
job's first start only: ``tests/_elastic_entry.py``): torch elastic restarts every rank, each
resumes its streams from its checkpoint in the job's staging area (``pipelines.elastic``), the
finished ones are not redone, and ``out`` ends up as an uninterrupted job's: every ``stream<b>/``
byte for byte, ``summary.json`` and ``index.json`` equal up to the timing fields.

2 ranks, gloo, 1 thread each, tiny inputs (the sample frames cropped; the small revisit render).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests._helpers import make_asl, make_loop_inputs, small_config
from tests.conftest import REPO, sample_frames

TORCHRUN = Path(sys.executable).with_name("torchrun")
ENTRY = REPO / "tests" / "_elastic_entry.py"
DEADLINE = 180  # s for one job (a restart included): far above its time, so only a hang reaches it
TIMING_KEYS = {"seconds", "frames_per_second", "tracker_seconds", "decode_seconds", "input_wait_seconds", "out",
               "distributed", "times", "keyframes_per_second"}


def torchrun(args, kill_rank=None, kill_at=None, restarts: int = 0) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc-per-node 2 [--max-restarts N] tests/_elastic_entry.py args``;
    ``kill_rank`` SIGKILLs itself at ``kill_at`` (the test hook) at the first start. The whole
    process group is killed at ``DEADLINE``."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    if kill_rank is not None:
        env.update(TF_TEST_KILL_RANK=str(kill_rank), TF_TEST_KILL_AT=kill_at)
    cmd = [str(TORCHRUN), "--standalone", "--nproc-per-node", "2", "--max-restarts", str(restarts),
           "--monitor-interval", "0.1", str(ENTRY), *map(str, args)]
    p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        out, err = p.communicate(timeout=DEADLINE)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        pytest.fail(f"torchrun still running after {DEADLINE} s:\n{out}\n{err}")
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


def _files(d: Path):
    return sorted(p.relative_to(d) for p in d.rglob("*") if p.is_file())


def _untimed(d: dict) -> dict:
    return {k: v for k, v in d.items() if k not in TIMING_KEYS}


def assert_same_job_outputs(ref: Path, got: Path) -> None:
    """Every file byte-identical; the ``summary.json`` files (merged and per input) and
    ``index.json`` equal up to the timing fields."""
    assert _files(ref) == _files(got)
    for rel in _files(ref):
        if rel.name in ("summary.json", "index.json"):
            assert _untimed(json.loads((ref / rel).read_text())) == _untimed(json.loads((got / rel).read_text())), rel
        else:
            assert (ref / rel).read_bytes() == (got / rel).read_bytes(), rel


def no_staging_left(out: Path) -> bool:
    """No temporary in ``out`` nor beside it (the ranks' staging folders are removed at the end)."""
    return not list(out.rglob(".*")) and not [p for p in out.parent.glob(f".{out.name}.*")]


# ----------------------------------------------------------------------------------------------
# track


@pytest.fixture(scope="module")
def track_job(tmp_path_factory):
    """Three small ASL sequences (lengths 8, 10, 6: rank 0 tracks the first two, rank 1 the third)
    and an uninterrupted job's ``out``."""
    root = tmp_path_factory.mktemp("elastic_track")
    fr = sample_frames("cam0")
    seqs = [make_asl(root / f"in{i}", frames=fr[a:b], small=True) for i, (a, b) in enumerate([(0, 8), (6, 16), (14, 20)])]
    args = ["track", small_config(root), *[a for s in seqs for a in ("--euroc", s)], "--no-progress"]
    ref = root / "ref"
    res = torchrun(args + ["--out", ref])
    assert res.returncode == 0, res.stderr
    return args, ref


def test_torchrun_rank_killed_once_resumes_from_its_checkpoint(track_job, tmp_path):
    """Rank 1 killed at its 3rd step (after its checkpoint at step 2): both ranks restarted, rank
    1 resumes at step 2, rank 0 from its own last checkpoint; ``out`` = the uninterrupted job's."""
    args, ref = track_job
    out = tmp_path / "out"
    res = torchrun(args + ["--out", out, "--checkpoint-every", 2], kill_rank=1, kill_at="frame:3", restarts=1)
    assert res.returncode == 0, res.stderr
    assert "rank 1: restart 1 of the job: resuming from its checkpoint at step 2" in res.stderr
    assert_same_job_outputs(ref, out)
    assert no_staging_left(out)


#: rank 0 killed around the end of its first input (8 frames; checkpoints every 4 steps), and where
#: its restart resumes. ``frame:10``: after that input was finished and checkpointed at step 9, so
#: the restarted rank keeps its folder as it is and tracks the other from step 9. ``frame:9``: right
#: after the input ended, before the checkpoint that says so: its output is not committed yet (its
#: staging folder, with the track images of the frames before the last checkpoint, stays), so the
#: restarted rank redoes it from step 8 (a commit before that checkpoint left an input the resume
#: redid without its earlier track images: the CI failure of stop 38). ``ended:9``: after that
#: checkpoint, before the input's output is swapped in: the restarted rank swaps the staged set in
#: and does not redo the input.
KILLS_AROUND_AN_END = {
    "finished_stream_not_redone": ("frame:10", "resuming from its checkpoint at step 9 (1 of its inputs finished)"),
    "ended_before_its_checkpoint": ("frame:9", "resuming from its checkpoint at step 8"),
    "ended_before_its_commit": ("ended:9", "resuming from its checkpoint at step 9 (1 of its inputs finished)"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(KILLS_AROUND_AN_END))
def test_torchrun_rank_killed_around_the_end_of_an_input(track_job, tmp_path, case):
    kill_at, resumed = KILLS_AROUND_AN_END[case]
    args, ref = track_job
    out = tmp_path / "out"
    res = torchrun(args + ["--out", out, "--checkpoint-every", 4], kill_rank=0, kill_at=kill_at, restarts=1)
    assert res.returncode == 0, res.stderr
    assert f"rank 0: restart 1 of the job: {resumed}" in res.stderr
    assert_same_job_outputs(ref, out)
    assert no_staging_left(out)


@pytest.mark.slow
def test_torchrun_without_restarts_fails_and_resume_continues(track_job, tmp_path):
    """Without --max-restarts the killed rank fails the job (as before); its checkpoints stay in
    the job's staging area, and the same command with --resume continues from them."""
    args, ref = track_job
    out = tmp_path / "out"
    res = torchrun(args + ["--out", out, "--checkpoint-every", 2], kill_rank=1, kill_at="frame:3")
    assert res.returncode != 0
    assert not (out / "summary.json").exists()
    assert ".out.rank1" in {p.name.split(".tf")[0] for p in tmp_path.glob(".out.rank*")}  # the killed rank's
    res = torchrun(args + ["--out", out, "--checkpoint-every", 2, "--resume"])
    assert res.returncode == 0, res.stderr
    assert "rank 1: --resume: resuming from its checkpoint at step 2" in res.stderr
    assert_same_job_outputs(ref, out)
    assert no_staging_left(out)


# ----------------------------------------------------------------------------------------------
# loop


@pytest.fixture(scope="module")
def loop_job(tmp_path_factory):
    """The small revisit render's two laps (rank 0: lap 1, rank 1: lap 2; 16 steps each) and the
    one-process run's outputs (what the shared-map job writes)."""
    from torch_frontend.cli import main

    root = tmp_path_factory.mktemp("elastic_loop")
    args = [str(a) for a in make_loop_inputs(root)]
    ref = root / "ref"
    assert main(args + ["--out", str(ref)]) == 0
    return args, ref


@pytest.mark.slow  # covered by the track case and test_resume_loop.py (make test-all and CI run it)
def test_torchrun_loop_rank_killed_once(loop_job, tmp_path):
    """Shared map: rank 1 killed while tracking (after its checkpoint at step 4); restarted, both
    ranks resume their tracking, rank 0 builds the graph: the one-process run's outputs."""
    args, ref = loop_job
    out = tmp_path / "out"
    res = torchrun(args + ["--out", out, "--checkpoint-every", 4], kill_rank=1, kill_at="frame:6", restarts=1)
    assert res.returncode == 0, res.stderr
    assert "rank 1: restart 1 of the job: resuming from its checkpoint at step 4" in res.stderr
    assert _files(ref) == _files(out)
    for rel in _files(ref):
        if rel.name == "summary.json":
            assert _untimed(json.loads((ref / rel).read_text())) == _untimed(json.loads((out / rel).read_text()))
        else:
            assert (ref / rel).read_bytes() == (out / rel).read_bytes(), rel
    assert no_staging_left(out)


@pytest.mark.slow
def test_torchrun_loop_separate_graphs_finished_input_not_redone(loop_job, tmp_path):
    """Separate graphs: rank 0 killed right after it wrote its input's ``stream0/`` and
    checkpointed it; restarted, rank 0 keeps that folder and redoes nothing, rank 1 resumes from
    its own checkpoint: ``out`` = the uninterrupted job's (``index.json`` and ``summary.json`` too)."""
    args, _ = loop_job
    args = args + ["--separate-graphs"]
    ref, out = tmp_path / "ref", tmp_path / "out"
    res = torchrun(args + ["--out", ref])
    assert res.returncode == 0, res.stderr
    res = torchrun(args + ["--out", out, "--checkpoint-every", 4], kill_rank=0, kill_at="written:1", restarts=1)
    assert res.returncode == 0, res.stderr
    assert "rank 0: restart 1 of the job: resuming from its checkpoint at step 17 (1 of its inputs finished)" \
        in res.stderr
    assert_same_job_outputs(ref, out)
    assert no_staging_left(out)
