"""The CHOLMOD binding (SuiteSparse, bundled in the cvxopt wheel): the sparse Cholesky factor.

This is the only module that knows cvxopt's CHOLMOD interface; CHOLMOD's own structs (reached
through ``ctypes`` to factor values where they lie) are in
:mod:`ga_ros.core.linalg.cholmod_ctypes`. :class:`SparseCholesky` reuses the symbolic analysis
(the fill-reducing ordering of :mod:`ga_ros.core.linalg.ordering`) across iterations. Without
cvxopt, SciPy's SuperLU is used. The interface the rest of the code relies on is
:class:`ga_ros.core.linalg.cholesky.CholeskyFactor`.
"""

from __future__ import annotations

import glob
import os
from collections import OrderedDict

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg import blocks
from ga_ros.core.linalg.blocks import BlockPattern, _expand_cols, _kept, _Permuted
from ga_ros.core.linalg.cholmod_ctypes import _DirectCholmod
from ga_ros.core.linalg.ordering import _trailing_ordering, block_ordering
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import openblas_coretype

try:  # CHOLMOD, bundled in the cvxopt wheel
    with openblas_coretype():
        import cvxopt
        from cvxopt import amd as _amd
        from cvxopt import cholmod as _cholmod

    _cholmod.options['supernodal'] = 2
    _cholmod.options['postorder'] = True
except ImportError:  # pragma: no cover - the pinned requirements include cvxopt
    cvxopt = None
    _amd = None
    _cholmod = None

#: CHOLMOD input matrices kept per pattern (the few latest: a window's, its freeze's).
_MATRICES: OrderedDict[bytes, object] = OrderedDict()


_MAX_MATRICES = 4

#: From this many stored entries of ``N`` on, the direct factorisation hands CHOLMOD ``N``
#: already permuted (:meth:`~ga_ros.core.linalg.cholmod_ctypes._DirectCholmod.permuted`: an
#: argsort of the entries once per analysis, ~0.1 s per million; a window's few hundred thousand
#: entries are factored as given).
_PERMUTE_FROM_NNZ = 1 << 22


_DIRECT: list = []  # [the _DirectCholmod or None], found on first use


def _direct_cholmod() -> _DirectCholmod | None:
    """The direct CHOLMOD call (:class:`_DirectCholmod`), or ``None`` when the library cvxopt
    bundles is not found or not the expected version (then cvxopt's ``numeric`` is used);
    ``GA_ROS_DIRECT_CHOLMOD=0`` turns it off."""
    if not _DIRECT:
        found = None
        if cvxopt is not None and os.environ.get('GA_ROS_DIRECT_CHOLMOD', '1') != '0':
            libs = glob.glob(os.path.join(os.path.dirname(os.path.dirname(cvxopt.__file__)),
                                          'cvxopt.libs', 'libcholmod*.so.3.*'))
            try:
                found = _DirectCholmod(libs[0], _model_factor) if len(libs) == 1 else None
            except (OSError, AttributeError):
                found = None
        _DIRECT.append(found)
    return _DIRECT[0]


def _model_factor():
    """A symbolic factor of cvxopt's own (of a 1 x 1 matrix): :class:`_DirectCholmod` gives its
    factors the same capsule name and destructor."""
    return _cholmod.symbolic(cvxopt.spmatrix([1.0], [0], [0]))


class SparseCholesky:
    """Factor of a symmetric positive definite matrix given by its lower triangle (CSC).

    Reuse one instance across matrices with the same pattern: :meth:`refactor` keeps the ordering.
    Raises :class:`DegenerateGeometryError` when the matrix is not positive definite (e.g. a datum
    is missing or part of the network is unconstrained). ``auto``: a small, very sparse matrix
    may get a simplicial factor
    (:meth:`~ga_ros.core.linalg.cholmod_ctypes._DirectCholmod.analyse`), which selected
    inversion reads through a copy; the default is supernodal (read in place).
    """

    def __init__(self, pattern: BlockPattern, data: FloatArray,
                 trailing: IntArray | None = None, analysis=None, auto: bool = False) -> None:
        self.pattern = pattern
        self.n = pattern.size
        self._auto = auto
        self._trailing = None if trailing is None else np.asarray(trailing, dtype=np.int64)
        self._symbolic = analysis  # a kept symbolic factor of this pattern (keep_analysis)
        self._permuted: _Permuted | None = None  # P N P' for the direct factorisation
        self._A = None
        self._F = None
        self._lu = None
        self.refactor(data)

    @property
    def analysis(self):
        """The symbolic analysis (ordering, supernodes) the next :meth:`refactor` reuses, or
        ``None`` before the first factorisation."""
        return self._symbolic

    def keep_analysis(self, analysis) -> None:
        """Keep only ``analysis`` (a symbolic factor of this pattern, e.g. after a selected
        inversion overwrote the numeric factor in place): the next :meth:`refactor` factors
        anew on it."""
        self._symbolic = analysis

    def refactor(self, data: FloatArray) -> None:
        """Numeric factorisation of new values on the same pattern (ordering reused).

        With the bundled CHOLMOD reachable through ``ctypes`` (:func:`_direct_cholmod`), the
        values are handed to ``cholmod_l_factorize`` where they lie: no copy of ``N``'s values
        and row indices into cvxopt, none into CHOLMOD's packed input (~0.75 GB for a survey of
        100,000 poses); the factor is the same (same library, same input)."""
        if not np.isfinite(data).all():
            raise DegenerateGeometryError('normal matrix has NaN or inf entries')
        p = self.pattern
        self._data = data
        if _cholmod is not None:
            direct = _direct_cholmod()
            if self._symbolic is None:
                self._permuted = None
                if direct is not None:  # no cvxopt copy of the pattern (~40 ms for a window)
                    self._symbolic = direct.analyse(p, self._ordering(), self._trailing is None,
                                                    self._auto)
                if self._symbolic is None:
                    if self._A is None:
                        self._A = _cvxopt_pattern(p, keep=direct is None)
                    self._symbolic = self._analyse()
                if direct is not None:
                    self._A = None  # only the analysis needs cvxopt's copy of the pattern
            try:
                if direct is not None:
                    if self._permuted is None and p.nnz >= _PERMUTE_FROM_NNZ:
                        self._permuted = direct.permuted(p, self._symbolic)
                    direct.factorize(p, data, self._symbolic, self._permuted)
                else:
                    self._A.V = cvxopt.matrix(np.ascontiguousarray(data, dtype=float))
                    _cholmod.numeric(self._A, self._symbolic)
            except ArithmeticError as exc:
                self._symbolic = None
                raise DegenerateGeometryError(
                    'the normal matrix is singular (not positive definite): some unknowns are not '
                    'determined by the observations; fix a datum (first node) or add priors'
                ) from exc
            self._F = self._symbolic
        else:  # pragma: no cover
            from scipy.sparse.linalg import splu
            N = p.full_csc(data)
            try:
                self._lu = splu(N, permc_spec='MMD_AT_PLUS_A')
            except RuntimeError as exc:
                raise DegenerateGeometryError('the normal matrix is singular') from exc

    def release_values(self) -> None:
        """Let go of the values last factored (the caller assembles new ones): a factor read
        out later (:meth:`trailing_lower`, selected inversion) cannot be recomputed for a
        solve then, until :meth:`refactor` is given values again."""
        self._data = None

    def _ordering(self) -> IntArray:
        """The scalar fill-reducing ordering: the block ordering, or the trailing blocks last."""
        if self._trailing is None:
            direct = _direct_cholmod()  # the orderings' flops from its symbolic analysis
            return block_ordering(self.pattern, None if direct is None else direct.analysis_flops)
        return _trailing_ordering(self.pattern, self._trailing)

    def _analyse(self):
        """CHOLMOD's symbolic analysis with the block ordering (trailing blocks last, kept in
        place: no postordering then), through cvxopt."""
        pvec = cvxopt.matrix(np.ascontiguousarray(self._ordering(), dtype=np.int64), tc='i')
        # only the ordering given (no second analysis with AMD); trailing blocks stay last
        saved = dict(_cholmod.options)
        _cholmod.options['nmethods'] = 1
        _cholmod.options['postorder'] = self._trailing is None
        try:
            return _cholmod.symbolic(self._A, p=pvec, uplo='L')
        finally:
            _cholmod.options.clear()
            _cholmod.options.update(saved)

    def permutation(self) -> IntArray:
        """``p`` of the factorisation ``P N P' = L L'``: row ``k`` of ``L`` is unknown ``p[k]``."""
        x = cvxopt.matrix(np.arange(self.n, dtype=float))
        _cholmod.solve(self._F, x, sys=7)
        return np.rint(np.array(x).ravel()).astype(np.int64)

    def trailing_lower(self, m: int) -> tuple[FloatArray, IntArray]:
        """The last ``m`` rows and columns of ``L`` (dense lower triangular) and the unknowns
        they belong to, in that order."""
        who = self.permutation()[self.n - m:]
        F = _cholmod.getfactor(self._F)  # this turns CHOLMOD's factor back into a symbolic one
        self._F = None
        self._symbolic = self._permuted = None  # analysed again if the factor is used again
        s0 = self.n - m
        colptr, rowind, values = F.CCS  # cvxopt matrices: read through the buffer protocol
        J = np.asarray(colptr).ravel()
        start = int(J[s0])
        rows = np.asarray(rowind).ravel()[start:]
        vals = np.asarray(values).ravel()[start:]
        cols = np.repeat(np.arange(s0, self.n), np.diff(J[s0:]))
        L = np.zeros((m, m))
        L[rows - s0, cols - s0] = vals
        return L, who

    def solve(self, b: FloatArray) -> FloatArray:
        """Solve ``N x = b`` for ``b`` of shape ``(n,)`` or ``(n, k)``."""
        b = np.asarray(b, dtype=float)
        if self._F is None and _cholmod is not None:  # the factor was read out: factor again
            if self._data is None:
                raise DegenerateGeometryError('this factor was read out and its values released:'
                                              ' refactor() it before solving')
            self.refactor(self._data)
        if self._F is not None:
            B = cvxopt.matrix(np.asfortranarray(b.reshape(self.n, -1)))
            _cholmod.solve(self._F, B)
            x = np.array(B).reshape(b.shape)
        else:  # pragma: no cover
            x = self._lu.solve(b)
        if not np.isfinite(x).all():
            raise DegenerateGeometryError('solving the normal equations produced NaN/inf: '
                                          'the problem is singular or badly scaled')
        return x


    def forward(self, b: FloatArray) -> FloatArray | None:
        """``L^-1 P b`` for ``b`` of shape ``(n, k)``, with ``P N P' = L L'`` this factor: half
        of :meth:`solve` (no backward solve); ``Y' Y`` of its columns is ``b' N^-1 b``, e.g. a
        node's marginal covariance from its unit columns. ``None`` without CHOLMOD's own factor
        (the caller solves then)."""
        if self._F is None and _cholmod is not None and self._data is not None:
            self.refactor(self._data)  # read out: factor again
        if self._F is None:
            return None
        B = cvxopt.matrix(np.asfortranarray(np.asarray(b, dtype=float).reshape(self.n, -1)))
        _cholmod.solve(self._F, B, sys=7)  # P b
        _cholmod.solve(self._F, B, sys=4)  # L^-1 (a supernodal factor is L L', no D)
        y = np.array(B)
        if not np.isfinite(y).all():
            raise DegenerateGeometryError('solving the normal equations produced NaN/inf: '
                                          'the problem is singular or badly scaled')
        return y


def _cvxopt_pattern(pattern: BlockPattern, keep: bool = True):
    """CHOLMOD's input matrix for a pattern (values are set before each factorisation). Building
    it sorts every entry again (~15 ms for 260,000 entries), so it is kept per pattern too
    (``keep``, or a pattern small enough to keep its entry positions; a large one not when only
    the symbolic analysis needs it: :func:`_direct_cholmod`)."""
    keep = keep or pattern.nnz < blocks._POSITIONS_KEPT_BELOW

    def build():
        return cvxopt.spmatrix(
            cvxopt.matrix(np.zeros(pattern.nnz)), cvxopt.matrix(pattern.indices.astype(np.int64)),
            cvxopt.matrix(_expand_cols(pattern.indptr)), (pattern.size, pattern.size))

    return _kept(_MATRICES, _MAX_MATRICES, pattern.key, build) if keep else build()
