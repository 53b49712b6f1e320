"""Peak memory of one track update for two survey sizes (tracemalloc)."""

from __future__ import annotations

import tracemalloc

import numpy as np

from ga_ros.errors import GaError
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.seeds import EXP_MEMORY, run_rng
from ga_ros.report.experiments.survey import window_available
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb


def memory_profile(cfg: ReproduceConfig) -> dict:
    """Peak traced memory (tracemalloc) of each track update for two survey sizes, and the
    memory retained by the aligner at the end (which holds the whole path, so it grows)."""
    if not window_available():
        return {'available': False}
    from ga_ros.core.window import AlignerConfig, TrackWindowAligner

    out: dict = {'available': True, 'sizes': {}}
    for n_tracks in cfg.memory_tracks:
        sc = aerial_scenario(n_tracks, cfg.aerial_positions_per_swath)
        nm = perturb(sc.true_motions(), NoiseModel(cfg.aerial_noise, sc.depth_m),
                     run_rng(cfg.seed, EXP_MEMORY, n_tracks))
        meas = sc.measurements(nm.z, nm.cov)
        tracemalloc.start()
        try:
            base = tracemalloc.get_traced_memory()[0]
            # the window update's own memory: without the background refinement (a batch of
            # the whole survey, whose memory grows with it by design)
            aligner = TrackWindowAligner(AlignerConfig(window_tracks=cfg.window_tracks,
                                                       refine_every_tracks=0),
                                         T_world_first=sc.T_world_node[0])
            peaks = []
            dst_track = np.array([m.dst_track for m in meas])
            bounds = np.searchsorted(dst_track, np.arange(n_tracks), side='right')
            start = 0
            for stop in bounds:
                for m in meas[start:stop]:
                    try:
                        aligner.add_measurement(m)
                    except GaError:
                        pass  # counted in the aligner's stats; memory is what is measured
                current = tracemalloc.get_traced_memory()[0]
                tracemalloc.reset_peak()
                aligner.finish_track()
                peaks.append(tracemalloc.get_traced_memory()[1] - current)
                start = stop
            retained = tracemalloc.get_traced_memory()[0] - base
        finally:
            tracemalloc.stop()
        full = peaks[min(cfg.window_tracks, len(peaks)) - 1:]  # updates with a full window
        out['sizes'][str(n_tracks)] = {
            'nodes': sc.n_nodes, 'connections': sc.n_connections,
            'full_window_updates': len(full),
            'update_peak_mib_full_window_mean': float(np.mean(full)) / 2**20,
            'update_peak_mib_max': float(max(peaks)) / 2**20,
            'retained_mib': float(retained) / 2**20}
    return out
