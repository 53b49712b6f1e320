"""Checking and repairing stacks of symmetric matrices (information or covariance).

A pose-graph edge, a bag measurement or a live measurement carries a symmetric ``(d, d)``
information (or covariance) matrix, ``d = 6`` in the order ``[x y z rx ry rz]`` or ``d = 3``
for ``[x y theta]``. Exporters sometimes write matrices that are not positive definite (an
indefinite edge in a real office dataset, rounding of tiny eigenvalues). The policy is:

* :func:`not_positive_definite` finds them, vectorised over the stack;
* :func:`nearest_positive_definite` repairs them by **eigenvalue clipping**: with
  ``A = V diag(w) V'``, the nearest symmetric positive semi-definite matrix in the Frobenius norm
  is ``V diag(max(w, 0)) V'`` (Higham, "Computing a nearest symmetric positive semidefinite
  matrix", Linear Algebra Appl. 103, 1988). To keep the result invertible the eigenvalues are
  clipped to ``floor = rel_floor * max(|w|)`` instead of 0, so the repaired matrix is positive
  definite with a condition number of at most ``1 / rel_floor``. Eigenvectors are unchanged:
  the well-determined directions keep their weight, the broken ones get almost none.
"""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray
from ga_ros.errors import InputError

#: a matrix whose smallest eigenvalue is at most this times its largest |entry| is rejected
PD_TOLERANCE = 1e-12
#: default clipping floor of :func:`nearest_positive_definite`, relative to the largest |eig|
CLIP_FLOOR = 1e-6


def not_positive_definite(matrices: FloatArray, tol: float = PD_TOLERANCE,
                          eigenvalues: FloatArray | None = None) -> BoolArray:
    """Which symmetric matrices of a stack are not (numerically) positive definite.

    Parameters
    ----------
    matrices : (k, d, d) symmetric matrices (only the lower triangle is read, as by ``eigvalsh``).
    tol : a matrix is flagged when its smallest eigenvalue is ``<= tol * max|entry|``.
    eigenvalues : (k, d) their eigenvalues in ascending order (``np.linalg.eigvalsh``), when the
        caller has them for another check too (finite matrices only); computed here otherwise.

    Returns
    -------
    (k,) boolean mask, ``True`` for a matrix that is not positive definite (or not finite).
    """
    A = np.asarray(matrices, dtype=float)
    if A.ndim != 3 or A.shape[1] != A.shape[2]:
        raise InputError(f'expected a (k, d, d) stack of square matrices, got shape {A.shape}')
    bad = ~np.isfinite(A).all(axis=(1, 2))
    out = bad.copy()
    ok = ~bad
    if ok.any():
        w = np.linalg.eigvalsh(A[ok]) if eigenvalues is None else eigenvalues[ok]
        scale = np.maximum(np.abs(A[ok]).max(axis=(1, 2)), 1e-300)
        out[ok] = w[:, 0] <= tol * scale
    return out


def nearest_positive_definite(matrices: FloatArray, rel_floor: float = CLIP_FLOOR) -> FloatArray:
    """Eigenvalue-clipped positive-definite versions of symmetric matrices (see module doc).

    Parameters
    ----------
    matrices : (k, d, d) finite symmetric matrices.
    rel_floor : eigenvalues below ``rel_floor * max(|w|)`` are raised to it (``0 < rel_floor
        < 1``). A matrix with no positive eigenvalue at all becomes ``rel_floor * max(|w|) * I``
        (or ``rel_floor * I`` if it is zero): it then carries almost no information.

    Returns
    -------
    (k, d, d) symmetric positive-definite matrices; an already positive-definite matrix whose
    eigenvalues are all above the floor comes back unchanged up to rounding.

    Raises
    ------
    InputError
        Non-finite entries or a bad ``rel_floor``.
    """
    if not 0 < rel_floor < 1:
        raise InputError(f'rel_floor must be in (0, 1), got {rel_floor}')
    A = np.asarray(matrices, dtype=float)
    if A.ndim != 3 or A.shape[1] != A.shape[2]:
        raise InputError(f'expected a (k, d, d) stack of square matrices, got shape {A.shape}')
    if not np.isfinite(A).all():
        raise InputError('cannot repair a matrix with NaN or inf entries')
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    w, V = np.linalg.eigh(A)
    largest = np.abs(w).max(axis=1, keepdims=True)
    floor = rel_floor * np.where(largest > 0, largest, 1.0)
    w = np.maximum(w, floor)
    out = (V * w[:, None, :]) @ np.swapaxes(V, 1, 2)
    return 0.5 * (out + np.swapaxes(out, 1, 2))
