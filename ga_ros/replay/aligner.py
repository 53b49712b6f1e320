"""The aligner a replay drives: what it needs of one, and the default factory."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError


class Aligner(Protocol):
    """What the replay needs of :class:`ga_ros.core.window.TrackWindowAligner`."""

    def add_measurement(self, m: Measurement) -> list[Any]: ...

    def finish_track(self) -> Any: ...

    def refine_batch(self) -> Any: ...

    def corrected_path(self) -> Any: ...

    def covariance(self, node_id: int) -> FloatArray: ...


AlignerFactory = Callable[[FloatArray | None], Aligner]


def aligner_config(config: Any) -> Any:
    """The aligner's settings of a :class:`~ga_ros.replay.config.ReplayConfig`: its
    ``aligner``, with ``calibrate`` on when the replay's is (``--calibrate``: the odometry
    calibrated online, :mod:`ga_ros.core.window.calibration`, as well as in the final batch)
    and then the cameras of ``calibrate_cameras`` in the online estimate (``--calibrate-camera``:
    published, not applied); ``aligner`` as it is for the batch aligner."""
    if not config.calibrate or config.aligner_kind != 'window':
        return config.aligner
    from ga_ros.core.window import AlignerConfig

    return replace(config.aligner or AlignerConfig(), calibrate=True,
                   calibrate_cameras=tuple(getattr(config, 'calibrate_cameras', ())))


def default_aligner_factory(config: Any = None, kind: str = 'window') -> AlignerFactory:
    """A factory of the aligner used by the replay.

    Parameters
    ----------
    config : :class:`ga_ros.core.window.AlignerConfig` (``kind='window'``) or
        :class:`ga_ros.core.solver.SolverConfig` (``kind='batch'``); None = defaults.
    kind : ``'window'`` (:class:`ga_ros.core.window.TrackWindowAligner`, the live node's) or
        ``'batch'`` (:class:`ga_ros.replay.batch.BatchAligner`, full re-solve per track).
    """
    if kind == 'batch':
        from ga_ros.replay.batch import BatchAligner

        return lambda T_world_first: BatchAligner(config, T_world_first=T_world_first)
    if kind != 'window':
        raise InputError(f"aligner must be 'window' or 'batch', got {kind!r}")
    try:
        from ga_ros.core.window import AlignerConfig, TrackWindowAligner
    except ImportError as exc:
        raise InputError(f'the track-window aligner is not available ({exc}); '
                         'use the batch aligner instead') from exc
    cfg = config if config is not None else AlignerConfig()

    def make(T_world_first: FloatArray | None) -> Aligner:
        return TrackWindowAligner(cfg, T_world_first=T_world_first)

    return make
