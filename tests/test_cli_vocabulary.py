"""``torch-frontend vocabulary train``: train on a few sample frames, load back, and one clear
stderr line + non-zero exit for each bad input."""

from __future__ import annotations

import shutil

import pytest
import torch

from tests._helpers import assert_one_error_line, run_cli
from tests.conftest import load_gray, sample_frames
from torch_frontend.cli import main
from torch_frontend.loop import Vocabulary, brief, fast


@pytest.fixture
def few_frames(tmp_path):
    """A folder with 4 sample frames (every 6th: some variety)."""
    d = tmp_path / "imgs"
    d.mkdir()
    for f in sample_frames("cam0")[::6][:4]:
        shutil.copy(f, d / f.name)
    return d


def test_train_npz_and_load_back(tmp_path, capsys, few_frames):
    out = tmp_path / "voc.npz"
    rc, stdout, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", out, "--k", 4, "--L", 2,
                              "--max-keypoints", 200, "--seed", 1, "--no-progress")
    assert rc == 0, err
    lines = stdout.strip().splitlines()
    assert len(lines) == 1 and "words (k=4, L=2)" in lines[0] and "of 4 images" in lines[0]
    assert "800 descriptors" in lines[0]  # 4 images x 200 strongest corners
    voc = Vocabulary.load(out)
    assert voc.k == 4 and voc.L == 2 and 4 < voc.num_words <= 16
    assert f"{voc.num_words} words" in lines[0]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left
    # a training image's descriptors spread over several words (IDF weights ln(4 / N_i) may all
    # be 0 here: with 16 words every word can occur in all 4 images)
    img = torch.from_numpy(load_gray(sorted(few_frames.iterdir())[0]))[None]
    pts, _, valid = fast(img, 20, max_points=200)
    words, weights = voc.transform_words(brief(img, pts, valid), valid)
    assert ((words >= 0) & (words < voc.num_words))[valid].all() and words[valid].unique().numel() > 4
    assert (weights >= 0).all() and torch.isfinite(weights).all()
    # files and folders mix (the folder repeats two files: 6 images, 4 evenly spaced kept)
    out2 = tmp_path / "voc2.npz"
    files = sorted(few_frames.iterdir())
    rc, _, err = run_cli(capsys, "vocabulary", "train", *files[:2], files[2].parent, "--out", out2, "--k", 4,
                         "--L", 2, "--max-keypoints", 200, "--max-images", 4, "--seed", 1, "--no-progress")
    assert rc == 0, err
    assert Vocabulary.load(out2).num_words > 4


def test_train_vins_bin_and_max_images(tmp_path, capsys, few_frames):
    out = tmp_path / "voc.bin"
    rc, stdout, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", out, "--k", 3, "--L", 2,
                              "--max-images", 2, "--max-keypoints", 100, "--fast-threshold", 30, "--no-progress")
    assert rc == 0, err
    assert "200 descriptors of 2 images" in stdout
    voc = Vocabulary.load_vins_bin(out)
    assert voc.k == 3 and voc.L == 2 and 3 <= voc.num_words <= 9
    hdr = torch.frombuffer(bytearray(out.read_bytes()[:24]), dtype=torch.int32).tolist()
    assert hdr[:2] == [3, 2] and hdr[5] == voc.num_words


def test_seed_reproducible(tmp_path, capsys, few_frames):
    outs = []
    for i in range(2):
        out = tmp_path / f"v{i}.npz"
        rc, _, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", out, "--k", 3, "--L", 2,
                             "--max-keypoints", 100, "--seed", 7, "--no-progress")
        assert rc == 0, err
        outs.append(Vocabulary.load(out))
    assert torch.equal(outs[0].node_desc, outs[1].node_desc)


def test_errors(tmp_path, capsys, few_frames):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no images here")
    out = tmp_path / "v.npz"
    rc, _, err = run_cli(capsys, "vocabulary", "train", empty, "--out", out)
    assert rc == 1
    assert_one_error_line(err, str(empty), "no images in folder")
    rc, _, err = run_cli(capsys, "vocabulary", "train", tmp_path / "missing", "--out", out)
    assert rc == 1
    assert_one_error_line(err, str(tmp_path / "missing"), "no such image file or folder")
    bad = tmp_path / "bad"
    bad.mkdir()
    shutil.copy(sorted(few_frames.iterdir())[0], bad / "a.png")
    (bad / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 10)
    rc, _, err = run_cli(capsys, "vocabulary", "train", bad, "--out", out, "--no-progress")
    assert rc == 1
    assert_one_error_line(err, str(bad / "b.png"))
    rc, _, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", tmp_path / "nodir" / "v.npz")
    assert rc == 2
    assert_one_error_line(err, "--out", str(tmp_path / "nodir"), "does not exist")
    rc, _, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", tmp_path)
    assert rc == 2
    assert_one_error_line(err, "is a folder")
    rc, _, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", out, "--k", 1)
    assert rc == 2
    assert_one_error_line(err, "--k must be >= 2, got 1")
    rc, _, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", out, "--L", 0)
    assert rc == 2
    assert_one_error_line(err, "--L must be >= 1, got 0")
    rc, _, err = run_cli(capsys, "vocabulary", "train", few_frames, "--out", out, "--fast-threshold", 255,
                         "--no-progress")
    assert rc == 1
    assert_one_error_line(err, "no FAST corners")
    rc, _, err = run_cli(capsys, "vocabulary")
    assert rc == 2
    assert_one_error_line(err, "train")
    assert not out.exists()  # nothing written by a failed run
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_help(capsys):
    for argv in (["vocabulary", "--help"], ["vocabulary", "train", "--help"]):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 0
        out = capsys.readouterr().out
        assert "usage: torch-frontend vocabulary" in out
    assert "--max-keypoints" in out and "--fast-threshold" in out
