"""The noisy aerial survey the benchmarks fly, and the command-line options that shape it.

The paper's aerial lawnmower survey (:func:`ga_ros.sim.aerial.aerial_scenario`) with Gaussian
noise on its true relative motions (:func:`ga_ros.sim.noise.perturb`, noise as a percentage of
each motion; see :class:`ga_ros.sim.noise.NoiseModel`). The benchmarks of ``ga_ros/bench`` build
it through :func:`noisy_survey` (or :func:`survey_noise` for another draw on the same survey),
so the same seed gives the same measurements in every benchmark.
"""

from __future__ import annotations

import argparse
from typing import NamedTuple

import numpy as np

from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, NoisyMotions, perturb
from ga_ros.sim.scenario import Scenario


class NoisySurvey(NamedTuple):
    """A simulated survey and one noise draw of its relative motions (unpacks as
    ``scenario, motions``).

    Attributes
    ----------
    scenario : the survey: true poses ``T_world_node`` (m), connections, tracks.
    motions : measured motions ``z`` (m, 6) ``[t, w]`` (m, rad) and their covariances ``cov``
        (m, 6, 6), ``[x y z rx ry rz]``, one per connection of ``scenario``.
    """

    scenario: Scenario
    motions: NoisyMotions


def survey_noise(scenario: Scenario, noise_pct: float,
                 rng: np.random.Generator | int) -> NoisyMotions:
    """One noise draw of the survey's true motions.

    Parameters
    ----------
    scenario : the survey.
    noise_pct : noise as a percentage of each true motion (``NoiseModel``; rotations scaled
        by the scene depth ``scenario.depth_m``).
    rng : the generator to draw from (advanced by the draw), or a seed for a new one.
    """
    if not isinstance(rng, np.random.Generator):
        rng = np.random.default_rng(rng)
    return perturb(scenario.true_motions(), NoiseModel(noise_pct, scenario.depth_m), rng)


def noisy_survey(n_tracks: int, noise_pct: float, rng: np.random.Generator | int,
                 positions_per_swath: int = 102) -> NoisySurvey:
    """The aerial survey of ``n_tracks`` double tracks and one noise draw of its motions.

    Parameters
    ----------
    n_tracks : double tracks (two swaths each).
    noise_pct : noise as a percentage of each true motion (see :func:`survey_noise`).
    rng : the generator to draw from (advanced by the draw), or a seed for a new one.
    positions_per_swath : poses per swath (102: the paper's survey).
    """
    sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=positions_per_swath)
    return NoisySurvey(sc, survey_noise(sc, noise_pct, rng))


def add_survey_arguments(parser: argparse.ArgumentParser, tracks: int,
                         positions: bool = True) -> None:
    """Add ``--tracks`` (default ``tracks``), ``--positions`` (102; only if ``positions``),
    ``--noise`` (10 %) and ``--window`` (5 tracks) to a benchmark's parser."""
    parser.add_argument('--tracks', type=int, default=tracks, help='double tracks of the survey')
    if positions:
        parser.add_argument('--positions', type=int, default=102, help='nodes per swath')
    parser.add_argument('--noise', type=float, default=10.0, help='noise (percent)')
    parser.add_argument('--window', type=int, default=5)
