"""The ``torch-frontend`` CLI: ``--help``, ``track`` and ``demo`` end to end on the sample frames
(few frames), the outputs, and one clear stderr line + non-zero exit for each bad input."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from tests._helpers import (
    CONFIG,
    OUTPUTS,
    TOPIC,
    assert_one_error_line,
    crop,
    make_asl,
    run_cli,
    small_config,
    small_frames,
    truncate,
    write_bag,
)
from tests.conftest import SAMPLE, sample_frames
from torch_frontend.cli import default_config_path, main


def test_help_everywhere(capsys):
    for argv in ([], ["track"], ["demo"]):
        with pytest.raises(SystemExit) as e:
            main(argv + ["--help"])
        assert e.value.code == 0
        out = capsys.readouterr().out
        assert "usage: torch-frontend" in out
    assert main([]) == 2  # no command: help, usage exit code
    assert "track" in capsys.readouterr().out
    assert default_config_path().name == "euroc.yaml"


def test_track_end_to_end(tmp_path, capsys):
    out = tmp_path / "run"
    rc, stdout, err = run_cli(capsys, "track", CONFIG, "--euroc", SAMPLE, "--out", out, "--max-frames", 5,
                              "--no-progress")
    assert rc == 0, err
    assert "published frames" in stdout and "frames/s" in stdout
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 5 and s["streams"] == 1 and s["skipped_bad_frames"] == 0
    assert s["published"] >= 2 and s["frames_per_second"] > 0
    assert s["mean_track_length"] > 1 and s["median_track_length"] >= 1
    with open(out / "features.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["stream", "timestamp", "id", "x", "y", "u", "v", "vx", "vy", "track_count"]
    assert len(rows) == s["published_features"] > 0
    assert all(int(r["track_count"]) >= 2 for r in rows)  # VINS-Mono publishes track_cnt > 1 only
    stamps = {int(f.stem) for f in sample_frames("cam0")[:5]}
    assert {int(r["timestamp"].replace(".", "")) for r in rows} <= stamps  # exact ns in the csv
    npz = np.load(out / "features.npz")
    assert len(npz["id"]) == len(rows)
    np.testing.assert_allclose(npz["u"], [float(r["u"]) for r in rows], atol=1e-5)
    assert np.all((npz["u"] >= 0) & (npz["u"] < 752) & (npz["v"] >= 0) & (npz["v"] < 480))
    tracks = sorted((out / "tracks" / "stream0").glob("*.png"))
    assert len(tracks) == s["published"] == s["track_images"]
    img = cv2.imread(str(tracks[-1]))
    assert img.shape == (480, 752, 3)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporaries left
    plot = cv2.imread(str(out / "features_per_frame.png"))
    assert plot is not None and plot.shape[0] > 100


def test_track_two_streams_one_ends_early(tmp_path, capsys):
    """An ASL folder of 5 frames and an image folder of 3 (later) frames as B = 2 streams."""
    seq = make_asl(tmp_path / "a", n=5, small=True)
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for f in sample_frames("cam0")[5:8]:
        cv2.imwrite(str(imgs / f.name), crop(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)))
    out = tmp_path / "run"
    rc, stdout, err = run_cli(capsys, "track", small_config(tmp_path), "--euroc", seq, "--images", imgs,
                              "--out", out, "--no-progress")
    assert rc == 0, err
    s = json.loads((out / "summary.json").read_text())
    assert s["streams"] == 2 and s["steps"] == 5 and s["frames"] == 8
    assert [p["frames"] for p in s["per_stream"]] == [5, 3]
    assert [p["published"] for p in s["per_stream"]] == [2, 1]
    assert len(list((out / "tracks" / "stream1").glob("*.png"))) == 1
    with open(out / "features.csv") as fh:
        rows = list(csv.DictReader(fh))
    later = {int(f.stem) for f in sample_frames("cam0")[5:8]}
    # stream 1 publishes nothing after its end (its last frame is fed again but ignored)
    assert all(int(r["timestamp"].replace(".", "")) in later for r in rows if r["stream"] == "1")


def test_track_without_config_uses_sensor_yaml(tmp_path, capsys):
    seq = make_asl(tmp_path / "a", n=2, small=True)
    rc, stdout, err = run_cli(capsys, "track", "--euroc", seq, "--out", tmp_path / "o", "--no-tracks",
                              "--no-progress")
    assert rc == 0, err
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["config"].endswith("sensor.yaml") and s["frames"] == 2


def test_track_ros_bags(tmp_path, capsys):
    """A ROS 1 and a ROS 2 bag as two streams, default topic from the config."""
    frames = [(int(f.stem), crop(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))) for f in sample_frames("cam0")[:3]]
    b1 = write_bag(tmp_path / "a.bag", frames, version=1)
    b2 = write_bag(tmp_path / "b2", frames, version=2, compressed=True)
    rc, stdout, err = run_cli(capsys, "track", small_config(tmp_path), "--bag", b1, "--bag", b2,
                              "--out", tmp_path / "o", "--no-tracks", "--no-progress")
    assert rc == 0, err
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["streams"] == 2 and s["frames"] == 6


def test_demo(tmp_path, capsys):
    rc, stdout, err = run_cli(capsys, "demo", "--out", tmp_path / "demo", "--max-frames", 3, "--no-progress")
    assert rc == 0, err
    assert "max_cnt" in stdout and "published frames" in stdout  # config + run summary
    for name in OUTPUTS:
        assert (tmp_path / "demo" / name).is_file()


def test_skip_bad_frames(tmp_path, capsys):
    seq = make_asl(tmp_path / "a", n=4, small=True)
    cfg = small_config(tmp_path)
    bad = sorted((seq / "mav0" / "cam0" / "data").glob("*.png"))[2]
    truncate(bad)
    rc, _, err = run_cli(capsys, "track", cfg, "--euroc", seq, "--out", tmp_path / "o1", "--no-progress")
    assert rc == 1
    assert_one_error_line(err, str(bad), "truncated PNG", "--skip-bad-frames")  # the flag that goes on
    assert not (tmp_path / "o1").exists()  # the failed run left nothing behind, not even the folder it made
    rc, stdout, err = run_cli(capsys, "track", cfg, "--euroc", seq, "--out", tmp_path / "o2",
                              "--skip-bad-frames", "--no-tracks", "--no-progress")
    assert rc == 0, err
    s = json.loads((tmp_path / "o2" / "summary.json").read_text())
    assert s["frames"] == 3 and s["skipped_bad_frames"] == 1 and bad.name in s["skipped"][0]["source"]
    assert "1 bad frames" in stdout


def test_failed_run_removes_only_the_folders_it_made(tmp_path, capsys):
    """An error after ``--out``'s folders were made (an image of the wrong size) removes them
    while empty, the parents it made too, and never a folder the user made."""
    small = tmp_path / "small"
    small.mkdir()
    cv2.imwrite(str(small / "1403715273262142976.png"), np.zeros((40, 60), np.uint8))
    rc, _, err = run_cli(capsys, "track", CONFIG, "--images", small, "--out", tmp_path / "a" / "b" / "run",
                         "--no-progress")
    assert rc == 1 and "60x40" in err
    assert not (tmp_path / "a").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    rc, _, err = run_cli(capsys, "track", CONFIG, "--images", small, "--out", mine, "--no-progress")
    assert rc == 1 and mine.is_dir()


def test_no_tracks_summary_and_track_paths_colour_bar(tmp_path, capsys, monkeypatch):
    """``--no-tracks``: the summary does not list ``tracks/``; ``track_paths.png`` has a colour bar
    (one more axes per panel) for the track lengths."""
    from torch_frontend.outputs import RunRecorder

    figs = []
    save = RunRecorder._save_fig
    monkeypatch.setattr(RunRecorder, "_save_fig", lambda self, fig, d, name: figs.append((name, fig)) or
                        save(self, fig, d, name))
    seq = make_asl(tmp_path / "a", n=3, small=True)
    rc, stdout, err = run_cli(capsys, "track", small_config(tmp_path), "--euroc", seq, "--out", tmp_path / "o",
                              "--no-tracks", "--no-progress")
    assert rc == 0, err
    outputs = [ln for ln in stdout.splitlines() if ln.startswith("outputs")]
    assert len(outputs) == 1 and "track_paths.png" in outputs[0] and "tracks/" not in outputs[0]
    fig = dict(figs)["track_paths.png"]
    assert len(fig.axes) == 2 and "track length" in fig.axes[1].get_ylabel()


def _bad_inputs(tmp_path: Path):
    """(argv, exit code, needles) for each bad input of the command line."""
    cases = []
    cases.append((["--euroc", tmp_path / "nope"], 1, [str(tmp_path / "nope"), "folder not found"]))
    cases.append((["--images", tmp_path / "nope2", "--fps", "20"], 1, ["nope2", "folder not found"]))
    cases.append((["--bag", tmp_path / "nope.bag"], 1, ["nope.bag", "bag not found"]))
    seq = make_asl(tmp_path / "trunc", n=2)
    first = sorted((seq / "mav0" / "cam0" / "data").glob("*.png"))[0]
    truncate(first)
    cases.append((["--euroc", seq], 1, [str(first), "truncated PNG"]))
    small = tmp_path / "small"
    small.mkdir()
    cv2.imwrite(str(small / "1403715273262142976.png"), np.zeros((240, 320), np.uint8))
    cases.append((["--images", small], 1, ["1403715273262142976.png", "320x240", "752x480"]))
    bag = write_bag(tmp_path / "b.bag", small_frames(1))
    cases.append((["--bag", bag, "--topic", "/cam1/image_raw"], 1, ["b.bag", "/cam1/image_raw", TOPIC]))
    empty = tmp_path / "empty"
    empty.mkdir()
    cases.append((["--images", empty], 1, [str(empty), "empty sequence"]))
    cases.append((["--euroc", make_asl(tmp_path / "emptyasl", frames=[])], 1, ["data.csv", "empty sequence"]))
    return cases


def test_bad_inputs_one_line_and_exit_code(tmp_path, capsys):
    for i, (argv, code, needles) in enumerate(_bad_inputs(tmp_path)):
        out = tmp_path / f"out{i}"
        rc, _, err = run_cli(capsys, "track", CONFIG, *argv, "--out", out, "--no-progress")
        assert rc == code, (argv, err)
        assert_one_error_line(err, *needles)
        assert not out.exists(), argv  # the folder the run made is gone with it
    # config problems: exit 2, the file named
    rc, _, err = run_cli(capsys, "track", tmp_path / "missing.yaml", "--euroc", SAMPLE, "--out", tmp_path / "o")
    assert rc == 2
    assert_one_error_line(err, "missing.yaml", "file not found")
    rc, _, err = run_cli(capsys, "track", "--images", tmp_path, "--out", tmp_path / "o")
    assert rc == 2
    assert_one_error_line(err, "no CONFIG given")
    rc, _, err = run_cli(capsys, "track", CONFIG, "--out", tmp_path / "o")
    assert rc == 2
    assert_one_error_line(err, "no input")
    if not torch.cuda.is_available():
        rc, _, err = run_cli(capsys, "track", CONFIG, "--euroc", SAMPLE, "--out", tmp_path / "o", "--device", "cuda")
        assert rc == 2
        assert_one_error_line(err, "CUDA is not available")


def test_fusion_mode(tmp_path, capsys):
    """VINS-Fusion rules: every frame is published, every tracked feature is in features.csv."""
    seq = make_asl(tmp_path / "a", n=3, small=True)
    out = tmp_path / "o"
    rc, _, err = run_cli(capsys, "track", small_config(tmp_path), "--euroc", seq, "--out", out, "--mode", "fusion",
                         "--no-tracks", "--no-progress")
    assert rc == 0, err
    s = json.loads((out / "summary.json").read_text())
    assert s["mode"] == "fusion" and s["published"] == s["frames"] == 3 and s["published_features"] > 0


def test_bad_option_values(capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        main(["track", CONFIG, "--euroc", str(SAMPLE), "--out", str(tmp_path), "--fps", "-3"])
    assert e.value.code == 2 and "--fps: must be > 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["track", CONFIG, "--euroc", str(SAMPLE)])  # --out missing
    assert e.value.code == 2


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX entry point path")
def test_installed_entry_point_error(tmp_path):
    """The real console script: a user error gives exactly one stderr line, no library noise."""
    exe = Path(sys.executable).parent / "torch-frontend"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "torch_frontend.cli"]
    seq = make_asl(tmp_path / "a", n=1)
    truncate(next((seq / "mav0" / "cam0" / "data").glob("*.png")), keep=0.3)
    r = subprocess.run(cmd + ["track", CONFIG, "--euroc", str(seq), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert r.returncode == 1
    assert_one_error_line(r.stderr, "truncated PNG")


def test_interrupt_leaves_no_partial_output(tmp_path, capsys, monkeypatch):
    """Ctrl-C in the middle of a run: exit 130, one line, no file (final or temporary) in --out."""
    from torch_frontend.tracker import FeatureTracker

    calls = []
    real_track = FeatureTracker.track

    def track(self, images, timestamps, right=None, active=None):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_track(self, images, timestamps, right, active)

    monkeypatch.setattr(FeatureTracker, "track", track)
    seq = make_asl(tmp_path / "a", n=3, small=True)
    out = tmp_path / "o"
    rc, _, err = run_cli(capsys, "track", small_config(tmp_path), "--euroc", seq, "--out", out, "--no-progress")
    assert rc == 130
    assert_one_error_line(err, "interrupted")
    assert not out.exists()  # nor the folder the run made


def test_out_is_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    seq = make_asl(tmp_path / "a", n=1, small=True)
    rc, _, err = run_cli(capsys, "track", small_config(tmp_path), "--euroc", seq, "--out", f, "--no-progress")
    assert rc == 1
    assert_one_error_line(err, str(f), "is a file, not a folder")
    assert "File exists" not in err
    assert f.read_text() == "x"


def test_track_prints_its_settings_and_config_typos(tmp_path, capsys):
    """``track`` prints one line of the settings it runs with; a config typo is one warning line
    naming the key, the file and the key it is close to; a key given twice is an error naming both lines."""
    cfg = small_config(tmp_path)
    cfg.write_text(cfg.read_text() + "equalise: 0\n")
    seq = make_asl(tmp_path / "a", n=2, small=True)
    rc, stdout, err = run_cli(capsys, "track", cfg, "--euroc", seq, "--out", tmp_path / "o", "--no-tracks",
                              "--no-progress")
    assert rc == 0, err
    settings = [ln for ln in stdout.splitlines() if ln.startswith("config ")]
    assert len(settings) == 1, stdout
    for part in ("PINHOLE 256x192", "max_cnt 60", "min_dist 30", "freq 10 Hz", "equalize 1", "F_threshold 1",
                 "fisheye 0"):
        assert part in settings[0], settings[0]
    warn = [ln for ln in err.splitlines() if ln.strip()]
    assert warn == [f"torch-frontend: warning: unknown key `equalise` in {cfg}: did you mean `equalize`? "
                    f"(the key is ignored)"], err
    cfg.write_text(cfg.read_text() + "max_cnt: 19\n")
    rc, _, err = run_cli(capsys, "track", cfg, "--euroc", seq, "--out", tmp_path / "o2", "--no-progress")
    assert rc == 2
    assert_one_error_line(err, str(cfg), "max_cnt", "given twice, on line")


def test_fps_folder_colour_frames_and_published_tracks(tmp_path, capsys):
    """An ``--fps`` folder of colour frames: one note that they are made grey, track images whose
    names sort in time order (zero-padded nanoseconds), and track statistics of published
    features only (the tracks of ``features.csv``)."""
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for i, f in enumerate(sample_frames("cam0")):  # 24 frames at 20 Hz: every other one published (freq 10)
        g = crop(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
        assert cv2.imwrite(str(imgs / f"frame_{chr(97 + i)}.png"), cv2.merge([g, g, g]))  # names: not times (a..x)
    out = tmp_path / "o"
    rc, _, err = run_cli(capsys, "track", small_config(tmp_path), "--images", imgs, "--fps", 20, "--out", out,
                         "--no-progress")
    assert rc == 0, err
    notes = [ln for ln in err.splitlines() if ln.strip()]
    assert len(notes) == 1 and notes[0].startswith("torch-frontend: note: images imgs: colour frames"), err
    assert "converted to grey" in notes[0]
    names = sorted(p.name for p in (out / "tracks" / "stream0").glob("*.png"))
    stamps = [int(n[:-4]) for n in names]
    assert len(stamps) >= 4 and max(stamps) >= 1_000_000_000 and stamps == sorted(stamps), names  # 0.1 s apart
    s = json.loads((out / "summary.json").read_text())
    with open(out / "features.csv") as fh:
        rows = list(csv.DictReader(fh))
    longest = {}
    for r in rows:
        longest[r["id"]] = max(longest.get(r["id"], 0), int(r["track_count"]))
    assert s["tracks"] == len(longest) > 0
    assert s["median_track_length"] == float(np.median(list(longest.values())))
    assert s["mean_track_length"] == pytest.approx(float(np.mean(list(longest.values()))))


def test_demo_flight_tracks_move(tmp_path, capsys):
    """``demo --flight``: the synthetic flight over the package photo; its published tracks move
    across the image (the sample EuRoC demo's camera stands still), drawn in track_paths.png."""
    out = tmp_path / "flight"
    rc, stdout, err = run_cli(capsys, "demo", "--flight", "--out", out, "--max-frames", 12, "--no-tracks",
                              "--no-progress")
    assert rc == 0, err
    assert "synthetic flight" in stdout and "published frames" in stdout
    assert cv2.imread(str(out / "track_paths.png")) is not None
    npz = np.load(out / "features.npz")
    moved = []
    for i in np.unique(npz["id"]):
        m = npz["id"] == i
        if m.sum() >= 3:
            u, v = npz["u"][m][np.argsort(npz["stamp_ns"][m])], npz["v"][m][np.argsort(npz["stamp_ns"][m])]
            moved.append(float(np.hypot(u[-1] - u[0], v[-1] - v[0])))
    assert len(moved) >= 50 and np.median(moved) > 10.0, (len(moved), np.median(moved))  # ~2.5 px/frame
    rc, _, err = run_cli(capsys, "demo", "--flight", "--loop", "--out", tmp_path / "x", "--no-progress")
    assert rc == 2
    assert_one_error_line(err, "--loop and --flight")
