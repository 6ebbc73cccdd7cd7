"""World-frame conventions of loop closure: which axis of the poses' world points up.

Convention:
    * VINS's 4-DoF pose graph optimises x, y, z and the yaw about the world's **+z** (gravity along
      -z, roll and pitch observable from the IMU). Poses whose world has another up axis (KITTI's
      camera-0 world: x right, **y down**, z forward, so up is ``-y``) are rotated into a z-up
      world for the graph and back afterwards (``pipelines.loop``): ``up`` is one of ``UP_AXES``.
    * :func:`to_z_up` is the rotation ``R`` (a signed permutation, exact in floating point) with
      ``R @ up = +z``; its first two rows are the plane perpendicular to up, in an order that
      keeps the view from above right-handed (``+z``: x, y; ``-y``: x, z), which the plots use
      (:func:`plane_axes`).
    * :func:`horizontal_problem` says when a trajectory's motion is far from horizontal in the
      assumed world (a warning, ``errors.WorldFrameWarning``, names the likely up axis): the
      normal of the plane its positions span (smallest principal axis) more than 45° from up, for
      a trajectory that spans a plane (second principal spread >= 10 % of the first, third <= 50 %
      of the second); a trajectory along a line, when the line is within 45° of up.
"""

from __future__ import annotations

import math
import warnings
from typing import Optional, Tuple

import numpy as np
import torch

__all__ = ["UP_AXES", "axis_name", "from_z_up", "horizontal_problem", "into_z_up", "plane_axes", "to_z_up",
           "warn_if_not_horizontal"]

UP_AXES = ("+z", "-z", "+x", "-x", "+y", "-y")
_NAMES = ("x", "y", "z")
#: the in-plane axes (a, b) of each up axis u, with a x b = u
_PLANES = {"+z": ("+x", "+y"), "-z": ("+y", "+x"), "+x": ("+y", "+z"), "-x": ("+z", "+y"),
           "+y": ("+z", "+x"), "-y": ("+x", "+z")}
_COS_45 = math.cos(math.radians(45.0))


def _unit(axis: str) -> np.ndarray:
    if axis not in UP_AXES:
        raise ValueError(f"up: expected one of {', '.join(UP_AXES)}, got {axis!r}")
    v = np.zeros(3)
    v[_NAMES.index(axis[1])] = 1.0 if axis[0] == "+" else -1.0
    return v


def to_z_up(up: str) -> np.ndarray:
    """``(3, 3)`` float64 rotation ``R`` with ``R @ unit(up) = (0, 0, 1)``: rows ``a, b, up`` of
    :func:`plane_axes` (identity for ``"+z"``)."""
    a, b = _PLANES[up] if up in _PLANES else (None, None)
    u = _unit(up)
    return np.stack([_unit(a), _unit(b), u])


def plane_axes(up: str) -> Tuple[str, str]:
    """The two signed world axes of the plane perpendicular to ``up``, as a plot's horizontal and
    vertical axes seen from above (``"+z"``: ``("+x", "+y")``; ``"-y"``: ``("+x", "+z")``)."""
    _unit(up)
    return _PLANES[up]


def axis_name(axis: str) -> str:
    """``"+x"`` -> ``"x"``, ``"-z"`` -> ``"-z"`` (a plot label)."""
    return axis[1] if axis[0] == "+" else axis


def _rotate(traj, R: np.ndarray):
    from ..geometry import R_to_quat
    from ..trajectory import Trajectory

    Rt = torch.as_tensor(R, dtype=torch.float64)
    return Trajectory(traj.time, traj.t.to(torch.float64) @ Rt.T, R_to_quat(Rt @ traj.R.to(torch.float64)))


def into_z_up(traj, up: str):
    """``traj`` (body-to-world ``Trajectory``) with its world rotated so that ``up`` becomes +z
    (``to_z_up(up) @ p``, ``to_z_up(up) @ R_w_i``); the same object for ``"+z"``."""
    return traj if up == "+z" else _rotate(traj, to_z_up(up))


def from_z_up(traj, up: str):
    """The inverse of :func:`into_z_up`: a z-up ``traj`` back in the world whose up is ``up``."""
    return traj if up == "+z" else _rotate(traj, to_z_up(up).T)


def horizontal_problem(positions, up: str) -> Optional[str]:
    """Why the motion of ``positions`` ``(N, 3)`` (metres) is far from horizontal in a world whose
    up is ``up`` (module docstring), naming the likely up axis; None when it looks horizontal, is
    3-D (a drone), or is too short to tell (fewer than 3 positions, or spread below 1 mm)."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] < 3:
        return None
    c = p - p.mean(axis=0)
    _, s, vt = np.linalg.svd(c, full_matrices=False)
    if s[0] < 1e-3 * math.sqrt(p.shape[0]):
        return None
    u = _unit(up)
    if s[1] >= 0.1 * s[0] and s[2] <= 0.5 * s[1]:  # planar motion: its normal should be up
        n = vt[2]
        if abs(float(n @ u)) >= _COS_45:
            return None
        k = int(np.argmax(np.abs(n)))
        tilt = math.degrees(math.acos(min(1.0, abs(float(n @ u)))))
        return (f"the motion lies in a plane whose normal is {tilt:.0f} deg from {up}, close to the "
                f"{_NAMES[k]} axis: the up axis is likely {_NAMES[k]} (-{_NAMES[k]} if {_NAMES[k]} points down, "
                f"as in KITTI's camera frames: -y)")
    if s[1] < 0.1 * s[0] and abs(float(vt[0] @ u)) >= _COS_45:  # a line, along up
        return f"the motion runs mostly along {up} (a vertical line?); in camera frames such as KITTI's the up " \
               f"axis is -y"
    return None


def warn_if_not_horizontal(traj, up: str, mode: str = "4dof", name: str = "poses") -> None:
    """A ``WorldFrameWarning`` when ``traj``'s motion is far from horizontal in the world whose up
    is ``up`` (:func:`horizontal_problem`), saying what it affects for pose graph ``mode`` and how
    to change the axis; ``name`` names the poses."""
    from ..errors import WorldFrameWarning

    why = horizontal_problem(traj.t.detach().cpu().numpy(), up)
    if why:
        effect = (f"the 4-DoF pose graph takes {up} as up (yaw about it, roll and pitch held)" if mode == "4dof"
                  else f"the plots look down along {up}")
        warnings.warn(f"{name}: {why}; {effect}: give the up axis (up=..., --up) or, without an IMU, the 6-DoF "
                      f"graph (mode='6dof', --pose-graph 6dof)", WorldFrameWarning, stacklevel=3)
