"""With ``variance_components: apply`` a change of the variance factors counts towards the
refinement's drift (``refine_relinearize_sigma``): the joint priors weight each source with the
factors of their linearisation, so a change of the factors calls for a refinement as a drift of
the frozen nodes does. Checked against the factors read from the book before and after each
update (``|sqrt(f_new / f_old) - 1|``, the largest over the sources)."""

from __future__ import annotations

import numpy as np
import pytest

import ga_ros.core.window.aligner as aligner_module
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb


@pytest.fixture(scope='module')
def ms():
    """An aerial survey whose odometry states covariances 4x too small (true factor 4)."""
    sc = aerial_scenario(n_tracks=8, positions_per_swath=6)
    nm = perturb(sc.true_motions(), NoiseModel(5.0, sc.depth_m), np.random.default_rng(5))
    return sc.measurements(nm.z, nm.cov / 4.0)


def _run(ms, sigma: float) -> tuple[TrackWindowAligner, list[tuple[float, float, float]]]:
    """Feed ``ms``; returns the aligner and, per update, ``(drift before, drift after, change
    of the factors)`` with the change computed here from the book's factors."""
    al = TrackWindowAligner(AlignerConfig(
        window_tracks=2, variance_components='apply', refine_every_tracks=1,
        refine_executor='inline', refine_relinearize_sigma=sigma))
    book = al.online_variance
    seen = []
    for m in ms:
        before, f0 = al.state.refine_drift, book.factors().copy()
        n_ref = al.handoff.n_refinements
        if al.add_measurement(m):
            f1 = book.factors()
            f0 = np.concatenate([f0, np.ones(f1.size - f0.size)])
            change = float(np.abs(np.sqrt(f1 / f0) - 1).max()) if f1.size else 0.0
            installed = al.handoff.n_refinements > n_ref
            seen.append((0.0 if installed else before, al.state.refine_drift, change))
    return al, seen


def test_a_change_of_the_factors_adds_to_the_drift(ms) -> None:
    al, seen = _run(ms, 1e6)   # never refines: the drift only grows
    assert al.handoff.n_refinements == 0
    assert max(c for _, _, c in seen) > 0.5     # the factors did change (1 -> about 4)
    for before, after, change in seen:
        assert after >= before + change - 1e-12, (before, after, change)


def test_a_change_of_the_factors_alone_starts_a_refinement(ms, monkeypatch) -> None:
    al, _ = _run(ms, 1.0)
    assert al.handoff.n_refinements >= 1
    # the same survey with the change of the factors not counted: the frozen nodes' drift
    # alone stays below 1 sigma and nothing is refined
    monkeypatch.setattr(aligner_module, 'factor_drift', lambda before, after: 0.0)
    al0, _ = _run(ms, 1.0)
    assert al0.handoff.n_refinements == 0
