"""The bad-input corpus: what each bad input a user may give raises, or which exit code and stderr
line the CLI gives, and the words the message must contain.

Add a new bad input as one ``Case`` in the list it belongs to:

* ``API_CASES``: ``run(ctx)`` calls the library and must raise ``expect`` (an exception type) with
  every one of ``words`` in its message; ``expect=None``: an input that must *work* (the call
  asserts what working means, e.g. a transposed image gives the contiguous image's result);
* ``CLI_CASES``: ``run(ctx)`` returns the argv of ``torch_frontend.cli.main`` (run in process);
  ``expect`` is the exit code and ``words`` must be in the one ``torch-frontend: error:`` line;
* ``SUBPROCESS_CASES``: the same through a real ``python -m torch_frontend.cli`` process (few: each
  costs an interpreter start), which also proves that no traceback or library noise is printed.

``ctx`` gives ``ctx.tmp`` (a fresh folder) and ``ctx.mp`` (pytest's monkeypatch). ``fixed=True``
marks the inputs that once gave garbage, a wrong message or a traceback (regression cases); the
others document behaviour that was always right.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, Tuple, Union

import cv2
import numpy as np
import pytest
import torch

import torch_frontend as tf
from tests._helpers import crop, make_asl, small_config, truncate
from tests.conftest import REPO, SAMPLE, load_gray, sample_frames
from torch_frontend.cli import main
from torch_frontend.config import config_from_sensor_yaml, load_config
from torch_frontend.errors import ConfigError, DataError
from torch_frontend.io import ImageFolderSequence, read_image
from torch_frontend.pipelines.common import InputOptions, OptionError
from torch_frontend.pipelines.loop import LoopOptions

CONFIG = REPO / "configs" / "euroc.yaml"
CONFIG_TEXT = CONFIG.read_text()
SAMPLE_DATA = SAMPLE / "mav0" / "cam0" / "data"
EPOCH = 1403715273.262142976  # the first sample frame's time, seconds


@dataclass(frozen=True)
class Case:
    id: str
    run: Callable[[Any], Any]
    expect: Union[type, int, None]
    words: Tuple[str, ...] = ()
    fixed: bool = False


# ---------------------------------------------------------------------------------------------
# helpers


def _config(ctx, old: str, new: str, name: str = "bad.yaml") -> Path:
    """``configs/euroc.yaml`` with one line replaced."""
    assert old in CONFIG_TEXT, old
    p = ctx.tmp / name
    p.write_text(CONFIG_TEXT.replace(old, new))
    return p


def _camera_node(model: str, **changes) -> dict:
    """A camodocal camera map (``tests/test_camera.py``'s) with ``block.key`` values changed."""
    from tests.test_camera import _node

    n = _node(model)
    for dotted, v in changes.items():
        block, _, key = dotted.partition("__")
        if key:
            n[block][key] = v
        else:
            n[block] = v
    return n


def _sensor_yaml(ctx, intrinsics="[458.654, 457.296, 367.215, 248.375]", resolution="[752, 480]") -> Path:
    p = ctx.tmp / "sensor.yaml"
    p.write_text(f"%YAML:1.0\ncamera_model: pinhole\nresolution: {resolution}\nintrinsics: {intrinsics}\n"
                 "distortion_model: radial-tangential\n"
                 "distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]\n")
    return p


def _frames(n: int = 3):
    """``n`` sample frames, cropped to ``tests.test_io.CROP`` (what ``small_config`` describes)."""
    return [torch.from_numpy(crop(load_gray(p)).copy()) for p in sample_frames()[:n]]


def _tracker(ctx, mode="mono", **kw):
    return tf.FeatureTracker(str(small_config(ctx.tmp)), mode=mode, **kw)


def _full_tracker(mode="mono"):
    return tf.FeatureTracker(str(CONFIG), mode=mode)


def _full_frame(i: int = 0) -> torch.Tensor:
    return torch.from_numpy(load_gray(sample_frames()[i]))[None, None]


def _run(trk, images, times):
    return [trk.track(im[None, None] if im.dim() == 2 else im, t) for im, t in zip(images, times)]


def _same_frames(a, b) -> None:
    for fa, fb in zip(a, b):
        for name in ("ids", "uv", "xy", "velocity", "track_count", "valid", "published"):
            x, y = getattr(fa, name), getattr(fb, name)
            assert torch.equal(torch.nan_to_num(x), torch.nan_to_num(y)), name


def _folder(ctx, names, name="imgs") -> Path:
    d = ctx.tmp / name
    d.mkdir()
    src = sample_frames()[0]
    for n in names:
        shutil.copy(src, d / n)
    return d


NS_NAMES = [f"{1403715273262142976 + i * 50_000_000}.png" for i in range(3)]


# ---------------------------------------------------------------------------------------------
# inputs that must work (expect=None): each asserts what working means


def _clahe_transposed(ctx):
    img = torch.from_numpy(load_gray(sample_frames()[0])[:400, :400].copy())
    t = img.t()[None, None]
    assert not t.is_contiguous()
    assert torch.equal(tf.clahe(t), tf.clahe(t.contiguous()))


def _tracker_transposed(ctx):
    frames = _frames(2)
    views = [torch.from_numpy(f.numpy().T.copy()).t() for f in frames]  # same pixels, transposed strides
    assert not views[0].is_contiguous()
    _same_frames(_run(_tracker(ctx), views, [0.0, 0.05]), _run(_tracker(ctx), frames, [0.0, 0.05]))


def _lk_nan_guess(ctx):
    a, b = (load_gray(p) for p in sample_frames()[:2])
    A, B = torch.from_numpy(a)[None, None], torch.from_numpy(b)[None, None]
    pts = torch.tensor([[[100.0, 100.0], [200.0, 150.0], [300.0, 200.0]]])
    guess = pts.clone()
    guess[0, 1] = float("nan")
    for capturable in (False, True):
        nxt, st = tf.track_lk(A, B, pts, init_pts=guess, capturable=capturable)
        ref, st_ref = tf.track_lk(A, B, pts, init_pts=pts, capturable=capturable)
        assert st.tolist() == [[True, False, True]] and st_ref.tolist() == [[True, True, True]]
        assert torch.equal(nxt[0, [0, 2]], ref[0, [0, 2]])  # the other lanes are untouched
        assert torch.isfinite(nxt).all()
    _, cv_st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts[0].numpy(), guess[0].numpy().copy(), winSize=(21, 21),
                                           maxLevel=3, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    assert cv_st.ravel().tolist() == [1, 0, 1]  # OpenCV's status for a NaN guess


def _fusion_nan_prediction(ctx):
    """A NaN prediction for one feature: that feature is lost (LK status 0, as OpenCV), every other
    one tracks exactly as with a clean prediction."""
    tracked = []
    for poison in (False, True):
        trk = _full_tracker("fusion")
        f0 = trk.track(_full_frame(0), 0.0)
        n0, lost = int(f0.valid.sum()), int(f0.ids[0, 3])
        uv = f0.uv.clone()
        if poison:
            uv[0, 3] = float("nan")
        trk.set_prediction(f0.ids, uv, f0.valid)
        f1 = trk.track(_full_frame(1), 0.05)
        # features of frame 0 (ids 0 .. n0 - 1) still tracked in frame 1
        tracked.append({int(i): p for i, p, v in zip(f1.ids[0], f1.uv[0], f1.valid[0]) if v and 0 <= i < n0})
    clean, bad = tracked
    assert len(clean) >= 10 and lost in clean  # the prediction path ran (VINS-Fusion falls back below 10)
    assert set(bad) == set(clean) - {lost}
    for i in bad:
        assert torch.equal(bad[i], clean[i]), i


def _fusion_real_size(ctx):
    """VINS-Fusion tracks the real image size (spec §6.2): a 300x200 image with the 752x480
    config; its features lie inside it."""
    img = _full_frame(0)[..., :200, :300]
    trk = _full_tracker("fusion")
    f = trk.track(img, 0.0)
    f = trk.track(_full_frame(1)[..., :200, :300], 0.05)
    uv = f.uv[f.valid]
    assert uv.shape[0] > 20
    assert (uv[:, 0] < 300).all() and (uv[:, 1] < 200).all()


def _float_good_path(ctx):
    """Float 0..255 images with integer values and float32 times since the start are as uint8 /
    float64 (bit for bit): the door's checks change nothing on good input."""
    frames = _frames(3)
    t64 = torch.tensor([0.0, 0.05, 0.1], dtype=torch.float64)
    t32 = t64.float()
    ref = _run(_tracker(ctx), frames, t32.double().tolist())
    _same_frames(_run(_tracker(ctx), [f.float() for f in frames], t32.double().tolist()), ref)
    _same_frames(_run(_tracker(ctx), frames, [t.reshape(1) for t in t32]), ref)
    dark = frames[0].float().clamp(max=1.0)  # a dark 0..255 image (integers <= 1) is not 0..1
    _tracker(ctx).track(dark[None, None], 0.0)


def _ten_digit_ns_names(ctx):
    names = [f"{1_000_000_000 + i * 50_000_000}.png" for i in range(3)]
    seq = ImageFolderSequence(_folder(ctx, names))
    assert [f.stamp_ns for f in seq] == [1_000_000_000, 1_050_000_000, 1_100_000_000]


def _unreadable_folder(ctx):
    d = _folder(ctx, NS_NAMES)
    real = Path.iterdir

    def iterdir(self):
        if Path(self) == d:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self)

    ctx.mp.setattr(Path, "iterdir", iterdir)
    return d


def _cli_os_error_names_reading(ctx):
    from torch_frontend.cli import _os_error_message

    out = ctx.tmp / "out"
    read = _os_error_message(PermissionError(13, "Permission denied", str(ctx.tmp / "images")), out)
    write = _os_error_message(PermissionError(13, "Permission denied", str(out / "features.csv")), out)
    assert read.startswith("cannot read") and str(ctx.tmp / "images") in read
    assert write.startswith("cannot write") and "features.csv" in write


def _corrupt_png(ctx):
    p = ctx.tmp / "c.png"
    data = bytearray(sample_frames()[0].read_bytes())
    data[100] ^= 0xFF
    p.write_bytes(bytes(data))
    read_image(p)


def _gftt_mask(shape):
    def run(ctx):
        tf.good_features_to_track(_full_frame(0), 10, mask=torch.ones(shape, dtype=torch.uint8))
    return run


API_CASES = [
    # --- item 5: camera values and rates, refused at load time naming file and key
    Case("config_fx_zero", lambda c: load_config(_config(c, "fx: 4.616e+02", "fx: 0", "fx0.yaml")), ConfigError,
         ("fx0.yaml", "projection_parameters.fx", "> 0"), fixed=True),
    Case("config_fy_nan", lambda c: load_config(_config(c, "fy: 4.603e+02", "fy: .nan")), ConfigError,
         ("projection_parameters.fy", "finite"), fixed=True),
    Case("config_k1_inf", lambda c: load_config(_config(c, "k1: -2.917e-01", "k1: .inf")), ConfigError,
         ("distortion_parameters.k1", "finite"), fixed=True),
    Case("config_freq_negative", lambda c: load_config(_config(c, "freq: 10", "freq: -5")), ConfigError,
         ("bad.yaml", "freq", ">= 0"), fixed=True),
    Case("camera_pinhole_fx_negative", lambda c: tf.camera_from_config(
        _camera_node("PINHOLE", projection_parameters__fx=-461.6), "cam.yaml"), ConfigError,
         ("cam.yaml", "projection_parameters.fx", "> 0"), fixed=True),
    Case("camera_pinhole_full_fy_zero", lambda c: tf.camera_from_config(
        _camera_node("PINHOLE_FULL", projection_parameters__fy=0.0)), ConfigError,
         ("projection_parameters.fy", "> 0"), fixed=True),
    Case("camera_mei_gamma1_zero", lambda c: tf.camera_from_config(
        _camera_node("MEI", projection_parameters__gamma1=0.0)), ConfigError,
         ("projection_parameters.gamma1", "> 0"), fixed=True),
    Case("camera_mei_xi_negative", lambda c: tf.camera_from_config(
        _camera_node("MEI", mirror_parameters__xi=-0.5)), ConfigError,
         ("mirror_parameters.xi", ">= 0"), fixed=True),
    Case("camera_kb_mv_zero", lambda c: tf.camera_from_config(
        _camera_node("KANNALA_BRANDT", projection_parameters__mv=0.0)), ConfigError,
         ("projection_parameters.mv", "> 0"), fixed=True),
    Case("camera_kb_k3_nan", lambda c: tf.camera_from_config(
        _camera_node("KANNALA_BRANDT", projection_parameters__k3=math.nan)), ConfigError,
         ("projection_parameters.k3", "finite"), fixed=True),
    Case("camera_scaramuzza_singular_affine", lambda c: tf.camera_from_config(
        _camera_node("scaramuzza", affine_parameters={"ac": 0.5, "ad": 1.0, "ae": 0.5, "cx": 400.0, "cy": 300.0})),
         ConfigError, ("affine_parameters.ac", "determinant"), fixed=True),
    Case("camera_scaramuzza_poly0_positive", lambda c: tf.camera_from_config(
        _camera_node("scaramuzza", poly_parameters__p0=230.0)), ConfigError,
         ("poly_parameters.p0", "< 0"), fixed=True),
    Case("camera_scaramuzza_inv_poly_inf", lambda c: tf.camera_from_config(
        _camera_node("scaramuzza", inv_poly_parameters__p7=math.inf)), ConfigError,
         ("inv_poly_parameters.p7", "finite"), fixed=True),
    Case("camera_image_width_zero", lambda c: tf.camera_from_config(_camera_node("PINHOLE", image_width=0)),
         ConfigError, ("image_width", "positive"), fixed=True),
    Case("sensor_yaml_fu_zero", lambda c: config_from_sensor_yaml(_sensor_yaml(c, intrinsics="[0, 457.3, 367.2, 248.4]")),
         ConfigError, ("sensor.yaml", "intrinsics[0]", "> 0"), fixed=True),
    Case("sensor_yaml_resolution_zero", lambda c: config_from_sensor_yaml(_sensor_yaml(c, resolution="[752, 0]")),
         ConfigError, ("sensor.yaml", "resolution", "positive"), fixed=True),
    Case("folder_fps_inf", lambda c: ImageFolderSequence(_folder(c, ["000001.png"]), fps=math.inf), DataError,
         ("fps", "finite"), fixed=True),
    Case("options_fps_inf", lambda c: InputOptions(fps=math.inf).check(), OptionError, ("fps", "finite"), fixed=True),
    # --- item 6: input conventions that gave silent garbage
    Case("timestamps_float32_epoch", lambda c: _full_tracker().track(
        _full_frame(), torch.tensor([EPOCH], dtype=torch.float32)), ValueError,
         ("timestamps are float32", "epoch seconds need float64", "128 s"), fixed=True),
    Case("timestamps_numpy_float32_epoch", lambda c: tf.tracker.step(
        (t := _full_tracker()).initial_state(), _full_frame(), np.array([EPOCH], dtype=np.float32), t.params),
         ValueError, ("timestamps are float32", "float64"), fixed=True),
    Case("timestamps_float16", lambda c: _full_tracker().track(_full_frame(), torch.tensor([1000.0]).half()),
         ValueError, ("timestamps are float16", "float64"), fixed=True),
    Case("images_float_0_to_1", lambda c: _full_tracker().track(_full_frame().float() / 255, 0.0), ValueError,
         ("values look like 0..1", "0..255"), fixed=True),
    Case("images_nan_pixel", lambda c: _full_tracker().track(
        _full_frame().float().index_put_((torch.tensor(0), torch.tensor(0), torch.tensor(5), torch.tensor(7)),
                                         torch.tensor(math.nan)), 0.0), ValueError, ("NaN pixels",), fixed=True),
    Case("images_good_float_and_float32_times", _float_good_path, None),
    # --- item 8: internal errors that must be clear ones, or work
    Case("clahe_transposed_uint8", _clahe_transposed, None, fixed=True),
    Case("tracker_transposed_uint8", _tracker_transposed, None, fixed=True),
    Case("lk_nan_initial_guess", _lk_nan_guess, None, fixed=True),
    Case("fusion_nan_prediction", _fusion_nan_prediction, None, fixed=True),
    Case("gftt_mask_wrong_size", _gftt_mask((100, 100)), ValueError, ("mask", "(H, W)", "(100, 100)"), fixed=True),
    Case("gftt_mask_wrong_size_batched", _gftt_mask((1, 100, 100)), ValueError, ("mask", "(1, 100, 100)")),
    Case("mono_image_size_not_config", lambda c: _full_tracker().track(_full_frame()[..., :200, :300], 0.0),
         ValueError, ("300x200", "differs from the config", "752x480")),
    Case("fusion_image_real_size", _fusion_real_size, None),
    Case("fusion_image_size_changes", lambda c: [(t := _full_tracker("fusion")).track(_full_frame()[..., :200, :300], 0.0),
                                                 t.track(_full_frame(), 0.05)], ValueError,
         ("752x480", "differs from the previous image", "300x200")),
    # --- item 9: timestamps from names
    Case("folder_stray_mask_png", lambda c: ImageFolderSequence(_folder(c, NS_NAMES + ["mask.png"])), DataError,
         ("'mask.png'", "not a time", "fps"), fixed=True),
    Case("folder_stray_short_number", lambda c: ImageFolderSequence(_folder(c, NS_NAMES + ["99.png"])), DataError,
         ("'99.png'", "not a time", "nanoseconds"), fixed=True),
    Case("folder_ten_digit_ns_names", _ten_digit_ns_names, None, fixed=True),
    Case("folder_frame_numbers_need_fps", lambda c: ImageFolderSequence(_folder(c, ["000001.png", "000002.png"])),
         DataError, ("000001.png", "give a frame rate (`fps`)")),
    Case("folder_unreadable", lambda c: ImageFolderSequence(_unreadable_folder(c)), DataError,
         ("cannot read folder", "Permission denied"), fixed=True),
    Case("cli_os_error_reading_is_not_writing", _cli_os_error_names_reading, None, fixed=True),
    Case("loop_options_keyframe_angle_inf", lambda c: LoopOptions(train_vocabulary=True, keyframe_angle=math.inf).check(),
         OptionError, ("keyframe_angle", "finite"), fixed=True),
    # --- a sample of what always gave a clear error
    Case("corrupt_png", _corrupt_png, DataError, ("c.png", "corrupt PNG", "CRC")),
    Case("config_without_max_cnt", lambda c: load_config(_config(c, "max_cnt: 150", "other_key: 150")), ConfigError,
         ("bad.yaml", "max_cnt", "missing")),
    Case("camera_without_fx", lambda c: tf.camera_from_config(_camera_node("PINHOLE", projection_parameters={
        "fy": 460.3, "cx": 363.0, "cy": 248.1}), "cam.yaml"), ConfigError, ("projection_parameters.fx", "missing")),
    Case("images_wrong_batch", lambda c: _full_tracker().track(_full_frame().expand(2, 1, 480, 752), 0.0), ValueError,
         ("expected 1 streams",)),
    Case("images_wrong_shape", lambda c: _full_tracker().track(torch.zeros(1, 3, 480, 752, dtype=torch.uint8), 0.0),
         ValueError, ("(B, 1, H, W)", "(1, 3, 480, 752)")),
    Case("timestamps_nan", lambda c: _full_tracker().track(_full_frame(), math.nan), ValueError, ("finite",)),
    Case("lk_points_wrong_shape", lambda c: tf.track_lk(_full_frame(), _full_frame(1), torch.zeros(1, 5, 3)),
         ValueError, ("pts", "(B, N, 2)")),
    Case("loop_options_keyframe_distance_negative", lambda c: LoopOptions(train_vocabulary=True,
                                                                          keyframe_distance=-1.0).check(),
         OptionError, ("keyframe_distance", ">= 0")),
]


@pytest.fixture
def ctx(tmp_path, monkeypatch):
    return SimpleNamespace(tmp=tmp_path, mp=monkeypatch)


@pytest.mark.parametrize("case", API_CASES, ids=[c.id for c in API_CASES])
def test_api_case(case: Case, ctx):
    if case.expect is None:
        case.run(ctx)  # asserts inside
        return
    with pytest.raises(case.expect) as ei:
        case.run(ctx)
    for w in case.words:
        assert w in str(ei.value), (w, str(ei.value))


# ---------------------------------------------------------------------------------------------
# the CLI, in process: exit code and one stderr line


def _track(ctx, *argv):
    return ["track", *argv, "--out", ctx.tmp / "out", "--no-progress", "--no-tracks"]


def _loop(ctx, *argv):
    return ["loop", CONFIG, "--images", SAMPLE_DATA, "--poses", ctx.tmp / "poses.csv", "--vocabulary",
            ctx.tmp / "voc.npz", "--out", ctx.tmp / "out", "--no-progress", *argv]


def _truncated_asl(ctx):
    seq = make_asl(ctx.tmp / "a", n=1)
    truncate(next((seq / "mav0" / "cam0" / "data").glob("*.png")), keep=0.3)
    return seq


CLI_CASES = [
    Case("cli_fps_inf", lambda c: _track(c, CONFIG, "--images", _folder(c, ["000001.png"]), "--fps", "inf"), 2,
         ("--fps", "finite"), fixed=True),
    Case("cli_config_fx_zero", lambda c: _track(c, _config(c, "fx: 4.616e+02", "fx: 0", "fx0.yaml"), "--euroc", SAMPLE,
                                                "--max-frames", 2), 2, ("fx0.yaml", "projection_parameters.fx"),
         fixed=True),
    Case("cli_config_freq_negative", lambda c: _track(c, _config(c, "freq: 10", "freq: -5"), "--euroc", SAMPLE,
                                                      "--max-frames", 2), 2, ("bad.yaml", "freq"), fixed=True),
    Case("cli_stray_mask_png", lambda c: _track(c, CONFIG, "--images", _folder(c, NS_NAMES + ["mask.png"])), 1,
         ("'mask.png'", "not a time"), fixed=True),
    Case("cli_unreadable_input_folder", lambda c: _track(c, CONFIG, "--images", _unreadable_folder(c)), 1,
         ("cannot read folder", "Permission denied"), fixed=True),
    Case("cli_loop_keyframe_angle_inf", lambda c: _loop(c, "--keyframe-angle", "inf"), 2,
         ("--keyframe-angle", "finite"), fixed=True),
    Case("cli_loop_keyframe_distance_negative", lambda c: _loop(c, "--keyframe-distance", "-1"), 2,
         ("--keyframe-distance", ">= 0", "-1")),
    Case("cli_loop_keyframe_angle_nan", lambda c: _loop(c, "--keyframe-angle", "nan"), 2,
         ("--keyframe-angle", ">= 0", "nan")),
    Case("cli_fps_negative", lambda c: _track(c, CONFIG, "--images", _folder(c, ["000001.png"]), "--fps", "-3"), 2,
         ("--fps", "> 0")),
    Case("cli_truncated_png", lambda c: _track(c, CONFIG, "--euroc", _truncated_asl(c)), 1, ("truncated PNG",)),
    Case("cli_missing_config", lambda c: _track(c, c.tmp / "missing.yaml", "--euroc", SAMPLE), 2,
         ("missing.yaml", "file not found")),
]


def _error_line(err: str, argparse_error: bool) -> str:
    """The error line of ``err``: the only line (the library's errors), or the last one after
    argparse's usage (a flag's type check)."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err, err
    if argparse_error:
        assert "usage:" in err and re.match(r"torch-frontend \w+: error: ", lines[-1]), err
    else:
        assert len(lines) == 1 and lines[0].startswith("torch-frontend: error: "), err
    return lines[-1]


@pytest.mark.parametrize("case", CLI_CASES, ids=[c.id for c in CLI_CASES])
def test_cli_case(case: Case, ctx, capsys):
    argv = [str(a) for a in case.run(ctx)]
    parser_error = False
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse's own errors (a flag's type): usage on stderr, exit 2
        rc, parser_error = e.code, True
    _, err = capsys.readouterr()
    assert rc == case.expect, (rc, err)
    line = _error_line(err, parser_error)
    for w in case.words:
        assert w in line, (w, line)
    out = ctx.tmp / "out"
    assert not out.exists() or not any(out.iterdir()), "a failed run left files in --out"


# ---------------------------------------------------------------------------------------------
# the CLI as a user runs it: a real process, exactly one stderr line


SUBPROCESS_CASES = [
    Case("process_fps_inf", lambda c: _track(c, CONFIG, "--images", _folder(c, ["000001.png"]), "--fps", "inf"), 2,
         ("--fps", "finite"), fixed=True),
    Case("process_config_fx_zero", lambda c: _track(c, _config(c, "fx: 4.616e+02", "fx: 0", "fx0.yaml"), "--euroc",
                                                    SAMPLE, "--max-frames", 2), 2, ("projection_parameters.fx",),
         fixed=True),
    Case("process_loop_keyframe_angle_inf", lambda c: _loop(c, "--keyframe-angle", "inf"), 2,
         ("--keyframe-angle", "finite"), fixed=True),
]


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX process")
@pytest.mark.parametrize("case", SUBPROCESS_CASES, ids=[c.id for c in SUBPROCESS_CASES])
def test_subprocess_case(case: Case, ctx):
    argv = [str(a) for a in case.run(ctx)]
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "PYTHONPATH": str(REPO)}
    r = subprocess.run([sys.executable, "-m", "torch_frontend.cli", *argv], capture_output=True, text=True,
                       timeout=120, env=env, cwd=REPO)
    assert r.returncode == case.expect, r.stderr
    line = _error_line(r.stderr, "usage:" in r.stderr)  # exactly one line unless argparse's usage
    for w in case.words:
        assert w in line, (w, line)


def test_corpus_ids_are_unique():
    ids = [c.id for c in API_CASES + CLI_CASES + SUBPROCESS_CASES]
    assert len(ids) == len(set(ids))
    assert all(c.expect is None or c.words for c in API_CASES + CLI_CASES + SUBPROCESS_CASES)

