"""Track-by-track sliding-window alignment (paper Sec. IV and Appendix).

A lawnmower survey is flown as tracks. Measurements arrive one by one; when a track ends
(explicitly, or because a measurement introduces a node of a newer track), the mixed adjustment
runs over the nodes of the latest ``K`` tracks only. The adjustment is warm-started from the
previous estimate (the new track's nodes start from their frame-to-frame integration), so each
update solves only for the increment the new track brings. Nodes of the track that leaves the
window stop being unknowns and are *frozen*:

* ``freeze_policy='weighted'`` (the paper, Sec. III-E): every frozen node that is still connected
  to the window stays an unknown of the next adjustments, as a weighted parameter with one joint
  Gaussian prior over all such nodes (their full covariance, correlations kept). The prior holds
  the information of the connections among frozen nodes only (absorbed by a Schur complement
  when a track freezes, the other frozen nodes eliminated); connections to the window stay in
  the window problem and are relinearised there. No connection is counted twice, so the
  published covariances are not overconfident (independent per-node priors with the marginal
  covariances of the last adjustment would count shared information again at every update:
  position NEES ~100 instead of 3).
* ``freeze_policy='marginal'``: the leaving track is marginalised out exactly (Schur complement
  of its terms, as fixed-lag smoothers do), which leaves a joint Gaussian prior on the window
  nodes it was connected to; its connections are absorbed into that prior.

The exact joint prior is dense over the boundary nodes (a whole swath); it is stored sparse
(``prior_band``, ``prior_hubs``; :func:`~ga_ros.core.window.freeze.band_prior`): the exact mean and
the exact covariance on a skeleton (a band along the trajectory plus hub nodes), maximum entropy
beyond it, so a freeze and every window factorisation cost linear in the swath length.

The cost of an update depends on the window only, not on the number of tracks flown.

A background refinement (``refine_every_tracks``, :mod:`ga_ros.core.window.refinement`)
re-solves the
survey (its last ``refine_horizon_tracks`` tracks, the older ones as one prior) off the update
path, when the linearisation demands it (``refine_relinearize_sigma``), and hands the result
back at a fixed later track: frozen poses and covariances refined,
priors rebuilt at the refined estimate, and the window's corrections carried back to the frozen
nodes of that horizon, so the online path follows the batch solution.

Measurements are validated by :mod:`~ga_ros.core.window.admission` (the rejection reasons);
gross outliers among overlap (cross) connections are detected after each update and excluded,
and re-admitted when a later estimate agrees with them (:mod:`~ga_ros.core.window.gate`).

Parts, one job each: :mod:`~ga_ros.core.window.aligner` (the facade), ``config`` (settings and
results), ``state`` (the declared :class:`WindowState` and its tables, ``storage``),
``admission``, ``update`` (the window problem and its solve), ``gate``, ``freeze`` (the freeze
policies and their maths), ``freeze_ahead``, ``handoff``, ``refinement`` / ``elimination`` /
``worker`` (the background refinement), ``queries`` (covariances), ``persistence`` (snapshot
files of a :class:`WindowState`).
"""

from __future__ import annotations

import importlib

#: Each public name and the submodule that defines it: imported on first access (PEP 562), so a
#: refinement worker process that unpickles :mod:`~ga_ros.core.window.worker`'s job imports the
#: modules of the refinement only, not the aligner's.
_EXPORTS = {
    'measurement_fingerprints': 'admission', 'TrackWindowAligner': 'aligner',
    'ALIGNER_SOLVER': 'config', 'GATES': 'config', 'AlignerConfig': 'config',
    'AlignerStats': 'config', 'BatchResult': 'config', 'CorrectedPath': 'config',
    'UpdateResult': 'config', 'FREEZE_POLICIES': 'freeze', 'FreezePolicy': 'freeze',
    'JointPrior': 'freeze', 'SavedState': 'persistence', 'is_state_file': 'persistence',
    'load_state': 'persistence', 'save_state': 'persistence', 'WindowState': 'state',
    'REFINE_EXECUTORS': 'worker',
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(f'{__name__}.{module}'), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


__all__ = [
    'ALIGNER_SOLVER', 'FREEZE_POLICIES', 'GATES', 'REFINE_EXECUTORS', 'AlignerConfig',
    'AlignerStats', 'BatchResult', 'CorrectedPath', 'FreezePolicy', 'JointPrior', 'SavedState',
    'TrackWindowAligner', 'UpdateResult', 'WindowState', 'is_state_file', 'load_state',
    'measurement_fingerprints', 'save_state',
]
