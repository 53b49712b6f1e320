"""Each relative source's own noise, from how much rougher its motions are than another
source's measuring the same motions (Grubbs' estimator of two instruments' precisions).

Why: two sources that measure the same keyframe motions and nothing else (two odometry streams,
two SLAM systems' outputs) give an adjustment whose residuals are their differences only. The
differences show the *sum* of the two sources' variances, never how it splits: every split
fits the residuals equally well (the variance-component estimation,
:mod:`ga_ros.core.quality.variance_components`, keeps whatever ratio it starts from). Grubbs
(1948) separates the two by treating the true motions as varying and the two sources' errors as
independent of each other and of the motion: ``var(z_a) = var(t) + s_a``, ``cov(z_a, z_b) =
var(t)``, so ``s_a = E[z_a (z_a - z_b)]``.

Here on the change between consecutive motions, so that the true motion varies little: for two
consecutive connections ``c1 = (i, j)``, ``c2 = (j, k)`` both measured by sources ``a`` and
``b``, with ``u_a = z_a(c2) - z_a(c1)`` (``[t, rotvec]``, the first-order change of motion) and
``W_a = (S_a(c1) + S_a(c2))^-1`` from ``a``'s stated covariances,

    ``g_a = u_a' W_a (u_a - u_b)``,   ``E[g_a] = 6 s_a``

(``s_a`` the variance factor of ``a``: true covariance / stated, the errors white and
independent of ``b``'s).

The motions are compared as rates: where the keyframes' stamps are known (``stamp_ns`` of the
measurements, the stamp of a motion's ``dst``; the earlier node's from the motion ending there)
each motion is its SE(3) logarithm divided by its duration, ``z = log(T) / dt`` with
``S / dt^2``. A source's keyframes chosen by distance come every ``1 m + one sample`` or so, so
consecutive motions differ by up to a sample's motion while their rates (at a smooth speed and
turn rate) do not: that difference is the true change ``Δt`` of the terms below, which adds the
other source's noise to a source's ``g`` (``Δt' W δ_b``) and biases it. On two SLAM streams of
20 Hz and 10 Hz (keyframes every 1 m of the first) the rates bring the better source's factor
from 39 % to 26 % spread over 40 runs, its mean from -11 % to -5 % of the truth (through the
replay, 24 runs: 33 % to 22 %; docs/benchmarks.md). ``dt`` is the same for
both sources (their stamps are the keyframes'), so the true motion still cancels in
``u_a - u_b``; without stamps (0, or a motion whose start was not seen) the motion is used as
``[t, rotvec]``. Per source ``k`` the terms against every other source give
``f_k = sum g / (6 n)`` over its ``n`` terms; its degrees of freedom are estimated from the
terms' own spread, ``nu_k = 2 n mean(g)^2 / (var(g) + 2 cov(g_i, g_i-1))`` (the term
``Δt' W (δ_a - δ_b)`` of a changing true motion and the other source's noise make it less
certain than ``6 n``; consecutive terms share a motion, hence the lag-1 covariance).

The estimate is a *start* for the variance-component estimation, never a replacement: where the
network determines each source's factor (a third source, loop closures, fixes) the estimation
converges to its own fixed point from any start; where it determines only the sum, its
iteration keeps the ratio of the start, so the sources are split as their consistency says
and scaled to what the residuals say. Its assumptions are stated, not tested: errors
independent between the two sources (two SLAM systems on the same camera share errors, which
makes both look better) and white in time (a source whose errors are smoothed looks better
than it is).

Memory is bounded: a connection's measurements are kept while newer connections arrive, the
latest ``keep`` node pairs; a source measuring a connection later than that adds no term.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement

#: scalar degrees of freedom of one term (the 6 components of a change of motion)
TERM_DOF = 6


class SourceConsistency:
    """The terms ``g`` of the module docstring, per source, fed measurement by measurement.

    Only consecutive motions with a named source take part (:attr:`Measurement.source`).

    Parameters
    ----------
    keep : node pairs whose measurements are kept to pair with later ones.
    """

    def __init__(self, keep: int = 64) -> None:
        self.keep = int(keep)
        self.names: list[str] = []
        # per source: number of terms, sum of g, sum of g^2, sum of g times the previous term
        # of the same pair of sources (the lag-1 products: consecutive terms share a motion)
        self._n = np.zeros(0)
        self._dof = np.zeros(0)
        self._sum = np.zeros(0)
        self._sum2 = np.zeros(0)
        self._lag = np.zeros(0)
        self._last: dict[tuple[str, str], float] = {}
        self._recent: OrderedDict[tuple[int, int], dict[str, tuple[FloatArray, FloatArray]]] = (
            OrderedDict())
        self._stamp: dict[tuple[int, int], int] = {}  # kept pair -> stamp of its dst (ns)
        self._ending: dict[int, tuple[int, int]] = {}   # node -> the kept pair ending there
        self._starting: dict[int, tuple[int, int]] = {}  # node -> the kept pair starting there

    def _index(self, name: str) -> int:
        if name not in self.names:
            self.names.append(name)
            self._n, self._dof, self._sum, self._sum2, self._lag = (
                np.append(a, 0.0) for a in (self._n, self._dof, self._sum, self._sum2,
                                            self._lag))
        return self.names.index(name)

    def add(self, m: Measurement) -> None:
        """Take one measurement (ignored unless a consecutive motion with a source)."""
        if m.kind != 'consecutive' or not m.source:
            return
        key = (int(m.src_id), int(m.dst_id))
        if key not in self._recent:
            self._recent[key] = {}
            self._ending[key[1]] = key
            self._starting[key[0]] = key
            while len(self._recent) > self.keep:
                old, _ = self._recent.popitem(last=False)
                self._stamp.pop(old, None)
                if self._ending.get(old[1]) == old:
                    del self._ending[old[1]]
                if self._starting.get(old[0]) == old:
                    del self._starting[old[0]]
        here = self._recent[key]
        if int(m.stamp_ns) > 0:
            self._stamp.setdefault(key, int(m.stamp_ns))
        s = str(m.source)
        if s in here:
            return  # a repeat of the same source's motion: its first stands
        self._index(s)
        here[s] = (np.asarray(m.z, float).reshape(6), np.asarray(m.cov, float).reshape(6, 6))
        for nkey in (self._ending.get(key[0]), self._starting.get(key[1])):
            there = self._recent.get(nkey) if nkey is not None else None
            if not there or s not in there:
                continue
            first, second = (there, here) if nkey[1] == key[0] else (here, there)
            k1, k2 = (nkey, key) if nkey[1] == key[0] else (key, nkey)
            rates = self._durations(k1, k2)
            for t in here:
                if t != s and t in there:
                    self._term(s, t, first, second, rates)
                    self._term(t, s, first, second, rates)

    def _durations(self, k1: tuple[int, int], k2: tuple[int, int]
                   ) -> tuple[float, float] | None:
        """Durations (s) of two consecutive kept pairs, None unless all three stamps are known
        and increasing."""
        before = self._ending.get(k1[0])
        t0 = self._stamp.get(before) if before is not None else None
        t1, t2 = self._stamp.get(k1), self._stamp.get(k2)
        if t0 is None or t1 is None or t2 is None or not t0 < t1 < t2:
            return None
        return (t1 - t0) * 1e-9, (t2 - t1) * 1e-9

    def _term(self, a: str, b: str, first: dict, second: dict,
              durations: tuple[float, float] | None) -> None:
        za1, Sa1 = first[a]
        za2, Sa2 = second[a]
        zb1, zb2 = first[b][0], second[b][0]
        if durations is not None:
            # rates: the SE(3) logarithm per second, its covariance scaled alike (docstring)
            d1, d2 = durations
            za1, za2, zb1, zb2 = _log(np.stack([za1, za2, zb1, zb2])) / [[d1], [d2], [d1], [d2]]
            Sa1, Sa2 = Sa1 / d1**2, Sa2 / d2**2
        u_a, u_b = za2 - za1, zb2 - zb1
        S = Sa1 + Sa2
        # the direction of travel left out: keyframes chosen by distance on one source make
        # its error along it correlated with the true motion (module docstring)
        along = za1[:3] + za2[:3] + zb1[:3] + zb2[:3]
        norm = float(np.linalg.norm(along))
        dof = TERM_DOF
        if norm > 0.0:
            v = np.zeros(6)
            v[:3] = along / norm
            B = np.linalg.qr(np.column_stack([v, np.eye(6)]))[0][:, 1:]
            u_a, u_b, S = B.T @ u_a, B.T @ u_b, B.T @ S @ B
            dof = TERM_DOF - 1
        try:
            g = float(u_a @ np.linalg.solve(S, u_a - u_b))
        except np.linalg.LinAlgError:
            return
        if not np.isfinite(g):
            return
        k = self.names.index(a)
        self._dof[k] += dof
        self._n[k] += 1.0
        self._sum[k] += g
        self._sum2[k] += g * g
        self._lag[k] += g * self._last.get((a, b), 0.0)
        self._last[(a, b)] = g

    # -------------------------------------------------------------------- output
    def estimates(self) -> dict[str, tuple[float, float]]:
        """Per source with terms: ``(f_k, nu_k)``, its factor (``sum g / (6 n)``, may be <= 0
        by chance when the source is far better than the other) and degrees of freedom."""
        out = {}
        for k, name in enumerate(self.names):
            n = self._n[k]
            if n < 2:
                continue
            mean = self._sum[k] / n
            var = max(self._sum2[k] / n - mean * mean, 1e-300) * n / (n - 1)
            lag1 = self._lag[k] / (n - 1) - mean * mean
            # the variance of the mean with the lag-1 correlation (never below a third of
            # the independent terms')
            var_sum = max(var + 2.0 * lag1, var / 3.0)
            out[name] = (float(self._sum[k] / self._dof[k]),
                         float(2.0 * n * mean * mean / var_sum))
        return out

    def split(self, min_terms: int = 10, bounds: tuple[float, float] = (1e-3, 1e3)
              ) -> dict[str, tuple[float, float]]:
        """``{source: (factor, dof)}`` of the sources with at least ``min_terms`` terms, the
        factor clipped to ``bounds`` (the ``split`` of
        :func:`~ga_ros.core.quality.variance_components.solve_with_variance_components`).

        A source far better than the one it is compared with has few degrees of freedom (its
        terms carry the other's noise) but is kept: leaving it out would leave the sum's split
        to the adjustment, which cannot make it, while any small factor weights it as the
        better source it is.
        """
        lo, hi = bounds
        return {name: (float(np.clip(f, lo, hi)), nu)
                for name, (f, nu) in self.estimates().items()
                if self._n[self.names.index(name)] >= min_terms}

    # ----------------------------------------------------------------- persistence
    def arrays(self) -> dict:
        """Plain arrays (a snapshot): source names; per source ``n``, ``dof``, ``sum``, ``sum2``,
        ``lag``; the last term of each pair of sources (``last_pair`` (q, 2) source indices,
        ``last_value``); the kept connections in their order (``pairs`` (p, 2) node ids,
        ``pair_source`` source index, ``z`` (p, 6), ``cov`` (p, 6, 6), ``pair_stamp`` (p,) the
        stamp of the pair's ``dst`` in ns, 0 when unknown)."""
        pairs, src, z, cov, stamps = [], [], [], [], []
        for key, here in self._recent.items():
            for s, (zz, cc) in here.items():
                pairs.append(key)
                stamps.append(self._stamp.get(key, 0))
                src.append(self.names.index(s))
                z.append(zz)
                cov.append(cc)
        last = [(self.names.index(a), self.names.index(b), g)
                for (a, b), g in self._last.items()]
        return {'names': list(self.names), 'n': self._n.copy(), 'dof': self._dof.copy(),
                'sum': self._sum.copy(),
                'sum2': self._sum2.copy(), 'lag': self._lag.copy(),
                'last_pair': np.asarray([x[:2] for x in last], np.int64).reshape(-1, 2),
                'last_value': np.asarray([x[2] for x in last], float),
                'pairs': np.asarray(pairs, np.int64).reshape(-1, 2),
                'pair_source': np.asarray(src, np.int64),
                'z': np.asarray(z, float).reshape(-1, 6),
                'cov': np.asarray(cov, float).reshape(-1, 6, 6),
                'pair_stamp': np.asarray(stamps, np.int64)}

    @classmethod
    def from_arrays(cls, values: dict, keep: int = 64) -> SourceConsistency:
        """The book of :meth:`arrays`."""
        book = cls(keep)
        book.names = [str(s) for s in values['names']]
        book._n = np.asarray(values['n'], float).copy()
        book._dof = np.asarray(values['dof'], float).copy()
        book._sum = np.asarray(values['sum'], float).copy()
        book._sum2 = np.asarray(values['sum2'], float).copy()
        book._lag = np.asarray(values['lag'], float).copy()
        for (a, b), g in zip(np.asarray(values['last_pair']).reshape(-1, 2).tolist(),
                             np.asarray(values['last_value'], float).tolist()):
            book._last[(book.names[int(a)], book.names[int(b)])] = float(g)
        pairs = np.asarray(values['pairs']).reshape(-1, 2).tolist()
        stamps = np.asarray(values.get('pair_stamp', np.zeros(len(pairs))), np.int64).tolist()
        for (a, b), k, zz, cc, st in zip(pairs, np.asarray(values['pair_source']).tolist(),
                                         np.asarray(values['z'], float).reshape(-1, 6),
                                         np.asarray(values['cov'], float).reshape(-1, 6, 6),
                                         stamps):
            key = (int(a), int(b))
            if st > 0:
                book._stamp.setdefault(key, int(st))
            if key not in book._recent:
                book._recent[key] = {}
                book._ending[key[1]] = key
                book._starting[key[0]] = key
            book._recent[key][book.names[int(k)]] = (zz.copy(), cc.copy())
        return book


def _log(z: FloatArray) -> FloatArray:
    """SE(3) logarithms ``[rho, w]`` of motions ``z = [t, rotvec]`` ``(n, 6)``: ``rho =
    J_l(w)^-1 t`` by its series to second order, ``t - w x t / 2 + w x (w x t) / 12`` (the
    next term is ``|w|^4 |t| / 720``: 1e-5 of ``t`` at a keyframe's 15 deg)."""
    t, w = z[:, :3], z[:, 3:]
    wt = _cross(w, t)
    return np.concatenate([t - 0.5 * wt + _cross(w, wt) / 12.0, w], axis=1)


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross products of two ``(n, 3)`` arrays."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def consistency_split(measurements: Iterable[Measurement], min_terms: int = 10
                      ) -> dict[str, tuple[float, float]]:
    """The ``split`` of :func:`~ga_ros.core.quality.variance_components.\
solve_with_variance_components` from a whole survey's measurements (all kept)."""
    ms = list(measurements)
    book = SourceConsistency(keep=max(64, len(ms)))
    for m in ms:
        book.add(m)
    return book.split(min_terms)
