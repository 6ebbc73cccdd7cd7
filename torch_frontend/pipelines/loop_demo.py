"""``torch-frontend demo --loop``: loop closure (``pipelines.loop.run_loop``) on a rendered
sequence that revisits places (``testing.synthetic.render_loop_sequence``): :func:`demo_loop`, its
render (``DEMO_RENDER``), options (``DEMO_OPTIONS``) and config."""

from __future__ import annotations

import time as _time
from dataclasses import replace
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from .common import resolve_device
from .inputs import ArraySequence
from .loop_options import LoopOptions, LoopRun

__all__ = ["DEMO_OPTIONS", "DEMO_RENDER", "demo_announcement", "demo_config", "demo_loop", "demo_options",
           "demo_sequence"]

PathLike = Union[str, Path]
_F64 = torch.float64


#: the demo's render (``render_loop_sequence`` arguments): two laps of 64 keyframes, one frame
#: between keyframes for the tracker, and a VIO drift of 0.15 deg of yaw per keyframe plus 3 % of
#: the distance flown (about 20 deg and 0.5 m after two laps)
DEMO_RENDER = dict(laps=2, keyframes_per_lap=64, frames_per_keyframe=2, width=320, height=240,
                   yaw_bias_deg=0.15, trans_drift=0.03)

#: the demo's :class:`LoopOptions`: the render moves ~0.13 m and turns ~5.6 deg per rendered
#: keyframe, so 0.1 m / 5 deg make a keyframe about every rendered keyframe or more often (147
#: keyframes on the 2 x 64 of the render, measured), and lap 2 lies more than VINS's 50 keyframes
#: after lap 1; the vocabulary is trained on the run
DEMO_OPTIONS = dict(train_vocabulary=True, keyframe_distance=0.1, keyframe_angle=5.0, vocabulary_sample=150)


def demo_announcement(options: Optional[LoopOptions] = None, **render_kwargs) -> str:
    """What ``demo --loop`` says it runs, before it renders: laps, frames and size of the render
    (``DEMO_RENDER`` updated by ``render_kwargs``), and the keyframe rule of ``options`` (the
    pipeline picks its keyframes itself: their number is in the summary)."""
    r = {**DEMO_RENDER, **render_kwargs}
    opt = demo_options() if options is None else options
    frames = int(r["laps"]) * int(r["keyframes_per_lap"]) * int(r["frames_per_keyframe"])
    rule = (f"every {opt.keyframe_every} frames" if opt.keyframe_every else
            f"VINS's rule, every {opt.keyframe_distance:g} m or {opt.keyframe_angle:g} deg")
    used = f" (the first {opt.max_frames} used)" if opt.max_frames and opt.max_frames < frames else ""
    return (f"synthetic revisit sequence: {r['laps']} laps, {frames} frames{used} {r['width']}x{r['height']}, "
            f"drifted VIO poses, ground truth; keyframes by {rule}")


def demo_sequence(seed: int = 0, **render_kwargs):
    """The demo's ``testing.SyntheticSequence`` (``DEMO_RENDER`` updated by ``render_kwargs``)."""
    from ..testing.synthetic import render_loop_sequence

    kw = dict(DEMO_RENDER)
    kw.update(render_kwargs)
    return render_loop_sequence(seed=seed, **kw)


def demo_config(seq):
    """A ``TrackerConfig`` for a ``SyntheticSequence``: its camera and size, 100 features 20 px
    apart, every frame published (``freq`` 100 Hz above the render's rate), no CLAHE."""
    from ..config import TrackerConfig

    H, W = int(seq.images.shape[-2]), int(seq.images.shape[-1])
    return TrackerConfig(path="demo (synthetic revisit sequence)", image_width=W, image_height=H,
                         camera=seq.camera, max_cnt=100, min_dist=20, freq=100, F_threshold=1.0, equalize=False)


def demo_options(**changes) -> LoopOptions:
    """The demo's :class:`LoopOptions` (``DEMO_OPTIONS``) with ``changes`` (any option)."""
    return LoopOptions(**{**DEMO_OPTIONS, **changes})


def demo_loop(out: Optional[PathLike] = "out/demo_loop", options: Optional[LoopOptions] = None, *,
              two_sequences: bool = False, sequence=None, seed: int = 0, **render_kwargs) -> LoopRun:
    """``torch-frontend demo --loop``: render the synthetic revisit sequence (``demo_sequence``:
    a room textured with the package's photo, two laps, exact poses, drifted VIO), run
    :func:`run_loop` on it with its drifted VIO poses as the input poses, its true poses as the
    ground truth and its camera-to-body extrinsic, and write the outputs into ``out`` (None:
    nothing written).

    Args:
        options: the run's options (default :func:`demo_options`); ``R_ic``/``t_ic`` default to
            the render's.
        two_sequences: the two laps become two input streams (sequences 1 and 2) that share one
            map (merged by their first loop) or, with ``options.separate_graphs``, keep one
            graph each.
        sequence: an already rendered ``SyntheticSequence`` (else ``demo_sequence(seed, ...)``).
        seed: seed of the render.
        render_kwargs: override ``DEMO_RENDER`` (e.g. smaller ``width``/``height``).
    """
    from ..geometry import R_to_quat
    from ..trajectory import Trajectory
    from .loop import run_loop

    opt = demo_options() if options is None else options
    opt.check()  # before the render, as the device
    resolve_device(opt.device)
    t0 = _time.perf_counter()
    seq = demo_sequence(seed, **render_kwargs) if sequence is None else sequence
    t_render = _time.perf_counter() - t0
    opt = replace(opt, R_ic=seq.R_ic.cpu() if opt.R_ic is None else opt.R_ic,
                  t_ic=seq.t_ic.cpu() if opt.t_ic is None else opt.t_ic)
    cfg = demo_config(seq)
    times = np.asarray(seq.times.cpu(), dtype=np.float64)
    imgs = np.asarray(seq.images.cpu())

    def traj(T, R, sl):
        return Trajectory(torch.as_tensor(times[sl], dtype=_F64), torch.as_tensor(T, dtype=_F64).cpu()[sl],
                          R_to_quat(torch.as_tensor(R, dtype=_F64).cpu()[sl]))

    n = len(times) // 2
    parts = [slice(0, n), slice(n, None)] if two_sequences else [slice(0, None)]
    sources = [ArraySequence(imgs[sl], times[sl], name=f"demo{'' if len(parts) == 1 else f'_lap{i + 1}'}")
               for i, sl in enumerate(parts)]
    poses = [traj(seq.T_vio, seq.R_vio, sl) for sl in parts]
    gts = [traj(seq.T_gt, seq.R_gt, sl) for sl in parts]
    extra = {"demo": {"render_seconds": round(t_render, 6), "frames": int(len(times)),
                      "size": [cfg.image_width, cfg.image_height], "two_sequences": bool(two_sequences)}}
    return run_loop(cfg, sources, poses, out, opt, ground_truth=gts, extra_summary=extra)
