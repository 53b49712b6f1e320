"""What a replay did: :class:`ReplayResult` (also written to ``summary.json``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, is_dataclass
from typing import Any

import numpy as np

from ga_ros.eval.metrics import TrajectoryError
from ga_ros.io.trajectory import Trajectory


@dataclass
class ReplayResult:
    """What a replay did (also written to ``summary.json``).

    ``errors`` maps ``'ga'`` (the final batch of everything read, or the online estimate when
    the final batch is off), ``'online'`` (the corrected path after the last track's update,
    what the live node publishes at the end) and ``'f2f'`` (the odometry, anchored as GA) to
    :class:`TrajectoryError` against ground truth (empty without ground truth);
    ``errors_compared`` says which RMSE the figures compare: ``'raw'`` (anchored at the ground
    truth) or ``'aligned'`` (``--no-anchor``: each after its rigid alignment).
    ``corrected`` is GA's trajectory, ``online`` the online one; ``final_batch`` whether GA is
    the final batch, ``final_batch_update`` its solve (as an entry of ``updates``, which holds
    the online updates). ``error`` is the message of the failure that cut the replay
    short (the outputs then hold everything up to it), else None. ``quality`` (aligner
    ``quality`` on): ``per_track``, the :class:`ga_ros.core.quality.QualitySummary` of every
    update with its ``track_id``, and ``final``, that of the last adjustment. ``notes``: what
    the user should know about an unusual but valid run (e.g. a robot that did not move).
    ``variance_components``: the variance factor per source estimated in the final batch
    (:meth:`~ga_ros.core.quality.variance_components.VarianceComponents.as_dict`; empty when
    not estimated); ``online_variance_components`` those estimated online after each track
    (:meth:`~ga_ros.core.quality.online_variance.OnlineVarianceComponents.as_dict`; empty when
    ``variance_components`` of the aligner is ``'off'``). ``calibration``: the additional
    parameters per source estimated in the final batch with ``calibrate``
    (:meth:`~ga_ros.core.calibration.CalibrationReport.as_dict`; empty otherwise);
    ``online_calibration`` those estimated online, the last estimate
    (:meth:`~ga_ros.core.window.calibration.OnlineCalibration.as_dict`; empty when the
    aligner's ``calibrate`` is off).
    ``ground_truth`` says what ground truth was used and how much of it matched; ``warnings``
    what the replay went on despite (e.g. a bag cut short). ``mosaic`` (``--mosaic``): per
    trajectory (``'ga'``, ``'f2f'``) its mosaic's files, covered area and seam misregistration
    (:func:`ga_ros.mapping.replay_mosaic.write_mosaics`).
    ``map``: the figures of ``--map``
    (:func:`ga_ros.replay.map_outputs.write_map_outputs`; absent without).
    ``failed_updates``: online window updates that failed (the aligner put its state back and
    retried the track in the next update), ``failed_update_examples`` the first ten reasons.
    """

    bag: str
    source: str
    out_dir: str
    n_inputs: int = 0
    n_measurements: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    rejected_examples: list[str] = field(default_factory=list)
    n_nodes: int = 0
    n_tracks: int = 0
    updates: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    errors: dict[str, TrajectoryError] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    output_counts: dict[str, int] = field(default_factory=dict)
    error: str | None = None
    source_stats: dict[str, Any] = field(default_factory=dict)
    corrected: Trajectory | None = None
    quality: dict[str, Any] = field(default_factory=dict)
    frames: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    ground_truth: str = ''
    warnings: list[str] = field(default_factory=list)
    gaps: dict[str, Any] = field(default_factory=dict)
    online: Trajectory | None = None
    final_batch: bool = False
    final_batch_update: dict[str, Any] = field(default_factory=dict)
    errors_compared: str = 'raw'
    variance_components: dict[str, Any] = field(default_factory=dict)
    mosaic: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)
    online_calibration: dict[str, Any] = field(default_factory=dict)
    online_variance_components: dict[str, Any] = field(default_factory=dict)
    map: dict[str, Any] = field(default_factory=dict)
    failed_updates: int = 0
    failed_update_examples: list[str] = field(default_factory=list)

    @property
    def rate(self) -> float:
        """Inputs (measurements or stereo pairs) processed per second."""
        return self.n_inputs / self.seconds if self.seconds > 0 else float('nan')

    def as_dict(self) -> dict[str, Any]:
        return {
            'bag': self.bag, 'source': self.source, 'out_dir': self.out_dir,
            'n_inputs': self.n_inputs, 'n_measurements': self.n_measurements,
            'rejected': self.rejected, 'rejected_examples': self.rejected_examples,
            'n_nodes': self.n_nodes, 'n_tracks': self.n_tracks, 'updates': self.updates,
            'failed_updates': self.failed_updates,
            'failed_update_examples': self.failed_update_examples,
            'seconds': self.seconds, 'inputs_per_s': self.rate,
            'errors_vs_ground_truth': {k: v.as_dict() for k, v in self.errors.items()},
            'errors_compared': self.errors_compared,
            'final_batch': self.final_batch_update if self.final_batch else None,
            'trajectories': {'ga': 'final batch' if self.final_batch else 'online',
                             'online': 'online (the live node at the end)',
                             'f2f': 'odometry anchored as ga'},
            'files': self.files, 'output_counts': self.output_counts, 'error': self.error,
            'source_stats': self.source_stats, 'quality': self.quality, 'frames': self.frames,
            'notes': self.notes, 'ground_truth': self.ground_truth, 'warnings': self.warnings,
            'gaps': self.gaps, 'variance_components': self.variance_components,
            'mosaic': self.mosaic, 'calibration': self.calibration,
            'online_calibration': self.online_calibration,
            'online_variance_components': self.online_variance_components,
            **({'map': self.map} if self.map else {})}

    def reject(self, reason: str) -> None:
        """Count a rejection under the text before its first ``:`` (keep 10 examples)."""
        key = reason.split(':', 1)[0]
        self.rejected[key] = self.rejected.get(key, 0) + 1
        if len(self.rejected_examples) < 10:
            self.rejected_examples.append(reason)


def plain_fields(obj: Any) -> dict[str, Any]:
    """The JSON-able scalar (and dict) fields of a dataclass or a mapping, numpy scalars as
    Python ones: an update or statistics entry of the summary (``{}`` for anything else, e.g.
    None)."""
    if isinstance(obj, dict):
        d = dict(obj)
    elif is_dataclass(obj) and not isinstance(obj, type):
        d = asdict(obj)
    else:
        return {}
    return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in d.items()
            if isinstance(v, (int, float, str, bool, np.generic, type(None), dict))}
