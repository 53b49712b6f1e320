"""Self-calibration online: a :class:`~ga_ros.core.window.TrackWindowAligner` that corrects each
odometry motion with its source's current additional parameters before it enters the window,
and estimates them again after every track.

:class:`CalibratingAligner` (a window aligner; everything else unchanged):

* every consecutive motion of a source is corrected with the source's current scale and
  yaw-rate corrections (:func:`~ga_ros.core.calibration.parameters.corrected_motions`, the
  duration from the stamps of its two nodes) before admission; its motion as measured is kept;
* after each track's update, the parameters are estimated again by
  :func:`~ga_ros.core.calibration.solve_with_calibration` on the newest
  :attr:`OnlineCalibrationConfig.horizon_nodes` nodes (their connections with the motions as
  measured, their fixes, and a weak gauge prior of ``datum='fixes'`` on the oldest of them at
  its current estimate), with the same tests as in the batch: a parameter the horizon does not
  determine, or that is not significant, is 0 until a later horizon shows it. The poses of
  that adjustment are not used: the window's estimate stays the window's own. The window keeps
  the motions it already holds as they were corrected on admission.

The estimate is a sliding batch over the horizon (each track's is independent of the last,
so no information is counted twice), not a recursive one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.calibration.batch import (
    CalibrationConfig,
    CalibrationReport,
    solve_with_calibration,
)
from ga_ros.core.calibration.parameters import corrected_motions
from ga_ros.core.measurement import Measurement
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior
from ga_ros.core.window.aligner import TrackWindowAligner
from ga_ros.core.window.config import AlignerConfig, UpdateResult
from ga_ros.errors import GaError, InputError
from ga_ros.geometry import se3


@dataclass(frozen=True)
class OnlineCalibrationConfig:
    """Settings of :class:`CalibratingAligner`.

    Attributes
    ----------
    calibration : the parameters and their tests (:class:`CalibrationConfig`).
    horizon_nodes : the newest nodes whose connections estimate the parameters after a track.
    every_tracks : estimate after every this many tracks.
    """

    calibration: CalibrationConfig = CalibrationConfig()
    horizon_nodes: int = 2000
    every_tracks: int = 1

    def __post_init__(self) -> None:
        if self.horizon_nodes < 2 or self.every_tracks < 1:
            raise InputError('online calibration: horizon_nodes >= 2 and every_tracks >= 1')


class CalibratingAligner(TrackWindowAligner):
    """The window aligner with online self-calibration of its odometry sources (module doc).

    Attributes
    ----------
    online : its settings.
    report : the last estimate (:class:`CalibrationReport`; None before the first).
    values : ``(source, parameter) -> value`` applied to the motions admitted now.
    """

    def __init__(self, config: AlignerConfig | None = None,
                 T_world_first: FloatArray | None = None,
                 online: OnlineCalibrationConfig | None = None) -> None:
        super().__init__(config, T_world_first)
        self.online = online or OnlineCalibrationConfig()
        self.report: CalibrationReport | None = None
        self.values: dict[tuple[str, str], float] = {}
        self._measured: dict[tuple[int, int], tuple[FloatArray, str]] = {}
        self._stamp: dict[int, int] = {}
        self._tracks = 0

    def _add(self, m: Measurement, checked_cov: FloatArray | None) -> list[UpdateResult]:
        self._stamp.setdefault(int(m.dst_id), int(m.stamp_ns))
        if m.kind != 'consecutive':
            return super()._add(m, checked_cov)
        source = m.source or 'motion'
        key = (int(m.src_id), int(m.dst_id))
        z = np.asarray(m.z, dtype=float)
        scale = self.values.get((source, 'scale'), 0.0)
        yaw = self.values.get((source, 'yaw_rate'), 0.0)
        if scale or yaw:
            t0 = self._stamp.get(key[0])
            dt = 0.0 if t0 is None else max(0.0, (int(m.stamp_ns) - t0) * 1e-9)
            Tc = corrected_motions(z[None], np.array([dt]), np.array([scale]),
                                   np.array([yaw]))
            m = replace(m, z=se3.to_translation_rotvec(Tc)[0])
        updates = super()._add(m, checked_cov)
        self._measured[key] = (z, source)
        return updates

    def finish_track(self) -> UpdateResult | None:
        up = super().finish_track()
        if up is not None:
            self._tracks += 1
            if self._tracks % self.online.every_tracks == 0:
                self._recalibrate()
        return up

    def _recalibrate(self) -> None:
        """Estimate the parameters on the horizon (module doc); a failed adjustment keeps the
        current values."""
        st = self.state
        n = len(st.ids)
        first = max(0, n - self.online.horizon_nodes)
        rows = np.arange(first, n)
        src, dst = st.src.a, st.dst.a
        keep = np.nonzero((st.status.a != 2) & (src >= first) & (dst >= first))[0]
        if keep.size == 0:
            return
        ids = st.idarr.a
        priors = st.fixes.priors(rows, st.T, ids)
        if not priors:
            return
        if first > 0:  # the weak gauge of datum='fixes' on the oldest node, at its estimate
            cfg = self.config
            cov = np.diag([cfg.gauge_sigma_m ** 2] * 3 + [cfg.gauge_sigma_tilt_rad ** 2] * 2
                          + [cfg.gauge_sigma_yaw_rad ** 2])
            priors = [GaussianPrior.from_covariances([ids[first]], st.T[first:first + 1],
                                                     cov[None]), *priors]
        net = st.subnetwork(rows, keep)
        arr = net.arrays()
        z = arr.z.copy()
        sources: list[str | None] = []
        for k, (a, b, cross) in enumerate(zip(ids[src[keep]].tolist(), ids[dst[keep]].tolist(),
                                              st.cross.a[keep].tolist())):
            measured = None if cross else self._measured.get((a, b))
            if measured is None:
                sources.append(None)
            else:
                z[k] = measured[0]
                sources.append(measured[1])
        net = ConnectionNetwork.from_arrays(net.node_ids, net.track_ids, arr.src, arr.dst, z,
                                            arr.cov)
        stamp = st.stamp.astype(np.float64)
        dt_s = (stamp[dst[keep]] - stamp[src[keep]]) * 1e-9
        try:
            _, report = solve_with_calibration(net, st.T[rows], sources, dt_s,
                                               self.config.solver_config(), fixed=[],
                                               priors=priors,
                                               calibration=self.online.calibration)
        except GaError:
            return
        self.report = report
        self.values = {(p.source, p.name): p.value for p in report.parameters if p.estimated}
