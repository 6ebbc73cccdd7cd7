"""What ``FeatureTracker`` does with inputs a new user gets wrong (issue 30):

* integer timestamps (EuRoC's int64 nanoseconds, milliseconds) are refused with the likely unit;
  before, they were taken as seconds: every frame a restart, ``valid`` all False, no word;
* a stream whose timestamps restart the clock at every step (seconds that are really ns or ms,
  or a camera slower than 1 Hz) warns once, naming the steps it saw;
* a device this process cannot use raises a ``ValueError`` naming it and what is available
  (before: torch's raw ``AssertionError: Torch not compiled with CUDA enabled``).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import torch_frontend as tf
from torch_frontend.tracker import FeatureTracker
from torch_frontend.tracker.clock import RESTART_WARN_STEPS

from .conftest import REPO, load_gray, sample_frames

CFG = REPO / "configs" / "euroc.yaml"
EUROC_NS = 1403636579763555584  # the first cam0 stamp of EuRoC MH_01, int64 ns


def _blank(B=1):
    return torch.zeros(B, 1, 480, 752, dtype=torch.uint8)


@pytest.mark.parametrize("stamps, unit", [
    (torch.tensor([EUROC_NS]), "nanoseconds.*/ 1e9"),
    (np.array([EUROC_NS // 10**6]), "milliseconds.*/ 1e3"),
    (torch.tensor([EUROC_NS // 10**3]), "microseconds.*/ 1e6"),
    (torch.tensor([3], dtype=torch.int32), "if they count seconds"),
])
def test_integer_timestamps_are_refused_naming_the_unit(stamps, unit):
    tr = FeatureTracker(CFG)
    with pytest.raises(ValueError, match=f"timestamps are int.*expected float64 seconds.*{unit}"):
        tr.track(_blank(), stamps)
    with pytest.raises(ValueError, match="timestamps are int"):
        tr.step(tr.initial_state(), _blank(), stamps)
    # Python numbers stay seconds, and float64 seconds from the ns pass
    tr.track(_blank(), 0)
    tr.track(_blank(), torch.tensor([EUROC_NS]).double() / 1e9)


def _restart_warnings(tracker, stamps, images=None):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        for k, t in enumerate(stamps):
            tracker.track(_blank(tracker.B) if images is None else images[k], t)
    return [str(w.message) for w in got if "restarted" in str(w.message)]


def test_nanoseconds_as_seconds_warn_once_naming_the_steps():
    """float64 ns (the int64 cast, not divided) on stream 1 of 2: one warning for stream 1 after
    RESTART_WARN_STEPS steps, naming them and the unit; stream 0's seconds give none."""
    tr = FeatureTracker(CFG, num_streams=2)
    stamps = [torch.tensor([1403636579.76 + 0.05 * k, float(EUROC_NS + k * 50_000_000)], dtype=torch.float64)
              for k in range(3 * RESTART_WARN_STEPS)]
    got = _restart_warnings(tr, stamps)
    assert len(got) == 1, got
    assert "stream 1" in got[0] and "5e+07 s" in got[0] and "nanoseconds" in got[0] and "1e9" in got[0], got
    ms = FeatureTracker(CFG)
    got = _restart_warnings(ms, [[1.4e12 + 50.0 * k] for k in range(RESTART_WARN_STEPS + 1)])
    assert len(got) == 1 and "milliseconds" in got[0] and "50 s" in got[0], got


def test_real_sequence_with_a_pause_and_a_jump_back_does_not_warn():
    """The sample frames, a 3 s pause, and time going backwards once: single restarts, no warning;
    steps from a fresh state start the count afresh."""
    files = sample_frames("cam0")[:8]
    imgs = [torch.from_numpy(load_gray(f))[None, None] for f in files]
    t = [int(f.stem) * 1e-9 for f in files]
    stamps = t[:4] + [x + 3.0 for x in t[4:6]] + [x - 10.0 for x in t[6:]]
    tr = FeatureTracker(CFG)
    assert _restart_warnings(tr, [[x] for x in stamps], imgs) == []
    # two restarting steps, reset(), two more: never RESTART_WARN_STEPS in one chain of states
    tr = FeatureTracker(CFG)
    n = RESTART_WARN_STEPS - 1
    assert _restart_warnings(tr, [[10.0 * k] for k in range(n + 1)]) == []
    tr.reset()
    assert _restart_warnings(tr, [[10.0 * k] for k in range(n + 1)]) == []
    # the pure step follows its chain of states too
    state = tr.initial_state()
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        for k in range(RESTART_WARN_STEPS + 1):
            state, _ = tr.step(state, _blank(), [10.0 * k])
    assert sum("restarted" in str(w.message) for w in got) == 1


def test_unavailable_devices_are_named_with_what_is_available():
    cfg = tf.load_config(CFG)
    bad = ["cuda:99"]
    if not torch.cuda.is_available():
        bad.append("cuda")
    mps = getattr(torch.backends, "mps", None)
    if mps is None or not mps.is_available():
        bad.append("mps")
    for dev in bad:
        with pytest.raises(ValueError, match=f"device '{dev}' is not available on this machine .*available here: cpu"):
            FeatureTracker(cfg, device=dev)
    with pytest.raises(ValueError, match="'gpu' is not a device.*available here: cpu"):
        FeatureTracker(cfg, device="gpu")
    assert FeatureTracker(cfg, device=torch.device("cpu")).device == torch.device("cpu")


def test_the_cli_names_an_unusable_device_in_one_line(capsys, tmp_path):
    """``--device mps`` (a device torch names but this machine lacks): one line, exit 2 (before: a
    traceback from the first allocation)."""
    from tests._helpers import CONFIG, assert_one_error_line
    from tests.conftest import SAMPLE
    from torch_frontend.cli import main

    mps = getattr(torch.backends, "mps", None)
    dev = "cuda:99" if mps is not None and mps.is_available() else "mps"
    rc = main(["track", CONFIG, "--euroc", str(SAMPLE), "--out", str(tmp_path / "o"), "--device", dev,
               "--no-progress", "--max-frames", "2"])
    assert rc == 2
    assert_one_error_line(capsys.readouterr().err, f"--device '{dev}'", "available here: cpu")


def test_the_restart_watch_reads_no_device_tensor():
    """Timestamps (or ``active``) on a device are not read: no op, no sync (a ``meta`` tensor stands
    for a CUDA one), and the watch starts afresh instead of counting."""
    from torch_frontend.testing.dispatch_count import OpCounter
    from torch_frontend.tracker.clock import RestartWatch

    class State:  # any weak-referenceable object stands for a TrackerState
        pass

    watch, state = RestartWatch(2, 1.0, steps=2), State()
    for k in range(2):
        watch.observe(state, [10.0 * k, 0.0], None)
        watch.follow(state)
    assert watch.run[0] == [10.0]
    dev_t = torch.zeros(2, dtype=torch.float64, device="meta")
    dev_a = torch.ones(2, dtype=torch.bool, device="meta")
    with OpCounter() as c:
        watch.observe(state, dev_t, None)
        watch.observe(state, [1.0, 1.0], dev_a)
    assert c.kernels == 0 and c.syncs == 0, c.summary()
    assert watch.run == [[], []] and watch.last == [None, None]
