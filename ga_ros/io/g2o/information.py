"""Edge information matrices: upper triangles to full matrices, positive-definite check and
repair, and the covariances (inverses) the connection network holds."""

from __future__ import annotations

import warnings

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.covariance import (
    PD_TOLERANCE,
    nearest_positive_definite,
    not_positive_definite,
)
from ga_ros.errors import FormatError
from ga_ros.io.g2o.planar import SE2_AXES


class InformationRepairWarning(UserWarning):
    """Some information matrices of a file were not positive definite and were repaired."""


def upper_to_full(upper: FloatArray, d: int) -> FloatArray:
    """Symmetric ``(d, d)`` matrices from their row-major upper triangles ``(..., d(d+1)/2)``."""
    iu = np.triu_indices(d)
    out = np.zeros(upper.shape[:-1] + (d, d))
    out[..., iu[0], iu[1]] = upper
    out[..., iu[1], iu[0]] = upper
    return out


def checked_information(upper: FloatArray, d: int, e_lines: IntArray, strict: bool,
                         spath: str) -> tuple[FloatArray, FloatArray, tuple[int, ...]]:
    """Full information matrices, their eigenvalues and the lines repaired; refuses (strict)
    or repairs (with one warning) a matrix that is not positive definite."""
    info = upper_to_full(upper, d)
    eig = np.linalg.eigvalsh(info)  # once, for both checks (here and the covariance's)
    bad = not_positive_definite(info, eigenvalues=eig)
    repaired: tuple[int, ...] = ()
    if bad.any():
        k = int(np.argmax(bad))
        if strict:
            raise FormatError(f'information matrix is not positive definite (eigenvalues '
                              f'{np.array2string(eig[k], precision=3)}); drop strict to repair '
                              f'it to the nearest positive-definite matrix', spath,
                              int(e_lines[k]))
        info[bad] = nearest_positive_definite(info[bad])
        eig[bad] = np.linalg.eigvalsh(info[bad])
        repaired = tuple(int(v) for v in e_lines[bad].tolist())
        shown = ', '.join(map(str, repaired[:20])) + (', ...' if len(repaired) > 20 else '')
        # stacklevel 3: the caller of read_g2o (this runs inside read_g2o)
        warnings.warn(f'{spath}: {len(repaired)} information matrices were not positive '
                      f'definite and were repaired by eigenvalue clipping (lines {shown}); '
                      f'read strictly to refuse them instead', InformationRepairWarning,
                      stacklevel=3)
    return info, eig, repaired


def edge_covariances(info: FloatArray, eig: FloatArray, dim: int, e_lines: IntArray,
                 spath: str) -> FloatArray:
    """The edges' 6x6 covariances; refuses an information too ill-conditioned to invert."""
    if dim == 3:
        info6 = info
    else:
        info6 = np.broadcast_to(np.eye(6), (len(info), 6, 6)).copy()
        info6[:, SE2_AXES[:, None], SE2_AXES[None, :]] = info
    cov = np.linalg.inv(info6)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    # the network's rule for a covariance (ga_ros.core.network.check_covariances: smallest
    # eigenvalue above PD_TOLERANCE of its largest |entry|), from the information's eigenvalues
    # (those of the covariance are their inverses; a 2-D edge's padding adds eigenvalue 1)
    cov_min = 1.0 / eig[:, -1] if dim == 3 else np.minimum(1.0 / eig[:, -1], 1.0)
    singular = ~(cov_min > PD_TOLERANCE * np.abs(cov).max(axis=(1, 2)))
    if singular.any():
        k = int(np.argmax(singular))
        raise FormatError(f'information matrix is too ill-conditioned to invert (eigenvalues '
                          f'{np.array2string(eig[k], precision=3)}): its covariance would not '
                          'be positive definite; fix the matrix', spath, int(e_lines[k]))
    return cov
