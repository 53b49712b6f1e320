"""Settings of the reproduction run (``ga-ros reproduce``)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from numbers import Integral

from ga_ros.errors import InputError
from ga_ros.sim.trajectories import SYNTHETIC_TRAJECTORIES

#: Noise levels of the paper's Table I (percent of the true motion).
PAPER_NOISE_LEVELS = (1.0, 5.0, 10.0, 18.0, 25.0)

#: Tracks shown in the paper's Fig. 8 (1-based track numbers).
PAPER_FIG8_TRACKS = (1, 2, 3, 4, 5, 11, 16, 21, 25)


@dataclass(frozen=True)
class ReproduceConfig:
    """What the reproduction runs and how often.

    Attributes
    ----------
    seed : master seed; run ``r`` of experiment ``e`` at noise index ``i`` for path family ``j``
        draws its noise from ``default_rng(SeedSequence([seed, e, j, i, r]))`` (see
        :func:`ga_ros.report.experiments.seeds.run_rng`), so every number can be recomputed
        alone.
    runs : Monte-Carlo runs per trajectory and noise level (Table I, Fig. 5; the paper: 100).
    noise_levels : noise levels (percent of the true motion).
    trajectories : synthetic trajectories (names from :mod:`ga_ros.sim.trajectories`).
    profile_noise : noise level (percent) of the error-along-the-trajectory plot (Fig. 5 left).
    paper_model_runs : runs of Table I with the paper's position model (eq. 1); 0 skips it.
    fig3_tracks : tracks of the aerial survey used for Fig. 2/3 (the paper: tracks 1-7).
    fig3_runs : noise draws per level for Fig. 2/3 (linearised, see
        :func:`ga_ros.report.experiments.future_tracks.future_tracks`).
    fig3_noise_levels : noise levels of Fig. 2/3 (the paper: 1, 5, 10 %).
    aerial_tracks : double tracks of the aerial survey for Fig. 7/8 and the window experiments.
    aerial_positions_per_swath : nodes per swath (the paper: 102).
    aerial_noise : noise level (percent) of the aerial experiments.
    window_tracks : sliding-window size K (the paper: 5).
    policies : freeze policies compared against the batch solution (``'<policy>+refine'``: with
        the background refinement after every track, :mod:`ga_ros.core.window.refinement`).
    policy_seeds : independent noise draws of the aerial survey on which the policies are
        compared (draw ``r`` from ``run_rng(seed, 4, r)``; draw 0 is the single-draw table):
        per policy the mean and sd of its gap to batch, and its paired difference with
        ``weighted`` on the same draws with a 95 % t interval (:func:`ga_ros.report.
        experiments.policies.policy_seeds`); 1 reports the single draw only (no interval).
    memory_tracks : two survey sizes (tracks) whose per-update memory is compared.
    fig8_tracks : 1-based track numbers whose before/after errors are plotted (Fig. 8).
    stereo_tracks, stereo_positions_per_swath : experiment 2 from rendered stereo (320x240,
        10 m steps, the paper: 25 tracks x 102 positions per swath); 0 tracks skips it.
    stereo_fig8_tracks : 1-based tracks of experiment 2's Fig. 8.
    outlier_tracks, outlier_positions_per_swath, outlier_noise : the reduced aerial survey of
        the wrong-connection table (:mod:`ga_ros.bench.outliers`); 0 tracks skips it.
    outlier_fractions : fractions of the cross-track connections replaced by gross errors.
    outlier_methods : defences compared (names of :data:`ga_ros.bench.outliers.METHODS`).
    """

    seed: int = 20051101
    runs: int = 100
    noise_levels: tuple[float, ...] = PAPER_NOISE_LEVELS
    trajectories: tuple[str, ...] = SYNTHETIC_TRAJECTORIES
    profile_noise: float = 10.0
    paper_model_runs: int = 10
    fig3_tracks: int = 7
    fig3_runs: int = 200
    fig3_noise_levels: tuple[float, ...] = (1.0, 5.0, 10.0)
    aerial_tracks: int = 25
    aerial_positions_per_swath: int = 102
    aerial_noise: float = 10.0
    window_tracks: int = 5
    policies: tuple[str, ...] = ('weighted', 'marginal', 'weighted+refine')
    policy_seeds: int = 10
    memory_tracks: tuple[int, int] = (25, 100)
    fig8_tracks: tuple[int, ...] = PAPER_FIG8_TRACKS
    stereo_tracks: int = 25
    stereo_positions_per_swath: int = 102
    stereo_fig8_tracks: tuple[int, ...] = PAPER_FIG8_TRACKS
    outlier_tracks: int = 6
    outlier_positions_per_swath: int = 40
    outlier_noise: float = 2.0
    outlier_fractions: tuple[float, ...] = (0.01, 0.05, 0.2)
    outlier_methods: tuple[str, ...] = ('ls', 'oracle', 'gate', 'snoop-w', 'huber', 'cauchy')
    preset: str = 'full'

    def __post_init__(self) -> None:
        if self.runs < 1 or self.fig3_runs < 1 or self.paper_model_runs < 0:
            raise InputError('runs and fig3_runs must be >= 1, paper_model_runs >= 0')
        if not self.noise_levels or any(p <= 0 for p in self.noise_levels):
            raise InputError('noise levels must be > 0 percent')
        if self.profile_noise not in self.noise_levels:
            raise InputError(f'profile_noise {self.profile_noise} must be one of the noise levels')
        bad = [t for t in self.trajectories if t not in SYNTHETIC_TRAJECTORIES]
        if bad or not self.trajectories:
            raise InputError(f'unknown trajectories {bad}; use {SYNTHETIC_TRAJECTORIES}')
        if self.fig3_tracks < 2 or self.aerial_tracks < 1 or self.window_tracks < 1:
            raise InputError('need fig3_tracks >= 2, aerial_tracks >= 1, window_tracks >= 1')
        if self.aerial_positions_per_swath < 4:
            raise InputError('aerial_positions_per_swath must be >= 4')
        if isinstance(self.policy_seeds, bool) or not isinstance(self.policy_seeds, Integral) \
                or self.policy_seeds < 1:
            raise InputError(f'policy_seeds must be an integer >= 1 (noise draws on which the '
                             f'policies are compared), got {self.policy_seeds!r}')
        if len(self.memory_tracks) != 2 or min(self.memory_tracks) < 1:
            raise InputError('memory_tracks must be two track counts >= 1')
        if self.stereo_tracks < 0 or (self.stereo_tracks and self.stereo_positions_per_swath < 4):
            raise InputError('stereo_tracks must be >= 0, stereo_positions_per_swath >= 4')
        if self.outlier_tracks < 0 or not all(0 < f < 1 for f in self.outlier_fractions):
            raise InputError('outlier_tracks must be >= 0 and outlier fractions in (0, 1)')


def preset(name: str) -> ReproduceConfig:
    """``'full'`` (the paper's 100 runs and full-size experiment 2), ``'quick'`` (same
    experiments with 3 runs per Table I cell, the aerial survey cut to 8 tracks, 6 vs 10 tracks
    for memory, experiment 2 on 6 tracks x 60 positions (more than
    the 5-track window), one wrong-connection fraction, the policies on 5 noise draws instead
    of 10) or
    ``'tiny'`` (smoke tests: small surveys)."""
    full = ReproduceConfig()
    if name == 'full':
        return full
    if name == 'quick':
        return replace(full, runs=3, paper_model_runs=1, fig3_runs=50, aerial_tracks=8,
                       memory_tracks=(6, 10), fig8_tracks=(1, 2, 3, 4, 5, 8), stereo_tracks=6,
                       stereo_positions_per_swath=30, stereo_fig8_tracks=(1, 2, 3, 4, 5, 6),
                       outlier_tracks=4, outlier_positions_per_swath=30,
                       outlier_fractions=(0.05,), outlier_methods=('ls', 'gate', 'snoop-w'),
                       policy_seeds=5, preset='quick')
    if name == 'tiny':
        return replace(full, runs=2, noise_levels=(1.0, 10.0), paper_model_runs=1,
                       fig3_tracks=4, fig3_runs=10, fig3_noise_levels=(10.0,),
                       aerial_tracks=6, aerial_positions_per_swath=20, memory_tracks=(3, 6),
                       fig8_tracks=(1, 2, 6), stereo_tracks=1, stereo_positions_per_swath=10,
                       stereo_fig8_tracks=(1,), outlier_tracks=2,
                       outlier_positions_per_swath=12, outlier_fractions=(0.05,),
                       outlier_methods=('ls', 'snoop-w'), policy_seeds=2, preset='tiny')
    raise InputError(f"unknown preset {name!r}; use 'full', 'quick' or 'tiny'")
