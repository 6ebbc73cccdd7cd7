"""The eager LK (``LKOptions(capturable=False)``, the default and the CPU's path; ``docs/lk.md``).

Per level the template and the gradient systems are computed for the lanes processed at that level
only; the iterations run on a compacted set of still-moving lanes (re-compacted when it halves) and
stop when none is left: one host sync per iteration. Lanes that converged, oscillated, left the
image or failed the eigenvalue test are frozen by masks and written back (:func:`_write_back`).
The per-iteration kernel is :func:`_lk_step` (``torch.compile``-able: ``LKOptions.compile_step``).

Convention:
    As :mod:`.windows`: points-last ``(2, m)`` lanes, window origins ``u = origin + win``,
    grey levels in 1/32 units.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from .. import _tuning
from .._cache import cached
from ..pyramid import Pyramid
from .options import LKOptions
from .windows import (
    _FLT_SCALE,
    _OSC,
    _gradient_system,
    _Level,
    _level_start,
    _template,
    _win_consts,
    _window_diff,
)


def _lk_step(p, pd, act, iv, g, a12, adiag, dinv, lane, J, jview, jstr, offs, k: dict, spanm1,
             first: bool, fixed: bool, eps2: float, osc_thr: float, iv_init: bool = False):
    """One LK iteration for ``m`` lanes (pure tensor function; ``torch.compile``-able).

    ``p``: (2, m) window origins (OpenCV's local ``nextPt``), ``pd``: previous deltas, ``act``: lanes
    still iterating; ``iv`` (m, wh * (ww + 1)) template grey levels x32, ``g`` (m, 2, wh * (ww + 1))
    template derivatives (both in :func:`_pitch` layout), ``a12`` (m,), ``adiag`` (2, m) = ``(A22, A11)``, ``dinv`` (m,) = ``1/det``; ``lane``
    (m,) stream offsets into the flat *padded* next image ``J`` (None for one stream), ``jview`` its
    overlapping ``(wh + 2, pw)`` window view, ``jstr`` (2, 1) = ``(1, Wp)``, ``offs`` ``(wh + 2, pw)`` the
    window's flat offsets (used when ``J`` needs a gradient), ``k`` constants (:func:`_win_consts`), ``spanm1`` (2, 1): allowed
    window origins are ``[-win, size)``. Returns the updated ``p, pd``, the lanes that keep iterating, the lanes that
    moved in this iteration (active and inside) and those that stopped by oscillation (None at j = 0).
    """
    diff, inside = _window_diff(p, iv, lane, J, jview, jstr, offs, k, spanm1, fixed, iv_init)
    moved = act & inside
    b = (g * diff.unsqueeze(1)).sum(2).t() * _FLT_SCALE  # (2, m): b1, b2
    # OpenCV: delta = ((A12 b2 - A22 b1) D, (A12 b1 - A11 b2) D), same float operation order
    delta = (a12 * b.flip(0) - adiag * b) * dinv
    dd = delta.detach().double()
    still = moved & ((dd * dd).sum(0) > eps2)  # OpenCV: stop when delta.ddot(delta) <= epsilon^2 (double)
    osc = None
    if not first:
        osc = still & ((delta.detach() + pd.detach()).abs() <= osc_thr).all(0)
        still = still & ~osc
    m2 = moved.unsqueeze(0)
    return torch.where(m2, p + delta, p), torch.where(m2, delta, pd), still, moved, osc


@cached(8)
def _compiled_step(compile_items: tuple):
    """``torch.compile(_lk_step, **dict(compile_items))`` (``LKOptions.compile_step``: the sorted
    keyword pairs), built once per setting."""
    return torch.compile(_lk_step, **dict(compile_items))


def _step_kernel(opts: LKOptions):
    """The per-iteration kernel of a call: :func:`_lk_step`, or its compiled form when
    ``opts.compile_step`` asks for one (per call: other calls and trackers keep theirs)."""
    return _lk_step if opts.compile_step is False else _compiled_step(opts.compile_step)


def _lk_eager(
    prev: Pyramid,
    nxt: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init: torch.Tensor | None,
    opts: LKOptions,
    top: int,
    want_overflow: bool = False,
    want_capped: bool = False,
) -> Tuple[torch.Tensor, torch.Tensor, Optional[torch.Tensor], Optional[torch.Tensor]]:
    """The eager LK of one group of streams on levels ``top..0``: template and iterations on the
    processed lanes only, the iterations compacted to the still-moving lanes, stopping when none is
    left (host syncs).

    Args:
        prev, nxt: the pyramids; pts, init: ``(B, N, 2)`` (init None: start at pts); valid:
            ``(B, N)`` bool; opts: the settings; top: the top level (capped, see ``track``).
        want_overflow: compute the overflow flag of a budget below ``max_iters``.
        want_capped: return the mask of the lanes still iterating when level 0's budget ended.

    Returns:
        ``next_pts (B, N, 2)``, ``status (B, N)``, ``overflow``: with ``want_overflow`` and some
        budget below ``max_iters`` ``(B,)`` bool, True where a lane of the stream was still
        iterating when a level's budget ended (else None), and ``capped``: with ``want_capped``
        the ``(B N,)`` bool mask above (read by the implicit gradient; no effect on the values),
        else None.
    """
    win, min_eig = opts.win_size, opts.min_eig_threshold
    fixed, eps2 = opts.fixed_point, opts.eps * opts.eps
    B, N, _ = pts.shape
    M = B * N
    dtype, dev = pts.dtype, pts.device
    ww, wh = win
    k = _win_consts(ww, wh, dtype, dev)
    half = k["half"]
    osc_thr = _OSC.get(dtype, 0.01)
    p0 = pts.reshape(M, 2).t().contiguous()  # (2, M): points last throughout
    valid = valid.reshape(M)
    status = valid
    lanes_all = torch.arange(B, device=dev).repeat_interleave(N) if B > 1 else None
    # OpenCV's nextPts[i] (window centre) at the current level's scale
    out = (p0 if init is None else init.reshape(M, 2).t().contiguous()) * (1.0 / (1 << top))
    overflow = capped = None
    step = _step_kernel(opts)

    for level in range(top, -1, -1):
        if level != top:
            out = out * 2.0
        budget = opts.budget_at(level)
        H, W = nxt.levels[level].shape[-2:]
        lv = _Level(prev.padded(level, wh + 1, ww + 1, dtype), nxt.padded(level, wh + 1, ww + 1, dtype), H, W,
                    win, dtype)

        # ---- lanes processed at this level: window origin inside [-win, size)
        uc, frac, proc = _level_start(lv, p0, valid, level, k)
        if level == 0:
            status = status & proc
        ws = proc.nonzero().squeeze(1)  # host sync: template and iterations on these lanes only
        if level == 0 and want_capped:
            capped = torch.zeros(M, dtype=torch.bool, device=dev)
        if ws.numel() == 0:
            continue
        ucl = uc.index_select(1, ws).long()
        frac = frac.index_select(1, ws)
        lanes = None if lanes_all is None else lanes_all.index_select(0, ws)
        o0 = out.index_select(1, ws)
        act = torch.ones_like(ws, dtype=torch.bool)

        # ---- template: previous image window, derivatives, gradient matrix (once per level)
        iv, g = _template(lv, ucl, frac, lanes, fixed, dtype, k, sync=True)
        a11, a12, a22, dinv, ok = _gradient_system(g, act, ww, wh, min_eig)
        adiag = torch.stack((a22, a11))

        # ---- iterations: only the next image is sampled
        # fixed point without gradients: the iterations add the rounding's 1/2 and subtract the
        # template in the interpolation's first multiply-add (one pass less per iteration; exact:
        # integers and multiples of 2^-9 below 2^14)
        iv_init = fixed and _tuning.inplace_ok(iv, lv.Jp, o0)
        if iv_init:
            iv = k["c05"] - iv
        fail = ~ok if level == 0 else None  # level 0: status 0 for failed eigenvalue test / lost lanes
        act = ok
        lane = None if lanes is None else lanes * lv.HWp
        p = o0 - half  # OpenCV's local nextPt (window origin)
        pd = torch.zeros_like(p)
        moved = oscf = None
        st = (lv.Jp, lv.Jview, lv.jstr, lv.offs, k, lv.spanm1)
        for j in range(budget):
            if j > 0:
                n_act = int(act.sum())  # host sync (early exit / compaction)
                if n_act == 0:
                    break
                if 2 * n_act <= act.shape[0]:
                    # write the lanes that stopped back, continue on the active ones: the copy cost
                    # is amortised over the iterations (the set at least halves each time)
                    out, status = _write_back(out, status, ws, o0, p, pd, moved, oscf, fail, half)
                    keep = act.nonzero().squeeze(1)
                    ws = ws.index_select(0, keep)
                    p, pd, o0, a12, adiag, dinv = (t.index_select(-1, keep) for t in (p, pd, o0, a12, adiag, dinv))
                    iv, g = iv.index_select(0, keep), g.index_select(0, keep)  # points first: whole rows
                    lane = None if lane is None else lane.index_select(0, keep)
                    act = torch.ones_like(keep, dtype=torch.bool)
                    moved = act
                    oscf = torch.zeros_like(act)
                    fail = None if fail is None else torch.zeros_like(act)
            act_in = act
            p, pd, act, mv, osc = step(p, pd, act, iv, g, a12, adiag, dinv, lane, *st, j == 0, fixed, eps2, osc_thr,
                                       iv_init)
            if j == 0:
                moved = mv  # a lane moves at j > 0 only if it moved at j = 0
                oscf = torch.zeros_like(mv)
            if osc is not None:
                oscf = oscf | osc
            if fail is not None:
                fail = fail | (act_in & ~mv)  # left the image
        if level == 0 and want_capped:
            capped = capped.index_copy(0, ws, act)
        if want_overflow and budget < opts.max_iters:  # lanes still iterating when the budget ended
            lost = torch.zeros(M, dtype=torch.bool, device=dev).index_copy_(0, ws, act).view(B, N).any(1)
            overflow = lost if overflow is None else overflow | lost
        if moved is not None:
            out, status = _write_back(out, status, ws, o0, p, pd, moved, oscf, fail, half)
        elif fail is not None:
            out, status = _write_back(out, status, ws, o0, p, pd, None, None, fail, half)
    if want_overflow and overflow is None and opts.inexact:
        overflow = torch.zeros(B, dtype=torch.bool, device=dev)
    return out.t().reshape(B, N, 2), status.reshape(B, N), overflow, capped


def _write_back(out, status, ws, o0, p, pd, moved, oscf, fail, half):
    """Results of the lanes ``ws`` (all lanes when None) into the level-wide ``out`` (2, M) and
    ``status``: OpenCV's stored ``nextPts = nextPt + halfWin`` for lanes that moved (minus half the
    last step after an oscillation), the level's starting value otherwise."""
    if moved is not None:
        o = torch.where(moved, p + half, o0)
        o = torch.where(oscf, o - pd * 0.5, o)
    else:
        o = o0
    if ws is None:
        out = o
        if fail is not None:
            status = status & ~fail
    else:
        out = out.index_copy(1, ws, o)
        if fail is not None:
            status = status.index_copy(0, ws, status.index_select(0, ws) & ~fail)
    return out, status

