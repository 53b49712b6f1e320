"""Whole process of ``ga-ros solve`` (issue 10: <= GTSAM's): what a batch solve imports, the
NumPy connected components that replace ``scipy.sparse.csgraph`` on its path, and the g2o
reader's network built from its validated arrays."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ga_ros import runtime
from ga_ros.core.network import component_labels

#: Modules a batch solve of a g2o file does not need (the SciPy ones ~0.3 s of start-up).
UNUSED = ('scipy.linalg', 'scipy.sparse.linalg', 'scipy.sparse.csgraph', 'scipy.spatial',
          'scipy.special', 'scipy.stats', 'scipy.sparse._base', 'numba', 'numpy.testing',
          'numpy.f2py',
          # nor these modules of its own path's other options (a few ms each)
          'numpy.char', 'ga_ros.io.trajectory', 'ga_ros.core.measurement')


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Two labellings describe the same components (label values may differ)."""
    pairs = np.unique(np.stack([a, b], axis=1), axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


@pytest.mark.parametrize('seed', range(6))
def test_component_labels_match_scipy_connected_components(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    m = int(rng.integers(0, 2 * n))
    src, dst = rng.integers(0, n, m), rng.integers(0, n, m)
    if seed == 0:  # a long chain (the worst case for label propagation) plus isolated nodes
        src, dst = np.arange(n - 1)[::-1][: n // 2], np.arange(1, n)[::-1][: n // 2]
    labels = component_labels(n, src, dst)
    _, ref = connected_components(coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n)),
                                  directed=False)
    assert _same_partition(labels, ref)
    # each label is the smallest node index of its component
    assert all(labels[k] == np.flatnonzero(ref == ref[k]).min() for k in range(n))


def test_component_labels_of_a_chain_given_in_reverse_order():
    n = 2000  # hooking goes one step per round here: pointer jumping keeps it O(log n) rounds
    labels = component_labels(n, np.arange(1, n)[::-1], np.arange(n - 1)[::-1])
    assert (labels == 0).all()


def test_batch_solve_imports_no_unused_scipy_module(tmp_path):
    """`ga-ros solve FILE --init file --out OUT` (parse, solve, cost, write) loads neither
    scipy.linalg nor csgraph nor the compiled kernels; SciPy's OpenBLAS is loaded (not imported)
    so the thread limit covers it. (The default ``--init auto`` compares the file's guess with
    a chordal initialisation, which needs SciPy's sparse solvers.)"""
    g2o = tmp_path / 'ring.g2o'
    lines = [f'VERTEX_SE2 {k} {np.cos(k / 3):.6f} {np.sin(k / 3):.6f} {k / 3 + 1.6:.6f}'
             for k in range(20)]
    lines += [f'EDGE_SE2 {k} {(k + 1) % 20} 0.33 0.01 0.333 100 0 0 100 0 1000'
              for k in range(20)]
    g2o.write_text('\n'.join(lines) + '\n')
    code = ('import sys\n'
            'from ga_ros.cli.main import main\n'
            f'assert main(["solve", {str(g2o)!r}, "--init", "file", "--out", '
            f'{str(tmp_path / "o.g2o")!r}]) == 0\n'
            'from threadpoolctl import threadpool_info\n'
            f'print(sorted(m for m in {UNUSED!r} if m in sys.modules))\n'
            "print(sorted({i['num_threads'] for i in threadpool_info()\n"
            "              if 'scipy.libs' in i['filepath']}))\n")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out[-2:] == ['[]', f'[{runtime.default_blas_threads()}]']


def test_g2o_network_equals_the_one_built_connection_by_connection(tmp_path):
    """read_g2o builds its network from the validated arrays at once; the same file through
    add_node / add_connections (each connection checked by the network) gives the same
    network, a repeated edge kept twice."""
    from ga_ros.core.network import ConnectionNetwork
    from ga_ros.io.g2o import read_g2o

    rng = np.random.default_rng(0)
    lines = [f'VERTEX_SE3:QUAT {k * 3} {k}.0 0 0 0 0 0 1' for k in range(6)]
    info = '100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 400 0 0 400 0 400'
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5), (0, 5), (2, 0)]:
        x, y, z = rng.normal(size=3)
        lines.append(f'EDGE_SE3:QUAT {i * 3} {j * 3} {x} {y} {z} 0.1 0 0 0.99498743710662 '
                     + info)
    (tmp_path / 'g.g2o').write_text('\n'.join(lines) + '\n')
    g = read_g2o(tmp_path / 'g.g2o')
    ref = ConnectionNetwork(duplicates='keep')
    for v in g.vertex_ids.tolist():
        ref.add_node(v, 0)
    a = g.network.arrays()
    ref.add_connections(g.vertex_ids[a.src], g.vertex_ids[a.dst], a.z, a.cov)
    b = ref.arrays()
    assert g.network.n_connections == ref.n_connections == 8
    np.testing.assert_array_equal(g.network.node_ids, ref.node_ids)
    for name in ('src', 'dst', 'z', 'cov'):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_allclose(np.linalg.inv(a.cov), g.information, rtol=1e-12)
    # the network keeps working like one built edge by edge
    g.network.add_connection(0, 15, np.zeros(6), np.eye(6))
    assert g.network.n_connections == 9 and g.network.unreachable_from([0]).size == 0

