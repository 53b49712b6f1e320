"""The stage clock of ``ga-ros bench window`` (:mod:`ga_ros.bench.stages`): outermost stage
only, per thread, and the CPU of the whole process tree."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
from solver_problems import make_problem, perturbed

from ga_ros.bench import stages
from ga_ros.bench.cpu import all_cpu_seconds
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import freeze, update


def _spin(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_a_stage_called_inside_another_counts_in_the_outer_one_per_thread(monkeypatch):
    # two stage functions replaced by CPU spinners: 'priors' (marginalise) calls a
    # 'covariances' function inside; the outer one gets all of it
    def inner(*args, **kwargs):
        _spin(0.02)

    def outer(self, *args, **kwargs):
        _spin(0.02)
        freeze.marginal_covariances(None, None)

    monkeypatch.setattr(freeze, 'marginal_covariances', inner)
    monkeypatch.setattr(freeze.FreezePolicy, 'marginalise', outer)
    monkeypatch.setattr(update, 'outliers', inner)
    with stages.timed_stages() as clock:
        freeze.FreezePolicy.marginalise(None)  # this thread: the track end
        t = threading.Thread(target=lambda: update.outliers())  # another: background
        t.start()
        t.join()
        got = clock.take()
        assert clock.take() == {}  # taken: starts anew
    assert set(got) == {('track end', 'priors'), ('background', 'quality tests')}
    assert got[('track end', 'priors')] >= 35.0  # both spins (ms), not the inner one apart
    assert got[('background', 'quality tests')] >= 18.0
    # put back afterwards
    assert freeze.marginal_covariances is inner and update.outliers is inner


def test_the_tree_cpu_counts_a_live_child_process():
    before = all_cpu_seconds()
    child = subprocess.Popen([sys.executable, '-c',
                              'import time\nend = time.process_time() + 0.6\n'
                              'while time.process_time() < end: pass\n'
                              'import sys; sys.stdout.write("x"); sys.stdout.flush()\n'
                              'time.sleep(60)'],
                             stdout=subprocess.PIPE)
    try:
        assert child.stdout.read(1) == b'x'  # it has spun 0.6 s of CPU and is still alive
        during = all_cpu_seconds()
    finally:
        child.kill()
        child.wait()
    if sys.platform.startswith('linux'):
        assert during - before >= 0.5


def test_exclusive_stages_count_a_nested_stage_in_its_own_stage(monkeypatch):
    # the same nesting as above with exclusive=True: the outer stage keeps only its own spin
    def inner(*args, **kwargs):
        _spin(0.03)

    def outer(self, *args, **kwargs):
        _spin(0.01)
        freeze.marginal_covariances(None, None)

    monkeypatch.setattr(freeze, 'marginal_covariances', inner)
    monkeypatch.setattr(freeze.FreezePolicy, 'marginalise', outer)
    with stages.timed_stages(exclusive=True) as clock:
        freeze.FreezePolicy.marginalise(None)
        got = clock.take()
    assert set(got) == {('track end', 'priors'), ('track end', 'covariances')}
    assert got[('track end', 'covariances')] >= 28.0
    assert 8.0 <= got[('track end', 'priors')] < 25.0  # its own 10 ms, not the inner 30


def test_the_work_count_matches_the_solvers_own_and_counts_by_part(monkeypatch):
    # a batch solve outside every part: its factorisations are the solver's own count, its
    # linearisations one per factorisation (no chord steps: reuse_factor_below 0) plus the
    # final one at the solution for the covariance asked below
    rng = np.random.default_rng(3)
    prob = make_problem(rng, n=15, noise=1.0)
    T0 = perturbed(rng, prob.T_true, 0.05)
    cfg = SolverConfig(reuse_factor_below=0.0)
    with stages.counted_work() as work:
        res = solve(prob.network, T0, cfg)
        res.covariance([3])
        got = work.take()
        assert work.take() == {}  # taken: starts anew
    assert res.iterations >= 2
    assert got[('other', 'factorisations')] == res.factorisations + 1
    assert got[('other', 'linearisations')] == res.iterations + 1
    # inside a part (the window's update, here standing in for it): counted there, the wrapper
    # put back afterwards
    calls = []

    def adjust(self, *args):
        calls.append(solve(prob.network, T0, cfg).factorisations)

    monkeypatch.setattr(update.WindowUpdate, 'adjust', adjust)
    with stages.counted_work() as work:
        update.WindowUpdate.adjust(None)
        got = work.take()
    assert set(k for k, _ in got) == {'window'}
    assert got[('window', 'factorisations')] == calls[0]
    assert update.WindowUpdate.adjust is adjust
