"""Linear solvers of the pose graph's Levenberg-Marquardt step: the block-sparse normal equations
``(B + U Uᵀ) x = rhs``, ``B`` symmetric positive definite with one ``p × p`` block per node and per
edge, ``U Uᵀ`` an optional low-rank part (the few long loop edges, by Woodbury).

Convention:
    * ``N`` nodes of ``p`` parameters each (4-DoF: 4, 6-DoF: 6); the unknown ``x`` and the right-hand
      side ``rhs`` are ``(N, p)`` float (float64 or float32) on the system's device.
    * The matrix part ``B`` (:class:`BlockSystem`): ``Hd (N, p, p)`` diagonal blocks; ``Hij (M, p, p)``
      the off-diagonal block at (row node ``ei[m]``, column node ``ej[m]``), ``ei, ej (M,)`` int64,
      the transposed block at ``(ej[m], ei[m])`` implied. Only the lower triangle of ``Hd`` is read by
      the LAPACK solver, the whole block by the others.
    * The low-rank part ``U`` (banded methods only, else None): the long ("far") edges' weighted
      Jacobians ``(rd, 2p, F)`` for ``rd`` residual rows per edge; column ``f·rd + r`` of ``U (Np, F·rd)``
      holds row ``r`` of far edge ``f``: its first ``p`` entries at node ``fi[f]``, the last ``p`` at
      node ``fj[f]`` (the nodes given to :func:`prepare_solver`).
    * :func:`solve` returns ``(x (N, p), ok)``, ``x`` in ``rhs``'s dtype and device; ``ok`` is False
      when a factorisation fails (not positive definite) or ``x`` is not finite.

Methods (``SOLVERS``): ``"dense"`` (torch Cholesky of the full ``Np × Np`` matrix; the CUDA default),
``"banded"`` (torch block cyclic reduction of the edges at most ``band`` nodes apart + Woodbury for
``U``), ``"lapack_banded"`` (scipy's LAPACK band Cholesky ``dpbtrf`` / ``dtbtrs`` + the same
Woodbury, float64 on the host) and ``"splu"`` (scipy.sparse SuperLU of the whole matrix, float64 on
the host); ``"auto"`` is :func:`choose_solver`'s pick. The scipy methods solve detached values
(the pose graph differentiates its optimum by the implicit-function theorem, not through the
solver). With ``"dense"`` and ``"splu"`` every edge is in the matrix part (no ``U``).
"""

from __future__ import annotations

from typing import Optional

import torch

from .._checks import check_int

__all__ = ["SOLVERS", "BlockSystem", "check_solver_options", "choose_solver", "dense_matrix",
           "prepare_solver", "solve"]

SOLVERS = ("auto", "dense", "banded", "lapack_banded", "splu")


def check_solver_options(solver: str, band: int) -> int:
    """Check the ``solver`` name (one of ``SOLVERS``) and ``band`` (a positive integer: the node
    distance treated as banded); returns ``band`` as an int.

    Raises:
        ValueError: naming ``solver`` or ``band`` and the value given.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver: expected one of {SOLVERS}, got {solver!r}")
    return check_int(band, "band", minimum=1)


class BlockSystem:
    """Block normal equations. ``Hd (N, p, p)`` diagonal blocks of the matrix part, ``(ei, ej,
    Hij (M, p, p))`` off-diagonal blocks (row node ei, column node ej; the transpose is implied),
    ``U`` or None: the low-rank part ``U Uᵀ`` (long edges, Woodbury), passed compactly as the long
    edges' weighted Jacobians ``(rd, 2p, F)`` (column ``f·rd + r`` of U holds row r of edge f's at
    its two nodes); the banded solvers scatter it into their right-hand-side buffers."""

    def __init__(self, Hd, ei, ej, Hij, U):
        self.Hd, self.ei, self.ej, self.Hij, self.U = Hd, ei, ej, Hij, U


def dense_matrix(Hd, ei, ej, Hij):
    """The full ``(N·p, N·p)`` matrix of the blocks (module docstring), node-major."""
    N, p = Hd.shape[:2]
    H = Hd.new_zeros(N, p, N, p)
    ar = torch.arange(N, device=Hd.device)
    H[ar, :, ar, :] = Hd
    a = torch.arange(p, device=Hd.device)
    if ei.numel():
        H.index_put_((ei[:, None, None], a[None, :, None], ej[:, None, None], a[None, None, :]), Hij, accumulate=True)
        H.index_put_((ej[:, None, None], a[None, :, None], ei[:, None, None], a[None, None, :]), Hij.mT,
                     accumulate=True)
    return H.reshape(N * p, N * p)


def _solve_dense(sys: BlockSystem, rhs):
    N, p = sys.Hd.shape[:2]
    H = dense_matrix(sys.Hd, sys.ei, sys.ej, sys.Hij)
    L, info = torch.linalg.cholesky_ex(H)
    x = torch.cholesky_solve(rhs.reshape(N * p, -1), L).reshape(rhs.shape)
    return x, bool(info == 0)


class _BandedCR:
    """Block-banded SPD solver by block cyclic reduction, for the edges at most ``band`` slots apart.

    Nodes are grouped ``band`` at a time into super-blocks of size ``m = band·p``, which makes the
    matrix block-tridiagonal: ``D (K, m, m)`` diagonal super-blocks, ``C (K, m, m)`` with
    ``C[k] = H[k, k+1]``; ``K`` is padded to a power of two with identity blocks. Each level
    eliminates the odd super-blocks (independent, so one batched Cholesky) and leaves a
    block-tridiagonal Schur complement on the even ones: log2(K) batched levels instead of K
    sequential block steps. The elimination is a permuted Cholesky ``B = L Lᵀ``; ``forward``
    applies ``L⁻¹`` (what Woodbury's capacitance needs, ``UᵀB⁻¹U = (L⁻¹U)ᵀ(L⁻¹U)``) and ``back``
    applies ``L⁻ᵀ``. The scatter pattern of the node blocks is built once per graph.
    """

    def __init__(self, N, p, band, ei, ej, dtype, device):
        s = band
        K = -(-N // s)
        self.N, self.p, self.s, self.m = N, p, s, s * p
        self.Kp = Kp = 1 << max(0, (K - 1).bit_length())
        m = self.m
        a = torch.arange(p, device=device)
        n = torch.arange(N, device=device)
        size = Kp * m * m

        def flat(blk, si, ai, sj, aj):  # index into D (or C with + size) of entry (si, ai; sj, aj) of block blk
            return ((blk * s + si) * p + ai) * m + sj * p + aj

        # diagonal node blocks -> D
        tgt = [flat((n // s)[:, None, None], (n % s)[:, None, None], a[None, :, None], (n % s)[:, None, None],
                    a[None, None, :]).reshape(-1)]
        src = [torch.arange(N * p * p, device=device)]
        if ei.numel():
            lo, hi = torch.minimum(ei, ej), torch.maximum(ei, ej)
            e = torch.arange(ei.shape[0], device=device)[:, None, None]
            # entry (a, b) of H[lo, hi]: Hij[a, b] when ei <= ej, else Hij[b, a]
            fwd = (ei <= ej)[:, None, None]
            sab = N * p * p + e * p * p + torch.where(fwd, a[None, :, None] * p + a[None, None, :],
                                                      a[None, None, :] * p + a[None, :, None])
            A, B = lo // s, hi // s
            same = (A == B)[:, None, None]
            ab = flat(A[:, None, None], (lo % s)[:, None, None], a[None, :, None], (hi % s)[:, None, None],
                      a[None, None, :])
            ba = flat(A[:, None, None], (hi % s)[:, None, None], a[None, None, :], (lo % s)[:, None, None],
                      a[None, :, None])
            sab = sab.expand(-1, p, p)
            # same super-block: both triangles into D; neighbouring super-blocks: H[lo, hi] into C[A]
            tgt += [torch.where(same, ab, ab + size).reshape(-1), ba[same.expand(-1, p, p)]]
            src += [sab.reshape(-1), sab[same.expand(-1, p, p)]]
        self.tgt, self.src = torch.cat(tgt), torch.cat(src)
        base = torch.zeros(2 * size, dtype=dtype, device=device)
        pad = torch.arange(N, Kp * s, device=device)  # padding nodes: identity blocks
        base.index_put_((flat((pad // s)[:, None], (pad % s)[:, None], a[None, :], (pad % s)[:, None], a[None, :])
                         .reshape(-1),), torch.ones((), dtype=dtype, device=device))
        self.base = base

    def factor(self, Hd, Hij):
        vals = torch.cat([Hd.reshape(-1), Hij.reshape(-1)])
        buf = self.base.index_add(0, self.tgt, vals[self.src])
        Kp, m = self.Kp, self.m
        D, C = buf[:Kp * m * m].reshape(Kp, m, m), buf[Kp * m * m:].reshape(Kp, m, m)
        levels = []
        ok = torch.ones((), dtype=torch.bool, device=Hd.device)
        while D.shape[0] > 1:
            De, Do, Ce, Co = D[0::2], D[1::2], C[0::2], C[1::2]
            Lo, info = torch.linalg.cholesky_ex(Do)
            ok = ok & (info == 0).all()
            # G = Lo⁻¹ [Ceᵀ, Co]: odd block i couples to even i (Ceᵀ) and even i + 1 (Co)
            G = torch.linalg.solve_triangular(Lo, torch.cat([Ce.mT, Co], -1), upper=False)
            GG = G.mT @ G  # [[G1ᵀG1, G1ᵀG2], [G2ᵀG1, G2ᵀG2]] in one batched product
            Dn = De - GG[:, :m, :m]
            Dn[1:] -= GG[:-1, m:, m:]
            levels.append((Lo, G))
            D, C = Dn, -GG[:, :m, m:]
        Lf, info = torch.linalg.cholesky_ex(D)
        return (levels, Lf), bool(ok & (info == 0).all())

    def set_far(self, fi, fj, rd):
        """Scatter pattern of the far edges' Jacobian ``(rd, 2p, F)`` into the right-hand sides
        ``[rhs, U]`` in block layout ``(Kp·s, p, 1 + k)``, ``k = F·rd`` (U column ``f·rd + r``)."""
        F, p = fi.shape[0], self.p
        self.k = k = F * rd
        a = torch.arange(p, device=fi.device)[None, :, None]
        col = 1 + torch.arange(F, device=fi.device)[None, None, :] * rd + torch.arange(rd, device=fi.device)[:, None, None]
        self.pos_u = torch.cat([(fi[None, None, :] * p + a) * (k + 1) + col,
                                (fj[None, None, :] * p + a) * (k + 1) + col], 1).reshape(-1)
        self.rbuf = None

    def far_blocks(self, rhs, Jf):
        """``[rhs, U]`` as ``(Kp, m, 1 + k)`` zero-padded, in a buffer reused across iterations
        (the forward elimination does not write into it)."""
        if self.rbuf is None:
            self.rbuf = rhs.new_zeros(self.Kp * self.s, self.p, self.k + 1)
        b = self.rbuf
        b.view(-1)[self.pos_u] = Jf.reshape(-1)
        b[:self.N, :, 0] = rhs
        return b.reshape(self.Kp, self.m, -1)

    def to_blocks(self, rhs):
        """``(N, p, r)`` -> ``(Kp, m, r)`` zero-padded."""
        b = rhs.new_zeros(self.Kp * self.s, self.p, rhs.shape[-1])
        b[:self.N] = rhs
        return b.reshape(self.Kp, self.m, -1)

    def forward(self, fac, b):
        """``L⁻¹ b`` as the list of per-level pieces (odd blocks of each level, then the last)."""
        levels, Lf = fac
        m = self.m
        ws = []
        for Lo, G in levels:
            w = torch.linalg.solve_triangular(Lo, b[1::2], upper=False)
            Gw = G.mT @ w
            b = b[0::2] - Gw[:, :m]
            b[1:] -= Gw[:-1, m:]
            ws.append(w)
        ws.append(torch.linalg.solve_triangular(Lf, b, upper=False))
        return ws

    def back(self, fac, ws):
        """``L⁻ᵀ`` of the forward pieces -> ``(N, p, r)``."""
        levels, Lf = fac
        x = torch.linalg.solve_triangular(Lf.mT, ws[-1], upper=True)
        for (Lo, G), w in zip(reversed(levels), reversed(ws[:-1])):
            xx = torch.cat([x, torch.cat([x[1:], torch.zeros_like(x[:1])])], 1)  # (x_even_i; x_even_i+1)
            xo = torch.linalg.solve_triangular(Lo.mT, w - G @ xx, upper=True)
            x = torch.stack([x, xo], 1).reshape(-1, *x.shape[1:])
        return x.reshape(self.Kp * self.s, self.p, -1)[:self.N]


def _solve_banded(sys: BlockSystem, rhs, cr: _BandedCR):
    """``(B + U Uᵀ) x = rhs`` with Woodbury on top of the cyclic-reduction factor of B:
    ``x = L⁻ᵀ (w_r − W_U c)``, ``c = (I + W_Uᵀ W_U)⁻¹ W_Uᵀ w_r``, ``W = L⁻¹ [rhs, U]``.
    ``sys.U`` is the far edges' compact ``(rd, 2p, F)`` Jacobian (see :meth:`_BandedCR.set_far`)."""
    fac, ok = cr.factor(sys.Hd, sys.Hij)
    ws = cr.forward(fac, cr.to_blocks(rhs[..., None]) if sys.U is None else cr.far_blocks(rhs, sys.U))
    if sys.U is not None:
        k = cr.k
        # [W_Uᵀ w_r, W_UᵀW_U] summed over the forward pieces: one product per piece, no concatenation
        P = sum(w.reshape(-1, k + 1)[:, 1:].mT @ w.reshape(-1, k + 1) for w in ws)
        cap = torch.eye(k, dtype=rhs.dtype, device=rhs.device) + P[:, 1:]
        Lc, info = torch.linalg.cholesky_ex(cap)
        ok = ok and bool(info == 0)
        c = torch.cholesky_solve(P[:, :1], Lc)
        ws = [w[..., :1] - w[..., 1:] @ c for w in ws]
    return cr.back(fac, ws)[..., 0], ok


class _LapackBanded:
    """LAPACK band Cholesky (``dpbtrf``) of the matrix part B, for the edges at most ``band``
    slots apart, plus Woodbury for the low-rank part: only the forward triangular solves
    ``W = L⁻¹ [rhs, U]`` are needed for the capacitance (``UᵀB⁻¹U = W_Uᵀ W_U``), then one
    backward solve ``x = L⁻ᵀ (w_r − W_U c)`` — half of ``solveh_banded`` on all the columns.
    The scatter pattern of the blocks into LAPACK's lower band storage is built once per graph.
    """

    def __init__(self, N, p, band, ei, ej, fi, fj, rd):
        from scipy.linalg import get_lapack_funcs

        self.N, self.p = N, p
        self.u = u = band * p + p - 1
        self.n = N * p
        a = torch.arange(p)
        node = torch.arange(N)
        # storage: torch (n, u + 1) row-major == LAPACK's column-major (u + 1, n), ab[r - c, c] = H[r, c]
        rows = (node[:, None, None] * p + a[None, :, None]).expand(N, p, p)
        cols = (node[:, None, None] * p + a[None, None, :]).expand(N, p, p)
        keep = (rows >= cols).reshape(-1)
        tgt = [(cols * (u + 1) + rows - cols).reshape(-1)[keep]]
        src = [torch.arange(N * p * p)[keep]]
        if ei.numel():
            ei, ej = ei.cpu(), ej.cpu()
            hi, lo = torch.maximum(ei, ej), torch.minimum(ei, ej)
            e = torch.arange(ei.shape[0])[:, None, None]
            # entry (a, b) of H[hi, lo] = Hij[b, a] when ei <= ej (Hij = H[ei, ej]), else Hij[a, b]
            sab = N * p * p + e * p * p + torch.where((ei >= ej)[:, None, None], a[None, :, None] * p + a[None, None, :],
                                                      a[None, None, :] * p + a[None, :, None])
            r_ = hi[:, None, None] * p + a[None, :, None]
            c_ = lo[:, None, None] * p + a[None, None, :]
            tgt.append((c_ * (u + 1) + r_ - c_).reshape(-1))
            src.append(sab.reshape(-1))
        self.tgt, self.src = torch.cat(tgt), torch.cat(src)
        # right-hand sides column-major for LAPACK: a torch (1 + k, n) row-major buffer, reused;
        # far edge f's Jacobian rows r (U's columns 1 + f·rd + r) sit at nodes fi[f] and fj[f]
        F = fi.shape[0]
        self.k = k = F * rd
        self.buf = torch.zeros(1 + k, self.n, dtype=torch.float64)
        # L⁻¹ of a column that is zero above node min(fi, fj) is zero there too: the far edges go
        # to the columns in order of that first node, and each chunk of columns is solved only on
        # the rows from its first nonzero one (the zeros are exact, the result is the same)
        fi, fj = fi.cpu(), fj.cpu()
        first = torch.minimum(fi, fj)
        order = torch.argsort(first, stable=True)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(F)
        chunk = max(1, 16 // rd)
        self.chunks = [(1 + c * rd, 1 + min(F, c + chunk) * rd, int(first[order[c]]) * p)
                       for c in range(0, F, chunk)]
        col = 1 + rank[None, None, :] * rd + torch.arange(rd)[:, None, None]  # (rd, 1, F)
        self.pos_u = torch.cat([col * self.n + fi[None, None, :] * p + a[None, :, None],
                                col * self.n + fj[None, None, :] * p + a[None, :, None]], 1).reshape(-1)
        self.pbtrf, self.tbtrs = get_lapack_funcs(("pbtrf", "tbtrs"), dtype="float64")

    def solve(self, sys: BlockSystem, rhs):
        import numpy as np

        N, p, n, u = self.N, self.p, self.n, self.u
        vals = torch.cat([sys.Hd.detach().reshape(-1), sys.Hij.detach().reshape(-1)]).cpu().double()
        ab = torch.zeros(n * (u + 1), dtype=torch.float64).index_add_(0, self.tgt, vals[self.src])
        c, info = self.pbtrf(ab.reshape(n, u + 1).numpy().T, lower=1, overwrite_ab=1)
        if info != 0:
            return rhs, False
        k = 0 if sys.U is None else self.k
        Rt = self.buf[:1 + k]
        if k:
            Rt.zero_()
            Rt.view(-1)[self.pos_u] = sys.U.detach().reshape(-1).cpu().double()
        Rt[0] = rhs.detach().reshape(n)
        _, info = self.tbtrs(c, Rt[:1].numpy().T, uplo="L", trans="N", overwrite_b=1)
        for c0, c1, r0 in self.chunks if k else ():
            y, info_u = self.tbtrs(c[:, r0:], Rt[c0:c1, r0:].numpy().T, uplo="L", trans="N")
            Rt[c0:c1, r0:] = torch.from_numpy(y).T
            info = info or info_u
        if info != 0:
            return rhs, False
        W = Rt.T  # (n, k + 1), column-major
        z = W[:, :1]
        ok = True
        if k:
            WU = W[:, 1:]
            # WUᵀWU by chunk rows of the lower triangle, each over its nonzero rows only
            G = torch.zeros(k, k, dtype=torch.float64)
            for c0, c1, r0 in self.chunks:
                G[c0 - 1:c1 - 1, :c1 - 1] = Rt[c0:c1, r0:] @ Rt[1:c1, r0:].T
            cap = torch.eye(k, dtype=torch.float64) + G.tril() + G.tril(-1).T
            Lc, cinfo = torch.linalg.cholesky_ex(cap)
            ok = bool(cinfo == 0)
            z = z - WU @ torch.cholesky_solve(WU.T @ z, Lc)
        x, info = self.tbtrs(c, np.asfortranarray(z.numpy()), uplo="L", trans="T", overwrite_b=1)
        x = torch.from_numpy(np.ascontiguousarray(x)).to(rhs).reshape(N, p)
        return x, ok and info == 0 and bool(torch.isfinite(x).all())


def _solve_splu(sys: BlockSystem, rhs):
    import numpy as np
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    N, p = sys.Hd.shape[:2]
    a = torch.arange(p)
    node = torch.arange(N)
    ei, ej = sys.ei.cpu(), sys.ej.cpu()
    Hij = sys.Hij.detach().cpu().double()
    rows = torch.cat([(node[:, None, None] * p + a[None, :, None]).expand(N, p, p).reshape(-1),
                      (ei[:, None, None] * p + a[None, :, None]).expand(-1, p, p).reshape(-1),
                      (ej[:, None, None] * p + a[None, None, :]).expand(-1, p, p).reshape(-1)])
    cols = torch.cat([(node[:, None, None] * p + a[None, None, :]).expand(N, p, p).reshape(-1),
                      (ej[:, None, None] * p + a[None, None, :]).expand(-1, p, p).reshape(-1),
                      (ei[:, None, None] * p + a[None, :, None]).expand(-1, p, p).reshape(-1)])
    vals = torch.cat([sys.Hd.detach().cpu().double().reshape(-1), Hij.reshape(-1), Hij.reshape(-1)])
    H = sp.csc_matrix((vals.numpy(), (rows.numpy(), cols.numpy())), shape=(N * p, N * p))
    try:
        lu = splu(H, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        x = lu.solve(rhs.detach().cpu().double().reshape(N * p, -1).numpy())
    except RuntimeError:  # exactly singular
        return rhs, False
    x = torch.from_numpy(np.ascontiguousarray(x)).to(rhs).reshape(rhs.shape)
    return x, bool(torch.isfinite(x).all())


def prepare_solver(method: str, N: int, p: int, band: int, ei: torch.Tensor, ej: torch.Tensor,
                   fi: torch.Tensor, fj: torch.Tensor, rd: int, dtype: torch.dtype,
                   device: torch.device) -> Optional[object]:
    """The per-graph set-up of ``method`` (its scatter patterns, built once and reused by every
    :func:`solve` on systems of this graph), or None for ``"dense"`` and ``"splu"``.

    Convention:
        method: a concrete method (not ``"auto"``: see :func:`choose_solver`); N nodes of p
        parameters; band: the largest node distance of the matrix part's edges.
        ei, ej: ``(M,)`` int64, the matrix part's off-diagonal blocks (as :class:`BlockSystem`).
        fi, fj: ``(F,)`` int64, the far edges' nodes (the low-rank part, ``F`` may be 0); rd: their
        residual rows per edge. dtype, device: the systems' (the LAPACK set-up is float64 on the host).
    """
    if method == "banded":
        cr = _BandedCR(N, p, band, ei, ej, dtype, device)
        if fi.numel():
            cr.set_far(fi, fj, rd)
        return cr
    if method == "lapack_banded":
        return _LapackBanded(N, p, band, ei, ej, fi, fj, rd)
    return None


def solve(sys: BlockSystem, rhs: torch.Tensor, method: str, cr=None):
    """Solve ``(B + U Uᵀ) x = rhs`` with a concrete ``method``; the low-rank part by Woodbury:
    ``(B + U Uᵀ)⁻¹ = B⁻¹ − B⁻¹U (I + Uᵀ B⁻¹ U)⁻¹ Uᵀ B⁻¹`` (B SPD, the capacitance SPD too).

    Convention:
        sys: the system (module docstring); rhs: ``(N, p)`` float. cr: :func:`prepare_solver`'s
        set-up of the same graph and method (None for ``"dense"`` / ``"splu"``).
        Returns ``(x (N, p), ok)``: ``ok`` False when a factorisation failed or ``x`` is not finite
        (``x`` is then no solution: the caller rejects the step).
    """
    if method == "dense":
        x, ok = _solve_dense(sys, rhs[..., None])
        return x[..., 0], ok
    if method == "splu":
        x, ok = _solve_splu(sys, rhs[..., None])
        return x[..., 0], ok
    if method == "banded":
        return _solve_banded(sys, rhs, cr)
    return cr.solve(sys, rhs)


def choose_solver(method: str, device: torch.device, n_far: int, N: int, p: int, rd: int) -> str:
    """The concrete method for ``method`` (itself unless ``"auto"``) on a graph of N nodes of p
    parameters with ``n_far`` far edges of ``rd`` residual rows each (the low-rank part)."""
    if method != "auto":
        return method
    if device.type != "cpu":
        return "dense"
    # the Woodbury part costs O(N p k²) for k long-edge residual rows: with 20 loop edges (k = 80,
    # 120) at N = 1,000 LAPACK's band Cholesky + Woodbury is the fastest (~2x SuperLU, ~2x the
    # torch cyclic reduction; at N = 128 ~4x dense); with 100 loop edges at N = 5,000 SuperLU is
    # ~2x faster than it (benchmarks/bench_pose_graph.py). Without scipy: the torch banded solver.
    try:
        import scipy  # noqa: F401
    except ImportError:  # pragma: no cover
        return "dense" if N * p <= 512 else "banded"  # tiny: op overhead dominates any structure
    if N * p <= 128:
        return "dense"
    return "lapack_banded" if n_far * rd <= 128 else "splu"

