"""Batched pyramidal Lucas–Kanade tracking, as ``cv2.calcOpticalFlowPyrLK`` (spec §5.1, §6.2–6.3).

All points of all streams move together: per pyramid level the template windows of the previous
image (grey levels and Scharr derivatives) and the 2x2 gradient matrices are computed once for every
point; each iteration then samples only the next image's ``win x win`` windows, solves the 2x2
systems in closed form and moves the points that are still active. Points that converged,
oscillated, left the image or failed the eigenvalue test are frozen by masks. Two strategies, the
same results bit for bit (every inexact float value — the template, ``b``, the step and its tests —
is computed by the same code on both):

* ``early_exit=True`` (default, the tuned path): template and iterations on the processed lanes
  only, the iterations on a compacted set of still-moving lanes (re-compacted when it halves),
  stopping when none is left: one host sync per iteration (:func:`_lk_impl`, per-iteration kernel
  ``_lk_step``; :func:`compile_step` swaps in a ``torch.compile`` d version).
* ``early_exit=False`` (the static path, the capturable tracker's): every lane of every stream in
  one pass, a fixed number of masked iterations per level (``LKOptions.iter_budget``, default
  ``max_iters``), no host sync once the per-size constants are cached, no data-dependent shape and
  an op count independent of B (:func:`_lk_static`, see "Static path" below).

Layers: :func:`track_lk` checks and normalises its arguments (into :class:`LKOptions`) and calls
``_track_lk_impl`` (the forward pass) and, with ``forward_backward``, ``_forward_backward_impl``
(VINS-Fusion's FLOW_BACK check); a pipeline that validated once calls those two on its pyramids
(``return_overflow=True`` adds the per-stream overflow flag of a budget below ``max_iters``). On the
CPU the early-exit path runs the streams in groups of at most ~1024 points
(``_tuning.Strategy.lk_streams``), elsewhere in one pass; the static path is one pass everywhere.
Every fast form (in place, window-view gather, folded template, difference image) gives the
reference form's values bit for bit, so results do not depend on whether gradients are recorded.

Static path (:func:`_lk_static`): 21 aten ops per iteration (fixed point on 8-bit levels, float32
points, no gradient; 22 with float64 points; 34 with float interpolation, whose window difference is
the early-exit path's), ~100 per level for the template and the bookkeeping: 4 levels x 30
iterations are ~2,900 launches per call, whatever B; ``iter_budget`` (an int, or one per level)
bounds them:

* OpenCV's fixed-point sample is exact integer arithmetic, so any formulation gives its values: per
  level the next image becomes a 4-channel *difference image* ``(J00 - J11, J01 - J11, J10 - J11,
  J11) 2^-9`` (plus an inside flag, :func:`_difference_image`); one ``searchsorted`` gives the
  window's top-left (floor, offset and clamp in one op), one advanced-index gather the ``(m, wh,
  ww + 1, 5)`` windows, one ``baddbmm`` with the weights ``(iw00, iw01, iw10, 2^14, 0)``
  (``remainder``, ``addcmul``, ``mul``, ``round``) and a ``floor`` the window difference. With
  gradients, float images or levels that are not 8-bit, the window difference is the early-exit
  path's (:func:`_window_diff`).
* ``b`` as the early-exit path's sum; the step ``C s dinv`` with ``C`` the 2x2 matrix times ``2^-20``
  (the same products and difference as ``(A12 b2 - A22 b1) D``), ``dinv`` times the inside flag (a
  lane outside the image takes a zero step).
* Stopping: the step test ``delta.double()`` + one ``bmm`` (float32 products are exact in float64:
  one rounding, as ``ddot``); signs alternate between iterations so that one ``cdist`` (inf norm)
  gives ``|delta + prevDelta|``; the two tests and the running mask are columns of a bool buffer
  whose ``all`` is the next running mask, and the update is one ``addcmul`` by that mask. A lane that
  stops does not take its stopping step in the loop: frozen at the same position it recomputes the
  same step every iteration, and the end of the level applies it (OpenCV's ``nextPt += delta``,
  ``-= delta / 2`` after an oscillation, told apart by ``|delta|^2 > eps^2``). A lane that stopped
  outside the image left it (status 0 at level 0); one still running when the budget ends keeps
  status 1 (OpenCV at ``max_iters``), or raises the overflow flag with a smaller budget.

Performance layout of the early-exit path, measured on CPU with ``benchmarks/bench_lk.py`` and py-spy:

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
* The static path trades memory passes for launches (a 5-channel gather and a batched matmul of
  tiny matrices, every lane every iteration): on the CPU it is ~10x slower than the early-exit
  path at B = 1 and ~25x at B = 16 (``aten::index`` and ``baddbmm`` dominate); it is meant for
  devices where launches and host syncs are the cost.

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
cheap because only few iterations run per point. ``grad_mode="implicit"`` instead runs the forward
without a graph and attaches the implicit-function gradient of the level-0 solution
(:func:`_implicit_attach`: two differentiable Newton steps with the true Jacobian ``dF/dy`` at the
detached solution, linearised at the root of the float equations; exact first and second
derivatives of the converged solution; memory independent of the iteration count; no gradient to
the coarse levels or ``init_pts``; zero gradient for lost, capped and ill-posed lanes). Bilinear interpolation is
only piecewise smooth: at exactly integer positions (e.g. ``goodFeaturesToTrack`` corners) the
gradient w.r.t. the points is the one-sided (right) derivative. The static path differentiates the
same function: its gradients w.r.t. the points equal the early-exit path's bit for bit, those
w.r.t. float images to rounding (the backward adds the windows' gradients into the images in
another order).

``torch.func``: ``vmap`` of :func:`track_lk` folds the vmapped dimension into the call (streams and
points are independent; the per-``v`` values bit for bit), ``grad``/``vjp``/``jacrev`` and forward
mode (``jvp``, ``jacfwd``, ``hessian``, ``torch.autograd.forward_ad`` dual tensors) differentiate
the reference forms, in both grad modes and on both paths; ``vmap`` *outside* a derivative
transform with vmapped primals (``vmap(grad(f))``) raises (see :func:`_track_lk_transformed`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Tuple, Union

import torch

from . import _tuning
from ._autodiff import straight_through
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
GRAD_MODES = ("unrolled", "implicit")
# implicit gradients: a lane gets a gradient only where the level-0 system at the solution is
# well posed: det(A) >= _IMPLICIT_MIN_DET_RATIO det(G) (A the true Jacobian of the normal equations'
# residual, G the Gauss-Newton matrix: equal under brightness constancy) and the Newton step at the
# solution is at most _IMPLICIT_MAX_STEP pixels (the solution is a root of the float equations)
_IMPLICIT_MIN_DET_RATIO = 0.05
_IMPLICIT_MAX_STEP = 0.1
_IMPLICIT_REFINE = 2  # Newton refinements of the linearisation point (no graph)


def _plain_cache(maxsize: int):
    """``functools.lru_cache(maxsize)`` for the per-size constant builders, whose entries are built
    outside ``torch.func`` transforms: under ``grad``/``jvp`` even a factory function returns a
    tensor wrapped at the transform's level, which, kept in the cache, would outlive it (an
    "escaped" wrapper in a later call). Outside transforms (and while dynamo traces) the builder
    runs as is."""

    def deco(fn):
        @functools.wraps(fn)
        def build(*args):
            if torch.compiler.is_compiling() or torch._C._functorch.peek_interpreter_stack() is None:
                return fn(*args)
            with _outside_transforms():
                return fn(*args)

        return functools.lru_cache(maxsize=maxsize)(build)

    return deco


@contextlib.contextmanager
def _outside_transforms():
    """The functorch interpreter stack cleared for the block (restored after)."""
    F = torch._C._functorch
    saved = []
    try:
        while F.peek_interpreter_stack() is not None:
            saved.append(F.pop_dynamic_layer_stack())
        yield
    finally:
        while saved:
            F.push_dynamic_layer_stack(saved.pop())


_ste = straight_through


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
    xs, ys = t[0].unsqueeze(0), t[1].unsqueeze(1)  # (1, 2, m), (2, 1, m): views
    iw = torch.round(ys * xs).reshape(4, m)  # rows: ys[i] xs[j] at 2i + j
    return torch.addmm(k[scale + "_b"], k[scale + "_C"], iw)


def _pitch(x: torch.Tensor) -> torch.Tensor:
    """``(m, ..., h, w)`` -> ``(m, ..., h * (w + 1))``: rows padded with one zero column, flattened:
    the iterations' layout (:func:`_interp_flat` with pitch ``w + 1``; the zero derivatives make its
    junk column drop out of ``b``)."""
    return torch.nn.functional.pad(x, (0, 1)).flatten(-2)


@_plain_cache(128)
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


@_plain_cache(32)
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
        # the static path's step matrices ((-A22, A12), (A12, -A11)) 2^-20, and their negatives
        step_signs=t([[[[-1.0, 1.0], [1.0, -1.0]]], [[[1.0, -1.0], [-1.0, 1.0]]]]) * _FLT_SCALE,
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
        self.Jview = Jp[o:].as_strided((Jp.numel() - o - (wh + 1) * Wp - ww, wh + 2, ww + 1), (1, Wp, 1))
        self.jstr, self.offs, self.ioffs = _level_offsets(Wp, ww, wh, dev)
        # previous image: (ph + 2, pw + 2) patches starting at padded (u_y, u_x)
        self.Ip = Ip = Ip.reshape(-1)
        self.Iview = Ip.as_strided((Ip.numel() - (wh + 2) * Wp - (ww + 2), wh + 3, ww + 3), (1, Wp, 1))


@_plain_cache(64)
def _level_offsets(Wp: int, ww: int, wh: int, device):
    """``jstr`` (2, 1) = ``(1, Wp)`` (int64: exact for any image size) and the flat offsets of the
    iteration's ``(wh + 2, ww + 1)`` window (from the patch's top-left ``Wp + 1``) and of the
    template's ``(wh + 3, ww + 3)`` patch in a padded level of row pitch ``Wp`` (cached: built once,
    not uploaded per call)."""
    jstr = torch.tensor([[1], [Wp]], device=device)
    dy, dx = torch.arange(wh + 2, device=device), torch.arange(ww + 1, device=device)
    offs = dy[:, None] * Wp + dx[None, :] + (Wp + 1)
    dy, dx = torch.arange(wh + 3, device=device), torch.arange(ww + 3, device=device)
    return jstr, offs, dy[:, None] * Wp + dx[None, :]


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


def _window_diff(p, iv, lane, J, jview, jstr, offs, k: dict, spanm1, fixed: bool, iv_init: bool = False):
    """The window difference of one iteration, ``J(p + x) - I(x)`` over the window in the pitched
    layout: ``(m, wh * (ww + 1))`` (1/32 grey levels; OpenCV's integers in fixed point), and the
    lanes whose window origin ``floor(p)`` is inside ``[-win, size)`` ``(m,)`` bool (the others read
    clamped, in-bounds windows). Shared by both paths (the float values must be computed by the same
    code); arguments as :func:`_lk_step`."""
    c05 = k["c05"]
    ip = torch.floor(p.detach())
    u = ip + k["win"]
    # clamp so that lanes that are masked out still read in-bounds memory; unchanged <=> inside
    uc = torch.clamp(u, min=k["zero"], max=spanm1)
    inside = (uc == u).all(0)
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
    return diff, inside


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
    if not _tuning.inplace_ok(f) or torch.compiler.is_compiling():  # the compiler takes no strided out=
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


def _gradient_system(g: torch.Tensor, act: torch.Tensor, ww: int, wh: int, min_eig: float):
    """The level's 2x2 gradient matrices of ``m`` lanes from their template derivatives ``g``
    ``(m, 2, n)`` (pitched, junk column 0): ``A11, A12, A22`` ``(m,)`` (scaled by ``2^-20``),
    ``dinv = 1/det`` (0 where not ``ok``) and ``ok`` = ``act`` and OpenCV's eigenvalue and determinant
    tests. Shared by both paths (same float operations)."""
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
    # 1/det where ok, else 0 (bool / float: 1/det or 0 exactly); the inner where keeps masked lanes
    # finite (torch.where differentiates both branches)
    dinv = ok / torch.where(ok, det, 1.0)
    return a11, a12, a22, dinv, ok


def _level_start(lv: _Level, p0: torch.Tensor, valid: torch.Tensor, level: int, k: dict):
    """Window origins of the template at ``level``: ``ip = floor(p0 / 2^level - halfWin)``,
    ``uc = ip + win`` clamped, the fractional part, and the lanes processed at this level
    (``valid`` and the origin inside ``[-win, size)``)."""
    pp = p0 * (1.0 / (1 << level)) - k["half"]
    ip = torch.floor(pp.detach())
    u = ip + k["win"]
    uc = torch.clamp(u, min=k["zero"], max=lv.spanm1)
    proc = valid & (uc == u).all(0)
    return uc, pp - ip, proc


def _lk_impl(
    prev: Pyramid,
    nxt: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init: torch.Tensor | None,
    opts: LKOptions,
    top: int,
    want_overflow: bool = False,
    capped: list | None = None,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The early-exit LK of one group of streams on levels ``top..0`` (see :func:`_track_lk_impl`):
    template and iterations on the processed lanes only, the iterations compacted to the
    still-moving lanes, stopping when none is left (host syncs). Returns ``next_pts (B, N, 2)``,
    ``status (B, N)`` and, with ``want_overflow`` and a budget below ``max_iters``, ``(B,)`` bool:
    some lane of the stream was still iterating when a level's budget ended (else None). With a
    list ``capped``, appends the ``(M,)`` bool mask of the lanes still iterating when level 0's
    budget ended (read by the implicit gradient; no effect on the values)."""
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
    overflow = None

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
        if level == 0 and capped is not None:
            capped.append(torch.zeros(M, dtype=torch.bool, device=dev))
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
            p, pd, act, mv, osc = _STEP[0](p, pd, act, iv, g, a12, adiag, dinv, lane, *st,
                                           j == 0, fixed, eps2, osc_thr, iv_init)
            if j == 0:
                moved = mv  # a lane moves at j > 0 only if it moved at j = 0
                oscf = torch.zeros_like(mv)
            if osc is not None:
                oscf = oscf | osc
            if fail is not None:
                fail = fail | (act_in & ~mv)  # left the image
        if level == 0 and capped is not None:
            capped[-1] = capped[-1].index_copy(0, ws, act)
        if want_overflow and budget < opts.max_iters:  # lanes still iterating when the budget ended
            lost = torch.zeros(M, dtype=torch.bool, device=dev).index_copy_(0, ws, act).view(B, N).any(1)
            overflow = lost if overflow is None else overflow | lost
        if moved is not None:
            out, status = _write_back(out, status, ws, o0, p, pd, moved, oscf, fail, half)
        elif fail is not None:
            out, status = _write_back(out, status, ws, o0, p, pd, None, None, fail, half)
    if want_overflow and overflow is None and opts.inexact:
        overflow = torch.zeros(B, dtype=torch.bool, device=dev)
    return out.t().reshape(B, N, 2), status.reshape(B, N), overflow


@_plain_cache(64)
def _lane_index(B: int, N: int, device) -> torch.Tensor:
    """``(B N,)`` int64: the stream of each lane (cached: no per-call upload, no host sync)."""
    return torch.arange(B, device=device).repeat_interleave(N, output_size=B * N)


@_plain_cache(64)
def _static_tables(H: int, W: int, ww: int, wh: int, dtype: torch.dtype, device):
    """Per level-size constants of the static path's fixed-point iterations (cached).

    ``grid`` ``(2, L)``: boundaries for ``searchsorted(grid, p, right=True)``, which gives, per axis,
    ``idx = floor(p) + win + 1`` for window origins inside ``[-win, size)`` (rows ``-win .. size``,
    the shorter padded with ``+inf``), 0 below and ``size + win + 1`` above: one op for the floor,
    the offset, the clamp and the integer conversion. ``idx`` is the window's top-left in the
    padded level's 4-channel image (:func:`_difference_image`). ``flag`` ``(Hp - 1, Wp, 1)``: 1 at
    the ``idx`` of inside origins, 0 at the two margins (outside)."""
    gx = torch.arange(-ww, W + 1, dtype=dtype, device=device)
    gy = torch.arange(-wh, H + 1, dtype=dtype, device=device)
    grid = torch.full((2, max(gx.numel(), gy.numel())), math.inf, dtype=dtype, device=device)
    grid[0, :gx.numel()] = gx
    grid[1, :gy.numel()] = gy
    r = torch.arange(H + 2 * wh + 1, device=device)
    c = torch.arange(W + 2 * ww + 2, device=device)
    flag = (((r >= 1) & (r <= H + wh))[:, None] & ((c >= 1) & (c <= W + ww))[None, :]).to(dtype)
    return grid, flag.unsqueeze(-1)


@_plain_cache(32)
def _static_consts(device):
    """OpenCV's bilinear weights as one ``addcmul`` + one product (see :func:`_fixed_weights`):
    ``T = off + frac * sgn`` ``(2: x/y, m, 5)``, ``iw = round(T[0] T[1])`` = ``(iw00, iw01, iw10, 2^14,
    0)``, the weights of the difference image's channels."""
    f32 = torch.float32
    off = torch.tensor([[[128.0, 0, 128, 128, 0]], [[128.0, 128, 0, 128, 0]]], dtype=f32, device=device)
    sgn = torch.tensor([[[-128.0, 128, -128, 0, 0]], [[-128.0, -128, 128, 0, 0]]], dtype=f32, device=device)
    return off, sgn


def _difference_image(Jp: torch.Tensor, flag: torch.Tensor) -> torch.Tensor:
    """The padded next level ``(B, 1, Hp, Wp)`` as ``(B, Hp - 1, Wp, 5)``: at ``(y, x)`` the channels
    ``(J00 - J11, J01 - J11, J10 - J11, J11) 2^-9`` of the 2x2 block ``J[y:y+2, x:x+2]`` and the
    inside flag (the last column is padding). OpenCV's fixed-point sample ``sum iw_ab J_ab 2^-9`` is
    then one dot product with ``(iw00, iw01, iw10, 2^14, 0)``: exact (integers times ``2^-9`` below
    ``2^23``), whatever the order of the multiply-adds."""
    J = Jp[:, 0]
    d = torch.stack((J[:, :-1, :-1], J[:, :-1, 1:], J[:, 1:, :-1], J[:, 1:, 1:]), -1)
    d = torch.cat((d[..., :3] - d[..., 3:], d[..., 3:]), -1) * 2.0**-9
    d = torch.nn.functional.pad(d, (0, 0, 0, 1))
    return torch.cat((d, flag.expand(d.shape[:-1] + (1,))), -1)


def _bmm_exact(device) -> bool:
    """The difference-image dot products are exact unless CUDA matmuls may round to TF32."""
    return torch.device(device).type != "cuda" or not torch.backends.cuda.matmul.allow_tf32


def _lk_static(
    prev: Pyramid,
    nxt: Pyramid,
    pts: torch.Tensor,
    valid: torch.Tensor,
    init: torch.Tensor | None,
    opts: LKOptions,
    top: int,
    capped: list | None = None,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The static LK (``early_exit=False``): all lanes of all streams in one pass, ``opts.budget_at``
    masked iterations per level, no host sync, an op count independent of the batch and of the data.

    Same results as :func:`_lk_impl` bit for bit (both compute every inexact float value, ``b``, the
    step, the tests, with the same code): a lane that stops (OpenCV's loop break) is frozen by a
    ``running`` mask. Returns ``next_pts (B, N, 2)``, ``status (B, N)`` and, with a budget below
    ``max_iters``, the ``(B,)`` overflow flag (a lane of the stream still running at the end of some
    level's budget), else None.

    Per iteration (fixed point, no gradient; see the module notes): ``searchsorted`` gives the
    window's top-left in the difference image, one advanced-index gather reads ``(m, wh, ww + 1,
    5)`` windows, one ``baddbmm`` with the weights (``remainder``, ``addcmul``, ``mul``, ``round``)
    plus ``floor`` gives the window difference; with gradients, or float images, the window
    difference is :func:`_window_diff`'s (the early-exit path's code). Then ``b`` and the step as
    the early-exit path, the step frozen (0) for lanes outside the image; a lane that stops does
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
    n = wh * (ww + 1)  # pitched window
    k = _win_consts(ww, wh, dtype, dev)
    half, zero = k["half"], k["zero"]
    osc_thr = _OSC.get(dtype, 0.01)
    if M == 0:
        return torch.empty_like(pts), valid.clone(), None
    p0 = pts.reshape(M, 2).t().contiguous()  # (2, M): points last
    valid = valid.reshape(M)
    status = valid
    lanes = _lane_index(B, N, dev)
    out = (p0 if init is None else init.reshape(M, 2).t().contiguous()) * (1.0 / (1 << top))
    overflow = None

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
        iv, g = _template(lv, ucl, frac, lanes, fixed, dtype, k, sync=False)
        a11, a12, a22, dinv, ok = _gradient_system(g, proc, ww, wh, min_eig)
        o0 = out
        if budget == 0:
            if level == 0:
                status = status & ok
                if capped is not None:
                    capped.append(ok)
            if inexact:
                lost = ok.view(B, N).any(1)
                overflow = lost if overflow is None else overflow | lost
            continue
        # the difference image's dot products are exact for OpenCV's 8-bit levels only
        fast = fixed and nxt.rounded and _tuning.inplace_ok(iv, g, lv.Jp, o0) and _bmm_exact(dev)
        if fixed and _tuning.inplace_ok(iv, lv.Jp, o0):
            iv = k["c05"] - iv  # 1/2 - template: the rounding's 1/2 and the difference in one op
            iv_init = True
        else:
            iv_init = False
        if fast:
            grid, flag_img = _static_tables(H, W, ww, wh, dtype, dev)
            J5 = _difference_image(Jpad, flag_img)
            Hq, Wq = J5.shape[1:3]
            J5w = J5.as_strided((B, Hq - wh + 1, Wq - ww, wh, ww + 1, 5), (Hq * Wq * 5, Wq * 5, 5, Wq * 5, 5, 1))
            w_off, w_sgn = _static_consts(dev)
            hiv = iv.view(M, n, 1)
        else:
            lane = lanes * lv.HWp
            st = (lv.Jp, lv.Jview, lv.jstr, lv.offs, k, lv.spanm1)
        # step = C s dinv with C = ((-A22, A12), (A12, -A11)) 2^-20: the products and the difference
        # as the early-exit path's (A12 b2 - A22 b1, A12 b1 - A11 b2) (b = s 2^-20, a power of two)
        # even / odd iterations: the step with alternating signs (2, M, 2, 2); the scale and signs
        # are powers of two: exact
        Cs = torch.stack((a22, a12, a12, a11), 1).view(M, 2, 2) * k["step_signs"]
        p = torch.where(proc, o0 - half, zero)  # OpenCV's local nextPt (window origin)
        # the stopping tests as columns (conv, osc, running) of two alternating bool buffers: one
        # ``all`` gives the next running mask (iteration j reads tst[j % 2], writes tst[1 - j % 2])
        tst = torch.empty((2, 3, M), dtype=torch.bool, device=dev)
        tst[0, 1].fill_(True)  # j = 0: no oscillation test
        tst[0, 2].copy_(ok)
        sdp = None
        for j in range(budget):
            sg = 1.0 - 2.0 * (j % 2)
            if fast:
                idx = torch.searchsorted(grid, p, right=True)  # (2, m) int64
                Wn = J5w[lanes, idx[1], idx[0]]  # (m, wh, ww + 1, 5)
                f = torch.remainder(p, 1.0)  # p - floor(p), exact
                if f.dtype != torch.float32:
                    f = f.float()  # OpenCV's weights are float32 (as _fixed_weights)
                iw = torch.addcmul(w_off, f.unsqueeze(-1), w_sgn)  # (2, m, 5)
                iw = torch.mul(iw[0], iw[1]).round_()
                if iw.dtype != dtype:
                    iw = iw.to(dtype)
                diff = torch.baddbmm(hiv, Wn.view(M, n, 5), iw.unsqueeze(-1)).floor_().view(M, 1, n)
                flag = Wn[:, 0, 0, 4]
            else:
                diff, inside = _window_diff(p, iv, lane, *st, fixed, iv_init)
                diff = diff.unsqueeze(1)
                flag = inside.to(dtype)
            s = (g * diff).sum(2)  # (m, 2): b / 2^-20, as the early-exit path's sum
            sd = (Cs[j % 2] * s.unsqueeze(1)).sum(2) * (dinv * flag).unsqueeze(1)  # (m, 2): sg * delta
            t, t1 = tst[j % 2], tst[1 - j % 2]
            dd = sd.detach().double()
            # OpenCV: continue while delta.ddot(delta) > eps^2 (any dot: exact float32 products, one rounding)
            torch.gt(torch.bmm(dd.unsqueeze(1), dd.unsqueeze(2)).view(M), eps2, out=t[0])
            if j > 0:  # and not |delta + prevDelta| <= 0.01: |sd - sdp| (alternating signs), inf-norm
                osc = torch.cdist(sd.detach().unsqueeze(1), sdp.unsqueeze(1), p=math.inf).view(M)
                torch.gt(osc, osc_thr, out=t[1])
            else:
                moved0 = flag > 0
            run = torch.all(t, 0, out=t1[2])
            if not _tuning.inplace_ok(p, sd):
                run = run.clone()  # autograd keeps the mask, the buffer is rewritten two iterations on
            p = torch.addcmul(p, sd.t(), run, value=sg)
            sdp = sd.detach()
        conv = t[0]  # the last iteration's step test: for a frozen lane, that of its stopping step
        # ---- end of level: the stopping step of the lanes that stopped inside the image
        stopped = ok > run  # ok & ~run: converged, oscillated, or left the image
        inside = flag > 0  # the last iteration's: where the frozen lanes are
        left = stopped > inside  # stopped outside: left the image (OpenCV: status 0 at level 0)
        took = stopped & inside  # converged or oscillated: take the stopping step
        o = torch.addcmul(p, sd.t(), took, value=sg) + half
        o = torch.addcmul(o, sd.t(), took & conv, value=-0.5 * sg)  # oscillated: |delta|^2 > eps^2
        out = torch.where(ok & moved0, o, o0)  # lanes that never moved keep the level's start
        if level == 0:
            status = status & (ok > left)
            if capped is not None:
                capped.append(run.clone())
        if inexact:
            lost = run.view(B, N).any(1)
            overflow = lost if overflow is None else overflow | lost
    return out.t().reshape(B, N, 2), status.reshape(B, N), overflow


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
            iteration; the tuned path); False: the static, capturable path (a fixed number of
            masked iterations, all streams in one pass, no host sync; the same results).
        grad_mode: ``"unrolled"`` (default: autograd through every iteration) or ``"implicit"``
            (implicit-function gradient of the level-0 solution, see :func:`_implicit_attach`; the
            forward values are the same bit for bit).
        iter_budget: iterations run per level (None: ``max_iters``, exact), an int or a tuple per
            level (``iter_budget[l]`` for level ``l``, the last entry for the levels above). A
            smaller budget bounds the work of the static path (on both paths the same results); a
            lane still iterating when it ends may differ from OpenCV, which
            ``_track_lk_impl(..., return_overflow=True)`` reports per stream.

    Raises:
        ConfigError: a window <= 2, a negative / non-int ``max_level`` or ``iter_budget``, an
            unknown ``grad_mode``.
    """

    win_size: Tuple[int, int] = (21, 21)
    max_level: int = 3
    max_iters: int = 30
    eps: float = 0.01
    min_eig_threshold: float = 1e-4
    fixed_point: bool = True
    early_exit: bool = True
    iter_budget: int | Tuple[int, ...] | None = None
    grad_mode: str = "unrolled"

    def __post_init__(self):
        if self.grad_mode not in GRAD_MODES:
            raise ConfigError(f"grad_mode must be one of {GRAD_MODES}, got {self.grad_mode!r}")
        win = self.win_size
        win = (win, win) if isinstance(win, int) else (int(win[0]), int(win[1]))
        if win[0] <= 2 or win[1] <= 2:
            raise ConfigError(f"win_size must be > 2 in both axes, got {self.win_size!r}")
        if not isinstance(self.max_level, int) or self.max_level < 0:
            raise ConfigError(f"max_level must be an int >= 0, got {self.max_level!r}")
        fields = dict(win_size=win, max_iters=min(max(int(self.max_iters), 0), 100),
                      eps=min(max(float(self.eps), 0.0), 10.0), min_eig_threshold=float(self.min_eig_threshold),
                      fixed_point=bool(self.fixed_point), early_exit=bool(self.early_exit))
        b = self.iter_budget
        if b is not None:
            items = b if isinstance(b, (tuple, list)) else (b,)
            if not items or any(isinstance(x, bool) or not isinstance(x, int) or x < 0 for x in items):
                raise ConfigError(f"iter_budget must be None, an int >= 0 or a non-empty tuple of them, got {b!r}")
            fields["iter_budget"] = tuple(items) if isinstance(b, (tuple, list)) else b
        for name, value in fields.items():
            object.__setattr__(self, name, value)

    def budget_at(self, level: int) -> int:
        """Iterations run at ``level``: ``iter_budget`` capped by ``max_iters`` (``max_iters`` when None)."""
        b = self.iter_budget
        if b is None:
            return self.max_iters
        if isinstance(b, tuple):
            b = b[min(level, len(b) - 1)]
        return min(b, self.max_iters)

    @property
    def budget(self) -> int:
        """The largest per-level budget (``max_iters`` when ``iter_budget`` is None)."""
        b = self.iter_budget
        return max(self.budget_at(l) for l in range(len(b))) if isinstance(b, tuple) else self.budget_at(0)

    @property
    def inexact(self) -> bool:
        """Some level's budget is below ``max_iters`` (results may differ from OpenCV: overflow flag)."""
        b = self.iter_budget
        return b is not None and any(min(x, self.max_iters) < self.max_iters for x in (b if isinstance(b, tuple) else (b,)))


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
    grad_mode: str = "unrolled",
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
        grad_mode: ``"unrolled"`` (default) differentiates every iteration of every level;
            ``"implicit"`` runs the forward without a graph and attaches the implicit-function
            gradient of the level-0 solution (memory independent of the iteration count; no
            gradient to ``init_pts``; zero gradient for lanes with status False, lanes that hit
            ``max_iters`` at level 0, and ill-posed lanes). Same values either way.

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

    ``torch.func``: ``vmap`` over an outer batch (``(V, B, ...)`` inputs, any of them shared with
    ``in_dims=None``) gives the per-``v`` calls' results bit for bit; ``grad``, ``vjp``, ``jacrev``,
    ``jvp``, ``jacfwd``, ``hessian`` and forward-AD dual tensors work in both grad modes (and
    compose with that ``vmap`` inside them). ``vmap`` over the primals of a derivative transform
    (``vmap(grad(f))``) raises ``NotImplementedError``: take the derivative of the loss summed over
    the batch (the streams are independent).
    """
    if _transforms_active():  # torch.func / forward-AD dual tensors: see _track_lk_transformed
        return _track_lk_transformed(prev, next, pts, valid, init_pts, dict(
            win_size=win_size, max_level=max_level, max_iters=max_iters, eps=eps, min_eig_threshold=min_eig_threshold,
            forward_backward=forward_backward, fb_threshold=fb_threshold, fb_max_level=fb_max_level,
            fb_use_initial_flow=fb_use_initial_flow, fixed_point=fixed_point, early_exit=early_exit,
            grad_mode=grad_mode))
    return _track_lk_door(prev, next, pts, valid, init_pts, win_size, max_level, max_iters, eps, min_eig_threshold,
                          forward_backward, fb_threshold, fb_max_level, fb_use_initial_flow, fixed_point, early_exit,
                          grad_mode)


def _track_lk_door(prev, next, pts, valid, init_pts, win_size, max_level, max_iters, eps, min_eig_threshold,
                   forward_backward, fb_threshold, fb_max_level, fb_use_initial_flow, fixed_point, early_exit,
                   grad_mode):
    """:func:`track_lk`'s checks and calls (its arguments, in its order)."""
    check_points(pts, "pts")
    valid = default_valid(pts, valid, "valid")
    if init_pts is not None:
        check_shape(init_pts, tuple(pts.shape), "init_pts")
    if fixed_point is None:

        def _is8(x):
            return x.rounded if isinstance(x, Pyramid) else as_image_batch(x).dtype == torch.uint8

        fixed_point = _is8(prev) and _is8(next)
    opts = LKOptions(win_size, max_level, max_iters, eps, min_eig_threshold, fixed_point, early_exit,
                     grad_mode=grad_mode)
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
    return_overflow: bool = False,
    capped: list | None = None,
):
    """Forward LK (:func:`track_lk` without the backward check), no input checks.

    Args:
        prev, next: pyramids of the B streams, with equal level sizes (as many levels as
            ``opts.max_level`` asks for, or fewer: the LK then uses fewer).
        pts: ``(B, N, 2)`` float, pixels ``(x, y)`` in ``prev``.
        valid: ``(B, N)`` bool.
        init_pts: ``(B, N, 2)`` initial guess in ``next``, or None (start at ``pts``).
        opts: :class:`LKOptions`.
        return_overflow: also return the ``(B,)`` bool overflow flag.
        capped: a list to which the ``(B N,)`` bool mask of the lanes that hit level 0's
            iteration budget is appended (a lane not processed at level 0 is False).

    Returns:
        ``next_pts (B, N, 2)`` (pts dtype, pixels in ``next``) and ``status (B, N)`` bool; with
        ``return_overflow`` also ``overflow (B,)`` bool: some lane of the stream was still iterating
        when a level's iteration budget (``opts.iter_budget``) ended, so that its result may differ
        from OpenCV's (always False when the budget is ``max_iters``).

    ``opts.early_exit`` (the tuned path): on the CPU the streams are tracked in groups
    (``_tuning.Strategy.lk_streams``), so that the per-level temporaries (``(win+1)^2 x lanes``
    windows and their indices) stay cache friendly; the padded levels are built once for the whole
    batch and shared by the groups as views (a pyramid that is ``next`` now keeps them for the call
    in which it is ``prev``). Elsewhere: one pass. ``early_exit=False`` (the capturable path): one
    static pass on every device (:func:`_lk_static`): no host sync once the per-size constants are
    cached, an op count independent of B, the same results.

    ``opts.grad_mode == "implicit"`` with a gradient to compute: the forward above without a graph,
    then :func:`_implicit_attach` (the same values).

    Under a ``torch.func`` transform or a forward-AD dual level every kernel takes its reference
    (out-of-place, differentiable) form (:func:`_tuning.reference_forms`: the same values): the
    fast forms write in place / into ``out=`` buffers, which forward-mode AD does not support, and
    they tell from ``requires_grad`` alone that no derivative is needed, which dual tensors do not
    set.
    """
    if _transforms_active() and _tuning.inplace_ok():
        with _tuning.reference_forms():
            return _track_lk_impl(prev, next, pts, valid, init_pts, opts, return_overflow, capped)
    if opts.grad_mode == "implicit" and _wants_grad(prev, next, pts, init_pts):
        return _track_lk_implicit(prev, next, pts, valid, init_pts, opts, return_overflow)
    top = _level_cap(prev, next, opts.max_level, opts.win_size)
    B, N = pts.shape[:2]
    if init_pts is not None:
        # a non-finite guess (a NaN prediction) would index outside the image: its lane is not
        # tracked and starts at its pts (status False, as OpenCV's 0). Elementwise, no host sync;
        # a finite guess is kept exactly.
        guessed = torch.isfinite(init_pts).all(-1)
        init_pts = torch.where(guessed.unsqueeze(-1), init_pts, pts)
        valid = valid & guessed
    per = _tuning.for_device(pts.device).lk_streams(B, N) if opts.early_exit else None
    if not opts.early_exit:
        out, status, overflow = _lk_static(prev, next, pts, valid, init_pts, opts, top, capped)
    elif per is None:
        out, status, overflow = _lk_impl(prev, next, pts, valid, init_pts, opts, top, return_overflow, capped)
    else:
        ww, wh = opts.win_size
        for l in range(top + 1):
            for x in (prev, next):
                x.padded(l, wh + 1, ww + 1, pts.dtype)
        outs, sts, ovfs = [], [], []
        caps = None if capped is None else []
        for s0 in range(0, B, per):
            sl = slice(s0, min(B, s0 + per))
            o, st, ov = _lk_impl(prev.select(sl), next.select(sl), pts[sl], valid[sl],
                                 None if init_pts is None else init_pts[sl], opts, top, return_overflow, caps)
            outs.append(o)
            sts.append(st)
            ovfs.append(ov)
        out, status = torch.cat(outs), torch.cat(sts)
        overflow = None if ovfs[0] is None else torch.cat(ovfs)
        if capped is not None and caps:
            capped.append(torch.cat(caps))
    if not return_overflow:
        return out, status
    if overflow is None:
        overflow = torch.zeros(B, dtype=torch.bool, device=pts.device)
    return out, status, overflow


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
    return_overflow: bool = False,
):
    """VINS-Fusion's FLOW_BACK check of a forward LK result, no input checks.

    Tracks ``out`` back from ``next`` to ``prev`` (lanes with ``status``; ``opts`` with
    ``max_level = fb_max_level``; starting at ``pts`` when ``fb_use_initial_flow``, else at ``out``)
    and returns ``status & back_status & (|back - pts| <= fb_threshold)`` ``(B, N)`` bool, the
    distance in float64 pixels; with ``return_overflow`` also the backward pass's ``(B,)`` overflow
    flag (see :func:`_track_lk_impl`). ``pts``, ``out``: ``(B, N, 2)``; ``status``: ``(B, N)``
    bool. A discrete test: no gradient.
    """
    if _forward_ad_active():  # no_grad does not stop forward-mode AD: a discrete test, no tangents
        prev, next = _detached(prev), _detached(next)
    with torch.no_grad():
        init = pts.detach() if fb_use_initial_flow else None
        res = _track_lk_impl(next, prev, out.detach(), status, init, dataclasses.replace(opts, max_level=fb_max_level),
                             return_overflow)
        err = torch.linalg.vector_norm((res[0] - pts.detach()).double(), dim=-1)
        ok = status & res[1] & (err <= fb_threshold)
        return (ok, res[2]) if return_overflow else ok


# ---------------------------------------------------------------------- implicit gradients
def _wants_grad(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, init: torch.Tensor | None) -> bool:
    """A gradient is being recorded and some input of level 0 (or the points) needs one, or
    forward-mode AD is active (dual tensors do not set ``requires_grad``)."""
    if _forward_ad_active():
        return True
    if not torch.is_grad_enabled():
        return False
    return pts.requires_grad or prev.levels[0].requires_grad or nxt.levels[0].requires_grad or (
        init is not None and init.requires_grad)


@_plain_cache(32)
def _patch_offsets(Wp: int, ww: int, wh: int, device) -> torch.Tensor:
    """Flat offsets ``(wh + 1, ww + 2)`` of the bilinear patch of a window whose origin ``u`` is
    addressed as in :class:`_Level` (padded rows/columns start at ``u + 1``)."""
    dy, dx = torch.arange(wh + 1, device=device), torch.arange(ww + 2, device=device)
    return dy[:, None] * Wp + dx[None, :] + (Wp + 1)


def _newton_terms(lv: _Level, q: torch.Tensor, lane: torch.Tensor, iv: torch.Tensor, g: torch.Tensor, k: dict):
    """The level's LK residual and its Jacobian at window origins ``q`` ``(2, m)`` (float bilinear,
    differentiable w.r.t. ``q``, the next level and, through ``iv``/``g``, the previous one):
    ``F = sum_x g(x) (32 J(q + x) - iv(x))`` ``(2, m)`` (the normal equations' right-hand side,
    ``G delta = -F``) and ``A = dF/dq`` ``(2, 2, m)`` (``A[i, j] = sum_x g_i dJ/dq_j``; ``A = G``
    under brightness constancy), plus the lanes whose window is inside ``[-win, size)``. Layout as
    the iterations' (pitched, ``g`` zero on the junk column)."""
    ww, wh = lv.ww, lv.wh
    ip = torch.floor(q.detach())
    u = ip + k["win"]
    uc = torch.clamp(u, min=k["zero"], max=lv.spanm1)
    inside = (uc == u).all(0)
    base = (uc.long() * lv.jstr).sum(0) + lane
    idx = base.view(-1, 1, 1) + _patch_offsets(lv.Wp, ww, wh, lv.Jp.device)
    P = lv.Jp.index_select(0, idx.view(-1)).view(idx.shape).to(q.dtype)  # (m, wh + 1, ww + 2)
    m = P.shape[0]

    def flat(t):
        return t.reshape(m, -1)

    j00, j01 = flat(P[:, :wh, :ww + 1]), flat(P[:, :wh, 1:])
    j10, j11 = flat(P[:, 1:, :ww + 1]), flat(P[:, 1:, 1:])
    a, b = (q - ip).unsqueeze(-1).unbind(0)  # (m, 1) each
    val = (1 - b) * ((1 - a) * j00 + a * j01) + b * ((1 - a) * j10 + a * j11)
    da = (1 - b) * (j01 - j00) + b * (j11 - j10)
    db = (1 - a) * (j10 - j00) + a * (j11 - j01)
    F = (g * (32.0 * val - iv).unsqueeze(1)).sum(-1).t()  # (2, m)
    A = (g.unsqueeze(2) * (32.0 * torch.stack((da, db), 1)).unsqueeze(1)).sum(-1)  # (m, 2, 2)
    return F, A.permute(1, 2, 0), inside


def _solve2(A: torch.Tensor, F: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """``A^-1 F`` for ``(2, 2, m)`` / ``(2, m)`` in closed form, 0 where not ``ok`` (the masked lanes'
    inputs are replaced first, so that neither the value nor the gradient can be NaN there)."""
    eye = torch.eye(2, dtype=A.dtype, device=A.device).unsqueeze(-1)
    A = torch.where(ok, A, eye)
    F = torch.where(ok, F, 0.0)
    det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    det = torch.where(ok, det, 1.0)
    x0 = A[1, 1] * F[0] - A[0, 1] * F[1]
    x1 = A[0, 0] * F[1] - A[1, 0] * F[0]
    return torch.stack((x0, x1)) / det


def _implicit_attach(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, out: torch.Tensor, mask: torch.Tensor,
                     opts: LKOptions) -> Tuple[torch.Tensor, torch.Tensor]:
    """Attach the implicit-function gradient to a forward LK result (values unchanged).

    At the converged level-0 solution ``y*`` the LK equations ``F(y*, theta) = 0`` hold (``F`` =
    :func:`_newton_terms`' residual, ``theta`` = the points and both level-0 images), so
    ``dy*/dtheta = -A^-1 dF/dtheta`` with ``A = dF/dy``: one 2x2 solve per point. It is realised as two
    differentiable Newton steps from the detached solution, ``y1 = N(y*)``, ``y2 = N(y1)`` with
    ``N(y) = y - A(y)^-1 F(y)``; the result is ``y* + (y2 - y2.detach())`` (value ``y*`` exactly).
    One step gives the exact first derivative (``dN/dy = 0`` at a root of ``F``), the second the exact
    second derivative (so that ``gradgradcheck`` holds), with the forward's residual (``|F|`` after
    ``eps``-stopping and fixed-point rounding) as the only error.

    Levels: only level 0 is differentiated. The root of level 0's equations does not depend on
    where the iteration started, so the coarse levels and ``init_pts`` (which only pick the basin)
    get no gradient. ``A`` is the true Jacobian (bilinear derivative of the next image), not the
    Gauss-Newton ``G``, so the gradient is that of the converged solution.

    Args:
        prev, nxt: the pyramids (level 0 carries the image gradients).
        pts: ``(B, N, 2)`` points in ``prev``; ``out``: ``(B, N, 2)`` the forward's result (detached).
        mask: ``(B, N)`` bool, lanes to differentiate (status True, not capped at level 0).

    Returns:
        ``next_pts (B, N, 2)`` with the gradient attached, and the ``(B, N)`` lanes that received one
        (``mask`` and well posed: window inside, ``det A >= 0.05 det G``, Newton step at the solution
        <= 0.1 px); the others get an exactly zero gradient.
    """
    B, N, _ = pts.shape
    M = B * N
    dtype, dev = pts.dtype, pts.device
    ww, wh = opts.win_size
    k = _win_consts(ww, wh, dtype, dev)
    half = k["half"]
    H, W = nxt.levels[0].shape[-2:]
    lv = _Level(prev.padded(0, wh + 1, ww + 1, dtype), nxt.padded(0, wh + 1, ww + 1, dtype), H, W, (ww, wh), dtype)
    mask = mask.reshape(M)
    p0 = torch.where(mask, pts.reshape(M, 2).t(), 0.0)  # masked lanes: finite, zero gradient
    lanes = _lane_index(B, N, dev)
    uc, frac, proc = _level_start(lv, p0, mask, 0, k)
    ucl = torch.where(proc, uc, k["zero"]).long()
    iv, g = _template(lv, ucl, frac, lanes, False, dtype, k, sync=False)
    lane = lanes * lv.HWp
    ystar = out.detach().reshape(M, 2).t()
    if not ystar.is_floating_point() or ystar.dtype != dtype:
        ystar = ystar.to(dtype)
    q0 = torch.where(proc, ystar - half, 0.0)
    with torch.no_grad():
        # linearise at the root of the float equations: the forward stopped at |delta| <= eps (and
        # solved the fixed-point equations in 8-bit mode); two Newton steps (true Jacobian) refine
        # the point at which the derivatives are taken, not the returned value
        gd = g.detach()
        Gd = (gd.unsqueeze(2) * gd.unsqueeze(1)).sum(-1)  # (m, 2, 2)
        detG = Gd[:, 0, 0] * Gd[:, 1, 1] - Gd[:, 0, 1] * Gd[:, 1, 0]
        ok = proc & (detG > 0)
        qr = q0
        for it in range(_IMPLICIT_REFINE + 1):
            Fd, Ad, inside = _newton_terms(lv, qr, lane, iv.detach(), gd, k)
            detA = Ad[0, 0] * Ad[1, 1] - Ad[0, 1] * Ad[1, 0]
            ok = ok & inside & (detA >= _IMPLICIT_MIN_DET_RATIO * detG)
            step = _solve2(Ad, Fd, ok)
            if it == 0:
                ok = ok & (step.abs() <= _IMPLICIT_MAX_STEP).all(0)
            if it < _IMPLICIT_REFINE:
                qr = qr - torch.where(ok, step, 0.0)
        ok = ok & ((qr - q0).abs() <= _IMPLICIT_MAX_STEP).all(0)
        q0 = torch.where(ok, qr, q0)
    F0, A0, _ = _newton_terms(lv, q0, lane, iv, g, k)
    c1 = _solve2(A0, F0, ok)
    q1 = q0 + (c1.detach() - c1)  # value q0, derivative of N(q0) = q0 - A^-1 F
    F1, A1, _ = _newton_terms(lv, q1, lane, iv, g, k)
    c2 = _solve2(A1, F1, ok)
    corr = q1 - c2
    corr = corr - corr.detach()  # exactly 0 (finite), the derivative of N(N(q0))
    res = ystar + torch.where(ok, corr, 0.0)
    return res.t().reshape(B, N, 2), ok.view(B, N)


def _track_lk_implicit(prev: Pyramid, nxt: Pyramid, pts: torch.Tensor, valid: torch.Tensor,
                       init: torch.Tensor | None, opts: LKOptions, return_overflow: bool):
    """``_track_lk_impl`` with ``grad_mode="implicit"``: the forward without a graph (the same code,
    so the same values), then :func:`_implicit_attach` on the lanes with status True that did not
    hit level 0's iteration budget."""
    capped: list = []
    P, Q = prev, nxt
    if _forward_ad_active():  # no_grad does not stop forward-mode AD: run the forward on plain levels
        P, Q = _detached(prev), _detached(nxt)
    with torch.no_grad():
        res = _track_lk_impl(P, Q, pts.detach(), valid, None if init is None else init.detach(),
                             dataclasses.replace(opts, grad_mode="unrolled"), return_overflow, capped)
    out, status = res[0], res[1]
    cap = capped[0].view(status.shape) if capped else torch.zeros_like(status)
    out, _ = _implicit_attach(prev, nxt, pts, out, status & ~cap, opts)
    return (out, status) + tuple(res[2:])


# ---------------------------------------------------------------------- torch.func
# torch.func (vmap, grad, vjp, jacrev, jvp, jacfwd, hessian) and forward-AD dual tensors. The
# private functorch helpers used here (_unwrap_batched, _add_batch_dim, peek_interpreter_stack,
# pop/push_dynamic_layer_stack, the Python interpreters and their lower()) are those torch's own
# autograd.Function vmap rule is built on (in torch since 2.0/2.1; get_interpreter_stack is
# optional: without it forward mode is assumed possible under any transform). Tested on 2.13.
_fwad = torch.autograd.forward_ad


def _transforms_active() -> bool:
    if torch.compiler.is_compiling():
        return False
    return _fwad._current_level >= 0 or torch._C._functorch.peek_interpreter_stack() is not None


def _forward_ad_active() -> bool:
    """Forward-mode AD may be recording: a forward-AD dual level, or a ``torch.func.jvp`` (``jacfwd``,
    ``hessian``) level on the functorch stack. Dual tensors do not set ``requires_grad``, and
    ``torch.no_grad`` does not stop forward-mode AD."""
    if torch.compiler.is_compiling():
        return False
    if _fwad._current_level >= 0:
        return True
    if torch._C._functorch.peek_interpreter_stack() is None:
        return False
    stack = getattr(torch._C._functorch, "get_interpreter_stack", lambda: None)()
    if stack is None:  # cannot tell (older torch): assume it may
        return True
    jvp = torch._C._functorch.TransformType.Jvp
    return any(i.key() == jvp for i in stack)


def _detached(p: Pyramid) -> Pyramid:
    """``p`` with detached levels (and cached padded levels): no gradient, no tangent."""
    out = Pyramid([t.detach() for t in p.levels], None, p.rounded)
    out._padded = {k: v.detach() for k, v in p._padded.items()}
    return out


def _batched_inside(x) -> bool:
    """``x`` (tensor or pyramid) holds a tensor batched by some vmap level below its outer wrapper."""
    F = torch._C._functorch
    for t in (x.levels if isinstance(x, Pyramid) else (x,)):
        while isinstance(t, torch.Tensor) and F.is_functorch_wrapped_tensor(t):
            if F.is_batchedtensor(t):
                return True
            t = F.get_unwrapped(t)
    return False


def _track_lk_transformed(prev, next, pts, valid, init_pts, kw: dict):
    """:func:`track_lk` under ``torch.func`` transforms or forward-AD dual tensors.

    * ``vmap`` (the innermost transform): the LK's streams and points are independent, so the
      vmapped dimension is folded into the call instead of batching its ops (the early-exit path
      sizes its work by host syncs and ``nonzero``, which vmap cannot batch). The arguments are
      unwrapped at the vmap level and the LK runs one level lower on the folded tensors: into the
      batch (``(V, B, ...) -> (V B, ...)``) when an image is vmapped (unvmapped images are
      repeated), else into the points (``(V, B, N, 2) -> (B, V N, 2)``: shared images, neither
      copied nor rebuilt); the results are ``(V, B, N, 2)`` / ``(V, B, N)`` re-wrapped at the level.
      The values are those of one call per ``v`` bit for bit (every lane is computed by the same
      per-lane code whatever the lane set). Nested vmaps fold level by level; an outer ``grad`` /
      ``jvp`` sees the folded call's ops.
    * otherwise (``grad``, ``vjp``, ``jvp``, ``jacfwd``, dual tensors): the checked call with every
      kernel in its reference form (see :func:`_track_lk_impl`); with ``grad_mode="implicit"`` the
      forward runs on detached levels and the implicit gradient is attached whenever forward-mode
      AD is active. A given :class:`Pyramid`'s padded-level cache is not written to (a copy is).
    * a vmap *outside* a ``grad``/``jvp``/``vjp`` with vmapped primals (``vmap(grad(f))``,
      ``vmap(jvp(f))``, per-sample derivatives) cannot be folded (the derivative transform's
      wrappers hold the batched tensors): ``NotImplementedError``. Since the streams are
      independent, the derivative of the summed loss w.r.t. the batched inputs gives the
      per-stream derivatives.
    """
    from torch._functorch.pyfunctorch import retrieve_current_functorch_interpreter

    F = torch._C._functorch
    args = (prev, next, pts, valid, init_pts)
    interp = retrieve_current_functorch_interpreter() if F.peek_interpreter_stack() is not None else None
    if interp is not None and interp.key() == F.TransformType.Vmap:
        level = interp.level()
        un = [_unwrap_at(x, level) for x in args]
        if not any(b for _, b in un):
            with interp.lower():  # nothing batched at this level: an outer level's business
                return _call(*(x for x, _ in un), kw)
        folded, unfold = _fold(un)
        with interp.lower():
            out, status = _call(*folded, kw)
        return F._add_batch_dim(unfold(out), 0, level), F._add_batch_dim(unfold(status), 0, level)
    if interp is not None and any(_batched_inside(x) for x in args if x is not None):
        raise NotImplementedError(
            "track_lk: vmap over the primals of a derivative transform (vmap(grad(f)), vmap(jvp(f)), "
            "vmap(vjp(f))) is not supported: the early-exit LK's nonzero/host syncs cannot be batched "
            "inside the derivative's wrappers. Put vmap inside the derivative (grad(vmap(f))), or take the "
            "derivative of the loss summed over the batch: the streams are independent.")
    # a given pyramid's padded-level cache is read, not written: entries built here would be
    # wrapped at this transform's level and outlive it
    args = tuple(_cache_copy(x) if isinstance(x, Pyramid) else x for x in args)
    with _tuning.reference_forms():
        return _track_lk_door(*args, **kw)


def _cache_copy(p: Pyramid) -> Pyramid:
    """``p`` with a private copy of its padded-level cache (the same level tensors)."""
    out = Pyramid(p.levels, p.grads, p.rounded)
    out._padded = dict(p._padded)
    return out


def _call(prev, next, pts, valid, init_pts, kw: dict):
    """:func:`track_lk` (the door again: the next transform level is handled there)."""
    return track_lk(prev, next, pts, valid, init_pts=init_pts, **kw)


def _unwrap_at(x, level: int):
    """``x`` (a tensor, a pyramid or None) unwrapped at vmap ``level``: ``(value, batched)``, the
    batch dimension of a batched tensor moved to 0 (``(V, ...)``; a pyramid's unbatched levels are
    expanded to match)."""
    F = torch._C._functorch
    if isinstance(x, Pyramid):
        levels = [_unwrap_at(t, level) for t in x.levels]
        if not any(b for _, b in levels):
            return x, False
        V = next(t.shape[0] for t, b in levels if b)
        lv = [t if b else t.unsqueeze(0).expand(V, *t.shape) for t, b in levels]
        return Pyramid(lv, None, x.rounded), True
    if not isinstance(x, torch.Tensor):
        return x, False
    t, bdim = F._unwrap_batched(x, level)
    if bdim is None:
        return t, False
    return t.movedim(bdim, 0), True


def _fold(un):
    """Fold the vmapped dimension of ``(prev, next, pts, valid, init_pts)`` (each ``(value,
    batched)``, see :func:`_unwrap_at`) into the batch (an image is batched) or into the points;
    returns the folded arguments and the map of an output ``(V B, N, ...)`` / ``(B, V N, ...)``
    back to ``(V, B, N, ...)``."""
    V = next(_vsize(x) for x, b in un if b)
    into_batch = un[0][1] or un[1][1]

    def rep(x, b):  # an unbatched argument repeated along a new dim 0 of size V (a view)
        return x if b else x.unsqueeze(0).expand(V, *x.shape)

    out = []
    for i, (x, b) in enumerate(un):
        if x is None:
            out.append(None)
        elif i < 2:  # images / pyramids: folded only into the batch
            if not into_batch:
                out.append(x)
            elif isinstance(x, Pyramid):
                lv = x.levels if b else [t.unsqueeze(0).expand(V, *t.shape) for t in x.levels]
                out.append(Pyramid([t.flatten(0, 1) for t in lv], None, x.rounded))
            else:
                out.append(rep(x, b).flatten(0, 1))
        else:  # pts (V, B, N, 2), valid (V, B, N), init_pts (V, B, N, 2)
            x = rep(x, b)
            out.append(x.flatten(0, 1) if into_batch else x.movedim(0, 1).flatten(1, 2))
    if into_batch:
        B = out[2].shape[0] // V

        def unfold(y):
            return y.unflatten(0, (V, B))
    else:
        N = out[2].shape[1] // V

        def unfold(y):
            return y.unflatten(1, (V, N)).movedim(1, 0)
    return out, unfold


def _vsize(x) -> int:
    return x.levels[0].shape[0] if isinstance(x, Pyramid) else x.shape[0]
