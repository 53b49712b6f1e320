"""A simulated survey with absolute fixes, as a stream of inputs (ROS-free): the journal,
recovery and fault-catalogue cases feed it to an
:class:`~ga_ros.pipeline.session.AlignmentSession` in arrival order.

Entries are a :class:`~ga_ros.core.measurement.Measurement` or a fix ``(FixTerm, C_offset)``
(the arguments of :meth:`AlignmentSession.add_fix
<ga_ros.pipeline.session.AlignmentSession.add_fix>`). Stamps: node ``k`` at ``k`` s, its fixes
0.3 s later. Each fix is taken by a sensor on a lever arm from its node (:data:`LEVER`, known,
with the odometry offset's covariance :data:`C_OFFSET`), with the position known to its
source's sigma per axis, the tilt unknown and the heading to 0.1 rad.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3

#: node -> fix sensor (m, rad): the lever arm of every fix
LEVER = se3.from_translation_rotvec([0.3, 0.5, 1.0], [0.0, 0.0, 0.05])
#: (6, 6) covariance of the offset from the node to the fix's stamp (odometry over 0.3 s)
C_OFFSET = np.diag([1e-3] * 3 + [1e-5] * 3)
#: ``(every, source, sigma_m)``: a fix of ``source`` on every ``every``-th node
FIX_SOURCES: tuple[tuple[int, str, float], ...] = ((3, 'gnss0', 0.3), (5, 'usbl1', 0.5))
#: the line survey's true step between nodes (m, map frame)
STEP = np.array([1.0, 0.2, 0.0])


def fixes_of_node(rng: np.random.Generator, k: int, T_map_sensor: FloatArray,
                  sources: Iterable[tuple[int, str, float]] = FIX_SOURCES) -> list:
    """The fixes of node ``k`` (module doc): one per source of ``sources`` whose ``every``
    divides ``k``, at the sensor's true pose ``T_map_sensor`` (4, 4) with its position
    perturbed by the source's sigma (drawn from ``rng`` in the order of ``sources``)."""
    out = []
    T_true = np.asarray(T_map_sensor, float)
    for every, source, sigma in sources:
        if k % every == 0:
            T = T_true.copy()
            T[:3, 3] = T_true[:3, 3] + rng.normal(0, sigma, 3)
            fix = AbsoluteFix.from_covariance(k * 10 ** 9 + 3 * 10 ** 8, T,
                                              np.diag([sigma ** 2] * 3 + [-1, -1, 0.01]),
                                              source)
            out.append((FixTerm(k, LEVER, fix), C_OFFSET))
    return out


def line_fix_survey(rng: np.random.Generator, n_tracks: int, per: int,
                    odometry: tuple[tuple[str, float], ...] = (('', 0.05),),
                    sources: Iterable[tuple[int, str, float]] = FIX_SOURCES) -> list:
    """A straight line of ``n_tracks * per`` nodes (``per`` a track, :data:`STEP` apart):
    frame-to-frame measurements, node ``i`` to ``i + 1`` by the odometry source
    ``odometry[i % len(odometry)]`` (``(name, sigma_m)``: position noise sigma per axis,
    rotation noise 0.01 rad, stated as such), each followed by the fixes of its destination
    node (:func:`fixes_of_node`; the sensor's true pose: the node's position, heading 0.1 rad,
    so the lever arm is not the fix's true offset). Entries in arrival order (module doc)."""
    out: list = []
    sources = tuple(sources)
    for i in range(n_tracks * per - 1):
        name, sigma_t = odometry[i % len(odometry)]
        cov = np.diag([sigma_t ** 2] * 3 + [1e-4] * 3)
        z = np.concatenate([STEP + rng.normal(0, sigma_t, 3), rng.normal(0, 0.01, 3)])
        out.append(Measurement(i, i + 1, i // per, (i + 1) // per, z, cov,
                               stamp_ns=(i + 1) * 10 ** 9, source=name))
        k = i + 1
        out += fixes_of_node(rng, k, se3.from_translation_rotvec(STEP * k, [0.0, 0.0, 0.1]),
                             sources)
    return out


def feed_entries(session, entries: Iterable) -> int:
    """Give ``entries`` to ``session`` (an
    :class:`~ga_ros.pipeline.session.AlignmentSession`) in order, as a live node would: a
    measurement to ``step``, a fix to ``add_fix``, a fix it refuses (a frozen or unknown
    node: :class:`~ga_ros.errors.InputError`) left out. Returns the number refused."""
    refused = 0
    for e in entries:
        if isinstance(e, Measurement):
            session.step(e)
        else:
            try:
                session.add_fix(*e)
            except InputError:
                refused += 1
    return refused
