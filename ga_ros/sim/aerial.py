"""The aerial survey of the paper's Sec. IV: a 1 km x 1 km lawnmower at 110 m altitude.

Geometry (defaults reproduce the paper): ``n_tracks`` double tracks (25), i.e. ``2 n_tracks``
swaths (50) of ``positions_per_swath`` nodes (102, so 204 per double track) ``step_m`` apart
(10 m, so a swath is ~1 km long); adjacent swaths ``swath_spacing_m`` apart (20 m). The camera
looks straight down from ``altitude_m`` (110 m) with a fixed orientation and images a square ground
footprint of ``footprint_m`` (100 m), so consecutive frames overlap by 1 - 10/100 = 90 % and
adjacent swaths by 1 - 20/100 = 80 %. The paper's terrain (5-65 m above the reference plane) is
not modelled: the footprint size is the same everywhere (the scene depth used by the noise model is
the altitude).

Swath ``s`` flies along ``+x`` when ``s`` is even and ``-x`` when odd, at ``y = s *
swath_spacing_m``; the turn between swaths is one ordinary 20 m step. Node ids are ``0 .. N-1`` in
flight order and the track id is the double-track index ``s // 2``. Connections follow the 70 %
footprint-overlap rule of :mod:`ga_ros.sim.scenario`: each node connects to the next 3 nodes of its
swath (10, 20, 30 m: overlap 0.9, 0.8, 0.7) and to the 3 nearest nodes of the adjacent swath
(overlap 0.72 and 0.8); swaths two apart overlap by 60 % and are not connected. With the defaults:
5100 nodes and 29,896 connections (the paper quotes ~17,000 for its own overlap measure).
"""

from __future__ import annotations

import numpy as np

from ga_ros.errors import InputError
from ga_ros.sim.scenario import Scenario, scenario_from_path


def aerial_scenario(n_tracks: int = 25, positions_per_swath: int = 102, step_m: float = 10.0,
                    swath_spacing_m: float = 20.0, altitude_m: float = 110.0,
                    footprint_m: float = 100.0, min_overlap: float = 0.7) -> Scenario:
    """The paper's aerial lawnmower survey (Sec. IV); see the module docstring.

    Parameters
    ----------
    n_tracks : number of double tracks (paper: 25).
    positions_per_swath : nodes per swath (paper: 102, i.e. 204 per double track).
    step_m : travel between consecutive frames (m).
    swath_spacing_m : distance between adjacent swaths (m).
    altitude_m : flying height (m); also the scene depth of the noise model.
    footprint_m : side of the square ground footprint (m).
    min_overlap : connection threshold (fraction of the footprint area).
    """
    if n_tracks < 1 or positions_per_swath < 2:
        raise InputError('need n_tracks >= 1 and positions_per_swath >= 2')
    if min(step_m, swath_spacing_m, altitude_m, footprint_m) <= 0:
        raise InputError('step, swath spacing, altitude and footprint must be > 0')
    n_swaths = 2 * int(n_tracks)
    k = np.arange(positions_per_swath) * step_m
    xs = [k if s % 2 == 0 else k[::-1] for s in range(n_swaths)]
    x = np.concatenate(xs)
    y = np.repeat(np.arange(n_swaths) * swath_spacing_m, positions_per_swath)
    z = np.full(x.shape, altitude_m)
    tracks = np.repeat(np.arange(n_swaths) // 2, positions_per_swath)
    return scenario_from_path('aerial', np.stack([x, y, z], axis=1), tracks, footprint_m,
                              altitude_m, min_overlap)
