"""The four synthetic trajectories of the paper's Sec. V-A (Fig. 4).

The paper's sizes are lost in its text extraction; these are ours (same camera as the aerial
scenario: nadir, fixed orientation, 110 m altitude, 100 m square footprint, 10 m between frames,
70 % overlap rule):

* ``lawnmower_open``: one double track of the aerial scenario ("one track of the lawnmower
  pattern in the scenario described in Section IV"): 2 swaths of 102 nodes (~1 km, 20 m apart)
  whose back swath stops 60 m short of the start edge (so its end does not overlap the start by
  70 %): 198 nodes. Each node connects to the next 3 of its swath and to ~3 of the other swath.
* ``lawnmower_closed``: the full double track (204 nodes) plus a return leg of 20 m steps
  (along ``x = -20 m``) from the end of the back swath to a node 20 m from node 0, so the last
  nodes connect to the first.
* ``looping_open``: two loops of a figure-eight (Gerono lemniscate ``x = A sin s,
  y = (B/2) sin 2s``, ``A = 400 m``, ``B = 120 m``) sampled every 10 m, both loops crossing at the
  start point (the paper's "looping tracks crossing repeatedly at some known position"); the legs
  of a loop are far apart except near the crossing and the loop ends, so there are fewer cross
  connections than in the lawnmower. The open path stops 60 m short of its start. Track id = loop.
* ``looping_closed``: the whole figure-eight; its last node is one step from node 0.
"""

from __future__ import annotations

import numpy as np

from ga_ros.errors import InputError
from ga_ros.sim.scenario import Scenario, scenario_from_path

#: Names of the four synthetic trajectories, in the order of the paper's Table I.
SYNTHETIC_TRAJECTORIES = ('lawnmower_open', 'lawnmower_closed', 'looping_open', 'looping_closed')

ALTITUDE_M = 110.0
FOOTPRINT_M = 100.0
STEP_M = 10.0


def lawnmower(closed: bool, n_swaths: int = 2, positions_per_swath: int = 102,
              swath_spacing_m: float = 20.0, open_gap_m: float = 60.0) -> Scenario:
    """Lawnmower of ``n_swaths`` swaths (an even number: whole double tracks).

    ``closed`` adds a return leg (20 m steps along the start edge) ending next to the start;
    otherwise the last swath stops ``open_gap_m`` short of the start edge.
    """
    if n_swaths < 2 or n_swaths % 2:
        raise InputError(f'n_swaths must be an even number >= 2, got {n_swaths}')
    k = np.arange(positions_per_swath) * STEP_M
    x = np.concatenate([k if s % 2 == 0 else k[::-1] for s in range(n_swaths)])
    y = np.repeat(np.arange(n_swaths) * swath_spacing_m, positions_per_swath)
    tracks = np.repeat(np.arange(n_swaths) // 2, positions_per_swath)
    if closed:
        # back along x = -20 m from the last swath's y down to y = 0, next to node 0
        y_ret = np.arange((n_swaths - 1) * swath_spacing_m, -1e-9, -swath_spacing_m)
        x_ret = np.full(y_ret.shape, -2 * STEP_M)
        x = np.concatenate([x, x_ret])
        y = np.concatenate([y, y_ret])
        tracks = np.concatenate([tracks, np.full(y_ret.shape, tracks[-1])])
    else:
        drop = int(round(open_gap_m / STEP_M))
        x, y, tracks = x[:x.size - drop], y[:y.size - drop], tracks[:tracks.size - drop]
    p = np.stack([x, y, np.full(x.shape, ALTITUDE_M)], axis=1)
    return scenario_from_path('lawnmower_closed' if closed else 'lawnmower_open', p, tracks,
                              FOOTPRINT_M, ALTITUDE_M)


def looping(closed: bool, half_length_m: float = 400.0, width_m: float = 120.0,
            open_gap_m: float = 60.0) -> Scenario:
    """Figure-eight of two loops crossing at the start (see the module docstring)."""
    s = np.linspace(0.0, 2 * np.pi, 20001)
    xy = np.stack([half_length_m * np.sin(s), 0.5 * width_m * np.sin(2 * s)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    total = arc[-1]
    n = int(np.floor(total / STEP_M))
    stop = total - (0.0 if closed else open_gap_m)
    a = np.arange(n + 1) * (total / n)
    a = a[a < stop - 1e-6]
    x = np.interp(a, arc, xy[:, 0])
    y = np.interp(a, arc, xy[:, 1])
    tracks = (a >= total / 2).astype(np.int64)
    p = np.stack([x, y, np.full(x.shape, ALTITUDE_M)], axis=1)
    return scenario_from_path('looping_closed' if closed else 'looping_open', p, tracks,
                              FOOTPRINT_M, ALTITUDE_M)


def synthetic_scenario(name: str) -> Scenario:
    """One of :data:`SYNTHETIC_TRAJECTORIES` by name."""
    if name not in SYNTHETIC_TRAJECTORIES:
        raise InputError(f'unknown trajectory {name!r}; use one of {SYNTHETIC_TRAJECTORIES}')
    kind, shape = name.split('_')
    closed = shape == 'closed'
    return lawnmower(closed) if kind == 'lawnmower' else looping(closed)
