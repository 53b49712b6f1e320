""":meth:`InputFrontEnd.map_to_odom <ga_ros.pipeline.inputs.InputFrontEnd.map_to_odom>`: the
newest row of the corrected path that is a keyframe of the first input, found without reading
the rows that can never be one (a restored state's nodes, numbered before the input's), and
equal to the walk over every row that it replaces."""

from __future__ import annotations

import numpy as np
from bag_fixtures import odometry_msg

from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.inputs import InputFrontEnd, InputSpec


def _front(first: int | None = None) -> InputFrontEnd:
    front = InputFrontEnd([InputSpec('/odom', 'odometry',
                                     OdometryInputConfig('odom0', keyframe_travel_m=1.0))])
    if first is not None:
        front.continue_from(first, 7)
    return front


def _drive(front: InputFrontEnd, n: int, rng: np.random.Generator) -> None:
    odo = front.inputs[front.primary]
    k0 = odo.stats.samples
    for k in range(k0, k0 + n):
        T = se3.from_translation_rotvec([0.6 * k, 0.1 * np.sin(k), 0.0],
                                        [0.0, 0.0, 0.05 * np.cos(k) + rng.normal(0, 0.01)])
        step = front.sample('odom0', odometry_msg(T, 10 ** 9 + k * 10 ** 8))
        assert not step.error, step.error


def _walk(front: InputFrontEnd, ids: np.ndarray, T_map: np.ndarray) -> np.ndarray | None:
    """The walk over every row, newest first (the reference)."""
    for k in range(len(ids) - 1, -1, -1):
        try:
            T_odom_k = front.keyframe_pose(int(ids[k]))
        except InputError:
            continue
        return T_map[k] @ se3.inverse(T_odom_k)
    return None


def _same(a, b) -> bool:
    return (a is None and b is None) or (a is not None and b is not None
                                         and np.array_equal(a, b))


def test_equal_to_the_walk_over_every_row_on_growing_paths() -> None:
    rng = np.random.default_rng(5)
    for first in (None, 40):
        front = _front(first)
        restored = list(range(0, 40)) if first else []   # a restored state's nodes
        ids = list(restored)
        hits = 0
        for _ in range(30):
            _drive(front, int(rng.integers(0, 4)), rng)
            lo, end = front.inputs[front.primary].keyframe_ids
            new = [i for i in range(lo, end) if i not in ids]
            ids += [int(i) for i in rng.permutation(new)][:max(len(new) - 1, 0)]
            if rng.random() < 0.2:
                ids.append(10_000 + len(ids))               # a node of no keyframe
            arr = np.array(ids, np.int64)
            T = se3.exp(rng.normal(size=(len(ids), 6)))
            got, want = front.map_to_odom(arr, T), _walk(front, arr, T)
            assert _same(got, want)
            hits += want is not None
        assert hits >= 10


def test_after_a_restart_the_restored_rows_are_read_once() -> None:
    rng = np.random.default_rng(6)
    n_restored = 5000
    front = _front(n_restored)
    ids = np.arange(n_restored, dtype=np.int64)
    T = se3.exp(rng.normal(size=(n_restored, 6)))
    assert front.map_to_odom(ids, T) is None                 # no keyframe yet: nothing read
    assert front._no_keyframe_rows[0] == 0
    _drive(front, 3, rng)                                    # keyframes, not in the path yet
    assert front.map_to_odom(ids, T) is None
    assert front._no_keyframe_rows == (n_restored, n_restored - 1)
    # the next calls read only the rows after them: restored ids changed there go unseen
    seen = ids.copy()
    seen[:-1] = n_restored                                   # as if keyframes (they are not)
    assert front.map_to_odom(seen, T) is None
    lo, end = front.inputs[front.primary].keyframe_ids
    ids2 = np.append(ids, np.arange(lo, end - 1))
    T2 = np.concatenate([T, se3.exp(rng.normal(size=(end - 1 - lo, 6)))])
    got = front.map_to_odom(ids2, T2)
    assert _same(got, _walk(front, ids2, T2)) and got is not None
    # another path (shorter, or other ids where the rows were read): read again from the start
    assert _same(front.map_to_odom(ids2[:10], T2[:10]), _walk(front, ids2[:10], T2[:10]))
