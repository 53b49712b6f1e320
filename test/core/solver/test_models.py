"""Constraint models as classes (ga_ros.core.models): one registry keyed by the setting's
name, looked up with a clear error; the Jacobians themselves are checked in test_solver.py."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core import models
from ga_ros.core.solver import SolverConfig
from ga_ros.errors import InputError
from ga_ros.geometry import se3


def test_registry_holds_one_model_per_setting():
    assert models.MODEL_NAMES == ('se3', 'se2', 'paper', 'linear')
    kinds = {name: type(m) for name, m in models.MODELS.items()}
    assert kinds == {'se3': models.Se3Model, 'se2': models.Se2Model,
                     'paper': models.PositionModel, 'linear': models.LinearModel}
    assert models.MOTION_MODELS == ('se3', 'se2')
    for name, m in models.MODELS.items():
        assert m.name == name and models.model_of(name) is m and models.model_of(m) is m
        assert models.dof(name) == m.dof == m.equations


def test_unknown_model_is_refused_with_the_choices():
    with pytest.raises(InputError, match="'se3', 'se2', 'paper', 'linear'"):
        models.model_of('sim3')
    with pytest.raises(InputError, match='se3'):
        SolverConfig(model='sim3')
    with pytest.raises(InputError, match='observes no motions'):
        models.model_of('paper').motion_misclosure(np.eye(4)[None], np.array([0]),
                                                   np.array([0]), np.eye(4)[None])


@pytest.mark.parametrize('name', models.MODEL_NAMES)
def test_retract_moves_only_the_given_nodes(name, rng):
    """``retract`` changes the named nodes by ``exp(d)`` (motion models) or ``+ d``
    (positions), and no other node."""
    m = models.model_of(name)
    xi = rng.normal(0, 1, (5, 6))
    if name == 'se2':  # planar poses
        xi[:, 2:5] = 0.0
    T = se3.exp(xi)
    d = rng.normal(0, 0.1, (2, m.dof))
    out = m.retract(T, np.array([1, 3]), d)
    np.testing.assert_array_equal(out[[0, 2, 4]], T[[0, 2, 4]])
    if name == 'se3':
        np.testing.assert_allclose(out[[1, 3]], T[[1, 3]] @ se3.exp(d), atol=1e-12)
    elif name == 'se2':
        d6 = np.zeros((2, 6))
        d6[:, [0, 1, 5]] = d
        np.testing.assert_allclose(out[[1, 3]], T[[1, 3]] @ se3.exp(d6), atol=1e-12)
    else:
        np.testing.assert_allclose(out[[1, 3], :3, 3], T[[1, 3], :3, 3] + d, atol=1e-15)
