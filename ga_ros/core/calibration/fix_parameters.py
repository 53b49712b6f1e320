"""The additional parameters of an absolute-fix source (self-calibration): what each corrects in
a measured fix position, and its Jacobian.

A fix source (a GNSS receiver, a USBL, a second localiser: every :class:`~ga_ros.core.fixes.
AbsoluteFix` with the same ``source``) measures the sensor's position ``p`` in the map frame.
Its systematic errors:

* ``b`` (:class:`FixOffsetAxis`, m, per axis ``offset_x``, ``offset_y``, ``offset_z``): a
  constant offset in the map frame (a datum or base-station shift, an antenna lever arm that is
  not in the TF tree): ``p_fix = p_true + b``;
* ``tau`` (:class:`TimeOffset`, s): the receiver's latency, the fix stamped ``t`` measured the
  position at ``t - tau``: ``p_fix = p_true(t - tau) = p_true(t) - v tau`` to first order, ``v``
  (m/s, map frame) the trajectory's velocity at the fix's keyframe, from its neighbouring
  keyframes in time (:func:`node_velocities`).

Both enter the fix's map-frame misclosure ``e = p_pred(t) - p_fix`` linearly,
``e(c) = p_pred(t) - (p_fix - b + v tau)``, so a parameter's Jacobian ``E = de/dc`` (``(k, 6)``
rows ``[dp, dtheta]``: ``[1 on its axis, 0]`` for an offset, ``[-v, 0]`` for a time offset) is
also its correction: the corrected fix is ``p_fix - E[:, :3] c`` (:func:`fix_shift`). ``v`` is
taken at the current estimate of the poses and held in the Jacobian with respect to the poses
(its dependence on them is second order: ``tau`` times a velocity change).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.fixes import FixBook, FixTerm, node_prior, sensor_jacobian, sensor_misclosure
from ga_ros.core.solver import GaussianPrior
from ga_ros.errors import InputError
from ga_ros.runtime import lazy_import

sla = lazy_import('scipy.linalg')  # block_diag of the priors' information (start-up)


@dataclass(frozen=True)
class FixOffsetAxis:
    """One axis of a fix source's constant offset ``b`` (m, map frame): ``p_fix = p_true + b``
    (module doc)."""

    axis: int
    name: str
    unit: str = 'm'
    family: ClassVar[str] = 'fix'
    #: no bound on its sigma (step 2 of :mod:`.batch`)
    max_sigma: ClassVar[float] = float('inf')
    on_fixes: ClassVar[bool] = True
    datum: ClassVar[bool] = True  # a reference source (the frame's definition) has none
    unobserved: ClassVar[str] = 'no fix that measures its axis'
    unseen: ClassVar[str] = ('no other absolute position (a second fix source, a held node or '
                             'a prior): its fixes define the frame')

    def acts_on(self, known: np.ndarray, velocity: FloatArray) -> FloatArray:
        """(k,) how much each fix tells about the parameter (1 where it measures the axis)."""
        return known[:, self.axis].astype(float)

    def jacobian(self, velocity: FloatArray) -> FloatArray:
        """(k, 6) ``E = de/db``: ``1`` in the axis' position row."""
        E = np.zeros((velocity.shape[0], 6))
        E[:, self.axis] = 1.0
        return E


@dataclass(frozen=True)
class TimeOffset:
    """A fix source's latency ``tau`` (s): the fix stamped ``t`` measured ``p_true(t - tau)``
    (module doc)."""

    name: str = 'time_offset'
    unit: str = 's'
    family: ClassVar[str] = 'fix'
    #: no bound on its sigma (step 2 of :mod:`.batch`)
    max_sigma: ClassVar[float] = float('inf')
    on_fixes: ClassVar[bool] = True
    datum: ClassVar[bool] = False
    unobserved: ClassVar[str] = 'no fix taken while moving (no velocity: stamps?)'
    unseen: ClassVar[str] = 'the poses absorb it (a straight run at constant velocity?)'

    def acts_on(self, known: np.ndarray, velocity: FloatArray) -> FloatArray:
        """(k,) how much each fix tells about the parameter (its speed in the measured axes,
        m/s)."""
        return np.linalg.norm(np.where(known[:, :3], velocity, 0.0), axis=1)

    def jacobian(self, velocity: FloatArray) -> FloatArray:
        """(k, 6) ``E = de/dtau``: ``-v`` in the position rows."""
        E = np.zeros((velocity.shape[0], 6))
        E[:, :3] = -np.asarray(velocity, dtype=float)
        return E


#: The additional parameters of a fix source, by name.
FIX_PARAMETERS = {p.name: p for p in (FixOffsetAxis(0, 'offset_x'), FixOffsetAxis(1, 'offset_y'),
                                      FixOffsetAxis(2, 'offset_z'), TimeOffset())}


def fix_parameter(name: str) -> FixOffsetAxis | TimeOffset:
    """The fix parameter called ``name`` (:data:`FIX_PARAMETERS`)."""
    try:
        return FIX_PARAMETERS[name]
    except KeyError:
        raise InputError(f'unknown fix calibration parameter {name!r}; choose from '
                         f'{sorted(FIX_PARAMETERS)}') from None


@dataclass(frozen=True)
class FixObservations:
    """The absolute fixes of an adjustment, one by one, for their sources' parameters.

    Attributes
    ----------
    terms : each fix tied to its keyframe (:class:`~ga_ros.core.fixes.FixTerm`; the source is
        ``term.fix.source``).
    information : (k, 6, 6) the information each fix enters with (map frame, its offset's
        covariance included, e.g. :meth:`~ga_ros.core.fixes.FixBook.information_used`).
    node_stamps_s : (n,) each node's stamp (s), network index order: the velocities of
        :func:`node_velocities`.
    """

    terms: Sequence[FixTerm]
    information: FloatArray
    node_stamps_s: FloatArray
    sources: list[str] = field(init=False)

    def __post_init__(self) -> None:
        info = np.asarray(self.information, dtype=float).reshape(-1, 6, 6)
        if info.shape[0] != len(self.terms):
            raise InputError(f'FixObservations: {info.shape[0]} informations for '
                             f'{len(self.terms)} fixes')
        object.__setattr__(self, 'terms', tuple(self.terms))
        object.__setattr__(self, 'information', info)
        object.__setattr__(self, 'node_stamps_s',
                           np.asarray(self.node_stamps_s, dtype=float).reshape(-1))
        object.__setattr__(self, 'sources', [t.fix.source for t in self.terms])

    def __len__(self) -> int:
        return len(self.terms)

    @property
    def known(self) -> np.ndarray:
        """(k, 6) bool: the dimensions each fix measures."""
        return np.array([t.fix.known for t in self.terms]).reshape(-1, 6)

    def rows(self, node_ids: IntArray) -> IntArray:
        """(k,) each fix's node row in ``node_ids`` (the network's order)."""
        ids = np.asarray(node_ids)
        order = np.argsort(ids, kind='stable')
        want = np.array([t.node_id for t in self.terms], dtype=ids.dtype)
        pos = np.searchsorted(ids[order], want)
        if want.size and (np.any(pos >= ids.size) or np.any(ids[order][np.minimum(
                pos, ids.size - 1)] != want)):
            raise InputError('FixObservations: a fix is tied to a node that is not in the '
                             'network')
        return order[pos]


def book_observations(book: FixBook, rows: IntArray, stamps_s: FloatArray,
                      applied: FloatArray | None = None) -> FixObservations:
    """The used fixes of an aligner's fix book on the node ``rows`` (the gauge prior of
    ``datum='fixes'`` left out: it stays a prior), one by one in the book's order, with the
    information they enter with (:meth:`~ga_ros.core.fixes.FixBook.information_used`);
    ``stamps_s`` (n,) the stamps of the network's nodes (s, network index order). The
    :func:`fix_priors` of the result equal the book's fix prior
    (:meth:`~ga_ros.core.fixes.FixBook.priors` without the gauge's) bit for bit.

    ``applied`` (len(book), 3): the shift (m, map) each book fix was stored with (the online
    calibration's correction, :func:`fix_shift`): the observations are then the fixes as
    measured (the stored position minus it; None or a zero row: as stored)."""
    used = [int(f) for f in book.used(rows) if book.gated[f]]
    info = book.information_used(used)
    terms = [book.terms[f] for f in used]
    if applied is not None:
        terms = [t if not np.any(applied[f]) else replace(t, fix=replace(
            t.fix, T_map_sensor=_moved(t.fix.T_map_sensor, -applied[f])))
            for t, f in zip(terms, used)]
    return FixObservations(terms, np.array(info).reshape(-1, 6, 6), stamps_s)


def node_velocity(T_world_node: FloatArray, stamps_s: FloatArray, row: int) -> FloatArray:
    """(3,) the velocity (m/s, world frame) of node ``row``: :func:`node_velocities`' value
    for that node, computed from its two neighbours in time only (the nodes ordered by stamp,
    ties by row, as :func:`node_velocities`' stable sort orders them)."""
    t = np.asarray(stamps_s, dtype=float)
    n = t.size
    idx = np.arange(n)
    tk = t[row]
    before = np.nonzero((t < tk) | ((t == tk) & (idx < row)))[0]
    after = np.nonzero((t > tk) | ((t == tk) & (idx > row)))[0]
    if before.size:
        last = t[before].max()
        prev = int(before[t[before] == last].max())
    else:
        prev = int(row)
    if after.size:
        first = t[after].min()
        nxt = int(after[t[after] == first].min())
    else:
        nxt = int(row)
    span = t[nxt] - t[prev]
    if not span > 0:
        return np.zeros(3)
    T = np.asarray(T_world_node)
    return (T[nxt, :3, 3] - T[prev, :3, 3]) / span


def node_velocities(T_world_node: FloatArray, stamps_s: FloatArray) -> FloatArray:
    """(n, 3) each node's velocity (m/s, world frame): the motion between its neighbours in
    time divided by their time difference (central; one-sided at the ends; 0 where the
    neighbours share a stamp or there is one node)."""
    T = np.asarray(T_world_node, dtype=float)
    t = np.asarray(stamps_s, dtype=float)
    n = t.size
    v = np.zeros((n, 3))
    if n < 2:
        return v
    order = np.argsort(t, kind='stable')
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n)
    prev = order[np.maximum(pos - 1, 0)]
    nxt = order[np.minimum(pos + 1, n - 1)]
    span = t[nxt] - t[prev]
    ok = span > 0
    v[ok] = (T[nxt[ok], :3, 3] - T[prev[ok], :3, 3]) / span[ok, None]
    return v


def fix_jacobians(obs: FixObservations, params: Sequence[FixOffsetAxis | TimeOffset],
                  velocity: FloatArray) -> FloatArray:
    """(k, 6, p) ``E = de/dc`` of every fix for the parameters ``params`` (one column each;
    the caller zeroes the fixes of other sources). ``velocity`` (k, 3): each fix's node
    velocity."""
    E = np.zeros((len(obs), 6, len(params)))
    for a, par in enumerate(params):
        E[:, :, a] = par.jacobian(velocity)
    return E


def fix_shift(E: FloatArray, values: FloatArray) -> FloatArray:
    """(k, 3) how much each fix's measured position moves to the corrected one: ``-E[:, :3] c``
    (module doc), ``E`` (k, 6, p) from :func:`fix_jacobians`, ``values`` (p,) the parameters
    (0 for the fixes of other sources via ``E``)."""
    return -(E[:, :3, :] @ np.asarray(values, dtype=float))


def fix_priors(obs: FixObservations, T_world_node: FloatArray, node_ids: IntArray,
               shift: FloatArray | None = None) -> list[GaussianPrior]:
    """The weighted parameters of the fixes at the poses ``T_world_node`` (network order,
    ``node_ids``), each fix's measured position moved by ``shift`` (k, 3) (None: as measured):
    one :class:`~ga_ros.core.solver.GaussianPrior` over every node with a fix, each node's
    fixes combined by :func:`~ga_ros.core.fixes.node_prior`, as the aligner's fix book does.
    No fixes: no prior."""
    if not len(obs):
        return []
    rows = obs.rows(node_ids)
    terms = list(obs.terms)
    if shift is not None:
        terms = [t if not np.any(d) else replace(t, fix=replace(
            t.fix, T_map_sensor=_moved(t.fix.T_map_sensor, d))) for t, d in zip(terms, shift)]
    keys = np.unique(rows)
    means = np.zeros((keys.size, 4, 4))
    infos = np.zeros((keys.size, 6, 6))
    for a, r in enumerate(keys):
        fs = np.nonzero(rows == r)[0]
        means[a], infos[a] = node_prior(T_world_node[r], [terms[f] for f in fs],
                                        [obs.information[f] for f in fs])
    return [GaussianPrior(np.asarray(node_ids)[keys], means, sla.block_diag(*infos))]


def _moved(T: FloatArray, d: FloatArray) -> FloatArray:
    out = np.array(T, dtype=float)
    out[:3, 3] += d
    return out


def fix_misclosures(obs: FixObservations, T_world_node: FloatArray, rows: IntArray,
                    shift: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(e (k, 6), A (k, 6, 6))``: each fix's map-frame misclosure against its corrected
    position (:func:`~ga_ros.core.fixes.sensor_misclosure` with the measured position moved by
    ``shift``) and its Jacobian with respect to its node's right perturbation
    (:func:`~ga_ros.core.fixes.sensor_jacobian`), at the poses ``T_world_node``."""
    k = len(obs)
    e = np.zeros((k, 6))
    A = np.zeros((k, 6, 6))
    for i, t in enumerate(obs.terms):
        T = T_world_node[rows[i]]
        e[i] = sensor_misclosure(T, t.T_node_sensor, t.fix)
        e[i, :3] -= shift[i]
        A[i] = sensor_jacobian(T, t.T_node_sensor)
    return e, A
