"""The connection network: nodes (sensor positions), tracks, and connections (noisy motions).

A *connection* ``(src, dst)`` is a measured motion ``T_src_dst`` (the pose of node ``dst`` in the
frame of node ``src``) stored as ``z = [t, w]``: translation ``t`` (m) and rotation vector ``w``
(rad), with a 6x6 covariance in the ROS order ``[x y z rx ry rz]``. The covariance is that of the
right perturbation ``xi`` in ``T_src_dst_true = T_src_dst_meas @ exp(xi)`` (the g2o / GTSAM / ROS
convention); for small noise it equals the covariance of ``[t, w]`` up to a rotation.

Duplicate policy: a second connection between the same two nodes (either direction) is an
independent measurement and is kept when ``duplicates='keep'`` (the default: redundancy is the
point of the method); ``'reject'`` raises :class:`NetworkError`, ``'replace'`` overwrites the
earlier one. A connection that repeats an earlier one *bit for bit* is always rejected as a
re-delivered message, since counting it twice would halve its covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.covariance import PD_TOLERANCE
from ga_ros.errors import InputError, NetworkError

DUPLICATE_POLICIES = ('keep', 'reject', 'replace')


def check_covariances(cov: FloatArray, what: str = 'covariance', rtol: float = 1e-6) -> FloatArray:
    """Validate a stack of covariance matrices ``(m, d, d)``: finite, symmetric, positive definite.

    Returns the symmetrised stack. Raises :class:`InputError` naming the first bad index.
    """
    cov = np.asarray(cov, dtype=float)
    if cov.ndim != 3 or cov.shape[1] != cov.shape[2]:
        raise InputError(f'{what}: expected shape (m, d, d), got {cov.shape}')
    bad = ~np.isfinite(cov).all(axis=(1, 2))
    if bad.any():
        raise InputError(f'{what} #{int(np.argmax(bad))} has NaN or inf entries')
    scale = np.maximum(np.abs(cov).max(axis=(1, 2)), 1e-300)
    asym = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2)) > rtol * scale
    if asym.any():
        raise InputError(f'{what} #{int(np.argmax(asym))} is not symmetric; pass (S + S.T) / 2 '
                         'if the asymmetry is round-off')
    sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    eig_min = np.linalg.eigvalsh(sym)[:, 0]
    notpd = eig_min <= PD_TOLERANCE * scale
    if notpd.any():
        k = int(np.argmax(notpd))
        raise InputError(f'{what} #{k} is not positive definite (smallest eigenvalue '
                         f'{eig_min[k]:.3g}); every observation needs a full-rank covariance')
    return sym


@dataclass(frozen=True)
class ConnectionArrays:
    """Plain arrays of ``m`` connections, by node *index* into :attr:`ConnectionNetwork.node_ids`.

    Attributes
    ----------
    src, dst : (m,) int64 node indices.
    z : (m, 6) measured motion ``[t, w]`` of ``T_src_dst`` (m, rad).
    cov : (m, 6, 6) covariance, order ``[x y z rx ry rz]``.
    """

    src: IntArray
    dst: IntArray
    z: FloatArray
    cov: FloatArray

    def __len__(self) -> int:
        return int(self.src.shape[0])


class ConnectionNetwork:
    """Nodes with track ids, and connections between them; validated on every insertion.

    Node ids are arbitrary non-negative integers (< 2**63); indices are their insertion order.
    Every method that rejects input leaves the network unchanged.
    """

    def __init__(self, duplicates: str = 'keep') -> None:
        if duplicates not in DUPLICATE_POLICIES:
            raise InputError(f'duplicates must be one of {DUPLICATE_POLICIES}, got {duplicates!r}')
        self.duplicates = duplicates
        self._ids: list[int] = []
        self._tracks: list[int] = []
        self._index: dict[int, int] = {}
        # the connections: arrays (``_cache``) after a bulk insertion, per-connection lists
        # after single ones; each built from the other only when needed (``None`` until then)
        self._src: list[int] | None = []
        self._dst: list[int] | None = []
        self._z: list[FloatArray] | None = []
        self._cov: list[FloatArray] | None = []
        # node-index pair -> connections; ``None``: to be built from the arrays when needed
        self._pairs: dict[tuple[int, int], list[int]] | None = {}
        self._cache: ConnectionArrays | None = None

    # ------------------------------------------------------------------ nodes
    @property
    def n_nodes(self) -> int:
        return len(self._ids)

    @property
    def n_connections(self) -> int:
        return len(self._cache) if self._src is None else len(self._src)

    @property
    def node_ids(self) -> IntArray:
        """(n,) node ids in index order."""
        return np.asarray(self._ids, dtype=np.int64)

    @property
    def track_ids(self) -> IntArray:
        """(n,) track id of each node, in index order."""
        return np.asarray(self._tracks, dtype=np.int64)

    def has_node(self, node_id: int) -> bool:
        return int(node_id) in self._index

    def index_of(self, node_id: int) -> int:
        """Index of a node id; :class:`NetworkError` if unknown."""
        try:
            return self._index[int(node_id)]
        except KeyError:
            raise NetworkError(f'unknown node {node_id}; add it with add_node() first') from None

    def indices_of(self, node_ids) -> IntArray:
        """Indices of several node ids; :class:`NetworkError` naming the unknown ones."""
        ids = np.asarray(node_ids, dtype=np.int64).ravel()
        get = self._index.get  # Python ints from tolist(): no NumPy scalar per look-up
        out = np.array([get(i, -1) for i in ids.tolist()], dtype=np.int64).reshape(ids.size)
        if (out < 0).any():
            missing = ids[out < 0][:10].tolist()
            raise NetworkError(f'unknown node(s) {missing}; add them with add_node() first')
        return out

    def track_of(self, node_id: int) -> int:
        return self._tracks[self.index_of(node_id)]

    def add_node(self, node_id: int, track_id: int = 0) -> int:
        """Add a node (no-op if it exists with the same track). Returns its index."""
        node_id = _check_id(node_id, 'node id')
        track_id = _check_id(track_id, 'track id')
        if node_id in self._index:
            k = self._index[node_id]
            if self._tracks[k] != track_id:
                raise NetworkError(f'node {node_id} already belongs to track {self._tracks[k]}, '
                                   f'not {track_id}')
            return k
        self._index[node_id] = len(self._ids)
        self._ids.append(node_id)
        self._tracks.append(track_id)
        return self._index[node_id]

    # ------------------------------------------------------------ connections
    def add_connection(self, src_id: int, dst_id: int, z: FloatArray, cov: FloatArray) -> int:
        """Add one connection ``T_src_dst`` (``z = [t, w]``, m and rad; ``cov`` 6x6, ROS order).

        Returns the connection index. Raises :class:`InputError` / :class:`NetworkError` and leaves
        the network unchanged on a self-loop, an unknown node, non-finite values, a covariance that
        is not symmetric positive definite, or a duplicate the policy forbids.
        """
        z = np.asarray(z, dtype=float).reshape(-1)
        if z.shape != (6,):
            raise InputError(f'motion must have 6 entries [x y z rx ry rz], got {z.shape}')
        if not np.isfinite(z).all():
            raise InputError(f'motion {src_id}->{dst_id} has NaN or inf entries')
        cov = np.asarray(cov, dtype=float)
        if cov.shape == (36,):
            cov = cov.reshape(6, 6)
        if cov.shape != (6, 6):
            raise InputError(f'covariance must be 6x6 (or 36 row-major values), got {cov.shape}')
        cov = check_covariances(cov[None], what=f'covariance of {src_id}->{dst_id}')[0]
        s, d = self.index_of(src_id), self.index_of(dst_id)
        if s == d:
            raise NetworkError(f'connection from node {src_id} to itself is meaningless')
        self._lists()
        key = (min(s, d), max(s, d))
        earlier = self._pairs.get(key, [])
        for c in earlier:
            same = np.array_equal(self._z[c], z) and np.array_equal(self._cov[c], cov)
            if self._src[c] == s and same:
                raise NetworkError(f'connection {src_id}->{dst_id} was already added with '
                                   'identical values (a re-delivered message?)')
        if earlier and self.duplicates == 'reject':
            raise NetworkError(f'nodes {src_id} and {dst_id} are already connected '
                               "(duplicates='reject')")
        if earlier and self.duplicates == 'replace':
            c = earlier[-1]
            self._src[c], self._dst[c], self._z[c], self._cov[c] = s, d, z, cov
            self._cache = None
            return c
        self._pairs.setdefault(key, []).append(len(self._src))
        self._src.append(s)
        self._dst.append(d)
        self._z.append(z)
        self._cov.append(cov)
        self._cache = None
        return len(self._src) - 1

    def add_connections(self, src_ids, dst_ids, z: FloatArray, cov: FloatArray) -> None:
        """Add many connections; all are validated first, so a bad one adds none of them.

        The first insertion into a network with the ``'keep'`` policy is stored as arrays (no
        Python object per connection); later ones go through :meth:`add_connection`'s checks
        (duplicates against the earlier connections)."""
        src_ids = np.asarray(src_ids, dtype=np.int64).ravel()
        dst_ids = np.asarray(dst_ids, dtype=np.int64).ravel()
        z = np.asarray(z, dtype=float).reshape(-1, 6)
        cov = np.asarray(cov, dtype=float).reshape(-1, 6, 6)
        m = src_ids.size
        if not (dst_ids.size == m and z.shape[0] == m and cov.shape[0] == m):
            raise InputError('src_ids, dst_ids, z and cov must have the same length')
        if not np.isfinite(z).all():
            raise InputError(f'motion #{int(np.argmax(~np.isfinite(z).all(axis=1)))} has NaN/inf')
        cov = check_covariances(cov)
        s = self.indices_of(src_ids)
        d = self.indices_of(dst_ids)
        if (s == d).any():
            k = int(np.argmax(s == d))
            raise NetworkError(f'connection #{k} from node {src_ids[k]} to itself is meaningless')
        if self.duplicates != 'keep' or self.n_connections:
            snapshot = self._snapshot()
            try:
                for k in range(m):
                    self.add_connection(src_ids[k], dst_ids[k], z[k], cov[k])
            except Exception:
                self._restore(snapshot)
                raise
            return
        # a first bulk insertion with the 'keep' policy: stored as arrays, no per-connection
        # Python objects (the duplicate bookkeeping is built if a single one follows)
        self._set_arrays(ConnectionArrays(s, d, z.copy(), cov), pairs=None)

    def _set_arrays(self, arrays: ConnectionArrays, pairs) -> None:
        """The connections become ``arrays`` (the lists are built from them if needed)."""
        self._cache = arrays
        self._src = self._dst = self._z = self._cov = None
        self._pairs = pairs

    def _lists(self) -> None:
        """The per-connection lists and the duplicate bookkeeping, from the arrays if the
        connections were stored as arrays (before a single connection is added)."""
        if self._src is None:
            c = self._cache
            self._src, self._dst = c.src.tolist(), c.dst.tolist()
            self._z, self._cov = list(c.z), list(c.cov)
        if self._pairs is None:
            self._pairs = {}
            for k, (a, b) in enumerate(zip(self._src, self._dst)):
                self._pairs.setdefault((min(a, b), max(a, b)), []).append(k)

    @classmethod
    def from_arrays(cls, node_ids: IntArray, track_ids: IntArray, src_idx: IntArray,
                    dst_idx: IntArray, z: FloatArray, cov: FloatArray) -> ConnectionNetwork:
        """Build from arrays that were validated already (e.g. a subset of another network).

        No checks beyond shapes are made: use :meth:`add_connections` for outside input.
        ``src_idx``/``dst_idx`` index into ``node_ids``. Duplicate bookkeeping is skipped, so
        the result uses the ``'keep'`` policy.
        """
        net = cls()
        ids = [int(i) for i in np.asarray(node_ids).tolist()]
        net._ids = ids
        net._tracks = [int(t) for t in np.asarray(track_ids).tolist()]
        net._index = {i: k for k, i in enumerate(ids)}
        if len(net._index) != len(ids) or len(net._tracks) != len(ids):
            raise InputError('node ids must be unique and have one track id each')
        m = int(np.asarray(src_idx).size)
        net._cache = ConnectionArrays(np.asarray(src_idx, dtype=np.int64).reshape(m),
                                      np.asarray(dst_idx, dtype=np.int64).reshape(m),
                                      np.asarray(z, dtype=float).reshape(m, 6),
                                      np.asarray(cov, dtype=float).reshape(m, 6, 6))
        # arrays only: per-connection lists (~0.3 KiB a connection) if one is added later
        net._set_arrays(net._cache, pairs={})
        return net

    def _snapshot(self):
        self._lists()
        return (len(self._src), {k: list(v) for k, v in self._pairs.items()},
                list(self._src), list(self._dst), list(self._z), list(self._cov))

    def _restore(self, snap) -> None:
        _, self._pairs, self._src, self._dst, self._z, self._cov = snap
        self._cache = None

    def arrays(self) -> ConnectionArrays:
        """All connections as arrays (cached until the next change)."""
        if self._cache is None:
            m = len(self._src)
            self._cache = ConnectionArrays(
                src=np.asarray(self._src, dtype=np.int64),
                dst=np.asarray(self._dst, dtype=np.int64),
                z=np.asarray(self._z, dtype=float).reshape(m, 6),
                cov=np.asarray(self._cov, dtype=float).reshape(m, 6, 6),
            )
        return self._cache

    # ------------------------------------------------------------- structure
    def unreachable_from(self, anchor_ids) -> IntArray:
        """Ids of nodes with no chain of connections to any of ``anchor_ids``."""
        n = self.n_nodes
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        anchors = self.indices_of(anchor_ids)
        c = self.arrays()
        labels = component_labels(n, c.src, c.dst)
        ok = np.isin(labels, labels[anchors])
        return self.node_ids[~ok]

    def check_connected(self, anchor_ids) -> None:
        """Raise :class:`NetworkError` naming the nodes not connected to the datum/anchors."""
        bad = self.unreachable_from(anchor_ids)
        if bad.size:
            shown = ', '.join(str(int(i)) for i in bad[:20])
            more = f' and {bad.size - 20} more' if bad.size > 20 else ''
            raise NetworkError(f'{bad.size} node(s) are not connected to the datum: '
                               f'{shown}{more}; add connections to them or remove them')

    def consecutive_chain(self) -> list[int]:
        """Connection indices ``k`` with ``dst == src + 1`` (in index order): the F2F chain."""
        c = self.arrays()
        return [int(k) for k in np.nonzero(c.dst == c.src + 1)[0]]


def _check_id(value, what: str) -> int:
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise InputError(f'{what} must be an integer, got {value!r}') from None
    if v != value or v < 0 or v >= 2**63:
        raise InputError(f'{what} must be an integer in [0, 2**63), got {value!r}')
    return v


def component_labels(n: int, src: IntArray, dst: IntArray) -> IntArray:
    """Connected-component label of each of ``n`` nodes of an undirected graph (the smallest
    node index of its component), edges ``src[k] - dst[k]``.

    NumPy only (``scipy.sparse.csgraph`` pulls ``scipy.sparse.linalg`` and ``scipy.linalg``
    into every process that solves, ~0.15 s of start-up): rounds of hooking each edge's larger
    root onto the smaller one, then pointer jumping to the roots, ``O(log n)`` rounds each
    ``O(m + n)``.
    """
    parent = np.arange(n, dtype=np.int64)
    src, dst = np.asarray(src, dtype=np.int64), np.asarray(dst, dtype=np.int64)
    while True:
        a, b = parent[src], parent[dst]
        diff = a != b
        if not diff.any():
            return parent
        lo, hi = np.minimum(a[diff], b[diff]), np.maximum(a[diff], b[diff])
        np.minimum.at(parent, hi, lo)  # hi are roots: each takes its smallest neighbour root
        while True:  # pointer jumping until every node points at its root
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
