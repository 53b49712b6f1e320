"""The corrected path kept in step with the aligner (:mod:`ga_ros.pipeline.path_mirror`): after
every input it equals, bit for bit, the path copied from scratch, and its serialized
``nav_msgs/Path`` equals :func:`~ga_ros.io.cdr.path_cdr` of that path, on a survey with fixes,
background refinements, several updates between two calls, a restart and ``refine_batch``,
while copying only the rows an update could change."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig
from ga_ros.io.cdr import PathCdr, path_cdr
from ga_ros.pipeline.journal import recover
from ga_ros.pipeline.path_mirror import PathMirror, newest_not_in_track
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.sim.fix_survey import line_fix_survey

INLINE = AlignerConfig(window_tracks=2, datum='fixes', refine_every_tracks=1,
                       refine_executor='inline', fix_gate_prob=0.0)
DEFAULT = AlignerConfig(datum='fixes')


def _entries(n_tracks: int = 14, per: int = 6, seed: int = 3) -> list:
    return line_fix_survey(np.random.default_rng(seed), n_tracks, per,
                           sources=((3, 'gnss0', 0.3), (5, 'usbl1', 0.5)))


def _give(session: AlignmentSession, e) -> None:
    if isinstance(e, Measurement):
        session.step(e)
    else:
        try:
            session.add_fix(*e)
        except Exception:  # noqa: BLE001 - a refused fix (frozen node) changes nothing
            pass


def _check(mirror: PathMirror, aligner, every_row: bool = False) -> int:
    """Sync and compare with the path from scratch; returns the first row copied."""
    got = mirror.sync(aligner, every_row)
    ref = aligner.corrected_path()
    for name in ('node_ids', 'track_ids', 'stamps_ns', 'T_world_node', 'frozen'):
        a, b = getattr(got, name), getattr(ref, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    if len(ref.node_ids):
        stamp = int(ref.stamps_ns[-1])
        assert mirror.path_message(stamp) == path_cdr(ref.T_world_node, ref.stamps_ns, 'map',
                                                      stamp)
        lo, movable = mirror.movable_rows()
        assert ref.frozen[:lo].all()
        assert np.array_equal(np.flatnonzero(~ref.frozen), lo + np.flatnonzero(movable))
    return mirror.changed_from


@pytest.mark.parametrize('config', [INLINE, DEFAULT], ids=['inline', 'default'])
def test_the_mirror_equals_the_path_from_scratch_after_every_input(config) -> None:
    session = AlignmentSession(config)
    mirror = PathMirror('map')
    firsts = []
    counted = 0
    for e in _entries():
        _give(session, e)
        firsts.append(_check(mirror, session.aligner))
        # the open track's nodes, counted among the rows an update can change
        open_track = session.aligner.open_track
        want = (0 if open_track is None else int(np.count_nonzero(
            session.aligner.corrected_path().track_ids == open_track)))
        assert session.dead_reckoned_nodes() == want
        counted += want > 0
    assert counted > 20
    session.aligner.close()
    assert session.aligner.stats.n_updates >= 13
    # it copied only the rows an update could change once the survey was long enough
    assert max(firsts) > 30


def test_several_updates_between_two_calls_and_a_batch_copy_every_row() -> None:
    session = AlignmentSession(INLINE)
    mirror = PathMirror('map')
    entries = _entries()
    for k, e in enumerate(entries):
        _give(session, e)
        if k % 17 == 0:   # about three tracks between two calls
            _check(mirror, session.aligner)
    _check(mirror, session.aligner)
    session.aligner.refine_batch()
    assert _check(mirror, session.aligner, every_row=True) == 0
    session.aligner.close()


def test_a_restart_gives_the_restored_path_then_follows_it(tmp_path) -> None:
    state = tmp_path / 'state.ga'
    entries = _entries()
    cut = len(entries) // 2
    session = AlignmentSession(INLINE, SessionConfig(str(state), True))
    assert session.resume() is None
    mirror = PathMirror('map')
    for e in entries[:cut]:
        _give(session, e)
        _check(mirror, session.aligner)
    session.journal.close()   # killed: the journal holds what the snapshot does not
    session.aligner.close()
    restored = AlignmentSession(INLINE, SessionConfig(str(state), True))
    assert restored.resume() is not None
    assert _check(mirror, restored.aligner) == 0   # another aligner: every row again
    for e in entries[cut:]:
        _give(restored, e)
        _check(mirror, restored.aligner)
    restored.aligner.close()
    ref = recover(state, INLINE).aligner   # the journal of the whole run gives the same path
    assert np.array_equal(ref.corrected_path().T_world_node[:mirror.n],
                          mirror.path().T_world_node[:len(ref.corrected_path().node_ids)])
    ref.close()


def test_path_cdr_rows_updated_in_place_give_the_bytes_from_scratch() -> None:
    from ga_ros.geometry import se3
    rng = np.random.default_rng(0)
    for frame in ('map', 'm', 'abcdefg', 'ab'):
        buf = PathCdr(frame)
        T = se3.from_translation_rotvec(rng.normal(size=(60, 3)), rng.normal(size=(60, 3)))
        stamps = np.sort(rng.integers(0, 10 ** 12, 60))
        n = 0
        for _ in range(40):
            lo = int(rng.integers(0, n + 1))
            n = max(lo, min(60, n + int(rng.integers(-2, 6))))
            T[lo:n] = se3.from_translation_rotvec(rng.normal(size=(n - lo, 3)),
                                                  rng.normal(size=(n - lo, 3)))
            buf.update(T[lo:n], stamps[lo:n], lo)
            s = int(rng.integers(0, 10 ** 12))
            assert buf.message(s) == path_cdr(T[:n], stamps[:n], frame, s)


def test_newest_not_in_track_reads_back_only_the_open_track() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        t = np.sort(rng.integers(0, 6, int(rng.integers(0, 120))))
        track = int(rng.integers(0, 7)) if rng.random() < 0.9 else None
        other = np.flatnonzero(t != track) if track is not None else np.arange(t.size)
        want = int(other[-1]) if other.size else None
        assert newest_not_in_track(t, track) == want
