"""Chi-square quantiles of ga_ros.core.chi2 against SciPy's distributions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import gammainc
from scipy.stats import chi2

from ga_ros.core.chi2 import chi2_quantile, gamma_p
from ga_ros.errors import InputError


@pytest.mark.parametrize('dof', [0.5, 1, 2, 3, 7, 30, 101, 2355, 118812])
@pytest.mark.parametrize('p', [1e-9, 0.025, 0.5, 0.975, 1 - 1e-9])
def test_quantile_equals_scipy(dof, p):
    assert chi2_quantile(dof, p) == pytest.approx(chi2.ppf(p, dof), rel=1e-10)


def test_incomplete_gamma_equals_scipy(rng):
    a = rng.uniform(0.1, 5000.0, size=200)
    x = a * rng.uniform(0.2, 2.0, size=200)
    ours = np.array([gamma_p(ai, xi) for ai, xi in zip(a, x)])
    np.testing.assert_allclose(ours, gammainc(a, x), rtol=1e-10, atol=1e-300)


@pytest.mark.parametrize('dof, p', [(0, 0.5), (3, 0.0), (3, 1.0), (-1, 0.5)])
def test_bad_arguments_raise(dof, p):
    with pytest.raises(InputError):
        chi2_quantile(dof, p)
