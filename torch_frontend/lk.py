"""Batched pyramidal Lucas–Kanade tracking, as ``cv2.calcOpticalFlowPyrLK`` (spec §5.1, §6.2–6.3).

All points of all streams move together: per pyramid level the template windows of the previous
image (grey levels and Scharr derivatives) and the 2x2 gradient matrices are computed once for every
point; each iteration then samples only the next image's ``win x win`` windows (one ``index_select``
of a ``(win+1) x (win+1)`` patch per point, four multiply-adds), solves the 2x2 systems in closed
form and moves the points that are still active. Points that converged, oscillated, left the image
or failed the eigenvalue test are frozen by masks. With ``early_exit`` (default) the template and
the iterations work on the processed lanes only, the iterations on a compacted set of still-moving
lanes (re-compacted when it halves), stopping when none is left: one host sync per iteration. With
``early_exit=False`` exactly ``max_iters`` masked iterations run with no host sync (same results).
The per-iteration kernel ``_lk_step`` is a pure tensor function; :func:`compile_step` swaps in a
``torch.compile`` d version.

Layers: :func:`track_lk` checks and normalises its arguments (into :class:`LKOptions`) and calls
``_track_lk_impl`` (the forward pass) and, with ``forward_backward``, ``_forward_backward_impl``
(VINS-Fusion's FLOW_BACK check); a pipeline that validated once calls those two on its pyramids.
On the CPU the streams run in groups of at most ~1024 points (``_tuning.Strategy.lk_streams``),
elsewhere in one pass. Every fast form (in place, window-view gather, folded template) gives the
reference form's values bit for bit, so results do not depend on whether gradients are recorded.

Performance layout (CPU and GPU alike), measured with ``benchmarks/bench_lk.py`` and py-spy:

* Both images are padded once per frame with BORDER_REFLECT_101 (:meth:`Pyramid.padded`: built when
  a pyramid is the next image, reused when it is the previous one) and every window set is one
  ``index_select`` of whole patches through an overlapping window view, points *first*
  ``(m, rows, cols)``: that gather is a plain strided copy, while a transpose to points-last cost
  more than the gather itself.
* Every window op runs on the *flattened* patch with a row pitch (:func:`_interp_flat`): the four
  bilinear taps are offsets ``0, 1, pitch, pitch + 1`` into one contiguous run per point, so each
  op is one long vectorised run instead of ``rows`` runs of ``cols``; the column that wraps into the
  next row is junk and drops out because the template derivatives there are zero (:func:`_pitch`).
* The template's Scharr derivatives come from the ``(win+3)^2`` grey-level patch it gathers anyway
  (no full-image derivatives: ~5x fewer pixels at level 0 for a few hundred points); their zero
  border is a mask applied only when some window touches the edge.
* OpenCV's integer weights take ~9 ops (``_fixed_weights``). For a few hundred points on CPU the
  cost is the number of small ops (~50 per iteration, ~60 per level template), for thousands the
  memory passes over the windows and the gathers (~10x an elementwise pass per element).

OpenCV behaviour reproduced (``modules/video/src/lkpyramid.cpp``, checked against cv2 4.x):

* pyramids: ``pyrDown`` chain (8-bit rounding per level for uint8 input), levels seen padded by
  the window size with BORDER_REFLECT_101; Scharr derivatives of the previous image computed on the
  unpadded level (REFLECT_101 inside) and seen padded with *zeros* (``BORDER_CONSTANT``) — that is
  what a window hanging over the image edge sees. The number of levels is capped where OpenCV's
  ``buildOpticalFlowPyramid`` stops (next level <= ``win_size``).
* per level ``L..0``: ``prevPt = pts / 2^l``; ``nextPt = init / 2^L`` at the top level, ``2 nextPt``
  below; window origin ``floor(pt - halfWin)`` must lie in ``[-win, W) x [-win, H)`` (else the point
  is skipped at this level, and gets status 0 at level 0); ``G`` and
  ``minEig = (G11 + G22 - sqrt((G11 - G22)^2 + 4 G12^2)) / (2 win_w win_h)`` with ``G`` scaled by
  ``2^-20``; ``minEig < min_eig_threshold`` or ``det(G) < FLT_EPSILON`` skips the level (status 0 at
  level 0); iterations ``delta = G^-1 b``, stop when ``delta.delta <= eps^2``, oscillation rule
  (``j > 0`` and ``|delta + prev_delta| < 0.01`` per axis: result ``-= delta / 2``, stop); hitting
  ``max_iters`` keeps status 1.
* fixed point (``fixed_point=True``, default for 8-bit input): bilinear weights
  ``iw = round(w * 2^14)`` (``iw11 = 2^14 - others``), window grey levels descaled to 1/32 grey
  level with round-half-up (``(s + 2^8) >> 9``), derivatives to integers (``(s + 2^13) >> 14``,
  in int32: exact). With these the results agree with OpenCV bit for bit on >99 % of points and to
  ~1e-4 px on the rest (float summation order of the 2x2 matrix and of ``b``). The rounding is
  applied with a straight-through estimator, so gradients still flow (those of the float
  interpolation). Float images default to plain float bilinear interpolation (differentiable, exact
  gradients; ~1e-4 px median from OpenCV).

Gradients: the iterations are *unrolled* — the autograd graph keeps every iteration of every level
and frozen lanes pass through ``torch.where``. This differentiates exactly the function computed
(including the iteration cap, early stop and coarse-to-fine hand-over), needs no assumption that the
solution is a converged stationary point (with ``eps = 0.01`` it usually is not, to ~1e-2 px) and is
cheap because only few iterations run per point. An implicit-function gradient would need
``dJ/dx`` at the solution and a converged fixed point; it is not used. Bilinear interpolation is
only piecewise smooth: at exactly integer positions (e.g. ``goodFeaturesToTrack`` corners) the
gradient w.r.t. the points is the one-sided (right) derivative.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Tuple, Union

import torch

from . import _tuning
from ._checks import as_image_batch, check_points, check_shape, default_valid
from .errors import ConfigError
from .pyramid import Pyramid, _build_pyramid_impl

__all__ = ["track_lk", "LKOptions", "compile_step"]

_W_BITS = 14
_W_ONE = float(1 << _W_BITS)
_FLT_SCALE = 2.0**-20
_FLT_EPSILON = 1.1920928955078125e-07  # FLT_EPSILON
# OpenCV's oscillation test ``|d| < 0.01`` compares a float with a double. For a float32 ``d`` it is
# ``d <= float32(0.01)`` (float32(0.01) < 0.01 and the next float32 is > 0.01); for float64 ``d``
# it is ``d <= nextafter(0.01, 0)``. Both as ``<=`` on the tensor's own dtype: no float64 copy.
_OSC = {torch.float32: 0.009999999776482582, torch.float64: math.nextafter(0.01, 0.0)}

ImageOrPyramid = Union[torch.Tensor, Pyramid]


def _ste(soft: torch.Tensor, hard: torch.Tensor) -> torch.Tensor:
    """Value of ``hard`` with the gradient of ``soft`` (straight-through estimator). The reference
    form adds ``soft - soft.detach()``, which is exactly 0, so the value is ``hard`` bit for bit; the
    fast form (no gradient needed) is ``hard`` itself."""
    if _tuning.inplace_ok(soft):
        return hard
    return hard.detach() + (soft - soft.detach())


def _soft_weights(frac: torch.Tensor) -> torch.Tensor:
    """``(2, m)`` fractional offsets ``(a, b)`` -> ``(4, m)`` float weights ``w00, w01, w10, w11``
    (``w00 = (1-a)(1-b)``, ``w01 = a(1-b)``, ``w10 = (1-a)b``, ``w11 = ab``): row ``2i + j`` is
    ``ys[i] * xs[j]`` with ``xs = (1-a, a)``, ``ys = (1-b, b)``."""
    t = torch.stack((1 - frac, frac))  # (2: [1-t, t], 2: axis, m)
    return (t[:, 1].unsqueeze(1) * t[:, 0].unsqueeze(0)).reshape(4, -1)


def _fixed_weights(frac: torch.Tensor, k: dict, scale: str = "iw") -> torch.Tensor:
    """OpenCV's integer bilinear weights ``(4, m)`` float32: ``iw00 = cvRound((1-a)(1-b) 2^14)``,
    ``iw01 = cvRound(a(1-b) 2^14)``, ``iw10 = cvRound((1-a)b 2^14)`` evaluated in float32 (half-even,
    as ``torch.round``), ``iw11 = 2^14 - others``; times ``2^-9`` with ``scale="iw9"``.

    Few ops (this runs every iteration): ``t = 2^7 (1-f), 2^7 f`` in one ``addcmul`` (scaling by a
    power of two commutes with float rounding, so ``round(2^7(1-a) * 2^7(1-b))`` is exactly
    OpenCV's ``cvRound((1-a)(1-b) 2^14)``), the outer product through two strided views, and
    ``iw11`` plus the scale in one ``addmm`` (integers: exact)."""
    f = frac.detach()
    if f.dtype != torch.float32:
        f = f.float()
    m = f.shape[-1]
    t = torch.addcmul(k["w_off"], f.unsqueeze(1), k["w_sgn"])  # (axis, [1-f, f], m) x 2^7
    (s0, s1, s2), o = t.stride(), t.storage_offset()
    xs = t.as_strided((1, 2, m), (0, s1, s2), o)  # t[0]
    ys = t.as_strided((2, 1, m), (s1, 0, s2), o + s0)  # t[1]
    iw = torch.round(ys * xs).reshape(4, m)  # rows: ys[i] xs[j] at 2i + j
    return torch.addmm(k[scale + "_b"], k[scale + "_C"], iw)


def _pitch(x: torch.Tensor) -> torch.Tensor:
    """``(m, ..., h, w)`` -> ``(m, ..., h * (w + 1))``: rows padded with one zero column, flattened:
    the iterations' layout (:func:`_interp_flat` with pitch ``w + 1``; the zero derivatives make its
    junk column drop out of ``b``)."""
    return torch.nn.functional.pad(x, (0, 1)).flatten(-2)


@functools.lru_cache(maxsize=128)
def _level_tables(H: int, W: int, ww: int, wh: int, dtype: torch.dtype, device):
    """Per level-size constants (cached: they depend on sizes only).

    Window rows/columns are addressed by ``r = y + wh``, ``c = x + ww`` (``y in [-wh, H + wh)``):
    ``rowin[r]``/``colin[c]`` are 1 inside the image and 0 outside (the derivative windows see
    zeros there: ``calc()`` pads ``derivI`` with BORDER_CONSTANT).
    ``spanm1 = (W + ww - 1, H + wh - 1)``: the largest allowed window origin + ``win``.
    """
    yy = torch.arange(-wh, H + wh, device=device)
    xx = torch.arange(-ww, W + ww, device=device)
    rowin = ((yy >= 0) & (yy < H)).to(dtype)
    colin = ((xx >= 0) & (xx < W)).to(dtype)
    spanm1 = torch.tensor([[W + ww - 1], [H + wh - 1]], dtype=dtype, device=device)
    return rowin, colin, spanm1


@functools.lru_cache(maxsize=32)
def _win_consts(ww: int, wh: int, dtype: torch.dtype, device):
    """Small per-call constants as tensors (an op with a Python scalar costs more than the op)."""
    def t(v, dt=dtype):
        return torch.tensor(v, dtype=dt, device=device)

    f32 = torch.float32
    C = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [-1, -1, -1, 0]], dtype=f32, device=device)
    b = torch.tensor([[0.0], [0.0], [0.0], [_W_ONE]], dtype=f32, device=device)
    return dict(
        w_off=t([[[128.0], [0.0]]], f32),
        w_sgn=t([[[-128.0], [128.0]]], f32),
        iw_C=C, iw_b=b, iw9_C=C * 2.0**-9, iw9_b=b * 2.0**-9,
        half=t([[(ww - 1) * 0.5], [(wh - 1) * 0.5]]),
        win=t([[float(ww)], [float(wh)]]),
        zero=t(0.0),
        c05=t(0.5),
        i8192=torch.tensor(1 << (_W_BITS - 1), dtype=torch.int32, device=device),
        ar_ph=torch.arange(wh + 1, device=device),
        ar_c=torch.arange(ww + 3, device=device).clamp_max(ww),  # junk columns: any in-range index
    )


class _Level:
    """Padded images of one pyramid level (all streams) and the window geometry.

    Both images are padded by ``win + 1`` with BORDER_REFLECT_101 (:meth:`Pyramid.padded`: built
    once per frame when the pyramid is the next image, reused when it is the previous one) and seen
    through overlapping window views, so that every window set is one ``index_select`` of whole
    patches by top-left flat index. Window origins are addressed as ``u = origin + win`` (in
    ``[0, size + win)``); ``u`` is flat index ``u_y Wp + u_x`` of the padded image's patch that starts
    one pixel above and left of the window — the ``(win + 3)^2`` patch the template needs for its
    Scharr derivatives — and ``Wp + 1`` further on for the ``(wh + 2) x (ww + 1)`` patch an iteration
    reads (one spare row for the pitched interpolation).
    """

    def __init__(self, Ip, Jp, H, W, win, dtype):
        ww, wh = win
        self.ww, self.wh = ww, wh
        Hp, Wp = H + 2 * wh + 2, W + 2 * ww + 2
        self.Wp, self.HWp = Wp, Hp * Wp
        self.rowin, self.colin, self.spanm1 = _level_tables(H, W, ww, wh, dtype, Jp.device)
        dev = Jp.device
        # next image: (ph, pw) patches starting at padded (u_y + 1, u_x + 1)
        self.Jp = Jp = Jp.reshape(-1)
        o = Wp + 1
        # one extra row (wh + 2 rows): the iteration interpolates on the flattened patch with a row
        # pitch of pw (see _interp_flat), whose last tap reads one element past wh + 1 rows
        self.Jview = Jp.as_strided((Jp.numel() - o - (wh + 1) * Wp - ww, wh + 2, ww + 1), (1, Wp, 1),
                                   Jp.storage_offset() + o)
        self.jstr = torch.tensor([[1], [Wp]], device=dev)  # int64: exact for any image size
        dy, dx = torch.arange(wh + 2, device=dev), torch.arange(ww + 1, device=dev)
        self.offs = dy[:, None] * Wp + dx[None, :] + o
        # previous image: (ph + 2, pw + 2) patches starting at padded (u_y, u_x)
        self.Ip = Ip = Ip.reshape(-1)
        self.Iview = Ip.as_strided((Ip.numel() - (wh + 2) * Wp - (ww + 2), wh + 3, ww + 3), (1, Wp, 1))
        dy, dx = torch.arange(wh + 3, device=dev), torch.arange(ww + 3, device=dev)
        self.ioffs = dy[:, None] * Wp + dx[None, :]


def _gather(view: torch.Tensor, flat: torch.Tensor, base: torch.Tensor, offs: torch.Tensor) -> torch.Tensor:
    """Windows with top-left flat indices ``base`` (m,) as ``(m, *window)``. Reference form: an
    explicit differentiable index ``base + offs`` into ``flat``; fast form: one ``index_select`` of
    whole patches through the overlapping window view of ``flat`` (the same elements)."""
    if _tuning.inplace_ok(flat):
        return view.index_select(0, base)
    idx = base.view(-1, 1, 1) + offs
    return flat.index_select(0, idx.view(-1)).view(idx.shape)


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
    c05 = k["c05"]
    ip = torch.floor(p.detach())
    u = ip + k["win"]
    # clamp so that lanes that are masked out still read in-bounds memory; unchanged <=> inside
    uc = torch.clamp(u, min=k["zero"], max=spanm1)
    moved = act & (uc == u).all(0)
    # top-left flat index in the padded next image; whole (ph, pw) patches, points first
    base = (uc.long() * jstr).sum(0)
    if lane is not None:
        base = base + lane
    jp = _gather(jview, J, base, offs)  # (m, wh + 2, pw)
    pw = jp.shape[2]
    n = (jp.shape[1] - 2) * pw
    jp = jp.reshape(jp.shape[0], -1)
    frac = p - ip
    # iv, g in the pitched layout (m, wh * pw), (m, 2, wh * pw): g is 0 on the junk column
    if fixed:  # OpenCV: CV_DESCALE(sum iw J, W_BITS1 - 5) = floor(sum iw J / 2^9 + 1/2), exact in float
        w = _fixed_weights(frac, k, "iw9")
        if w.dtype != p.dtype:
            w = w.to(p.dtype)
        if iv_init:  # iv holds 1/2 - template: floor(x + 1/2) - iv = floor(x + (1/2 - iv)), iv integer
            diff = _interp_flat(jp, w, n, pw, 0, iv).floor_()
        elif _tuning.inplace_ok(frac, jp):
            diff = _interp_flat(jp, w, n, pw, 0, c05).floor_().sub_(iv)
        else:  # reference: straight-through, the values above with the gradient of the float version
            jval = _interp_flat(jp, _ste(_soft_weights(frac) * 32.0, w), n, pw, 0, c05)
            diff = _ste(jval - 0.5, torch.floor(jval)) - iv
    else:  # x32: grey levels in 1/32 units (exact scaling)
        diff = _interp_flat(jp, _soft_weights(frac) * 32.0, n, pw) - iv
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


# indirection so that a benchmark / user can swap in ``torch.compile(_lk_step, dynamic=True)``
_STEP = [_lk_step]


def compile_step(enable: bool = True, **compile_kwargs) -> None:
    """Use ``torch.compile`` for the per-iteration kernel (``enable=False`` restores eager)."""
    if enable:
        compile_kwargs.setdefault("dynamic", True)
        _STEP[0] = torch.compile(_lk_step, **compile_kwargs)
    else:
        _STEP[0] = _lk_step


def _interp_flat(f: torch.Tensor, w: torch.Tensor, n: int, pitch: int, off: int = 0,
                 init: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinear values on flattened patches with row pitch ``pitch``: ``f`` ``(m, ..., L)``, ``w``
    ``(4, m)`` -> ``(m, ..., n)``, ``out[j] = [init +] w00 f[o+j] + w01 f[o+j+1] + w10 f[o+j+p] +
    w11 f[o+j+p+1]`` (``o = off``, ``p = pitch``), summed in that order; needs
    ``L >= off + n + pitch + 1``. Output position ``j = r pitch + c`` is the window value at row
    ``r``, column ``c``; columns whose taps wrap into the next patch row are junk (callers drop them
    or give them zero weight). One contiguous run of ``n`` values per point and op: on CPU ~1.7x
    faster than ``rows`` short runs for 21x21 windows."""
    w0, w1, w2, w3 = w.view(w.shape + (1,) * (f.dim() - 1)).unbind(0)
    t0, t1 = f[..., off:off + n], f[..., off + 1:off + 1 + n]
    t2, t3 = f[..., off + pitch:off + pitch + n], f[..., off + pitch + 1:off + pitch + 1 + n]
    out = t0 * w0 if init is None else torch.addcmul(init, t0, w0)
    if _tuning.inplace_ok(f, w, init):  # the same multiply-adds in place
        return out.addcmul_(t1, w1).addcmul_(t2, w2).addcmul_(t3, w3)
    return torch.addcmul(torch.addcmul(torch.addcmul(out, t1, w1), t2, w2), t3, w3)


def _scharr_flat(f: torch.Tensor, pitch: int, n: int) -> torch.Tensor:
    """Scharr ``(Ix, Iy)`` as OpenCV's ``calcSharrDeriv`` (``[3 10 3]`` smoothing across, ``[-1 0 1]``
    difference along) on flattened patches ``f`` ``(m, L)`` with row pitch ``pitch``: ``(m, 2, n + 1)``,
    position ``j = r pitch + c`` holding the derivative at patch pixel ``(r + 1, c + 1)`` (columns
    ``c >= pitch - 2`` junk; the last 3 values 0, so that :func:`_interp_flat` can read one past
    ``n``). Needs ``L >= n + 2 pitch``. Integer taps: exact on integer grey levels (float32 or int32)
    whatever the order of the additions."""
    up, mid, down = f[:, 0:n], f[:, pitch:pitch + n], f[:, 2 * pitch:2 * pitch + n]
    if not _tuning.inplace_ok(f):
        s = torch.add((up + down) * 3, mid, alpha=10)
        d = down - up
        G = torch.stack((s[:, 2:] - s[:, :-2], torch.add((d[:, :-2] + d[:, 2:]) * 3, d[:, 1:-1], alpha=10)), 1)
        return torch.nn.functional.pad(G, (0, 3))
    # fast form: the same operations into one preallocated output
    m = f.shape[0]
    out = f.new_empty((m, 2, n + 1))
    out[:, :, n - 2:].zero_()
    s = torch.add(up, down).mul_(3).add_(mid, alpha=10)
    torch.sub(s[:, 2:], s[:, :-2], out=out[:, 0, :n - 2])
    d = torch.sub(down, up, out=s)  # reuse the buffer
    iy = out[:, 1, :n - 2]
    torch.add(d[:, :-2], d[:, 2:], out=iy)
    iy.mul_(3).add_(d[:, 1:-1], alpha=10)
    return out


def _template(lv: _Level, ucl: torch.Tensor, frac: torch.Tensor, lanes: torch.Tensor | None, fixed: bool,
              dtype, k: dict, sync: bool = True):
    """Windows of the previous image for ``m`` lanes with window origins ``ucl`` (``(2, m)`` long, as
    ``u = origin + win``), fractional offsets ``frac`` and stream indices ``lanes``: grey levels x32
    ``(m, wh * (ww + 1))`` and Scharr derivatives ``(m, 2, wh * (ww + 1))`` in the iterations'
    :func:`_pitch` layout, as OpenCV computes them.

    One ``(win + 3)^2`` patch per lane from the padded level gives both: its centre is the grey-level
    window, its Scharr derivatives (on the reflect-101 padding, so BORDER_REFLECT_101 at the image
    edge, as ``calcSharrDeriv``) the derivative window — no full-image derivatives are needed (for a
    few hundred points the patches are ~5x fewer pixels than the image at level 0). Everything runs
    on the flattened patch (row pitch ``ww + 3``, see :func:`_interp_flat`)."""
    wh, ww = lv.wh, lv.ww
    C = ww + 3  # patch row pitch
    base = ucl[1] * lv.Wp + ucl[0]
    if lanes is not None:
        base = base + lanes * lv.HWp
    P = _gather(lv.Iview, lv.Ip, base, lv.ioffs)  # (m, wh + 3, ww + 3)
    m = P.shape[0]
    f = P.reshape(m, -1)
    nS, nW = (wh + 1) * C, wh * C  # derivative rows (wh + 1), window rows (wh), pitch C
    # the float (soft) windows: the result in float mode, the straight-through gradient in fixed point
    need_soft = not fixed or not _tuning.inplace_ok(P, frac)
    # derivatives: zero where the window hangs over the image edge (BORDER_CONSTANT); with ``sync``
    # one host sync skips the mask pass in the usual case of no window at the edge
    edge = None
    if not sync or bool(((ucl < k["win"].long()) | (ucl >= lv.spanm1.long() - k["win"].long())).any()):
        edge = (lv.rowin.take(ucl[1].unsqueeze(1) + k["ar_ph"]).unsqueeze(2)
                * lv.colin.take(ucl[0].unsqueeze(1) + k["ar_c"]).unsqueeze(1)).view(m, 1, nS)

    def masked(G):
        if edge is None:
            return G
        if _tuning.inplace_ok(G):
            G[..., :nS] *= edge.to(G.dtype)
            return G
        return torch.cat((G[..., :nS] * edge.to(G.dtype), G[..., nS:]), -1)

    def unpitch(x):  # (m, ..., wh * C) -> the iterations' layout (m, ..., wh * (ww + 1))
        return _pitch(x.unflatten(-1, (wh, C))[..., :ww])

    if need_soft:
        PG = masked(_scharr_flat(f, C, nS))
        w = _soft_weights(frac)
        iv, g = _interp_flat(f, w * 32.0, nW, C, C + 1), _interp_flat(PG, w, nW, C)
    if fixed:
        iw = _fixed_weights(frac, k)
        # grey levels: sum(I * iw) / 2^9 is exact in float32 (22 bits); OpenCV rounds half up.
        # derivatives: sum(dI * iw) needs up to 26 bits: int32 (exact, cheaper than float64) or
        # float64 — the descaled integer is OpenCV's CV_DESCALE(., 14) exactly.
        hiv = _interp_flat(f.detach(), (iw * 2.0**-9).to(dtype), nW, C, C + 1, k["c05"]).floor_()
        if dtype == torch.float64:
            PGd = PG.detach() if need_soft else masked(_scharr_flat(f.detach(), C, nS))
            hg = _interp_flat(PGd, iw.double() * 2.0**-14, nW, C, 0, k["c05"]).floor_()
        else:  # CV_DESCALE(s, 14) = (s + 2^13) >> 14
            # from the integer grey levels, also when the float derivatives exist (they truncate to
            # the same integers only for integer grey levels)
            PGi = masked(_scharr_flat(f.detach().int(), C, nS))
            hg = _interp_flat(PGi, iw.int(), nW, C, 0, k["i8192"]).bitwise_right_shift_(_W_BITS).to(dtype)
        if need_soft:
            iv, g = _ste(iv, hiv), _ste(g, hg)
        else:
            iv, g = hiv, hg
    return unpitch(iv), unpitch(g)


def _lk_impl(
    prev: Pyramid,
    nxt: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init: torch.Tensor | None,
    opts: LKOptions,
    top: int,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """The LK of one group of streams on levels ``top..0`` (see :func:`_track_lk_impl`)."""
    win, max_iters, min_eig = opts.win_size, opts.max_iters, opts.min_eig_threshold
    fixed, early_exit, eps2 = opts.fixed_point, opts.early_exit, opts.eps * opts.eps
    B, N, _ = pts.shape
    M = B * N
    dtype, dev = pts.dtype, pts.device
    ww, wh = win
    k = _win_consts(ww, wh, dtype, dev)
    half, winv, zero = k["half"], k["win"], k["zero"]
    osc_thr = _OSC.get(dtype, 0.01)
    p0 = pts.reshape(M, 2).t().contiguous()  # (2, M): points last throughout
    valid = valid.reshape(M)
    status = valid
    lanes_all = torch.arange(B, device=dev).repeat_interleave(N) if B > 1 else None
    # OpenCV's nextPts[i] (window centre) at the current level's scale
    out = (p0 if init is None else init.reshape(M, 2).t().contiguous()) * (1.0 / (1 << top))

    for level in range(top, -1, -1):
        if level != top:
            out = out * 2.0
        H, W = nxt.levels[level].shape[-2:]
        lv = _Level(prev.padded(level, wh + 1, ww + 1, dtype), nxt.padded(level, wh + 1, ww + 1, dtype), H, W,
                    win, dtype)

        # ---- lanes processed at this level: window origin inside [-win, size)
        pp = p0 * (1.0 / (1 << level)) - half
        ip = torch.floor(pp.detach())
        u = ip + winv
        uc = torch.clamp(u, min=zero, max=lv.spanm1)
        proc = valid & (uc == u).all(0)
        if level == 0:
            status = status & proc
        frac = pp - ip
        if early_exit:
            ws = proc.nonzero().squeeze(1)  # host sync: template and iterations on these lanes only
            if ws.numel() == 0:
                continue
            ucl = uc.index_select(1, ws).long()
            frac = frac.index_select(1, ws)
            lanes = None if lanes_all is None else lanes_all.index_select(0, ws)
            o0 = out.index_select(1, ws)
            act = torch.ones_like(ws, dtype=torch.bool)
        else:
            # all lanes, masked; lanes not processed get origin 0 so that nothing reads out of
            # bounds even for non-finite input (they never move: their result stays ``out``)
            ws, lanes, o0, act = None, lanes_all, out, proc
            ucl = torch.where(proc, uc, zero).long()

        # ---- template: previous image window, derivatives, gradient matrix (once per level)
        iv, g = _template(lv, ucl, frac, lanes, fixed, dtype, k, sync=early_exit)
        # (4, m): A11, A12, A21, A22 (the junk column of g is 0). Products and a contiguous sum:
        # ~3x faster on CPU than a bmm of (m, 2, n) matrices
        A = (g.unsqueeze(2) * g.unsqueeze(1)).sum(-1).view(-1, 4).t() * _FLT_SCALE
        a11, a12, _, a22 = A.unbind(0)
        Ad = A.detach()
        with torch.no_grad():  # discrete decision; sqrt at 0 would poison gradients
            d11, d12, _, d22 = Ad.unbind(0)
            det = d11 * d22 - d12 * d12
            dd = d11 - d22
            eig = (d22 + d11 - torch.sqrt(dd * dd + 4.0 * d12 * d12)) / (2.0 * ww * wh)
            ok = act & (eig >= min_eig) & (det >= _FLT_EPSILON)
        if not _tuning.inplace_ok(A):  # the same determinant, differentiable
            det = a11 * a22 - a12 * a12
        # keep masked lanes finite: torch.where differentiates both branches
        dinv = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det))
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
        if ws is None:
            p = torch.where(proc, p, zero)
        pd = torch.zeros_like(p)
        moved = oscf = None
        st = (lv.Jp, lv.Jview, lv.jstr, lv.offs, k, lv.spanm1)
        for j in range(max_iters):
            if ws is not None and j > 0:
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
            p, pd, act, mv, osc = _STEP[0](p, pd, act, iv, g, a12, adiag, dinv, lane, *st,
                                           j == 0, fixed, eps2, osc_thr, iv_init)
            if j == 0:
                moved = mv  # a lane moves at j > 0 only if it moved at j = 0
                oscf = torch.zeros_like(mv)
            if osc is not None:
                oscf = oscf | osc
            if fail is not None:
                fail = fail | (act_in & ~mv)  # left the image
        if moved is not None:
            out, status = _write_back(out, status, ws, o0, p, pd, moved, oscf, fail, half)
        elif fail is not None:
            out, status = _write_back(out, status, ws, o0, p, pd, None, None, fail, half)
    return out.t().reshape(B, N, 2), status.reshape(B, N)


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


def _as_pyramid(x: ImageOrPyramid, name: str, levels: int) -> Pyramid:
    if isinstance(x, Pyramid):
        return x
    return _build_pyramid_impl(as_image_batch(x, name), levels, False, x.dtype == torch.uint8)


def _check_level_sizes(prev: Pyramid, nxt: Pyramid, levels: int) -> None:
    for l in range(min(levels, prev.max_level, nxt.max_level) + 1):
        if prev.levels[l].shape[-2:] != nxt.levels[l].shape[-2:]:
            raise ValueError(
                f"prev/next: level {l} sizes differ: {tuple(prev.levels[l].shape)} vs {tuple(nxt.levels[l].shape)}"
            )


def _level_cap(prev: Pyramid, nxt: Pyramid, max_level: int, win: Tuple[int, int]) -> int:
    """The top level an LK uses: ``max_level`` capped by both pyramids and where OpenCV's
    ``buildOpticalFlowPyramid`` stops (before a level whose size is <= ``win``)."""
    top = min(max_level, prev.max_level, nxt.max_level)
    for l in range(1, top + 1):
        h, w = prev.levels[l].shape[-2:]
        if w <= win[0] or h <= win[1]:
            return l - 1
    return top


@dataclass(frozen=True)
class LKOptions:
    """The parameters of one LK pass, checked and normalised once (as :func:`track_lk` takes them).

    Attributes:
        win_size: window ``(w, h)`` in pixels, each > 2 (an int is taken as ``(w, w)``).
        max_level: top pyramid level, >= 0 (capped by the pyramids and OpenCV's size rule).
        max_iters: iterations per level, clamped to ``[0, 100]`` as OpenCV.
        eps: stop when ``|delta| <= eps`` pixels, clamped to ``[0, 10]`` as OpenCV.
        min_eig_threshold: ``minEigThreshold``.
        fixed_point: OpenCV's 14-bit fixed-point interpolation (8-bit images).
        early_exit: compact to the still-moving points, stop when none is left (one host sync per
            iteration); False: exactly ``max_iters`` masked iterations, no host sync.

    Raises:
        ConfigError: a window <= 2 or a negative / non-int ``max_level``.
    """

    win_size: Tuple[int, int] = (21, 21)
    max_level: int = 3
    max_iters: int = 30
    eps: float = 0.01
    min_eig_threshold: float = 1e-4
    fixed_point: bool = True
    early_exit: bool = True

    def __post_init__(self):
        win = self.win_size
        win = (win, win) if isinstance(win, int) else (int(win[0]), int(win[1]))
        if win[0] <= 2 or win[1] <= 2:
            raise ConfigError(f"win_size must be > 2 in both axes, got {self.win_size!r}")
        if not isinstance(self.max_level, int) or self.max_level < 0:
            raise ConfigError(f"max_level must be an int >= 0, got {self.max_level!r}")
        fields = dict(win_size=win, max_iters=min(max(int(self.max_iters), 0), 100),
                      eps=min(max(float(self.eps), 0.0), 10.0), min_eig_threshold=float(self.min_eig_threshold),
                      fixed_point=bool(self.fixed_point), early_exit=bool(self.early_exit))
        for name, value in fields.items():
            object.__setattr__(self, name, value)


def track_lk(
    prev: ImageOrPyramid,
    next: ImageOrPyramid,
    pts: torch.Tensor,
    valid: torch.Tensor | None = None,
    win_size: Union[int, Tuple[int, int]] = 21,
    max_level: int = 3,
    max_iters: int = 30,
    eps: float = 0.01,
    min_eig_threshold: float = 1e-4,
    init_pts: torch.Tensor | None = None,
    forward_backward: bool = False,
    fb_threshold: float = 0.5,
    fb_max_level: int | None = None,
    *,
    fb_use_initial_flow: bool = True,
    fixed_point: bool | None = None,
    early_exit: bool = True,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sparse pyramidal Lucas–Kanade, as ``cv2.calcOpticalFlowPyrLK`` with the same arguments.

    Args:
        prev: previous image ``(B, 1, H, W)`` / ``(B, H, W)`` (uint8 or float 0..255) or its
            :class:`~torch_frontend.pyramid.Pyramid` (reused across frames; the LK takes the
            derivatives it needs from its own windows, so the pyramid needs no ``grads``).
        next: next image or pyramid, same sizes.
        pts: ``(B, N, 2)`` float, pixels ``(x, y)`` in ``prev``.
        valid: ``(B, N)`` bool, padded lanes False (not tracked, status False). Default all True.
        win_size: window ``int`` or ``(w, h)`` (OpenCV ``winSize``), each > 2.
        max_level: top pyramid level (0 = no pyramid); capped as OpenCV does (level size must stay
            > ``win_size``, and by the levels of given pyramids).
        max_iters, eps: ``TermCriteria(COUNT|EPS, max_iters, eps)``; a point stops when
            ``|delta|^2 <= eps^2`` (OpenCV squares ``epsilon``). Clamped to ``[0, 100]``/``[0, 10]``.
        min_eig_threshold: ``minEigThreshold`` (OpenCV default 1e-4).
        init_pts: ``(B, N, 2)`` initial guess in ``next`` (``OPTFLOW_USE_INITIAL_FLOW``).
        forward_backward: also track back from the result (``next -> prev``) and require both
            statuses and ``|back - pts| <= fb_threshold`` (VINS-Fusion FLOW_BACK).
        fb_threshold: pixels (0.5 in VINS-Fusion).
        fb_max_level: levels of the backward pass (default ``max_level``; VINS-Fusion uses 1 for the
            temporal check, 3 for the stereo one).
        fb_use_initial_flow: backward pass starts at ``pts`` (VINS-Fusion temporal check); set False
            for the stereo check (backward starts at the forward result, no guess).
        fixed_point: emulate OpenCV's 14-bit fixed-point interpolation and rounding. Default: True
            when both inputs are uint8 images (or pyramids built from uint8). Bit-level agreement
            needs float32 ``pts``; gradients use a straight-through estimator for the rounding.
        early_exit: compact the iteration to the still-moving points and stop when none is left —
            one host sync (``nonzero``) per iteration. False runs exactly ``max_iters`` masked
            iterations with no host sync (CUDA graphs / ``torch.compile`` friendly); same results.

    Returns:
        ``next_pts``: ``(B, N, 2)`` pts dtype, pixels in ``next``; ``status``: ``(B, N)`` bool.

    Convention:
        Pixel centres at integer coordinates. ``status`` is False for invalid lanes, for points whose
        level-0 window leaves ``[-win, W) x [-win, H)``, whose level-0 ``minEig`` is below the
        threshold, (with ``forward_backward``) that fail the check. Lanes with status False hold
        whatever OpenCV would leave there (finite); a lane whose ``init_pts`` is not finite gets
        status False (OpenCV: 0) and holds its ``pts`` (OpenCV: the NaN guess). Gradients flow to
        ``pts``, ``init_pts`` and float images (through the pyramid) via unrolled iterations; the
        backward check is discrete (no gradient). The values do not depend on whether gradients are recorded.
    """
    check_points(pts, "pts")
    valid = default_valid(pts, valid, "valid")
    if init_pts is not None:
        check_shape(init_pts, tuple(pts.shape), "init_pts")
    if fixed_point is None:

        def _is8(x):
            return x.rounded if isinstance(x, Pyramid) else as_image_batch(x).dtype == torch.uint8

        fixed_point = _is8(prev) and _is8(next)
    opts = LKOptions(win_size, max_level, max_iters, eps, min_eig_threshold, fixed_point, early_exit)
    fb_level = opts.max_level if fb_max_level is None else fb_max_level
    if not isinstance(fb_level, int) or fb_level < 0:
        raise ConfigError(f"fb_max_level must be an int >= 0, got {fb_max_level!r}")
    levels = max(opts.max_level, fb_level if forward_backward else 0)
    B = pts.shape[0]
    for name, x in (("prev", prev), ("next", next)):
        nb = x.batch if isinstance(x, Pyramid) else as_image_batch(x, name).shape[0]
        if nb != B:
            raise ValueError(f"{name}: batch {nb} does not match pts batch {B}")
    P, Q = _as_pyramid(prev, "prev", levels), _as_pyramid(next, "next", levels)
    _check_level_sizes(P, Q, levels)
    out, status = _track_lk_impl(P, Q, pts, valid, init_pts, opts)
    if forward_backward:
        status = _forward_backward_impl(P, Q, pts, out, status, opts, fb_level, float(fb_threshold),
                                        bool(fb_use_initial_flow))
    return out, status


def _track_lk_impl(
    prev: Pyramid,
    next: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init_pts: torch.Tensor | None,
    opts: LKOptions,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Forward LK (:func:`track_lk` without the backward check), no input checks.

    Args:
        prev, next: pyramids of the B streams, with equal level sizes (as many levels as
            ``opts.max_level`` asks for, or fewer: the LK then uses fewer).
        pts: ``(B, N, 2)`` float, pixels ``(x, y)`` in ``prev``.
        valid: ``(B, N)`` bool.
        init_pts: ``(B, N, 2)`` initial guess in ``next``, or None (start at ``pts``).
        opts: :class:`LKOptions`.

    Returns:
        ``next_pts (B, N, 2)`` (pts dtype, pixels in ``next``) and ``status (B, N)`` bool.

    On the CPU the streams are tracked in groups (``_tuning.Strategy.lk_streams``), so that the
    per-level temporaries (``(win+1)^2 x lanes`` windows and their indices) stay cache friendly; the
    padded levels are built once for the whole batch and shared by the groups as views (a pyramid
    that is ``next`` now keeps them for the call in which it is ``prev``). Elsewhere: one pass.
    """
    top = _level_cap(prev, next, opts.max_level, opts.win_size)
    B, N = pts.shape[:2]
    if init_pts is not None:
        # a non-finite guess (a NaN prediction) would index outside the image: its lane is not
        # tracked and starts at its pts (status False, as OpenCV's 0). Elementwise, no host sync;
        # a finite guess is kept exactly.
        guessed = torch.isfinite(init_pts).all(-1)
        init_pts = torch.where(guessed.unsqueeze(-1), init_pts, pts)
        valid = valid & guessed
    per = _tuning.for_device(pts.device).lk_streams(B, N)
    if per is None:
        return _lk_impl(prev, next, pts, valid, init_pts, opts, top)
    ww, wh = opts.win_size
    for l in range(top + 1):
        for x in (prev, next):
            x.padded(l, wh + 1, ww + 1, pts.dtype)
    outs, sts = [], []
    for s0 in range(0, B, per):
        sl = slice(s0, min(B, s0 + per))
        o, st = _lk_impl(prev.select(sl), next.select(sl), pts[sl], valid[sl],
                         None if init_pts is None else init_pts[sl], opts, top)
        outs.append(o)
        sts.append(st)
    return torch.cat(outs), torch.cat(sts)


def _forward_backward_impl(
    prev: Pyramid,
    next: Pyramid,
    pts: torch.Tensor,
    out: torch.Tensor,
    status: torch.Tensor,
    opts: LKOptions,
    fb_max_level: int,
    fb_threshold: float,
    fb_use_initial_flow: bool,
) -> torch.Tensor:
    """VINS-Fusion's FLOW_BACK check of a forward LK result, no input checks.

    Tracks ``out`` back from ``next`` to ``prev`` (lanes with ``status``; ``opts`` with
    ``max_level = fb_max_level``; starting at ``pts`` when ``fb_use_initial_flow``, else at ``out``)
    and returns ``status & back_status & (|back - pts| <= fb_threshold)`` ``(B, N)`` bool, the
    distance in float64 pixels. ``pts``, ``out``: ``(B, N, 2)``; ``status``: ``(B, N)`` bool.
    A discrete test: no gradient.
    """
    with torch.no_grad():
        init = pts.detach() if fb_use_initial_flow else None
        back, st_b = _track_lk_impl(next, prev, out.detach(), status, init,
                                    dataclasses.replace(opts, max_level=fb_max_level))
        err = torch.linalg.vector_norm((back - pts.detach()).double(), dim=-1)
        return status & st_b & (err <= fb_threshold)
