"""F-RANSAC's hypothesis scoring, counting, best-model choice and adaptive iteration bound as one
``torch.library`` op: ``torch_frontend::ransac_score`` (``docs/kernels.md``, "F-RANSAC").

``ransac_score(F, fok, x12, eff, n, table, live?, best?, niters?, done?, thr2)
-> (best, niters, done, kbest, mask)``

* ``F (B, M, 9)`` float64: a block of ``M = 3 S`` 7-point models per problem, row-major (sample ``i``
  gave models ``3 i .. 3 i + 2`` in OpenCV's root order); ``fok (B, M)`` bool: the model exists.
* ``x12 (B, N, 4)`` float64 ``(x1, y1, x2, y2)`` of float32-rounded virtual-pinhole pixels;
  ``eff (B, N)`` bool: the slot holds a point; ``n (B,)`` int64: the problem's point count.
* ``table (R, C)`` int64: OpenCV's iteration bound ``table[n, c + 1]`` after a best count ``c``
  (``ransac.bounds._niters_table``: rows ``>= max n + 1``, ``C >= R + 1``).
* The running state ``live`` (samples of the block to take), ``best`` (best count so far, -1: none),
  ``niters`` (the bound), ``done`` (samples drawn): ``(B,)`` int64, all four or none (a fresh problem:
  the whole block, -1, ``table[n, 0]``, 0).
* ``thr2``: OpenCV's ``threshold * threshold`` (compared as float32, as ``findInliers``).

Returns the state after the block: ``best``, ``niters``, ``done`` ``(B,)`` int64; ``kbest (B,)``
int64, the model index (in ``[0, M)``) the block accepted last (-1: none); ``mask (B, N)`` bool, its
inliers (all False where ``kbest`` is -1). Problems with ``n < 15`` are passed through (OpenCV runs
LMedS for them). The per-slot error and the loop are ``_numba_ransac``'s contract; the CPU kernel is
numba (``nogil``, stream groups on the thread pool of :mod:`.ops`), the CUDA kernel Triton
(``_triton_ransac``, one launch, grid ``(B,)``, no host sync). The 7-point models stay tensor code
(``ransac.seven_point``): OpenCV's cubic and null-space steps are a few batched ops per call
whatever the sample count, while the scoring is the ``S x 3 x N`` part.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch

from .ops import _np, _np_out, _run_groups

__all__ = ["ransac_score_op", "cuda_selfcheck"]

Tensor = torch.Tensor

torch.library.define(
    "torch_frontend::ransac_score",
    "(Tensor F, Tensor fok, Tensor x12, Tensor eff, Tensor n, Tensor table, Tensor? live, Tensor? best, "
    "Tensor? niters, Tensor? done, float thr2) -> (Tensor, Tensor, Tensor, Tensor, Tensor)")


def _check(F, fok, x12, eff, n, table, state) -> None:
    B, M = F.shape[:2]
    N = x12.shape[1]
    bad = [(name, tuple(t.shape), want) for name, t, want in (
        ("F", F, (B, M, 9)), ("fok", fok, (B, M)), ("x12", x12, (B, N, 4)), ("eff", eff, (B, N)), ("n", n, (B,)))
        if tuple(t.shape) != want]
    if bad:
        raise ValueError(f"torch_frontend::ransac_score: shapes {bad} (name, got, expected)")
    if M % 3:
        raise ValueError(f"torch_frontend::ransac_score: F holds {M} models per problem, not 3 per sample")
    if table.dim() != 2:
        raise ValueError(f"torch_frontend::ransac_score: table must be (R, C), got {tuple(table.shape)}")
    given = [s is not None for s in state]
    if any(given) and not all(given):
        raise ValueError("torch_frontend::ransac_score: give all of live, best, niters, done or none")


def _as(t: Tensor, dtype: torch.dtype) -> Tensor:
    """``t`` as a contiguous ``dtype`` tensor (itself when it is one: no op)."""
    if t.dtype != dtype:
        t = t.to(dtype)
    return t if t.is_contiguous() else t.contiguous()


@torch.library.impl("torch_frontend::ransac_score", "cpu")
def _ransac_score_cpu(F: Tensor, fok: Tensor, x12: Tensor, eff: Tensor, n: Tensor, table: Tensor,
                      live: Optional[Tensor], best: Optional[Tensor], niters: Optional[Tensor],
                      done: Optional[Tensor], thr2: float) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The op on CPU tensors (numba, ``_numba_ransac.ransac_score_streams``)."""
    from ._numba_ransac import ransac_score_streams

    _check(F, fok, x12, eff, n, table, (live, best, niters, done))
    B, N = F.shape[0], x12.shape[1]
    dev = F.device
    outs = [torch.empty((B,), dtype=torch.int64, device=dev) for _ in range(4)]
    mask = torch.empty((B, N), dtype=torch.bool, device=dev)
    f64, i64, b8 = torch.float64, torch.int64, torch.bool
    a = [_np(_as(t, d)) for t, d in ((F, f64), (fok, b8), (x12, f64), (eff, b8), (n, i64), (table, i64))]
    has = live is not None
    st = [_np(_as(t, i64)) for t in (live, best, niters, done)] if has else [a[4]] * 4
    o = [_np_out(t) for t in outs] + [_np_out(mask)]

    def run(s0, s1):
        ransac_score_streams(*a, *st, has, float(thr2), *o, s0, s1)

    _run_groups(run, B)
    return (*outs, mask)


@torch.library.register_fake("torch_frontend::ransac_score")
def _ransac_score_fake(F, fok, x12, eff, n, table, live, best, niters, done, thr2):
    B, N = F.shape[0], x12.shape[1]
    return (*(n.new_empty((B,), dtype=torch.int64) for _ in range(4)), eff.new_empty((B, N), dtype=torch.bool))


@torch.library.impl("torch_frontend::ransac_score", "cuda")
def _ransac_score_cuda(F, fok, x12, eff, n, table, live, best, niters, done, thr2):
    from ._triton_ransac import ransac_score_cuda

    _check(F, fok, x12, eff, n, table, (live, best, niters, done))

    def c(t, dtype):
        return None if t is None else t.to(dtype).contiguous()

    i64 = torch.int64
    return ransac_score_cuda(c(F, torch.float64), c(fok, torch.bool), c(x12, torch.float64), c(eff, torch.bool),
                             c(n, i64), c(table, i64), c(live, i64), c(best, i64), c(niters, i64), c(done, i64),
                             float(thr2))


#: ``ransac_score_op(F, fok, x12, eff, n, table, live, best, niters, done, thr2)``
ransac_score_op = torch.ops.torch_frontend.ransac_score


# ----------------------------------------------------------------------------------- self-check
def selfcheck_case(seed: int = 5):
    """A small built-in case (CPU tensors): 3 problems (24, 40 and 12 points, one slot masked out)
    scored on random models around a true F and on its exact fits; every branch of the bookkeeping
    (acceptance, a bound reached mid-block, an exhausted block, a skipped LMedS problem)."""
    g = torch.Generator().manual_seed(seed)
    B, N, S = 3, 40, 30
    x1 = torch.rand((B, N, 2), generator=g, dtype=torch.float64) * 400.0
    x2 = x1 + torch.tensor([3.0, 0.0], dtype=torch.float64)  # a pure x translation: F = [e]x
    x2[:, ::5] += torch.rand((B, (N + 4) // 5, 2), generator=g, dtype=torch.float64) * 30.0  # outliers
    x12 = torch.cat([x1, x2], -1).to(torch.float32).to(torch.float64)
    eff = torch.ones((B, N), dtype=torch.bool)
    eff[0, 24:] = False
    eff[2, 12:] = False
    eff[1, 7] = False
    n = eff.sum(-1)
    Ft = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    F = Ft + torch.randn((B, 3 * S, 9), generator=g, dtype=torch.float64) * 2e-4
    F[:, 6] = Ft  # sample 2's first model: exact
    fok = torch.rand((B, 3 * S), generator=g) < 0.6
    fok[:, 6] = True
    # an iteration-bound table of the right shape (any values serve the check; not ransac.bounds':
    # the kernel layer imports no solver): 1000 with no model, falling with the best count
    table = (1000 - 40 * torch.arange(-1, N + 1, dtype=torch.int64)).clamp_min(3).expand(N + 1, N + 2).contiguous()
    return F, fok, x12, eff, n, table


def cuda_selfcheck(device: str = "cuda") -> Optional[str]:
    """None when the CUDA kernel gives the CPU kernel's bits on :func:`selfcheck_case` (fresh and with a
    state), else why not (run once, outside any capture)."""
    try:
        args = selfcheck_case()
        B = args[0].shape[0]
        state = (torch.full((B,), 5, dtype=torch.int64), torch.full((B,), 3, dtype=torch.int64),
                 torch.full((B,), 9, dtype=torch.int64), torch.full((B,), 2, dtype=torch.int64))
        for st in ((None,) * 4, state):
            ref = ransac_score_op(*args, *st, 1.0)
            got = ransac_score_op(*(a.to(device) for a in args), *(None if s is None else s.to(device) for s in st),
                                  1.0)
            if not all(torch.equal(r, q.cpu()) for r, q in zip(ref, got)):
                return "the CUDA RANSAC kernel gives other bits than the CPU kernel on the built-in case"
    except Exception as e:  # noqa: BLE001 - any failure: the tensor scoring runs
        return f"the CUDA RANSAC kernel failed its self-check ({type(e).__name__}: {e})"
    return None
