"""Initial guesses for a pose graph that has none (or a poor one).

Three methods, all on plain arrays (vertex indices, measured motions ``T_i_j``, information):

* **odometry**: compose the measured motions along the chain of consecutive vertices (index
  ``k`` to ``k + 1``), what a front end's odometry would give; where that chain is broken, the
  most certain other edges bridge it (the spanning tree below, with chain edges preferred).
* **spanning-tree**: compose along a minimum spanning tree whose edge weight is the trace of
  the edge's covariance (``trace(Omega^-1)``), so the most certain edges are chained; this is
  g2o's own initialisation of an edge-only graph (breadth first from the datum).
* **chordal**: rotation first, then translation (Carlone, Tron, Daniilidis, Dellaert,
  "Initialization techniques for 3D SLAM: a survey on rotation estimation and its use in pose
  graph optimization", ICRA 2015, Sec. IV, "chordal relaxation"). With the datum's rotation
  fixed to ``I``, the relaxed problem ``min sum_k w_k ||R_j - R_i R_ij||_F^2`` over unconstrained
  ``d x d`` matrices is *linear*: with ``Y = R'`` each column obeys ``y_j - R_ij' y_i = 0``,
  three (2-D: two) sparse least-squares problems sharing one normal matrix. Each solution is
  projected to SO(d) by SVD. Given those rotations, the translations solve the linear
  least-squares problem ``t_j - t_i = R_i t_ij`` weighted by the translation information
  rotated to the world frame. Both systems are sparse (``d n x d n``, the graph's block
  pattern) and solved by the solver's sparse Cholesky; nothing dense of size ``n x n`` is
  formed. It uses every edge, so one bad chain
  edge does not bend the whole graph, and it is the standard start for the global optimum.

2-D graphs run the same code with ``d = 2`` (rotation about ``z``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.network import component_labels
from ga_ros.errors import DegenerateGeometryError, InputError, NetworkError
from ga_ros.geometry import se3
from ga_ros.runtime import lazy_import

sp = lazy_import('scipy.sparse')  # only some functions need it (start-up)

INIT_METHODS = ('odometry', 'spanning-tree', 'chordal')


@dataclass(frozen=True)
class PoseGraphEdges:
    """The edges of a pose graph, as the initialisers need them.

    Attributes
    ----------
    n : number of vertices.
    src, dst : (m,) vertex indices of each edge ``T_src_dst``.
    T_meas : (m, 4, 4) measured motions ``T_i_j`` (2-D: rotation about ``z``, ``z = 0``).
    information : (m, 6, 6) information in ``[x y z rx ry rz]``, or (m, 3, 3) in
        ``[x y theta]`` for a 2-D graph.
    dim : 2 or 3.
    """

    n: int
    src: IntArray
    dst: IntArray
    T_meas: FloatArray
    information: FloatArray
    dim: int

    def __post_init__(self) -> None:
        m = len(self.src)
        d = 6 if self.dim == 3 else 3
        if self.dim not in (2, 3):
            raise InputError(f'dim must be 2 or 3, got {self.dim}')
        if (len(self.dst) != m or np.shape(self.T_meas) != (m, 4, 4)
                or np.shape(self.information) != (m, d, d)):
            raise InputError('src, dst, T_meas (m, 4, 4) and information (m, d, d) must agree')
        if m and (min(np.min(self.src), np.min(self.dst)) < 0
                  or max(np.max(self.src), np.max(self.dst)) >= self.n):
            raise InputError(f'edge ends must be vertex indices in [0, {self.n})')

    def blocks(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``R_ij (m, d, d)``, ``t_ij (m, d)``, rotation weight ``(m,)`` (mean eigenvalue of the
        rotation information), translation information ``(m, d, d)``; ``d = dim``."""
        d = self.dim
        R = self.T_meas[:, :d, :d]
        t = self.T_meas[:, :d, 3]
        if d == 3:
            w = np.trace(self.information[:, 3:, 3:], axis1=1, axis2=2) / 3.0
            I_t = self.information[:, :3, :3]
        else:
            w = self.information[:, 2, 2].copy()
            I_t = self.information[:, :2, :2]
        return R, t, np.maximum(w, 1e-12 * max(float(np.max(w, initial=0.0)), 1e-300)), I_t


def _check_reached(reached: IntArray, n: int) -> None:
    """Raise :class:`NetworkError` naming the vertices missing from ``reached`` (the vertices
    a search from the datum visited)."""
    if reached.size != n:
        missing = np.setdiff1d(np.arange(n), reached)
        raise NetworkError(f'{missing.size} vertices (indices e.g. {missing[:5].tolist()}) are '
                           f'not connected to the datum by any edge; they cannot be placed')


def _compose_tree(edges: PoseGraphEdges, weight: FloatArray, root: int) -> FloatArray:
    """Poses composed from ``root`` (identity) along the minimum spanning tree of ``weight``."""
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree  # lazy: start-up

    n, src, dst = edges.n, np.asarray(edges.src), np.asarray(edges.dst)
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    order = np.argsort(weight, kind='stable')
    key = lo[order] * n + hi[order]
    _, first = np.unique(key, return_index=True)
    best = order[first]                      # the lightest edge of each vertex pair
    w = weight[best] - weight.min() + 1.0    # positive: csgraph drops zero weights
    G = sp.coo_matrix((w, (lo[best], hi[best])), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(G)
    visit, pred = breadth_first_order(tree, root, directed=False, return_predecessors=True)
    _check_reached(visit, n)
    pair_key = lo[best] * n + hi[best]
    sorter = np.argsort(pair_key)
    child = visit[1:]
    parent = pred[child]
    k = best[sorter[np.searchsorted(pair_key, np.minimum(child, parent) * n
                                    + np.maximum(child, parent), sorter=sorter)]]
    M = edges.T_meas[k].copy()
    flip = src[k] != parent                  # edge stored as T_child_parent: invert it
    M[flip] = se3.inverse(M[flip])
    T = np.empty((n, 4, 4))
    T[root] = np.eye(4)
    for c, p, Mk in zip(child.tolist(), parent.tolist(), M):  # breadth first: parent is set
        T[c] = T[p] @ Mk
    return T


def spanning_tree_initialization(edges: PoseGraphEdges, root: int = 0) -> FloatArray:
    """Poses ``T_world_node (n, 4, 4)`` composed along the minimum spanning tree of the edge
    covariances' traces, the ``root`` vertex at the identity (see module docstring).

    Raises
    ------
    NetworkError
        Some vertex has no path of edges to ``root``.
    """
    cov_trace = np.trace(np.linalg.inv(edges.information), axis1=1, axis2=2)
    return _compose_tree(edges, cov_trace, root)


def odometry_initialization(edges: PoseGraphEdges, root: int = 0) -> FloatArray:
    """Poses composed along the chain of consecutive vertex indices, bridged by the most
    certain other edges where the chain is broken; ``root`` at the identity.

    Raises
    ------
    NetworkError
        Some vertex has no path of edges to ``root``.
    """
    cov_trace = np.trace(np.linalg.inv(edges.information), axis1=1, axis2=2)
    chain = np.abs(np.asarray(edges.src) - np.asarray(edges.dst)) == 1
    # chain edges first (ranked among themselves by certainty), then the others
    weight = np.argsort(np.argsort(cov_trace, kind='stable'), kind='stable').astype(float)
    weight[~chain] += len(weight)
    return _compose_tree(edges, weight, root)


def _project_rotations(M: FloatArray) -> FloatArray:
    """Nearest rotations (Frobenius) of ``(n, d, d)`` matrices: ``U diag(1, .., det) V'``."""
    U, _, Vt = np.linalg.svd(M)
    det = np.linalg.det(U @ Vt)
    U[:, :, -1] *= det[:, None]
    return U @ Vt


def _solve_free(free: _FreeVertices, src: IntArray, dst: IntArray, blocks: FloatArray,
                b: FloatArray, d: int, what: str) -> FloatArray:
    """Solve the normal equations ``N x = b`` of a chordal system for the free vertices.

    ``N`` is given by ``(m, 4, d, d)`` blocks per edge ``k = (i, j)``: ``N_ii``, ``N_jj``,
    ``N_ij`` and ``N_ji`` (blocks of the datum dropped), summed into the graph's block pattern
    and factored by the solver's sparse Cholesky (:mod:`ga_ros.core.linalg.cholesky`; no SciPy
    on a solve's path). ``b``: ``(d nf,)`` or ``(d nf, k)``."""
    from ga_ros.core.linalg.blocks import BlockPattern
    from ga_ros.core.linalg.cholesky import SparseCholesky

    i, j = free.index[src], free.index[dst]
    rows = np.stack([i, j, i, j], axis=1).ravel()
    cols = np.stack([i, j, j, i], axis=1).ravel()
    pattern = BlockPattern(rows, cols, d, free.others.size)
    try:
        x = SparseCholesky(pattern, pattern.assemble(blocks.reshape(-1, d, d))).solve(b)
    except DegenerateGeometryError as exc:
        raise DegenerateGeometryError(f'chordal initialisation: the {what} system is '
                                      f'singular ({exc}); is every vertex connected to the '
                                      f'datum?') from None
    if not np.isfinite(x).all():
        raise DegenerateGeometryError(f'chordal initialisation: the {what} system gave NaN')
    return x


@dataclass(frozen=True)
class _FreeVertices:
    """The unknowns of the chordal systems: every vertex but the datum (``root``).

    Attributes
    ----------
    root : the datum's vertex index.
    others : (nf,) the other vertices, ascending.
    index : (n,) position of each vertex among ``others`` (-1 for the root).
    """

    root: int
    others: IntArray
    index: IntArray

    @classmethod
    def of(cls, n: int, root: int) -> _FreeVertices:
        """The free vertices of a graph of ``n`` vertices with the datum ``root``."""
        index = np.full(n, -1, dtype=np.int64)
        others = np.flatnonzero(np.arange(n) != root)
        index[others] = np.arange(others.size)
        return cls(root, others, index)


def _normal_system(free: _FreeVertices, src: IntArray, dst: IntArray, B_i: FloatArray,
                   B_j: FloatArray, W: FloatArray, rhs: FloatArray) -> tuple[FloatArray,
                                                                            FloatArray]:
    """The normal equations of the weighted least squares ``B_i[k] x_i + B_j[k] x_j =
    rhs[k]`` (weight ``W[k]``, ``(m, d, d)``) over the free vertices: the ``(m, 4, d, d)``
    blocks ``N_ii, N_jj, N_ij, N_ji`` of each edge for :func:`_solve_free` and ``b = A' W rhs``
    of shape ``(d nf, k)`` (``rhs``: ``(m, d, k)``; a datum's unknown is known and already
    moved into ``rhs``)."""
    d, nf = W.shape[1], free.others.size
    Bi_t, Bj_t = np.swapaxes(B_i, 1, 2), np.swapaxes(B_j, 1, 2)
    WBi, WBj = W @ B_i, W @ B_j
    blocks = np.stack([Bi_t @ WBi, Bj_t @ WBj, Bi_t @ WBj, Bj_t @ WBi], axis=1)
    Wr = W @ rhs
    b = np.zeros((nf + 1, d, rhs.shape[2]))  # row nf collects the datum's (dropped) terms
    np.add.at(b, free.index[src], Bi_t @ Wr)
    np.add.at(b, free.index[dst], Bj_t @ Wr)
    return blocks, b[:nf].reshape(nf * d, -1)


def _chordal_rotations(edges: PoseGraphEdges, free: _FreeVertices, R_ij: FloatArray,
                       w: FloatArray) -> FloatArray:
    """Rotations ``R_world_node (n, d, d)`` of the chordal relaxation: the weighted least
    squares ``y_j - R_ij' y_i = 0`` for each column of ``Y = R'`` (``Y_root = I``), each
    solution projected to SO(d)."""
    n, d, root = edges.n, edges.dim, free.root
    src, dst = np.asarray(edges.src), np.asarray(edges.dst)
    m, nf = src.size, free.others.size
    eye = np.broadcast_to(np.eye(d), (m, d, d))
    R_ij_t = np.swapaxes(R_ij, 1, 2)
    rhs = np.zeros((m, d, d))
    rhs[src == root] += R_ij_t[src == root]   # -(-R_ij' I)
    rhs[dst == root] -= eye[dst == root]      # -(I I)
    blocks, b = _normal_system(free, src, dst, -R_ij_t, eye, w[:, None, None] * eye, rhs)
    y = _solve_free(free, src, dst, blocks, b, d, 'rotation')
    R = np.empty((n, d, d))
    R[root] = np.eye(d)
    R[free.others] = np.swapaxes(y.reshape(nf, d, d), 1, 2)
    return _project_rotations(R)


def _chordal_translations(edges: PoseGraphEdges, free: _FreeVertices, R: FloatArray,
                          t_ij: FloatArray, I_t: FloatArray) -> FloatArray:
    """Translations ``t_world_node (n, d)`` given the rotations ``R``: the least squares
    ``t_j - t_i = R_i t_ij`` weighted by ``R_i I_t R_i'`` (``t_root = 0``)."""
    n, d = edges.n, edges.dim
    src, dst = np.asarray(edges.src), np.asarray(edges.dst)
    m, nf = src.size, free.others.size
    eye = np.broadcast_to(np.eye(d), (m, d, d))
    rhs = R[src] @ t_ij[:, :, None]
    W_blocks = R[src] @ I_t @ np.swapaxes(R[src], 1, 2)
    blocks, b = _normal_system(free, src, dst, -eye, eye,
                               0.5 * (W_blocks + np.swapaxes(W_blocks, 1, 2)), rhs)
    t = np.zeros((n, d))
    t[free.others] = _solve_free(free, src, dst, blocks, b, d, 'translation').reshape(nf, d)
    return t


def chordal_initialization(edges: PoseGraphEdges, root: int = 0) -> FloatArray:
    """Chordal rotation-first initialisation (Carlone et al., ICRA 2015; module docstring).

    Parameters
    ----------
    edges : the graph's edges.
    root : vertex index held at the identity (the datum).

    Returns
    -------
    (n, 4, 4) poses ``T_world_node``; 2-D graphs stay in the plane (``z = 0``).

    Raises
    ------
    NetworkError
        Some vertex has no path of edges to ``root``.
    DegenerateGeometryError
        The sparse systems cannot be solved.
    """
    n, d = edges.n, edges.dim
    labels = component_labels(n, edges.src, edges.dst)
    _check_reached(np.flatnonzero(labels == labels[root]), n)
    R_ij, t_ij, w, I_t = edges.blocks()
    free = _FreeVertices.of(n, root)
    if free.others.size == 0:  # the datum alone
        return np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    R = _chordal_rotations(edges, free, R_ij, w)
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    T[:, :d, :d] = R
    T[:, :d, 3] = _chordal_translations(edges, free, R, t_ij, I_t)
    return T


def initialize(edges: PoseGraphEdges, method: str, root: int = 0) -> FloatArray:
    """Initial poses ``T_world_node (n, 4, 4)`` by ``method`` (one of :data:`INIT_METHODS`),
    ``root`` at the identity."""
    if method == 'odometry':
        return odometry_initialization(edges, root)
    if method == 'spanning-tree':
        return spanning_tree_initialization(edges, root)
    if method == 'chordal':
        return chordal_initialization(edges, root)
    raise InputError(f'initialisation method must be one of {INIT_METHODS}, got {method!r}')
