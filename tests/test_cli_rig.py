"""Rigs and mixed inputs on the command line: each input its own config.

* two EuRoC-style inputs with different ``sensor.yaml`` (intrinsics; image size) and no CONFIG each
  get their own camera: ``summary.json`` names each stream's config and camera, and stream b's
  features are those of a run of input b alone (on a build that gave every input the first
  input's ``sensor.yaml`` stream 1's ``xy`` differ);
* ``--euroc A --config a.yaml --euroc B --config b.yaml``, CONFIG for the inputs without their own,
  a ``--config`` before the first input (CONFIG), ``--rig rig.yaml``: the same per-stream results;
* the usage and rig-file errors: one stderr line naming the flag, or the rig file, entry and key;
* ``loop`` keeps each input's config (separate graphs: stream b = its run alone), and refuses a
  shared map of two different extrinsics.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests._helpers import assert_one_error_line, make_asl, run_cli, small_config
from tests.conftest import load_gray

#: stream b of a run vs the run of its input alone: these columns of features.npz are equal
COLUMNS = ("stamp_ns", "id", "x", "y", "u", "v", "vx", "vy", "track_count")
FRAMES = 5
#: the third input's frames: a (H, W) = (128, 160) crop at (row, col) (32, 48) of the small frames
SUB = (128, 160, 32, 48)


def _scale_focal(asl: Path, factor: float) -> None:
    y = asl / "mav0" / "cam0" / "sensor.yaml"
    text = y.read_text()
    assert "458.654, 457.296" in text
    y.write_text(text.replace("458.654, 457.296", f"{458.654 * factor:.3f}, {457.296 * factor:.3f}"))


def _recrop(asl: Path) -> None:
    """Re-save the frames of a small ASL folder as their ``SUB`` crop, with a matching sensor.yaml."""
    h, w, r0, c0 = SUB
    cam = asl / "mav0" / "cam0"
    for f in (cam / "data").glob("*.png"):
        assert cv2.imwrite(str(f), np.ascontiguousarray(load_gray(f)[r0:r0 + h, c0:c0 + w]))
    y = cam / "sensor.yaml"
    text = y.read_text()
    res = next(ln for ln in text.splitlines() if ln.startswith("resolution:"))
    intr = next(ln for ln in text.splitlines() if ln.startswith("intrinsics:"))
    fu, fv, cu, cv = (float(v) for v in intr.split("[")[1].split("]")[0].split(","))
    text = text.replace(res, f"resolution: [{w}, {h}]").replace(
        intr, f"intrinsics: [{fu}, {fv}, {cu - c0}, {cv - r0}]")
    y.write_text(text)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """Three small ASL folders: A (the sample's crop), B (A's frames, focal lengths x 1.2 in its
    sensor.yaml), C (another size: 160 x 128); two VINS configs a.yaml, b.yaml (b: another focal
    length and max_cnt)."""
    root = tmp_path_factory.mktemp("rig")
    a = make_asl(root / "A", n=FRAMES, small=True)
    b = make_asl(root / "B", n=FRAMES, small=True)
    _scale_focal(b, 1.2)
    c = make_asl(root / "C", n=FRAMES, small=True)
    _recrop(c)
    cfg_a = small_config(root, max_cnt=60)
    cfg_a = cfg_a.rename(root / "a.yaml")
    text = cfg_a.read_text()
    assert "fx: 4.616e+02" in text and "max_cnt: 60" in text
    (root / "b.yaml").write_text(text.replace("fx: 4.616e+02", "fx: 5.5e+02").replace("max_cnt: 60", "max_cnt: 40"))
    return {"root": root, "A": a, "B": b, "C": c, "a": cfg_a, "b": root / "b.yaml"}


def _track(capsys, out, *argv):
    rc, stdout, err = run_cli(capsys, "track", *argv, "--out", out, "--max-frames", FRAMES, "--no-tracks",
                              "--no-progress")
    assert rc == 0, err
    return json.loads((out / "summary.json").read_text()), stdout


def _features(out: Path, stream: int | None = None):
    npz = np.load(out / "features.npz")
    keep = np.ones(len(npz["id"]), dtype=bool) if stream is None else npz["stream"] == stream
    return {k: npz[k][keep] for k in COLUMNS}


def assert_stream_is_alone_run(batch_out: Path, b: int, alone_out: Path) -> None:
    got, ref = _features(batch_out, b), _features(alone_out)
    assert len(ref["id"]) > 0
    for k in COLUMNS:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


def test_each_euroc_input_its_own_sensor_yaml(rig, tmp_path, capsys):
    """The acceptance run: no CONFIG, two inputs whose sensor.yaml differ in the intrinsics."""
    s, stdout = _track(capsys, tmp_path / "ab", "--euroc", rig["A"], "--euroc", rig["B"])
    ys = [str(rig[k] / "mav0" / "cam0" / "sensor.yaml") for k in "AB"]
    assert [e["config"] for e in s["per_stream"]] == ys
    assert [e["camera"]["model"] for e in s["per_stream"]] == ["PINHOLE", "PINHOLE"]
    assert all((e["camera"]["width"], e["camera"]["height"]) == (256, 192) for e in s["per_stream"])
    assert s["config"] == "; ".join(ys)
    settings = [ln for ln in stdout.splitlines() if ln.startswith("config ")]  # one line per config
    assert len(settings) == 2 and settings[0].endswith("(stream 0)") and settings[1].endswith("(stream 1)")
    for b, k in enumerate("AB"):
        _track(capsys, tmp_path / k, "--euroc", rig[k])
        assert_stream_is_alone_run(tmp_path / "ab", b, tmp_path / k)
    # B's own camera matters: B tracked with A's sensor.yaml gives other normalised points
    _track(capsys, tmp_path / "b_with_a", ys[0], "--euroc", rig["B"])
    other = _features(tmp_path / "b_with_a")
    assert not np.array_equal(other["x"], _features(tmp_path / "ab", 1)["x"])


def test_mixed_image_sizes_in_one_batch(rig, tmp_path, capsys):
    """A 256 x 192 and a 160 x 128 input (each its own sensor.yaml): one padded batch, each
    stream its own size; ``--workers 1`` decodes them in a worker."""
    s, _ = _track(capsys, tmp_path / "ac", "--euroc", rig["A"], "--euroc", rig["C"], "--workers", 1)
    assert [(e["camera"]["width"], e["camera"]["height"]) for e in s["per_stream"]] == [(256, 192), (160, 128)]
    for b, k in enumerate("AC"):
        _track(capsys, tmp_path / k, "--euroc", rig[k])
        assert_stream_is_alone_run(tmp_path / "ac", b, tmp_path / k)
    uv = _features(tmp_path / "ac", 1)
    assert uv["u"].max() < 160 and uv["v"].max() < 128


def test_config_after_each_input(rig, tmp_path, capsys):
    """``--euroc A --config a.yaml --euroc A --config b.yaml``; CONFIG for the one without."""
    s, _ = _track(capsys, tmp_path / "ab", "--euroc", rig["A"], "--config", rig["a"], "--euroc", rig["A"],
                  "--config", rig["b"])
    assert [e["config"] for e in s["per_stream"]] == [str(rig["a"]), str(rig["b"])]
    for b, k in enumerate("ab"):
        _track(capsys, tmp_path / k, rig[k], "--euroc", rig["A"])
        assert_stream_is_alone_run(tmp_path / "ab", b, tmp_path / k)
    assert len(_features(tmp_path / "ab", 1)["id"]) != len(_features(tmp_path / "ab", 0)["id"])
    # CONFIG (positional) for the input without its own --config
    s, _ = _track(capsys, tmp_path / "mixed", rig["a"], "--euroc", rig["A"], "--euroc", rig["A"], "--config", rig["b"])
    assert [e["config"] for e in s["per_stream"]] == [str(rig["a"]), str(rig["b"])]
    for b, k in enumerate("ab"):
        assert_stream_is_alone_run(tmp_path / "mixed", b, tmp_path / k)
    # a --config before the first input is CONFIG: every input's
    s, stdout = _track(capsys, tmp_path / "lead", "--config", rig["b"], "--euroc", rig["A"], "--euroc", rig["A"])
    assert [e["config"] for e in s["per_stream"]] == [str(rig["b"])] * 2 and s["config"] == str(rig["b"])
    assert len([ln for ln in stdout.splitlines() if ln.startswith("config ")]) == 1


def test_rig_file(rig, tmp_path, capsys):
    """``--rig``: relative paths, a config and a camera folder per entry, an entry without config
    (its sensor.yaml), combined with a command-line input after it."""
    r = rig["root"]
    (r / "rig.yaml").write_text("# two streams of A and one of B\n"
                                "- {euroc: A, config: a.yaml, camera: cam0}\n"
                                "- euroc: A\n  config: b.yaml\n"
                                "- {euroc: B}\n")
    s, _ = _track(capsys, tmp_path / "rig", "--rig", r / "rig.yaml", "--euroc", rig["C"])
    assert [e["config"] for e in s["per_stream"]] == [str(r / "a.yaml"), str(r / "b.yaml"),
                                                      str(r / "B" / "mav0" / "cam0" / "sensor.yaml"),
                                                      str(rig["C"] / "mav0" / "cam0" / "sensor.yaml")]
    assert s["inputs"][0]["camera"] == "cam0" and s["inputs"][0]["path"] == str(r / "A")
    _track(capsys, tmp_path / "a", rig["a"], "--euroc", rig["A"])
    _track(capsys, tmp_path / "b", rig["b"], "--euroc", rig["A"])
    _track(capsys, tmp_path / "B", "--euroc", rig["B"])
    for b, alone in enumerate(("a", "b", "B")):
        assert_stream_is_alone_run(tmp_path / "rig", b, tmp_path / alone)


@pytest.mark.parametrize("text, needles", [
    ("- {euroc: A, cofnig: a.yaml}\n", ("rig.yaml", "[0].cofnig", "unknown key", "did you mean 'config'")),
    ("- {euroc: A}\n- {euroc: missing}\n", ("rig.yaml", "[1].euroc", "input not found", "missing")),
    ("- {euroc: A, config: nope.yaml}\n", ("rig.yaml", "[0].config", "config file not found", "nope.yaml")),
    ("- {euroc: A, images: A}\n", ("rig.yaml", "[0]", "exactly one input kind", "euroc, images")),
    ("- {config: a.yaml}\n", ("rig.yaml", "[0]", "exactly one input kind", "none")),
    ("euroc: A\n", ("rig.yaml", "expected a list of inputs", "dict")),
    ("- {images: A, camera: cam1, config: a.yaml}\n", ("rig.yaml", "[0].camera", "goes with euroc inputs")),
    ("- {euroc: A\n", ("rig.yaml", "not valid YAML")),
])
def test_rig_file_errors(rig, tmp_path, capsys, text, needles):
    p = rig["root"] / "rig.yaml"
    p.write_text(text)
    rc, _, err = run_cli(capsys, "track", "--rig", p, "--out", tmp_path / "o", "--no-progress")
    assert rc == 2, err
    assert_one_error_line(err, *needles)
    assert not (tmp_path / "o").exists()


def test_usage_errors(rig, tmp_path, capsys):
    out = tmp_path / "o"
    cases = [
        (("--rig", tmp_path / "none.yaml"), ("none.yaml", "rig file not found")),
        (("--euroc", rig["A"], "--config", rig["a"], "--config", rig["b"]),
         ("--config", "input 1", "already has --config", "a.yaml")),
        (("--config", rig["a"], "--euroc", rig["A"], "--euroc", rig["B"], "--config", rig["b"]),
         ("before the first input", "applies to the input just before it", "input 2")),
        ((rig["a"], "--config", rig["b"], "--euroc", rig["A"]), ("given twice", "a.yaml", "b.yaml")),
        (("--images", rig["A"] / "mav0" / "cam0" / "data", "--euroc", rig["A"]),
         ("no CONFIG given for input 1", "--images", "--config FILE after this input")),
        (("--euroc", rig["A"], "--config", tmp_path / "missing.yaml"), ("missing.yaml", "file not found")),
    ]
    rigfile = rig["root"] / "rig_ok.yaml"
    rigfile.write_text("- {euroc: A}\n")
    cases.append((("--rig", rigfile, "--config", rig["a"]), ("after --rig", "rig_ok.yaml", "'config:' key")))
    for argv, needles in cases:
        rc, _, err = run_cli(capsys, "track", *argv, "--out", out, "--no-progress")
        assert rc == 2, (argv, err)
        assert_one_error_line(err, *needles)
        assert not out.exists(), argv


def test_track_help_documents_config_and_rig(capsys):
    from torch_frontend.cli import main

    for cmd in ("track", "loop"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "--rig FILE" in text and "the input just before it" in text and "Before the first input" in text


# ---------------------------------------------------------------------------------------- loop


def _loop_config(seq, max_cnt: int, t_shift: float = 0.0) -> str:
    cam = seq.camera
    t_ic = seq.t_ic.clone()
    t_ic[0] += t_shift
    return ("%YAML:1.0\nmodel_type: PINHOLE\ncamera_name: synthetic\n"
            f"image_width: {seq.images.shape[2]}\nimage_height: {seq.images.shape[1]}\n"
            "distortion_parameters:\n   k1: 0.0\n   k2: 0.0\n   p1: 0.0\n   p2: 0.0\n"
            f"projection_parameters:\n   fx: {float(cam.fx)}\n   fy: {float(cam.fy)}\n   cx: {float(cam.cx)}\n"
            f"   cy: {float(cam.cy)}\n"
            "extrinsicRotation: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
            f"   data: [{', '.join(str(float(v)) for v in seq.R_ic.reshape(-1).tolist())}]\n"
            "extrinsicTranslation: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n"
            f"   data: [{', '.join(str(float(v)) for v in t_ic.tolist())}]\n"
            f"max_cnt: {max_cnt}\nmin_dist: 10\nfreq: 100\nF_threshold: 1.0\nequalize: 0\nfisheye: 0\n")


@pytest.fixture(scope="module")
def loop_rig(tmp_path_factory):
    """A short render (one lap of 8 keyframes, 160 x 120) as an image folder with its VIO poses,
    three configs of its camera (max_cnt 100; max_cnt 50; max_cnt 100 with another extrinsic) and
    a vocabulary."""
    import torch

    from torch_frontend.geometry import R_to_quat
    from torch_frontend.loop.vocabulary import Vocabulary
    from torch_frontend.pipelines import loop as loop_run
    from torch_frontend.trajectory import Trajectory, write_vins_csv

    root = tmp_path_factory.mktemp("loop_rig")
    seq = loop_run.demo_sequence(laps=1, keyframes_per_lap=8, width=160, height=120)
    d = root / "images"
    d.mkdir()
    for t, im in zip(seq.times.tolist(), seq.images.numpy()):
        assert cv2.imwrite(str(d / f"{t:.6f}.png"), im)
    write_vins_csv(root / "vio.csv", Trajectory(seq.times.double(), seq.T_vio.double(), R_to_quat(seq.R_vio.double())))
    for name, kw in (("a", dict(max_cnt=100)), ("b", dict(max_cnt=50)), ("c", dict(max_cnt=100, t_shift=0.05))):
        (root / f"{name}.yaml").write_text(_loop_config(seq, **kw))
    g = torch.Generator().manual_seed(0)
    desc = torch.randint(-(2**62), 2**62, (4, 50, 4), generator=g, dtype=torch.int64)
    Vocabulary.train(desc, k=4, L=2, generator=g).save(root / "voc.npz")
    return root


def _loop(capsys, root: Path, out: Path, *inputs):
    return run_cli(capsys, "loop", *inputs, "--vocabulary", root / "voc.npz", "--keyframe-every", 2,
                   "--out", out, "--no-progress")


@pytest.mark.slow  # covered by the sharded track's per-input configs (test_distributed.py) (make test-all and CI run it)
def test_loop_keeps_each_inputs_config(loop_rig, tmp_path, capsys):
    r = loop_rig
    one = ("--images", r / "images", "--poses", r / "vio.csv")
    rc, _, err = _loop(capsys, r, tmp_path / "ab", *one, "--config", r / "a.yaml", *one, "--config", r / "b.yaml",
                       "--separate-graphs")
    assert rc == 0, err
    s = json.loads((tmp_path / "ab" / "summary.json").read_text())
    assert [e["config"] for e in s["per_stream"]] == [str(r / "a.yaml"), str(r / "b.yaml")]
    assert s["per_stream"][0]["camera"] == {"model": "PINHOLE", "name": "synthetic", "width": 160, "height": 120}
    keys = ("frames", "published", "keyframes", "mean_points", "loops_accepted", "config", "camera", "extrinsic")
    for b, name in enumerate("ab"):
        rc, _, err = _loop(capsys, r, tmp_path / name, r / f"{name}.yaml", *one)
        assert rc == 0, err
        alone = json.loads((tmp_path / name / "summary.json").read_text())["per_stream"][0]
        assert {k: s["per_stream"][b][k] for k in keys} == {k: alone[k] for k in keys}, name
        assert (tmp_path / "ab" / f"stream{b}" / "trajectory_loop.tum").read_bytes() == \
            (tmp_path / name / "trajectory_loop.tum").read_bytes()
    assert s["per_stream"][0]["mean_points"] != s["per_stream"][1]["mean_points"]  # max_cnt 100 vs 50
    # a shared map has one extrinsic: two different ones are refused before tracking
    rc, _, err = _loop(capsys, r, tmp_path / "ac", *one, "--config", r / "a.yaml", *one, "--config", r / "c.yaml")
    assert rc == 2
    assert_one_error_line(err, "a.yaml", "c.yaml", "different camera-to-body extrinsics", "--separate-graphs")
    assert not (tmp_path / "ac").exists()


def test_each_stream_checked_against_its_own_size(rig, tmp_path, capsys):
    """The 160 x 128 input twice, with its own sensor.yaml and with a 256 x 192 config: the error
    names the frame, its stream and that stream's expected size (exit 1, nothing written)."""
    out = tmp_path / "o"
    rc, _, err = run_cli(capsys, "track", "--euroc", rig["C"], "--euroc", rig["C"], "--config", rig["a"],
                         "--out", out, "--no-progress", "--no-tracks")
    assert rc == 1, err
    assert_one_error_line(err, "image size 160x128 differs from the expected 256x192 of stream 1")
    assert not out.exists() or not any(out.iterdir())


def test_stack_images_pads_mixed_sizes():
    """``io.multistream.stack_images``: one size stacks (sizes None); several pad at the bottom
    and right with zeros, into a given (pinned-like) buffer too, and give each (H_b, W_b)."""
    from torch_frontend.io.multistream import padded_shape, stack_images

    a = np.full((4, 6), 7, np.uint8)
    b = np.full((5, 3), 9, np.uint8)
    same, sizes = stack_images([a, a])
    assert sizes is None and same.shape == (2, 4, 6)
    buf = np.full(padded_shape([a, b]), 255, np.uint8)  # a reused buffer: the padding is cleared
    out, sizes = stack_images([a, b], out=buf)
    assert out is buf and sizes.tolist() == [[4, 6], [5, 3]]
    assert (out[0, :4, :6] == 7).all() and (out[0, 4:] == 0).all()
    assert (out[1, :5, :3] == 9).all() and (out[1, :, 3:] == 0).all()


def test_bags_and_compare_per_stream(rig, tmp_path, capsys):
    """``--write-bag`` with two configs: stream 1's bag is the bag of input 1's run alone with its
    config (``compare``: 100 % agreement), and ``compare`` names the compared stream's config."""
    _track(capsys, tmp_path / "ab", "--euroc", rig["A"], "--config", rig["a"], "--euroc", rig["A"],
           "--config", rig["b"], "--write-bag", "features.bag")
    _track(capsys, tmp_path / "b", rig["b"], "--euroc", rig["A"], "--write-bag", "features.bag")
    rc, stdout, err = run_cli(capsys, "compare", tmp_path / "b" / "features.bag", tmp_path / "ab", "--stream", 1,
                              "--out", tmp_path / "cmp")
    assert rc == 0, err
    assert "agreement     100.00 %" in stdout
    r = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert r["other"].endswith("features_stream1.bag") and r["agreement"] == 1.0
    assert r["other_stream"]["config"] == str(rig["b"]) and r["other_stream"]["camera"]["width"] == 256
