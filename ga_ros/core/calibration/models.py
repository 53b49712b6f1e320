"""How a source's additional parameter varies over the survey: a constant
(:class:`ConstantLevel`, the default), a random walk (:class:`RandomWalk`, an odometry
parameter) or a fix source's constant with a random walk about it (:class:`BiasWalk`, a fix
parameter: a GNSS receiver's offset that wanders with multipath and the atmosphere).

A random walk ``c(t)`` with process noise ``q`` (the parameter's unit per ``sqrt(s)``) is
represented by its values ``c_k`` at knots ``t_k`` spaced ``segment_s`` apart over the span of
the source's motions, linearly interpolated between them (the Brownian bridge's mean given the
knots): the motion whose mid-time is ``t`` in ``[t_k, t_k+1]`` uses

    c(t) = (1 - f) c_k + f c_k+1,    f = (t - t_k) / (t_k+1 - t_k).

Consecutive knots are tied by the random walk's pseudo-observations (Madjidi & Negahdaripour's
adjustment, a weighted parameter per difference)

    c_k+1 - c_k = 0 + w_k,    w_k ~ N(0, q^2 (t_k+1 - t_k)),

exact for a Wiener process sampled at the knots. A parameter's unknowns are then the ``K``
knot values instead of one constant (:mod:`.batch` borders them onto the pose system like the
constant: ``K`` columns of ``N_xc``, each the constant's column weighted by the knot's hat
function). ``q -> 0`` ties the knots into the constant; ``q -> inf`` leaves each segment to the
fixes alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError


@dataclass(frozen=True)
class WalkBasis:
    """The knots of one source's random walk and the interpolation of its motions.

    Attributes
    ----------
    knots_s : (K,) the knots' times (s, the stamps' clock), increasing, ``K >= 2``.
    left : (m,) each motion's knot interval ``k`` (its mid-time in ``[t_k, t_k+1]``).
    frac : (m,) its position ``f`` in that interval (0 at ``t_k``, 1 at ``t_k+1``).
    sigma_per_sqrt_s : the process noise ``q`` (the parameter's unit per ``sqrt(s)``).
    """

    knots_s: FloatArray
    left: np.ndarray
    frac: FloatArray
    sigma_per_sqrt_s: float

    @property
    def size(self) -> int:
        return int(self.knots_s.size)

    def values(self, c: FloatArray) -> FloatArray:
        """(m,) the parameter of each motion for knot values ``c`` (K,)."""
        c = np.asarray(c, dtype=float)
        return (1.0 - self.frac) * c[self.left] + self.frac * c[self.left + 1]

    def column(self, k: int) -> FloatArray:
        """(m,) the weight of knot ``k`` in each motion's parameter (its hat function)."""
        w = np.zeros(self.left.size)
        w[self.left == k] = 1.0 - self.frac[self.left == k]
        w[self.left == k - 1] = self.frac[self.left == k - 1]
        return w

    def difference_weights(self) -> FloatArray:
        """(K-1,) the weights ``1 / (q^2 (t_k+1 - t_k))`` of the pseudo-observations."""
        return 1.0 / (self.sigma_per_sqrt_s ** 2 * np.diff(self.knots_s))

    def normal(self) -> FloatArray:
        """(K, K) ``D' W D`` of the pseudo-observations ``D c = 0`` (``D`` the differences of
        consecutive knots): their cost at ``c`` is ``c' (D' W D) c``, their gradient
        ``(D' W D) c``."""
        K = self.size
        D = np.diff(np.eye(K), axis=0)
        return D.T @ (self.difference_weights()[:, None] * D)


@dataclass(frozen=True)
class ParameterModel:
    """How the additional parameter ``parameter`` varies over the survey (module doc).

    ``family``: the parameters it models (``'odometry'``: ``'scale'``, ``'yaw_rate'``;
    ``'fix'``: a fix source's ``'offset_x'``, ``'offset_y'``, ``'offset_z'``,
    ``'time_offset'``). ``about_constant``: the walk is estimated as deviations about the
    parameter's constant, with their own test (:class:`BiasWalk`), rather than in place of a
    constant that passed its test (:class:`RandomWalk`)."""

    parameter: str
    name: ClassVar[str] = ''
    family: ClassVar[str] = 'odometry'
    about_constant: ClassVar[bool] = False

    def basis(self, t_s: FloatArray) -> WalkBasis | None:
        """The knots and interpolation of motions with mid-times ``t_s`` (m,) s; None for a
        single constant."""
        raise NotImplementedError


@dataclass(frozen=True)
class ConstantLevel(ParameterModel):
    """One constant per source over the survey (the default)."""

    name: ClassVar[str] = 'constant'

    def basis(self, t_s: FloatArray) -> None:
        return None


@dataclass(frozen=True)
class RandomWalk(ParameterModel):
    """A random walk (module doc).

    Attributes
    ----------
    parameter : the parameter (``'scale'``, ``'yaw_rate'``).
    segment_s : the knots' spacing (s): the shortest time over which the parameter is seen
        to change. The knots span the source's motions' mid-times: the span divided into a
        whole number of intervals (rounded), the last one ending at the last motion
        (``0.5 - 1.5 segment_s`` long).
    sigma_per_sqrt_s : the process noise ``q`` (the parameter's unit per ``sqrt(s)``: a
        yaw rate in rad/s/sqrt(s)): after ``T`` seconds the parameter has moved by
        ``q sqrt(T)`` (one sigma). The default, 2e-5 rad/s/sqrt(s) for the yaw rate (0.4 mrad/s
        over 400 s), is the process noise the CMU Plaza run's odometry estimates for itself
        (docs/calibration.md, *A random walk*).
    """

    segment_s: float = 60.0
    sigma_per_sqrt_s: float = 2e-5
    name: ClassVar[str] = 'random_walk'

    def __post_init__(self) -> None:
        if not (np.isfinite(self.segment_s) and self.segment_s > 0):
            raise InputError(f'random walk of {self.parameter}: segment_s must be > 0, got '
                             f'{self.segment_s}')
        if not (np.isfinite(self.sigma_per_sqrt_s) and self.sigma_per_sqrt_s > 0):
            raise InputError(f'random walk of {self.parameter}: sigma_per_sqrt_s must be > 0, '
                             f'got {self.sigma_per_sqrt_s}')

    def basis(self, t_s: FloatArray) -> WalkBasis:
        t = np.asarray(t_s, dtype=float)
        t0, t1 = float(t.min()), float(t.max())
        n = max(int(np.floor((t1 - t0) / self.segment_s + 0.5)), 1)  # intervals
        knots = t0 + self.segment_s * np.arange(n + 1, dtype=float)
        if t1 > knots[-2]:
            knots[-1] = t1
        left = np.clip(np.searchsorted(knots, t, side='right') - 1, 0, n - 1)
        frac = np.clip((t - knots[left]) / (knots[left + 1] - knots[left]), 0.0, 1.0)
        return WalkBasis(knots, left, frac, float(self.sigma_per_sqrt_s))


@dataclass(frozen=True)
class BiasWalk(RandomWalk):
    """A fix source's parameter (an offset axis, m; or its time offset, s) as its constant
    plus a random walk of deviations about it (docs/calibration.md, *A wandering fix
    offset*): the knots of :class:`RandomWalk` constrained to the constant's mean over the
    source's fixes (``sum_i c(t_i) = 0`` for the deviations), so that with a single fix
    source, whose fixes define the frame and whose constant offset is therefore not
    determined, the walk's shape still is (the odometry sees it). The deviations are
    estimated after the constant's selection (:mod:`.batch`, steps 1-4) and kept only if
    they pass their own test (an F test of the ``K - 1`` deviations); otherwise the result is
    the one without the walk, bit for bit.

    Attributes
    ----------
    parameter : the fix parameter (``'offset_x'``, ``'offset_y'``, ``'offset_z'``,
        ``'time_offset'``).
    segment_s : the knots' spacing (s), as :class:`RandomWalk`'s.
    sigma_per_sqrt_s : the process noise ``q`` (m/sqrt(s) for an offset): after ``T`` s the
        offset has moved by ``q sqrt(T)`` (one sigma). The default, 0.05 m/sqrt(s), is 0.4 m
        in a minute, 1.2 m in ten (a code-phase receiver's multipath and atmosphere).
    estimate_sigma : estimate ``q`` from the data as well (Förstner's variance component of
        the walk's pseudo-observations: ``q^2 <- q^2 v'Pv / r``, from ``sigma_per_sqrt_s``,
        at most ``sigma_iterations`` times, until it moves by less than 10 %).
    sigma_iterations : the re-estimates of ``q`` at most.
    """

    segment_s: float = 60.0
    sigma_per_sqrt_s: float = 0.05
    estimate_sigma: bool = False
    sigma_iterations: int = 8
    name: ClassVar[str] = 'bias_walk'
    family: ClassVar[str] = 'fix'
    about_constant: ClassVar[bool] = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if int(self.sigma_iterations) < 1:
            raise InputError(f'bias walk of {self.parameter}: sigma_iterations must be >= 1')


#: The models, by name (``model: constant | random_walk | bias_walk``).
MODELS: dict[str, type[ParameterModel]] = {m.name: m for m in (ConstantLevel, RandomWalk,
                                                                BiasWalk)}


def parameter_model(parameter: str, model: str = 'constant', **settings: float
                    ) -> ParameterModel:
    """The model called ``model`` (:data:`MODELS`) of ``parameter`` with ``settings`` (a
    random walk's ``segment_s``, ``sigma_per_sqrt_s``): how a configuration names it."""
    try:
        cls = MODELS[model]
    except KeyError:
        raise InputError(f'unknown calibration model {model!r}; choose from '
                         f'{sorted(MODELS)}') from None
    try:
        return cls(parameter, **settings)
    except TypeError as exc:
        raise InputError(f'calibration model {model!r}: {exc}') from None
