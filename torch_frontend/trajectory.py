"""Trajectory files (TUM, VINS CSV, EuRoC ground truth, KITTI), interpolation, association, SE(3)/Sim(3)
alignment, ATE and synthetic VIO drift.

Convention:
    * A ``Trajectory`` holds N poses of the body (IMU) frame in the world frame, body-to-world as
      VINS's ``(R_w_i, T_w_i)``: ``time (N,)`` float64 seconds, ``t (N, 3)`` float64 metres,
      ``q (N, 4)`` float64 unit quaternions **w-first** ``(w, x, y, z)``. All CPU tensors; times
      strictly increasing.
    * File formats (``read_trajectory(path, format=...)``):

      - ``"tum"``: ``timestamp tx ty tz qx qy qz qw`` per line, whitespace-separated, timestamp in
        seconds, ``#`` comment lines (TUM RGB-D / evo). Note the quaternion is **x, y, z, w** there.
      - ``"vins"``: VINS's ``vins_result_no_loop.csv`` / ``vins_result_loop.csv`` (spec §7.11):
        ``time_ns,px,py,pz,qw,qx,qy,qz,`` with a trailing comma, optionally followed by more
        columns (velocities); ``time_ns`` may be printed with decimals (``%f`` of nanoseconds).
      - ``"euroc"``: EuRoC ``state_groundtruth_estimate0/data.csv``: a ``#timestamp [ns],p_RS_R_x
        [m],...,q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z [],...`` header, then the same first eight
        columns as VINS (OpenVINS's recomputed ground truth uses this layout too).
      - ``"kitti"``: KITTI odometry ``poses/NN.txt``: 12 space-separated values per line, the
        3×4 matrix ``[R | t]`` row by row (camera 0 to world), **no time**: line k (0-based,
        comments not counted) is at ``times[k]`` (the sequence's ``times.txt`` line k, or image
        k's time); ``read_trajectory`` needs ``times``. ``R`` may be off orthonormal by up to
        ``QUAT_TOL`` (printed digits); it becomes the nearest quaternion, normalised.
      - ``"auto"``: the first data line decides: commas -> CSV (``vins``/``euroc``, which share the
        column layout: time in **nanoseconds**, then position, then quaternion w-first),
        8 whitespace-separated values -> TUM, 12 -> KITTI; anything else is a ``DataError``
        naming the formats (``FORMAT_HELP``).

      In every format a first line of only non-numbers is taken as a header without ``#`` and
      skipped; blank lines and lines starting with ``#`` or ``%`` are comments.

    * Quaternions whose norm is off by up to ``QUAT_TOL`` (rounding of printed files) are
      normalised; larger deviations are rejected.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import List, NamedTuple, Tuple, Union

import numpy as np
import torch

from ._atomic import write_text_atomic
from .errors import DataError
from .geometry import R_to_quat, quat_to_R, slerp, yaw_to_R

PathLike = Union[str, Path]

#: largest accepted ``| |q| - 1 |`` of a quaternion read from a file (smaller ones are normalised)
QUAT_TOL = 1e-2

FORMATS = ("auto", "tum", "vins", "euroc", "kitti")

#: the trajectory formats read (``read_trajectory``), for messages
FORMAT_HELP = ("TUM (8 space-separated values: timestamp [s] tx ty tz qx qy qz qw), VINS CSV "
               "(time_ns,px,py,pz,qw,qx,qy,qz, trailing comma), EuRoC ground-truth CSV (#timestamp [ns],"
               "p_RS_R_x [m],...: the same first 8 columns), KITTI (12 space-separated values: [R|t] row by "
               "row, no times: line k pairs with the sequence's times.txt line k, or image k)")

__all__ = [
    "FORMATS",
    "FORMAT_HELP",
    "QUAT_TOL",
    "Trajectory",
    "add_drift",
    "align_se3",
    "associate",
    "ate_rmse",
    "covered",
    "interpolate",
    "read_trajectory",
    "write_tum",
    "write_vins_csv",
]


class Trajectory(NamedTuple):
    """N body-to-world poses: ``time (N,)`` s, ``t (N, 3)`` m, ``q (N, 4)`` wxyz, all float64."""

    time: torch.Tensor
    t: torch.Tensor
    q: torch.Tensor

    @property
    def R(self) -> torch.Tensor:
        """``(N, 3, 3)`` rotation matrices ``R_w_i``."""
        return quat_to_R(self.q)


# ----------------------------------------------------------------------------------------------
# reading

_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


def _is_nonfinite(tok: str) -> bool:
    return tok.lower().lstrip("+-") in ("nan", "inf", "infinity")


def _ns_to_seconds(tok: str) -> float:
    """A nanosecond time as printed (``1403715273262142976`` or ``1403715273262142976.000000``)
    -> seconds; integer part split so the seconds keep every digit float64 can hold."""
    if re.fullmatch(r"\d+(\.\d*)?", tok):
        whole, _, frac = tok.partition(".")
        ns = int(whole)
        return (ns // 1_000_000_000) + ((ns % 1_000_000_000) + (float("0." + frac) if frac else 0.0)) * 1e-9
    return float(tok) * 1e-9


def _is_header(toks: List[str]) -> bool:
    """A header line without ``#``: only non-numbers (and no NaN/inf)."""
    return bool(toks) and not any(_NUM.match(x) or _is_nonfinite(x) for x in toks)


def _detect(path: Path, lines: List[str]) -> str:
    """``"csv"``, ``"tum"`` or ``"kitti"`` from the first data line (a header line skipped)."""
    header = False
    for i, ln in enumerate(lines, start=1):
        s = ln.strip()
        if not s or s.startswith("#") or s.startswith("%"):
            continue
        if "," in s:
            toks = [x.strip() for x in s.split(",")]
            toks = toks[:-1] if toks and toks[-1] == "" else toks
            if not header and _is_header(toks):
                header = True
                continue
            if len(toks) < 8:
                raise DataError(f"{path}:{i}: expected at least 8 comma-separated values (VINS/EuRoC CSV: "
                                f"time_ns,px,py,pz,qw,qx,qy,qz), got {len(toks)}: {s[:80]!r}; the formats read: "
                                f"{FORMAT_HELP}")
            return "csv"
        toks = s.split()
        if not header and _is_header(toks):
            header = True
            continue
        if len(toks) == 12:
            return "kitti"
        if len(toks) != 8:
            raise DataError(f"{path}:{i}: expected 8 space-separated values (TUM) or 12 (KITTI), got "
                            f"{len(toks)}: {s[:80]!r}; the formats read: {FORMAT_HELP}")
        return "tum"
    raise DataError(f"{path}: empty trajectory file (no pose lines)")


def _parse_kitti(path: Path, lines: List[str], times) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """KITTI's ``[R|t]`` lines at ``times`` (s); returns as :func:`_parse`."""
    mats, linenos = [], []
    for i, ln in enumerate(lines, start=1):
        s = ln.strip()
        if not s or s.startswith("#") or s.startswith("%"):
            continue
        toks = s.split()
        if len(toks) != 12 or "," in s:
            raise DataError(f"{path}:{i}: expected 12 space-separated values (KITTI: r11 r12 r13 tx r21 ... tz), "
                            f"got {len(s.split())}: {s[:80]!r}")
        bad = [x for x in toks if not _NUM.match(x)]
        if bad and not mats and _is_header(toks):
            continue
        if bad:
            what = "NaN or infinite value" if any(_is_nonfinite(x) for x in bad) else "not a number"
            raise DataError(f"{path}:{i}: {what}: {bad[0]!r}")
        m = np.asarray([float(x) for x in toks], dtype=np.float64).reshape(3, 4)
        if not np.isfinite(m).all():
            raise DataError(f"{path}:{i}: NaN or infinite value")
        dev = float(np.abs(m[:, :3] @ m[:, :3].T - np.eye(3)).max())
        if dev > QUAT_TOL or np.linalg.det(m[:, :3]) < 0:
            raise DataError(f"{path}:{i}: the 3x3 part is not a rotation (R R^T - I off by {dev:.3g}, allowed "
                            f"{QUAT_TOL:g}; det {np.linalg.det(m[:, :3]):.3g})")
        mats.append(m)
        linenos.append(i)
    if not mats:
        raise DataError(f"{path}: empty trajectory file (no pose lines)")
    if times is None:
        raise DataError(f"{path}: KITTI poses (12 values per line) have no times: give the sequence's times "
                        f"(line k pairs with times.txt line k, or image k)")
    tt = np.asarray(times, dtype=np.float64).reshape(-1)
    if tt.size < len(mats):
        raise DataError(f"{path}: {len(mats)} KITTI poses but only {tt.size} times (line k pairs with times.txt "
                        f"line k, or image k): are they this sequence's poses?")
    a = np.stack(mats)
    q = R_to_quat(torch.from_numpy(a[:, :, :3].copy())).numpy()
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return tt[:len(mats)].copy(), a[:, :, 3].copy(), q, np.asarray(linenos)


def _parse(path: Path, lines: List[str], fmt: str) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Parse every pose line; returns ``time, t, q_wxyz, line_numbers`` (file order)."""
    csv = fmt in ("vins", "euroc", "csv")
    times, poses, linenos = [], [], []
    for i, ln in enumerate(lines, start=1):
        s = ln.strip()
        if not s or s.startswith("#") or s.startswith("%"):
            continue
        if csv:
            toks = [x.strip() for x in s.split(",")]
            if toks and toks[-1] == "":  # VINS's trailing comma
                toks = toks[:-1]
            if len(toks) < 8:
                raise DataError(f"{path}:{i}: expected at least 8 comma-separated values "
                                f"(time_ns,px,py,pz,qw,qx,qy,qz), got {len(toks)}: {s[:80]!r}")
        else:
            toks = s.split()
            if len(toks) != 8 or "," in s:
                raise DataError(f"{path}:{i}: expected 8 space-separated values (TUM: timestamp tx ty tz "
                                f"qx qy qz qw), got {len(s.split())}: {s[:80]!r}")
        head = toks[:8]
        bad = [x for x in head if not _NUM.match(x)]
        if bad and not times and len(bad) == len(head) and not any(_is_nonfinite(x) for x in head):
            continue  # a header line without '#' (e.g. 'timestamp,x,y,z,qw,qx,qy,qz'): skip it
        if bad:
            what = "NaN or infinite value" if any(_is_nonfinite(x) for x in bad) else "not a number"
            raise DataError(f"{path}:{i}: {what}: {bad[0]!r}")
        if csv:
            tsec = _ns_to_seconds(head[0])
            vals = [float(x) for x in head[1:]]  # px py pz qw qx qy qz
            p, q = vals[:3], vals[3:]
        else:
            tsec = float(head[0])
            vals = [float(x) for x in head[1:]]  # tx ty tz qx qy qz qw
            p, q = vals[:3], [vals[6], vals[3], vals[4], vals[5]]
        if not all(math.isfinite(v) for v in [tsec, *p, *q]):  # e.g. 1e999
            raise DataError(f"{path}:{i}: NaN or infinite value")
        n = math.sqrt(sum(v * v for v in q))
        if abs(n - 1.0) > QUAT_TOL:
            raise DataError(f"{path}:{i}: quaternion norm {n:.6g} is not 1 (allowed deviation {QUAT_TOL:g})")
        times.append(tsec)
        poses.append(p + [v / n for v in q])
        linenos.append(i)
    if not times:
        raise DataError(f"{path}: empty trajectory file (no pose lines)")
    a = np.asarray(poses, dtype=np.float64)
    return np.asarray(times, dtype=np.float64), a[:, :3], a[:, 3:], np.asarray(linenos)


def read_trajectory(path: PathLike, format: str = "auto", *, sort: bool = False, times=None) -> Trajectory:
    """Read a trajectory file (TUM, VINS CSV, EuRoC ground truth or KITTI; see the module docstring).

    Convention:
        Returns body-to-world poses, ``time (N,)`` float64 seconds (CSV nanoseconds / 1e9),
        ``t (N, 3)`` float64, ``q (N, 4)`` float64 unit quaternions ``(w, x, y, z)``, in time order.

    Args:
        path: the file.
        format: ``"auto"`` (default: from the content), ``"tum"``, ``"vins"``, ``"euroc"`` or ``"kitti"``.
        sort: if False (default) the times must strictly increase in the file (a decreasing time
            usually means a concatenated or corrupt file); if True lines are sorted by time.
            Duplicate times are rejected either way.
        times: ``(M,)`` seconds of a KITTI file's lines (line k at ``times[k]``; ``M`` >= the number
            of poses): the sequence's ``times.txt`` or its images' times; ignored by the other
            formats, which carry their own.

    Raises:
        DataError: missing/unreadable/empty file, or a bad line (naming ``file:line``): wrong
            column count, not a number, NaN/inf, quaternion norm off by more than ``QUAT_TOL``,
            a duplicate or decreasing time; a first line that fits no format (naming them:
            ``FORMAT_HELP``); a KITTI file without ``times`` or with more lines than times.
        ValueError: unknown ``format``.
    """
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {FORMATS}, got {format!r}")
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise DataError(f"{path}: trajectory file not found") from None
    except IsADirectoryError:
        raise DataError(f"{path}: is a folder, expected a trajectory file") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read trajectory file: {exc.strerror or exc}") from None
    lines = text.splitlines()
    fmt = _detect(path, lines) if format == "auto" else format
    if fmt == "kitti":
        time, t, q, linenos = _parse_kitti(path, lines, times)
    else:
        time, t, q, linenos = _parse(path, lines, fmt)
    if sort:
        order = np.argsort(time, kind="stable")
        time, t, q, linenos = time[order], t[order], q[order], linenos[order]
    dt = np.diff(time)
    if dt.size and not (dt > 0).all():
        k = int(np.flatnonzero(dt <= 0)[0])
        what = "duplicate time" if dt[k] == 0 else "time goes backwards"
        raise DataError(f"{path}:{linenos[k + 1]}: {what} ({time[k + 1]:.9f} s after {time[k]:.9f} s "
                        f"on line {linenos[k]})")
    return Trajectory(torch.from_numpy(time), torch.from_numpy(np.ascontiguousarray(t)),
                      torch.from_numpy(np.ascontiguousarray(q)))


# ----------------------------------------------------------------------------------------------
# writing


def _check_traj(traj: Trajectory) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not isinstance(traj, tuple) or len(tuple(traj)) != 3:
        raise TypeError("traj: expected a Trajectory (time, t, q)")
    time, t, q = (torch.as_tensor(x).detach().to("cpu", torch.float64) for x in traj)
    N = time.shape[0] if time.ndim == 1 else -1
    if time.ndim != 1:
        raise ValueError(f"traj.time: expected shape (N,), got {tuple(time.shape)}")
    if tuple(t.shape) != (N, 3):
        raise ValueError(f"traj.t: expected shape ({N}, 3), got {tuple(t.shape)}")
    if tuple(q.shape) != (N, 4):
        raise ValueError(f"traj.q: expected shape ({N}, 4), got {tuple(q.shape)}")
    return time.numpy(), t.numpy(), q.numpy()


def _seconds_to_ns(sec: float) -> int:
    # split off the whole seconds first: sec * 1e9 in float64 would round to 256 ns near 1.4e18
    whole = math.floor(sec)
    return int(whole) * 1_000_000_000 + int(round((sec - whole) * 1e9))


def write_tum(path: PathLike, traj: Trajectory) -> None:
    """Write ``timestamp tx ty tz qx qy qz qw`` lines (TUM / evo), atomically (temp + rename).

    Timestamp in seconds with 9 decimals, position and quaternion with 9 decimals; a ``#`` header.
    """
    time, t, q = _check_traj(traj)
    lines = ["# timestamp tx ty tz qx qy qz qw\n"]
    for i in range(time.shape[0]):
        w, x, y, z = q[i]
        lines.append(f"{time[i]:.9f} {t[i, 0]:.9f} {t[i, 1]:.9f} {t[i, 2]:.9f} "
                     f"{x:.9f} {y:.9f} {z:.9f} {w:.9f}\n")
    write_text_atomic(Path(path), "".join(lines))


def write_vins_csv(path: PathLike, traj: Trajectory) -> None:
    """Write VINS's ``vins_result_loop.csv`` (spec §7.11), atomically (temp + rename).

    Per pose: ``time·1e9`` with 0 decimals, then ``P.x, P.y, P.z, Q.w, Q.x, Q.y, Q.z`` with 5
    decimals, every value followed by a comma (trailing comma), no header.
    """
    time, t, q = _check_traj(traj)
    lines = []
    for i in range(time.shape[0]):
        vals = ",".join(f"{v:.5f}" for v in (*t[i], *q[i]))
        lines.append(f"{_seconds_to_ns(float(time[i]))},{vals},\n")
    write_text_atomic(Path(path), "".join(lines))


# ----------------------------------------------------------------------------------------------
# interpolation


def _brackets(time: torch.Tensor, qt: torch.Tensor, max_gap: float):
    """Bracketing sample index, its two times and the coverage masks of ``interpolate``'s rule."""
    N = time.shape[0]
    if N == 1:
        i0 = torch.zeros_like(qt, dtype=torch.int64)
        t0 = t1 = time[i0]
    else:
        i0 = (torch.searchsorted(time, qt, right=True) - 1).clamp(0, N - 2)
        t0, t1 = time[i0], time[i0 + 1]
    exact = (qt == t0) | (qt == t1)
    before, after = (qt < time[0]) & ~exact, (qt > time[-1]) & ~exact
    in_gap = ~before & ~after & ~exact & ((t1 - t0) > max_gap)  # never with one pose (t1 = t0)
    return i0, t0, t1, before, after, in_gap


def covered(traj: Trajectory, times, max_gap: float = 0.1) -> torch.Tensor:
    """``(M,)`` bool: which ``times`` (seconds) ``interpolate(traj, times, max_gap)`` accepts: equal
    to a pose time, or between two consecutive poses at most ``max_gap`` seconds apart."""
    time = torch.as_tensor(traj.time, dtype=torch.float64)
    qt = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    if time.shape[0] == 0:
        return torch.zeros(qt.shape, dtype=torch.bool)
    _, _, _, before, after, in_gap = _brackets(time, qt, max_gap)
    return ~(before | after | in_gap) & torch.isfinite(qt)


def interpolate(traj: Trajectory, times, max_gap: float = 0.1, name: str = "poses") -> Trajectory:
    """Poses at ``times``: linear in position, slerp in rotation between the bracketing samples.

    Convention:
        ``times (M,)`` seconds (any real sequence or tensor). A query is covered when it equals a
        sample time, or lies between two consecutive samples at most ``max_gap`` seconds apart.
        Returns a ``Trajectory`` of M poses (float64, ``q`` with ``w >= 0``).

    Raises:
        DataError: naming ``name`` (e.g. the pose file) and the uncovered times: how many lie before
            the first pose, after the last, or inside a gap longer than ``max_gap``.
    """
    time, t, q = (torch.as_tensor(x, dtype=torch.float64) for x in traj)
    qt = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    N = time.shape[0]
    if N == 0:
        raise DataError(f"{name}: no poses to interpolate")
    i0, t0, t1, before, after, in_gap = _brackets(time, qt, max_gap)
    nonfin = ~torch.isfinite(qt)
    bad = before | after | in_gap | nonfin
    if bool(bad.any()):
        parts = []
        if N == 1:
            parts.append(f"there is only one pose (at {float(time[0]):.6f} s)")
        if bool(before.any()):
            parts.append(f"{int(before.sum())} before the first pose ({float(time[0]):.6f} s), "
                         f"e.g. {float(qt[before][0]):.6f} s")
        if bool(after.any()):
            parts.append(f"{int(after.sum())} after the last pose ({float(time[-1]):.6f} s), "
                         f"e.g. {float(qt[after][0]):.6f} s")
        if N > 1 and bool(in_gap.any()):
            k = int(torch.nonzero(in_gap)[0])
            parts.append(f"{int(in_gap.sum())} in gaps longer than max_gap={max_gap:g} s, e.g. "
                         f"{float(qt[k]):.6f} s between poses at {float(t0[k]):.6f} and {float(t1[k]):.6f} s")
        if bool(nonfin.any()):
            parts.append(f"{int(nonfin.sum())} not finite")
        raise DataError(f"{name}: {int(bad.sum())} of {qt.numel()} query times not covered by the poses: "
                        + "; ".join(parts))
    if N == 1:
        return Trajectory(qt.clone(), t.expand(qt.numel(), 3).clone(), q.expand(qt.numel(), 4).clone())
    gap = t1 - t0
    a = ((qt - t0) / gap).clamp(0.0, 1.0)
    pos = t[i0] + a[:, None] * (t[i0 + 1] - t[i0])
    rot = slerp(q[i0], q[i0 + 1], a)
    return Trajectory(qt.clone(), pos, rot)


# ----------------------------------------------------------------------------------------------
# alignment and ATE


def align_se3(est_t: torch.Tensor, ref_t: torch.Tensor, with_scale: bool = False
              ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Umeyama alignment: ``R, t, s`` minimising ``sum |ref_i - (s R est_i + t)|^2``.

    Convention:
        ``est_t, ref_t (N, 3)`` corresponding positions (N >= 3, not all collinear for a unique
        rotation). Returns ``R (3, 3)``, ``t (3,)``, ``s ()`` float64 (``s = 1`` unless
        ``with_scale``), so that ``ref ≈ s * est @ R.T + t``. Differentiable.
    """
    est = torch.as_tensor(est_t, dtype=torch.float64)
    ref = torch.as_tensor(ref_t, dtype=torch.float64, device=est.device)
    if est.ndim != 2 or est.shape[1] != 3:
        raise ValueError(f"est_t: expected shape (N, 3), got {tuple(est.shape)}")
    if ref.shape != est.shape:
        raise ValueError(f"ref_t: expected shape {tuple(est.shape)} (as est_t), got {tuple(ref.shape)}")
    if est.shape[0] < 3:
        raise DataError(f"align_se3: need at least 3 corresponding positions, got {est.shape[0]}")
    mu_e, mu_r = est.mean(0), ref.mean(0)
    de, dr = est - mu_e, ref - mu_r
    n = est.shape[0]
    cov = dr.T @ de / n  # (3, 3) = E[(ref - mu_r)(est - mu_e)^T]
    U, S, Vh = torch.linalg.svd(cov)
    # reflection guard: force det(R) = +1 (Umeyama's S matrix)
    d = torch.sign(torch.linalg.det(U) * torch.linalg.det(Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.ones(3, dtype=torch.float64, device=est.device)
    D = torch.cat([D[:2], d.reshape(1)])
    R = U @ torch.diag(D) @ Vh
    if with_scale:
        var_e = (de * de).sum() / n
        s = (S * D).sum() / var_e.clamp_min(1e-300)
    else:
        s = torch.ones((), dtype=torch.float64, device=est.device)
    t = mu_r - s * (R @ mu_e)
    return R, t, s


def associate(est_time: torch.Tensor, ref_time: torch.Tensor, max_dt: float = 0.02
              ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Pairs ``(i_est, i_ref)`` of nearest times within ``max_dt`` seconds, one-to-one.

    Each estimate takes its nearest reference time; when several estimates take the same
    reference pose only the closest keeps it. Returns two ``(K,)`` int64 index tensors, in
    estimate order.
    """
    et = torch.as_tensor(est_time, dtype=torch.float64)
    rt = torch.as_tensor(ref_time, dtype=torch.float64)
    if et.numel() == 0 or rt.numel() == 0:
        e = torch.zeros(0, dtype=torch.int64)
        return e, e
    j = torch.searchsorted(rt, et).clamp(1, max(rt.numel() - 1, 1))
    lo = (j - 1).clamp(min=0)
    hi = j.clamp(max=rt.numel() - 1)
    d_lo, d_hi = (et - rt[lo]).abs(), (et - rt[hi]).abs()
    nearest = torch.where(d_hi < d_lo, hi, lo)
    dt = torch.minimum(d_lo, d_hi)
    ok = dt <= max_dt
    # one-to-one: the smallest dt per reference pose wins
    best = torch.full((rt.numel(),), float("inf"), dtype=torch.float64)
    best = best.scatter_reduce(0, nearest[ok], dt[ok], reduce="amin")
    ok = ok & (dt == best[nearest])
    # exact ties (two estimates equally close): keep the first
    idx = torch.nonzero(ok).squeeze(1)
    first = torch.ones_like(idx, dtype=torch.bool)
    if idx.numel() > 1:
        r = nearest[idx]
        seen = torch.full((rt.numel(),), idx.numel(), dtype=torch.int64)
        seen = seen.scatter_reduce(0, r, torch.arange(idx.numel()), reduce="amin")
        first = seen[r] == torch.arange(idx.numel())
    idx = idx[first]
    return idx, nearest[idx]


def ate_rmse(est: Trajectory, ref: Trajectory, max_dt: float = 0.02, align: str = "se3") -> float:
    """Absolute trajectory error (RMSE of position differences, metres) after alignment.

    Convention:
        Poses are associated by nearest time within ``max_dt`` seconds (``associate``). ``align``:
        ``"se3"`` (rotation + translation, Umeyama), ``"sim3"`` (+ scale, for monocular), ``"none"``.
        The error of pose i is ``|ref_t_i - (s R est_t_i + t)|``; returns ``sqrt(mean(err^2))``.

    Raises:
        DataError: fewer than 3 associated poses.
    """
    if align not in ("se3", "sim3", "none"):
        raise ValueError(f"align: expected 'se3', 'sim3' or 'none', got {align!r}")
    ie, ir = associate(est.time, ref.time, max_dt)
    if ie.numel() < 3:
        raise DataError(f"ate_rmse: only {ie.numel()} of {len(est.time)} estimated poses have a reference pose "
                        f"within max_dt={max_dt:g} s (need >= 3); do the time ranges "
                        f"[{_span(est.time)}] and [{_span(ref.time)}] overlap, in the same time unit?")
    pe = torch.as_tensor(est.t, dtype=torch.float64)[ie]
    pr = torch.as_tensor(ref.t, dtype=torch.float64)[ir]
    if align != "none":
        R, t, s = align_se3(pe, pr, with_scale=align == "sim3")
        pe = s * pe @ R.T + t
    return float(((pr - pe) ** 2).sum(-1).mean().sqrt())


def _span(time) -> str:
    time = torch.as_tensor(time)
    if time.numel() == 0:
        return "empty"
    return f"{float(time[0]):.3f}, {float(time[-1]):.3f} s"


# ----------------------------------------------------------------------------------------------
# synthetic drift


def add_drift(traj: Trajectory, yaw_deg_per_m: float = 0.1, trans_frac: float = 0.01, seed: int = 0
              ) -> Trajectory:
    """A VIO-like drifted copy of ``traj`` (e.g. EuRoC ground truth) for loop-closure tests.

    Convention (4-DoF, the drift a visual-inertial odometry accumulates, spec §7.8):
        With ``ds_i = |p_i - p_{i-1}|`` and ``s_i = sum ds`` (distance travelled):

        * yaw drift ``psi_i = yaw_deg_per_m * s_i`` degrees;
        * translation: the true step ``p_i - p_{i-1}`` is rotated by the yaw drift reached so far
          and a bias ``trans_frac * ds_i * u`` is added, ``u`` a unit direction drawn from ``seed``;
          so the pure translation error grows as ``trans_frac * s_i``;
        * rotation ``R'_i = Rz(psi_i) R_i``: pitch and roll (VINS ``R2ypr``) are unchanged.

        The first pose is unchanged. Returns a new ``Trajectory`` (same times).
    """
    time, p, q = (torch.as_tensor(x, dtype=torch.float64) for x in traj)
    if p.ndim != 2 or p.shape[1] != 3 or q.shape != (p.shape[0], 4):
        raise ValueError(f"traj: expected t (N, 3) and q (N, 4), got {tuple(p.shape)} and {tuple(q.shape)}")
    g = torch.Generator().manual_seed(int(seed))
    u = torch.randn(3, generator=g, dtype=torch.float64)
    u = u / u.norm()
    step = torch.diff(p, dim=0)  # (N-1, 3)
    ds = step.norm(dim=-1)
    s = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(ds, 0)])
    psi = yaw_deg_per_m * s  # (N,) degrees
    Rz = yaw_to_R(psi)  # (N, 3, 3)
    # step i is taken with the yaw drift reached at its start pose (psi_{i-1})
    dp = (Rz[:-1] @ step[..., None]).squeeze(-1) + trans_frac * ds[:, None] * u
    p2 = torch.cat([p[:1], p[:1] + torch.cumsum(dp, 0)])
    q2 = R_to_quat(Rz @ quat_to_R(q))
    return Trajectory(time.clone(), p2, q2)
