"""``ga-ros replay --calibrate``: a Nav2-shaped bag (``/odom`` with all-zero covariance, a yaw-rate
bias and a 2 % scale error; ``/amcl_pose`` at 1 Hz, written here with rosbags) replayed with
the final batch's self-calibration: the odometry's corrections are recovered within a few
sigma of the truth, printed and in ``summary.json``, and the corrected trajectory is closer to
the truth than without them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from bag_fixtures import ODOMETRY, POSE_COV_STAMPED, odometry_msg, pose_cov_stamped_msg
from test_fixes_replay import T0_NS, _drifting, _evaluate, _path

from ga_ros.core.window import AlignerConfig
from ga_ros.inputs.absolute import AbsoluteInputConfig
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.io.bag_writer import BagWriter
from ga_ros.pipeline.absolute import AbsoluteSpec
from ga_ros.pipeline.inputs import InputSpec
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.inputs import InputTopics
from ga_ros.replay.pipeline import replay
from ga_ros.replay.text import calibration_lines, result_text

YAW_BIAS_PER_STEP = 6e-4  # rad per 0.1 s step of the odometry: 6e-3 rad/s
SCALE = 1.02  # the odometry's translation is 2 % long


def test_replay_calibrate_recovers_the_odometry_bias(tmp_path: Path) -> None:
    rng = np.random.default_rng(21)
    legs = np.array([[0, 0], [30, 0], [30, 8], [0, 8], [0, 16], [30, 16], [30, 24], [0, 24]],
                    float)
    gt = _path(legs, 0.5)
    odom = _drifting(gt, rng, YAW_BIAS_PER_STEP, SCALE)
    stamps = T0_NS + (np.arange(len(gt)) * 1e8).astype(np.int64)
    with BagWriter(tmp_path / 'in') as bag:
        for k, (s, T) in enumerate(zip(stamps, odom)):
            s = int(s)
            bag.write('/odom', ODOMETRY, odometry_msg(gt[0] @ T, s), s)
            if k % 10 == 5:
                T_m = gt[k].copy()
                T_m[:2, 3] += rng.normal(0, 0.3, 2)
                cov = np.zeros((6, 6))
                cov[0, 0] = cov[1, 1] = 0.3 ** 2
                cov[5, 5] = 1.0
                bag.write('/amcl_pose', POSE_COV_STAMPED,
                          pose_cov_stamped_msg(T_m, s, cov, 'map'), s)
    spec = InputSpec('/odom', 'odometry', OdometryInputConfig('odom0', keyframe_travel_m=0.5))
    amcl = AbsoluteSpec('/amcl_pose', 'pose_cov', AbsoluteInputConfig('amcl0', frame_id='map'))
    rmse, online = {}, {}
    for calibrate in (False, True):
        cfg = ReplayConfig(inputs=InputTopics((spec,), absolutes=(amcl,)), plot=False,
                           aligner=AlignerConfig(datum='fixes', refine_executor='inline'),
                           calibrate=calibrate)
        out = tmp_path / f'out{int(calibrate)}'
        res = replay(tmp_path / 'in', out, cfg)
        rmse[calibrate] = _evaluate(res, stamps, gt, odom)[0]
        online[calibrate] = _evaluate(res, stamps, gt, odom, 'trajectory_online')[0]
    summary = json.loads((out / 'summary.json').read_text())
    # every odometry motion is odom0's in the final batch, those stored corrected by the
    # online calibration too (none left to the unnamed default group 'motion')
    assert {p['source'] for p in summary['calibration']['parameters']
            if p['name'] in ('scale', 'yaw_rate')} == {'odom0'}, summary['calibration']
    cal = {p['name']: p for p in summary['calibration']['parameters']
           if p['source'] == 'odom0'}
    assert cal['yaw_rate']['estimated'] and cal['scale']['estimated'], cal
    truth = {'yaw_rate': -YAW_BIAS_PER_STEP * 10.0, 'scale': 1.0 / SCALE - 1.0}
    for name, value in truth.items():
        assert abs(cal[name]['value'] - value) < 4 * cal[name]['sigma'], (name, cal[name])
    lines = calibration_lines(summary['calibration'])
    assert any('odom0' in t and 'yaw_rate' in t and '+-' in t for t in lines)
    assert rmse[True] < 0.8 * rmse[False], rmse
    # online (--calibrate calibrates the window aligner too): the last online estimate of the
    # yaw rate, with its sigma, in summary.json and the text; the online path closer to the truth
    on = {p['name']: p for p in summary['online_calibration']['parameters']
          if p['source'] == 'odom0'}
    assert on['yaw_rate']['estimated'], on
    assert abs(on['yaw_rate']['value'] - truth['yaw_rate']) < 4 * on['yaw_rate']['sigma'], on
    assert summary['online_calibration']['estimates'] > 0
    text = result_text(res)
    lines = calibration_lines(summary['online_calibration'], 'online, the last estimate')
    assert any('odom0' in t and 'yaw_rate' in t and '+-' in t for t in lines)
    assert 'calibration (online, the last estimate' in text, text
    assert online[True] < 0.8 * online[False], online


def test_command_line_calibrate() -> None:
    """``--calibrate`` sets ``ReplayConfig.calibrate`` (off by default)."""
    import argparse

    from ga_ros.cli.commands.replay import add_replay_arguments, replay_config

    p = argparse.ArgumentParser()
    add_replay_arguments(p)
    assert not replay_config(p.parse_args([]), progress=False).calibrate
    assert replay_config(p.parse_args(['--calibrate']), progress=False).calibrate


def test_calibration_lines_name_the_reason() -> None:
    """The printout gives an estimated parameter with its sigma and a fixed one with its
    reason (the summary's plain data, as ``summary.json`` holds it)."""
    from ga_ros.core.calibration import AdditionalParameter, CalibrationReport

    rep = CalibrationReport([
        AdditionalParameter('odom0', 'yaw_rate', 'rad/s', 0.005, 0.0004, 12.5, 3.3, 0.2, True),
        AdditionalParameter('odom0', 'scale', '1', reason='not significant: |t| 0.8 < 3.3')],
        alpha=0.001)
    d = json.loads(json.dumps(rep.as_dict()))
    assert d['parameters'][1]['sigma'] is None  # NaN is not JSON
    lines = calibration_lines(d)
    assert 'yaw_rate' in lines[1] and '+- 0.0004 rad/s' in lines[1]
    assert 'not estimated (not significant' in lines[2]
    assert calibration_lines({}) == []


def test_calibration_lines_show_the_noise_factors() -> None:
    """The re-estimated noise of a calibrated source (CalibrationReport.noise) in the text,
    and its summary.json form is plain JSON (no NaN)."""
    import json

    from ga_ros.core.calibration import CalibrationReport, NoiseFactor

    rep = CalibrationReport(noise=[
        NoiseFactor('odom0', 'rotation', factor=0.05, estimate=0.05, sigma=0.02,
                    redundancy=8.4, stated_ratio=0.29, quantiles=(0.13, 2.9), applied=True),
        NoiseFactor('odom0', 'translation', redundancy=0.6)], alpha=0.001, sigma0_sq=1.0)
    d = json.loads(json.dumps(rep.as_dict(), allow_nan=False))
    lines = calibration_lines({**d, 'parameters': [
        {'source': 'odom0', 'name': 'yaw_rate', 'estimated': True, 'value': 0.005,
         'sigma': 0.0003, 'unit': 'rad/s', 'test': 17.0}]})
    assert any('rotation noise' in ln and '0.05 +- 0.02 applied' in ln for ln in lines), lines
    assert any('translation noise' in ln and 'stated covariance kept' in ln for ln in lines)
    assert d['noise'][1]['quantiles'] == [None, None]
