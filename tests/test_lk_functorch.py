"""``track_lk`` under ``torch.func`` and activation checkpointing.

* ``vmap`` over an outer batch ``V`` (images ``(V, B, 1, H, W)``, points ``(V, B, N, 2)``, also with
  shared images ``in_dims=None``, mixed, nested, and a pyramid closed over) gives the per-``v``
  calls' values bit for bit (the vmapped dimension is folded into the call through public
  ``autograd.Function`` gateways, see ``torch_frontend.lk.transforms``);
* ``grad`` / ``jacrev`` through ``vmap`` equal autograd of the flattened call exactly;
* forward mode (``jvp``, ``jacfwd``, ``hessian``, ``torch.autograd.forward_ad`` dual tensors) w.r.t.
  the points and float images equals the reverse-mode J v to float64 precision, both grad modes,
  both paths; the primal values are those of the plain call;
* ``vmap`` over the primals of a derivative transform raises a clear ``NotImplementedError``;
* ``torch.utils.checkpoint`` (non-reentrant) gives the same gradients bit for bit;
* the per-size constant caches never keep a tensor wrapped by a transform.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.autograd.forward_ad as fwAD
from torch.func import grad, hessian, jacfwd, jacrev, jvp, vmap
from torch.utils.checkpoint import checkpoint

from tests.conftest import load_gray, sample_frames
from torch_frontend import lk
from torch_frontend._cache import holds_plain_tensors
from torch_frontend.lk import track_lk
from torch_frontend.pyramid import build_pyramid

# torch scripts its forward-AD decompositions on the first dual tensor (its own deprecation warning)
pytestmark = [pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning"),
              pytest.mark.usefixtures("single_thread")]

MODES = ("unrolled", "implicit")
LEVELS = 2
#: float64 agreement of forward- and reverse-mode derivatives (observed ~1e-14 relative)
FWD_REV_RTOL = 1e-10


@pytest.fixture(scope="module")
def data():
    """Real EuRoC crops: ``V = 2`` outer x ``B = 2`` streams of consecutive 72x96 crops (uint8
    ``(V, B, 1, H, W)``) and ``N = 6`` points per stream (float64 ``(V, B, N, 2)``: corners off the
    integer grid, one near the border, one outside the image)."""
    fr = [load_gray(p) for p in sample_frames("cam0")]
    offs = [(150, 300), (200, 380), (120, 250), (260, 420)]
    prev, nxt, pts = [], [], []
    rng = np.random.default_rng(0)
    for i, (y, x) in enumerate(offs):
        a, b = fr[i % 2][y:y + 72, x:x + 96], fr[i % 2 + 1][y:y + 72, x:x + 96]
        p = np.concatenate([rng.uniform([20, 20], [76, 52], (4, 2)), [[2.5, 30.25], [120.0, 10.0]]])
        prev.append(a), nxt.append(b), pts.append(p)
    u8 = lambda L: torch.from_numpy(np.stack(L)).view(2, 2, 1, 72, 96)  # noqa: E731
    return u8(prev), u8(nxt), torch.from_numpy(np.stack(pts)).view(2, 2, 6, 2)


def _per_v(fn, *args, in_dims):
    """``fn`` called once per ``v`` (the vmap reference): outputs stacked along a new dim 0."""
    V = next(a.shape[d] for a, d in zip(args, in_dims) if d is not None)
    outs = [fn(*(a if d is None else a.select(d, v) for a, d in zip(args, in_dims))) for v in range(V)]
    return tuple(torch.stack(o) for o in zip(*outs))


def _close(a, b):
    return (a - b).abs().max() <= FWD_REV_RTOL * max(1.0, float(b.abs().max()))


def _equal(a, b):
    return all(torch.equal(x, y) for x, y in zip(a, b))


# ---------------------------------------------------------------------- vmap (values)
@pytest.mark.parametrize("capturable", [False, True], ids=["eager", "capturable"])
@pytest.mark.parametrize("kind", ["uint8", "float64"])
def test_vmap_outer_batch_bit_for_bit(data, kind, capturable, device):
    I, J, p = (x.to(device) for x in data)
    if kind == "float64":
        I, J = I.double(), J.double()
    valid = torch.ones(p.shape[:-1], dtype=torch.bool, device=device)
    valid[1, 0, 2] = False
    init = p + torch.tensor([0.75, -0.5], dtype=p.dtype, device=device)
    kw = dict(max_level=LEVELS, capturable=capturable)

    def f(a, b, q, v, g):
        return track_lk(a, b, q, v, init_pts=g, forward_backward=True, **kw)

    for dims in [(0, 0, 0, 0, 0), (None, None, 0, 0, 0), (None, 0, 0, None, 0), (0, None, None, 0, None)]:
        args = [x if d == 0 else x[0] for x, d in zip((I, J, p, valid, init), dims)]
        got = vmap(f, in_dims=dims)(*args)
        ref = _per_v(f, *args, in_dims=dims)
        assert got[0].shape == p.shape and got[1].shape == valid.shape
        assert _equal(got, ref), dims
    assert not got[1].all() and got[1].any()  # a real mix of tracked and lost lanes


def test_vmap_nested_and_pyramid(data):
    I, J, p = data
    kw = dict(max_level=LEVELS)
    # two vmapped levels (V and B), one stream per innermost call
    got = vmap(vmap(lambda a, b, q: track_lk(a[None], b[None], q[None], **kw)))(I[:, :, 0], J[:, :, 0], p)
    ref = track_lk(I.flatten(0, 1), J.flatten(0, 1), p.flatten(0, 1), **kw)
    assert torch.equal(got[0][:, :, 0].flatten(0, 1), ref[0]) and torch.equal(got[1][:, :, 0].flatten(0, 1), ref[1])
    # a pyramid closed over, vmapped points (folded into the points: the pyramid is not rebuilt)
    P, Q = build_pyramid(I[0], LEVELS), build_pyramid(J[0], LEVELS)
    got = vmap(lambda q: track_lk(P, Q, q, **kw))(p)
    assert _equal(got, _per_v(lambda q: track_lk(P, Q, q, **kw), p, in_dims=(0,)))

    # pyramids built inside the vmapped function (batched levels; one shared): folded level by level
    def both(a, b, q):
        return track_lk(build_pyramid(a, LEVELS, False), build_pyramid(b, LEVELS, False), q, **kw)

    def shared_prev(b, q):
        return track_lk(P, build_pyramid(b, LEVELS, False), q, **kw)

    assert _equal(vmap(both)(I, J, p), _per_v(both, I, J, p, in_dims=(0, 0, 0)))
    assert _equal(vmap(shared_prev)(J, p), _per_v(shared_prev, J, p, in_dims=(0, 0)))


# ---------------------------------------------------------------------- reverse mode through vmap
@pytest.mark.parametrize("mode", MODES)
def test_grad_and_jacrev_through_vmap(data, mode):
    I, J, p = (x.double() for x in data)
    V, B, N, _ = p.shape
    w = torch.randn(p.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    kw = dict(max_level=LEVELS, grad_mode=mode)

    def loss(a, b, q):
        return (vmap(lambda x, y, z: track_lk(x, y, z, **kw)[0])(a, b, q) * w).sum()

    g = grad(loss, argnums=(0, 1, 2))(I, J, p)
    leaves = [x.clone().requires_grad_() for x in (I, J, p)]
    flat = track_lk(*(x.flatten(0, 1) for x in leaves), **kw)[0].view(p.shape)
    ref = torch.autograd.grad((flat * w).sum(), leaves)
    assert _equal(g, ref)
    assert ref[2].abs().sum() > 0 and ref[0].abs().sum() > 0
    Jr = jacrev(lambda q: vmap(lambda x, y, z: track_lk(x, y, z, **kw)[0])(I, J, q))(p)
    n = p.numel()
    assert _close(w.flatten() @ Jr.reshape(n, n), ref[2].flatten())  # w^T J = the vjp


# ---------------------------------------------------------------------- forward mode
@pytest.mark.parametrize("capturable", [False, True], ids=["eager", "capturable"])
@pytest.mark.parametrize("mode", MODES)
def test_jvp_matches_reverse(data, mode, capturable, device):
    """jvp w.r.t. points and both float images = reverse-mode J v (float64); jacfwd = jacrev; dual
    tensors of ``torch.autograd.forward_ad`` alike; the primal is the plain call's value."""
    I, J, p = (x[0].double().to(device) for x in data)
    gen = torch.Generator().manual_seed(2)
    tI, tJ, tp = (torch.randn(x.shape, generator=gen, dtype=torch.float64).to(device) for x in (I, J, p))

    def f(a, b, q):
        return track_lk(a, b, q, max_level=LEVELS, capturable=capturable, grad_mode=mode, forward_backward=True)[0]

    prim, tan = jvp(f, (I, J, p), (tI, tJ, tp))
    Jr = jacrev(f, argnums=(0, 1, 2))(I, J, p)
    ref = sum((Jx * tx).flatten(p.dim()).sum(-1) for Jx, tx in zip(Jr, (tI, tJ, tp)))
    assert torch.equal(prim, f(I, J, p))
    assert ref.abs().max() > 0.1 and _close(tan, ref)
    assert _close(jacfwd(f, argnums=2)(I, J, p), Jr[2])
    with fwAD.dual_level():
        out = f(*(fwAD.make_dual(x, t) for x, t in zip((I, J, p), (tI, tJ, tp))))
        prim2, tan2 = fwAD.unpack_dual(out)
    assert torch.equal(prim2, prim) and _close(tan2, ref)


@pytest.mark.parametrize("mode", MODES)
def test_jvp_through_vmap_and_hessian(data, mode):
    I, J, p = (x.double() for x in data)
    kw = dict(max_level=LEVELS, grad_mode=mode)
    gen = torch.Generator().manual_seed(3)
    tp = torch.randn(p.shape, generator=gen, dtype=torch.float64)
    _, tan = jvp(lambda q: vmap(lambda x, y, z: track_lk(x, y, z, **kw)[0])(I, J, q), (p,), (tp,))
    _, ref = jvp(lambda q: track_lk(I.flatten(0, 1), J.flatten(0, 1), q, **kw)[0], (p.flatten(0, 1),),
                 (tp.flatten(0, 1),))
    assert torch.equal(tan, ref.view(p.shape))
    # second derivatives: forward-over-reverse = reverse-over-reverse (one stream, 4 points)
    q0 = p[0, 0, :4].unsqueeze(0)

    def energy(q):
        return (track_lk(I[0, :1], J[0, :1], q, **kw)[0] ** 2).sum()

    H1, H2 = hessian(energy)(q0), jacrev(jacrev(energy))(q0)
    assert H2.abs().max() > 0.1 and _close(H1, H2)


def test_float32_forward_mode(data):
    """float32 points, uint8 images (the fixed-point path): the jvp primal is the plain call's
    value bit for bit; jacfwd agrees with jacrev to float32 rounding."""
    I, J, p = data[0][0], data[1][0], data[2][0].float()

    def f(q):
        return track_lk(I, J, q, max_level=LEVELS, grad_mode="implicit")[0]

    prim, _ = jvp(f, (p,), (torch.ones_like(p),))
    assert torch.equal(prim, f(p))
    Jf, Jr = jacfwd(f)(p), jacrev(f)(p)
    assert Jr.abs().max() > 0.5 and (Jf - Jr).abs().max() <= 1e-4


# ---------------------------------------------------------------------- limitation, caches
def test_vmap_over_derivative_raises(data):
    I, J, p = (x.double() for x in data)

    def loss(a, b, q):
        return track_lk(a, b, q, max_level=LEVELS)[0].sum()

    with pytest.raises(NotImplementedError, match="vmap over the primals of a derivative transform"):
        vmap(grad(loss, argnums=2))(I, J, p)
    with pytest.raises(NotImplementedError, match="grad\\(vmap\\(f\\)\\)"):
        vmap(lambda a, b, q: jvp(lambda z: loss(a, b, z), (q,), (q,))[1])(I, J, p)


def test_caches_keep_plain_tensors(data):
    """Constants first built under grad / jvp are plain tensors (a wrapped one would outlive its
    transform: a later nested transform failed with functorch's "escaped?" assertion); a given
    pyramid's padded-level cache is not written under a transform."""
    I, J, p = data[0][0].double(), data[1][0].double(), data[2][0]
    caches = [lk._level_tables, lk._win_consts, lk._level_offsets, lk._lane_index, lk._capturable_tables,
              lk._capturable_consts, lk._patch_offsets]
    for c in caches:
        c.cache_clear()
    P, Q = build_pyramid(I, LEVELS), build_pyramid(J, LEVELS)
    n0 = (len(P._padded), len(Q._padded))
    for cap in (False, True):
        def f(q, cap=cap):
            return track_lk(P, Q, q, max_level=LEVELS, capturable=cap, grad_mode="implicit")[0]

        jvp(f, (p,), (torch.ones_like(p),))
        grad(lambda q: f(q).sum())(p)
    assert all(c.cache_stats().size > 0 for c in caches[:4] + caches[-1:])  # built under the transforms
    assert any(c.cache_stats().rebuilt > 0 for c in caches)  # ... as plain tensors, in the builder thread
    dev = p.device
    misses = lk._win_consts.cache_stats().misses + lk._level_tables.cache_stats().misses
    held = [lk._win_consts(21, 21, torch.float64, dev), lk._level_tables(72, 96, 21, 21, torch.float64, dev),
            lk._lane_index(1, p.shape[1], dev), lk._patch_offsets(96 + 44, 21, 21, dev)]
    assert lk._win_consts.cache_stats().misses + lk._level_tables.cache_stats().misses == misses  # hits
    assert holds_plain_tensors(held)
    assert (len(P._padded), len(Q._padded)) == n0

    def energy(q):
        return (track_lk(P, Q, q, max_level=LEVELS)[0] ** 2).sum()

    assert torch.isfinite(jacrev(jacrev(energy))(p[:, :2])).all()
    assert torch.equal(track_lk(P, Q, p, max_level=LEVELS)[0], track_lk(I, J, p, max_level=LEVELS)[0])


# ---------------------------------------------------------------------- checkpointing
@pytest.mark.parametrize("mode", MODES)
def test_checkpoint_same_gradients(data, mode):
    I, J, p = (x[0].double() for x in data)
    w = torch.randn(p.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)

    def loss(a, b, q):
        return (track_lk(a, b, q, max_level=LEVELS, grad_mode=mode)[0] * w).sum()

    leaves = [x.clone().requires_grad_() for x in (I, J, p)]
    ref = torch.autograd.grad(loss(*leaves), leaves)
    got = torch.autograd.grad(checkpoint(loss, *leaves, use_reentrant=False), leaves)
    assert _equal(got, ref) and ref[2].abs().sum() > 0
