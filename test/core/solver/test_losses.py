"""Robust losses (ga_ros.core.solver.losses): each IRLS weight is the derivative of its cost,
the registry is the one list of choices, and unknown names are refused with the list."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.solver import SolverConfig
from ga_ros.core.solver.losses import LOSSES, ROBUST_LOSSES, RobustLoss, robust_loss
from ga_ros.errors import InputError


@pytest.mark.parametrize('name', ROBUST_LOSSES)
@pytest.mark.parametrize('scale', [0.7, 3.0])
def test_weight_is_the_derivative_of_rho_in_r2(name, scale, rng):
    """IRLS minimises ``sum rho(r^2)`` when a connection is weighted by ``d rho / d r^2``:
    checked by central differences of ``rho`` at distances on both sides of the scale."""
    loss = robust_loss(name, scale)
    r = np.concatenate([rng.uniform(0.05, scale * 0.95, 20), rng.uniform(scale * 1.05, 10, 20)])
    h = 1e-6 * np.maximum(r * r, 1.0)
    numeric = (loss.rho(r * r + h) - loss.rho(r * r - h)) / (2 * h)
    np.testing.assert_allclose(loss.weight(r), numeric, rtol=1e-6, atol=1e-9)
    # below the scale every loss is least squares to first order: rho(r2) ~ r2
    small = np.array([1e-4 * scale])
    np.testing.assert_allclose(loss.rho(small**2), small**2, rtol=1e-6)


def test_registry_is_the_one_list_of_choices():
    assert ROBUST_LOSSES[0] == 'none' and set(ROBUST_LOSSES) == {'none', 'huber', 'cauchy'}
    for name, cls in LOSSES.items():
        assert issubclass(cls, RobustLoss) and cls.name == name
    cfg = SolverConfig(robust_loss='cauchy', robust_scale=2.0)
    assert type(cfg.loss) is LOSSES['cauchy'] and cfg.loss.scale == 2.0
    from ga_ros.cli.commands import replay, solve
    for module in (replay, solve):  # the command lines offer the registry's names
        assert module.ROBUST_LOSSES is ROBUST_LOSSES


def test_unknown_loss_or_bad_scale_is_refused_with_the_choices():
    with pytest.raises(InputError, match='huber'):
        robust_loss('tukey')
    with pytest.raises(InputError, match='huber'):
        SolverConfig(robust_loss='tukey')
    with pytest.raises(InputError, match='> 0'):
        robust_loss('huber', 0.0)
