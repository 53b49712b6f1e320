"""The map frame's geodetic origin beside a state file: written atomically, read back, cleared
with the state, never over a foreign file, a damaged file refused with what to do."""

from __future__ import annotations

import json

import pytest

from ga_ros.errors import ForeignFileError, FormatError
from ga_ros.pipeline.journal import clear_state, datum_path, read_datum, write_datum


def test_written_read_back_and_cleared_with_the_state(tmp_path) -> None:
    state = tmp_path / 'survey.npz'
    assert read_datum(state) is None
    write_datum(state, (47.3977, 8.5456, 488.25))
    assert read_datum(state) == (47.3977, 8.5456, 488.25)
    assert json.loads(datum_path(state).read_text()) == {'datum_lla': [47.3977, 8.5456, 488.25]}
    assert datum_path(state) in clear_state(state)
    assert not datum_path(state).exists() and read_datum(state) is None


def test_a_foreign_file_is_left_alone_and_damage_is_refused(tmp_path) -> None:
    state = tmp_path / 'survey.npz'
    datum_path(state).write_text('{"other": 1}')
    with pytest.raises(ForeignFileError):
        write_datum(state, (1.0, 2.0, 3.0))
    with pytest.raises(ForeignFileError):
        clear_state(state)
    assert datum_path(state).read_text() == '{"other": 1}'
    with pytest.raises(FormatError, match='move it aside'):
        read_datum(state)
    datum_path(state).write_text('{"datum_lla": [1.0, NaN, 3.0]}')
    with pytest.raises(FormatError, match='lat_deg'):
        read_datum(state)
    with pytest.raises(FormatError):
        write_datum(tmp_path / 'b.npz', (1.0, 2.0))
