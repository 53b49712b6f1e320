"""The ROS-free alignment session: typed rejection counts, and recovery from its state files
equals the live state (checked against the aligner fed directly)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError, Reason
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample


@pytest.fixture(scope='module')
def measurements() -> list:
    return aerial_sample(n_tracks=3, positions_per_swath=6, noise_pct=5.0, seed=9).measurements


def test_reason_is_typed_and_defaults_to_invalid() -> None:
    assert InputError('x').reason == Reason.INVALID
    err = InputError('x', reason='duplicate')
    assert err.reason is Reason.DUPLICATE and err.reason == 'duplicate'
    with pytest.raises(ValueError):
        InputError('x', reason='no such reason')


def test_step_counts_rejections_by_reason(measurements: list) -> None:
    session = AlignmentSession(AlignerConfig(window_tracks=2))
    direct = TrackWindowAligner(AlignerConfig(window_tracks=2))
    n_updates = 0
    for k, m in enumerate(measurements):
        out = session.step(m)
        direct.add_measurement(m)
        assert out.accepted
        n_updates += len(out.updates)
        if k == 5:
            again = session.step(m)  # an identical re-delivery
            assert not again.accepted and again.reason is Reason.DUPLICATE
    values = session.diagnostic_values()
    assert values['rejected'] == 1 and values['rejected/duplicate'] == 1
    assert values['measurements_accepted'] == len(measurements)
    assert values['updates'] == n_updates == 2
    np.testing.assert_array_equal(session.aligner.corrected_path().T_world_node,
                                  direct.corrected_path().T_world_node)


@pytest.mark.parametrize('damage', ['none', 'snapshot'])
def test_resume_equals_the_live_state(tmp_path: Path, measurements: list, damage: str) -> None:
    state = tmp_path / 'state.npz'
    live = AlignmentSession(AlignerConfig(window_tracks=2), SessionConfig(str(state)))
    assert live.resume() is None        # nothing to resume; opens the journal
    for m in measurements:
        live.step(m)
    live.close()
    if damage == 'snapshot':
        corrupt_snapshot(state)
    warnings: list[str] = []
    again = AlignmentSession(AlignerConfig(window_tracks=2), SessionConfig(str(state)),
                             warn=warnings.append)
    how = again.resume()
    assert how is not None and how.startswith('snapshot' if damage == 'none' else 'journal:')
    assert bool(warnings) == (damage == 'snapshot')
    a, b = live.aligner.corrected_path(), again.aligner.corrected_path()
    np.testing.assert_array_equal(a.node_ids, b.node_ids)
    np.testing.assert_array_equal(a.T_world_node, b.T_world_node)
    again.close()


def corrupt_snapshot(state: Path) -> None:
    """Flip one byte in the middle of a ga_ros snapshot (its header stays: a corrupt state,
    not a foreign file)."""
    data = bytearray(state.read_bytes())
    data[len(data) // 2] ^= 0xFF
    state.write_bytes(bytes(data))
