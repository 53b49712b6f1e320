"""Seeds of the experiments: every random draw of the report comes from :func:`run_rng`."""

from __future__ import annotations

import numpy as np

#: Path families of the synthetic trajectories (the first key of a Table I run).
FAMILIES = ('lawnmower', 'looping')

#: Experiment keys of :func:`run_rng`.
EXP_TABLE1, EXP_PAPER_MODEL, EXP_FUTURE, EXP_AERIAL, EXP_MEMORY = 1, 2, 3, 4, 5
EXP_OUTLIERS = 6


def run_rng(seed: int, experiment: int, *keys: int) -> np.random.Generator:
    """The generator of one run: ``default_rng(SeedSequence([seed, experiment, *keys]))``.

    Table I uses ``keys = (family, noise index, run)`` with ``family`` the index of the path's
    family in :data:`FAMILIES`. The open path's nodes and connections are a prefix of the closed
    one's, and a standard normal draw of the first ``m`` rows equals the first ``m`` rows of a
    longer draw, so open and closed share the noise of their common connections (common random
    numbers): their difference is the effect of closing the path, not of the draw.
    """
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(experiment),
                                                         *map(int, keys)]))


def noise_key(percent: float) -> str:
    """JSON key of a noise level: ``'10'`` for 10.0, ``'2.5'`` for 2.5."""
    return f'{percent:g}'
