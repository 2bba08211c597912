"""The linear solver of each LM step: the normal equations and their Schur complement on the points (Ceres' ``SchurComplementSolver``).

``V`` (the point blocks) is block diagonal, so it is inverted 3x3 block by 3x3 block and the
points are eliminated; the reduced camera system is solved densely by Cholesky or, above
``dense_limit`` unknowns, sparse. The whole method: :mod:`course_lib.sfm.lm`.

Introduced in ``notebooks/05_bundle_adjustment.ipynb`` ("How does this scale?").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg

__all__ = ["BlockStructure", "NormalEquations", "normal_equations", "schur_solve"]


class BlockStructure:
    """Index bookkeeping that depends only on which camera sees which point (built once).

    The observations must be sorted by camera (:func:`solve` sorts them), so that the rows of
    camera ``i`` are the slice ``cam_start[i]:cam_start[i + 1]``.
    """

    def __init__(self, n_cameras: int, n_points: int, n: int, cam_idx: np.ndarray, pt_idx: np.ndarray):
        if np.any(np.diff(cam_idx) < 0):
            raise ValueError("BlockStructure needs the observations sorted by camera")
        self.M, self.N, self.n = n_cameras, n_points, n
        K = len(cam_idx)
        self.cam_idx, self.pt_idx = cam_idx, pt_idx
        self.cam_start = np.searchsorted(cam_idx, np.arange(n_cameras + 1))
        self.to_pt = sp.csr_matrix((np.ones(K), (pt_idx, np.arange(K))), shape=(n_points, K))
        self.to_cam = sp.csr_matrix((np.ones(K), (cam_idx, np.arange(K))), shape=(n_cameras, K))
        self.seen = np.zeros(n_points, bool)
        self.seen[pt_idx] = True
        # Pairs (k, l) of observations of the same point with camera(k) <= camera(l): the terms of
        # W V^-1 W^T (its upper block triangle), grouped by camera pair (i, l).
        order = np.argsort(pt_idx, kind="stable")
        counts = np.bincount(pt_idx, minlength=n_points)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        nk = counts[pt_idx]
        pk = np.repeat(np.arange(K), nk)
        offs = np.arange(pk.size) - np.repeat(np.cumsum(nk) - nk, nk)
        pl = order[np.repeat(starts[pt_idx], nk) + offs]
        keep = cam_idx[pk] < cam_idx[pl]  # the diagonal blocks (k == l) are summed camera by camera
        pk, pl = pk[keep], pl[keep]
        cp = cam_idx[pk] * n_cameras + cam_idx[pl]
        o = np.argsort(cp, kind="stable")
        self.pair_k, self.pair_l = pk[o], pl[o]
        self.block_ids, first = np.unique(cp[o], return_index=True)
        self.block_bounds = np.append(first, len(o))
        self.n_pairs = len(o) + K

    def reduced_blocks(self, Yt: np.ndarray, Wt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The blocks of ``W V^-1 W^T``: ``(diag (M, n, n), off (n_blocks, n, n))``.

        ``diag[i] = sum_{k in i} W_k V_j^-1 W_k^T`` and ``off[q]`` the same sum over the points
        that cameras ``i < l`` (``divmod(block_ids[q], M)``) share. ``Yt (K, 3, n)`` holds
        ``V_j^-1 W_k^T`` and ``Wt (K, 3, n)`` holds ``W_k^T``; each block is ONE matrix product
        over all the points of the camera or camera pair.
        """
        n = self.n
        diag = np.empty((self.M, n, n))
        Yf, Wf = Yt.reshape(-1, n), Wt.reshape(-1, n)
        c = 3 * self.cam_start
        for i in range(self.M):  # observations of camera i are contiguous: no gather
            np.matmul(Yf[c[i] : c[i + 1]].T, Wf[c[i] : c[i + 1]], out=diag[i])
        Yg = Yt[self.pair_k].reshape(-1, n)  # (3 P, n)
        Wg = Wt[self.pair_l].reshape(-1, n)
        off = np.empty((len(self.block_ids), n, n))
        b = 3 * self.block_bounds
        for q in range(len(self.block_ids)):
            np.matmul(Yg[b[q] : b[q + 1]].T, Wg[b[q] : b[q + 1]], out=off[q])
        return diag, off


def _outer2(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``P_k^T Q_k`` for blocks ``P (K, 2, a)``, ``Q (K, 2, b)`` -> ``(K, a, b)``."""
    return np.matmul(np.swapaxes(P, 1, 2), Q)


@dataclass
class NormalEquations:
    """The blocks of ``J^T W J`` and ``J^T W r`` (weights from the robust loss).

    Attributes:
        U: ``(M, n, n)`` camera blocks. V: ``(N, 3, 3)`` point blocks. Wt: ``(K, 3, n)`` the
        off-diagonal block of each observation, transposed (``B_k^T w A_k``). g_c: ``(M, n)``.
        g_p: ``(N, 3)``. U_ss, U_cs, Z, g_s: the blocks of the shared parameters (or None).
    """

    U: np.ndarray
    V: np.ndarray
    Wt: np.ndarray
    g_c: np.ndarray
    g_p: np.ndarray
    #: With shared parameters (``p`` of them, :class:`SimpleRadialCamera`): ``U_ss (p, p)``,
    #: ``U_cs (M, n, p)``, ``Z (N, p, 3)`` (point blocks, ``C^T w B`` summed), ``g_s (p,)``; else None.
    U_ss: np.ndarray | None = None
    U_cs: np.ndarray | None = None
    Z: np.ndarray | None = None
    g_s: np.ndarray | None = None


def normal_equations(structure: BlockStructure, r: np.ndarray, A: np.ndarray, B: np.ndarray, w: np.ndarray,
                     C: np.ndarray | None = None) -> NormalEquations:
    """Accumulate the blocks of the normal equations from the per-observation Jacobian blocks.

    Args:
        structure: bookkeeping of the (camera-sorted) observations.
        r: ``(K, 2)`` residuals. A: ``(K, 2, n)``, B: ``(K, 2, 3)`` Jacobian blocks. w: ``(K,)`` weights.
        C: ``(K, 2, p)`` Jacobian blocks of the parameters shared by all cameras, or None.
    """
    st = structure
    n = A.shape[2]
    Aw = A * w[:, None, None]
    Bw = B * w[:, None, None]
    U = np.empty((st.M, n, n))
    g_c = np.empty((st.M, n))
    p = 0 if C is None else C.shape[2]
    U_cs = None if C is None else np.empty((st.M, n, p))
    for i in range(st.M):  # one matrix product per camera over all its observations
        s, e = st.cam_start[i], st.cam_start[i + 1]
        Ai = A[s:e].reshape(-1, n)
        Awi = Aw[s:e].reshape(-1, n)
        U[i] = Awi.T @ Ai
        g_c[i] = Awi.T @ r[s:e].ravel()
        if C is not None:
            U_cs[i] = Awi.T @ C[s:e].reshape(-1, p)
    V = (st.to_pt @ _outer2(Bw, B).reshape(len(B), 9)).reshape(st.N, 3, 3)
    Wt = _outer2(Bw, A)
    g_p = st.to_pt @ (Bw[:, 0] * r[:, :1] + Bw[:, 1] * r[:, 1:])
    if C is None:
        return NormalEquations(U, V, Wt, g_c, g_p)
    Cw = C * w[:, None, None]
    U_ss = np.einsum("kai,kaj->ij", Cw, C)
    Z = (st.to_pt @ _outer2(Cw, B).reshape(len(B), 3 * p)).reshape(st.N, p, 3)
    g_s = np.einsum("kai,ka->i", Cw, r)
    return NormalEquations(U, V, Wt, g_c, g_p, U_ss, U_cs, Z, g_s)


def _damping(D: np.ndarray) -> np.ndarray:
    return np.clip(D, 1e-6, 1e32)


def schur_solve(structure: BlockStructure, ne: NormalEquations, lam: float, free_cam: np.ndarray, dense_limit: int = 4000,
                free_shared: np.ndarray | None = None):
    """Solve the damped normal equations by eliminating the points (Schur complement).

    Args:
        structure: the problem's index bookkeeping.
        ne: :class:`NormalEquations`.
        lam: damping; the system is ``(J^T J + lam D) delta = -J^T r``, ``D = diag(J^T J)`` clamped.
        free_cam: ``(M, n)`` bool, False for camera parameters held fixed (gauge).
        dense_limit: up to this many camera unknowns the reduced system is solved densely.
        free_shared: ``(p,)`` bool, False for shared parameters held fixed (with ``ne.U_ss``).

    Returns:
        ``(dc (M, n), dp (N, 3), ds (p,) or None, predicted_decrease)``. The shared parameters
        border the reduced camera system: ``[[S, S_cs], [S_csᵀ, S_ss]]`` with
        ``S_cs = U_cs - W V^-1 Zᵀ`` and ``S_ss = U_ss + lam D_s - Z V^-1 Zᵀ``.
    """
    st = structure
    M, n = st.M, st.n
    pt = st.pt_idx
    shared = ne.U_ss is not None
    Vdiag = _damping(np.einsum("jii->ji", ne.V))
    Vd = ne.V + lam * Vdiag[:, :, None] * np.eye(3)
    Vd[~st.seen] = np.eye(3)  # points without observations do not move
    try:
        Vinv = np.linalg.inv(Vd)
    except np.linalg.LinAlgError:  # a point seen once is free along its ray when lam is tiny
        Vinv = np.linalg.pinv(Vd)
    Yt = np.matmul(Vinv[pt], ne.Wt)  # (K, 3, n): V_j^-1 W_k^T
    diag, blocks = st.reduced_blocks(Yt, ne.Wt)
    Udiag = _damping(np.einsum("kii->ki", ne.U))
    q = np.einsum("jab,jb->ja", Vinv, ne.g_p)  # V^-1 g_X
    rhs = -(ne.g_c - st.to_cam @ np.einsum("kab,ka->kb", ne.Wt, q[pt])).ravel()
    fixed = ~free_cam.ravel()
    if shared:
        p_sh = len(ne.g_s)
        ZV = np.einsum("jab,jbc->jac", ne.Z, Vinv)  # (N, p, 3): Z_j V_j^-1
        Sdiag = _damping(np.diag(ne.U_ss).copy())
        S_ss = ne.U_ss + lam * np.diag(Sdiag) - np.einsum("jac,jdc->ad", ZV, ne.Z)
        S_cs = ne.U_cs - (st.to_cam @ np.einsum("kan,kpa->knp", Yt, ne.Z[pt]).reshape(len(pt), n * p_sh)).reshape(M, n, p_sh)
        rhs = np.concatenate([rhs, -(ne.g_s - np.einsum("jab,jb->a", ZV, ne.g_p))])
        fixed = np.concatenate([fixed, ~np.asarray(free_shared, bool) if free_shared is not None else np.zeros(p_sh, bool)])
    rhs[fixed] = 0.0
    S_border = (S_cs.reshape(n * M, p_sh), S_ss) if shared else None
    delta = _solve_reduced(st, ne.U + lam * Udiag[:, :, None] * np.eye(n) - diag, blocks, S_border, fixed, rhs, dense_limit)
    nS = n * M + (p_sh if shared else 0)
    dc = delta[: n * M].reshape(M, n)
    ds = delta[n * M: nS] if shared else None
    tmp = ne.g_p + st.to_pt @ np.einsum("kab,kb->ka", ne.Wt, dc[st.cam_idx])
    if shared:
        tmp = tmp + np.einsum("jpa,p->ja", ne.Z, ds)
    dp = -np.einsum("jab,jb->ja", Vinv, tmp)
    # predicted decrease of the quadratic model: 0.5 * delta^T (lam D delta - g)
    pred = 0.5 * (
        float(np.sum(dc * (lam * Udiag * dc - ne.g_c))) + float(np.sum(dp * (lam * Vdiag * dp - ne.g_p)))
    )
    if shared:
        pred += 0.5 * float(np.sum(ds * (lam * Sdiag * ds - ne.g_s)))
    return dc, dp, ds, pred


def _solve_reduced(st: BlockStructure, diag_blocks: np.ndarray, off_blocks: np.ndarray, border, fixed: np.ndarray,
                   rhs: np.ndarray, dense_limit: int) -> np.ndarray:
    """Solve the reduced camera system ``S delta = rhs``, the ``fixed`` unknowns held at 0.

    ``S`` has the ``(M, n, n)`` blocks ``diag_blocks`` on its diagonal and ``-off_blocks[q]`` at the
    camera pairs ``divmod(block_ids[q], M)`` (and their transposes), bordered by the shared
    parameters' ``border = (S_cs (nM, p), S_ss (p, p))`` or None. Up to ``dense_limit`` camera
    unknowns by dense Cholesky (least squares where it fails), above by sparse LU.
    """
    M, n = st.M, st.n
    bi, bl = np.divmod(st.block_ids, M)
    if n * M <= dense_limit:
        S = np.zeros((M, M, n, n))
        S[bi, bl] = -off_blocks
        S[bl, bi] = -np.transpose(off_blocks, (0, 2, 1))
        S[np.arange(M), np.arange(M)] = diag_blocks
        S = S.transpose(0, 2, 1, 3).reshape(n * M, n * M)
        if border is not None:
            S = np.block([[S, border[0]], [border[0].T, border[1]]])
        S[fixed, :] = 0.0
        S[:, fixed] = 0.0
        S[fixed, fixed] = 1.0
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(S, check_finite=False), rhs, check_finite=False)
        except np.linalg.LinAlgError:
            return np.linalg.lstsq(S, rhs, rcond=None)[0]
    data = np.concatenate([-off_blocks, -np.transpose(off_blocks, (0, 2, 1)), diag_blocks])
    rows = np.concatenate([bi, bl, np.arange(M)])
    cols = np.concatenate([bl, bi, np.arange(M)])
    order = np.lexsort((cols, rows))
    indptr = np.searchsorted(rows[order], np.arange(M + 1))
    S = sp.bsr_matrix((data[order], cols[order], indptr), shape=(n * M, n * M)).tocsr()
    if border is not None:
        Scs = sp.csr_matrix(border[0])
        S = sp.bmat([[S, Scs], [Scs.T, sp.csr_matrix(border[1])]]).tocsr()
    keep = sp.diags((~fixed).astype(float))
    S = (keep @ S @ keep + sp.diags(fixed.astype(float))).tocsc()
    return scipy.sparse.linalg.spsolve(S, rhs)
