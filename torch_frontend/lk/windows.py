"""The LK's per-level machinery, shared by both paths (``docs/lk.md``): OpenCV's bilinear weights,
the padded levels and their window views, the template windows (grey levels and Scharr
derivatives), the window differences of an iteration, the 2x2 gradient systems, and the per-size
constant tables.

Both paths compute every inexact float value (the template, ``b``, the step and its tests) with
this code, which is why their results agree bit for bit. Every window op runs on the flattened
patch with a row pitch (:func:`_interp_flat`): the four bilinear taps are offsets ``0, 1, pitch,
pitch + 1`` into one contiguous run per point, and the column that wraps into the next row is junk
that drops out because the template derivatives there are zero (:func:`_pitch`).

Convention:
    Points are pixels ``(x, y)`` with pixel centres at integer coordinates, kept points-last
    ``(2, m)`` (``m`` lanes = streams x points); windows are points-first ``(m, ...)``. Window
    origins are addressed as ``u = origin + win`` in the level padded by ``win + 1``
    (:class:`_Level`). Grey levels of the windows are in 1/32 units (OpenCV's fixed point).
"""

from __future__ import annotations

import math

import torch

from .. import _tuning
from .._autodiff import straight_through
from .._cache import cached

_W_BITS = 14
_W_ONE = float(1 << _W_BITS)
_FLT_SCALE = 2.0**-20
_FLT_EPSILON = 1.1920928955078125e-07  # FLT_EPSILON
# OpenCV's oscillation test ``|d| < 0.01`` compares a float with a double. For a float32 ``d`` it is
# ``d <= float32(0.01)`` (float32(0.01) < 0.01 and the next float32 is > 0.01); for float64 ``d``
# it is ``d <= nextafter(0.01, 0)``. Both as ``<=`` on the tensor's own dtype: no float64 copy.
_OSC = {torch.float32: 0.009999999776482582, torch.float64: math.nextafter(0.01, 0.0)}

# the 8-bit emulation's roundings: the rounded value, the derivative of the float form
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


@cached(128)
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


@cached(32)
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
        # the capturable path's step matrices ((-A22, A12), (A12, -A11)) 2^-20, and their negatives
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


@cached(64)
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


def _window_diff(p, iv, lane, J, jview, jstr, offs, k: dict, spanm1, fixed: bool, iv_init: bool = False):
    """The window difference of one iteration, ``J(p + x) - I(x)`` over the window in the pitched
    layout: ``(m, wh * (ww + 1))`` (1/32 grey levels; OpenCV's integers in fixed point), and the
    lanes whose window origin ``floor(p)`` is inside ``[-win, size)`` ``(m,)`` bool (the others read
    clamped, in-bounds windows). Shared by both paths (the float values must be computed by the same
    code); arguments as :func:`.eager._lk_step`."""
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
            G[..., :nS].mul_(edge.to(G.dtype))  # (``G[...] *=`` would add __setitem__'s copy_ onto itself)
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


@cached(64)
def _lane_index(B: int, N: int, device) -> torch.Tensor:
    """``(B N,)`` int64: the stream of each lane (cached: no per-call upload, no host sync)."""
    return torch.arange(B, device=device).repeat_interleave(N, output_size=B * N)

