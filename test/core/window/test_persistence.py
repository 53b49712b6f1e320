"""Aligner snapshots (core/window/persistence.py) and the safe-write helper (safe_write.py)."""

from __future__ import annotations

import json
import os
import zlib
from dataclasses import asdict, replace

import numpy as np
import pytest

from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import _PREFIX, MAGIC, is_state_file, load_state, save_state
from ga_ros.errors import CorruptFileError, ForeignFileError, InputError, UnsafePathError
from ga_ros.safe_write import atomic_write, move_aside
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb


def _survey(n_tracks=4, per_swath=6, seed=5):
    sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=per_swath)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(seed))
    return sc, sc.measurements(nm.z, nm.cov)


def _aligner(ms, policy='weighted', upto=None):
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, freeze_policy=policy))
    al.add_measurements(ms[:upto])
    return al


def _state(al):
    """Every array and counter of an aligner, for an exact comparison."""
    p = al.corrected_path()
    src, dst, z, cross, status = al.connection_arrays()
    st = al.stats
    return dict(ids=p.node_ids, tracks=p.track_ids, stamps=p.stamps_ns, T=p.T_world_node,
                frozen=p.frozen, src=src, dst=dst, z=z, cross=cross, status=status,
                ccov=al.connection_covariances(), cov=al.state.cov[:len(al.state.ids)],
                priors=[np.concatenate([np.ravel(a.toarray() if hasattr(a, 'toarray') else a)
                                        .astype(float) for a in p]) for p in al.state.priors],
                counts=(st.n_nodes, st.n_connections, st.n_rejected, st.tracks_in_window,
                        st.n_updates, st.n_outliers, al.open_track))


@pytest.mark.parametrize('policy', ['weighted', 'marginal'])
def test_round_trip_is_exact_and_resumes_like_an_uninterrupted_run(tmp_path, policy):
    sc, ms = _survey()
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 3) + 4   # mid-track, tracks frozen
    al = _aligner(ms, policy, cut)
    save_state(al, tmp_path / 'state', journal_records=cut)
    back = load_state(tmp_path / 'state')
    assert back.journal_records == cut
    a, b = _state(al), _state(back.aligner)
    al.state.prune_pairs()   # the duplicate keys a measurement can still hit (no frozen node)
    # the duplicate test is restored too
    assert back.aligner.state.pairs == al.state.pairs and al.state.pairs
    for key in a:
        if key == 'priors':
            assert len(a[key]) == len(b[key]) and a[key]   # both policies carry joint priors
            for x, y in zip(a[key], b[key]):
                np.testing.assert_array_equal(x, y)
        elif key == 'counts':
            assert a[key] == b[key]
        else:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    # covariances of window nodes are recomputed on demand from the same window problem, at
    # the saved estimate: the uninterrupted aligner's come from its update's last
    # factorisation (solve(factor_at_solution=False)), a fraction of a correction away
    window_ids = al.corrected_path().node_ids[al.state.last_window]
    ref = al.covariances(window_ids[1:6])
    np.testing.assert_allclose(back.aligner.covariances(window_ids[1:6]), ref, rtol=1e-3,
                               atol=1e-4 * np.abs(ref).max())
    for x in (al, back.aligner):
        x.add_measurements(ms[cut:])
        x.finish_track()
    np.testing.assert_allclose(back.aligner.corrected_path().T_world_node,
                               al.corrected_path().T_world_node, atol=1e-9)


#: The flat config a version-1 snapshot header holds (solver fields beside the aligner's).
OLD_FLAT_CONFIG = {'window_tracks': 2, 'freeze_policy': 'weighted', 'model': 'se3',
                   'max_iterations': 10, 'tolerance': 1e-7, 'damping': 'none',
                   'robust_loss': 'none', 'robust_scale': 3.0, 'outlier_chi2_prob': 0.99999}


def test_the_config_round_trips_nested_and_old_flat_headers_still_load(tmp_path):
    sc, ms = _survey(n_tracks=3)
    cfg = AlignerConfig(window_tracks=2, outlier_chi2_prob=0.999,
                        solver=replace(ALIGNER_SOLVER, tolerance=1e-7, robust_loss='huber'))
    al = TrackWindowAligner(cfg)
    al.add_measurements(ms)
    path = save_state(al, tmp_path / 'state')
    assert load_state(path).aligner.config == cfg                 # nested header
    # the same file as written before the solver settings were nested: a flat header
    buf = bytearray(path.read_bytes())
    _, version, hlen, _ = _PREFIX.unpack_from(buf)
    head = json.loads(bytes(buf[_PREFIX.size:_PREFIX.size + hlen]))
    nested = head['meta']['config']
    solver = nested.pop('solver')
    del solver['reuse_factor_below']                               # not saved before
    head['meta']['config'] = {**nested, **solver}
    header = json.dumps(head).encode()
    header += b' ' * (hlen - len(header))                          # arrays stay where they are
    assert len(header) == hlen
    buf[:_PREFIX.size] = _PREFIX.pack(MAGIC, version, hlen, zlib.crc32(header))
    buf[_PREFIX.size:_PREFIX.size + hlen] = header
    path.write_bytes(bytes(buf))
    back = load_state(path).aligner
    assert back.config == cfg
    np.testing.assert_array_equal(back.corrected_path().T_world_node,
                                  al.corrected_path().T_world_node)
    assert AlignerConfig.from_dict(asdict(cfg)) == cfg
    with pytest.raises(InputError, match='unknown aligner config fields'):
        AlignerConfig.from_dict({'window_tracks': 2, 'tolerence': 1e-7})


def test_version_one_npz_snapshots_are_still_read(tmp_path):
    """A snapshot in the old .npz layout (written here as the previous save() did) loads."""
    sc, ms = _survey(n_tracks=3)
    al = _aligner(ms)
    n = len(al.state.ids)
    meta = {'version': 1, 'config': OLD_FLAT_CONFIG,
            'tracks': al.state.tracks, 'finished': sorted(al.state.finished),
            'open_track': al.state.open_track,
            'rejected': al.state.rejected, 'n_updates': al.state.n_updates,
            'n_outliers': al.state.n_outliers, 'last_window': al.state.last_window.tolist()}
    np.savez_compressed(tmp_path / 'old.npz',
                        meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
                        T_first=al.state.T_first, ids=np.asarray(al.state.ids),
                        track=np.asarray(al.state.track),
                        stamp=np.asarray(al.state.stamp), T=al.state.T[:n], cov=al.state.cov[:n],
                        frozen=al.state.frozen[:n], src=al.state.src.a, dst=al.state.dst.a,
                        z=al.state.z.a,
                        ccov=al.connection_covariances(), cross=al.state.cross.a,
                        status=al.state.status.a.astype(np.int64),
                        n_priors=np.array(0))
    assert is_state_file(tmp_path / 'old.npz')
    back = load_state(tmp_path / 'old.npz').aligner
    al.state.prune_pairs()
    assert back.state.pairs == al.state.pairs
    assert back.config == AlignerConfig(window_tracks=2,
                                        solver=replace(ALIGNER_SOLVER, tolerance=1e-7))
    np.testing.assert_array_equal(back.corrected_path().T_world_node,
                                  al.corrected_path().T_world_node)
    save_state(back, tmp_path / 'old.npz')            # an old state of ours may be replaced
    assert (tmp_path / 'old.npz').read_bytes().startswith(MAGIC)


def test_a_foreign_file_is_never_overwritten_nor_read_as_a_state(tmp_path):
    sc, ms = _survey(n_tracks=2)
    al = _aligner(ms)
    notes = tmp_path / 'notes.txt'
    notes.write_text('my thesis\n')
    with pytest.raises(ForeignFileError, match='left untouched'):
        save_state(al, notes)
    with pytest.raises(ForeignFileError):
        load_state(notes)
    assert notes.read_text() == 'my thesis\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['notes.txt']   # no temporary left


@pytest.mark.parametrize('damage', ['flip_array_byte', 'flip_header_byte', 'truncate'])
def test_a_damaged_snapshot_is_detected(tmp_path, damage):
    sc, ms = _survey(n_tracks=2)
    path = save_state(_aligner(ms), tmp_path / 'state')
    data = bytearray(path.read_bytes())
    if damage == 'flip_array_byte':
        data[-200] ^= 0x10
    elif damage == 'flip_header_byte':
        data[40] ^= 0x01
    else:
        data = data[:len(data) // 2]
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptFileError):
        load_state(path)


def test_writes_never_follow_planted_symlinks(tmp_path):
    sc, ms = _survey(n_tracks=2)
    al = _aligner(ms)
    victim = tmp_path / 'victim'
    victim.write_text('precious')
    # links planted at the names the old code used for its temporary files
    for name in ('state.tmp.npz', 'state.json.tmp', '.state.tmp1.npz'):
        os.symlink(victim, tmp_path / name)
    save_state(al, tmp_path / 'state')
    assert victim.read_text() == 'precious'
    os.symlink(victim, tmp_path / 'linked')
    with pytest.raises(UnsafePathError):
        save_state(al, tmp_path / 'linked')
    with pytest.raises(UnsafePathError):
        load_state(tmp_path / 'linked')
    assert victim.read_text() == 'precious' and os.path.islink(tmp_path / 'linked')


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    target = tmp_path / 'f'
    atomic_write(target, b'old')

    def chunks():
        yield b'new, half'
        raise RuntimeError('disk full')

    with pytest.raises(RuntimeError):
        atomic_write(target, chunks())
    assert target.read_bytes() == b'old'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['f']


def test_move_aside_keeps_the_content_and_never_overwrites(tmp_path):
    f = tmp_path / 'j'
    f.write_bytes(b'one')
    a = move_aside(f)
    f.write_bytes(b'two')
    b = move_aside(f)
    assert a != b and a.read_bytes() == b'one' and b.read_bytes() == b'two'
    assert not f.exists() and a.name.startswith('j.corrupt-')


def test_version_two_files_load_and_unknown_versions_are_refused(tmp_path, monkeypatch):
    """Version 2 stored the covariances as full 6x6 matrices (written here as that version's
    save did); they load into the compact storage exactly. A newer version is refused with
    a message that says what to do."""
    from ga_ros.core.window import persistence
    from ga_ros.core.window.storage import unpack_sym6

    sc, ms = _survey(n_tracks=4)
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 3) + 2
    al = _aligner(ms, 'weighted', cut)
    state_of = persistence._state_of

    def version_two(aligner):
        meta, arrays = state_of(aligner)
        arrays['cov'] = unpack_sym6(arrays.pop('cov21'))
        arrays['ccov'] = unpack_sym6(arrays.pop('ccov21'))
        return meta, arrays

    with monkeypatch.context() as mp:
        mp.setattr(persistence, '_state_of', version_two)
        mp.setattr(persistence, 'FORMAT_VERSION', 2)
        path = save_state(al, tmp_path / 'v2')
    assert _PREFIX.unpack_from(path.read_bytes())[1] == 2
    back = load_state(path)
    assert back.version == 2
    a, b = _state(al), _state(back.aligner)
    for key in ('T', 'cov', 'ccov', 'status', 'src', 'dst', 'z'):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    for x in (al, back.aligner):
        x.add_measurements(ms[cut:])
        x.finish_track()
    np.testing.assert_array_equal(back.aligner.corrected_path().T_world_node,
                                  al.corrected_path().T_world_node)
    # a file from a newer ga_ros
    buf = bytearray(path.read_bytes())
    _, _, hlen, hcrc = _PREFIX.unpack_from(buf)
    buf[:_PREFIX.size] = _PREFIX.pack(MAGIC, 99, hlen, hcrc)
    path.write_bytes(bytes(buf))
    with pytest.raises(InputError, match='state format version 99, this ga_ros reads versions'):
        load_state(path)
