"""Gaps that heal in a live node: an alignment node process killed (kill -9) and restarted on
its state file, which misses what was published while it was down, still publishes every node;
no measurement is rejected as ``unknown_source``."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip('rclpy')

from live_node import live_node  # noqa: E402

from ga_ros.core.window import AlignerConfig  # noqa: E402
from ga_ros.pipeline.session import AlignmentSession  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.harness import domain_id  # noqa: E402
from ga_ros.sim.aerial import aerial_scenario  # noqa: E402
from ga_ros.sim.noise import NoiseModel, perturb  # noqa: E402


@pytest.mark.ros
def test_a_restarted_node_that_missed_measurements_keeps_every_node(tmp_path, rng) -> None:
    dom = domain_id(77)
    sc = aerial_scenario(n_tracks=3, positions_per_swath=6)
    noisy = perturb(sc.true_motions(), NoiseModel(3.0, sc.depth_m), rng)
    ms = [conv.odometry_to_measurement(conv.measurement_to_odometry(m))
          for m in sc.measurements(noisy.z, noisy.cov)]
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 1) + 12   # inside track 1
    lost = [m.dst_id for m in ms[cut:]][:1]
    down = next(k for k, m in enumerate(ms) if m.dst_id >= lost[0] + 3)  # 3 nodes' worth
    stream = ms[:cut] + ms[down:]
    state = tmp_path / 'state.npz'
    # volatile: nothing published while the node was down comes back (a real gap)
    params = {'state_file': str(state), 'window_tracks': 2, 'diagnostics_period_sec': 0.1,
              'measurement_durability': 'volatile', 'allow_finish_track': True}
    with live_node(dom, params, tmp_path / 'node.log') as node:
        client = node.client
        client.publish(ms[:cut])
        client.wait_received(cut, proc=node.proc)
        node.kill_and_restart(lambda: client.publish(ms[cut:down]))  # nobody listens: lost
        paths: list = []
        client.subscribe_path(paths)
        client.publish(ms[down:])
        client.wait_received(len(ms) - down, proc=node.proc)
        resp = client.call('finish_track')
        assert resp.success, resp.message
        ref = AlignmentSession(AlignerConfig(window_tracks=2))  # the same stream, no restart
        for m in stream:
            ref.step(m)
        ref.finish_track()
        want = ref.aligner.corrected_path()
        every = {ms[0].src_id} | {m.dst_id for m in ms}
        assert want.node_ids.size == len(every)                # every node, even the missed
        client.spin_until(lambda: paths and len(paths[-1][1].poses) == want.node_ids.size, 20,
                          'the final path', node.proc)
        np.testing.assert_allclose(conv.path_msg_to_poses(paths[-1][1]), want.T_world_node,
                                   atol=1e-6)
        client.spin_until(lambda: client.diag_int('held_measurements') == 0, 10, 'diagnostics',
                          node.proc)
        assert client.diag_int('rejected/unknown_source', 0) == 0, client.diagnostics
        assert client.diag_int('rejected') == 0, client.diagnostics
        assert client.diag_int('unjoined_nodes') == 0, client.diagnostics
        assert node.proc.poll() is None
