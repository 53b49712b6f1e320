"""Start-up of ``ga-ros`` (issue 36: ``--help`` and a small solve in a blink) and the whole
process of ``ga-ros solve`` (issue 10: <= GTSAM's): what ``--help`` and a batch solve import,
the NumPy connected components and the chordal systems on the solver's own Cholesky that
replace ``scipy.sparse`` on its path, the g2o reader's network built from its validated arrays,
and the compiled kernels' on-disk cache."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ga_ros import runtime
from ga_ros.cli.commands import SUMMARIES
from ga_ros.cli.main import build_parser, command_modules
from ga_ros.core import kernels
from ga_ros.core.initialization import PoseGraphEdges, chordal_initialization
from ga_ros.core.network import component_labels
from ga_ros.geometry import se3
from ga_ros.io.g2o.planar import se2_to_se3

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


@pytest.mark.parametrize('init', [['--init', 'file'], []])
def test_batch_solve_imports_no_unused_scipy_module(tmp_path, init):
    """`ga-ros solve FILE --out OUT` (parse, start, solve, cost, write) loads neither
    scipy.linalg nor scipy.sparse nor the compiled kernels, with the file's start and with the
    default ``--init auto`` (which also computes the chordal start, on the solver's own sparse
    Cholesky); SciPy's OpenBLAS is loaded (not imported) so the thread limit covers it."""
    g2o = tmp_path / 'ring.g2o'
    lines = [f'VERTEX_SE2 {k} {np.cos(k / 3):.6f} {np.sin(k / 3):.6f} {k / 3 + 1.6:.6f}'
             for k in range(20)]
    lines += [f'EDGE_SE2 {k} {(k + 1) % 20} 0.33 0.01 0.333 100 0 0 100 0 1000'
              for k in range(20)]
    g2o.write_text('\n'.join(lines) + '\n')
    code = ('import sys\n'
            'from ga_ros.cli.main import main\n'
            f'assert main(["solve", {str(g2o)!r}, *{init!r}, "--out", '
            f'{str(tmp_path / "o.g2o")!r}]) == 0\n'
            'from threadpoolctl import threadpool_info\n'
            f'print(sorted(m for m in {UNUSED + ("scipy.sparse",)!r} if m in sys.modules))\n'
            "print(sorted({i['num_threads'] for i in threadpool_info()\n"
            "              if 'scipy.libs' in i['filepath']}))\n"
            'import gc\n'
            'print(list(gc.get_threshold()))\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out[-3:] == ['[]', f'[{runtime.default_blas_threads()}]',
                        str(list(runtime.COMMAND_GC_THRESHOLDS))]  # set by the entry point
    if not init:  # auto compared the file's start with chordal
        assert 'auto, costs at the starts: file' in '\n'.join(out)


#: What ``ga-ros --help`` does not import: NumPy and what stands on it, ROS, plotting, and no
#: command's module.
NOT_FOR_HELP = ('numpy', 'scipy', 'numba', 'cvxopt', 'threadpoolctl', 'matplotlib', 'rclpy',
                'cv2', 'yaml', 'ga_ros.runtime', 'ga_ros.core', 'ga_ros.cli.commands.')


@pytest.mark.parametrize('argv', [['--help'], [], ['--version'], ['no-such-command']])
def test_help_imports_no_command_module_nor_numpy(argv):
    code = ('import sys\n'
            'from ga_ros.cli.main import main\n'
            'try:\n'
            f'    code = main({argv!r})\n'
            'except SystemExit as exc:\n'
            '    code = exc.code\n'
            'loaded = sorted(m for m in sys.modules\n'
            f'                if m.split(".")[0] in {NOT_FOR_HELP!r}\n'
            f'                or m.startswith({NOT_FOR_HELP!r}))\n'
            'print("LOADED", loaded, "EXIT", code)\n')
    res = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True)
    assert res.stdout.splitlines()[-1].startswith('LOADED [] EXIT '), res.stdout[-500:]
    if argv in (['--help'], []):  # every command listed with its summary
        listing = ' '.join(res.stdout.split())
        for name, summary in SUMMARIES.items():
            assert f'{name} {" ".join(summary.split())}' in listing, name
    if argv == ['no-such-command']:
        assert 'invalid choice' in res.stderr and res.stdout.split()[-1] == '2'


def test_every_command_module_has_its_summary_and_registers_it():
    """``ga-ros --help`` lists :data:`SUMMARIES` without importing the modules: each module
    is listed there and its own parser shows the same summary."""
    assert set(SUMMARIES) == {m.replace('_', '-') for m in command_modules()}
    for name in SUMMARIES:
        sub = next(a for a in build_parser(name)._actions if a.dest == 'command')
        assert list(sub.choices) == [name]
        assert [a.help for a in sub._choices_actions] == [SUMMARIES[name]]


def _dense_chordal(n: int, src, dst, T_meas, information, dim: int, root: int):
    """The chordal relaxation by dense weighted least squares (``np.linalg.lstsq`` of the
    whitened full design matrix): rotations ``Y = R'`` from ``y_j - R_ij' y_i = 0`` with the
    mean rotation information as weight, projected to SO(d) by SVD; then translations from
    ``t_j - t_i = R_i t_ij`` weighted by ``R_i I_t R_i'``; ``root`` at the identity."""
    d, m = dim, len(src)
    free = [k for k in range(n) if k != root]
    col = {v: c for c, v in enumerate(free)}
    R_ij, t_ij = T_meas[:, :d, :d], T_meas[:, :d, 3]
    if d == 3:
        w, I_t = np.trace(information[:, 3:, 3:], axis1=1, axis2=2) / 3, information[:, :3, :3]
    else:
        w, I_t = information[:, 2, 2], information[:, :2, :2]
    A = np.zeros((d * m, d * len(free)))
    rhs = np.zeros((d * m, d))
    for k, (i, j) in enumerate(zip(src, dst)):
        r = slice(d * k, d * k + d)
        for v, B in ((i, -R_ij[k].T), (j, np.eye(d))):
            if v == root:
                rhs[r] -= B  # Y_root = I
            else:
                A[r, d * col[v]:d * col[v] + d] += B
    sw = np.repeat(np.sqrt(w), d)[:, None]
    Y = np.linalg.lstsq(sw * A, sw * rhs, rcond=None)[0]
    R = np.empty((n, d, d))
    R[root] = np.eye(d)
    for v in free:
        U, _, Vt = np.linalg.svd(Y[d * col[v]:d * col[v] + d].T)
        R[v] = U @ np.diag([1.0] * (d - 1) + [np.linalg.det(U @ Vt)]) @ Vt
    A_t = np.zeros((d * m, d * len(free)))
    b_t = np.zeros(d * m)
    for k, (i, j) in enumerate(zip(src, dst)):
        W = R[i] @ I_t[k] @ R[i].T
        L = np.linalg.cholesky(0.5 * (W + W.T)).T  # L'L = W
        r = slice(d * k, d * k + d)
        for v, sign in ((i, -1.0), (j, 1.0)):
            if v != root:
                A_t[r, d * col[v]:d * col[v] + d] += sign * L
        b_t[r] = L @ R[i] @ t_ij[k]
    t = np.zeros((n, d))
    t[free] = np.linalg.lstsq(A_t, b_t, rcond=None)[0].reshape(-1, d)
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    T[:, :d, :d], T[:, :d, 3] = R, t
    return T


@pytest.mark.parametrize('dim,root', [(3, 0), (3, 4), (2, 0), (2, 7)])
def test_chordal_start_equals_dense_least_squares_on_a_noisy_graph(rng, dim, root):
    n = 12
    if dim == 3:
        T = se3.exp(rng.normal(0, [3, 3, 3, 1, 1, 1], (n, 6)))
        noise = se3.exp(rng.normal(0, 0.1, (n - 1 + 15, 6)))
        d = 6
    else:
        T = se2_to_se3(rng.normal(0, [3, 3, 1], (n, 3)))
        noise = se2_to_se3(rng.normal(0, 0.1, (n - 1 + 15, 3)))
        d = 3
    pairs = np.array([(k, k + 1) for k in range(n - 1)]
                     + [tuple(rng.choice(n, 2, replace=False)) for _ in range(15)])
    pairs = np.concatenate([pairs, pairs[:2]])  # a repeated edge, kept twice
    noise = np.concatenate([noise, noise[:2][::-1]])
    A = rng.normal(size=(len(pairs), d, d))
    info = A @ np.swapaxes(A, 1, 2) + np.eye(d)
    T_meas = se3.relative(T[pairs[:, 0]], T[pairs[:, 1]]) @ noise
    edges = PoseGraphEdges(n=n, src=pairs[:, 0], dst=pairs[:, 1], T_meas=T_meas,
                           information=info, dim=dim)
    got = chordal_initialization(edges, root)
    ref = _dense_chordal(n, pairs[:, 0], pairs[:, 1], T_meas, info, dim, root)
    np.testing.assert_allclose(got, ref, atol=1e-9)
    assert np.abs(ref - se3.inverse(T[root]) @ T).max() > 1e-2  # the noise moved it


def test_chordal_start_of_the_datum_alone():
    """A one-vertex graph: nothing to solve for, the datum at the identity (the solve then
    says that every node is fixed)."""
    for dim, d in ((3, 6), (2, 3)):
        edges = PoseGraphEdges(n=1, src=np.zeros(0, dtype=np.int64),
                               dst=np.zeros(0, dtype=np.int64), T_meas=np.zeros((0, 4, 4)),
                               information=np.zeros((0, d, d)), dim=dim)
        np.testing.assert_array_equal(chordal_initialization(edges, 0), np.eye(4)[None])


@pytest.mark.skipif(not kernels.AVAILABLE, reason='numba not installed (or GA_ROS_JIT=0)')
def test_kernels_compile_with_and_without_a_writable_cache(tmp_path):
    """:func:`ga_ros.core.kernels.jit` caches machine code in ``$NUMBA_CACHE_DIR`` (a second
    process loads it), and compiles without a cache, warning once, when no cache directory is
    writable (a read-only install with a read-only home): here ``__pycache__`` beside the
    source is a file and the home directory lies under a file."""
    pkg = tmp_path / 'src'
    pkg.mkdir()
    (pkg / 'tiny_kernel.py').write_text('def add(a, b):\n    return a + b * 2\n')
    code = ('import warnings\n'
            'import tiny_kernel\n'
            'from ga_ros.core.kernels import jit\n'
            'with warnings.catch_warnings(record=True) as caught:\n'
            "    warnings.simplefilter('always')\n"
            '    f = jit(tiny_kernel.add)\n'
            '    g = jit(tiny_kernel.add)\n'
            'assert f(1, 2) == 5 and g(1.5, 1.0) == 3.5\n'
            "print('WARNINGS', sum('NUMBA_CACHE_DIR' in str(w.message) for w in caught))\n"
            "print('HITS', sum(f.stats.cache_hits.values()))\n")
    blocked = tmp_path / 'a-file'
    blocked.write_text('')
    env = {k: v for k, v in os.environ.items() if k != 'NUMBA_CACHE_DIR'}
    env['PYTHONPATH'] = os.pathsep.join([str(pkg), *sys.path])
    env['HOME'] = env['XDG_CACHE_HOME'] = str(blocked / 'home')

    def run(extra: dict[str, str]) -> tuple[int, int]:
        out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                             env={**env, **extra}, check=True).stdout.split()
        return int(out[out.index('WARNINGS') + 1]), int(out[out.index('HITS') + 1])

    (pkg / '__pycache__').write_text('')  # numba's cache beside the source cannot be made
    assert run({}) == (1, 0)  # no cache anywhere: compiled, one warning
    cache = tmp_path / 'cache'
    assert run({'NUMBA_CACHE_DIR': str(cache)}) == (0, 0)  # compiled and saved
    assert any(cache.rglob('*.nbi'))
    assert run({'NUMBA_CACHE_DIR': str(cache)}) == (0, 1)  # loaded from the cache


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



#: What no command's ``--help`` imports: SciPy's statistics, OpenCV, ROS, plotting (each
#: imported by the function that uses it).
NOT_FOR_COMMAND_HELP = ('scipy.stats', 'cv2', 'rclpy', 'matplotlib')


@pytest.mark.parametrize('command', sorted(SUMMARIES))
def test_command_help_imports_no_statistics_opencv_ros_nor_plotting(command):
    code = ('import sys\n'
            'from ga_ros.cli.main import main\n'
            'try:\n'
            f'    code = main([{command!r}, "--help"])\n'
            'except SystemExit as exc:\n'
            '    code = exc.code\n'
            'loaded = sorted(m for m in sys.modules\n'
            f'                if m in {NOT_FOR_COMMAND_HELP!r}\n'
            f'                or m.startswith(tuple(p + "." for p in {NOT_FOR_COMMAND_HELP!r})))\n'
            'print("LOADED", loaded, "EXIT", code)\n')
    res = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True)
    assert res.stdout.splitlines()[-1] == 'LOADED [] EXIT 0', res.stdout[-500:]
    assert f'ga-ros {command}' in res.stdout  # its own usage line
