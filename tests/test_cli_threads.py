"""The CLI's thread policy (issue 30): ``track``, ``demo`` and ``demo --loop``, ``loop`` run torch and
OpenCV on 1 thread unless ``--threads N`` is given or the user set ``OMP_NUM_THREADS`` /
``MKL_NUM_THREADS``, and put the previous counts back afterwards; the library never changes them.

Before: only ``demo --loop`` set one thread (for good); ``track`` ran on torch's default: on the
shared 2-core machine's worst sitting 0.3-1.6 frames/s on the sample, 8.5-14.3 with one thread
(docs/cli.md#threads).
The pipelines are replaced by a probe that records the counts the command runs with (no tracking).
"""

from __future__ import annotations

import cv2
import pytest
import torch

import torch_frontend.pipelines.loop as loop_pipeline
import torch_frontend.pipelines.track as track_pipeline
from tests._helpers import CONFIG, assert_one_error_line
from tests.conftest import SAMPLE, sample_frames
from torch_frontend.cli import THREAD_ENV, main
from torch_frontend.tracker import FeatureTracker


class _Ran(Exception):
    """Raised by the probe: the command got as far as its pipeline."""


@pytest.fixture
def probe(monkeypatch):
    seen = []

    def record(*args, **kwargs):
        seen.append((torch.get_num_threads(), cv2.getNumThreads()))
        raise _Ran

    for mod, name in ((track_pipeline, "run_track"), (loop_pipeline, "run_loop"), (loop_pipeline, "demo_loop")):
        monkeypatch.setattr(mod, name, record)
    for var in THREAD_ENV:
        monkeypatch.delenv(var, raising=False)
    return seen


@pytest.fixture
def two_threads():
    """The process at 2 torch / 2 OpenCV threads (tests run on 1: conftest), restored after."""
    saved = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(2)
    cv2.setNumThreads(2)
    yield
    torch.set_num_threads(saved[0])
    cv2.setNumThreads(saved[1])


COMMANDS = {
    "track": ["track", str(CONFIG), "--euroc", str(SAMPLE)],
    "demo": ["demo"],
    "demo --loop": ["demo", "--loop"],
    "loop": ["loop", str(CONFIG), "--euroc", str(SAMPLE), "--poses", "poses.csv", "--train-vocabulary"],
}


def _run(argv, tmp_path):
    with pytest.raises(_Ran):
        main(argv + ["--out", str(tmp_path / "out"), "--no-progress"])


@pytest.mark.parametrize("command", list(COMMANDS))
def test_one_thread_by_default_and_restored(command, probe, two_threads, tmp_path):
    _run(COMMANDS[command], tmp_path)
    assert probe == [(1, 1)], probe
    assert (torch.get_num_threads(), cv2.getNumThreads()) == (2, 2)  # put back after the command


@pytest.mark.parametrize("command", list(COMMANDS))
def test_threads_option(command, probe, tmp_path):
    _run(COMMANDS[command] + ["--threads", "2"], tmp_path)
    assert probe == [(2, 2)], probe


def test_users_omp_num_threads_is_left_alone(probe, two_threads, tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    _run(COMMANDS["track"], tmp_path)
    _run(COMMANDS["track"] + ["--threads", "1"], tmp_path)  # the option still wins
    assert probe == [(2, 2), (1, 1)], probe


def test_bad_threads_value(capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        main(COMMANDS["track"] + ["--out", str(tmp_path / "o"), "--threads", "0"])
    assert e.value.code == 2
    assert "--threads: must be >= 1, got 0" in capsys.readouterr().err


def test_a_pipeline_error_restores_the_threads(two_threads, tmp_path, capsys, monkeypatch):
    for var in THREAD_ENV:
        monkeypatch.delenv(var, raising=False)
    assert main(["track", str(CONFIG), "--images", str(tmp_path / "missing"), "--out", str(tmp_path / "o"),
                 "--no-progress"]) != 0
    assert_one_error_line(capsys.readouterr().err, "missing")
    assert (torch.get_num_threads(), cv2.getNumThreads()) == (2, 2)


def test_the_library_leaves_the_threads_alone(two_threads):
    """FeatureTracker (construction and steps) does not change the process's threads."""
    from tests.conftest import load_gray

    tr = FeatureTracker(CONFIG)
    for f in sample_frames("cam0")[:2]:
        tr.track(torch.from_numpy(load_gray(f))[None, None], [int(f.stem) * 1e-9])
    assert (torch.get_num_threads(), cv2.getNumThreads()) == (2, 2)
