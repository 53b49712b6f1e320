"""The aligner's compact storage (issue 14 item 2) changes no result.

``data/window_seeded_reference.npz`` holds the corrected path, the covariances and the
connection status of two seeded runs (one per freeze policy, with gross outliers injected),
written by running this file with python. The compact storage was checked against the
numbers of commit b7669ba, before the storage was made compact (Python lists, dicts and 6x6
covariance rows); the reference was then rewritten once, deliberately, when the update itself
changed (priors through ``refinement.tangent_prior``, chord steps below 0.5 m / rad), and again
when the prior residual took position and rotation apart (poses moved <= 2.3 mm, covariances
<= 2e-4 relative), and again when the update became a pre-alignment of the new track and
chord steps from one factorisation, with the covariances from that factorisation (poses moved
<= 23 um, the same statuses, variances <= 1.9 % relative: test_window_fast.py bounds that
difference), and again when chord steps stopped on the decrease the next step predicts
(poses moved <= 0.81 mm, the same statuses, variances <= 1.5e-5 relative), so that a
refactoring of the storage or of the update that is meant to change nothing is caught. The
run keeps the background refinement off (its own tests cover it).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.storage import IdIndex, SymArray, SymRows, TrackLists, TrackRanges
from ga_ros.geometry import se3
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

REFERENCE = Path(__file__).resolve().parents[2] / 'data' / 'window_seeded_reference.npz'
POLICIES = ('weighted', 'marginal')


def seeded_run(policy: str) -> dict[str, np.ndarray]:
    """Five double tracks of 24 poses, 5 % noise, every 23rd cross connection 30 m off; node
    ids are gapped and not in arrival order (track-dependent offsets)."""
    sc = aerial_scenario(n_tracks=5, positions_per_swath=12)
    nm = perturb(sc.true_motions(), NoiseModel(5.0, sc.depth_m), np.random.default_rng(11))
    ms = sc.measurements(nm.z, nm.cov)

    def node_id(i: int, track: int) -> int:
        return 5000 - 1000 * (track % 3) + 7 * i

    al = TrackWindowAligner(AlignerConfig(window_tracks=2, freeze_policy=policy,
                                          refine_every_tracks=0),
                            sc.T_world_node[0])
    n_cross = 0
    for m in ms:
        z = m.z
        if m.kind == 'cross':
            n_cross += 1
            if n_cross % 23 == 0:
                z = se3.to_translation_rotvec(m.T_src_dst @ se3.from_translation_rotvec(
                    np.array([30.0, -20.0, 0.0]), np.zeros(3)))
        al.add_measurement(Measurement(node_id(m.src_id, m.src_track),
                                       node_id(m.dst_id, m.dst_track), m.src_track,
                                       m.dst_track, z, m.cov, m.stamp_ns, m.kind))
    al.finish_track()
    cp = al.corrected_path()
    src, dst, z, cross, status = al.connection_arrays()
    return {'node_ids': cp.node_ids, 'T_world_node': cp.T_world_node,
            'cov': al.covariances(cp.node_ids), 'status': status, 'src': src, 'dst': dst,
            'ccov': al.connection_covariances()}


@pytest.mark.parametrize('policy', POLICIES)
def test_seeded_run_gives_the_reference_numbers(policy: str) -> None:
    if not REFERENCE.exists():
        pytest.skip(f'{REFERENCE} is missing')
    with np.load(REFERENCE) as ref:
        want = {k.split('/', 1)[1]: ref[k] for k in ref.files if k.startswith(policy + '/')}
    got = seeded_run(policy)
    assert (want['status'] == 2).sum() >= 1  # the gate excluded some of the wrong matches
    for key in ('node_ids', 'src', 'dst', 'status'):
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    np.testing.assert_array_equal(got['ccov'], want['ccov'])
    # bit-identical on the machine that wrote the reference (one BLAS thread, as here); the
    # tolerances leave room for another BLAS (the window covariances of a multi-threaded
    # OpenBLAS differ by up to 1e-6 relative), for another order of the linearisation's
    # floating-point operations (poses within 3e-10 m over the run) and for another
    # factorisation of the same matrix (CHOLMOD's simplicial factor instead of its supernodal
    # one: poses within 1.3e-10 m, covariances within 3e-11 of sd_i sd_j). Each covariance
    # entry is compared on the scale of its two standard deviations: a near-zero correlation
    # is rounding-dominated (1e-5 relative at 3e-11 of sd_i sd_j), a real change is not.
    np.testing.assert_allclose(got['T_world_node'], want['T_world_node'], rtol=0, atol=1e-9)
    var = np.einsum('kii->ki', want['cov'])
    sd = np.sqrt(np.where(var > 0, var, 1.0))  # the datum's zero covariance: absolute
    scale = sd[:, :, None] * sd[:, None, :]
    np.testing.assert_allclose(got['cov'] / scale, want['cov'] / scale, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.einsum('kii->ki', got['cov']), var, rtol=1e-6, atol=1e-14)


def test_id_index_answers_like_a_dict(rng) -> None:
    index, want = IdIndex(), {}
    ids = rng.choice(2**62, size=5000, replace=False)
    for k, node in enumerate(ids.tolist()):
        index.add(node, k)
        want[node] = k
        if k % 997 == 0:  # before and after merges into the sorted arrays
            probe = ids[rng.integers(0, k + 1, 20)].tolist() + [-1, 2**63 - 1, node + 1]
            assert [index.get(p) for p in probe] == [want.get(p) for p in probe]
    assert len(index) == len(want)
    assert all(index[n] == k for n, k in want.items()) and (12345 in index) == (12345 in want)
    with pytest.raises(KeyError):
        index[-5]
    again = IdIndex.of(ids)
    assert [again.get(n) for n in ids[::50].tolist()] == list(range(0, 5000, 50))
    with pytest.raises(ValueError, match='not unique'):
        IdIndex.of(np.array([3, 1, 3]))


def test_symmetric_rows_round_trip_exactly(rng) -> None:
    A = rng.normal(size=(40, 6, 6))
    S = A @ np.swapaxes(A, 1, 2)
    S = 0.5 * (S + np.swapaxes(S, 1, 2))  # exactly symmetric, as the aligner stores them
    rows = SymRows()
    for s in S:
        rows.append(s)
    np.testing.assert_array_equal(rows.full(), S)
    np.testing.assert_array_equal(rows.a[[3, 1, 30]], S[[3, 1, 30]])
    np.testing.assert_array_equal(rows[7], S[7])
    assert rows.packed.shape == (40, 21)
    arr = SymArray(4)
    arr[[0, 2]] = S[:2]
    arr[3] = 0.0
    np.testing.assert_array_equal(arr[[0, 2, 3]], np.stack([S[0], S[1], np.zeros((6, 6))]))


def test_track_ranges_and_lists() -> None:
    track = np.array([4, 4, 4, 9, 9, 2])
    ranges = TrackRanges.of(track)
    assert ranges[4].tolist() == [0, 1, 2] and ranges[2].tolist() == [5] and 9 in ranges
    ranges.add(2, 6)
    assert ranges[2].tolist() == [5, 6]
    with pytest.raises(ValueError, match='not contiguous'):
        TrackRanges.of(np.array([1, 1, 2, 1]))
    lists = TrackLists.of(np.array([5, 3, 5, 5]), np.array([2, 0, 7, 1]))
    assert lists[5].tolist() == [1, 2, 7] and lists.get(3).tolist() == [0]
    assert lists.get(8, []) == []
    lists.add({3, 8}, 9)
    assert lists[3].tolist() == [0, 9] and lists[8].tolist() == [9]


def test_pruned_duplicate_keys_refuse_exactly_what_the_full_set_did() -> None:
    """Re-delivering every measurement of a survey: with the duplicate-key set pruned after
    every few connections, each is refused for the same reason as with the full set: a
    duplicate, whether its nodes are in the window or frozen (the frozen tracks' keys are
    answered from the connection table, :mod:`ga_ros.core.window.received`); a new
    measurement to a frozen node is refused as ``frozen``."""
    sc = aerial_scenario(n_tracks=4, positions_per_swath=8)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(4))
    ms = sc.measurements(nm.z, nm.cov)
    reasons = []
    for pairs_min in (8, 10**9):
        al = TrackWindowAligner(AlignerConfig(window_tracks=2), sc.T_world_node[0])
        al._PAIRS_MIN = pairs_min
        al.add_measurements(ms)
        if pairs_min == 8:
            al.state.prune_pairs()
            assert 0 < len(al.state.pairs) < len(ms) - 50   # the frozen tracks' keys are gone
        got = al.add_measurements(ms)
        assert got.n_accepted == 0
        reasons.append(got.rejected)
        new = [replace(m, z=np.asarray(m.z) + 1e-3) for m in ms[:5]]   # not received before
        assert al.add_measurements(new).rejected == {'frozen': 5}
    assert reasons[0] == reasons[1] == {'duplicate': len(ms)}


if __name__ == '__main__':
    from ga_ros.runtime import limit_blas_threads

    REFERENCE.parent.mkdir(exist_ok=True)
    with limit_blas_threads():  # as the tests run (conftest.py)
        np.savez_compressed(REFERENCE, **{f'{p}/{k}': v for p in POLICIES
                                          for k, v in seeded_run(p).items()})
    print(f'wrote {REFERENCE}', file=sys.stderr)
