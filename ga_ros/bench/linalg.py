"""Side-by-side evaluation of sparse Cholesky back ends on the solver's normal matrices.

Run ``ga-ros bench linalg [--repeat 5] [--json]``; the figures are kept in
``docs/linear_algebra.md``. Each variant runs in its own subprocess (the OpenBLAS kernel is chosen
when the library loads). For every matrix it prints the numeric factorisation time (median of
``repeat``), the GFlop of one factorisation (``sum_j c_j^2`` over the columns of ``L``, ``c_j``
their non-zeros) and the GFlop/s reached, and the OpenBLAS kernel that threadpoolctl reports.

Variants: CHOLMOD of the cvxopt wheel with its own kernel detection (``Prescott`` on CPUs newer
than its OpenBLAS 0.3.15) and with the kernel :mod:`ga_ros.runtime` chooses; AMD ordering (what
CHOLMOD picks) against nested dissection of the 6x6 *block* graph (METIS through ``pymetis``,
expanded to scalars); scikit-sparse against the system SuiteSparse/OpenBLAS when installed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ga_ros.bench.data import POSE_GRAPHS

GRAPHS = POSE_GRAPHS
GRAPH_FILES = ('input_M3500_g2o.g2o', 'intel.g2o', 'parking-garage.g2o', 'sphere2500.g2o',
               'torus3D.g2o')
VARIANTS = ('cvxopt-bundled', 'cvxopt', 'cvxopt-metis', 'sksparse', 'sksparse-metis')


@dataclass
class Figure:
    variant: str
    matrix: str
    n: int
    nnz_lower: int
    kernel: str
    symbolic_s: float
    numeric_s: float
    gflop: float
    gflops: float


def matrices(graph_dir: Path = GRAPHS) -> dict[str, sp.csc_matrix]:
    """Normal matrices (full symmetric CSC) at the initial guesses: the aerial survey (10 %
    noise, F2F start) and the shared pose graphs that are present."""
    from ga_ros.bench.survey import noisy_survey
    from ga_ros.core.solver import normal_matrix_at
    from ga_ros.io.g2o import read_g2o

    sc, nm = noisy_survey(25, 10.0, 0)
    net = sc.network(nm.z, nm.cov)
    out = {'aerial': normal_matrix_at(net, sc.f2f(nm.z), fixed=[int(net.node_ids[0])])[0]}
    for name in GRAPH_FILES:
        path = graph_dir / name
        if path.exists():
            g = read_g2o(path)
            fixed = list(g.fixed) or [int(g.network.node_ids[0])]
            out[name.removesuffix('.g2o')] = normal_matrix_at(g.network, g.T_init,
                                                              fixed=fixed)[0]
    return out


def block_nd_permutation(N: sp.csc_matrix, d: int = 6) -> np.ndarray:
    """Nested-dissection ordering (METIS) of the block graph, expanded to scalar indices."""
    import pymetis

    nb = N.shape[0] // d
    B = sp.csr_matrix(N[::d, ::d])
    B.setdiag(0)
    B.eliminate_zeros()
    perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(B.indptr, B.indices))
    perm = np.asarray(perm, dtype=np.int64)
    assert perm.size == nb
    return (perm[:, None] * d + np.arange(d)[None, :]).reshape(-1)


def _flops(col_counts: np.ndarray) -> float:
    return float(np.sum(col_counts.astype(float) ** 2))


def _kernel(prefix: str) -> str:
    from threadpoolctl import threadpool_info

    return ','.join(sorted({str(i.get('architecture')) for i in threadpool_info()
                            if prefix in i.get('filepath', '')})) or '?'


def _run_variant(variant: str, repeat: int) -> list[Figure]:
    from ga_ros.runtime import blas_threads

    mats = matrices()
    figs = []
    for name, N in mats.items():
        lower = sp.tril(N).tocsc()
        lower.sort_indices()
        perm = block_nd_permutation(N) if variant.endswith('metis') else None
        with blas_threads(1):
            if variant.startswith('cvxopt'):
                figs.append(_cvxopt(variant, name, lower, perm, repeat))
            else:
                figs.append(_sksparse(variant, name, N, perm, repeat))
    return figs


def _cvxopt(variant: str, name: str, lower: sp.csc_matrix, perm, repeat: int) -> Figure:
    import cvxopt
    from cvxopt import cholmod

    cholmod.options['supernodal'] = 2
    cholmod.options['postorder'] = True
    n = lower.shape[0]
    cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(lower.indptr))
    A = cvxopt.spmatrix(cvxopt.matrix(lower.data), cvxopt.matrix(lower.indices.astype(np.int64)),
                        cvxopt.matrix(cols), (n, n))
    t = time.perf_counter()
    F = (cholmod.symbolic(A, uplo='L') if perm is None
         else cholmod.symbolic(A, p=cvxopt.matrix(perm.astype(np.int32)), uplo='L'))
    sym = time.perf_counter() - t
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        cholmod.numeric(A, F)
        times.append(time.perf_counter() - t)
    L = cholmod.getfactor(F)
    counts = np.bincount(np.array(L.J, dtype=np.int64).ravel(), minlength=n)
    num = float(np.median(times))
    gflop = _flops(counts) / 1e9
    return Figure(variant, name, n, lower.nnz, _kernel('cvxopt'), sym, num, gflop, gflop / num)


def _sksparse(variant: str, name: str, N: sp.csc_matrix, perm, repeat: int) -> Figure:
    from sksparse.cholmod import analyze

    t = time.perf_counter()
    F = analyze(N, mode='supernodal', ordering_method='amd') if perm is None else \
        analyze(N, mode='supernodal', ordering_method='natural')
    sym = time.perf_counter() - t
    M = N if perm is None else N[perm][:, perm].tocsc()
    if perm is not None:
        F = analyze(M, mode='supernodal', ordering_method='natural')
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        F.cholesky_inplace(M)
        times.append(time.perf_counter() - t)
    L = F.L().tocsc()
    num = float(np.median(times))
    gflop = _flops(np.diff(L.indptr)) / 1e9
    return Figure(variant, name, N.shape[0], sp.tril(N).nnz, _kernel('openblas'), sym, num,
                  gflop, gflop / num)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog='ga-ros bench linalg', description=__doc__.split('\n\n')[0], allow_abbrev=False)
    p.add_argument('--repeat', type=int, default=5)
    p.add_argument('--json', action='store_true')
    p.add_argument('--variant', choices=VARIANTS, help='run one variant in this process')
    args = p.parse_args(argv)
    if args.variant:
        print(json.dumps([asdict(f) for f in _run_variant(args.variant, args.repeat)]))
        return 0
    rows: list[dict] = []
    for variant in VARIANTS:
        env = dict(os.environ)
        env.pop('OPENBLAS_CORETYPE', None)
        if variant == 'cvxopt-bundled':
            env['OPENBLAS_CORETYPE'] = 'Prescott'  # what 0.3.15 detects on CPUs it does not know
        proc = subprocess.run([sys.executable, '-m', 'ga_ros.bench.linalg', '--variant', variant,
                               '--repeat', str(args.repeat)], env=env, capture_output=True,
                              text=True, check=False)
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ['?'])[-1]
            print(f'# {variant}: not run ({last})', file=sys.stderr)
            continue
        rows += json.loads(proc.stdout.strip().splitlines()[-1])
    if args.json:
        print(json.dumps(rows))
        return 0
    print('| matrix | n | variant | kernel | symbolic s | numeric s | GFlop | GFlop/s |')
    print('|---|---:|---|---|---:|---:|---:|---:|')
    for r in sorted(rows, key=lambda r: (r['matrix'], VARIANTS.index(r['variant']))):
        print(f"| {r['matrix']} | {r['n']} | {r['variant']} | {r['kernel']} | "
              f"{r['symbolic_s']:.3f} | {r['numeric_s']:.3f} | {r['gflop']:.2f} | "
              f"{r['gflops']:.1f} |")
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
