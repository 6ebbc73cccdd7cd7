"""The pipelines sharded over processes with ``torch.distributed`` (gloo on the CPU, 2
ranks, 1 thread each, tiny inputs).

* ``torchrun -m torch_frontend track`` with 2 ranks: every ``stream<b>/`` output set is the one a
  one-process run of that input writes, byte for byte (``summary.json`` up to wall times), and the
  merged summary has the one-process run's counts;
* ``vocabulary train`` with 2 ranks: the same file as one process with the same seed (k-medians
  over ranks is exact); ``distributed.train_vocabulary`` equals ``Vocabulary.train`` bit for bit;
* faults: a corrupt input on one rank, and a rank killed mid-run, make the job exit non-zero
  naming the rank and its input, write no merged summary and leave the finished per-input
  outputs valid; the next run clears the killed rank's temporaries;
* ``FrameStream`` (DataLoader decoding) gives ``MultiStream``'s batches and errors; sharding,
  the output-folder rules, and results that no process-global state (the global RNG) changes.

Ranks other than the ``torchrun`` test are forked from the test process (``RANK``/``WORLD_SIZE``/
``MASTER_PORT`` on a free port; the store lives in rank 0), so they start without importing torch
again. Every launch has a deadline: a hanging rank fails the test, it cannot hang the suite.
"""

from __future__ import annotations

import faulthandler
import json
import multiprocessing
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

# (matplotlib's Agg backend, the writers, pipelines, tracker, pose graph, kmedians: imported here,
# before any rank is forked, so that the ranks inherit them instead of importing them again: seconds each on a
# busy 2-core machine)
import matplotlib.backends.backend_agg  # noqa: F401
import numpy as np
import pytest
import torch

import torch_frontend.loop.pose_graph  # noqa: F401
import torch_frontend.loop.report  # noqa: F401
import torch_frontend.outputs  # noqa: F401
import torch_frontend.pipelines.loop  # noqa: F401
import torch_frontend.pipelines.sharded  # noqa: F401
import torch_frontend.tracker  # noqa: F401
from tests._helpers import make_asl, make_loop_inputs, small_config, truncate
from tests.conftest import REPO, sample_frames
from torch_frontend.cli import main
from torch_frontend.distributed import dist_env, rank_device, shard, shard_indices
from torch_frontend.distributed import kmedians as _kmedians  # noqa: F401
from torch_frontend.pipelines.track import TrackOptions, run_track

TORCHRUN = Path(sys.executable).with_name("torchrun")
#: wall-time limit of one launch (s): far above what a run takes, so only a hang reaches it
DEADLINE = 90
TIMING_KEYS = {"seconds", "frames_per_second", "tracker_seconds", "decode_seconds", "input_wait_seconds", "out",
               "distributed", "index"}


# ----------------------------------------------------------------------------------------------
# launching ranks


@dataclass
class RankResult:
    rc: Optional[int]
    out: str
    err: str


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_main(rank: int, world: int, port: int, argv: List[str], logdir: str, entry=None) -> None:
    """A forked rank: the launcher's environment, output into files, ``entry`` (``cli.main``),
    ``os._exit``."""
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world),
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    out = open(os.path.join(logdir, f"{rank}.out"), "w", buffering=1)
    err = open(os.path.join(logdir, f"{rank}.err"), "w", buffering=1)
    os.dup2(out.fileno(), 1)
    os.dup2(err.fileno(), 2)
    sys.stdout, sys.stderr = out, err
    # a rank the deadline finds still running dumps every thread's stack into its .err before the kill
    faulthandler.register(signal.SIGUSR1, file=err, all_threads=True)
    torch.set_num_threads(1)
    rc = 99
    try:
        rc = (entry or main)([str(a) for a in argv])
        rc = rc if isinstance(rc, int) else 0
    except BaseException:  # a traceback the test shows
        traceback.print_exc()
    finally:
        out.flush()
        err.flush()
        os._exit(rc)


def run_ranks(argv, logdir: Path, world: int = 2, kill_rank: Optional[int] = None, kill_when=None,
              entry=None) -> List[RankResult]:
    """``torch-frontend argv`` (or ``entry(argv)``) on ``world`` forked ranks; ``kill_when()``
    (polled) says when to SIGKILL ``kill_rank``. Fails the test if a rank outlives ``DEADLINE``."""
    logdir.mkdir(parents=True, exist_ok=True)
    ctx = multiprocessing.get_context("fork")
    port = _free_port()
    procs = [ctx.Process(target=_rank_main, args=(r, world, port, list(argv), str(logdir), entry))
             for r in range(world)]
    for p in procs:
        p.start()
    t_end = time.monotonic() + DEADLINE
    killed = kill_rank is None
    while any(p.is_alive() for p in procs) and time.monotonic() < t_end:
        if not killed and kill_when():
            os.kill(procs[kill_rank].pid, signal.SIGKILL)
            killed = True
        time.sleep(0.01)
    hung = [r for r, p in enumerate(procs) if p.is_alive()]
    for r in hung:
        os.kill(procs[r].pid, signal.SIGUSR1)  # its stacks into {r}.err (faulthandler)
    if hung:
        time.sleep(1.0)
    for p in procs:
        if p.is_alive():
            p.kill()
        p.join()
    res = [RankResult(p.exitcode, (logdir / f"{r}.out").read_text(), (logdir / f"{r}.err").read_text())
           for r, p in enumerate(procs)]
    assert not hung, f"ranks {hung} still running after {DEADLINE} s: {res}"
    return res


def run_torchrun(args, timeout: float = DEADLINE) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc-per-node 2 -m torch_frontend args``, its whole process group
    killed at ``timeout``."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    cmd = [str(TORCHRUN), "--standalone", "--nproc-per-node", "2", "-m", "torch_frontend", *map(str, args)]
    p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        pytest.fail(f"torchrun still running after {timeout} s:\n{out}\n{err}")
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


# ----------------------------------------------------------------------------------------------
# inputs and comparisons


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Three small ASL sequences (cropped sample frames; different excerpts, lengths 8, 10, 6)
    and their config."""
    root = tmp_path_factory.mktemp("dist_inputs")
    fr = sample_frames("cam0")
    seqs = [make_asl(root / f"in{i}", frames=fr[a:b], small=True) for i, (a, b) in enumerate([(0, 8), (6, 16), (14, 20)])]
    return {"root": root, "seqs": seqs, "config": small_config(root)}


def _files(d: Path):
    return sorted(p.relative_to(d) for p in d.rglob("*") if p.is_file())


def assert_same_output_set(ref: Path, got: Path) -> None:
    """Every file byte-identical, except ``summary.json``: equal up to wall times and paths."""
    assert _files(ref) == _files(got), (ref, got)
    for rel in _files(ref):
        if rel.name == "summary.json":
            a, b = json.loads((ref / rel).read_text()), json.loads((got / rel).read_text())
            assert {k: v for k, v in a.items() if k not in TIMING_KEYS} == \
                   {k: v for k, v in b.items() if k not in TIMING_KEYS}, rel
        else:
            assert (ref / rel).read_bytes() == (got / rel).read_bytes(), rel


def no_temporaries(d: Path) -> bool:
    return not [p for p in d.rglob(".*")]


# ----------------------------------------------------------------------------------------------
# track


def test_torchrun_track_two_ranks_matches_one_process(inputs, tmp_path):
    """The acceptance run: ``torchrun --nproc-per-node 2 -m torch_frontend track`` on 3 inputs
    (rank 0 gets inputs 0-1 as its batch, rank 1 input 2)."""
    cfg, seqs = inputs["config"], inputs["seqs"]
    out = tmp_path / "dist"
    args = ["track", cfg, *[a for s in seqs for a in ("--euroc", s)], "--out", out, "--no-progress"]
    res = run_torchrun(args)
    assert res.returncode == 0, res.stderr
    assert "ranks         2 (gloo)" in res.stdout and res.stdout.count("streams       3") == 1  # rank 0 prints
    assert res.stdout.count("config        ") == 1 and "max_cnt" in res.stdout  # the settings, once
    s = json.loads((out / "summary.json").read_text())
    index = json.loads((out / "index.json").read_text())
    assert [e["rank"] for e in index["streams"]] == [0, 0, 1]
    assert s["distributed"]["world_size"] == 2 and [r["streams"] for r in s["distributed"]["ranks"]] == [[0, 1], [2]]
    # each stream's outputs = a one-process run of that input alone
    for b, seq in enumerate(seqs):
        one = tmp_path / f"one{b}"
        run_track(cfg, [("euroc", seq)], one, TrackOptions(progress=False))
        assert_same_output_set(one, out / f"stream{b}")
    # the merged summary = the one-process summary of all three inputs as one batch of B = 3
    ref = run_track(cfg, [("euroc", s) for s in seqs], tmp_path / "all", TrackOptions(progress=False, write_tracks=False))
    ref["track_images"] = s["track_images"]  # tracks/ not drawn in the reference
    assert {k: v for k, v in ref.items() if k not in TIMING_KEYS} == {k: v for k, v in s.items() if k not in TIMING_KEYS}
    marker = json.loads((out / "written-by-torch-frontend.json").read_text())
    assert marker["kind"] == "track-sharded" and marker["folders"] == ["stream0", "stream1", "stream2"]
    assert sorted(marker["files"]) == ["index.json", "summary.json"]
    assert no_temporaries(out)


def test_sharded_track_keeps_each_inputs_config(inputs, tmp_path):
    """2 forked ranks, three inputs with three configs (``--config`` after input 0, another after
    input 1, input 2 its own sensor.yaml): each ``stream<b>/`` is the run of input b alone with
    its config, the merged summary names every stream's config (per_stream) and camera."""
    cfg, seqs = inputs["config"], inputs["seqs"]
    other = tmp_path / "other.yaml"
    text = cfg.read_text()
    assert "fx: 4.616e+02" in text and "max_cnt: 60" in text
    other.write_text(text.replace("fx: 4.616e+02", "fx: 5.5e+02").replace("max_cnt: 60", "max_cnt: 40"))
    per = [cfg, other, seqs[2] / "mav0" / "cam0" / "sensor.yaml"]
    out = tmp_path / "dist"
    args = ["track", "--euroc", seqs[0], "--config", cfg, "--euroc", seqs[1], "--config", other, "--euroc", seqs[2],
            "--out", out, "--no-progress", "--no-tracks", "--max-frames", 4]
    res = run_ranks(args, tmp_path / "logs")
    assert [r.rc for r in res] == [0, 0], res
    assert res[0].out.count("config        ") == 3 and "(stream 1)" in res[0].out  # one line per config
    s = json.loads((out / "summary.json").read_text())
    assert [e["config"] for e in s["per_stream"]] == [str(p) for p in per]
    assert s["per_stream"][2]["camera"]["model"] == "PINHOLE"
    for b, seq in enumerate(seqs):
        one = tmp_path / f"one{b}"
        run_track(per[b], [("euroc", seq)], one, TrackOptions(progress=False, write_tracks=False, max_frames=4))
        assert_same_output_set(one, out / f"stream{b}")


def test_corrupt_input_on_one_rank_fails_cleanly(inputs, tmp_path):
    cfg = inputs["config"]
    fr = sample_frames("cam0")
    good = make_asl(tmp_path / "good", frames=fr[:4], small=True)  # rank 0: done long before rank 1 fails
    bad_seq = make_asl(tmp_path / "bad", frames=fr[4:16], small=True)
    bad = sorted((bad_seq / "mav0" / "cam0" / "data").glob("*.png"))[-1]  # rank 1: its last frame
    truncate(bad)
    out = tmp_path / "dist"
    res = run_ranks(["track", cfg, "--euroc", good, "--euroc", bad_seq, "--out", out, "--no-progress",
                     "--timeout", 30], tmp_path / "logs")
    assert [r.rc for r in res] == [1, 1], res
    # the failed rank: its own line; rank 0: the job's line; both name rank 1, its input and the file
    for r in res:
        lines = [ln for ln in r.err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("torch-frontend: error: "), r.err
        assert "rank 1" in lines[0] and str(bad_seq) in lines[0] and str(bad) in lines[0] and "truncated PNG" in lines[0]
    assert "no merged summary written" in res[0].err
    assert not (out / "summary.json").exists() and not (out / "index.json").exists()
    assert not (out / "stream1").exists() or not any((out / "stream1").iterdir())  # the failed input: nothing
    one = tmp_path / "one0"
    run_track(cfg, [("euroc", good)], one, TrackOptions(progress=False))
    assert_same_output_set(one, out / "stream0")  # the finished input's outputs are complete
    assert no_temporaries(out)


def test_killed_rank_fails_within_timeout_and_next_run_cleans_up(inputs, tmp_path):
    cfg, seqs = inputs["config"], inputs["seqs"]
    out = tmp_path / "dist"
    args = ["track", cfg, "--euroc", seqs[2], "--euroc", seqs[1], "--out", out, "--no-progress", "--timeout", 30]
    # kill rank 1 once it is writing its outputs (its staging folder, beside out, exists)
    res = run_ranks(args, tmp_path / "logs", kill_rank=1,
                    kill_when=lambda: any(tmp_path.glob(".dist.rank1.*/stream1")))
    assert res[1].rc == -signal.SIGKILL and res[0].rc == 1, res
    line = res[0].err.strip().splitlines()[-1]
    assert line.startswith("torch-frontend: error: ") and "rank 1" in line and str(seqs[1]) in line
    assert "died" in line and "stalled" not in line  # found by its process being gone, not by the timeout
    assert not (out / "summary.json").exists()
    one = tmp_path / "one"
    run_track(cfg, [("euroc", seqs[2])], one, TrackOptions(progress=False))
    assert_same_output_set(one, out / "stream0")
    assert list(tmp_path.glob(".dist.rank1.*"))  # the killed rank could not remove its staging folder
    # the next run removes it (its process is gone) and writes a complete set
    res = run_ranks(args[:-2], tmp_path / "logs2")
    assert [r.rc for r in res] == [0, 0], res
    assert (out / "summary.json").is_file() and no_temporaries(out) and not list(tmp_path.glob(".dist.*"))
    assert_same_output_set(one, out / "stream0")


def test_sharded_out_folder_rules(inputs, tmp_path):
    """A folder with foreign files (or a one-process output set) is refused before any work, by
    rank 0 alone; the previous job's streams are cleared."""
    cfg, seqs = inputs["config"], inputs["seqs"]
    out = tmp_path / "dist"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    res = run_ranks(["track", cfg, "--euroc", seqs[0], "--euroc", seqs[2], "--out", out, "--no-progress",
                     "--no-tracks"], tmp_path / "l1")
    assert [r.rc for r in res] == [1, 1] and res[1].err == ""
    assert "notes.txt" in res[0].err and "sharded run" in res[0].err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    (out / "notes.txt").unlink()
    (out / "stream5").mkdir()  # an earlier, larger job's folder (empty: replaceable)
    res = run_ranks(["track", cfg, "--euroc", seqs[0], "--euroc", seqs[2], "--out", out, "--no-progress",
                     "--no-tracks", "--max-frames", 3], tmp_path / "l2")
    assert [r.rc for r in res] == [0, 0], res
    assert sorted(p.name for p in out.iterdir()) == ["index.json", "stream0", "stream1", "summary.json",
                                                      "written-by-torch-frontend.json"]
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 6 and [p["frames"] for p in s["per_stream"]] == [3, 3]
    # a one-process run may replace the sharded folder as a whole (its marker lists everything)
    run_track(cfg, [("euroc", seqs[0])], out, TrackOptions(progress=False, write_tracks=False, max_frames=2))
    assert (out / "features.csv").is_file() and not (out / "stream0").exists()


# ----------------------------------------------------------------------------------------------
# vocabulary


def test_vocabulary_train_two_ranks_same_file(tmp_path):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for f in sample_frames("cam0")[::4][:5]:  # 5 images: 3 on rank 0, 2 on rank 1
        shutil.copy(f, imgs / f.name)
    args = ["vocabulary", "train", imgs, "--k", 4, "--L", 3, "--max-keypoints", 150, "--seed", 3, "--no-progress"]
    one = tmp_path / "one.npz"
    assert main([str(a) for a in args + ["--out", one]]) == 0
    two = tmp_path / "two.npz"
    res = run_ranks(args + ["--out", two], tmp_path / "logs")
    assert [r.rc for r in res] == [0, 0], res
    assert two.read_bytes() == one.read_bytes()
    assert "750 descriptors of 5 images" in res[0].out and res[1].out == ""


def test_train_vocabulary_one_process_equals_vocabulary_train():
    from torch_frontend.distributed import train_vocabulary
    from torch_frontend.loop.vocabulary import Vocabulary

    g = torch.Generator().manual_seed(5)
    base = torch.randint(-(2**62), 2**62, (30, 4), generator=g, dtype=torch.int64)
    desc = base[torch.randint(0, 30, (7, 40), generator=g)]  # repeated descriptors: ties everywhere
    valid = torch.rand(7, 40, generator=g) < 0.8
    for k, L in [(3, 3), (10, 2)]:
        ref = Vocabulary.train(desc, valid, k=k, L=L, generator=torch.Generator().manual_seed(1))
        got = train_vocabulary(desc, valid, k=k, L=L, generator=torch.Generator().manual_seed(1))
        for name in ("parent", "node_desc", "node_weight", "node_word"):
            assert torch.equal(getattr(ref, name), getattr(got, name)), (k, L, name)


# ----------------------------------------------------------------------------------------------
# the pieces


def test_shard_indices_cover_inputs_in_order():
    for n in range(0, 9):
        for world in range(1, 5):
            parts = [list(shard_indices(n, r, world)) for r in range(world)]
            assert sum(parts, []) == list(range(n))
            sizes = [len(p) for p in parts]
            assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)
    assert shard("abcde", 1, 2) == ["d", "e"] and shard("abcde", 0, 2) == ["a", "b", "c"]
    with pytest.raises(ValueError):
        shard_indices(3, 2, 2)


def test_env_and_device(monkeypatch):
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE"):
        monkeypatch.delenv(k, raising=False)
    e = dist_env()
    assert (e.rank, e.world_size, e.launched) == (0, 1, False)
    monkeypatch.setenv("RANK", "3")
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("LOCAL_RANK", "1")
    e = dist_env()
    assert (e.rank, e.world_size, e.local_rank, e.launched) == (3, 4, 1, True)
    assert rank_device(1, "cpu") == torch.device("cpu")
    assert rank_device(1, "cuda") == torch.device("cuda:1")
    expected = torch.device("cuda:1") if torch.cuda.is_available() else torch.device("cpu")
    assert rank_device(1) == expected


def test_frame_stream_gives_multistream_batches(tmp_path):
    """Workers 0, 1 and 2, with and without skipping a corrupt frame, streams of different
    lengths, ``max_steps``: the same batches, skipped frames and error as ``MultiStream``."""
    from torch_frontend.errors import DataError
    from torch_frontend.io import MultiStream, open_sequence
    from torch_frontend.pipelines.prefetch import FrameStream

    fr = sample_frames("cam0")
    a = make_asl(tmp_path / "a", frames=fr[:6], small=True)
    b = make_asl(tmp_path / "b", frames=fr[3:7], small=True)
    for i in (1, 2):
        truncate(sorted((b / "mav0" / "cam0" / "data").glob("*.png"))[i])

    def batches(cls, skip, **kw):
        st = cls([open_sequence("euroc", a, skip_bad=skip), open_sequence("euroc", b, skip_bad=skip)], **kw)
        got = []
        try:
            for x in st:
                got.append((x.step, x.images.clone(), x.timestamps.clone(), x.stamps_ns.tolist(), x.alive.tolist(),
                            list(x.sources), [r.copy() for r in x.raw]))
        except DataError as exc:  # the same error; each layer names its own option (`skip_bad`, `skip_bad_frames`)
            got.append(re.sub(r" \(`\w+` skips unreadable frames\)$", "", str(exc)))
        return got, st.skipped

    def same(x, y):
        if len(x[0]) != len(y[0]) or x[1] != y[1]:
            return False
        for p, q in zip(x[0], y[0]):
            if isinstance(p, str) or isinstance(q, str):
                if p != q:
                    return False
            elif not (p[0] == q[0] and torch.equal(p[1], q[1]) and torch.equal(p[2], q[2]) and p[3:6] == q[3:6]
                      and all(np.array_equal(u, v) for u, v in zip(p[6], q[6]))):
                return False
        return True

    for skip in (False, True):
        for max_steps in (None, 3):
            ref = batches(MultiStream, skip, max_steps=max_steps)
            assert isinstance(ref[0][-1], str) != skip  # without skipping: the corrupt frame's error
            for workers in (0, 1, 2):
                got = batches(FrameStream, skip, max_steps=max_steps, workers=workers)
                assert same(ref, got), (skip, max_steps, workers)


def test_track_workers_same_outputs_and_decode_times(inputs, tmp_path):
    cfg, seqs = inputs["config"], inputs["seqs"]
    srcs = [("euroc", seqs[0]), ("euroc", seqs[2])]
    a = run_track(cfg, srcs, tmp_path / "w0", TrackOptions(progress=False, write_tracks=False))
    b = run_track(cfg, srcs, tmp_path / "w2", TrackOptions(progress=False, write_tracks=False, workers=2))
    for name in ("features.csv", "features.npz"):
        assert (tmp_path / "w0" / name).read_bytes() == (tmp_path / "w2" / name).read_bytes()
    assert a["workers"] == 0 and b["workers"] == 2
    for s in (a, b):
        assert s["decode_seconds"] > 0 and s["input_wait_seconds"] > 0 and s["tracker_seconds"] > 0


def test_results_do_not_depend_on_the_global_rng(inputs, tmp_path):
    """What a DDP script does on each rank (seed torch per rank, draw from it) changes nothing."""
    cfg, seqs = inputs["config"], inputs["seqs"]
    outs = []
    for i, seed in enumerate((0, 12345)):
        torch.manual_seed(seed)
        np.random.seed(seed)
        torch.rand(100 + i)
        run_track(cfg, [("euroc", seqs[1])], tmp_path / f"r{i}", TrackOptions(progress=False, write_tracks=False,
                                                                              max_frames=6))
        outs.append((tmp_path / f"r{i}" / "features.npz").read_bytes())
    assert outs[0] == outs[1]


# ----------------------------------------------------------------------------------------------
# loop


LOOP_TIMING_KEYS = TIMING_KEYS | {"times", "keyframes_per_second"}


@pytest.fixture(scope="module")
def loop_inputs(tmp_path_factory):
    """The demo's revisit render, small (``tests._helpers.make_loop_inputs``): the ``loop`` arguments."""
    return make_loop_inputs(tmp_path_factory.mktemp("dist_loop"))


def _same_summary(a: dict, b: dict) -> None:
    assert {k: v for k, v in a.items() if k not in LOOP_TIMING_KEYS} == \
           {k: v for k, v in b.items() if k not in LOOP_TIMING_KEYS}


def test_loop_shared_map_two_ranks_matches_one_process(loop_inputs, tmp_path):
    """Rank 0 builds the one pose graph from both ranks' keyframes: the one-process output set."""
    one, two = tmp_path / "one", tmp_path / "two"
    assert main([str(a) for a in loop_inputs + ["--out", one]]) == 0
    res = run_ranks(loop_inputs + ["--out", two], tmp_path / "logs")
    assert [r.rc for r in res] == [0, 0], res
    assert "ranks         2 (gloo)" in res[0].out and res[1].out == ""
    assert _files(one) == _files(two)
    for rel in _files(one):
        if rel.name != "summary.json":
            assert (one / rel).read_bytes() == (two / rel).read_bytes(), rel
    a, b = (json.loads((d / "summary.json").read_text()) for d in (one, two))
    _same_summary(a, b)
    assert b["keyframes"] >= 10 and b["streams"] == 2 and b["graphs"] == 1
    assert [r["streams"] for r in b["distributed"]["ranks"]] == [[0], [1]]


@pytest.mark.slow  # the shared-map case above runs the same sharding (make test-all and CI run it)
def test_loop_separate_graphs_two_ranks_matches_one_process(loop_inputs, tmp_path):
    """One graph per input on its rank (the vocabulary trained once on both inputs' keyframes):
    each ``stream<b>/`` holds the one-process run's trajectories and pose graph of input b."""
    from torch_frontend.loop.report import STREAM_FILES

    args = loop_inputs + ["--separate-graphs"]
    one, two = tmp_path / "one", tmp_path / "two"
    assert main([str(a) for a in args + ["--out", one]]) == 0
    res = run_ranks(args + ["--out", two], tmp_path / "logs")
    assert [r.rc for r in res] == [0, 0], res
    for b in range(2):
        for name in STREAM_FILES:
            assert (one / f"stream{b}" / name).read_bytes() == (two / f"stream{b}" / name).read_bytes(), name
        ref_graph = one / f"stream{b}" / "pose_graph"
        assert _files(ref_graph) == _files(two / f"stream{b}" / "pose_graph")
        for rel in _files(ref_graph):
            assert (ref_graph / rel).read_bytes() == (two / f"stream{b}" / "pose_graph" / rel).read_bytes(), rel
        assert (two / f"stream{b}" / "summary.json").is_file() and (two / f"stream{b}" / "loops.csv").is_file()
    _same_summary(json.loads((one / "summary.json").read_text()), json.loads((two / "summary.json").read_text()))
    index = json.loads((two / "index.json").read_text())
    assert [e["rank"] for e in index["streams"]] == [0, 1] and no_temporaries(two)


def test_ddp_example_script(tmp_path, monkeypatch):
    """``docs/examples/ddp_track.py``: each rank tracks its own sequence (the sample's cam0 on rank 0,
    its shorter cam1 on rank 1: uneven steps under ``DistributedDataParallel.join``)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("ddp_track", REPO / "docs" / "examples" / "ddp_track.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    destroy = dist.destroy_process_group

    def counted_destroy(*a, **k):
        # a DDP wrapper alive when the group goes would free the group later, from its C++ reducer
        # with the GIL held: the teardown deadlock the script avoids (one CI run hung in it)
        import gc

        gc.collect()
        live = sum(isinstance(o, DistributedDataParallel) for o in gc.get_objects())
        print(f"DDP wrappers alive at destroy_process_group: {live}")
        return destroy(*a, **k)

    monkeypatch.setattr(dist, "destroy_process_group", counted_destroy)  # the forked ranks inherit it
    res = run_ranks(["--steps", 8, "--workers", 1], tmp_path / "logs", entry=mod.main)
    assert [r.rc for r in res] == [0, 0], res
    assert "rank 0: 1 sequences, 8 steps" in res[0].out and "rank 1: 1 sequences, 6 steps" in res[1].out
    assert "2 ranks, 2 sequences: mean loss" in res[0].out
    assert all("DDP wrappers alive at destroy_process_group: 0" in r.out for r in res), res


def test_job_in_one_process(monkeypatch):
    """Without a launcher a job is rank 0 of 1 (an in-memory store): results pass through, a
    failure becomes the job's one-line report, each phase has its own outcomes."""
    from torch_frontend.distributed import Job, RankFailure
    from torch_frontend.errors import DataError

    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE"):
        monkeypatch.delenv(k, raising=False)

    def boom():
        raise DataError("in.png: truncated PNG")

    with Job("track", inputs="euroc:a, euroc:b", timeout=5) as job:
        assert (job.rank, job.world_size, job.distributed) == (0, 1, False)
        assert job.run(lambda: 5) == 5
        with pytest.raises(RankFailure, match=r"rank 0 \(euroc:a, euroc:b\) failed: in.png: truncated PNG") as e:
            job.run(boom, phase="second")
        assert e.value.exit_code == 1 and e.value.statuses[0]["outcome"] == "failed"
        assert job.gather("x") == ["x"] and job.broadcast(3) == 3
