"""World-frame conventions of loop closure (``loop.world``, ``LoopOptions.up``): the rotations into
a z-up world, the warning for poses far from horizontal, and the acceptance test: the demo's
revisit sequence rotated into a y-down world (KITTI's camera-0 convention) gives, with
``up="-y"``, the z-up run's loop-corrected trajectory, rotated."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from torch_frontend.errors import WorldFrameWarning
from torch_frontend.geometry import R_to_quat
from torch_frontend.loop.world import (
    UP_AXES,
    from_z_up,
    horizontal_problem,
    into_z_up,
    plane_axes,
    to_z_up,
    warn_if_not_horizontal,
)
from torch_frontend.pipelines import loop as loop_run
from torch_frontend.pipelines.common import OptionError
from torch_frontend.pipelines.inputs import ArraySequence
from torch_frontend.trajectory import Trajectory


@pytest.mark.parametrize("up", UP_AXES)
def test_rotation_into_z_up(up):
    R = to_z_up(up)
    u = np.zeros(3)
    u["xyz".index(up[1])] = 1.0 if up[0] == "+" else -1.0
    assert np.array_equal(R @ u, [0.0, 0.0, 1.0]) and np.linalg.det(R) == pytest.approx(1.0)
    a, b = plane_axes(up)  # the plot's axes: R's first two rows, a x b = up
    assert np.array_equal(np.cross(R[0], R[1]), u) and a != b and up[1] not in a + b
    assert plane_axes("-y") == ("+x", "+z") and plane_axes("+z") == ("+x", "+y")


def test_round_trip_and_identity_for_z_up():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(5, 4, generator=g, dtype=torch.float64)
    tr = Trajectory(torch.arange(5.0, dtype=torch.float64), torch.randn(5, 3, generator=g, dtype=torch.float64),
                    q / q.norm(dim=1, keepdim=True))
    assert into_z_up(tr, "+z") is tr
    back = from_z_up(into_z_up(tr, "-y"), "-y")
    assert torch.equal(back.t, tr.t)  # a signed permutation: exact
    torch.testing.assert_close(back.R, tr.R, atol=1e-15, rtol=0)


def _circle(n=40, r=5.0):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([r * np.cos(a), 0.05 * np.sin(3 * a), r * np.sin(a)], 1)  # in the x-z plane (y down/up)


def test_warning_names_the_likely_up_axis():
    p = _circle()
    why = horizontal_problem(p, "+z")
    assert why is not None and "likely y" in why and "-y" in why
    assert horizontal_problem(p, "-y") is None and horizontal_problem(p, "+y") is None
    line = np.stack([np.zeros(20), np.zeros(20), np.linspace(0, 30, 20)], 1)  # KITTI driving straight ahead
    assert "mostly along +z" in horizontal_problem(line, "+z") and horizontal_problem(line, "-y") is None
    drone = np.random.default_rng(0).normal(size=(50, 3))  # 3-D motion: no opinion
    assert horizontal_problem(drone, "+z") is None
    tr = Trajectory(torch.zeros(40, dtype=torch.float64), torch.from_numpy(p), torch.tensor([[1.0, 0, 0, 0]] * 40,
                                                                                            dtype=torch.float64))
    with pytest.warns(WorldFrameWarning, match=r"poses.txt: .*likely y.*4-DoF pose graph takes \+z"):
        warn_if_not_horizontal(tr, "+z", "4dof", "poses.txt")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_not_horizontal(tr, "-y", "4dof", "poses.txt")


def test_up_option_is_checked():
    with pytest.raises(OptionError, match="up: expected"):
        loop_run.LoopOptions(train_vocabulary=True, up="y").check()


@pytest.fixture(scope="module")
def revisit():
    """The demo's two laps, 240 x 180 (five loops accepted: enough for the 4-DoF graph to move)."""
    return loop_run.demo_sequence(keyframes_per_lap=56, frames_per_keyframe=1, width=240, height=180)


def _run(seq, up: str):
    M = torch.as_tensor(to_z_up(up).T)  # z-up world -> the world whose up is `up`
    tt = seq.times.double()

    def traj(T, R):
        return Trajectory(tt.clone(), T.double() @ M.T, R_to_quat(M @ R.double()))

    opt = loop_run.demo_options(progress=False, R_ic=seq.R_ic.cpu(), t_ic=seq.t_ic.cpu(), up=up)
    with warnings.catch_warnings():
        warnings.simplefilter("error", WorldFrameWarning)  # the rotated poses are horizontal in `up`
        return loop_run.run_loop(loop_run.demo_config(seq), [ArraySequence(seq.images.numpy(), tt.numpy())],
                                 [traj(seq.T_vio, seq.R_vio)], None, opt, ground_truth=[traj(seq.T_gt, seq.R_gt)])


def test_y_down_world_gives_the_rotated_result(revisit):
    z, y = _run(revisit, "+z"), _run(revisit, "-y")
    assert z.summary["loops_accepted"] >= 3 and z.summary["ate_after"] < z.summary["ate_before"]
    for key in ("keyframes", "loops_accepted", "loops_rejected"):
        assert y.summary[key] == z.summary[key], key
    assert y.summary["up"] == "-y" and y.summary["ate_after"] == pytest.approx(z.summary["ate_after"], abs=1e-9)
    M = torch.as_tensor(to_z_up("-y").T)
    a, b = z.streams[0], y.streams[0]
    torch.testing.assert_close(b.corrected.t, a.corrected.t @ M.T, atol=1e-8, rtol=0)
    torch.testing.assert_close(b.corrected.R, M @ a.corrected.R, atol=1e-8, rtol=0)
    torch.testing.assert_close(b.vio.t, a.vio.t @ M.T, atol=1e-12, rtol=0)  # outputs in the poses' own world
    # trajectory_top.png: the plane perpendicular to up, so both runs draw the same picture
    from torch_frontend.loop.report import _keyframe_xy

    none = {"before": {0: None}, "after": {0: None}}
    pz, py = _keyframe_xy(z, none)["after"], _keyframe_xy(y, none)["after"]
    assert pz.keys() == py.keys() and all(np.allclose(pz[k], py[k], atol=1e-8) for k in pz)
    # the rotated poses, taken as z-up, are far from horizontal: the warning names y
    with pytest.warns(WorldFrameWarning, match="likely y"):
        warn_if_not_horizontal(y.streams[0].vio, "+z")
