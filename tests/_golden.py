"""The golden battery: every output of every step of the golden scenarios, as per-array digests.

A scenario is a short, deterministic run of ``FeatureTracker`` on the repo's own data (the EuRoC
sample, the planar flight, crops of them); a *variant* is a way of building the tracker (the
default CPU path, ``capturable=True``, ``differentiable=True`` with float images that require a
gradient, both, ``F_method="lo"``). Every field of every :class:`FeatureFrame` of every step, and
the final state's feature table, is reduced to a digest of its dtype, shape and raw bytes
(stale values in empty slots included: the battery pins every bit a user can read).

``tests/test_golden.py`` recomputes the digests and compares them with ``tests/data/golden.txt``;
a change that moves one bit fails until the file is regenerated on purpose with
``python -m tests.regenerate_golden`` (see its docstring), and the diff of that file is part of
the change.

The scenarios cover mono (VINS-Mono clock: skipped first image, publish every other frame,
restart after a gap and after time going backwards, an inactive stream), two streams with
different images, fusion stereo with FLOW_BACK, fusion with predictions and removals,
Kannala-Brandt with the fisheye mask, and the planar flight. Each (scenario, variant) is one case;
``FAST`` are those the default suite runs, the rest carry the ``slow`` marker.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Callable, Dict, Iterator, List, NamedTuple, Optional, Tuple

import numpy as np
import torch

import torch_frontend as tf

from .conftest import REPO, SHARED_DATA, load_gray, sample_frames

GOLDEN_FILE = REPO / "tests" / "data" / "golden.txt"
DIGEST_CHARS = 10  # 40 bits of sha256 per array: a moved bit goes unseen with probability 1e-12

CONFIGS = REPO / "configs"


class Variant(NamedTuple):
    """How a scenario's tracker is built and fed."""

    capturable: bool = False
    differentiable: bool = False
    F_method: Optional[str] = None
    lk_backend: Optional[str] = None


_BASE_VARIANTS: Dict[str, Variant] = {
    "default": Variant(),
    "capturable": Variant(capturable=True),
    "differentiable": Variant(differentiable=True),
    "diff_capturable": Variant(capturable=True, differentiable=True),
    "lo": Variant(F_method="lo"),
    "lo_capturable": Variant(capturable=True, F_method="lo"),
}


def tensor_variant(variant: str) -> str:
    """The name of ``variant`` run with the tensor LK and pyramid (``lk_backend="tensor"``): ``tensor``
    for ``default``, ``tensor_<variant>`` for the others. Their digests are the ones every variant
    had before the fused kernels became the default (kept, not regenerated: the tensor path's bits
    did not move)."""
    return "tensor" if variant == "default" else f"tensor_{variant}"


#: every variant on the default backend (the fused kernels on the CPU), and each on the tensor kernels
VARIANTS: Dict[str, Variant] = {**_BASE_VARIANTS,
                                **{tensor_variant(k): v._replace(lk_backend="tensor") for k, v in _BASE_VARIANTS.items()}}


# ---------------------------------------------------------------------------------------------
# digests


def digest(x) -> str:
    """A tensor's dtype, shape and raw bytes (detached, on the CPU, contiguous) as ``DIGEST_CHARS``
    hex digits of sha256; ``-`` for None."""
    if x is None:
        return "-"
    t = x.detach().cpu().contiguous()
    raw = (t.to(torch.uint8) if t.dtype == torch.bool else t).numpy().tobytes()
    h = hashlib.sha256(f"{t.dtype} {tuple(t.shape)} ".encode() + raw)
    return h.hexdigest()[:DIGEST_CHARS]


FRAME_FIELDS = tuple(f.name for f in dataclasses.fields(tf.FeatureFrame))


def _table_fields() -> Tuple[str, ...]:
    from torch_frontend.tracker.table import FeatureTable

    return tuple(f.name for f in dataclasses.fields(FeatureTable))


STATE_FIELDS = ("next_id",) + tuple(f"features.{n}" for n in _table_fields())


def frame_digests(frame: tf.FeatureFrame) -> Tuple[str, ...]:
    return tuple(digest(getattr(frame, n)) for n in FRAME_FIELDS)


def state_digests(state) -> Tuple[str, ...]:
    return (digest(state.next_id),) + tuple(digest(getattr(state.features, n)) for n in _table_fields())


def fields_of(key: str) -> Tuple[str, ...]:
    """The field names of a digest line's columns (a step's frame, or the final ``state``)."""
    return STATE_FIELDS if key.endswith("/state") else FRAME_FIELDS


# ---------------------------------------------------------------------------------------------
# inputs


def _stamp(path: Path) -> float:
    return int(path.stem) * 1e-9


def _euroc(camera: str = "cam0", n: Optional[int] = None) -> List[Tuple[float, np.ndarray]]:
    return [(_stamp(f), load_gray(f)) for f in sample_frames(camera)[:n]]


class Step(NamedTuple):
    """One call: ``images (B, H, W)`` uint8, ``timestamps (B,)``, optional right images and
    ``active``, and an optional hook run on the tracker before the call (predictions, removals)."""

    images: np.ndarray
    timestamps: List[float]
    right: Optional[np.ndarray] = None
    active: Optional[List[bool]] = None
    before: Optional[Callable[[tf.FeatureTracker], None]] = None


class Scenario(NamedTuple):
    config: Callable[[], tf.TrackerConfig]
    mode: str
    num_streams: int
    steps: Callable[[], List[Step]]


def _mono_steps(n: int = 24, gap_at: int = 10, back_at: Optional[int] = 16) -> List[Step]:
    """Two streams of the EuRoC sample: stream 0 in order; stream 1 five frames later (other
    images), with a 2 s gap at step ``gap_at`` (restart), time going backwards at step ``back_at``
    (restart), and inactive at steps 6 and 7."""
    seq = _euroc("cam0")
    out = []
    t1_shift = 0.0
    for k in range(n):
        t0, a = seq[k % len(seq)]
        _, b = seq[(k + 5) % len(seq)]
        if k == gap_at:
            t1_shift += 2.0
        if k == back_at:
            t1_shift -= 3.0
        out.append(Step(np.stack((a, b)), [t0, t0 + t1_shift], active=[True, k not in (6, 7)]))
    return out


def _stereo_steps() -> List[Step]:
    left, right = _euroc("cam0"), _euroc("cam1")
    return [Step(a[None], [t], right=b[None]) for (t, a), (_, b) in zip(left, right)]


def _prediction_steps(n: int = 8) -> List[Step]:
    """Fusion mono: at step 3 every feature gets a prediction (its current pixel shifted by half
    a pixel), at step 5 a prediction and then the removal of every third feature (VINS-Fusion's
    ``setPrediction`` / ``removeOutliers``)."""
    seq = _euroc("cam0", n)

    def predict(tr: tf.FeatureTracker) -> None:
        table = tr.state.features
        tr.set_prediction(table.ids, table.pts + 0.5, table.valid)

    def predict_and_remove(tr: tf.FeatureTracker) -> None:
        predict(tr)
        table = tr.state.features
        ids = table.ids[0][table.valid[0]]
        tr.remove(0, ids[::3].tolist())

    hooks = {3: predict, 5: predict_and_remove}
    return [Step(img[None], [t], before=hooks.get(k)) for k, (t, img) in enumerate(seq)]


def _fisheye_steps(n: int = 12) -> List[Step]:
    """The EuRoC sample cut to the TUM-VI config's 512x512: the left 512 columns, the 480 rows
    reflected to 512 (the fisheye disc masks the corners)."""
    return [Step(np.pad(img[:, :512], ((0, 32), (0, 0)), mode="reflect")[None], [t]) for t, img in _euroc("cam0", n)]


def _flight_steps(n: int = 14) -> List[Step]:
    from torch_frontend.testing.flight import synthetic_flight

    frames, _ = synthetic_flight(n_frames=n, size=(480, 752))
    return [Step(f[None], [0.05 * k]) for k, f in enumerate(frames)]


def _micro_steps() -> List[Step]:
    root = SHARED_DATA / "sequences" / "euroc_v1_01_easy_micro" / "mav0" / "cam0" / "data"
    files = sorted(root.glob("*.png"))
    return [Step(load_gray(f)[None], [_stamp(f)]) for f in files]


def _mono_mei_single() -> tf.TrackerConfig:
    return dataclasses.replace(tf.load_config(CONFIGS / "euroc_mono_mei.yaml"), num_of_cam=1, camera1=None)


SCENARIOS: Dict[str, Scenario] = {
    "mono": Scenario(lambda: tf.load_config(CONFIGS / "euroc.yaml"), "mono", 2, _mono_steps),
    # 8 steps of "mono" with its restart after a gap early (first image, publishing, a restart, the
    # inactive stream): the default suite's capturable cases
    "mono8": Scenario(lambda: tf.load_config(CONFIGS / "euroc.yaml"), "mono", 2,
                      lambda: _mono_steps(8, gap_at=3, back_at=None)),
    "stereo": Scenario(lambda: tf.load_config(CONFIGS / "euroc_stereo_mei.yaml"), "fusion", 1, _stereo_steps),
    "prediction": Scenario(_mono_mei_single, "fusion", 1, _prediction_steps),
    "kb_fisheye": Scenario(lambda: tf.load_config(CONFIGS / "tum_vi.yaml"), "mono", 1, _fisheye_steps),
    "flight": Scenario(lambda: tf.load_config(CONFIGS / "euroc.yaml"), "mono", 1, _flight_steps),
    "micro": Scenario(lambda: tf.load_config(CONFIGS / "euroc.yaml"), "mono", 1, _micro_steps),
}

# (scenario, variant) cases on the default backend; each also runs on the tensor kernels
_BASE_CASES: List[Tuple[str, str]] = [
    *((s, "default") for s in SCENARIOS),
    *((s, v) for s in ("mono", "stereo", "prediction", "kb_fisheye", "flight")
      for v in ("capturable", "differentiable", "diff_capturable")),
    ("mono", "lo"), ("flight", "lo"), ("mono", "lo_capturable"),
    ("mono8", "capturable"), ("mono8", "diff_capturable"), ("mono8", "lo_capturable"),
]
CASES: List[Tuple[str, str]] = _BASE_CASES + [(s, tensor_variant(v)) for s, v in _BASE_CASES]
# the default suite runs FAST, the slow marker the rest
FAST = {("mono", "default"), ("mono8", "default"), ("stereo", "default"), ("prediction", "default"),
        ("kb_fisheye", "default"), ("flight", "default"), ("mono8", "capturable"), ("stereo", "capturable"),
        ("prediction", "differentiable"), ("mono", "differentiable"), ("mono", "lo"),
        ("mono8", "tensor"), ("mono8", "tensor_capturable"), ("stereo", "tensor")}
NEEDS_SHARED = {"micro"}


def run_case(scenario: str, variant: str) -> Iterator[Tuple[str, Tuple[str, ...]]]:
    """``(key, digests)`` of every step of the case (``scenario/variant/step``, the columns of
    :data:`FRAME_FIELDS`), then of its final state (``scenario/variant/state``)."""
    sc, v = SCENARIOS[scenario], VARIANTS[variant]
    cfg = sc.config()
    if v.F_method is not None:
        cfg = dataclasses.replace(cfg, F_method=v.F_method)
    tr = tf.FeatureTracker(cfg, num_streams=sc.num_streams, mode=sc.mode, capturable=v.capturable,
                           differentiable=v.differentiable, lk_backend=v.lk_backend)
    for k, s in enumerate(sc.steps()):
        if s.before is not None:
            s.before(tr)
        img = torch.from_numpy(s.images)[:, None]
        right = None if s.right is None else torch.from_numpy(s.right)[:, None]
        if v.differentiable:
            img = img.float().requires_grad_()
            right = None if right is None else right.float().requires_grad_()
        frame = tr.track(img, torch.tensor(s.timestamps, dtype=torch.float64), right=right, active=s.active)
        yield f"{case_id(scenario, variant)}/{k:03d}", frame_digests(frame)
    yield f"{case_id(scenario, variant)}/state", state_digests(tr.state)


def case_id(scenario: str, variant: str) -> str:
    return f"{scenario}/{variant}"


SAME = "="  # a variant's line that equals its scenario's default line


def read_golden(path: Path = GOLDEN_FILE) -> Dict[str, Tuple[str, ...]]:
    """``key -> digests`` of the golden file (``key<TAB>digest digest ...`` lines, ``#``
    comments). A variant's line ``=`` stands for the default variant's line of the same step."""
    out: Dict[str, Tuple[str, ...]] = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line and not line.startswith("#"):
            key, value = line.split("\t")
            if value == SAME:
                scenario, _, step = key.split("/")
                out[key] = out[f"{scenario}/default/{step}"]
            else:
                out[key] = tuple(value.split(" "))
    return out


def write_golden(digests: Dict[str, Tuple[str, ...]], path: Path = GOLDEN_FILE) -> None:
    """Write ``digests`` (temp file + rename), cases in :data:`CASES` order, a variant's line that
    equals the default's as ``=``."""
    order = {case_id(s, v): i for i, (s, v) in enumerate(CASES)}
    keys = sorted(digests, key=lambda k: (order.get(k.rsplit("/", 1)[0], len(order)), k))
    lines = [
        f"# golden battery (tests/_golden.py): every output of every step, sha256[:{DIGEST_CHARS}] of dtype, shape, bytes",
        "# regenerate on purpose: python -m tests.regenerate_golden [scenario/variant ...]",
        "# frame columns: " + " ".join(FRAME_FIELDS),
        "# state columns: " + " ".join(STATE_FIELDS),
        "# '=': the same digests as the scenario's default variant at this step",
    ]
    for k in keys:
        scenario, variant, step = k.split("/")
        base = digests.get(f"{scenario}/default/{step}")
        same = variant != "default" and base == digests[k]
        lines.append(f"{k}\t{SAME if same else ' '.join(digests[k])}")
    tmp = path.with_suffix(".tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    tmp.replace(path)


def shared_available() -> bool:
    return (SHARED_DATA / "sequences" / "euroc_v1_01_easy_micro").exists()
