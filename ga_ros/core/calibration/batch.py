"""Self-calibration in the batch adjustment: the additional parameters of each odometry source
(:mod:`ga_ros.core.calibration.parameters`), of each camera
(:mod:`ga_ros.core.calibration.camera_parameters`: its extrinsic's rotation, on all of its
connections, cross-track included) and of each fix source
(:mod:`ga_ros.core.calibration.fix_parameters`) estimated with the poses, where the network
determines them.

The joint adjustment. The unknowns are the poses ``x`` and the parameters ``c``; a connection
of a calibrated source has the misclosure ``e = log(T_corr(c)^-1 T_i^-1 T_j)``. Its normal
equations border the solver's normal matrix ``N_xx`` (poses, fixes and priors):

    [N_xx  N_xc] [dx]     [u_x]        N_xc = sum A' W E,  N_cc = sum E' W E,  u_c = sum E' W e
    [N_cx  N_cc] [dc] = - [u_c]

with ``A = de/dx`` (the solver's ``[-J_r(e)^-1 Ad(T_ij^-1), J_r(e)^-1]``), ``E = de/dc``
(:func:`~ga_ros.core.calibration.parameters.misclosure_jacobian`) and ``W`` the connection's
weight (``S^-1`` times its robust weight). The poses are eliminated with the factor of ``N_xx``
that the solver keeps (:meth:`~ga_ros.core.solver.SolveResult.solve_normal`): the reduced
normal matrix of the parameters is ``H = N_cc - N_cx N_xx^-1 N_xc`` and, at a pose solution
for the current ``c`` (``u_x = 0``), the step is ``dc = -H^-1 u_c``; the poses are then solved
again with the motions corrected by the new ``c`` (:func:`ga_ros.core.solver.solve`, warm from
the last estimate). This is Gauss-Newton on the joint problem with the poses re-solved at every
step (variable projection), and ``Q_cc = H^-1`` is the parameters' block of the joint inverse.
A step that raises the joint cost (the adjustment's ``v' P v``) is halved, at most
``_STEP_HALVINGS`` times; then the parameters stay where they are.

A fix source's parameters (given the fixes one by one,
:class:`~ga_ros.core.calibration.fix_parameters.FixObservations`) border the same matrix
through the fixes: each fix's
map-frame misclosure ``e = p_pred - p_corr(c)`` has ``A = de/dx`` the sensor Jacobian of its
node (:func:`~ga_ros.core.fixes.sensor_jacobian`), ``E = de/dc`` the parameter's Jacobian and
``W`` its information; the poses are solved with the fixes corrected by ``c`` (their weighted
parameters rebuilt from the corrected positions). The odometry and fix parameters are one
vector ``c``: they couple through the poses only.

Which parameters are estimated (as data snooping decides which observation is an outlier:
never estimate what the data cannot see). All candidates (every source x every parameter kind)
start free; then, one at a time, a parameter is fixed to zero with the reason recorded:

1. no motion it acts on (no translation for a scale, zero durations for a yaw rate);
2. not determined: its information left after the poses are eliminated, ``H_jj / N_cc,jj``,
   is below :attr:`CalibrationConfig.min_information_ratio` (odometry without fixes or loop
   closures: the poses absorb a scale or a heading drift completely), or its sigma with the
   other parameters known, ``1 / sqrt(H_jj)``, is above the parameter's ``max_sigma`` (a
   camera's extrinsic rotation: a first-order correction, 0.05 rad);
3. not separable: the condition number of ``H`` in correlation form exceeds
   :attr:`CalibrationConfig.max_condition`: of the parameters in the near-dependency (the
   eigenvector of the smallest eigenvalue), the one with the least information ratio goes
   (two fix sources' offsets, of which only the difference is determined: the better
   source's goes, and it stays the reference);
4. not significant: ``|c_j| / (sigma0 sqrt(Q_cc,jj))`` (``sigma0^2`` the a-posteriori variance
   factor of the joint adjustment, redundancy ``r - p``) below the two-sided quantile of
   Student's t with ``r - p`` degrees of freedom at :attr:`CalibrationConfig.alpha` (the
   least significant goes, and the rest are estimated again). With no systematic error a
   parameter is switched on with probability ``alpha``. A weak datum prior (``datum='fixes'``'s
   gauge) counts in the solver's redundancy without adding residuals, so on a small network
   ``sigma0^2`` comes out low and the test switches on a little more often.

The noise of a calibrated source. A source's stated covariance often stands for its systematic
error as well (a wheel odometry's yaw sigma chosen so that a heading drift fits as a random
walk); once the drift is a parameter, that covariance is too large and the fixes pull the
corrected path about more than they should. So, where a parameter of a source is estimated
(:attr:`CalibrationConfig.noise`, on by default), its noise is re-estimated (Förstner's
variance components, as :mod:`ga_ros.core.quality.variance_components` does per source, here
per block): the source's covariance splits into a translation and a rotation part (one part
where the stated covariances correlate the two), each scaled by a variance factor ``s``
(``D S D``, ``D = sqrt(s)`` on the part's rows). A part with less redundancy than
:attr:`CalibrationConfig.noise_min_redundancy` at its stated covariance keeps it (``r`` the
sum of its redundancy numbers, the diagonal of ``(Q_vv P)_ii``). The others are re-weighted,
with the parameters selected and estimated again (from their last values) at each new weight:

- the estimate at the current weights is the damped factor of
  :func:`~ga_ros.core.quality.variance_components.damped_factor` (the online variance
  components' definition): ``C / R`` (``C = v' S^-1 v`` under the stated covariances, ``R``
  the part's redundancy under the weights in use) shrunk towards 1 with a prior of
  :attr:`CalibrationConfig.noise_prior_dof` degrees of freedom,
  ``(C / R) ^ (R / (R + noise_prior_dof))``. Without the prior the iteration
  ``s <- s v' P v / r`` can collapse: a part whose weight grows loses redundancy and residual
  together and runs to 0 (a rotation factor of 0.001 at a redundancy of 0.2 with a fix every
  10 keyframes); with it, the estimate tends to 1 as the redundancy vanishes;
- each step moves a factor by at most the ratio :attr:`CalibrationConfig.noise_max_step`;
- a part whose redundancy falls below the minimum at its new factor keeps the factor at which
  it was last determined (:attr:`NoiseFactor.held`), and the others go on;
- the iteration stops when no factor would move by more than
  :attr:`CalibrationConfig.noise_tolerance`.

The estimate depends continuously on the data: no test decides whether a part is re-weighted
(the chi-square test of the stated covariance, ``v' P v / r`` against ``chi2(r) / r`` at
:attr:`CalibrationConfig.noise_alpha`, is reported beside it), so a rounding-sized change of
the input gives a rounding-sized change of the factors. The prior biases a factor towards 1 by
the exponent ``R / (R + noise_prior_dof)``: below 10 % where ``R`` is some hundreds, large
where the part is poorly determined. The fixes, the priors and the connections without a
source keep their stated covariances (the factors are relative to them). The factors are
reported with their sigmas ``s sqrt(2 / R)`` (:class:`NoiseFactor`).

Where fix (or camera) parameters were candidates and none is estimated, the selection is run
again without them, so the result is the adjustment without fix (camera) parameters bit for
bit (the candidates' reasons are kept in the report). A fix source's noise is not re-estimated (its
stated covariance stands).

A random walk. A parameter kind whose model (:attr:`CalibrationConfig.models`) is a
:class:`~ga_ros.core.calibration.models.RandomWalk` is selected as a constant (steps 1-4: the
test is that of its mean level); where it is kept, it is then estimated as the walk
(:func:`_walk`): its knots' values are columns bordered onto the pose system like the constant
(the constant's column of ``N_xc`` weighted by each knot's hat function), the random walk's
pseudo-observations ``c_k+1 - c_k = 0`` add their ``D' W D`` to the reduced normal matrix, and
Gauss-Newton runs on the knots (and the other kept parameters) from the constants' estimates,
the poses re-solved at each step, a step that raises the joint cost (``v' P v`` plus the
pseudo-observations') halved. The report keeps the constant's test and gives the walk
(:class:`WalkEstimate`).

The published sigma of a parameter is ``sqrt(Q_cc,jj)`` (a-priori, as the poses' covariances
``Q_x = N^-1``). The poses' covariances of the result are those given the parameters (they
leave out the parameters' own uncertainty, ``N_xx^-1 N_xc Q_cc N_cx N_xx^-1``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.calibration.camera_parameters import (
    CAMERA_PARAMETERS,
    camera_parameter,
    camera_sources,
)
from ga_ros.core.calibration.fix_parameters import (
    FIX_PARAMETERS,
    FixObservations,
    fix_jacobians,
    fix_misclosures,
    fix_parameter,
    fix_priors,
    fix_shift,
    node_velocities,
)
from ga_ros.core.calibration.models import BiasWalk, ConstantLevel, ParameterModel, WalkBasis
from ga_ros.core.calibration.parameters import (
    PARAMETERS,
    CorrectedMotions,
    MotionCorrections,
    misclosure_jacobian,
    parameter,
)
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.quality.variance_components import damped_factor, factor_sigma
from ga_ros.core.solver import GaussianPrior, SolverConfig, SolveResult, solve
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.runtime import lazy_import

stats = lazy_import('scipy.stats')  # the significance test only (start-up)

#: A parameter takes part in a near-dependency of the parameters when its component of the
#: eigenvector of the smallest eigenvalue (correlation form) is at least this share of the
#: largest (step 3 of the module doc).
_DEPENDENCY_SHARE = 0.1
#: A parameter step that raises the joint cost is halved at most this many times (then the
#: parameters stay where they are).
_STEP_HALVINGS = 6
#: The parameter lookup of each model family (:attr:`ParameterModel.family`).
_FAMILY_PARAMETER = {'odometry': parameter, 'fix': fix_parameter}


@dataclass(frozen=True)
class CalibrationConfig:
    """Settings of :func:`solve_with_calibration`.

    Attributes
    ----------
    parameters : the parameter kinds estimated per odometry source (:data:`PARAMETERS`:
        ``'scale'``, ``'yaw_rate'``).
    fix_parameters : the parameter kinds estimated per fix source, when the fixes are given
        one by one (:data:`~ga_ros.core.calibration.fix_parameters.FIX_PARAMETERS`:
        ``'offset_x'``, ``'offset_y'``, ``'offset_z'``, ``'time_offset'``). By default the
        time offset only: a receiver's latency is common and a moving robot's own fixes
        determine it, while a constant offset is only seen against other absolute
        information (a second fix source, a held node, a prior) and with a single fix source
        the fixes define the map frame (docs/calibration.md, *Fix sources*). Where no fix
        parameter is estimated the result is the one without fix parameters, bit for bit.
    fix_reference : fix sources that define the frame: they get no offset (their time offset
        stays a candidate). Without one, of two sources whose offsets only their difference
        determines, the better one's is dropped (step 3).
    cameras : the sources that are cameras (the ``source`` of their measurements,
        consecutive and cross-track: :func:`~ga_ros.core.calibration.camera_parameters.
        camera_sources`, which the aligner's final batch uses): each gets
        ``camera_parameters`` on every one of its connections. None by default: a camera's
        extrinsic is seen only against another source of the body's orientation
        (docs/calibration.md, *Cameras*), so it is switched on by naming the camera.
    camera_parameters : the parameter kinds estimated per camera
        (:data:`~ga_ros.core.calibration.camera_parameters.CAMERA_PARAMETERS`:
        ``'extrinsic_rx'``, ``'extrinsic_ry'``, ``'extrinsic_rz'``, rad, body frame). Where no
        camera parameter is estimated the result is the one without them, bit for bit.
    models : how a parameter varies over the survey, one entry per parameter kind whose
        model is not the default constant: an odometry parameter's
        :class:`~ga_ros.core.calibration.models.RandomWalk` (knots every ``segment_s`` tied
        by a random walk of ``sigma_per_sqrt_s``; module doc, *A random walk*), a fix
        parameter's :class:`~ga_ros.core.calibration.models.BiasWalk` (its constant plus a
        random walk about it, tested on its own; module doc, *A wandering fix offset*). Empty
        by default: every parameter is a constant, as without the field.
    alpha : significance level of the two-sided test of each parameter (module doc, step 4):
        the probability of switching a parameter on when the source has no such error.
    min_information_ratio : a parameter whose information left after eliminating the poses is
        below this fraction of its own (step 2) is not determined by the network.
    max_condition : largest condition number of the parameters' reduced normal matrix in
        correlation form (step 3).
    max_iterations : Gauss-Newton steps of the parameters per set of free parameters.
    tolerance : the steps stop when every parameter moved less than this fraction of its
        sigma.
    noise : re-estimate the noise of every source with an estimated parameter (module doc,
        *The noise of a calibrated source*); ``False``: keep its stated covariance.
    noise_iterations : re-weighted adjustments at most.
    noise_tolerance : stop when no factor would move by more than this fraction.
    noise_min_redundancy : a part with less redundancy at its stated covariance is not
        estimated (its factor stays 1); a part whose redundancy falls below it while it is
        re-weighted keeps the factor at which it was last determined.
    noise_prior_dof : degrees of freedom of the prior ``s = 1`` each factor is shrunk
        towards (:func:`~ga_ros.core.quality.variance_components.damped_factor`).
    noise_max_step : a factor changes by at most this ratio per re-weighted adjustment.
    noise_factor_bounds : ``v' P v / r`` is clipped to this range before it is damped.
    noise_alpha : significance level of the reported test of a part's stated covariance
        (the range of ``chi2(r) / r``, :attr:`NoiseFactor.quantiles`).
    """

    parameters: tuple[str, ...] = ('scale', 'yaw_rate')
    fix_parameters: tuple[str, ...] = ('time_offset',)
    fix_reference: tuple[str, ...] = ()
    cameras: tuple[str, ...] = ()
    camera_parameters: tuple[str, ...] = ('extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz')
    models: tuple[ParameterModel, ...] = ()
    alpha: float = 0.001
    min_information_ratio: float = 1e-6
    max_condition: float = 1e6
    max_iterations: int = 10
    tolerance: float = 1e-3
    noise: bool = True
    noise_iterations: int = 20
    noise_tolerance: float = 0.01
    noise_min_redundancy: float = 3.0
    noise_prior_dof: float = 4.0
    noise_max_step: float = 2.0
    noise_factor_bounds: tuple[float, float] = (1e-3, 1e3)
    noise_alpha: float = 0.01

    def __post_init__(self) -> None:
        for p in self.parameters:
            parameter(p)
        for p in self.fix_parameters:
            fix_parameter(p)
        for p in self.camera_parameters:
            camera_parameter(p)
        for m in self.models:
            if not isinstance(m, ParameterModel):
                raise InputError(f'calibration models: {m!r} is not a ParameterModel')
            _FAMILY_PARAMETER[m.family](m.parameter)
        named = [m.parameter for m in self.models]
        if len(set(named)) != len(named):
            raise InputError(f'calibration models: a parameter has two models ({named})')
        if not 0.0 < self.alpha < 1.0:
            raise InputError(f'calibration alpha must be in (0, 1), got {self.alpha}')
        if not 0.0 < self.noise_alpha < 1.0:
            raise InputError(f'calibration noise_alpha must be in (0, 1), got '
                             f'{self.noise_alpha}')
        if int(self.noise_iterations) < 1 or not self.noise_tolerance > 0:
            raise InputError('calibration: noise_iterations must be >= 1 and noise_tolerance '
                             '> 0')
        if not self.noise_prior_dof >= 0 or not self.noise_max_step > 1:
            raise InputError('calibration: noise_prior_dof must be >= 0 and noise_max_step > 1')
        lo, hi = self.noise_factor_bounds
        if not 0 < lo < 1 < hi:
            raise InputError('calibration: noise_factor_bounds must be (lo, hi) with '
                             '0 < lo < 1 < hi')

    def model(self, kind: str) -> ParameterModel:
        """The model of the parameter ``kind`` (:attr:`models`, else a constant)."""
        return next((m for m in self.models if m.parameter == kind), ConstantLevel(kind))


@dataclass
class AdditionalParameter:
    """One source's additional parameter after the adjustment.

    Attributes
    ----------
    source : the odometry source (the group of its measurements).
    name, unit : the parameter (:data:`~ga_ros.core.calibration.parameters.PARAMETERS`).
    value : its estimate (0 when not estimated).
    sigma : its a-priori standard deviation ``sqrt(Q_cc,jj)`` (NaN when never estimated).
    test : ``|value| / (sigma0 sigma)`` when last estimated (NaN if never).
    quantile : the test's critical value (two-sided Student t quantile of ``alpha``).
    information_ratio : ``H_jj / N_cc,jj`` (module doc, step 2).
    estimated : whether the value is used (``False``: fixed to 0 for ``reason``).
    reason : why it is not estimated ('' when it is).
    tested_value : the estimate when it was tested (the value that was not significant; with
        a random walk, the constant whose test decided it).
    walk : with a random-walk model (:attr:`CalibrationConfig.models`) and the parameter
        estimated, the walk (:class:`WalkEstimate`); ``value`` is then the walk's mean over
        the source's motions (duration-weighted; a fix parameter's: over its fixes, the
        constant) and ``sigma`` the constant's.
    walk_note : a :class:`~ga_ros.core.calibration.models.BiasWalk` that was not kept: why
        ('' otherwise).
    """

    source: str
    name: str
    unit: str
    value: float = 0.0
    sigma: float = float('nan')
    test: float = float('nan')
    quantile: float = float('nan')
    information_ratio: float = float('nan')
    estimated: bool = False
    reason: str = ''
    tested_value: float = float('nan')
    walk: WalkEstimate | None = None
    walk_note: str = ''

    def line(self) -> str:
        """One line of text: the estimate with its sigma and test, or why it is fixed."""
        head = f'{self.source} {self.name}'
        note = f'; {self.walk_note}' if self.walk_note else ''
        if self.estimated and self.walk is not None and np.isfinite(self.walk.test):
            w = self.walk
            return (f'{head}: constant {self.value:.6g} {self.unit} plus a random walk of '
                    f'{len(w.values)} knots every {w.segment_s:g} s, {min(w.values):.4g} to '
                    f'{max(w.values):.4g} (sigmas {min(w.sigmas):.2g}-{max(w.sigmas):.2g}), '
                    f'q {w.sigma_per_sqrt_s:.2g} {self.unit}/sqrt(s), F {w.test:.1f} > '
                    f"{w.quantile:.2f}; pseudo-observations v'Pv/r {w.ratio:.3g} "
                    f'(r {w.redundancy:.1f})')
        if self.estimated and self.walk is not None:
            w = self.walk
            return (f'{head} = {self.tested_value:.6g} +- {self.sigma:.2g} {self.unit} '
                    f'(|t| {self.test:.1f} > {self.quantile:.2f}); random walk '
                    f'{len(w.values)} knots every {w.segment_s:g} s, {min(w.values):.4g} to '
                    f'{max(w.values):.4g} (sigmas {min(w.sigmas):.2g}-{max(w.sigmas):.2g}), '
                    f'q {w.sigma_per_sqrt_s:.2g}/sqrt(s), pseudo-observations '
                    f"v'Pv/r {w.ratio:.3g} (r {w.redundancy:.1f})")
        if self.estimated:
            return (f'{head} = {self.value:.6g} +- {self.sigma:.2g} {self.unit} '
                    f'(|t| {self.test:.1f} > {self.quantile:.2f}){note}')
        return f'{head}: not estimated ({self.reason}){note}'


@dataclass
class WalkEstimate:
    """A parameter's random walk after the adjustment (module doc, *A random walk*).

    Attributes
    ----------
    knots_s : the knots' times (s, the stamps' clock).
    values : the parameter at each knot (its unit; linear between knots).
    sigmas : their a-priori standard deviations (the diagonal of the knots' ``Q_cc``).
    segment_s, sigma_per_sqrt_s : the model's knot spacing (s) and process noise ``q``.
    cost : ``v' P v`` of the pseudo-observations ``c_k+1 - c_k = 0``.
    redundancy : their redundancy ``K - 1 - tr(W D Q_cc D')``.
    ratio : ``cost / redundancy``: about 1 where ``q`` fits the data; ``q sqrt(ratio)`` is
        the process noise the data estimate (one step of a variance-component estimate).
    test, quantile : a walk about the constant
        (:class:`~ga_ros.core.calibration.models.BiasWalk`): the F statistic of its
        deviations and the critical value it passed (NaN for a
        :class:`~ga_ros.core.calibration.models.RandomWalk`, whose constant's test decides).
    """

    knots_s: list[float]
    values: list[float]
    sigmas: list[float]
    segment_s: float
    sigma_per_sqrt_s: float
    cost: float = float('nan')
    redundancy: float = float('nan')
    ratio: float = float('nan')
    test: float = float('nan')
    quantile: float = float('nan')


@dataclass
class NoiseFactor:
    """The re-estimated noise of one part of a calibrated source's stated covariance.

    Attributes
    ----------
    source : the odometry source.
    part : ``'translation'`` (the ``[x y z]`` block), ``'rotation'`` (the ``[rx ry rz]``
        block) or ``'motion'`` (the whole covariance, where the stated one correlates the two).
    factor : the variance factor the weights use (``4``: the stated covariance of the part is
        4x too small; the standard deviations 2x); 1 where not applied.
    estimate : the factor estimated at the last weights (where applied, equal to ``factor``
        within :attr:`CalibrationConfig.noise_tolerance`).
    sigma : its standard deviation ``estimate sqrt(2 / redundancy)``.
    redundancy : the part's redundancy ``r_k`` (sum of its redundancy numbers) at the last
        weights.
    stated_ratio : ``v' P v / r`` at the stated covariance (the test statistic).
    quantiles : the range of ``chi2(r) / r`` at ``noise_alpha`` (NaN: too little redundancy
        to test).
    applied : whether the weights use it (the part had enough redundancy to estimate it).
    held : its redundancy fell below the minimum while it was re-weighted: ``factor`` is the
        one at which it was last determined.
    """

    source: str
    part: str
    factor: float = 1.0
    estimate: float = 1.0
    sigma: float = float('nan')
    redundancy: float = 0.0
    stated_ratio: float = float('nan')
    quantiles: tuple[float, float] = (float('nan'), float('nan'))
    applied: bool = False
    held: bool = False

    def line(self) -> str:
        """One line of text."""
        head = f'{self.source} {self.part} noise'
        lo, hi = self.quantiles
        test = (f"stated: v'Pv/r {self.stated_ratio:.3g}, chi2 range [{lo:.2g}, {hi:.2g}]"
                if np.isfinite(lo) else 'too little redundancy to test')
        if self.applied:
            held = (', held: its redundancy fell below the minimum when re-weighted'
                    if self.held else '')
            return (f'{head}: variance factor {self.factor:.3g} +- {self.sigma:.2g} applied '
                    f'(redundancy {self.redundancy:.1f}{held}; {test})')
        return (f'{head}: stated covariance kept (redundancy {self.redundancy:.1f}; '
                f'{test})')


@dataclass
class CalibrationReport:
    """The additional parameters of every source, and how they were found; the re-estimated
    noise of the calibrated sources (``noise``, empty when none was re-estimated)."""

    parameters: list[AdditionalParameter] = field(default_factory=list)
    alpha: float = float('nan')
    sigma0_sq: float = float('nan')
    iterations: int = 0
    solves: int = 0
    noise: list[NoiseFactor] = field(default_factory=list)
    noise_iterations: int = 0

    def estimated(self) -> list[AdditionalParameter]:
        return [p for p in self.parameters if p.estimated]

    def value(self, source: str, name: str) -> float:
        """The value of one parameter (0 when not estimated or unknown)."""
        return next((p.value for p in self.parameters
                     if p.source == source and p.name == name), 0.0)

    def as_dict(self) -> dict:
        """Plain data (``summary.json``)."""
        return {'alpha': self.alpha, 'sigma0_sq': self.sigma0_sq,
                'iterations': self.iterations, 'solves': self.solves,
                'parameters': [_plain(p) for p in self.parameters],
                'noise': [_plain(f) for f in self.noise],
                'noise_iterations': self.noise_iterations}

    def lines(self) -> list[str]:
        """The report as text, one parameter (and one noise factor) per line."""
        return [p.line() for p in self.parameters] + [f.line() for f in self.noise]


def _plain(obj: AdditionalParameter | NoiseFactor) -> dict:
    def one(v):
        if isinstance(v, (tuple, list)):
            return [one(x) for x in v]
        if isinstance(v, dict):
            return {k: one(x) for k, x in v.items()}
        return None if isinstance(v, float) and not np.isfinite(v) else v
    # a constant's report has no walk (the key is left out, as before there were walks)
    return {k: one(v) for k, v in asdict(obj).items()
            if not (k == 'walk' and v is None) and not (k == 'walk_note' and not v)}


@dataclass
class _Candidates:
    """The candidate parameters: ``(source, kind)``, the parameter (odometry:
    :data:`~ga_ros.core.calibration.parameters.PARAMETERS`; fix:
    :data:`~ga_ros.core.calibration.fix_parameters.FIX_PARAMETERS`) and the connections (or,
    for a fix parameter, the fixes) it acts on."""

    sources: list[str]
    kinds: list[str]
    masks: list[np.ndarray]
    params: list = field(default_factory=list)

    def on_fixes(self, j: int) -> bool:
        return self.params[j].on_fixes


def _candidates(sources: Sequence[str | None], names: Sequence[str],
                fix_sources: Sequence[str] = (), fix_names: Sequence[str] = (),
                reference: Sequence[str] = (), cameras: Sequence[str | None] = (),
                camera_names: Sequence[str] = ()) -> _Candidates:
    """Every source x parameter kind: the odometry's, then the cameras', then the fix
    sources' (the selection's order)."""
    out = _Candidates([], [], [])
    for srcs, kinds, table in ((sources, names, PARAMETERS),
                               (cameras, camera_names, CAMERA_PARAMETERS),
                               (fix_sources, fix_names, FIX_PARAMETERS)):
        src = np.array(['' if s is None else str(s) for s in srcs], dtype=object)
        for s in sorted({str(s) for s in srcs if s}):
            mask = src == s
            for k in kinds:
                if table[k].datum and s in reference:
                    continue
                out.sources.append(s)
                out.kinds.append(k)
                out.masks.append(mask)
                out.params.append(table[k])
    return out


def _per_connection(cand: _Candidates, values: FloatArray, m: int,
                    walks: dict[int, FloatArray] | None = None) -> MotionCorrections:
    """The corrections of every connection: candidate ``j``'s ``values[j]`` on its
    connections, or with a random walk ``walks[j]`` (its value on each of them, in their
    order)."""
    corr = MotionCorrections.zeros(m)
    for j, (par, mask) in enumerate(zip(cand.params, cand.masks)):
        if not par.on_fixes:
            par.add(corr, mask, values[j] if not walks or j not in walks else walks[j])
    return corr


@dataclass
class _FixState:
    """The fixes at one estimate of the poses: their node rows, velocities and the Jacobians
    ``E`` (k, 6, c) of every candidate (zero for a non-fix candidate and for the fixes of
    other sources)."""

    rows: np.ndarray
    velocity: FloatArray
    E: FloatArray

    @staticmethod
    def at(obs: FixObservations | None, network: ConnectionNetwork, T: FloatArray,
           cand: _Candidates) -> _FixState | None:
        if obs is None or not len(obs):
            return None
        rows = obs.rows(network.node_ids)
        v = node_velocities(T, obs.node_stamps_s)[rows]
        E = np.zeros((len(obs), 6, len(cand.kinds)))
        for j, par in enumerate(cand.params):
            if par.on_fixes:
                E[cand.masks[j], :, j] = fix_jacobians(obs, [par], v)[cand.masks[j], :, 0]
        return _FixState(rows, v, E)


@dataclass
class _Bordered:
    """The reduced normal equations of the free parameters at a pose solution."""

    H: FloatArray  # (p, p) N_cc - N_cx N_xx^-1 N_xc
    g: FloatArray  # (p,) u_c
    Ncc_diag: FloatArray  # (p,)


def _bordered(network: ConnectionNetwork, res: SolveResult, motions: CorrectedMotions,
              cand: _Candidates, active: list[int],
              fixes: FixObservations | None = None, values: FloatArray | None = None,
              weights: Sequence[FloatArray | None] | None = None,
              walks: dict[int, FloatArray] | None = None) -> _Bordered:
    """The reduced normal equations of the ``active`` parameters at the adjustment ``res``:
    the connections of the odometry parameters (misclosures of the corrected motions
    ``motions``) and the fixes of the fix parameters (misclosures against the fixes corrected
    by ``values``, the Jacobians ``E`` at the velocities of ``res``'s poses). ``weights``: per
    entry of ``active`` (a candidate may come several times), None or its weight on each of
    the candidate's connections or fixes (a random walk's knot: its hat function), which
    scales the column; ``walks``: the fix parameters' values fix by fix where they are walks
    (:func:`_fix_shift`)."""
    arrays = network.arrays()
    p = len(active)
    free_ids = res.free_node_ids
    col = np.full(network.n_nodes, -1, dtype=np.int64)
    col[network.indices_of(free_ids)] = np.arange(free_ids.size)
    Ncc = np.zeros((p, p))
    g = np.zeros(p)
    Nxc = np.zeros((free_ids.size, 6, p))
    odo = [a for a, j in enumerate(active) if not cand.on_fixes(j)]
    sel = np.zeros(len(arrays), bool)
    for a in odo:
        sel |= cand.masks[active[a]]
    idx = np.nonzero(sel)[0]
    if idx.size:
        T = res.T_world_node
        src, dst = arrays.src[idx], arrays.dst[idx]
        Tij = se3.relative(T[src], T[dst])
        mo = motions.rows(idx)
        e = se3.log(se3.inverse(mo.T) @ Tij)
        Jr_inv = se3.right_jacobian_inv(e)
        A_dst = Jr_inv
        A_src = -Jr_inv @ se3.adjoint(se3.inverse(Tij))
        E = np.zeros((idx.size, 6, p))
        own: dict[int, FloatArray] = {}   # each candidate's Jacobian, for its knots' columns
        for a in odo:
            j = active[a]
            rows = cand.masks[j][idx]
            if j not in own:
                G = cand.params[j].generator_of(mo.rows(rows))
                own[j] = misclosure_jacobian(e[rows], G)
            E[rows, :, a] = own[j]
            if weights is not None and weights[a] is not None:
                E[rows, :, a] *= weights[a][:, None]
        W = np.linalg.inv(arrays.cov[idx])
        if res.weights is not None:
            W = W * np.asarray(res.weights)[idx, None, None]
        WE = W @ E
        Ncc += np.einsum('mki,mkj->ij', E, WE)
        g += np.einsum('mki,mk->i', E, (W @ e[:, :, None])[:, :, 0])
        for c, A in ((col[src], A_src), (col[dst], A_dst)):
            keep = c >= 0
            np.add.at(Nxc, c[keep], (np.swapaxes(A, 1, 2) @ WE)[keep])
    if fixes is not None and len(odo) < p:
        fs = _FixState.at(fixes, network, res.T_world_node, cand)
        Ef = fs.E[:, :, active]
        if weights is not None:
            for a, j in enumerate(active):
                if weights[a] is not None and cand.on_fixes(j):
                    Ef[cand.masks[j], :, a] *= weights[a][:, None]
        ef, Af = fix_misclosures(fixes, res.T_world_node, fs.rows,
                                 _fix_shift(fs.E, cand, values, walks))
        WE = fixes.information @ Ef
        Ncc += np.einsum('mki,mkj->ij', Ef, WE)
        g += np.einsum('mki,mk->i', Ef, (fixes.information @ ef[:, :, None])[:, :, 0])
        c = col[fs.rows]
        keep = c >= 0
        np.add.at(Nxc, c[keep], (np.swapaxes(Af, 1, 2) @ WE)[keep])
    Nxc = Nxc.reshape(-1, p)
    Z = res.solve_normal(Nxc)
    H = Ncc - Nxc.T @ Z
    return _Bordered(0.5 * (H + H.T), g, np.diag(Ncc).copy())


def _fix_shift(E: FloatArray, cand: _Candidates, values: FloatArray,
               walks: dict[int, FloatArray] | None) -> FloatArray:
    """(k, 3) each fix's shift to its corrected position (:func:`~ga_ros.core.calibration.
    fix_parameters.fix_shift`) with the fix parameters ``values``, those in ``walks`` (a
    :class:`~ga_ros.core.calibration.models.BiasWalk`'s) taking their value fix by fix (on
    the candidate's fixes, in their order). No fix walk: :func:`fix_shift` itself."""
    fix_walks = {j: w for j, w in (walks or {}).items() if cand.on_fixes(j)}
    if not fix_walks:
        return fix_shift(E, values)
    V = np.tile(np.asarray(values, dtype=float), (E.shape[0], 1))
    for j, w in fix_walks.items():
        V[cand.masks[j], j] = w
    return -np.einsum('kip,kp->ki', E[:, :3, :], V)


def solve_with_calibration(network: ConnectionNetwork, T_init: FloatArray,
                           sources: Sequence[str | None], dt_s: FloatArray,
                           config: SolverConfig | None = None,
                           fixed: Sequence[int] | None = None,
                           priors: Sequence[GaussianPrior] = (),
                           calibration: CalibrationConfig | None = None,
                           fixes: FixObservations | None = None,
                           groups: Sequence[str | None] | None = None,
                           stamps_s: FloatArray | None = None
                           ) -> tuple[SolveResult, CalibrationReport]:
    """The batch adjustment with each odometry source's, each camera's and each fix source's
    additional parameters (module doc).

    Parameters
    ----------
    network : the connections, their motions as measured (uncorrected).
    T_init : (n, 4, 4) initial poses, network index order.
    sources : (m,) the source of each connection, in connection order; ``None`` (or '') for
        connections without additional parameters (cross-track connections, bridges).
    dt_s : (m,) duration of each connection's motion (s; ``stamp(dst) - stamp(src)``); a
        non-finite or negative one counts as 0 (no yaw-rate correction).
    config, fixed, priors : as :func:`ga_ros.core.solver.solve`.
    calibration : which parameters, and the tests (:class:`CalibrationConfig`).
    fixes : the absolute fixes one by one
        (:class:`~ga_ros.core.calibration.fix_parameters.FixObservations`), for their
        sources' parameters
        (:attr:`CalibrationConfig.fix_parameters`): they enter as the weighted parameters
        of :func:`~ga_ros.core.calibration.fix_parameters.fix_priors` before ``priors``
        (which must then not hold them again): as measured, linearised at ``T_init``, while
        no fix parameter is non-zero; corrected, linearised at the poses each adjustment
        starts from, otherwise. None: the fixes are in ``priors`` and have no parameters.
    groups : (m,) the source of every connection, consecutive and cross-track alike (the
        variance group of its measurement, :func:`~ga_ros.core.measurement.variance_group`):
        the connections of each camera named in :attr:`CalibrationConfig.cameras` get its
        extrinsic parameters. None: ``sources``.
    stamps_s : (m,) the stamp of each connection's first node (s), for the parameters whose
        model is a random walk (:attr:`CalibrationConfig.models`; a connection's parameter is
        the walk's at its mid-time, ``stamps_s + dt_s / 2``). None: each source's motions
        follow each other in connection order (the stamp of one is the sum of the durations
        before it).

    Returns
    -------
    The adjustment with the motions corrected by the estimated parameters (and, with
    :attr:`CalibrationConfig.noise`, the calibrated sources weighted by their re-estimated
    noise), and the :class:`CalibrationReport` (every candidate: value and sigma, or why it
    was fixed to 0; the noise factors).
    """
    cal = calibration or CalibrationConfig()
    arrays = network.arrays()
    m = len(arrays)
    if len(sources) != m:
        raise InputError(f'solve_with_calibration: {len(sources)} sources for {m} connections')
    dt = np.asarray(dt_s, dtype=float).reshape(-1)
    if dt.size != m:
        raise InputError(f'solve_with_calibration: {dt.size} durations for {m} connections')
    dt = np.where(np.isfinite(dt) & (dt > 0), dt, 0.0)
    if groups is not None and len(groups) != m:
        raise InputError(f'solve_with_calibration: {len(groups)} groups for {m} connections')
    mid_s = _mid_times(sources, dt, stamps_s) if cal.models else None
    fix_base = ([] if fixes is None else
                fix_priors(fixes, np.asarray(T_init, dtype=float), network.node_ids))
    cameras = camera_sources(['' if g is None else str(g) for g in
                              (sources if groups is None else groups)], cal.cameras)
    cand = _candidates(sources, cal.parameters, fixes.sources if fixes is not None else (),
                       cal.fix_parameters, cal.fix_reference, cameras, cal.camera_parameters)
    res, net, used, report = _select(network, np.asarray(T_init, dtype=float), cand, dt,
                                     config, fixed, priors, cal, fixes=fixes,
                                     fix_base=fix_base, mid_s=mid_s)
    order = list(range(len(cand.params)))   # the candidates' places in the report
    dropped: list[tuple[int, AdditionalParameter]] = []
    gone = [j for fam in ('camera', 'fix')
            if not any(p.estimated for p, q in zip(report.parameters, cand.params)
                       if q.family == fam)
            for j, q in enumerate(cand.params) if q.family == fam]
    if gone:
        # no camera (or no fix) parameter estimated: the adjustment without them, bit for
        # bit (the drops re-solved from warm starts), with their reasons kept
        dropped = [(j, report.parameters[j]) for j in gone]
        order = [j for j in order if j not in gone]
        cand = _Candidates([cand.sources[j] for j in order], [cand.kinds[j] for j in order],
                           [cand.masks[j] for j in order], [cand.params[j] for j in order])
        solves = report.solves
        res, net, used, report = _select(network, np.asarray(T_init, dtype=float), cand, dt,
                                         config, fixed, priors, cal, fixes=fixes,
                                         fix_base=fix_base, mid_s=mid_s)
        report.solves += solves
    parts = _noise_parts(cand, report, arrays.cov)
    if not (cal.noise and parts):
        _restore(report, order, dropped)
        return res, report
    # the noise of the calibrated sources (module doc)
    solves = report.solves
    factors = np.ones(len(parts))
    noise = _noise_factors(net, res, used, parts, factors, cal)
    for f in noise:
        _test_stated(f, cal)
    stated = noise
    estimated = np.array([f.applied for f in noise])
    held = ~estimated   # parts whose factor no longer moves
    last = factors.copy()   # the last factor of each part at which it was determined
    iterations = 1
    for _ in range(int(cal.noise_iterations)):
        if held.all():
            break
        target = np.array([f.estimate for f in noise])
        step = np.clip(target / factors, 1.0 / cal.noise_max_step, cal.noise_max_step)
        new = np.where(held, factors, factors * step)
        if np.all(np.abs(new / factors - 1.0) < cal.noise_tolerance):
            break
        last, factors = factors, new
        res, net, used, report = _select(_scaled(network, parts, factors), res.T_world_node,
                                         cand, dt, config, fixed, priors, cal, report, fixes,
                                         fix_base, mid_s)
        solves += report.solves
        iterations += 1
        noise = _noise_factors(net, res, used, parts, factors, cal)
        lost = ~held & (np.array([f.redundancy for f in noise]) < cal.noise_min_redundancy)
        if lost.any():
            # re-weighting took a part's redundancy below the minimum: it keeps the factor at
            # which it was last determined, and the others go on from there
            held |= lost
            factors = np.where(lost, last, factors)
            res, net, used, report = _select(_scaled(network, parts, factors),
                                             res.T_world_node, cand, dt, config, fixed,
                                             priors, cal, report, fixes, fix_base, mid_s)
            solves += report.solves
            iterations += 1
            noise = _noise_factors(net, res, used, parts, factors, cal)
    for f, f0, h in zip(noise, stated, held):
        f.stated_ratio, f.quantiles, f.applied = f0.stated_ratio, f0.quantiles, f0.applied
        f.held = bool(h and f0.applied)
    report.noise = noise
    report.noise_iterations = iterations
    report.solves = solves
    _restore(report, order, dropped)
    return res, report


def _mid_times(sources: Sequence[str | None], dt: FloatArray, stamps_s: FloatArray | None
               ) -> FloatArray:
    """(m,) each connection's mid-time (s): ``stamps_s + dt / 2``, or without stamps each
    source's durations summed in connection order (:func:`solve_with_calibration`)."""
    if stamps_s is not None:
        t = np.asarray(stamps_s, dtype=float).reshape(-1)
        if t.size != dt.size or not np.all(np.isfinite(t)):
            raise InputError(f'solve_with_calibration: stamps_s must be {dt.size} finite '
                             f'stamps')
        return t + 0.5 * dt
    src = np.array(['' if s is None else str(s) for s in sources], dtype=object)
    t = np.zeros(dt.size)
    for s in set(src.tolist()):
        mask = src == s
        t[mask] = np.cumsum(dt[mask]) - 0.5 * dt[mask]
    return t


def _restore(report: CalibrationReport, order: list[int],
             dropped: list[tuple[int, AdditionalParameter]]) -> None:
    """Put the candidates left out of the last selection (``dropped``: their places and
    reports) back among ``report``'s parameters (at the places ``order``), in the
    candidates' order."""
    if not dropped:
        return
    at = dict(zip(order, report.parameters))
    at.update(dropped)
    report.parameters = [at[j] for j in sorted(at)]


def _test_stated(f: NoiseFactor, cal: CalibrationConfig) -> None:
    """A part's redundancy and the test of its stated covariance, at the stated weights
    (module doc): ``applied`` (its factor is estimated) where the part has at least
    :attr:`CalibrationConfig.noise_min_redundancy`; the range of ``chi2(r) / r`` at
    ``noise_alpha``, which ``v' P v / r`` falls in if the stated covariance is right, is
    reported with it (the estimate does not depend on it)."""
    if f.redundancy < max(cal.noise_min_redundancy, 1e-9):
        return
    r = f.redundancy
    lo = float(stats.chi2.ppf(cal.noise_alpha / 2.0, r)) / r
    hi = float(stats.chi2.ppf(1.0 - cal.noise_alpha / 2.0, r)) / r
    f.quantiles = (lo, hi)
    f.applied = True


@dataclass
class _NoisePart:
    """A block of a calibrated source's covariance that gets its own noise factor."""

    source: str
    part: str
    mask: np.ndarray  # (m,) the source's connections
    dims: np.ndarray  # the rows/columns of the covariance it scales


def _noise_parts(cand: _Candidates, report: CalibrationReport, cov: FloatArray
                 ) -> list[_NoisePart]:
    """Per odometry source or camera with an estimated parameter (a fix source keeps its
    stated covariance), on the connections of its estimated parameters (a camera that is also
    an odometry source: its consecutive and cross-track ones): a translation and a rotation
    part where its stated covariances do not correlate the two, else one part for the whole
    covariance."""
    out: list[_NoisePart] = []
    masks: dict[str, np.ndarray] = {}
    for j, (par, src) in enumerate(zip(report.parameters, cand.sources)):
        if par.estimated and not cand.on_fixes(j):
            masks[src] = masks[src] | cand.masks[j] if src in masks else cand.masks[j]
    for src, mask in masks.items():
        if np.any(cov[mask][:, :3, 3:] != 0.0):
            out.append(_NoisePart(src, 'motion', mask, np.arange(6)))
        else:
            out.append(_NoisePart(src, 'translation', mask, np.arange(3)))
            out.append(_NoisePart(src, 'rotation', mask, np.arange(3, 6)))
    return out


def _scaled(network: ConnectionNetwork, parts: list[_NoisePart], factors: FloatArray
            ) -> ConnectionNetwork:
    """``network`` with each part's covariance block scaled by its factor (``D S D``, ``D``
    the square roots of the factors on the part's rows)."""
    arrays = network.arrays()
    d = np.ones((len(arrays), 6))
    for p, f in zip(parts, factors):
        d[np.ix_(np.nonzero(p.mask)[0], p.dims)] = np.sqrt(f)
    cov = arrays.cov * d[:, :, None] * d[:, None, :]
    return ConnectionNetwork.from_arrays(network.node_ids, network.track_ids, arrays.src,
                                         arrays.dst, arrays.z, cov)


def _noise_factors(net: ConnectionNetwork, res: SolveResult, priors: Sequence[GaussianPrior],
                   parts: list[_NoisePart], factors: FloatArray, cal: CalibrationConfig
                   ) -> list[NoiseFactor]:
    """Förstner's estimate of each part's variance factor at the adjustment ``res`` of
    ``net`` (whose covariances carry ``factors``): ``s <- s v' P v / r`` over the part's
    block (its covariance is block-diagonal against the rest, so ``v' P v`` splits), ``r``
    the sum of the part's redundancy numbers (the diagonal of ``(Q_vv P)_ii``)."""
    from ga_ros.core.quality import quality_control

    red_comp = quality_control(net, res, priors).redundancy_components
    cov = net.arrays().cov
    v = res.residuals
    out = []
    for p, s in zip(parts, factors):
        idx = np.nonzero(p.mask)[0]
        blk = cov[idx][:, p.dims][:, :, p.dims]
        vb = v[idx][:, p.dims]
        cost = float(np.einsum('mi,mi->', vb, np.linalg.solve(blk, vb[:, :, None])[:, :, 0]))
        r = float(red_comp[idx][:, p.dims].sum())
        est = float(damped_factor(s * cost, r, cal.noise_prior_dof, cal.noise_factor_bounds))
        out.append(NoiseFactor(p.source, p.part, float(s), est, float(factor_sigma(est, r)),
                               r, stated_ratio=s * cost / r if r > 0 else float('nan')))
    return out


def _select(network: ConnectionNetwork, T_init: FloatArray, cand: _Candidates, dt: FloatArray,
            config: SolverConfig | None, fixed: Sequence[int] | None,
            priors: Sequence[GaussianPrior], cal: CalibrationConfig,
            start: CalibrationReport | None = None, fixes: FixObservations | None = None,
            fix_base: Sequence[GaussianPrior] = (), mid_s: FloatArray | None = None
            ) -> tuple[SolveResult, ConnectionNetwork, list[GaussianPrior], CalibrationReport]:
    """Which parameters are determined and significant, and their estimates (module doc,
    steps 1-4), with the covariances of ``network``: the adjustment, the corrected network
    and the priors (the corrected fixes', then ``priors``) it solved, and the report.
    ``start``: the parameters' values to start from (those of an adjustment with other
    weights, whose poses ``T_init`` are; else 0). ``fix_base``: the fixes' priors as
    measured (linearised at the caller's initial poses), used while no fix parameter is
    non-zero. ``mid_s`` (m,): each connection's mid-time (s), for the parameters whose model
    is a random walk: estimated as one where the selection kept them (:func:`_walk`)."""
    arrays = network.arrays()
    m = len(arrays)
    n_c = len(cand.kinds)
    on_fixes = np.array([cand.on_fixes(j) for j in range(n_c)], dtype=bool)
    report = CalibrationReport(
        [AdditionalParameter(s, k, par.unit)
         for s, k, par in zip(cand.sources, cand.kinds, cand.params)], alpha=cal.alpha)
    values = np.zeros(n_c)
    if start is not None:
        values[:] = [p.value for p in start.parameters]
    fs0 = _FixState.at(fixes, network, T_init, cand)
    active = []
    observed = []   # the candidates with something they act on
    for j in range(n_c):
        mask = cand.masks[j]
        acts = (cand.params[j].acts_on(fixes.known[mask], fs0.velocity[mask]) if on_fixes[j]
                else cand.params[j].acts_on(arrays.z[mask], dt[mask]))
        if np.any(acts > 0):
            active.append(j)
            observed.append(j)
        else:
            values[j] = 0.0
            report.parameters[j].reason = cand.params[j].unobserved
    solved: list = [network, list(priors)]
    walks: dict[int, FloatArray] = {}  # a random walk's value on each of its connections

    def adjust(T0: FloatArray) -> tuple[SolveResult, FloatArray]:
        Tcorr = _per_connection(cand, values, m, walks).apply(arrays.z, dt)
        net = (network if not (values[~on_fixes].any() or walks)
               else ConnectionNetwork.from_arrays(
            network.node_ids, network.track_ids, arrays.src, arrays.dst,
            se3.to_translation_rotvec(Tcorr.T), arrays.cov))
        used = list(priors)
        if fixes is not None and (values[on_fixes].any()
                                  or any(cand.on_fixes(j) for j in walks)):
            shift = _fix_shift(_FixState.at(fixes, network, T0, cand).E, cand, values, walks)
            used = fix_priors(fixes, T0, network.node_ids, shift) + used
        elif fixes is not None:
            used = list(fix_base) + used
        solved[:] = [net, used]
        report.solves += 1
        return solve(net, T0, config, fixed=fixed, priors=used), Tcorr

    res, Tcorr = adjust(T_init)

    def drop(j: int, reason: str) -> None:
        nonlocal stalled
        stalled = False
        active.remove(j)
        values[j] = 0.0
        report.parameters[j].reason = reason

    steps, stalled = 0, False
    while active:
        b = _bordered(network, res, Tcorr, cand, active, fixes, values)
        ratio = np.diag(b.H) / np.maximum(b.Ncc_diag, np.finfo(float).tiny)
        for a, j in enumerate(active):
            report.parameters[j].information_ratio = float(ratio[a])
        worst = int(np.argmin(ratio))
        if ratio[worst] < cal.min_information_ratio:
            had = values.any()
            drop(active[worst], f'not determined by the network: {ratio[worst]:.1e} of its '
                 f'information is left after the poses ({cand.params[active[worst]].unseen})')
            if had:
                res, Tcorr = adjust(res.T_world_node)
            steps = 0
            continue
        # a parameter that is a first-order correction: known to less than its largest
        # sigma even with the others known (1 / sqrt(H_jj)), it is not determined
        bound = np.array([cand.params[j].max_sigma for j in active])
        loose = np.nonzero(np.isfinite(bound)
                           & (np.diag(b.H) * np.where(np.isfinite(bound), bound, 0.0) ** 2
                              < 1.0))[0]
        if loose.size:
            a = int(loose[0])
            j = active[a]
            had = values.any()
            drop(j, f'not determined by the network: sigma '
                 f'{1.0 / np.sqrt(max(b.H[a, a], np.finfo(float).tiny)):.2g} '
                 f'{cand.params[j].unit} > {bound[a]:g} ({cand.params[j].unseen})')
            if had:
                res, Tcorr = adjust(res.T_world_node)
            steps = 0
            continue
        d = np.sqrt(np.maximum(np.diag(b.H), np.finfo(float).tiny))
        Hs = b.H / np.outer(d, d)
        cond = np.linalg.cond(Hs)
        # a reduced normal matrix that rounding left indefinite determines nothing along its
        # non-positive direction (its inverse would give a negative variance)
        definite = bool(np.linalg.eigvalsh(Hs)[0] > 0.0)
        if cond > cal.max_condition or not definite:
            # the least informed of the parameters in the near-dependency (the eigenvector
            # of the smallest eigenvalue), so that two offsets that only their difference
            # determines do not take an independent third one with them
            u = np.abs(np.linalg.eigh(Hs)[1][:, 0])
            part = u >= _DEPENDENCY_SHARE * u.max()
            worst = int(np.argmin(np.where(part, ratio, np.inf)))
            j = active[worst]
            others = ', '.join(f'{cand.sources[k]} {cand.kinds[k]}'
                               for a, k in enumerate(active) if k != j and part[a])
            drop(j, f'not separable from {others} (condition number {cond:.1e})'
                 if cond > cal.max_condition
                 else f'not determined: its reduced normal matrix with {others or "itself"} '
                      f'is not positive definite')
            res, Tcorr = adjust(res.T_world_node)
            steps = 0
            continue
        Q = np.linalg.inv(b.H)
        dc = -Q @ b.g
        sig = np.sqrt(np.diag(Q))
        converged = stalled or bool(np.all(np.abs(dc) <= cal.tolerance * sig))
        if not converged and steps < cal.max_iterations:
            old, kept = values[active].copy(), (res, Tcorr, list(solved))
            for _ in range(_STEP_HALVINGS + 1):
                values[active] = old + dc
                res, Tcorr = adjust(kept[0].T_world_node)
                if res.cost <= kept[0].cost * (1.0 + 1e-9):
                    break
                dc = 0.5 * dc  # a step that raised the cost: backtrack
            else:
                # no step along dc lowers the cost: the parameters stay where they are
                values[active] = old
                res, Tcorr, solved[:] = kept
                stalled = True
            steps += 1
            report.iterations += 1
            continue
        # the joint adjustment's redundancy and variance factor (the solver's count the
        # poses only)
        dof = res.redundancy - len(active)
        if dof <= 0:
            j = active[worst]
            drop(j, f'no redundancy left to test it (redundancy {res.redundancy})')
            res, Tcorr = adjust(res.T_world_node)
            steps = 0
            continue
        s0 = np.sqrt(max(res.sigma0_sq * res.redundancy / dof, np.finfo(float).tiny))
        quantile = float(stats.t.ppf(1.0 - cal.alpha / 2.0, dof))
        t = np.abs(values[active]) / (s0 * sig)
        for a, j in enumerate(active):
            par = report.parameters[j]
            par.sigma, par.test, par.quantile = float(sig[a]), float(t[a]), quantile
            par.tested_value = float(values[j])
        weakest = int(np.argmin(t))
        if t[weakest] < quantile:
            drop(active[weakest], f'not significant: |t| {t[weakest]:.2f} < {quantile:.2f} '
                 f'(alpha {cal.alpha:g})')
            res, Tcorr = adjust(res.T_world_node)
            steps = 0
            continue
        break
    bases = {} if mid_s is None else {
        j: cal.model(cand.kinds[j]).basis(mid_s[cand.masks[j]])
        for j in active if cand.params[j].family == 'odometry'
        and not cal.model(cand.kinds[j]).about_constant}
    bases = {j: b for j, b in bases.items() if b is not None}
    if bases:
        # the parameters whose model is a random walk, where the selection kept them
        res, Tcorr, estimates = _walk(adjust, res, Tcorr, solved, network, cand, active,
                                      bases, walks, values, dt, cal, report, fixes)
        for j, w in estimates.items():
            report.parameters[j].walk = w
    about = {j: cal.model(cand.kinds[j]) for j in observed if fixes is not None
             and cand.on_fixes(j) and cal.model(cand.kinds[j]).about_constant}
    kept: dict[int, WalkEstimate] = {}
    if about:
        # the fix parameters whose model is a walk about the constant (module doc, *A
        # wandering fix offset*): their deviations, kept where significant
        res, Tcorr, kept = _bias_walks(adjust, res, Tcorr, solved, network, cand, active,
                                       about, walks, values, cal, report, fixes)
    for j in range(n_c):
        par = report.parameters[j]
        par.estimated = j in active or j in kept
        par.value = float(values[j])
        if j in kept:
            par.walk = kept[j]
        if par.estimated:
            par.reason = ''
    report.sigma0_sq = float(res.sigma0_sq)
    return res, solved[0], solved[1], report


def _walk_steps(bordered, adjust, put, res: SolveResult, Tcorr: CorrectedMotions,
                solved: list, c: FloatArray, H_rw: FloatArray, cal: CalibrationConfig,
                report: CalibrationReport
                ) -> tuple[SolveResult, CorrectedMotions, FloatArray, FloatArray, _Bordered]:
    """Gauss-Newton on the bordered parameters ``c`` with the walks' pseudo-observations
    (normal matrix ``H_rw``, their cost ``c' H_rw c``): ``bordered(res, Tcorr)`` the parameters'
    reduced system at the adjustment ``res``, ``put(c)`` installs ``c`` for ``adjust`` (which
    re-solves the poses from given ones); a step that raises the joint cost is halved, one
    that no halving makes lower leaves ``c`` where it was. Stops when every step is within
    ``cal.tolerance`` of its sigma or after ``cal.max_iterations``. Returns the adjustment, its
    corrected motions, ``c``, the inverse ``Q`` of the last joint normal matrix and the last
    reduced system ``bordered`` gave."""
    Q = b = None
    for _ in range(int(cal.max_iterations) + 1):
        b = bordered(res, Tcorr)
        Q = np.linalg.inv(b.H + H_rw)
        dc = -Q @ (b.g + H_rw @ c)
        if np.all(np.abs(dc) <= cal.tolerance * np.sqrt(np.diag(Q))):
            break
        old, kept = c.copy(), (res, Tcorr, list(solved))
        cost0 = kept[0].cost + float(old @ H_rw @ old)
        for _ in range(_STEP_HALVINGS + 1):
            c = old + dc
            put(c)
            res, Tcorr = adjust(kept[0].T_world_node)
            if res.cost + float(c @ H_rw @ c) <= cost0 * (1.0 + 1e-9):
                break
            dc = 0.5 * dc
        else:  # no step along dc lowers the cost: the walks stay where they are
            c = old
            put(c)
            res, Tcorr, solved[:] = kept
            break
        report.iterations += 1
    return res, Tcorr, c, Q, b


def _walk(adjust, res: SolveResult, Tcorr: CorrectedMotions, solved: list,
          network: ConnectionNetwork, cand: _Candidates, active: list[int],
          bases: dict[int, WalkBasis], walks: dict[int, FloatArray], values: FloatArray,
          dt: FloatArray, cal: CalibrationConfig, report: CalibrationReport,
          fixes: FixObservations | None
          ) -> tuple[SolveResult, CorrectedMotions, dict[int, WalkEstimate]]:
    """The selected parameters ``active`` with those in ``bases`` as random walks (module
    doc, *A random walk*): Gauss-Newton on the knots (and the constants) bordered onto the
    poses, the pseudo-observations' normal matrix added to the parameters' reduced one, from
    the constants' estimates (``values``); a step that raises the joint cost (the
    adjustment's ``v' P v`` plus the pseudo-observations') is halved as in the selection.
    ``adjust`` re-solves the poses with ``walks`` (filled here: each walk's value on its
    connections) and ``values`` (the constants; a walk's entry becomes its mean). Returns
    the adjustment, its corrected motions and each walk's estimate."""
    cols: list[int] = []
    weights: list[FloatArray | None] = []
    at: dict[int, slice] = {}
    for j in active:
        b = bases.get(j)
        k = 1 if b is None else b.size
        at[j] = slice(len(cols), len(cols) + k)
        cols += [j] * k
        weights += [None] if b is None else [b.column(i) for i in range(k)]
    H_rw = np.zeros((len(cols), len(cols)))
    for j, b in bases.items():
        H_rw[at[j], at[j]] = b.normal()
    c = np.concatenate([np.full(at[j].stop - at[j].start, values[j]) for j in active])

    def put(c: FloatArray) -> None:
        for j in active:
            if j in bases:
                walks[j] = bases[j].values(c[at[j]])
                w = dt[cand.masks[j]]
                values[j] = float(np.average(walks[j], weights=w if w.sum() > 0 else None))
            else:
                values[j] = c[at[j]][0]

    put(c)
    res, Tcorr = adjust(res.T_world_node)
    res, Tcorr, c, Q, _ = _walk_steps(
        lambda res, Tcorr: _bordered(network, res, Tcorr, cand, cols, fixes, values, weights),
        adjust, put, res, Tcorr, solved, c, H_rw, cal, report)
    out = {}
    for j, b in bases.items():
        cj, Qj, Hj = c[at[j]], Q[at[j], at[j]], H_rw[at[j], at[j]]
        cost = float(cj @ Hj @ cj)
        r = float(b.size - 1 - np.trace(Hj @ Qj))
        out[j] = WalkEstimate([float(x) for x in b.knots_s], [float(x) for x in cj],
                              [float(x) for x in np.sqrt(np.diag(Qj))],
                              float(cal.model(cand.kinds[j]).segment_s), b.sigma_per_sqrt_s,
                              cost, r, cost / r if r > 0 else float('nan'))
    return res, Tcorr, out


@dataclass
class _Deviations:
    """One fix parameter's random walk about its constant (:func:`_bias_walks`): the knots'
    basis, the hat matrix of its fixes ``(k_j, K)``, the zero-mean basis ``B`` (K, K-1) of the
    deviations (``w' B = 0``, ``w`` the hat matrix's column sums: their mean over the fixes is
    0), and the pseudo-observations' normal matrix of the deviations at ``q = 1``."""

    basis: WalkBasis
    hat: FloatArray
    B: FloatArray
    normal_q1: FloatArray
    q: float

    @staticmethod
    def of(model: BiasWalk, t_s: FloatArray) -> _Deviations:
        b = model.basis(t_s)
        K = b.size
        hat = np.zeros((b.left.size, K))
        i = np.arange(b.left.size)
        hat[i, b.left] = 1.0 - b.frac
        hat[i, b.left + 1] += b.frac
        w = hat.sum(axis=0)
        B = np.linalg.svd(w[None, :])[2][1:].T   # (K, K-1) orthonormal, w' B = 0
        normal_q1 = B.T @ b.normal() @ B * b.sigma_per_sqrt_s ** 2
        return _Deviations(b, hat, B, normal_q1, b.sigma_per_sqrt_s)

    @property
    def size(self) -> int:
        return self.B.shape[1]

    def normal(self) -> FloatArray:
        return self.normal_q1 / self.q ** 2


def _bias_walks(adjust, res: SolveResult, Tcorr: CorrectedMotions, solved: list,
                network: ConnectionNetwork, cand: _Candidates, active: list[int],
                about: dict[int, BiasWalk], walks: dict[int, FloatArray], values: FloatArray,
                cal: CalibrationConfig, report: CalibrationReport, fixes: FixObservations
                ) -> tuple[SolveResult, CorrectedMotions, dict[int, WalkEstimate]]:
    """The fix parameters ``about`` (observed, their model a
    :class:`~ga_ros.core.calibration.models.BiasWalk`) as their constant (``values[j]``:
    the selection's estimate, 0 where it was not kept) plus a zero-mean random walk of
    deviations (module doc, *A wandering fix offset*): Gauss-Newton on the deviations' knots
    and the kept constants (an odometry random walk stays at its estimate), the poses
    re-solved at each step as in :func:`_walk`; then each walk's F test
    ``d' S d / ((K-1) sigma0^2)`` against ``F(K-1, r - p)`` at ``alpha`` (``S`` the
    deviations' information from the data, the other unknowns eliminated; ``sigma0^2`` and
    ``r - p`` the selection's). The least significant walk that fails goes and the rest are
    estimated again; with none left, the adjustment, ``values`` and ``walks`` are those of
    the selection, untouched. Returns the adjustment, its corrected motions and each kept
    walk's estimate."""
    start = (res, Tcorr, list(solved), values.copy(), dict(walks))
    dof = res.redundancy - len(active)
    s0_sq = res.sigma0_sq * res.redundancy / dof if dof > 0 else float('nan')
    times = np.array([t.fix.stamp_ns for t in fixes.terms], dtype=float) * 1e-9
    devs = {j: _Deviations.of(m, times[cand.masks[j]]) for j, m in about.items()}
    consts = [j for j in active if j not in walks]
    notes: dict[int, str] = {}
    while devs and dof > 0:
        res, Tcorr, solved[:] = start[0], start[1], list(start[2])
        values[:] = start[3]
        walks.clear()
        walks.update(start[4])
        cols: list[int] = list(consts)
        weights: list[FloatArray | None] = [None] * len(consts)
        at: dict[int, slice] = {}
        for j, d in devs.items():
            at[j] = slice(len(cols), len(cols) + d.size)
            cols += [j] * d.size
            weights += [d.hat @ d.B[:, i] for i in range(d.size)]
        c = np.concatenate([values[consts], np.zeros(len(cols) - len(consts))])

        def put(c: FloatArray) -> None:
            values[consts] = c[:len(consts)]
            for j, d in devs.items():
                walks[j] = values[j] + d.hat @ (d.B @ c[at[j]])

        def prior() -> FloatArray:
            H_rw = np.zeros((len(cols), len(cols)))
            for j, d in devs.items():
                H_rw[at[j], at[j]] = d.normal()
            return H_rw

        put(c)
        res, Tcorr = adjust(res.T_world_node)
        reestimates = max(int(m.sigma_iterations) if m.estimate_sigma else 0
                          for j, m in about.items() if j in devs)
        for sweep in range(reestimates + 1):
            H_rw = prior()
            res, Tcorr, c, Q, b = _walk_steps(
                lambda res, Tcorr: _bordered(network, res, Tcorr, cand, cols, fixes, values,
                                             weights, walks),
                adjust, put, res, Tcorr, solved, c, H_rw, cal, report)
            if sweep == reestimates:
                break
            # the process noise from the data (Förstner: q^2 <- q^2 v'Pv / r of the
            # pseudo-observations), where the model asks for it
            moved = False
            for j, d in devs.items():
                if not about[j].estimate_sigma:
                    continue
                Hj = H_rw[at[j], at[j]]
                dj = c[at[j]]
                r = float(d.size - np.trace(Hj @ Q[at[j], at[j]]))
                if not r > 0:
                    continue
                ratio = float(dj @ Hj @ dj) / r
                q = d.q * np.sqrt(min(max(ratio, 1e-4), 1e4))
                moved |= abs(q / d.q - 1.0) > 0.05   # the variance moved by more than 10 %
                d.q = q
            if not moved:
                break
        # each walk's test, the other unknowns eliminated (their pseudo-observations kept
        # so that they are determined)
        tests: dict[int, tuple[float, float]] = {}
        for j in devs:
            mine = np.zeros(len(cols), bool)
            mine[at[j]] = True
            M = b.H + np.where(mine[:, None] | mine[None, :], 0.0, H_rw)
            S = b.H[np.ix_(mine, mine)]
            if (~mine).any():
                S = S - M[np.ix_(mine, ~mine)] @ np.linalg.solve(M[np.ix_(~mine, ~mine)],
                                                                 M[np.ix_(~mine, mine)])
            # the deviations the data alone give (one Gauss-Newton step from the estimate
            # without the pseudo-observations): d_ls = d + S^+ P d, and the Wald test of
            # d_ls = 0 with their information S
            dj = c[at[j]]
            lam, U = np.linalg.eigh(0.5 * (S + S.T))
            keep = lam > 1e-10 * max(float(lam.max()), np.finfo(float).tiny)
            rank = int(keep.sum())
            u = U[:, keep].T @ ((S + H_rw[at[j], at[j]]) @ dj)   # S d_ls in S's eigenbasis
            f = float(u @ (u / lam[keep])) / (max(rank, 1) * s0_sq)
            tests[j] = (f, float(stats.f.ppf(1.0 - cal.alpha, max(rank, 1), dof)))
        weakest = min(tests, key=lambda j: tests[j][0] / tests[j][1])
        f, quantile = tests[weakest]
        if f >= quantile:
            for j, note in notes.items():
                report.parameters[j].walk_note = note
            out = {}
            for j, d in devs.items():
                sl = at[j]
                # the knots: the constant (where kept) plus B d
                Mk = np.zeros((d.basis.size, len(cols)))
                Mk[:, sl] = d.B
                if j in consts:
                    Mk[:, consts.index(j)] = 1.0
                Hj = H_rw[sl, sl]
                dj = c[sl]
                r = float(d.size - np.trace(Hj @ Q[sl, sl]))
                cost = float(dj @ Hj @ dj)
                out[j] = WalkEstimate(
                    [float(x) for x in d.basis.knots_s],
                    [float(x) for x in values[j] + d.B @ dj],
                    [float(x) for x in np.sqrt(np.diag(Mk @ Q @ Mk.T))],
                    float(about[j].segment_s), float(d.q), cost, r,
                    cost / r if r > 0 else float('nan'), tests[j][0], tests[j][1])
            return res, Tcorr, out
        notes[weakest] = f'random walk not significant: F {f:.2f} < {quantile:.2f}'
        del devs[weakest]
    # no walk kept: the selection's adjustment, untouched
    res, Tcorr, solved[:] = start[0], start[1], list(start[2])
    values[:] = start[3]
    walks.clear()
    walks.update(start[4])
    for j in about:
        report.parameters[j].walk_note = notes.get(j, 'random walk not tested: no redundancy')
    return res, Tcorr, {}
