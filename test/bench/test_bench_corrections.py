"""``ga-ros bench corrections`` runs and prints what it compares (figures: docs/benchmarks.md)."""

from __future__ import annotations

from ga_ros.cli.main import main


def test_bench_corrections_prints_the_whole_path_and_each_tracker(capsys) -> None:
    assert main(['bench', 'corrections', '--tracks', '2', '--refine-every', '0',
                 '--thresholds', '0.01:0.001', '0:0']) == 0
    out = capsys.readouterr().out
    assert '408 keyframes, 2 window updates (aligner: window_tracks 5, refine_every' in out
    rows = [line for line in out.splitlines() if line.startswith('| ')][1:]  # no header
    assert rows[0].startswith('| whole path (ga/corrected_path) | ')
    assert rows[1].startswith('| corrections (0.01 m, 0.001 rad, the default) | ')
    assert rows[2].startswith('| corrections (0 m, 0 rad: every change) | ')
    whole, exact = ([c.strip() for c in row.split('|')] for row in (rows[0], rows[2]))
    # the ratio is what the (rounded) mean bytes say
    ratio = 100 * float(exact[2].replace(',', '')) / float(whole[2].replace(',', ''))
    assert exact[3].endswith(' %') and abs(float(exact[3][:-2]) - ratio) < 0.1
    # the floor: the keyframes added (408 in 2 updates) at the whole path's bytes a pose
    floor = next(line for line in out.splitlines() if line.startswith('keyframes added'))
    assert floor.startswith('keyframes added per update: 204 (mean); at the whole path of 72 ')
    pct = float(floor.split(' bytes, ')[1].split(' %')[0])
    assert abs(pct - 100 * 204 * 72 / float(whole[2].replace(',', ''))) < 0.2
