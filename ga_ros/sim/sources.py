"""Several relative sources on one keyframe graph, each with its own true noise and a stated
noise that may be wrong (the set-up of variance-component estimation,
:mod:`ga_ros.core.quality.variance_components`).

A ground robot drives a weaving path of ``n_nodes`` keyframes ``step_m`` apart. Every source
measures every consecutive keyframe motion, ``T_meas = T_true exp(xi)`` with
``xi ~ N(0, diag(sigma^2))`` and ``sigma`` from the paper's noise model at the source's
*true* percentage (:class:`ga_ros.sim.noise.NoiseModel`); the covariance it states is the same
model at its *stated* percentage (5 %: the inputs' default when a stream carries no
covariance). The stated covariance is thus the true one times ``(stated / true)^2``, and the
variance factor that makes it right is ``(true / stated)^2`` (:attr:`SourceSpec.true_factor`).
Optionally, every ``loop_every`` nodes a loop-closure source (``'cross'``) measures the motion
from a node back to one ``loop_span`` nodes earlier, as a cross-track connection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.sim.noise import NoiseModel


@dataclass(frozen=True)
class SourceSpec:
    """One relative source.

    Attributes
    ----------
    name : the source's name (``odom0``, ...; the group of its measurements).
    true_percent : its true motion noise, percent of the motion (paper's noise model).
    stated_percent : the noise its covariances state (5: the inputs' default).
    """

    name: str
    true_percent: float
    stated_percent: float = 5.0

    @property
    def true_factor(self) -> float:
        """The variance factor that turns the stated covariance into the true one."""
        return (self.true_percent / self.stated_percent) ** 2


@dataclass(frozen=True)
class MultiSourceSurvey:
    """The ground truth and every source's measurements.

    Attributes
    ----------
    T_true : (n, 4, 4) true ``T_world_node``, the first at the identity.
    measurements : every source's consecutive motions (source by source, in node order), then
        the loop closures; ``Measurement.source`` names the source.
    sources : the sources' specifications (loop closures included, as ``'cross'``).
    """

    T_true: FloatArray
    measurements: tuple[Measurement, ...]
    sources: tuple[SourceSpec, ...]

    def of(self, name: str) -> list[Measurement]:
        """The measurements of one source."""
        return [m for m in self.measurements if m.source == name]


def weaving_path(n_nodes: int, step_m: float = 1.0, period: int = 60,
                 yaw_amplitude: float = 0.12) -> FloatArray:
    """(n, 4, 4) a planar weaving path: steps of ``step_m`` along the body x axis with a yaw
    step of ``yaw_amplitude sin(2 pi k / period)`` rad, starting at the identity."""
    T = np.empty((n_nodes, 4, 4))
    T[0] = np.eye(4)
    for k in range(n_nodes - 1):
        yaw = yaw_amplitude * np.sin(2 * np.pi * k / period)
        T[k + 1] = T[k] @ se3.from_translation_rotvec(np.array([step_m, 0.0, 0.0]),
                                                      np.array([0.0, 0.0, yaw]))
    return T


def multi_source_survey(rng: np.random.Generator, sources: tuple[SourceSpec, ...],
                        n_nodes: int = 400, step_m: float = 1.0, depth_m: float = 10.0,
                        loop: SourceSpec | None = None, loop_every: int = 50,
                        loop_span: int = 30, nodes_per_track: int = 100) -> MultiSourceSurvey:
    """Simulate the sources of the module doc on one weaving path.

    Parameters
    ----------
    rng : seeded generator.
    sources : the relative sources (each measures every consecutive motion).
    n_nodes, step_m : keyframes and their spacing (m).
    depth_m : the noise model's depth (m), turning a translation into its equivalent rotation.
    loop : the loop-closure source (None: none); its measurements have kind ``'cross'``.
    loop_every, loop_span : a loop closure from node ``k`` back to ``k - loop_span`` every
        ``loop_every`` nodes.
    nodes_per_track : track length (the track id is ``node // nodes_per_track``).
    """
    if not sources or n_nodes < 2:
        raise InputError('multi_source_survey: needs at least one source and two nodes')
    T = weaving_path(n_nodes, step_m)
    tr = np.arange(n_nodes) // nodes_per_track
    rel = se3.inverse(T[:-1]) @ T[1:]
    z_true = se3.to_translation_rotvec(rel)
    out: list[Measurement] = []
    for s in sources:
        out += _measure(rng, s, z_true, rel, np.arange(n_nodes - 1), np.arange(1, n_nodes), tr,
                        depth_m, 'consecutive')
    specs = tuple(sources)
    if loop is not None:
        dst = np.arange(loop_span, n_nodes, loop_every)
        src = dst - loop_span
        rel_l = se3.inverse(T[src]) @ T[dst]
        out += _measure(rng, loop, se3.to_translation_rotvec(rel_l), rel_l, src, dst, tr,
                        depth_m, 'cross')
        specs += (loop,)
    return MultiSourceSurvey(T, tuple(out), specs)


def _measure(rng: np.random.Generator, s: SourceSpec, z_true: FloatArray, rel: FloatArray,
             src: np.ndarray, dst: np.ndarray, tr: np.ndarray, depth_m: float,
             kind: str) -> list[Measurement]:
    true = NoiseModel(s.true_percent, depth_m)
    cov = NoiseModel(s.stated_percent, depth_m).covariances(z_true)
    xi = rng.standard_normal(z_true.shape) * true.sigmas(z_true)
    z = se3.to_translation_rotvec(rel @ se3.exp(xi))
    return [Measurement(int(a), int(b), int(tr[a]), int(tr[b]), z[k], cov[k],
                        int(b) * 10 ** 8, kind, s.name)
            for k, (a, b) in enumerate(zip(src, dst))]


def sources_network(n_nodes: int, ms: list[Measurement]) -> ConnectionNetwork:
    """The connection network of ``ms`` over nodes ``0 .. n_nodes - 1`` (100 nodes a track)."""
    net = ConnectionNetwork()
    for i in range(n_nodes):
        net.add_node(i, i // 100)
    for m in ms:
        net.add_connection(m.src_id, m.dst_id, m.z, m.cov)
    return net


def chained_poses(n_nodes: int, ms: list[Measurement]) -> FloatArray:
    """(n, 4, 4) poses ``T_world_node`` integrated from the identity along the first
    consecutive measurement of every node pair (a start for the adjustment)."""
    T = [np.eye(4)]
    for m in ms:
        if m.kind == 'consecutive' and m.dst_id == len(T) and len(T) < n_nodes:
            T.append(T[-1] @ m.T_src_dst)
    return np.array(T)
