"""``refine_executor='auto'`` (the default): a snapshot smaller than
``worker.INLINE_BELOW_CONNECTIONS`` connections is refined inline at its hand-off, a larger one
in the worker process, and the path is bit for bit the one of either executor alone."""

from __future__ import annotations

import numpy as np
from solver_problems import noisy_aerial_survey

from ga_ros.core.window import AlignerConfig, TrackWindowAligner, worker


def _run(executor: str, ms, T0, sizes: list[int] | None = None):
    cfg = AlignerConfig(window_tracks=2, refine_every_tracks=1, refine_executor=executor,
                        refine_horizon_tracks=4, refine_relinearize_sigma=0.0)
    al = TrackWindowAligner(cfg, T0)
    refiner = al.handoff.refiner
    submit = refiner.submit
    pools = []

    def recording(snap, due):
        submit(snap, due)
        if sizes is not None:
            sizes.append(len(snap.src))
        pools.append(refiner._pool is not None)

    refiner.submit = recording
    ups = [up for m in ms for up in al.add_measurement(m)]
    ups.append(al.finish_track())
    path = al.corrected_path().T_world_node.copy()
    al.close()
    return path, [u.refined_after_tracks for u in ups if u is not None], pools


def test_auto_is_inline_when_small_and_process_when_large_bit_for_bit(monkeypatch):
    sc, _, ms = noisy_aerial_survey(8, 6, 2.0, 5)
    sizes: list[int] = []
    inline, installed, pools = _run('inline', ms, sc.T_world_node[0], sizes)
    assert len(sizes) >= 3 and not any(pools)
    # the default threshold: every snapshot of this small survey is refined inline, no worker
    assert max(sizes) < worker.INLINE_BELOW_CONNECTIONS
    auto, installed_auto, pools = _run('auto', ms, sc.T_world_node[0])
    assert not any(pools), 'a small snapshot started a worker process'
    assert installed_auto == installed
    np.testing.assert_array_equal(auto, inline)
    # a threshold between the snapshots' sizes: the first ones inline, the later in the process
    cut = int(np.median(sizes))
    monkeypatch.setattr(worker, 'INLINE_BELOW_CONNECTIONS', cut)
    mixed, installed_mixed, pools = _run('auto', ms, sc.T_world_node[0])
    assert pools == [s >= cut or any(t >= cut for t in sizes[:k])
                     for k, s in enumerate(sizes)]
    assert any(pools) and not all(pools)
    assert installed_mixed == installed
    np.testing.assert_array_equal(mixed, inline)
    process, installed_process, _ = _run('process', ms, sc.T_world_node[0])
    assert installed_process == installed
    np.testing.assert_array_equal(process, inline)
