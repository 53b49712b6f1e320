"""Inverses and factors of stacks of SPD matrices (:mod:`ga_ros.core.linalg.runs`): a
stack with runs of equal matrices is inverted once per run, bit for bit as every matrix alone."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.linalg import completion
from ga_ros.core.linalg.runs import RUNS_FROM
from ga_ros.errors import DegenerateGeometryError


def _spd(rng, m):
    A = rng.normal(size=(m, 6, 6))
    return A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(6)


@pytest.mark.parametrize('runs', [1, 3, 40])
def test_runs_of_equal_matrices_give_the_same_bits_as_each_alone(runs):
    rng = np.random.default_rng(runs)
    distinct = _spd(rng, runs)
    M = np.repeat(distinct, rng.integers(1, 9, runs), axis=0)
    if M.shape[0] < RUNS_FROM:
        M = np.repeat(M, RUNS_FROM // M.shape[0] + 1, axis=0)
    out = completion.spd_inverse(M, 'x')
    alone = np.concatenate([completion.spd_inverse(M[k:k + 1], 'x') for k in range(len(M))])
    assert out.view(np.int64).tolist() == alone.view(np.int64).tolist()
    np.testing.assert_allclose(out @ M, np.broadcast_to(np.eye(6), M.shape), atol=1e-8)
    out[0] = 0.0  # rows of one run are copies, not views of one inverse
    assert out[1].any()


def test_matrices_equal_but_for_the_sign_of_a_zero_are_inverted_each():
    M = np.repeat(np.eye(6)[None], RUNS_FROM, axis=0)
    M[1::2, 0, 1] = M[1::2, 1, 0] = -0.0
    out = completion.spd_inverse(M, 'x')
    alone = np.concatenate([completion.spd_inverse(M[k:k + 1], 'x') for k in range(len(M))])
    assert out.view(np.int64).tolist() == alone.view(np.int64).tolist()


def test_a_matrix_not_positive_definite_in_a_run_is_refused():
    M = np.repeat(np.eye(6)[None], 2 * RUNS_FROM, axis=0)
    M[5:9] = -np.eye(6)
    with pytest.raises(DegenerateGeometryError, match='not PD here'):
        completion.spd_inverse(M, 'not PD here')


def test_cholesky_by_runs_is_numpys_bit_for_bit():
    from ga_ros.core.linalg.runs import by_runs

    rng = np.random.default_rng(5)
    M = np.repeat(_spd(rng, 6), [1, 30, 2, 9, 1, 20], axis=0)
    out = by_runs(np.linalg.cholesky, M)
    assert out.view(np.int64).tolist() == np.linalg.cholesky(M).view(np.int64).tolist()
    few = _spd(rng, RUNS_FROM)  # no runs: the stack as it is
    assert np.array_equal(by_runs(np.linalg.cholesky, few), np.linalg.cholesky(few))
