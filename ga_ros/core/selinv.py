"""Marginal covariance blocks of many nodes: selected inversion of a normal matrix.

Two implementations of Takahashi's equations (``Sigma = N^-1`` on a sparsity pattern, from the
last column back, without any column of ``N^-1``):

* :class:`SelectedInverse`, on CHOLMOD's sparse Cholesky factor of ``N``, in place: ``Sigma``
  on the pattern of ``L`` (every node block and every connected pair), time about that of the
  factorisation, no memory beyond the factor. Used for large systems (batch adjustments of whole
  surveys; quality control).
* :func:`banded_marginal_blocks`, on the banded ``N``: with a bandwidth-reducing node ordering
  (reverse Cuthill-McKee) a survey's normal matrix is banded with half-bandwidth ``b``; cut into
  ``b x b`` blocks it is block tridiagonal. Its block Cholesky factor ``N = L L'`` (diagonal
  blocks ``D_k``, sub-diagonal blocks ``C_k``) and the backward recursion::

    Sigma_KK = D_K^-T D_K^-1
    Sigma_kk = D_k^-T (I + C_k' Sigma_{k+1,k+1} C_k) D_k^-1

  give every diagonal block in ``O(n b^2)`` operations and ``O(n b)`` memory (the RTS smoother
  in information form). For a window of five lawnmower tracks (6,000 unknowns) this is a few
  tens of milliseconds and needs no compiled kernel; for a whole survey the memory
  (unknowns x band) is prohibitive.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.kernels import AVAILABLE
from ga_ros.core.sparse import _CholmodFactor
from ga_ros.errors import DegenerateGeometryError


def banded_marginal_blocks(N: sp.spmatrix, d: int, max_band: int = 3000,
                           wanted: np.ndarray | None = None,
                           coords: np.ndarray | None = None) -> FloatArray | None:
    """Diagonal ``d x d`` blocks of ``N^-1`` for a symmetric positive definite ``N``.

    Nodes of high degree (e.g. those of a dense joint prior) would widen the band of every other
    node; they can be ordered last as a dense border ``P`` (an arrowhead matrix), the others
    ``Q`` keep their narrow band. The border rows of the factor and the Schur complement::

        L_Pk = (N_Pk - L_P,k-1 C_k-1') D_k^-T,    S = D_P D_P' = N_PP - sum_k L_Pk L_Pk'

    give ``Sigma_QQ = N_QQ^-1 + Z S^-1 Z'`` with ``Z = N_QQ^-1 N_QP = L_QQ^-T L_P'`` (block
    back substitution), evaluated only for the wanted rows; ``Sigma_PP = S^-1``.
    The plan (border or not, ordering of ``Q``) with the smaller operation count is used.

    Parameters
    ----------
    N : (d u, d u) sparse symmetric matrix, ``u`` node blocks of size ``d``.
    d : block size (parameters per node).
    max_band : give up (return ``None``) if the reordered half-bandwidth or the border exceeds
        this many scalars; the caller then uses sparse solves.
    wanted : optional (k,) node blocks that are needed; the backward recursion stops once it
        has passed them (blocks of other nodes are left as NaN). Default: all nodes.
    coords : optional (u, 3) node positions. Besides reverse Cuthill-McKee, the ordering along
        their principal axis is tried (for a survey strip it gives a narrower band); the
        ordering with the smaller band is used.

    Returns
    -------
    (u, d, d) covariance blocks in the original node order, or ``None`` (band too wide).
    """
    N = sp.csr_matrix(N)
    n = N.shape[0]
    u = n // d
    coo = N.tocoo()
    rows_n, cols_n = coo.row // d, coo.col // d
    G = sp.coo_matrix((np.ones(coo.nnz), (rows_n, cols_n)), shape=(u, u)).tocsr()
    plans = [_plan(G, rows_n, cols_n, coords, np.zeros(u, dtype=bool), d)]
    degree = np.diff(G.indptr)
    if u > 2:
        dense = degree > max(16.0, 4.0 * float(np.median(degree)))
        if 0 < dense.sum() < u // 2:
            plans.append(_plan(G, rows_n, cols_n, coords, dense, d))
    order_q, border, b, _ = min(plans, key=lambda plan: plan[3])
    p = border.size * d
    if b > max_band or p > max_band:
        return None
    order = np.concatenate([order_q, border])
    nq = order_q.size * d
    pos = np.empty(u, dtype=np.int64)
    pos[order] = np.arange(u)
    if wanted is None or len(wanted) == 0:
        first_needed = 0
    else:
        wpos = pos[np.asarray(wanted, dtype=np.int64)]
        wpos = wpos[wpos < order_q.size]
        first_needed = int(wpos.min()) if wpos.size else order_q.size
    perm = (order[:, None] * d + np.arange(d)[None, :]).ravel()
    inv = np.empty(n, dtype=np.int64)
    inv[perm] = np.arange(n)
    r, c = inv[coo.row], inv[coo.col]
    nb = max(-(-nq // b), 1)
    size = nb * b
    # dense diagonal and sub-diagonal blocks of the banded part (padded with identity), the
    # border rows E (p, b) per block and the border's own block
    inq = (r < nq) & (c < nq)
    rq, cq, vq = r[inq], c[inq], coo.data[inq]
    br, bc = rq // b, cq // b
    diag = br == bc
    lin = (br[diag] * b + rq[diag] % b) * b + cq[diag] % b
    A = np.bincount(lin, weights=vq[diag], minlength=nb * b * b).reshape(nb, b, b)
    low = br == bc + 1
    lin = (bc[low] * b + rq[low] % b) * b + cq[low] % b
    C = np.bincount(lin, weights=vq[low],
                    minlength=max(nb - 1, 0) * b * b).reshape(max(nb - 1, 0), b, b)
    bord = (r >= nq) & (c < nq)
    lin = ((c[bord] // b) * p + (r[bord] - nq)) * b + c[bord] % b
    E = np.bincount(lin, weights=coo.data[bord],
                    minlength=nb * p * b).reshape(nb, p, b).astype(float)
    pp = (r >= nq) & (c >= nq)
    App = np.bincount((r[pp] - nq) * p + (c[pp] - nq), weights=coo.data[pp],
                      minlength=p * p).reshape(p, p).astype(float)
    pad = np.arange(nq, size)
    A[pad // b, pad % b, pad % b] = 1.0
    # block Cholesky: D_k D_k' = A_k - C_{k-1} C_{k-1}'; C_k <- C_k D_k^-T; border rows likewise
    Dinv = np.empty_like(A)
    eye = np.eye(b)
    for k in range(nb):
        if k:
            A[k] -= C[k - 1] @ C[k - 1].T
            E[k] -= E[k - 1] @ C[k - 1].T
        Dinv[k] = _inverse_factor(A[k], eye)
        if k < nb - 1:
            C[k] = C[k] @ Dinv[k].T
        E[k] = E[k] @ Dinv[k].T
    if p:
        Ecat = np.concatenate(list(E), axis=1)
        App -= Ecat @ Ecat.T
    out = np.full((u, d, d), np.nan)
    Dp = np.zeros((0, 0))
    if p:
        Dp = _inverse_factor(App, np.eye(p))
        Spp = Dp.T @ Dp
        for q in range(border.size):
            out[border[q]] = Spp[q * d:(q + 1) * d, q * d:(q + 1) * d]
    want = np.ones(order_q.size, dtype=bool)
    if wanted is not None and len(wanted):
        want[:] = False
        wpos = pos[np.asarray(wanted, dtype=np.int64)]
        want[wpos[wpos < order_q.size]] = True
    # backward recursion over the diagonal blocks of N_QQ^-1, plus the border's share
    # Z S^-1 Z' with Z = N_QQ^-1 N_QP = L_QQ^-T L_P' (back substitution) for wanted rows only
    Sigma_next = None
    Z = np.zeros((b, p))
    stop = (first_needed * d) // b
    for k in range(nb - 1, min(stop, nb) - 1, -1):
        if Sigma_next is None:
            S = Dinv[k].T @ Dinv[k]
            Z = Dinv[k].T @ E[k].T
        else:
            S = Dinv[k].T @ (eye + C[k].T @ Sigma_next @ C[k]) @ Dinv[k]
            Z = Dinv[k].T @ (E[k].T - C[k].T @ Z)
        Sigma_next = S
        lo, hi = k * b, min((k + 1) * b, nq)
        qs = np.arange(lo // d, hi // d)
        qs = qs[want[qs]]
        if qs.size == 0:
            continue
        rows = ((qs - lo // d)[:, None] * d + np.arange(d)).ravel()
        blocks = S[rows[:, None], rows[None, :]].reshape(qs.size, d, qs.size, d)
        blocks = blocks[np.arange(qs.size), :, np.arange(qs.size), :]
        if p:
            W = (Z[rows] @ Dp.T).reshape(qs.size, d, p)
            blocks = blocks + W @ np.swapaxes(W, 1, 2)
        out[order[qs]] = blocks
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _inverse_factor(A: FloatArray, eye: FloatArray) -> FloatArray:
    """``D^-1`` of the lower Cholesky factor ``D D' = A``."""
    try:
        D = np.linalg.cholesky(A)
    except np.linalg.LinAlgError as exc:
        raise DegenerateGeometryError('normal matrix is not positive definite') from exc
    return sla.solve_triangular(D, eye, lower=True)


def _plan(G: sp.csr_matrix, rows_n: np.ndarray, cols_n: np.ndarray,
          coords: np.ndarray | None, border: np.ndarray,
          d: int) -> tuple[np.ndarray, np.ndarray, int, float]:
    """Ordering of the non-border nodes, the border nodes, the block size ``b`` (scalars) and
    an operation count of the selected inversion with that plan."""
    u = G.shape[0]
    q_nodes = np.nonzero(~border)[0]
    p_nodes = np.nonzero(border)[0]
    Gq = G[q_nodes][:, q_nodes]
    candidates = [q_nodes[reverse_cuthill_mckee(Gq, symmetric_mode=True)]]
    if coords is not None and len(coords) == u and q_nodes.size > 2:
        xyz = np.asarray(coords, dtype=float)[q_nodes]
        xyz = xyz - np.mean(xyz, axis=0)
        axis = np.linalg.svd(xyz, full_matrices=False)[2][0]
        candidates.append(q_nodes[np.argsort(xyz @ axis, kind='stable')])
    both = ~border[rows_n] & ~border[cols_n]
    rq, cq = rows_n[both], cols_n[both]

    def node_band(order: np.ndarray) -> int:
        pos = np.empty(u, dtype=np.int64)
        pos[order] = np.arange(order.size)
        return int(np.abs(pos[rq] - pos[cq]).max()) if rq.size else 0

    bands = [node_band(o) for o in candidates]
    best = int(np.argmin(bands))
    b = (bands[best] + 1) * d
    nq, p = q_nodes.size * d, p_nodes.size * d
    cost = nq * (4.0 * b * b + 4.0 * p * b + 2.0 * p * p) + p ** 3
    return candidates[best], p_nodes, b, cost


# ------------------------------------------------------------ selected inversion on a factor
def supernodes(colptr: IntArray, rowind: IntArray) -> IntArray:
    """First column of each (fundamental) supernode of a lower-triangular CSC factor, plus ``n``.

    Column ``j + 1`` continues the supernode of column ``j`` when it is ``j``'s parent in the
    elimination tree (the first sub-diagonal row of column ``j`` is ``j + 1``) and has one entry
    fewer: then both columns have the same rows below the supernode (the pattern of a Cholesky
    factor is closed: ``struct(j)`` without ``j`` lies in ``struct(parent(j))``).
    """
    colptr = np.asarray(colptr, dtype=np.int64)
    n = colptr.size - 1
    if n == 0:
        return np.zeros(1, dtype=np.int64)
    count = np.diff(colptr)
    j = np.arange(n - 1)
    second = np.where(count[:-1] > 1, colptr[:-2] + 1, 0)
    cont = (count[:-1] > 1) & (np.asarray(rowind)[second] == j + 1) & (count[1:] == count[:-1] - 1)
    starts = np.concatenate([[0], np.nonzero(~cont)[0] + 1, [n]])
    return starts.astype(np.int64)


def _takahashi_py(starts, pi, nrows, srows, colbase, x, where):  # pragma: no cover - compiled
    """In place: the values of ``L`` (``P N P' = L L'``) become those of ``Sigma = N^-1``
    (permuted) on the pattern of ``L``.

    Supernode ``k`` has the columns ``starts[k] .. starts[k+1]-1`` and the sorted rows
    ``srows[pi[k] : pi[k] + nrows[k]]`` (its own columns first); the value at its ``z``-th row in
    column ``c`` is ``x[colbase[c] + z]`` (CHOLMOD's supernodal layout and a CSC factor both fit).
    Takahashi's equations per supernode (columns ``J``, rows ``B`` below them), from the last
    back (``Sigma L = L^-T``, upper triangular)::

        U = L_BJ L_JJ^-1,   Sigma_BJ = -Sigma_BB U,   Sigma_JJ = L_JJ^-T L_JJ^-1 - Sigma_BJ' U

    ``Sigma_BB`` lies on the pattern of later supernodes (closure of the factor's pattern), all
    already overwritten; it is gathered through ``where`` (row -> position in an ancestor's row
    list, -1 elsewhere). Returns 0; 1 if a needed entry is not on the pattern, 2 if rows are not
    sorted (nothing was changed then).
    """
    ns = starts.size - 1
    for k in range(ns):
        for z in range(pi[k] + 1, pi[k] + nrows[k]):
            if srows[z] <= srows[z - 1]:
                return 2
    for t in range(ns - 1, -1, -1):
        f = starts[t]
        m = starts[t + 1] - f
        r = nrows[t] - m
        Ljj = np.zeros((m, m))
        Lbj = np.empty((r, m))
        for i in range(m):
            q = colbase[f + i]
            for a in range(i, m):
                Ljj[a, i] = x[q + a]
            for a in range(r):
                Lbj[a, i] = x[q + m + a]
        Linv = np.linalg.inv(Ljj)
        for i in range(m):  # exactly lower triangular
            for a in range(i):
                Linv[a, i] = 0.0
        Sjj = Linv.T @ Linv
        Sbj = np.empty((r, m))
        if r:
            U = Lbj @ Linv
            B = srows[pi[t] + m:pi[t] + nrows[t]]
            Sbb = np.empty((r, r))
            a = 0
            while a < r:  # the rows of B that are columns of one ancestor supernode
                c = B[a]
                lo, hi = 0, ns
                while hi - lo > 1:  # supernode of column c (binary search)
                    mid = (lo + hi) // 2
                    if starts[mid] <= c:
                        lo = mid
                    else:
                        hi = mid
                q0, nt, lt = pi[lo], nrows[lo], starts[lo + 1]
                for z in range(nt):
                    where[srows[q0 + z]] = z
                b = a
                while b < r and B[b] < lt:
                    b += 1
                for mm in range(a, b):
                    base = colbase[B[mm]]
                    for l2 in range(mm, r):
                        z = where[B[l2]]
                        if z < 0:
                            return 1
                        v = x[base + z]
                        Sbb[l2, mm] = v
                        Sbb[mm, l2] = v
                for z in range(nt):
                    where[srows[q0 + z]] = -1
                a = b
            Sbj = -(Sbb @ U)
            Sjj -= Sbj.T @ U
        for i in range(m):
            q = colbase[f + i]
            for a in range(i, m):
                x[q + a] = Sjj[a, i]
            for a in range(r):
                x[q + m + a] = Sbj[a, i]
    return 0


def _entries_py(starts, pi, nrows, srows, colbase, x, rows, cols, out):  # pragma: no cover
    """``out[e]`` = the value at (``rows[e] >= cols[e]``) of the layout of :func:`_takahashi_py`
    (binary searches); returns the number of entries not on the pattern (left NaN)."""
    missing = 0
    ns = starts.size - 1
    for e in range(rows.size):
        c, r = cols[e], rows[e]
        lo, hi = 0, ns
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if starts[mid] <= c:
                lo = mid
            else:
                hi = mid
        a, b = pi[lo] + (c - starts[lo]), pi[lo] + nrows[lo]
        while a < b:
            mid = (a + b) // 2
            if srows[mid] < r:
                a = mid + 1
            else:
                b = mid
        if a < pi[lo] + nrows[lo] and srows[a] == r:
            out[e] = x[colbase[c] + a - pi[lo]]
        else:
            out[e] = np.nan
            missing += 1
    return missing


_KERNELS: dict = {}
#: The kernels are compiled (numba installed, ``GA_ROS_JIT`` not ``0``); without, they run as
#: plain Python (correct, but only for small systems: callers choose another path then).
COMPILED = AVAILABLE


def _kernel(name: str):
    """The numba-compiled kernel (cached on disk), or the Python one (:data:`COMPILED`)."""
    fn = _KERNELS.get(name)
    if fn is None:
        fn = globals()[name + '_py']
        if COMPILED:
            import numba

            fn = numba.njit(cache=True, nogil=True)(fn)
        _KERNELS[name] = fn
    return fn


@dataclass
class _Layout:
    """A factor's values and pattern as :func:`_takahashi_py` reads them; ``keep`` holds the
    objects that own the memory."""

    starts: IntArray
    pi: IntArray
    nrows: IntArray
    srows: IntArray
    colbase: IntArray
    x: FloatArray
    perm: IntArray
    keep: tuple


def _supernodal_layout(capsule, n: int) -> _Layout | None:
    """CHOLMOD's supernodal factor in place (no copy): its arrays viewed through ``ctypes``.
    ``None`` if the factor does not look as expected (another CHOLMOD build): the caller then
    reads it out with ``getfactor``."""
    api = ctypes.pythonapi
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    api.PyCapsule_GetName.restype = ctypes.c_char_p
    api.PyCapsule_GetName.argtypes = [ctypes.py_object]
    try:
        name = api.PyCapsule_GetName(capsule)
        if name != b'CHOLMOD FACTOR D L':
            return None
        L = _CholmodFactor.from_address(api.PyCapsule_GetPointer(capsule, name))
    except (TypeError, ValueError):  # pragma: no cover - not a capsule
        return None
    ns = int(L.nsuper)
    if not (L.n == n and L.minor == n and L.is_super == 1 and L.is_ll == 1 and L.xtype == 1
            and L.dtype == 0 and L.itype == 2 and 0 < ns <= n and L.ssize > 0 and L.xsize > 0
            and all((L.super, L.pi, L.px, L.s, L.x, L.Perm))):
        return None

    def view(ptr, count, ctype):
        return np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(ctype)), shape=(count,))

    sup = view(L.super, ns + 1, ctypes.c_int64).astype(np.int64)
    pi = view(L.pi, ns + 1, ctypes.c_int64).astype(np.int64)
    px = view(L.px, ns + 1, ctypes.c_int64).astype(np.int64)
    perm = view(L.Perm, n, ctypes.c_int64).astype(np.int64)
    width, nrows = np.diff(sup), np.diff(pi)
    if (sup[0] != 0 or sup[-1] != n or pi[0] != 0 or pi[-1] > L.ssize or px[0] != 0
            or px[-1] > L.xsize or (width <= 0).any() or (nrows < width).any()
            or (np.diff(px) < nrows * width).any()
            or not np.array_equal(np.sort(perm), np.arange(n))):
        return None
    x = view(L.x, int(L.xsize), ctypes.c_double)
    srows = view(L.s, int(L.ssize), ctypes.c_int64)
    step = np.diff(srows[:pi[-1]]) > 0
    step[pi[1:-1] - 1] = True  # a new supernode may start lower
    if not step.all():  # rows not sorted within a supernode
        return None
    k = np.repeat(np.arange(ns), width)
    colbase = px[k] + (np.arange(n) - sup[k]) * nrows[k]  # column-major nrows x width blocks
    return _Layout(sup, pi[:-1], nrows, srows, colbase, x, perm, (capsule,))


def _csc_layout(chol) -> _Layout:
    """The factor read out with ``cholmod.getfactor`` (a simplicial copy: ~2x the factor's
    memory at the peak), its supernodes found from the pattern (:func:`supernodes`)."""
    from ga_ros.core.sparse import _cholmod

    perm = chol.permutation()
    F = _cholmod.getfactor(chol._F)
    colptr, rowind, values = F.CCS  # views of cvxopt's buffers (writable), which they keep
    colptr = np.asarray(colptr, dtype=np.int64).ravel()
    rowind = np.asarray(rowind, dtype=np.int64).ravel()
    starts = supernodes(colptr, rowind)
    pi = colptr[starts[:-1]]
    k = np.repeat(np.arange(starts.size - 1), np.diff(starts))
    colbase = colptr[:-1] - (np.arange(colptr.size - 1) - starts[k])
    return _Layout(starts, pi, np.diff(colptr)[starts[:-1]], rowind, colbase,
                   np.asarray(values, dtype=float).ravel(), perm, (F,))


class SelectedInverse:
    """``Sigma = N^-1`` on the pattern of the Cholesky factor of ``N`` (selected inversion).

    The CHOLMOD factor of ``N`` (a :class:`~ga_ros.core.sparse.SparseCholesky`, ordered by the
    project's block ordering: AMD of the node graph, each node's ``d`` unknowns together) is
    overwritten in place by Takahashi's equations (:func:`_takahashi_py`, compiled with numba),
    supernode by supernode with dense products, in CHOLMOD's own supernodal storage (viewed
    through ``ctypes``, no copy; if that layout is not recognised, a ``getfactor`` copy is used).
    The extra memory is one dense ``rows x rows`` block of the widest supernode: no band, no
    dense column, no second factor. Every entry of ``Sigma`` on the pattern of ``N`` is on the
    pattern of ``L`` (``P N P'`` lies within ``L + L'``), so the diagonal blocks of all nodes and
    the cross blocks of all connected node pairs can be read (:meth:`blocks`).

    Parameters
    ----------
    chol : the factored ``N`` (``d x d`` node blocks). Its factor is taken over: ``chol`` is left
        without one and factors again (with a new analysis) on its next solve.
    copy : read the factor out with ``getfactor`` even when the in-place layout is available.

    Raises
    ------
    DegenerateGeometryError
        No CHOLMOD, or the factor's pattern is not that of a Cholesky factor.
    """

    def __init__(self, chol, copy: bool = False) -> None:
        from ga_ros.core.sparse import _cholmod

        if _cholmod is None or chol._F is None:  # pragma: no cover - cvxopt is pinned
            raise DegenerateGeometryError('selected inversion needs a CHOLMOD factor (cvxopt)')
        self.d = chol.pattern.d
        lay = None if copy else _supernodal_layout(chol._F, chol.n)
        self.in_place = lay is not None
        if lay is None:
            lay = _csc_layout(chol)
        chol._F = chol._symbolic = chol._permuted = None  # the values become Sigma's
        self._lay = lay
        self._pos = np.empty_like(lay.perm)
        self._pos[lay.perm] = np.arange(lay.perm.size)
        where = np.full(lay.perm.size, -1, dtype=np.int64)
        status = _kernel('_takahashi')(lay.starts, lay.pi, lay.nrows, lay.srows, lay.colbase,
                                       lay.x, where)
        if status:
            raise DegenerateGeometryError('the factor pattern is not that of a Cholesky factor '
                                          f'(code {status}): report this with the graph')

    @property
    def nnz(self) -> int:
        """Stored entries of ``L`` (and of ``Sigma``; supernodal storage counts whole blocks)."""
        return int(self._lay.x.size)

    def blocks(self, rows: IntArray, cols: IntArray, off_pattern: str = 'raise') -> FloatArray:
        """Blocks ``(rows[k], cols[k])`` of ``Sigma`` (``d x d`` node blocks, columns of ``N``),
        ``(k, d, d)``. Each pair should be a diagonal block or a connected pair of ``N``; a pair
        off the factor's pattern raises :class:`DegenerateGeometryError` (``off_pattern=
        'raise'``) or comes back as NaN (``'nan'``)."""
        d = self.d
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        a = np.arange(d)
        sr = self._pos[(rows[:, None, None] * d + a[None, :, None])]  # (k, d, 1)
        sc = self._pos[(cols[:, None, None] * d + a[None, None, :])]  # (k, 1, d)
        sr, sc = np.broadcast_arrays(sr, sc)
        lo, hi = np.minimum(sr, sc).ravel(), np.maximum(sr, sc).ravel()
        out = np.empty(lo.size)
        lay = self._lay
        missing = _kernel('_entries')(lay.starts, lay.pi, lay.nrows, lay.srows, lay.colbase,
                                      lay.x, hi, lo, out)
        if missing and off_pattern == 'raise':
            raise DegenerateGeometryError('a requested block is not on the pattern of the '
                                          'normal matrix: only node and connected-pair blocks')
        return out.reshape(rows.size, d, d)

    def diagonal_blocks(self, nodes: IntArray) -> FloatArray:
        """Marginal covariance blocks ``(k, d, d)`` of the given node columns (symmetrised)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        out = self.blocks(nodes, nodes)
        return 0.5 * (out + np.swapaxes(out, 1, 2))
