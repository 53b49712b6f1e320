"""The covariance skeleton of a sparse joint prior: the band and hub blocks of ``(N^-1)_TT``
over target nodes, by selected inversion on the sparse factor of ``N`` (or, without compiled
kernels, by the banded selection and solves with the same factor)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg import selinv
from ga_ros.core.linalg.blocks import _blake2b

if TYPE_CHECKING:
    from ga_ros.core.linalg.completion import CovarianceSkeleton

def sparse_skeleton(N: sp.spmatrix, d: int, targets: IntArray, w: int, n_hubs: int,
                    coords: FloatArray | None = None, rhs: FloatArray | None = None
                    ) -> tuple[CovarianceSkeleton, FloatArray | None]:
    """The :class:`CovarianceSkeleton` of ``Sigma = (N^-1)_TT`` over the target nodes ``T``
    (in band order) from a sparse symmetric ``N`` (both triangles), and ``N^-1 rhs``.

    With the compiled kernels: the skeleton's block pairs are added to the pattern of ``N`` (as
    explicit zeros), so that they lie on the pattern of its sparse Cholesky factor, and
    Takahashi's selected inversion on that factor
    (:class:`~ga_ros.core.linalg.selinv.SelectedInverse`) gives all of them at once; the fill of a
    band of ``w`` nodes and ``h`` hub rows is linear in the number of targets. Without: the
    band by :func:`banded_selection`, the hubs' columns by solves with the same factor
    (``h d`` right-hand sides). Both exact and linear in the number of nodes for a strip.

    Raises
    ------
    DegenerateGeometryError
        ``N`` is not positive definite.
    """
    from ga_ros.core.linalg.banded import banded_selection
    from ga_ros.core.linalg.cholmod import _cholmod
    from ga_ros.core.linalg.completion import CovarianceSkeleton, skeleton_layout

    t = np.asarray(targets, dtype=np.int64)
    rest, hubs = skeleton_layout(t.size, w, n_hubs)
    if selinv.COMPILED and _cholmod is not None:
        return _selected_skeleton(N, d, t, rest, hubs, w, rhs)
    n = N.shape[0]
    E = np.zeros((n, hubs.size * d))
    for a, node in enumerate(t[hubs].tolist()):
        E[node * d:(node + 1) * d, a * d:(a + 1) * d] = np.eye(d)
    b = E if rhs is None else np.column_stack([np.reshape(rhs, (n, -1)), E])
    sel = banded_selection(N, d, t[rest], w, coords=coords, rhs=b)
    X = sel.solution[:, b.shape[1] - E.shape[1]:]  # Sigma_{., hubs}
    h = hubs.size
    u = n // d
    cross = X.reshape(u, d, h, d)[t[rest]].transpose(2, 0, 3, 1)  # (h, r, d, d): Sigma_{a, r}
    hub_cov = X.reshape(u, d, h * d)[t[hubs]].reshape(h * d, h * d)
    x = None
    if rhs is not None:
        x = sel.solution[:, :b.shape[1] - E.shape[1]].reshape(np.shape(rhs))
    return CovarianceSkeleton(rest, hubs, sel.band, cross, 0.5 * (hub_cov + hub_cov.T)), x


@dataclass
class _SkeletonPlan:
    """What :func:`_selected_skeleton` computes from the pattern of ``N`` and the targets alone
    (the absorbed terms of a freeze repeat their pattern every track): the factor's block
    pattern with the skeleton's pairs, where its values come from in ``N``'s, the symbolic
    analysis, and where the skeleton's entries lie in the factor's values.

    Attributes
    ----------
    indptr, indices : the pattern of ``N`` (compressed rows or columns) it was made for.
    pattern : block pattern of ``N`` plus the skeleton's pairs (explicit zeros).
    source : (nnz,) position in ``N.data`` of each of its lower-triangle values (-1: a zero).
    pa, pc : block pairs of the skeleton (band among the others, hubs with every target, hubs
        with hubs); bi, bj : positions (among the others) of the band pairs.
    kept : a symbolic factor of ``pattern`` and the positions of the blocks ``(pa, pc)`` in
        the values of its selected inverse (``None`` before the first use, and while a thread
        uses them).
    """

    indptr: IntArray
    indices: IntArray
    pattern: object
    source: IntArray
    pa: IntArray
    pc: IntArray
    bi: IntArray
    bj: IntArray
    kept: tuple | None = None


#: Plans of :func:`_selected_skeleton` by the shape of ``N`` and the skeleton, for the pattern of
#: ``N`` they hold: the latest two (a plan holds a symbolic factor, ~10 MB for the aerial
#: survey's 102-pose swaths; a survey's freezes repeat one or two patterns). A lock around
#: taking and returning a plan's analysis: freezes and refinements may run in threads at once.
_PLANS: OrderedDict[bytes, _SkeletonPlan] = OrderedDict()
_MAX_PLANS = 2
_PLANS_LOCK = threading.Lock()


def _skeleton_plan(N: sp.spmatrix, d: int, t: IntArray, rest: IntArray, hubs: IntArray,
                   w: int) -> _SkeletonPlan:
    """The :class:`_SkeletonPlan` of ``N`` (CSR or CSC, both triangles) and a skeleton."""
    key = _blake2b(b''.join([N.format.encode(), np.array([*N.shape, N.nnz, d, w], dtype=np.int64)
                             .tobytes(), t.tobytes(), hubs.tobytes()]), digest_size=16).digest()
    with _PLANS_LOCK:
        plan = _PLANS.get(key)
        if plan is not None and np.array_equal(plan.indptr, N.indptr) \
                and np.array_equal(plan.indices, N.indices):
            _PLANS.move_to_end(key)
            return plan
    from ga_ros.core.linalg.blocks import BlockPattern
    from ga_ros.core.linalg.completion import band_pairs

    u = N.shape[0] // d
    # the positions of N's values travel through the conversions instead of the values
    # (1-based: an explicit zero of the new pattern comes out as 0)
    where = type(N)((np.arange(1, N.nnz + 1, dtype=float), N.indices, N.indptr), shape=N.shape)
    # a symmetric CSC matrix is its own CSR transpose: no conversion
    Nr = sp.csr_matrix((where.data, where.indices, where.indptr), shape=N.shape) \
        if N.format == 'csc' else where
    Nb = sp.bsr_matrix(Nr, blocksize=(d, d))
    Nb.sort_indices()
    rows_n = np.repeat(np.arange(u, dtype=np.int64), np.diff(Nb.indptr))
    cols_n = Nb.indices.astype(np.int64)
    tr, th = t[rest], t[hubs]
    r, h = tr.size, th.size
    # the skeleton's pairs: the band among the others, every hub with every target
    bi, bj, _ = band_pairs(r, w)
    hub_a = np.repeat(np.arange(h), r)
    rest_i = np.tile(np.arange(r), h)
    pa = np.concatenate([tr[bi], th[hub_a], np.repeat(th, h)])
    pc = np.concatenate([tr[bj], tr[rest_i], np.tile(th, h)])
    diag = np.arange(u, dtype=np.int64)
    pattern = BlockPattern(np.concatenate([rows_n, diag, np.maximum(pa, pc)]),
                           np.concatenate([cols_n, diag, np.minimum(pa, pc)]), d, u)
    blocks = np.zeros((rows_n.size + u + pa.size, d, d))
    blocks[:rows_n.size] = Nb.data
    source = np.rint(pattern.assemble(blocks)).astype(np.int64) - 1
    plan = _SkeletonPlan(N.indptr.copy(), N.indices.copy(), pattern, source, pa, pc, bi, bj)
    with _PLANS_LOCK:
        _PLANS[key] = plan
        while len(_PLANS) > _MAX_PLANS:
            _PLANS.popitem(last=False)
    return plan


def _selected_skeleton(N: sp.spmatrix, d: int, t: IntArray, rest: IntArray, hubs: IntArray,
                       w: int, rhs: FloatArray | None
                       ) -> tuple[CovarianceSkeleton, FloatArray | None]:
    """:func:`sparse_skeleton` by selected inversion on the sparse factor of ``N`` with the
    skeleton's pairs added to its pattern (pattern, analysis and the entries' positions kept
    per pattern: :class:`_SkeletonPlan`)."""
    from ga_ros.core.linalg.cholesky import SparseCholesky
    from ga_ros.core.linalg.completion import CovarianceSkeleton

    if N.format not in ('csr', 'csc') or not N.has_canonical_format:
        N = sp.csr_matrix(N)
        N.sum_duplicates()  # one value per position: the plan maps positions
    plan = _skeleton_plan(N, d, t, rest, hubs, w)
    data = np.where(plan.source >= 0, N.data[plan.source], 0.0)
    with _PLANS_LOCK:  # the plan's analysis, unless another thread is using it
        kept, plan.kept = plan.kept, None
    analysis, offsets = kept if kept is not None else (None, None)
    chol = SparseCholesky(plan.pattern, data, analysis=analysis)
    analysis = chol.analysis
    x = None if rhs is None else chol.solve(rhs)
    inv = selinv.SelectedInverse(chol, columns=t)  # their supernodes and ancestors
    if offsets is None:  # they depend on the analysis only
        offsets = inv.offsets(plan.pa, plan.pc)
    S = inv.at(offsets)  # Sigma_{pa, pc}: targets only
    if inv.in_place:  # the factor is a symbolic one again: kept for the next
        with _PLANS_LOCK:
            plan.kept = (analysis, offsets)
    bi, bj = plan.bi, plan.bj
    r, h = rest.size, hubs.size
    band = np.zeros((r, w + 1, d, d))
    band[bi, bj - bi] = S[:bi.size]
    cross = S[bi.size:bi.size + h * r].reshape(h, r, d, d)
    hub_cov = S[bi.size + h * r:].reshape(h, h, d, d).transpose(0, 2, 1, 3).reshape(h * d, h * d)
    return CovarianceSkeleton(rest, hubs, band, cross, 0.5 * (hub_cov + hub_cov.T)), x
