"""The background refinement with the online variance factors applied
(:mod:`ga_ros.core.quality.online_variance`, ``variance_components='apply'``).

The refinement re-solves the horizon from a snapshot of the connection table
(:meth:`RefinementHandoff.snapshot <ga_ros.core.window.handoff.RefinementHandoff.snapshot>`),
whose covariances are the stated ones. :class:`ScaledRefinementHandoff` hands it every
connection's covariance times its group's factor at the time of the snapshot, so the refined
estimate, its published covariances and the joint priors rebuilt from it weight the sources as
the window adjustments do.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.window.config import AlignerConfig
from ga_ros.core.window.handoff import RefinementHandoff
from ga_ros.core.window.snapshot import RefinementSnapshot
from ga_ros.core.window.state import WindowState


class ScaledRefinementHandoff(RefinementHandoff):
    """:class:`~ga_ros.core.window.handoff.RefinementHandoff` whose snapshots carry the
    connections' covariances scaled by ``factors_of(rows)`` (``(m,)`` factor of each
    connection row)."""

    def __init__(self, state: WindowState, config: AlignerConfig,
                 factors_of: Callable[[IntArray], FloatArray]) -> None:
        super().__init__(state, config)
        self.factors_of = factors_of

    def snapshot(self, *args, **kwargs) -> RefinementSnapshot:
        snap = super().snapshot(*args, **kwargs)
        m = snap.cov21.shape[0]
        rows = np.arange(m) if snap.conn_rows is None else np.asarray(snap.conn_rows)
        f = self.factors_of(rows)
        if (f == 1.0).all():
            return snap
        return replace(snap, cov21=snap.cov21 * f[:, None])
