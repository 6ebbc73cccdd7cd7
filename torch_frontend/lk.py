"""Batched pyramidal Lucas–Kanade tracking, as ``cv2.calcOpticalFlowPyrLK`` (spec §5.1, §6.2–6.3).

All points of all streams move together: per pyramid level the template windows of the previous
image (grey levels and Scharr derivatives) and the 2x2 gradient matrices are computed once for every
point; each iteration then samples only the next image's ``win x win`` windows (one gather of a
``(win+1) x (win+1)`` patch per point through an overlapping-window view, plus four multiply-adds on
the flattened patch), solves the 2x2 systems in closed form and moves the points that are still
active. Points that converged, oscillated, left the image or failed the eigenvalue test are frozen
by masks. With ``early_exit`` (default) the iteration works on a compacted set of still-moving lanes
(re-compacted when it halves) and stops when none is left: one host sync per iteration. With
``early_exit=False`` exactly ``max_iters`` masked iterations run with no host sync (same results).
The per-iteration kernel ``_lk_step`` is a pure tensor function; :func:`compile_step` swaps in a
``torch.compile`` d version.

OpenCV behaviour reproduced (``modules/video/src/lkpyramid.cpp``, checked against cv2 4.x):

* pyramids: ``pyrDown`` chain (8-bit rounding per level for uint8 input), levels padded by the
  window size with BORDER_REFLECT_101; Scharr derivatives of the previous image computed on the
  unpadded level (REFLECT_101 inside) and padded with *zeros* (``BORDER_CONSTANT``) — that is what
  a window hanging over the image edge sees. The number of levels is capped where OpenCV's
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
  level with round-half-up (``(s + 2^8) >> 9``), derivatives to integers (``(s + 2^13) >> 14``).
  With these the results agree with OpenCV bit for bit on >99 % of points and to ~1e-5 px on the
  rest (float summation order). The rounding is applied with a straight-through estimator, so
  gradients still flow (those of the float interpolation). Float images default to plain float
  bilinear interpolation (differentiable, exact gradients; ~1e-4 px median from OpenCV).

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

from typing import Tuple, Union

import torch
import torch.nn.functional as F

from ._checks import as_image_batch, check_points, check_shape, default_valid
from .errors import ConfigError
from .pyramid import Pyramid, build_pyramid, pad_reflect101

__all__ = ["track_lk", "compile_step"]

_W_BITS = 14
_FLT_SCALE = 2.0**-20
_FLT_EPSILON = 1.1920928955078125e-07  # FLT_EPSILON

ImageOrPyramid = Union[torch.Tensor, Pyramid]


def _ste(soft: torch.Tensor, hard: torch.Tensor) -> torch.Tensor:
    """Value of ``hard`` with the gradient of ``soft`` (straight-through); plain ``hard`` when no
    gradient is needed (saves the extra ops)."""
    if soft.requires_grad:
        return soft + (hard - soft).detach()
    return hard


def _fixed_weights(frac: torch.Tensor) -> torch.Tensor:
    """OpenCV's integer bilinear weights ``(M, 4)`` (float32 holding integers): ``iw00 =
    cvRound((1-a)(1-b) 2^14)``, ``iw01 = cvRound(a(1-b) 2^14)``, ``iw10 = cvRound((1-a)b 2^14)``
    evaluated in float32 (half-even, as ``torch.round``), ``iw11 = 2^14 - others``."""
    f = frac.detach().float()
    xs = torch.stack([1 - f, f], dim=2)  # (M, axis, [1-t, t])
    w = (xs[:, 1, :2, None] * xs[:, 0, None, :]).reshape(-1, 4)[:, :3]
    iw = torch.round(w * float(1 << _W_BITS))
    return torch.cat([iw, float(1 << _W_BITS) - iw.sum(1, keepdim=True)], dim=1)


def _bilinear_weights(frac: torch.Tensor, fixed: bool) -> torch.Tensor:
    """``(M, 2)`` fractional offsets ``(a, b)`` -> ``(M, 4)`` weights ``w00, w01, w10, w11``
    (``w00 = (1-a)(1-b)``, ``w01 = a(1-b)``, ``w10 = (1-a)b``, ``w11 = ab``).

    Fixed point: the values are OpenCV's ``iw / 2^14`` (exact in float), the gradient that of the
    float weights (straight-through).
    """
    xs = torch.stack([1 - frac, frac], dim=2)
    w = (xs[:, 1, :, None] * xs[:, 0, None, :]).reshape(-1, 4)
    if not fixed:
        return w
    return _ste(w, (_fixed_weights(frac) * (1.0 / (1 << _W_BITS))).to(w.dtype))


def _interp_flat(pf: torch.Tensor, w: torch.Tensor, pw: int, init: float | None = None) -> torch.Tensor:
    """Bilinear windows on flattened patches.

    ``pf``: ``(..., M, (wh+1) * pw)`` row-major ``(wh+1) x pw`` patches (``pw = ww + 1``); ``w``:
    ``(M, 4)`` weights. Returns ``(..., M, K)`` with ``K = wh * pw - 1``: entry ``q = r * pw + c`` is
    the window value at row ``r``, column ``c`` for ``c < ww``; ``c == ww`` is a junk column (it mixes
    two rows) that callers neutralise by zero derivative weights. Working on the flat patch turns the
    four shifted terms into contiguous slices (about twice as fast as 2-D slicing). Exact in fixed
    point whatever the summation order. ``init`` is added first (OpenCV's rounding constant).
    """
    K = pf.shape[-1] - pw - 1
    wv = w.t().unsqueeze(-1)  # (4, M, 1)
    if pf.is_floating_point():
        if init is None:
            out = pf[..., :K] * wv[0]
        else:
            out = torch.addcmul(torch.full((), init, dtype=pf.dtype, device=pf.device), pf[..., :K], wv[0])
        out = torch.addcmul(out, pf[..., 1:K + 1], wv[1])
        out = torch.addcmul(out, pf[..., pw:pw + K], wv[2])
        return torch.addcmul(out, pf[..., pw + 1:pw + 1 + K], wv[3])
    out = pf[..., :K] * wv[0]
    if init is not None:
        out += int(init)
    out += pf[..., 1:K + 1] * wv[1]
    out += pf[..., pw:pw + K] * wv[2]
    out += pf[..., pw + 1:pw + 1 + K] * wv[3]
    return out


class _Level:
    """Padded, flattened images of one pyramid level (all streams) and the patch geometry."""

    def __init__(self, I, grads, J, win, batch_of_lane):
        ww, wh = win
        B, _, H, W = J.shape
        self.H, self.W, self.ww, self.wh = H, W, ww, wh
        Hp, Wp = H + 2 * wh, W + 2 * ww
        self.Wp, self.pw, self.ph = Wp, ww + 1, wh + 1
        dev = J.device
        # next image: (B*Hp*Wp,), BORDER_REFLECT_101 padding as buildOpticalFlowPyramid
        self.J = pad_reflect101(J, wh, ww).reshape(-1)
        # template sources, each flat (B*Hp*Wp,): grey levels (REFLECT_101) and derivatives computed on
        # the unpadded level with the border filled with zeros (calc() pads derivI BORDER_CONSTANT)
        self.IG = [pad_reflect101(I, wh, ww).reshape(-1)] + [
            F.pad(grads[:, c:c + 1], (ww, ww, wh, wh)).reshape(-1) for c in range(2)]
        dy = torch.arange(self.ph, device=dev)
        dx = torch.arange(self.pw, device=dev)
        self.offs = (dy[:, None] * Wp + dx[None, :]).reshape(-1)
        self.lane_base = batch_of_lane * (Hp * Wp)
        self.K = wh * self.pw - 1
        # 0 on the junk column of the flat window layout (see _interp_flat)
        self.colmask = (torch.arange(self.K, device=dev) % self.pw < ww).to(J.dtype)

    def inside(self, ip: torch.Tensor) -> torch.Tensor:
        x, y = ip[:, 0], ip[:, 1]
        return (x >= -self.ww) & (x < self.W) & (y >= -self.wh) & (y < self.H)

    def base(self, ip: torch.Tensor, lane_base: torch.Tensor) -> torch.Tensor:
        # clamp so that lanes that will be masked out still read in-bounds memory
        x = ip[:, 0].clamp(-self.ww, self.W - 1).long() + self.ww
        y = ip[:, 1].clamp(-self.wh, self.H - 1).long() + self.wh
        return lane_base + y * self.Wp + x

    def patches(self, flat: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """``(L,)`` flat padded image, ``(m,)`` top-left indices -> ``(m, ph*pw)`` patches."""
        if flat.requires_grad:  # differentiable gather through an explicit (m, ph*pw) index
            idx = (base[:, None] + self.offs[None, :]).reshape(-1)
            return flat.index_select(0, idx).view(base.shape[0], -1)
        return _window_view(flat, self.Wp, self.ph, self.pw).index_select(0, base).flatten(-2)


def _window_view(flat: torch.Tensor, Wp: int, ph: int, pw: int) -> torch.Tensor:
    """``(n, ph, pw)`` overlapping view of a 1-D flat padded image: entry ``s`` is the patch whose
    top-left element is flat index ``s`` (no copy; gathering whole patches needs no big index)."""
    n = flat.shape[0] - ((ph - 1) * Wp + pw - 1)
    return flat.as_strided((n, ph, pw), (flat.stride(0), Wp * flat.stride(0), flat.stride(0)), flat.storage_offset())


def _lk_step(p, o, pd, act, iv, g, a12, adiag, dinv, lane_base, J, jview, offs, half, lo, hi, strides,
             pw: int, first: bool, fixed: bool, eps2: float):
    """One LK iteration for a set of ``m`` lanes (pure tensor function; ``torch.compile``-able).

    ``p``: (m, 2) window origins (OpenCV's local ``nextPt``), ``o``: (m, 2) stored results
    (``nextPts``), ``pd``: previous deltas, ``act``: lanes still iterating; ``iv`` (m, K) template
    grey levels x32, ``g`` (m, 2, K) template derivatives (0 on the junk column), ``a12`` (m, 1),
    ``adiag`` (m, 2) = ``(A22, A11)``, ``dinv`` (m, 1) = ``1/det``. ``lo``/``hi``: allowed window
    origins ``[-win, size)``; ``strides``: ``(1, Wp)``. Returns the updated ``p, o, pd``, the lanes
    that keep iterating and the lanes that left the image in this iteration.
    """
    ip = torch.floor(p.detach())
    inb = ((ip >= lo) & (ip < hi)).all(1)
    lost = act & ~inb
    act = act & inb
    w = _bilinear_weights(p - ip, fixed) * 32.0  # x32: grey levels in 1/32 units (exact scaling)
    # clamp so that lanes that are masked out still read in-bounds memory
    base = lane_base + ((torch.minimum(torch.maximum(ip, lo), hi - 1) - lo) * strides).sum(1).long()
    if jview is not None:  # overlapping-window view: gathers whole patches, no (m, K) index
        jp = jview.index_select(0, base).flatten(1)
    else:
        jp = J.index_select(0, (base[:, None] + offs[None, :]).reshape(-1)).view(base.shape[0], -1)
    if fixed:  # OpenCV: CV_DESCALE(sum, W_BITS1 - 5) = floor(sum / 2^9 + 1/2)
        jval = _interp_flat(jp, w, pw, 0.5)
        jval = _ste(jval - 0.5, torch.floor(jval))
    else:
        jval = _interp_flat(jp, w, pw)
    b = ((jval - iv).unsqueeze(1) * g).sum(2) * _FLT_SCALE  # (m, 2): b1, b2
    # OpenCV: delta = ((A12 b2 - A22 b1) D, (A12 b1 - A11 b2) D), same float operation order
    delta = (a12 * b.flip(1) - adiag * b) * dinv
    p_new = p + delta
    o_new = p_new + half
    dd = delta.detach().double()
    conv = (dd * dd).sum(1) <= eps2  # OpenCV: delta.ddot(delta) <= epsilon^2 in double
    still = act & ~conv
    if not first:
        osc = still & ((delta.detach() + pd.detach()).double().abs() < 0.01).all(1)
        o_new = torch.where(osc[:, None], o_new - delta * 0.5, o_new)
        still = still & ~osc
    a2 = act[:, None]
    return torch.where(a2, p_new, p), torch.where(a2, o_new, o), torch.where(a2, delta, pd), still, lost


# indirection so that a benchmark / user can swap in ``torch.compile(_lk_step, dynamic=True)``;
# the compiled kernel gathers through an explicit index (Inductor fuses it into the arithmetic; an
# overlapping as_strided view would be materialised)
_STEP = [_lk_step]
_USE_VIEW = [True]


def compile_step(enable: bool = True, **compile_kwargs) -> None:
    """Use ``torch.compile`` for the per-iteration kernel (``enable=False`` restores eager)."""
    if enable:
        compile_kwargs.setdefault("dynamic", True)
        _STEP[0] = torch.compile(_lk_step, **compile_kwargs)
        _USE_VIEW[0] = False
    else:
        _STEP[0] = _lk_step
        _USE_VIEW[0] = True


def _template(lv: _Level, pp: torch.Tensor, fixed: bool, dtype):
    """Window of the previous image at ``pp`` (window origins, (M, 2)): grey levels x32 ``(M, K)``
    and Scharr derivatives ``(M, 2, K)`` (junk column zeroed), as OpenCV computes them."""
    ip = torch.floor(pp.detach())
    frac = pp - ip
    base = lv.base(ip, lv.lane_base)
    patches = [lv.patches(c, base) for c in lv.IG]  # I, Ix, Iy: (M, ph*pw) each
    need_soft = not fixed or any(c.requires_grad for c in lv.IG) or frac.requires_grad
    if need_soft:
        w = _bilinear_weights(frac, False)
        ws = (w * 32.0, w, w)
        vals = [_interp_flat(pc, wc, lv.pw) for pc, wc in zip(patches, ws)]
    if fixed:
        iw = _fixed_weights(frac)
        # grey levels: sum(I * iw) / 2^9 is exact in float32 (22 bits); OpenCV rounds half up.
        # derivatives: sum(dI * iw) / 2^14 needs up to 26 bits, so in float32 a product can be
        # rounded; the descaled integer can then differ by 1 when the exact value lies within ~1e-3
        # of a half integer (rare; effect on tracked points < 1e-5 px). float64 input is exact.
        wts = ((iw * 2.0**-9).to(dtype), (iw * 2.0**-14).to(dtype))
        hard = [torch.floor(_interp_flat(pc.detach(), wts[min(k, 1)], lv.pw, 0.5)) for k, pc in enumerate(patches)]
        vals = [_ste(s, h) for s, h in zip(vals, hard)] if need_soft else hard
    g = torch.stack([vals[1] * lv.colmask, vals[2] * lv.colmask], dim=1)
    return vals[0], g


def _lk_impl(
    prev: Pyramid,
    nxt: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init: torch.Tensor | None,
    win: Tuple[int, int],
    top: int,
    max_iters: int,
    eps2: float,
    min_eig: float,
    fixed: bool,
    early_exit: bool,
) -> Tuple[torch.Tensor, torch.Tensor]:
    B, N, _ = pts.shape
    M = B * N
    dtype, dev = pts.dtype, pts.device
    ww, wh = win
    half = torch.tensor([(ww - 1) * 0.5, (wh - 1) * 0.5], dtype=dtype, device=dev)
    p0 = pts.reshape(M, 2)
    status = valid.reshape(M).clone()
    lanes = torch.arange(B, device=dev).repeat_interleave(N)
    # OpenCV's nextPts[i] (window centre) at the current level's scale
    out = (p0 if init is None else init.reshape(M, 2)) * (1.0 / (1 << top))

    for level in range(top, -1, -1):
        if level != top:
            out = out * 2.0
        lv = _Level(prev.levels[level].to(dtype), prev.grads[level].to(dtype), nxt.levels[level].to(dtype),
                    win, lanes)

        # ---- template: previous image window, derivatives, gradient matrix (once per level)
        pp = p0 * (1.0 / (1 << level)) - half
        proc = valid.reshape(M) & lv.inside(torch.floor(pp.detach()))
        if level == 0:
            status = status & proc
        ival, g = _template(lv, pp, fixed, dtype)
        a11 = (g[:, 0] * g[:, 0]).sum(1) * _FLT_SCALE
        a12 = (g[:, 0] * g[:, 1]).sum(1) * _FLT_SCALE
        a22 = (g[:, 1] * g[:, 1]).sum(1) * _FLT_SCALE
        with torch.no_grad():  # discrete decision; sqrt at 0 would poison gradients
            d11, d12, d22 = a11.detach(), a12.detach(), a22.detach()
            det = d11 * d22 - d12 * d12
            eig = (d22 + d11 - torch.sqrt((d11 - d22) * (d11 - d22) + 4.0 * d12 * d12)) / (2.0 * ww * wh)
            ok = proc & (eig >= min_eig) & (det >= _FLT_EPSILON)
        if level == 0:
            status = status & ok
        det = a11 * a22 - a12 * a12
        # keep masked lanes finite: torch.where differentiates both branches
        dinv = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det))

        # ---- iterations: only the next image is sampled
        amat = torch.stack([a12, a22, a11, dinv], dim=1)  # (M, 4): A12, (A22, A11), 1/det
        lo = torch.tensor([-ww, -wh], dtype=dtype, device=dev)
        hi = torch.tensor([lv.W, lv.H], dtype=dtype, device=dev)
        strides = torch.tensor([1, lv.Wp], dtype=dtype, device=dev)
        jv = _window_view(lv.J, lv.Wp, lv.ph, lv.pw) if _USE_VIEW[0] and not lv.J.requires_grad else None
        if early_exit:
            # working set = lanes still iterating; re-compacted (template rows gathered again) only
            # when it has shrunk to half, so the copy cost is amortised over the iterations
            ws = ok.nonzero().squeeze(1)  # host sync
        else:
            ws = None  # all lanes, masked; no host sync
        npt = out - half  # OpenCV's local nextPt (window origin)
        p, o, iv, gw, aw, bw, act = (t if ws is None else t.index_select(0, ws)
                                     for t in (npt, out, ival, g, amat, lv.lane_base, ok))
        pd = torch.zeros_like(p)
        for j in range(max_iters):
            if ws is not None:
                n_act = int(act.sum())  # host sync (early exit / compaction)
                if n_act == 0:
                    break
                if 2 * n_act <= act.shape[0]:
                    out = out.index_put((ws,), o)
                    keep = act.nonzero().squeeze(1)
                    ws = ws.index_select(0, keep)
                    p, o, pd, iv, gw, aw, bw = (t.index_select(0, keep) for t in (p, o, pd, iv, gw, aw, bw))
                    act = torch.ones_like(keep, dtype=torch.bool)
            p, o, pd, act, gone = _STEP[0](p, o, pd, act, iv, gw, aw[:, :1], aw[:, 1:3], aw[:, 3:], bw, lv.J, jv,
                                          lv.offs, half, lo, hi, strides, lv.pw, j == 0, fixed, eps2)
            if level == 0:
                if ws is None:
                    status = status & ~gone
                elif bool(gone.any()):
                    status = status.index_put((ws[gone],), torch.zeros_like(ws[gone], dtype=torch.bool))
        out = o if ws is None else out.index_put((ws,), o)
    return out.reshape(B, N, 2), status.reshape(B, N)


def _as_pyramid(x: ImageOrPyramid, name: str, levels: int, need_grads: bool) -> Pyramid:
    if isinstance(x, Pyramid):
        return x.with_gradients() if need_grads else x
    img = as_image_batch(x, name)
    return build_pyramid(img, levels, with_gradients=need_grads)


def _effective_top(prev: Pyramid, nxt: Pyramid, max_level: int, win: Tuple[int, int]) -> int:
    top = min(max_level, prev.max_level, nxt.max_level)
    for l in range(top + 1):
        if prev.levels[l].shape[-2:] != nxt.levels[l].shape[-2:]:
            raise ValueError(
                f"prev/next: level {l} sizes differ: {tuple(prev.levels[l].shape)} vs {tuple(nxt.levels[l].shape)}"
            )
    # buildOpticalFlowPyramid stops before a level whose size is <= win_size
    for l in range(1, top + 1):
        h, w = prev.levels[l].shape[-2:]
        if w <= win[0] or h <= win[1]:
            return l - 1
    return top


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
            :class:`~torch_frontend.pyramid.Pyramid` (reused across frames; gradients are computed if
            it has none).
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
        whatever OpenCV would leave there (finite). Gradients flow to ``pts``, ``init_pts`` and float
        images (through the pyramid) via unrolled iterations; the backward check is discrete (no
        gradient).
    """
    check_points(pts, "pts")
    valid = default_valid(pts, valid, "valid")
    if init_pts is not None:
        check_shape(init_pts, tuple(pts.shape), "init_pts")
    if isinstance(win_size, int):
        win = (win_size, win_size)
    else:
        win = (int(win_size[0]), int(win_size[1]))
    if win[0] <= 2 or win[1] <= 2:
        raise ConfigError(f"win_size must be > 2 in both axes, got {win_size!r}")
    if not isinstance(max_level, int) or max_level < 0:
        raise ConfigError(f"max_level must be an int >= 0, got {max_level!r}")
    fb_level = max_level if fb_max_level is None else fb_max_level
    if not isinstance(fb_level, int) or fb_level < 0:
        raise ConfigError(f"fb_max_level must be an int >= 0, got {fb_max_level!r}")
    max_iters = min(max(int(max_iters), 0), 100)
    eps = min(max(float(eps), 0.0), 10.0)
    eps2 = eps * eps

    if fixed_point is None:

        def _is8(x):
            return x.rounded if isinstance(x, Pyramid) else as_image_batch(x).dtype == torch.uint8

        fixed_point = _is8(prev) and _is8(next)
    levels = max(max_level, fb_level if forward_backward else 0)
    P = _as_pyramid(prev, "prev", levels, need_grads=True)
    Q = _as_pyramid(next, "next", levels, need_grads=forward_backward)
    for name, pyr in (("prev", P), ("next", Q)):
        if pyr.batch != pts.shape[0]:
            raise ValueError(f"{name}: batch {pyr.batch} does not match pts batch {pts.shape[0]}")

    top = _effective_top(P, Q, max_level, win)
    fb_top = _effective_top(Q, P, fb_level, win) if forward_backward else 0
    args = (win, top, fb_top, max_iters, eps2, float(min_eig_threshold), bool(fixed_point), early_exit,
            forward_backward, fb_use_initial_flow, float(fb_threshold))
    B, N = pts.shape[:2]
    # streams are independent: process them in groups of <= _MAX_LANES points so that the per-level
    # temporaries (padded images, (lanes, win^2) windows) stay cache/memory friendly; a loop over
    # groups of streams, not over points (measured: B=64 x N=1000 in one piece was ~4x slower/point)
    per = max(1, min(_MAX_STREAMS, _MAX_LANES // max(N, 1)))
    if B <= per:
        return _track(P, Q, pts, valid, init_pts, *args)
    outs, sts = [], []
    for s0 in range(0, B, per):
        sl = slice(s0, min(B, s0 + per))
        o, st = _track(P.select(sl), Q.select(sl), pts[sl], valid[sl], None if init_pts is None else init_pts[sl],
                       *args)
        outs.append(o)
        sts.append(st)
    return torch.cat(outs), torch.cat(sts)


_MAX_LANES = 8192
_MAX_STREAMS = 8


def _track(P, Q, pts, valid, init_pts, win, top, fb_top, max_iters, eps2, min_eig, fixed, early_exit,
           forward_backward, fb_use_initial_flow, fb_threshold):
    out, status = _lk_impl(P, Q, pts, valid, init_pts, win, top, max_iters, eps2, min_eig, fixed, early_exit)
    if forward_backward:
        with torch.no_grad():  # a discrete acceptance test: no gradient
            init = pts.detach() if fb_use_initial_flow else None
            back, st_b = _lk_impl(Q, P, out.detach(), status, init, win, fb_top, max_iters, eps2, min_eig,
                                  fixed, early_exit)
            err = torch.linalg.vector_norm((back - pts.detach()).double(), dim=-1)
            status = status & st_b & (err <= fb_threshold)
    return out, status
