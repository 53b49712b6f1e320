"""A fix source's offset as a random walk about its constant
(ga_ros.core.calibration.models.BiasWalk, in the batch): a simulated wandering offset followed by
the knots within 3 sigma, with a better path than the constant model; a constant or no offset:
the walk is not kept and the result is the one without the model, bit for bit; the process
noise estimated from the data; the model validated."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ga_ros.core.calibration import (
    BiasWalk,
    CalibrationConfig,
    FixObservations,
    RandomWalk,
    parameter_model,
    solve_with_calibration,
)
from ga_ros.core.fixes import gauge_information
from ga_ros.core.solver import GaussianPrior
from ga_ros.errors import InputError
from ga_ros.sim.biased import FixSource, biased_fixes, biased_survey

N = 300          # keyframes, 0.5 s apart: 150 s
Q = 0.2          # the simulated walk's process noise (m/sqrt(s))
SEGMENT_S = 15.0  # the knots' spacing (s)
AXES = ('offset_x', 'offset_y')


def _survey(seed: int, offset: str, q: float = Q, sources=None):
    """The survey with one fix source ``fix0`` (a fix every second, 0.2 m) whose x, y offset
    is ``offset``: 'walk' (a random walk of ``q`` m/sqrt(s) from 0 at the knots), 'constant'
    (1.5, -1.0) or 'none'; ``sources``: other fix sources, without the offset. Returns the
    survey, the fixes, the fix times (s) and fix0's true offsets (k, 2)."""
    rng = np.random.default_rng(seed)
    s = biased_survey(rng, n_nodes=N, sigma_xy_m=0.01, sigma_yaw_rad=0.001)
    stamps = np.arange(N) * 0.5
    obs = biased_fixes(rng, s.T_true, stamps, [FixSource('fix0', every=2, sigma_m=0.2)]
                       + list(sources or []))
    own = np.array([t.fix.source == 'fix0' for t in obs.terms])
    t = np.array([x.fix.stamp_ns for x in obs.terms]) * 1e-9
    k = int(own.sum())
    if offset == 'walk':
        # a random walk sampled at the model's knots, linear between them (the model's own
        # assumption: the bench, ga-ros bench fixwalk, draws a Gauss-Markov process instead)
        knots = BiasWalk('offset_x', segment_s=SEGMENT_S).basis(t[own]).knots_s
        steps = rng.normal(0.0, 1.0, (knots.size - 1, 2)) * q * np.sqrt(np.diff(knots))[:, None]
        at_knots = np.cumsum(np.r_[np.zeros((1, 2)), steps], axis=0)
        off = np.stack([np.interp(t[own], knots, at_knots[:, a]) for a in range(2)], axis=1)
    elif offset == 'constant':
        off = np.tile([1.5, -1.0], (k, 1))
    else:
        off = np.zeros((k, 2))
    terms = list(obs.terms)
    for i, o in zip(np.nonzero(own)[0], off):
        T = terms[i].fix.T_map_sensor.copy()
        T[:2, 3] += o
        terms[i] = replace(terms[i], fix=replace(terms[i].fix, T_map_sensor=T))
    return s, FixObservations(terms, obs.information, stamps), t[own], off


def _solve(s, obs, cal):
    m = len(s.network.arrays())
    gauge = GaussianPrior(s.network.node_ids[:1], s.T_true[:1],
                          gauge_information(1000.0, 0.05, 3.0), weak=True)
    return solve_with_calibration(s.network, s.T_true, ['odom0'] * m, np.full(m, 0.5),
                                  fixed=[], priors=[gauge], calibration=cal, fixes=obs,
                                  stamps_s=np.arange(m) * 0.5)


def _walk_cal(q: float = Q, **kw) -> CalibrationConfig:
    return CalibrationConfig(fix_parameters=AXES, **kw, models=tuple(
        BiasWalk(a, segment_s=SEGMENT_S, sigma_per_sqrt_s=q) for a in AXES))


def _rmse_frame(T, s, off):
    """2-D RMSE against the truth moved by the offset's mean (the frame one source defines)."""
    d = T[:, :2, 3] - s.T_true[:, :2, 3] - off.mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_knots_follow_a_simulated_wandering_offset(seed):
    """One fix source: its constant offset is the frame's (not determined), the walk about it
    is: kept (its F test), >= 80 % of the knots within 3 sigma of the true offset less its mean
    over the fixes, and the path at most half the constant model's error."""
    s, obs, t, off = _survey(seed, 'walk')
    res0, _ = _solve(s, obs, CalibrationConfig(fix_parameters=AXES))
    res, rep = _solve(s, obs, _walk_cal())
    for a, name in enumerate(AXES):
        par = next(p for p in rep.parameters if p.name == name)
        assert par.estimated and par.walk is not None, par.line()
        assert par.walk.test > par.walk.quantile
        assert par.value == 0.0   # the constant is the frame's
        true = np.interp(par.walk.knots_s, t, off[:, a]) - off[:, a].mean()
        err = np.abs(np.asarray(par.walk.values) - true)
        assert np.mean(err <= 3.0 * np.asarray(par.walk.sigmas)) >= 0.8, (err, par.line())
        # the knots' mean over the fixes is the constant (0): the frame is the fixes'
        hat = np.interp(t, par.walk.knots_s, par.walk.values)
        assert abs(hat.mean()) < 1e-9
    assert _rmse_frame(res.T_world_node, s, off) < 0.5 * _rmse_frame(res0.T_world_node, s, off)


@pytest.mark.parametrize('offset, seed', [('constant', 0), ('constant', 1), ('none', 0),
                                          ('none', 3)])
def test_constant_or_no_offset_keeps_no_walk_bit_for_bit(offset, seed):
    """A constant (or no) offset: the walk's deviations are not significant, nothing is
    estimated, and the adjustment is the one without the model, bit for bit."""
    s, obs, _, _ = _survey(seed, offset)
    res0, rep0 = _solve(s, obs, CalibrationConfig(fix_parameters=AXES))
    res, rep = _solve(s, obs, _walk_cal())
    np.testing.assert_array_equal(res.T_world_node, res0.T_world_node)
    for p, p0 in zip(rep.parameters, rep0.parameters):
        assert (p.estimated, p.value) == (p0.estimated, p0.value)
        assert p.walk is None
        if p.name in AXES:
            assert 'random walk not significant' in p.walk_note, p.line()
            assert 'random walk not significant' in p.line()


def test_a_second_source_with_a_constant_offset_ties():
    """A reference source and a second one with a constant offset: the offset is estimated as
    a constant, its walk is not kept, the result is the constant model's bit for bit."""
    rng_src = [FixSource('ref', every=6, first=1, sigma_m=0.2)]
    s, obs, _, off = _survey(5, 'constant', sources=rng_src)
    cal0 = CalibrationConfig(fix_parameters=AXES, fix_reference=('ref',))
    res0, rep0 = _solve(s, obs, cal0)
    res, rep = _solve(s, obs, replace(_walk_cal(), fix_reference=('ref',)))
    np.testing.assert_array_equal(res.T_world_node, res0.T_world_node)
    for a, name in enumerate(AXES):
        par = next(p for p in rep.parameters if p.name == name and p.source == 'fix0')
        assert par.estimated and par.walk is None
        assert abs(par.value - off[0, a]) < 3.0 * par.sigma, par.line()


def test_process_noise_estimated_from_the_data():
    """``estimate_sigma``: from a process noise 10x too large, the estimate comes within a
    factor of 2.5 of the simulated one (10 knots per axis: a rough estimate)."""
    s, obs, _, _ = _survey(0, 'walk')
    cal = CalibrationConfig(fix_parameters=AXES, models=tuple(
        BiasWalk(a, segment_s=SEGMENT_S, sigma_per_sqrt_s=10 * Q, estimate_sigma=True)
        for a in AXES))
    _, rep = _solve(s, obs, cal)
    qs = [p.walk.sigma_per_sqrt_s for p in rep.parameters if p.walk is not None]
    assert len(qs) == 2
    for q in qs:
        assert Q / 2.5 < q < 2.5 * Q, qs


def test_models_are_validated():
    with pytest.raises(InputError):
        CalibrationConfig(models=(BiasWalk('scale'),))   # a fix parameter's model
    with pytest.raises(InputError):
        CalibrationConfig(models=(RandomWalk('offset_x'),))   # an odometry parameter's
    with pytest.raises(InputError):
        BiasWalk('offset_x', sigma_iterations=0)
    m = parameter_model('offset_y', 'bias_walk', segment_s=20.0, sigma_per_sqrt_s=0.02)
    assert isinstance(m, BiasWalk) and m.family == 'fix'
    CalibrationConfig(fix_parameters=AXES, models=(m,))


def test_refine_batch_carries_the_bias_walk():
    """The window aligner's final batch (fixes one by one from its book, stamps from 1,000 s)
    with the walk: kept, its knots on the fixes' clock, the path in the fixes' frame closer
    to the truth than with the constant model."""
    from ga_ros.core.measurement import Measurement
    from ga_ros.core.window import AlignerConfig, TrackWindowAligner

    t0 = 1000.0
    s, obs, t, off = _survey(0, 'walk')
    arr = s.network.arrays()
    stamps = t0 + np.arange(N) * 0.5
    at: dict[int, list] = {}
    for term in obs.terms:
        at.setdefault(int(term.node_id), []).append(replace(term, fix=replace(
            term.fix, stamp_ns=int(round((t0 * 1e9) + term.fix.stamp_ns)))))
    al = TrackWindowAligner(AlignerConfig(datum='fixes', refine_executor='inline'),
                            T_world_first=s.T_true[0])
    track = prev = 0
    for c in range(len(arr)):
        i = c + 1
        al.add_measurement(Measurement(c, i, prev, track, arr.z[c], arr.cov[c],
                                       int(stamps[i] * 1e9), 'consecutive', 'odom0'))
        prev = track
        for node in ((0, i) if i == 1 else (i,)):
            for term in at.get(node, ()):
                al.add_fix(term)
        if i in at:
            al.finish_track()
            track += 1
    al.refine_batch(calibration=CalibrationConfig(fix_parameters=AXES))
    const = _rmse_frame(al.corrected_path().T_world_node, s, off)
    al.refine_batch(calibration=_walk_cal())
    walk = _rmse_frame(al.corrected_path().T_world_node, s, off)
    pars = [p for p in al.calibration.parameters if p.name in AXES]
    al.close()
    assert all(p.walk is not None for p in pars), al.calibration.lines()
    for p in pars:
        assert t0 - 1e-6 <= p.walk.knots_s[0] and p.walk.knots_s[-1] <= stamps[-1] + 1e-6
    assert walk < 0.5 * const, (walk, const)
