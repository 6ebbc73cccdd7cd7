"""``torch_frontend.pipelines`` as a library: options are checked with their own names (never a CLI
flag), the CLI puts its flag in their place, and the shared helpers (ragged-to-padded, progress bar,
config resolution) do what they say. The pipelines end to end are in ``test_cli*.py`` and
``test_loop_run.py``."""

from __future__ import annotations

import ast
import re

import pytest
import torch

from tests._helpers import CONFIG, assert_one_error_line, run_cli
from tests.conftest import REPO
from torch_frontend.errors import ConfigError
from torch_frontend.pipelines import (
    LoopOptions,
    OptionError,
    TrackOptions,
    VocabularyOptions,
    demo_loop,
    demo_options,
    pad_ragged,
    progress_bar,
    resolve_config,
    run_loop,
    run_track,
    run_vocabulary_train,
)

FLAG = re.compile(r"--[a-z]")


def _raised_strings(tree: ast.AST):
    """Every string literal (or f-string part) inside a ``raise`` statement."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Raise):
            for sub in ast.walk(node):
                if isinstance(sub, ast.Constant) and isinstance(sub.value, str):
                    yield sub.lineno, sub.value


def test_no_cli_flag_in_library_errors():
    bad = []
    for path in sorted((REPO / "torch_frontend" / "pipelines").glob("*.py")):
        for line, text in _raised_strings(ast.parse(path.read_text(encoding="utf-8"))):
            if FLAG.search(text):
                bad.append(f"{path.name}:{line}: {text!r}")
    assert not bad, "CLI flags in library errors:\n" + "\n".join(bad)


@pytest.mark.parametrize("options, option", [
    (TrackOptions(max_frames=0), "max_frames"),
    (TrackOptions(mode="stereo"), "mode"),
    (TrackOptions(fps=-1.0), "fps"),
    (LoopOptions(), "vocabulary"),
    (LoopOptions(train_vocabulary=True, vocabulary="voc.bin"), "vocabulary"),
    (LoopOptions(train_vocabulary=True, mode="3dof"), "mode"),
    (LoopOptions(train_vocabulary=True, tracker_mode="x"), "tracker_mode"),
    (LoopOptions(train_vocabulary=True, keyframe_distance=-0.1), "keyframe_distance"),
    (LoopOptions(train_vocabulary=True, keyframe_every=0), "keyframe_every"),
    (LoopOptions(train_vocabulary=True, max_pose_gap=0.0), "max_pose_gap"),
    (VocabularyOptions(k=1), "k"),
    (VocabularyOptions(L=0), "L"),
])
def test_options_name_the_bad_option(options, option):
    with pytest.raises(OptionError) as e:
        options.check()
    assert e.value.option == option
    assert str(e.value).startswith(option) and not FLAG.search(str(e.value))
    assert isinstance(e.value, ValueError)


def test_pipelines_check_before_reading(tmp_path):
    """Bad options and argument counts fail before any input is opened (the paths do not exist)."""
    with pytest.raises(OptionError, match="^sources"):
        run_track(None, [], tmp_path / "o")
    with pytest.raises(OptionError, match="^mode"):
        run_track(None, [("euroc", tmp_path / "nope")], tmp_path / "o", TrackOptions(mode="bad"))
    with pytest.raises(OptionError, match="^device"):
        run_track(None, [("euroc", tmp_path / "nope")], tmp_path / "o", TrackOptions(device="abacus"))
    with pytest.raises(OptionError, match="^poses: expected one poses file per input"):
        run_loop(None, [("images", tmp_path)], [], None, LoopOptions(train_vocabulary=True))
    with pytest.raises(OptionError, match="^k must be >= 2, got 1"):
        run_vocabulary_train([tmp_path], tmp_path / "v.npz", VocabularyOptions(k=1))
    with pytest.raises(OptionError, match="^out .*is a folder"):
        run_vocabulary_train([tmp_path], tmp_path, VocabularyOptions())
    with pytest.raises(OptionError, match="^device"):  # before the (slow) render
        demo_loop(None, demo_options(device="abacus"))
    assert not (tmp_path / "o").exists()


def test_cli_names_the_flag_of_a_bad_option(tmp_path, capsys):
    rc, _, err = run_cli(capsys, "loop", CONFIG, "--images", tmp_path, "--poses", tmp_path / "p.tum",
                         "--train-vocabulary", "--out", tmp_path / "o", "--keyframe-distance", -1, "--no-progress")
    assert rc == 2
    assert_one_error_line(err, "--keyframe-distance: expected >= 0, got -1")
    rc, _, err = run_cli(capsys, "track", CONFIG, "--euroc", tmp_path, "--out", tmp_path / "o", "--device", "abacus")
    assert rc == 2
    assert_one_error_line(err, "--device: expected cpu or cuda, got 'abacus'")


def test_resolve_config(tmp_path):
    cfg = resolve_config(CONFIG)
    assert cfg.camera is not None and cfg.image_width == 752
    assert resolve_config(cfg) is cfg
    with pytest.raises(ConfigError, match="no config given"):
        resolve_config(None, [("images", tmp_path)])


@pytest.mark.parametrize("dtype", [torch.float32, torch.int64])
def test_pad_ragged(dtype):
    items = [torch.arange(6, dtype=dtype).reshape(3, 2), torch.zeros(0, 2, dtype=dtype),
             torch.ones(1, 2, dtype=dtype)]
    x, valid = pad_ragged(items)
    assert x.shape == (3, 3, 2) and x.dtype == dtype and valid.dtype == torch.bool
    assert valid.tolist() == [[True] * 3, [False] * 3, [True, False, False]]
    assert torch.equal(x[0], items[0]) and torch.equal(x[2, 0], items[2][0])
    assert not x[1].any() and not x[2, 1:].any()  # zero padding
    x, valid = pad_ragged([torch.zeros(0, 4, dtype=dtype)], min_length=1)
    assert x.shape == (1, 1, 4) and not valid.any()
    with pytest.raises(ValueError):
        pad_ragged([])


def test_progress_bar():
    with progress_bar(False, 10, "x", "frame") as bar:
        assert bar is None
    with progress_bar(True, 10, "x", "frame") as bar:
        assert bar is not None and not bar.disable
        bar.update(3)
        assert bar.n == 3
    assert bar.disable  # closed on leaving the block
