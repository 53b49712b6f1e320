"""Absolute fixes (GNSS, AMCL, USBL, motion capture) as weighted parameters (paper Sec. III-E).

An :class:`AbsoluteFix` is a measured pose (or position) of a *sensor* in the map frame with a
6x6 covariance ``[x y z rx ry rz]`` (REP 103/145: position errors and rotation errors about the
axes of the map frame). Dimensions nobody measured (an AMCL pose's z, roll and pitch, a GNSS
fix's orientation) carry zero information: :func:`fix_information` reads REP 145's markers
(a variance ``-1``, NaN or one at least ``unknown_variance``) as unknown.

A fix at a stamp between two keyframes is tied to the keyframe graph by the odometry
(:class:`FixTerm`): the keyframe ``k`` at or before the stamp and the offset
``T_k_sensor = T_odom(k)^-1 T_odom(t) T_base_sensor`` (odometry interpolated at ``t``, the
sensor's lever arm ``T_base_sensor``), so no keyframe is snapped to a stamp it does not have. The
fix then observes the point ``p_k + R_k o`` (``o`` the offset's translation) and, for a full
pose, the rotation ``R_k R_o``.

The weighted parameter of node ``k`` (:meth:`FixBook.prior`) is a
:class:`~ga_ros.core.solver.GaussianPrior` on that node: every fix on ``k`` is written as a
quadratic in the map-frame perturbation ``delta = [dp, dtheta]`` of the observed sensor pose at
the node's current estimate, the fixes' quadratics are summed (information ``L = sum L_i``,
mean ``mu = L^+ sum L_i e_i`` with the misclosures ``e_i``), and the result is expressed in the
solver's residual ``[R_m' (p - p_m), log(R_m' R)]`` with ``T_m = (exp(mu_r) R_k, p_k + mu_p)``
and information ``B' L B``, ``B = blkdiag(R_m, R_m)``. The mean is recomputed from the current
estimate of ``R_k`` at every update: exact for ``o = 0``; with a lever arm the residual's
dependence on ``R_k`` through ``R_k o`` is held at the update's starting estimate, an error of
``|o|`` times the heading correction within one update (second order in the correction).

Gating (:meth:`FixBook.gate`): after each window adjustment, every fix of an adjusted node is
tested by the chi-square test of its Mahalanobis misclosure (degrees of freedom: its known
dimensions) at the configured probability: a fix in the adjustment against its residual
covariance ``C - J Q J'``, an excluded one against the predicted ``C + J Q J'`` (``Q`` the
node's marginal covariance, ``J`` the Jacobian of the sensor pose), both scaled by the
adjustment's variance factor when it exceeds 1 (Pope's tau test: the odometry's drift is
often larger than its covariance says, and then sparse fixes would all fail the test).
Failing fixes are excluded (``fix_outlier``) and re-tested at every later adjustment of their
node, like the window's connections, so a good fix excluded next to a gross one comes back.
One fix is excluded per adjustment round (the worst), since a gross fix drags the residuals of
its neighbours too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.chi2 import chi2_quantile
from ga_ros.core.solver import GaussianPrior, SolveResult
from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3
from ga_ros.runtime import lazy_import

sla = lazy_import('scipy.linalg')  # only some functions need it (start-up)

#: Variances at or above this (m^2 / rad^2) mark an unknown dimension (REP 145 habit: 1e6..1e12).
UNKNOWN_VARIANCE = 1e6
#: Datum modes of the aligner: the first node held fixed, or the fixes' frame (module doc).
DATUMS = ('first_node', 'fixes')


@dataclass(frozen=True)
class AbsoluteFix:
    """One measured pose of a sensor in the map frame.

    Attributes
    ----------
    stamp_ns : acquisition time (ns).
    T_map_sensor : (4, 4) measured pose; for a position-only fix the rotation is ignored
        (identity by convention).
    information : (6, 6) inverse covariance ``[x y z rx ry rz]`` in the map frame (position
        errors along the map axes, rotation errors about them: left perturbation
        ``exp(dtheta) R``), zero in unknown dimensions (:func:`fix_information`).
    source : name of the input that made it (``fix0``, ``amcl0``, ...).
    """

    stamp_ns: int
    T_map_sensor: FloatArray
    information: FloatArray
    source: str = 'fix0'

    def __post_init__(self) -> None:
        T = np.asarray(self.T_map_sensor, dtype=float)
        L = np.asarray(self.information, dtype=float)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError(f'{self.source}: a fix pose must be a finite 4x4 matrix',
                             reason='non_finite')
        if L.shape != (6, 6) or not np.isfinite(L).all() or not np.allclose(L, L.T, atol=1e-9 * (
                1.0 + np.abs(L).max())):
            raise InputError(f'{self.source}: a fix information must be a finite symmetric 6x6 '
                             'matrix', reason='bad_covariance')
        if not np.any(np.diag(L) > 0):
            raise InputError(f'{self.source}: the fix has no known dimension (every variance '
                             'unknown)', reason='bad_covariance')
        object.__setattr__(self, 'T_map_sensor', T)
        object.__setattr__(self, 'information', 0.5 * (L + L.T))

    @property
    def known(self) -> np.ndarray:
        """(6,) bool: the dimensions the fix measures (non-zero information)."""
        return np.diag(self.information) > 0

    @staticmethod
    def from_covariance(stamp_ns: int, T_map_sensor: FloatArray, cov: FloatArray,
                        source: str = 'fix0', unknown_variance: float = UNKNOWN_VARIANCE
                        ) -> AbsoluteFix:
        """A fix from a REP 145 covariance (unknown rows marked, see :func:`fix_information`)."""
        return AbsoluteFix(int(stamp_ns), T_map_sensor, fix_information(cov, unknown_variance),
                           source)


def fix_information(cov: FloatArray, unknown_variance: float = UNKNOWN_VARIANCE) -> FloatArray:
    """Information (6, 6) of a fix covariance ``[x y z rx ry rz]`` with unknown dimensions.

    A dimension is unknown when its variance is NaN, negative (``-1``), infinite or at least
    ``unknown_variance``; its row and column of the result are zero (no information). The known
    block must be symmetric positive definite.

    Raises
    ------
    InputError
        A known block that is not positive definite (e.g. a zero variance: substitute the
        default first), or no known dimension (``reason='bad_covariance'``).
    """
    C = np.asarray(cov, dtype=float).reshape(6, 6)
    d = np.diag(C)
    known = np.isfinite(d) & (d > 0) & (d < unknown_variance)
    zero = np.isfinite(d) & (d == 0)
    if zero.any() or not known.any():
        raise InputError('a fix covariance has a zero variance or no known dimension: set a '
                         'default (default_sigma_m / default_sigma_rad)', reason='bad_covariance')
    K = C[np.ix_(known, known)]
    if not np.isfinite(K).all():
        raise InputError('a fix covariance has non-finite entries in its known block',
                         reason='bad_covariance')
    K = 0.5 * (K + K.T)
    try:
        Lc = np.linalg.cholesky(K)
    except np.linalg.LinAlgError:
        raise InputError('a fix covariance is not positive definite in its known dimensions',
                         reason='bad_covariance') from None
    Linv = np.linalg.inv(Lc)
    L = np.zeros((6, 6))
    L[np.ix_(known, known)] = Linv.T @ Linv
    return 0.5 * (L + L.T)


@dataclass(frozen=True)
class FixTerm:
    """A fix tied to a keyframe (node) by the odometry (module doc).

    Attributes
    ----------
    node_id : the keyframe ``k`` it is attached to.
    T_node_sensor : (4, 4) offset from the keyframe to the sensor at the fix's stamp.
    fix : the fix; its information already includes the odometry's uncertainty over the
        offset (:func:`offset_information`).
    """

    node_id: int
    T_node_sensor: FloatArray
    fix: AbsoluteFix


def offset_information(fix: AbsoluteFix, T_map_node: FloatArray, C_offset: FloatArray
                       ) -> FloatArray:
    """The fix's information with the offset's covariance added in its known dimensions.

    Parameters
    ----------
    fix : the fix.
    T_map_node : (4, 4) the node's pose (its rotation carries ``C_offset`` to the map axes).
    C_offset : (6, 6) covariance of the odometry offset ``T_node_sensor`` (right perturbation,
        node frame).

    Returns
    -------
    (6, 6) information, zero in the fix's unknown dimensions as before.
    """
    known = fix.known
    R = np.asarray(T_map_node, float)[:3, :3]
    B = np.zeros((6, 6))
    B[:3, :3] = B[3:, 3:] = R
    C_map = B @ np.asarray(C_offset, float) @ B.T
    Lk = fix.information[np.ix_(known, known)]
    Ck = np.linalg.inv(Lk) + C_map[np.ix_(known, known)]
    L = np.zeros((6, 6))
    L[np.ix_(known, known)] = np.linalg.inv(0.5 * (Ck + Ck.T))
    return 0.5 * (L + L.T)


def sensor_jacobian(T_map_node: FloatArray, T_node_sensor: FloatArray) -> FloatArray:
    """(6, 6) Jacobian of the map-frame sensor error ``[dp, dtheta]`` (left) with respect to the
    node's right perturbation ``T exp([d_p, d_w])``: ``[[R, -R [o]x], [0, R]]``."""
    R = np.asarray(T_map_node, float)[:3, :3]
    o = np.asarray(T_node_sensor, float)[:3, 3]
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[:3, 3:] = -R @ so3.hat(o)
    J[3:, 3:] = R
    return J


def sensor_misclosure(T_map_node: FloatArray, T_node_sensor: FloatArray, fix: AbsoluteFix
                      ) -> FloatArray:
    """(6,) map-frame error of the predicted sensor pose against the fix: ``[p_s - p_fix,
    log(R_s R_fix')]`` (rotation zero for a fix without known rotation)."""
    T_s = np.asarray(T_map_node, float) @ np.asarray(T_node_sensor, float)
    e = np.zeros(6)
    e[:3] = T_s[:3, 3] - fix.T_map_sensor[:3, 3]
    if fix.known[3:].any():
        e[3:] = so3.log(T_s[:3, :3] @ fix.T_map_sensor[:3, :3].T)
    return e


def node_prior(T_map_node: FloatArray, terms: list[FixTerm], information: list[FloatArray]
               ) -> tuple[FloatArray, FloatArray]:
    """Mean (4, 4) and information (6, 6) of the weighted parameter of one node from its fixes
    (module doc), in the residual of :func:`ga_ros.core.models.prior_residual`.

    Parameters
    ----------
    T_map_node : (4, 4) the node's current estimate (the linearisation point).
    terms : its fixes.
    information : each fix's information (map frame), e.g. with the offset's covariance added.
    """
    L = np.zeros((6, 6))
    b = np.zeros(6)
    for term, Li in zip(terms, information):
        e = sensor_misclosure(T_map_node, term.T_node_sensor, term.fix)
        L += Li
        b += Li @ e
    mu = -np.linalg.lstsq(L, b, rcond=1e-12)[0]
    T = np.asarray(T_map_node, float)
    T_m = np.eye(4)
    T_m[:3, :3] = so3.exp(mu[3:]) @ T[:3, :3]
    T_m[:3, 3] = T[:3, 3] + mu[:3]
    B = np.zeros((6, 6))
    B[:3, :3] = B[3:, 3:] = T_m[:3, :3]
    H = B.T @ L @ B
    return T_m, 0.5 * (H + H.T)


@dataclass
class FixStats:
    """Counters of a :class:`FixBook`.

    Attributes
    ----------
    added : fixes accepted into the book.
    rejected : refused fixes by reason (``fix_no_keyframe``, ``fix_frozen_node``,
        ``fix_bad_covariance``, ...).
    outliers : fixes currently excluded by the gate (``fix_outlier``).
    readmitted : exclusions undone by a later test.
    """

    added: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    outliers: int = 0
    readmitted: int = 0


class FixBook:
    """The fixes of an aligner's nodes (state declared here, not in the aligner).

    Parameters
    ----------
    gate_prob : chi-square probability of the gate (0 disables it).
    """

    def __init__(self, gate_prob: float = 0.9999) -> None:
        if not 0.0 <= gate_prob < 1.0:
            raise InputError(f'fix_gate_prob must be in [0, 1), got {gate_prob}')
        self.gate_prob = float(gate_prob)
        self.terms: list[FixTerm] = []
        self.info: list[FloatArray] = []  # information with the offset's covariance
        self.rows: list[int] = []  # aligner node row of each term
        self._of_row: dict[int, list[int]] = {}  # node row -> its fixes (increasing index)
        self.status = np.zeros(0, dtype=np.int8)  # 0 used, 2 excluded (replaced, never in place)
        self.gated = np.zeros(0, dtype=bool)  # never gated (the gauge prior)
        self.stats = FixStats()
        # the variance factor of each fix index (online variance components applied, by
        # source): its information is divided by it in the priors and the gate; None: 1
        self.info_factors: Callable[[IntArray], FloatArray] | None = None

    def __len__(self) -> int:
        return len(self.terms)

    def reject(self, reason: str) -> None:
        """Count a refused fix."""
        self.stats.rejected[reason] = self.stats.rejected.get(reason, 0) + 1

    def add(self, row: int, term: FixTerm, information: FloatArray, gated: bool = True) -> None:
        """Store a fix of node row ``row`` with its (map-frame) information."""
        self.terms.append(term)
        self.info.append(np.asarray(information, float))
        self._of_row.setdefault(int(row), []).append(len(self.rows))
        self.rows.append(int(row))
        self.status = np.append(self.status, np.int8(0))
        self.gated = np.append(self.gated, bool(gated))
        if gated:
            self.stats.added += 1

    def _by_row(self, rows: IntArray, active: bool = True, count: int | None = None,
                gauge: bool = True) -> dict[int, list[int]]:
        """The (used, if ``active``) fixes of the node ``rows`` among the first ``count``, by
        row (each list in increasing fix index; the gauge prior only if ``gauge``; the rows in
        no particular order): a look-up per row asked for or per row with a fix, whichever are
        fewer."""
        status = self.status  # a fix added meanwhile (another thread) appends its status last
        n = min(len(self.rows), status.size, len(self.info))
        n = n if count is None else min(n, int(count))
        out: dict[int, list[int]] = {}
        asked, of_row = set(np.asarray(rows, np.int64).tolist()), self._of_row
        # the rows asked for that have a fix, by the shorter scan (a window's rows mostly have
        # none; a long survey's book has more rows than a window)
        hits = ([r for r in of_row if r in asked] if len(of_row) < len(asked)
                else [r for r in asked if r in of_row])
        for r in hits:
            fs = [f for f in of_row[r] if f < n and (not active or status[f] == 0)
                  and (gauge or self.gated[f])]
            if fs:
                out[r] = fs
        return out

    def of_rows(self, rows: IntArray) -> list[int]:
        """Indices (increasing) of every fix (used or excluded) of the node ``rows``."""
        return sorted(f for r in set(np.asarray(rows, np.int64).tolist())
                      for f in self._of_row.get(r, ()))

    def has_fix(self, rows: IntArray) -> BoolArray:
        """``(k,)`` whether each of the node ``rows`` has a fix (used or excluded)."""
        return np.array([int(r) in self._of_row for r in np.asarray(rows).tolist()], dtype=bool)

    def used(self, rows: IntArray, count: int | None = None) -> IntArray:
        """Indices (increasing) of the used (not excluded) fixes of the node rows ``rows``,
        among the first ``count`` fixes (default all)."""
        return np.array(sorted(f for fs in self._by_row(rows, count=count).values() for f in fs),
                        dtype=np.int64)

    def information_used(self, fixes: list[int]) -> list[FloatArray]:
        """The information each of ``fixes`` enters the adjustment with: its own (offset's
        covariance included) divided by its variance factor (:attr:`info_factors`)."""
        if self.info_factors is None or not fixes:
            return [self.info[f] for f in fixes]
        fac = self.info_factors(np.asarray(fixes, np.int64))
        return [self.info[f] if s == 1.0 else self.info[f] / s for f, s in zip(fixes, fac)]

    def prior_terms(self, rows: IntArray, T: FloatArray, count: int | None = None,
                    gauge: bool = True) -> tuple[IntArray, FloatArray, FloatArray]:
        """``(rows with a used fix (k,), means (k, 4, 4), informations (k, 6, 6))`` of the
        weighted parameters of the node rows ``rows`` at poses ``T`` (indexed by row), from the
        first ``count`` fixes (default all), the gauge prior's only if ``gauge``; each fix
        weighted as :meth:`information_used` says."""
        by_row = self._by_row(rows, count=count, gauge=gauge)
        keys = sorted(by_row)
        means = np.zeros((len(keys), 4, 4))
        infos = np.zeros((len(keys), 6, 6))
        for a, r in enumerate(keys):
            fs = by_row[r]
            means[a], infos[a] = node_prior(T[r], [self.terms[f] for f in fs],
                                            self.information_used(fs))
        return np.asarray(keys, np.int64), means, infos

    def gate(self, rows: IntArray, T: FloatArray, Q: FloatArray, excluded_now: set[int],
             variance_factor: float = 1.0) -> bool:
        """Test the fixes of the adjusted node rows ``rows`` (poses ``T``, marginal covariances
        ``Q`` (k, 6, 6), both in the order of ``rows``) and exclude / re-admit them (module
        doc): the worst failing fix in the adjustment is excluded (one per call: a gross fix
        drags its neighbours' residuals too), fixes excluded earlier that pass are re-admitted;
        a fix excluded since the update began (``excluded_now``, updated here) is not re-tested
        in it, so the gate cannot oscillate. ``variance_factor``: the adjustment's a-posteriori
        ``sigma0^2``; when above 1 the covariances are scaled by it (Pope's tau test), so a
        model whose odometry covariance is too small (a drift it does not describe) does not
        reject every sparse fix. Returns whether any status changed."""
        if self.gate_prob <= 0 or not self.terms:
            return False
        pos = {int(r): a for a, r in enumerate(np.asarray(rows).tolist())}
        status = self.status.copy()
        worst, worst_ratio = -1, 1.0
        scale = max(1.0, float(variance_factor)) if np.isfinite(variance_factor) else 1.0
        for f in self.of_rows(rows):  # in fix order, as a scan of the whole book would
            a = pos[self.rows[f]]
            if not self.gated[f] or f in excluded_now:
                continue
            term = self.terms[f]
            known = term.fix.known
            e = sensor_misclosure(T[a], term.T_node_sensor, term.fix)[known]
            J = sensor_jacobian(T[a], term.T_node_sensor)
            P = (J @ Q[a] @ J.T)[np.ix_(known, known)]
            C = np.linalg.inv(self.information_used([f])[0][np.ix_(known, known)])
            S = C - P if self.status[f] == 0 else C + P
            # the residual covariance of a fix in the adjustment is positive semidefinite in
            # exact arithmetic; floor it at 1 % of the fix's own against round-off
            w, V = np.linalg.eigh(0.5 * (S + S.T))
            w = np.maximum(w, 1e-2 * np.linalg.eigvalsh(C).min())
            ratio = float(e @ (V @ ((V.T @ e) / w))) / (
                scale * chi2_quantile(int(known.sum()), self.gate_prob))
            if self.status[f] == 2 and ratio <= 1.0:
                status[f] = 0
            elif self.status[f] == 0 and ratio > worst_ratio:
                worst, worst_ratio = f, ratio
        if worst >= 0:
            status[worst] = 2
            excluded_now.add(worst)
        changed = not np.array_equal(status, self.status)
        if changed:
            self.stats.readmitted += int(((self.status == 2) & (status == 0)).sum())
            self.status = status
            self.stats.outliers = int((status == 2).sum())
        return changed

    def arrays(self) -> tuple[dict, dict[str, np.ndarray]]:
        """``(meta, arrays)`` of the book for a state file (:meth:`of_arrays` reads them)."""
        k = len(self.terms)
        meta = {'sources': [t.fix.source for t in self.terms],
                'stats': {'added': self.stats.added, 'rejected': dict(self.stats.rejected),
                          'outliers': self.stats.outliers,
                          'readmitted': self.stats.readmitted}}
        arrays = {
            'fix_rows': np.asarray(self.rows, np.int64).reshape(k),
            'fix_node_ids': np.array([t.node_id for t in self.terms], np.int64).reshape(k),
            'fix_stamps': np.array([t.fix.stamp_ns for t in self.terms], np.int64).reshape(k),
            'fix_offset': np.array([t.T_node_sensor for t in self.terms]).reshape(k, 4, 4),
            'fix_T': np.array([t.fix.T_map_sensor for t in self.terms]).reshape(k, 4, 4),
            'fix_own_info': np.array([t.fix.information for t in self.terms]).reshape(k, 6, 6),
            'fix_info': np.array(self.info).reshape(k, 6, 6),
            'fix_status': self.status.astype(np.int64), 'fix_gated': self.gated.copy()}
        return meta, arrays

    @classmethod
    def of_arrays(cls, meta: dict, arrays: dict[str, np.ndarray], gate_prob: float) -> FixBook:
        """The book written by :meth:`arrays`."""
        book = cls(gate_prob)
        sources = list(meta.get('sources', []))
        for f in range(int(np.asarray(arrays['fix_rows']).size)):
            fix = AbsoluteFix(int(arrays['fix_stamps'][f]), arrays['fix_T'][f],
                              arrays['fix_own_info'][f], str(sources[f]))
            book.terms.append(FixTerm(int(arrays['fix_node_ids'][f]),
                                      np.array(arrays['fix_offset'][f], float), fix))
            book.info.append(np.array(arrays['fix_info'][f], float))
            book._of_row.setdefault(int(arrays['fix_rows'][f]), []).append(len(book.rows))
            book.rows.append(int(arrays['fix_rows'][f]))
        book.status = np.asarray(arrays['fix_status'], np.int8).copy()
        book.gated = np.asarray(arrays['fix_gated'], bool).copy()
        st = meta.get('stats', {})
        book.stats = FixStats(int(st.get('added', 0)), dict(st.get('rejected', {})),
                              int(st.get('outliers', 0)), int(st.get('readmitted', 0)))
        return book

    @property
    def has_gauge(self) -> bool:
        """Whether the gauge prior of ``datum='fixes'`` is in the book: then no node is held
        fixed (the first node is a node like the others)."""
        return bool((~self.gated).any())

    def add_gauge(self, row: int, node_id: int, stamp_ns: int, T_world_first: FloatArray,
                  information: FloatArray) -> None:
        """The weak gauge prior of ``datum='fixes'`` on the first node (never gated)."""
        gauge = AbsoluteFix(int(stamp_ns), T_world_first, information, 'gauge')
        self.add(row, FixTerm(int(node_id), identity_offset(), gauge), gauge.information,
                 gated=False)

    def priors(self, rows: IntArray, T: FloatArray, ids: IntArray) -> list:
        """The weighted parameters of the fixes of node ``rows`` (none, one or two
        :class:`~ga_ros.core.solver.GaussianPrior`), at the poses ``T`` and with the node ids
        ``ids`` (both indexed by row): the fixes', and the gauge prior's apart, marked
        ``weak`` (a datum, not an observation: left out of the variance factor's
        redundancy)."""
        if not self.terms:
            return []
        out = []
        keys, means, infos = self.prior_terms(rows, T, gauge=False)
        if keys.size:
            out.append(GaussianPrior(np.asarray(ids)[keys], means, sla.block_diag(*infos)))
        if self.has_gauge:
            gauge = [f for f in self.used(rows) if not self.gated[f]]
            if gauge:
                r = self.rows[gauge[0]]
                T_m, H = node_prior(T[r], [self.terms[f] for f in gauge],
                                    [self.info[f] for f in gauge])
                out.append(GaussianPrior(np.asarray(ids)[[r]], T_m[None], H, weak=True))
        return out

    def gate_adjusted(self, nodes: IntArray, res: SolveResult, ids: IntArray,
                      frozen: np.ndarray, excluded_now: set[int], lock=None) -> bool:
        """:meth:`gate` after an adjustment ``res`` of the node rows ``nodes`` (in its order;
        ``ids``, ``frozen`` indexed by row): the fixes of its free, unfrozen nodes, with their
        marginal covariances (under ``lock``, if given: the factor may be shared)."""
        if not self.terms or self.gate_prob <= 0:
            return False
        with_fix = self.has_fix(nodes)
        free = np.isin(np.asarray(ids)[nodes], res.free_node_ids) & ~frozen[nodes]
        sel = np.nonzero(free & with_fix)[0]
        if sel.size == 0:
            return False
        if lock is None:
            Q = res.covariance(np.asarray(ids)[nodes[sel]])
        else:
            with lock:
                Q = res.covariance(np.asarray(ids)[nodes[sel]])
        return self.gate(nodes[sel], res.T_world_node[sel], Q, excluded_now, res.sigma0_sq)

    def state(self) -> tuple[np.ndarray, int, int]:
        """What a failed update puts back (:meth:`restore`)."""
        return self.status, self.stats.outliers, self.stats.readmitted

    def restore(self, state: tuple[np.ndarray, int, int]) -> None:
        """Put back the statuses of :meth:`state` (fixes added since stay, used)."""
        status, self.stats.outliers, self.stats.readmitted = state
        self.status[:status.size] = status


def gauge_information(sigma_m: float, sigma_tilt_rad: float, sigma_yaw_rad: float
                      ) -> FloatArray:
    """(6, 6) information of the weak gauge prior on the first node when the fixes define the
    map frame: ``diag(1/sigma_m^2 (x3), 1/sigma_tilt^2 (roll, pitch), 1/sigma_yaw^2)``."""
    s = np.array([sigma_m] * 3 + [sigma_tilt_rad] * 2 + [sigma_yaw_rad], dtype=float)
    if not (np.isfinite(s).all() and (s > 0).all()):
        raise InputError(f'gauge sigmas must be finite and > 0, got {s.tolist()}')
    return np.diag(1.0 / s ** 2)


def identity_offset() -> FloatArray:
    """(4, 4) the offset of a fix taken at its keyframe's own stamp with no lever arm."""
    return se3.identity()
