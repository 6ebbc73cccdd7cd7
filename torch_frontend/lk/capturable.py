"""The capturable LK (``LKOptions(capturable=True)``, the capturable tracker's; ``docs/lk.md``).

Every lane of every stream in one pass, a fixed number of masked iterations per level
(``LKOptions.iter_budget``, default ``max_iters``), no host sync once the per-size constants are
cached, no data-dependent shape, and a kernel count independent of B and of the data: 21 aten ops
per iteration (fixed point on 8-bit levels, float32 points, no gradient; 23 with float64 points;
34 with float interpolation, whose window difference is the eager path's), ~75 per level for the
template (:func:`_template_conv` on the fast path) and the bookkeeping.

* OpenCV's fixed-point sample is exact integer arithmetic, so any formulation gives its values: one
  ``searchsorted`` gives the window's top-left (floor, offset and clamp in one op), one gather the
  ``(wh + 1, ww + 2)`` patch of the next level's grey levels (4 bytes a pixel, once), one grouped
  ``conv2d`` with OpenCV's four integer weights (plus the template as a second channel) and a
  ``floor_divide`` the window difference (:func:`_fast_iterations`); nothing image-sized is built
  per level but the padded level itself.
* Stopping: the step test in float64 via one ``bmm``; signs alternate between iterations so that
  one ``cdist`` (inf norm) gives ``|delta + prevDelta|``; the tests and the running mask are
  columns of a bool buffer whose ``all`` is the next running mask. A lane that stops does not take
  its stopping step in the loop: frozen at the same position it recomputes the same step, and the
  end of the level applies it. A lane still running when a budget below ``max_iters`` ends raises
  its stream's ``overflow`` flag.

Convention:
    As :mod:`.windows`: points-last ``(2, m)`` lanes, window origins ``u = origin + win``,
    grey levels in 1/32 units.
"""

from __future__ import annotations

import contextlib
import math
from typing import Optional, Tuple

import torch
import torch.nn.functional as F

from .. import _tuning
from .._cache import cached
from ..pyramid import Pyramid, pad_reflect101
from .options import LKOptions
from .windows import (
    _OSC,
    _fixed_weights,
    _gradient_system,
    _lane_index,
    _Level,
    _level_start,
    _template,
    _win_consts,
    _window_diff,
)


@cached(64)
def _capturable_tables(H: int, W: int, ww: int, wh: int, dtype: torch.dtype, device):
    """Per level-size constants of the capturable path's fixed-point iterations (cached).

    ``grid`` ``(2, L)``: boundaries for ``searchsorted(grid, p, right=True)``, which gives, per axis,
    ``idx = floor(p) + win + 1`` for window origins inside ``[-win, size)`` (rows ``-win .. size``,
    the shorter padded with ``+inf``), 0 below and ``size + win + 1`` above: one op for the floor,
    the offset, the clamp and the integer conversion. ``idx`` addresses the window's patch in the
    level's patch view (:func:`_fast_iterations`'s ``Jw``). ``inside`` ``(H + wh + 2, W + ww +
    2)`` bool: True at the ``idx`` of inside origins, False at the two margins (outside); the
    iterations gather it straight into their stopping-test buffer."""
    gx = torch.arange(-ww, W + 1, dtype=dtype, device=device)
    gy = torch.arange(-wh, H + 1, dtype=dtype, device=device)
    grid = torch.full((2, max(gx.numel(), gy.numel())), math.inf, dtype=dtype, device=device)
    grid[0, :gx.numel()] = gx
    grid[1, :gy.numel()] = gy
    r = torch.arange(H + wh + 2, device=device)
    c = torch.arange(W + ww + 2, device=device)
    inside = ((r >= 1) & (r <= H + wh))[:, None] & ((c >= 1) & (c <= W + ww))[None, :]
    return grid, inside


@cached(32)
def _capturable_consts(dtype: torch.dtype, device):
    """OpenCV's bilinear weights as one ``addcmul`` + one product (see :func:`_fixed_weights`):
    ``T = off + frac * sgn`` ``(2: x/y, m, 4)``, ``R = round(T[0] T[1])`` = ``(iw00, iw01, iw10,
    2^14)``; ``C`` ``(4, 4)`` (``dtype``): ``R C`` = ``(iw00, iw01, iw10, iw11)`` with OpenCV's
    ``iw11 = 2^14 - iw00 - iw01 - iw10`` (integers: exact in any order); and ``w1`` ``(1, 2, 2, 2)``
    (``dtype``), the convolution weights of a lane before its channel 0 is written: channel 1 (the
    template) ``2^9`` at the kernel's top-left (:func:`_fast_iterations`)."""
    f32 = torch.float32
    off = torch.tensor([[[128.0, 0, 128, 128]], [[128.0, 128, 0, 128]]], dtype=f32, device=device)
    sgn = torch.tensor([[[-128.0, 128, -128, 0]], [[-128.0, -128, 128, 0]]], dtype=f32, device=device)
    C = torch.tensor([[1.0, 0, 0, -1], [0, 1, 0, -1], [0, 0, 1, -1], [0, 0, 0, 1]], dtype=dtype, device=device)
    w1 = torch.zeros((1, 2, 2, 2), dtype=dtype, device=device)
    w1[0, 1, 0, 0] = _DESCALE
    return off, sgn, C, w1


#: OpenCV's ``CV_DESCALE(., W_BITS1 - 5)`` divisor of the fixed-point sample (grey levels x 2^14
#: weights -> 1/32 grey levels)
_DESCALE = 512.0


def _exact_float32(device) -> bool:
    """The fast path's ``mm`` and ``conv2d`` on float32 integers are exact unless CUDA may round their
    inputs to TF32 (10-bit mantissa: OpenCV's 14-bit weights would lose bits); the tracker's step
    runs under :func:`exact_float32`."""
    if torch.device(device).type != "cuda":
        return True
    return not torch.backends.cuda.matmul.allow_tf32 and not (torch.backends.cudnn.enabled
                                                               and torch.backends.cudnn.allow_tf32)


@contextlib.contextmanager
def exact_float32(device):
    """On CUDA, TF32 off for matmuls and cuDNN convolutions while the block runs (the caller's
    settings are restored after it): the capturable LK's window sums need full float32 inputs. A
    no-op elsewhere and where TF32 is already off. Host-side: wrap a compiled or captured step,
    not a traced region."""
    if torch.device(device).type != "cuda" or _exact_float32(device):
        yield
        return
    mm, cudnn = torch.backends.cuda.matmul, torch.backends.cudnn
    old = mm.allow_tf32, cudnn.allow_tf32
    mm.allow_tf32 = cudnn.allow_tf32 = False
    try:
        yield
    finally:
        mm.allow_tf32, cudnn.allow_tf32 = old


@cached(32)
def _template_consts(m: int, device):
    """The convolution template's constants (:func:`_template_conv`, float64, cached per lane
    count): ``K (3, 1, 3, 3)`` the grey level at the centre and OpenCV's Scharr ``(Ix, Iy)``
    (``calcSharrDeriv``: ``[3 10 3]`` across, ``[-1 0 1]`` along), ``bias (3 m,)`` the
    ``CV_DESCALE`` halves per lane ``(2^8, 2^13, 2^13)`` and ``div (3, 1, 1)`` their divisors
    ``(2^9, 2^14, 2^14)``."""
    f64 = torch.float64
    K = torch.zeros((3, 1, 3, 3), dtype=f64, device=device)
    K[0, 0, 1, 1] = 1.0
    K[1, 0] = torch.tensor([[-3.0, 0, 3], [-10, 0, 10], [-3, 0, 3]], dtype=f64, device=device)
    K[2, 0] = torch.tensor([[-3.0, -10, -3], [0, 0, 0], [3, 10, 3]], dtype=f64, device=device)
    half = torch.tensor([2.0**8, 2.0**13, 2.0**13], dtype=f64, device=device)
    return K, half.repeat(m), (half * 2.0).view(3, 1, 1)


def _template_conv(lv: _Level, ucl: torch.Tensor, frac: torch.Tensor, lanes: torch.Tensor, dtype, k: dict):
    """:func:`.windows._template`'s fixed-point template of OpenCV's 8-bit levels, bit for bit, in
    ~18 ops instead of ~38 (the capturable fast path's): grey levels x32 ``(m, wh (ww + 1))`` and
    Scharr derivatives ``(m, 2, wh (ww + 1))`` in the iterations' pitched layout (zero junk column).

    One gather of the ``(wh + 3, ww + 3)`` patches; one convolution gives the centre grey levels and
    both derivatives ``(m, 3, wh + 1, ww + 1)`` (the derivatives zeroed where the window hangs over
    the image edge, as ``calcSharrDeriv``'s BORDER_CONSTANT ``derivI``); one grouped convolution
    with OpenCV's four integer weights per lane and the ``CV_DESCALE`` halves as its bias, and one
    ``floor_divide``, give ``CV_DESCALE(sum iw I, 9)`` and ``CV_DESCALE(sum iw dI, 14)``. In
    float64: every value is an integer below ``2^27`` (weights ``<= 2^14``, derivatives
    ``<= 4080``), exact in any order of the multiply-adds, and ``floor_divide`` by a power of two
    is the arithmetic shift of OpenCV's integers."""
    wh, ww = lv.wh, lv.ww
    m = ucl.shape[1]
    Hp = lv.HWp // lv.Wp
    B = lv.Ip.numel() // lv.HWp
    # (win + 3)^2 patches at every origin u = (ucl[0], ucl[1]) of the padded previous level
    view = lv.Ip.as_strided((B, Hp - wh - 2, lv.Wp - ww - 2, wh + 3, ww + 3), (lv.HWp, lv.Wp, 1, lv.Wp, 1))
    P = view[lanes, ucl[1], ucl[0]].to(torch.float64)  # (m, wh + 3, ww + 3)
    K, bias, div = _template_consts(m, P.device)
    Q = F.conv2d(P.unsqueeze(1), K)  # (m, 3, wh + 1, ww + 1): I at patch (r + 1, c + 1), Ix, Iy there
    edge = (lv.rowin.take(ucl[1].unsqueeze(1) + k["ar_ph"]).unsqueeze(2)
            * lv.colin.take(ucl[0].unsqueeze(1) + k["ar_c"][:ww + 1]).unsqueeze(1))
    # mul_ on the slice, not ``Q[:, 1:] *= ...``, whose __setitem__ adds a copy_ of the slice onto itself
    Q[:, 1:].mul_(edge.unsqueeze(1))
    iw = _fixed_weights(frac, k)  # (4, m): iw00, iw01, iw10, iw11 (float32 integers)
    w = iw.t().to(torch.float64).reshape(m, 1, 1, 2, 2).expand(m, 3, 1, 2, 2).reshape(3 * m, 1, 2, 2)
    S = F.conv2d(Q.view(1, 3 * m, wh + 1, ww + 1), w, bias, groups=3 * m).view(m, 3, wh, ww)
    if torch.compiler.is_compiling():  # the compiler takes no strided out=
        T = F.pad(S.floor_divide_(div), (0, 1)).to(dtype)
    else:  # the integers, exact in ``dtype``, into the pitched layout (m, 3, wh, ww + 1): zero junk column
        T = torch.zeros((m, 3, wh, ww + 1), dtype=dtype, device=P.device)
        torch.floor_divide(S, div, out=T[..., :ww])
    n = wh * (ww + 1)
    return T[:, 0].reshape(m, n), T[:, 1:].reshape(m, 2, n)


# The fast iterations keep the step ``sd`` in float64 (the step tests' type: no conversion op);
# with float32 points its values are float32's (computed in float32, stored exactly). The
# oscillation test ``fl32(|d + d'|) > float32(0.01)`` then reads ``|d + d'|`` in float64:
# ``fl32(fl64(x)) = fl32(x)`` for a sum of two float32 (53 >= 2 * 24 + 2 bits), and ``fl32(y) > t``
# iff ``y > t + ulp(t) / 2`` (``t``'s last bit is 0: the midpoint rounds to ``t``). Likewise
# ``p + delta`` computed in float64 and stored as float32 is float32's correctly rounded sum.
_OSC_TEST = {torch.float32: _OSC[torch.float32] + 2.0**-31, torch.float64: _OSC[torch.float64]}


#: The fast iterations' split of a full budget (``LKOptions.tail_share``): the lanes run in stages,
#: each on a fixed sub-batch of the one before, the running lanes first. OpenCV stops most lanes
#: early (converged or oscillating), so most of the 30 iterations of most lanes are masked no-ops
#: that move bytes and change no bit (a frozen lane recomputes the same step). Stages as ``(first
#: iteration, seats x tail_share / lanes, least seats)``: iterations 8-11 on ``1/tail_share`` of
#: the lanes (at least 16: the split's first form), 12-29 on a quarter of those (at least 8). The
#: second stage is the default's refinement, kept only from ``tail_share`` 8 up (a smaller share
#: asks for more seats). Measured on the golden scenarios' temporal tracking (EuRoC mono, mono8,
#: micro = V1_01's 95 frames, TUM-VI fisheye, the planar flight: 616 level passes of 150-300
#: lanes), the largest share of lanes still running was 0.027 after 8 iterations (V1_01: 2 lanes of
#: 150 past 8, none past 12); on ``tests/test_lk_capturable.py``'s warps of up to 12 px, 2 of 144
#: lanes ran past 12 (one level with 12 px: 40, hence the gate). An earlier stage does not pay:
#: after 4 iterations up to 14 % of the lanes of real frames still run, and over half of a
#: 12-px warp's backward check. A running lane that finds no seat stops there and raises its
#: stream's ``overflow`` flag (the one case where the result may differ from OpenCV's); with
#: seats for all, the result is the full budget's bit for bit. Every stage starts on an even
#: iteration and the budget's rest is even: the iterations alternate two test buffers and the
#: step's sign, so the lanes left behind stay on the parity the level's end reads. Lane-iterations
#: per level at B = 64 (9,600 lanes): 103,200 with the split at 8 alone, 87,000 with both stages.
#: A stage after the first is added only where the stage before it has at least
#: ``_STAGE_MIN_SEATS`` seats: below that a sub-batch's kernels are at the launch floor of a GPU
#: (an H100 moves a 300-lane window gather in ~1.7 us, less than a graph node's 2.5 us), so fewer
#: seats save no time there and the stage's ~16 launches per level would only add to it.
_STAGES = ((8, 1.0, 16), (12, 0.25, 8))
#: the least ``tail_share`` that keeps the stages after the first
_LATE_MIN_SHARE = 8
#: the least seats of the stage before for a stage after the first (lanes; see above)
_STAGE_MIN_SEATS = 512
#: the split's first stage (the tail's start), as the docs and tests name it
_TAIL_FROM = _STAGES[0][0]


def _split_plan(M: int, budget: int, share: int) -> Tuple[Tuple[int, int], ...]:
    """The stages of a level's fast iterations for ``M`` lanes, a budget and ``tail_share``: a tuple
    of ``(first iteration, seats)``, each stage's seats fewer than the stage before it (a stage
    that would seat every lane of the one before is left out); empty: every lane runs every
    iteration (``share`` 1, a budget that is not the full one, or too few lanes)."""
    if share <= 1:
        return ()
    plan, m = [], M
    for k, (j, factor, least) in enumerate(_STAGES):
        if j >= budget or (budget - j) % 2 or (k and (share < _LATE_MIN_SHARE or m < _STAGE_MIN_SEATS)):
            break
        seats = max(least, math.ceil(M * factor / share))
        if seats < m:
            plan.append((j, seats))
            m = seats
    return tuple(plan)


def _staged_iterations(j0: int, budget: int, plan, p, tst, sdp, lanes, xb, wb, g, Cs, dinv_c, tabs, moved0=None):
    """Iterations ``j0 .. budget - 1`` of the fast path on ``m`` lanes, in place in ``p`` and
    ``tst``, with the sub-batch stages ``plan`` (:func:`_split_plan`, the ones from ``j0`` on): the
    lanes run together up to the next stage, whose seats go to the running lanes first (a stable
    sort of the device's own mask: no sync); the sub-batch recurses on the rest of the plan and is
    written back. Returns ``(sd, sdp, moved0, lost)``: as :func:`_fast_iterations`, and ``(m,)``
    bool of the lanes still running at a stage's start without a seat (None without a stage)."""
    j1 = plan[0][0] if plan else budget
    sd, sdp, moved0 = _fast_iterations(j0, j1, p, tst, sdp, lanes, xb, wb, g, Cs, dinv_c, tabs, moved0)
    if not plan:
        return sd, sdp, moved0, None
    m2 = plan[0][1]
    # the frozen lanes would only repeat their step: they stay behind
    running = tst[j1 % 2, 2]
    rows = torch.sort((~running).to(torch.uint8), stable=True).indices[:m2]
    sub_p, sub_tst = p.index_select(1, rows), tst.index_select(2, rows)
    sub_sd, _, _, sub_lost = _staged_iterations(
        j1, budget, plan[1:], sub_p, sub_tst, sdp.index_select(0, rows), lanes.index_select(0, rows),
        xb.index_select(0, rows), wb.index_select(0, rows), g.index_select(0, rows), Cs.index_select(1, rows),
        dinv_c.index_select(0, rows), tabs, moved0)
    # running lanes without a seat stop here (still running: status kept, no stopping step)
    lost = running.index_fill(0, rows, False)
    if sub_lost is not None:
        lost.index_copy_(0, rows, sub_lost)
    p.index_copy_(1, rows, sub_p)
    tst.index_copy_(2, rows, sub_tst)
    sd.index_copy_(0, rows, sub_sd)
    return sd, sdp, moved0, lost


def _fast_iterations(j0: int, j1: int, p, tst, sdp, lanes, xb, wb, g, Cs, dinv_c, tabs, moved0=None):
    """Iterations ``j0 .. j1 - 1`` of the fast (8-bit, fixed-point, no gradient) path on ``m`` lanes,
    in place in ``p (2, m)`` and the test buffers ``tst (2, 4, m)``. ``xb (m, 2, wh + 1, ww + 2)``:
    the convolution's input, channel 0 the window patch (written by each iteration), channel 1 the
    lanes' ``1/2 - template`` (zero-padded); ``wb (m, 2, 2, 2)``: its weights, channel 0 OpenCV's
    (written by each iteration), channel 1 ``2^9`` at the top-left. ``tabs``: the level's ``(Jw,
    grid, inside_tab, w_off, w_sgn, w_C, eps2, osc_cmp)``. Returns ``(sd, sdp, moved0)``: the last
    iteration's step (float64, signed as its parity), the one before, and (when ``j0 == 0``) the
    window test of the first iteration.

    The window difference ``floor(sum iw_ab J_ab / 2^9 + 1/2) - template`` is ``floor_divide(conv,
    2^9)`` of ``conv = sum iw_ab J_ab + 2^9 (1/2 - template)``: integers below ``2^23`` in every
    partial sum (``sum iw_ab = 2^14``, ``J <= 255``, the template below ``2^13``), so exact in
    any order of the multiply-adds and in float32 (the values of the difference image's
    ``baddbmm`` before it, bit for bit). Each iteration writes its patch and weights into the
    lanes' buffers (``out=``: no concatenation); under the compiler, which takes no strided
    ``out=``, they are stacked instead."""
    Jw, grid, inside_tab, w_off, w_sgn, w_C, eps2, osc_cmp = tabs
    m, _, ph, pw = xb.shape
    n = (ph - 1) * (pw - 1)
    dtype = p.dtype
    compiling = torch.compiler.is_compiling()
    sd = None
    for j in range(j0, j1):
        sg = 1.0 - 2.0 * (j % 2)
        t, t1 = tst[j % 2], tst[1 - j % 2]
        # (2, m) int64; the compiler may lay ``p`` out strided (searchsorted then copies it with a warning)
        idx = torch.searchsorted(grid, p.contiguous() if compiling else p, right=True)
        if compiling:
            x = torch.stack((Jw[lanes, idx[1], idx[0]], xb[:, 1]), 1)
        else:  # the (wh + 1, ww + 2) patches into channel 0
            torch.ops.aten.index.Tensor_out(Jw, [lanes, idx[1], idx[0]], out=xb[:, 0])
            x = xb
        # the window test, gathered into its column of the test buffer (a lane outside
        # stops there, as OpenCV's break; its step is finite and never applied)
        torch.ops.aten.index.Tensor_out(inside_tab, [idx[1], idx[0]], out=t[3])
        f = torch.remainder(p, 1.0)  # p - floor(p), exact
        if f.dtype != torch.float32:
            f = f.float()  # OpenCV's weights are float32 (as _fixed_weights)
        iw = torch.addcmul(w_off, f.unsqueeze(-1), w_sgn)  # (2, m, 4)
        iw = torch.mul(iw[0], iw[1]).round_()  # (iw00, iw01, iw10, 2^14)
        if iw.dtype != dtype:
            iw = iw.to(dtype)
        if compiling:
            w = torch.stack((torch.mm(iw, w_C).view(m, 2, 2), wb[:, 1]), 1)
        else:  # (iw00, iw01, iw10, iw11) into channel 0
            torch.mm(iw, w_C, out=wb[:, 0].view(m, 4))
            w = wb
        diff = F.conv2d(x.view(1, 2 * m, ph, pw), w, groups=m).view(m, 1, n).floor_divide_(_DESCALE)
        s = (g * diff).sum(2)  # (m, 2): b / 2^-20, as the eager path's sum
        # (m, 2): sg * delta, computed in dtype and stored as float64 (the tests' type)
        sd = torch.mul((Cs[j % 2] * s.unsqueeze(1)).sum(2), dinv_c,
                       out=torch.empty((m, 2), dtype=torch.float64, device=p.device))
        # OpenCV: continue while delta.ddot(delta) > eps^2 (any dot: exact float32 products, one rounding)
        torch.gt(torch.bmm(sd.unsqueeze(1), sd.unsqueeze(2)).view(m), eps2, out=t[0])
        if j > 0:  # and not |delta + prevDelta| <= 0.01: |sd - sdp| (alternating signs), inf-norm
            osc = torch.cdist(sd.unsqueeze(1), sdp.unsqueeze(1), p=math.inf).view(m)
            torch.gt(osc, osc_cmp, out=t[1])
        else:
            moved0 = t[3].clone()
        run = torch.all(t, 0, out=t1[2])
        # in place, computed in float64 and rounded once: fl32(p + delta) (see _OSC_TEST)
        torch.addcmul(p, sd.t(), run, value=sg, out=p)
        sdp = sd
    return sd, sdp, moved0


def _lk_capturable(
    prev: Pyramid,
    nxt: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init: torch.Tensor | None,
    opts: LKOptions,
    top: int,
    want_capped: bool = False,
) -> Tuple[torch.Tensor, torch.Tensor, Optional[torch.Tensor], Optional[torch.Tensor]]:
    """The capturable LK: all lanes of all streams in one pass, ``opts.budget_at`` masked
    iterations per level, no host sync, an op count independent of the batch and of the data.

    Same results as the eager path (:func:`.eager._lk_eager`) bit for bit (both compute every
    inexact float value, ``b``, the step, the tests, with the same code): a lane that stops
    (OpenCV's loop break) is frozen by a ``running`` mask. Arguments as ``_lk_eager``'s. Returns
    ``next_pts (B, N, 2)``, ``status (B, N)``, with a budget below ``max_iters`` the ``(B,)``
    overflow flag (a lane of the stream still running at the end of some level's budget), else
    None, and with ``want_capped`` the ``(B N,)`` mask of the lanes still running at the end of
    level 0's budget (else None).

    Per iteration (fixed point, no gradient; see the module notes): ``searchsorted`` gives the
    window's top-left in the difference image, one advanced-index gather reads ``(m, wh, ww + 1,
    5)`` windows, one ``baddbmm`` with the weights (``remainder``, ``addcmul``, ``mul``, ``round``)
    plus ``floor`` gives the window difference; with gradients, or float images, the window
    difference is :func:`_window_diff`'s (the eager path's code). Then ``b`` and the step as
    the eager path, the step frozen (0) for lanes outside the image; a lane that stops does
    not take the stopping step in the loop: it is applied at the end of the level from the last
    iteration's step, which a frozen lane recomputes identically at the same position (OpenCV's
    ``nextPt += delta``, and ``-= delta / 2`` after an oscillation). Signs alternate between
    iterations so that one ``cdist`` (inf-norm) gives ``|delta + prevDelta|``.
    """
    win, min_eig = opts.win_size, opts.min_eig_threshold
    fixed, eps2 = opts.fixed_point, opts.eps * opts.eps
    B, N, _ = pts.shape
    M = B * N
    dtype, dev = pts.dtype, pts.device
    ww, wh = win
    k = _win_consts(ww, wh, dtype, dev)
    half, zero = k["half"], k["zero"]
    osc_thr = _OSC.get(dtype, 0.01)
    if M == 0:
        return torch.empty_like(pts), valid.clone(), None, None
    p0 = pts.reshape(M, 2).t().contiguous()  # (2, M): points last
    valid = valid.reshape(M)
    status = valid
    lanes = _lane_index(B, N, dev)
    out = (p0 if init is None else init.reshape(M, 2).t().contiguous()) * (1.0 / (1 << top))
    overflow = capped = None

    for level in range(top, -1, -1):
        if level != top:
            out = out * 2.0
        budget = opts.budget_at(level)
        inexact = budget < opts.max_iters
        H, W = nxt.levels[level].shape[-2:]
        Jpad = nxt.padded(level, wh + 1, ww + 1, dtype)
        lv = _Level(prev.padded(level, wh + 1, ww + 1, dtype), Jpad, H, W, win, dtype)
        uc, frac, proc = _level_start(lv, p0, valid, level, k)
        if level == 0:
            status = status & proc
        # lanes not processed get origin 0 so that nothing reads out of bounds even for non-finite
        # input (they never move: their result stays ``out``)
        ucl = torch.where(proc, uc, zero).long()
        if (fixed and prev.rounded and nxt.rounded and dtype in _OSC_TEST
                and _tuning.inplace_ok(lv.Ip, frac, lv.Jp, out)):
            iv, g = _template_conv(lv, ucl, frac, lanes, dtype, k)
        else:
            iv, g = _template(lv, ucl, frac, lanes, fixed, dtype, k, sync=False)
        a11, a12, a22, dinv, ok = _gradient_system(g, proc, ww, wh, min_eig)
        o0 = out
        if budget == 0:
            if level == 0:
                status = status & ok
                if want_capped:
                    capped = ok
            if inexact:
                lost = ok.view(B, N).any(1)
                overflow = lost if overflow is None else overflow | lost
            continue
        # the window sums are exact for OpenCV's 8-bit levels only
        fast = (fixed and nxt.rounded and dtype in _OSC_TEST and _tuning.inplace_ok(iv, g, lv.Jp, o0)
                and _exact_float32(dev))
        if fixed and _tuning.inplace_ok(iv, lv.Jp, o0):
            iv = k["c05"] - iv  # 1/2 - template: the rounding's 1/2 and the difference in one op
            iv_init = True
        else:
            iv_init = False
        if fast:
            # the coarser level's buffers are dead: dropped before this level's exist (peak memory)
            Jw = tabs = xb = wb = None
            grid, inside_tab = _capturable_tables(H, W, ww, wh, dtype, dev)
            w_off, w_sgn, w_C, w_1 = _capturable_consts(dtype, dev)
            # the next level padded by one more column on each side, so that the (wh + 1, ww + 2)
            # patch of every window origin in [-win - 1, size] (margins included) lies in its own
            # stream's padded image: ``Jw[b, iy, ix]`` is the patch of the window at ``idx = (ix, iy)``
            # (not cached on the pyramid: dropped with the level, while the usual padding is kept
            # for the next frame's template)
            Jp2 = pad_reflect101(nxt.levels[level].to(dtype), wh + 1, ww + 2)
            Hp, Wp2 = Jp2.shape[-2:]
            Jw = Jp2.reshape(-1)[1:].as_strided((B, H + wh + 2, W + ww + 2, wh + 1, ww + 2),
                                                (Hp * Wp2, Wp2, 1, Wp2, 1))
            # the convolution's buffers: channel 1 of the input is 1/2 - template (zero-padded: the
            # weights that read its padding are 0), of the weights 2^9 at the top-left
            xb = torch.zeros((M, 2, wh + 1, ww + 2), dtype=dtype, device=dev)
            xb[:, 1, :wh, :ww + 1] = iv.view(M, wh, ww + 1)
            wb = w_1.expand(M, 2, 2, 2).contiguous()
            dinv_c = dinv.unsqueeze(1)
            osc_cmp = _OSC_TEST[dtype]
        else:
            lane = lanes * lv.HWp
            st = (lv.Jp, lv.Jview, lv.jstr, lv.offs, k, lv.spanm1)
            osc_cmp = osc_thr
        # step = C s dinv with C = ((-A22, A12), (A12, -A11)) 2^-20: the products and the difference
        # as the eager path's (A12 b2 - A22 b1, A12 b1 - A11 b2) (b = s 2^-20, a power of two)
        # even / odd iterations: the step with alternating signs (2, M, 2, 2); the scale and signs
        # are powers of two: exact
        Cs = torch.stack((a22, a12, a12, a11), 1).view(M, 2, 2) * k["step_signs"]
        p = torch.where(proc, o0 - half, zero)  # OpenCV's local nextPt (window origin)
        # the stopping tests as columns (conv, osc, running, inside) of two alternating bool buffers:
        # one ``all`` gives the next running mask (iteration j reads tst[j % 2], writes tst[1 - j % 2])
        tst = torch.empty((2, 4, M), dtype=torch.bool, device=dev)
        tst[0, 1].fill_(True)  # j = 0: no oscillation test
        tst[0, 2].copy_(ok)
        if not fast:  # the window test is in the step (a zero step for lanes outside)
            tst[:, 3].fill_(True)
        sdp = None
        if fast:
            tabs = (Jw, grid, inside_tab, w_off, w_sgn, w_C, eps2, osc_cmp)
            plan = _split_plan(M, budget, opts.tail_share) if budget == opts.max_iters else ()
            # the derivatives are integers of at most |16 x 255| = 4080 (Scharr of 8-bit levels,
            # descaled by weights summing to 2^14): exact in int16, and ``g * diff`` converts them
            # exactly in its kernel. Read by every iteration: half the bytes of float32 (the
            # products' pass moves 20 % less), one conversion per level
            g = g.to(torch.int16)
            sd, sdp, moved0, lost = _staged_iterations(0, budget, plan, p, tst, sdp, lanes, xb, wb, g, Cs, dinv_c,
                                                       tabs)
            if lost is not None:
                lost = lost.view(B, N).any(1)
                overflow = lost if overflow is None else overflow | lost
            j = budget - 1
            sg = 1.0 - 2.0 * (j % 2)
            t, run = tst[j % 2], tst[1 - j % 2, 2]
        else:
            for j in range(budget):
                sg = 1.0 - 2.0 * (j % 2)
                t, t1 = tst[j % 2], tst[1 - j % 2]
                diff, inside = _window_diff(p, iv, lane, *st, fixed, iv_init)
                s = (g * diff.unsqueeze(1)).sum(2)  # (m, 2): b / 2^-20, as the eager path's sum
                sd = (Cs[j % 2] * s.unsqueeze(1)).sum(2) * (dinv * inside.to(dtype)).unsqueeze(1)
                so = sd.detach()
                dd = so.double()
                # OpenCV: continue while delta.ddot(delta) > eps^2 (any dot: exact float32 products, one rounding)
                torch.gt(torch.bmm(dd.unsqueeze(1), dd.unsqueeze(2)).view(M), eps2, out=t[0])
                if j > 0:  # and not |delta + prevDelta| <= 0.01: |sd - sdp| (alternating signs), inf-norm
                    osc = torch.cdist(so.unsqueeze(1), sdp.unsqueeze(1), p=math.inf).view(M)
                    torch.gt(osc, osc_cmp, out=t[1])
                else:
                    moved0 = inside
                run = torch.all(t, 0, out=t1[2])
                if not _tuning.inplace_ok(p, sd):
                    run = run.clone()  # autograd keeps the mask, the buffer is rewritten two iterations on
                p = torch.addcmul(p, sd.t(), run, value=sg)
                sdp = so
        conv = t[0]  # the last iteration's step test: for a frozen lane, that of its stopping step
        # ---- end of level: the stopping step of the lanes that stopped inside the image
        stopped = ok > run  # ok & ~run: converged, oscillated, or left the image
        if fast:
            inside = t[3]  # the last iteration's: where the frozen lanes are
        left = stopped > inside  # stopped outside: left the image (OpenCV: status 0 at level 0)
        took = stopped & inside  # converged or oscillated: take the stopping step
        if fast:  # float64 steps: float32 results as above
            o = torch.addcmul(p, sd.t(), took, value=sg, out=torch.empty_like(p)) + half
            o = torch.addcmul(o, sd.t(), took & conv, value=-0.5 * sg, out=o)  # oscillated: |delta|^2 > eps^2
        else:
            o = torch.addcmul(p, sd.t(), took, value=sg) + half
            o = torch.addcmul(o, sd.t(), took & conv, value=-0.5 * sg)
        out = torch.where(ok & moved0, o, o0)  # lanes that never moved keep the level's start
        if level == 0:
            status = status & (ok > left)
            if want_capped:
                capped = run.clone()
        if inexact:
            lost = run.view(B, N).any(1)
            overflow = lost if overflow is None else overflow | lost
    return out.t().reshape(B, N, 2), status.reshape(B, N), overflow, capped
