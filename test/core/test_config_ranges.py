"""Parameter ranges declared once on the config fields (:mod:`ga_ros.core.config_ranges`): the
dataclass, the replay's parameter reader and the node refuse the same values with the same
message; the former flat track settings are refused with their new names."""

from __future__ import annotations

import math
from dataclasses import fields, is_dataclass, replace

import pytest

from ga_ros.core.config_ranges import check_ranges, field_range, range_message, ranged
from ga_ros.core.solver import SolverConfig
from ga_ros.core.tracks import TrackRules
from ga_ros.core.window import AlignerConfig
from ga_ros.errors import InputError
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.params import config_from_params
from ga_ros.vo.odometry import VoConfig

RANGED = (AlignerConfig, SolverConfig, TrackRules)


def _outside(cls: type) -> list[tuple[str, object]]:
    """``(field, value)`` just outside each declared range of ``cls`` (below and above)."""
    out: list[tuple[str, object]] = []
    for f in fields(cls):
        rng = f.metadata.get('range')
        if rng is None:
            continue
        is_int = isinstance(getattr(cls(), f.name), int)
        step = 1 if is_int else max(1e-3, 1e-3 * abs(rng[1] - rng[0]))
        out += [(f.name, rng[0] - step), (f.name, rng[1] + step)]
    return out


CASES = [(cls, name, value) for cls in RANGED for name, value in _outside(cls)]


def test_every_ranged_config_declares_ranges() -> None:
    assert {cls for cls, _, _ in CASES} == set(RANGED)
    assert field_range(AlignerConfig, 'window_tracks') == (1, 1000)
    assert field_range(AlignerConfig, 'freeze_policy') is None


@pytest.mark.parametrize(('cls', 'name', 'value'), CASES,
                         ids=[f'{c.__name__}.{n}={v}' for c, n, v in CASES])
def test_outside_a_range_same_refusal_everywhere(cls: type, name: str, value: object) -> None:
    lo, hi = field_range(cls, name)
    assert not lo <= value <= hi  # the case is really outside
    with pytest.raises(InputError) as direct:
        replace(cls(), **{name: value})
    expected = f'{cls.__name__}.{name} = {value!r} is outside [{lo:g}, {hi:g}]'
    assert str(direct.value) == expected
    # the replay's reader, top level and as the nested field of the enclosing config
    with pytest.raises(InputError) as read:
        config_from_params(cls, {name: value})
    assert str(read.value) == expected
    outer = {SolverConfig: (AlignerConfig, 'solver.'), TrackRules: (OdometryInputConfig,
                                                                    'track.')}.get(cls)
    if outer is not None:
        with pytest.raises(InputError) as nested:
            config_from_params(outer[0], {outer[1] + name: value})
        assert str(nested.value) == expected


def test_inside_the_ranges_accepted_and_nan_refused() -> None:
    AlignerConfig(window_tracks=1000, prior_band=-1, refine_horizon_tracks=0,
                  solver=replace(AlignerConfig().solver, max_iterations=1))
    TrackRules('heading', swaths=1, heading_reversal_deg=180.0)
    assert range_message('C', 'x', 0.5, (0.0, 1.0)) is None
    assert 'outside' in range_message('C', 'x', math.nan, (0.0, 1.0))
    with pytest.raises(InputError, match=r'TrackRules.heading_reversal_deg = nan'):
        TrackRules(heading_reversal_deg=math.nan)


def test_check_ranges_on_any_dataclass() -> None:
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Demo:
        n: int = ranged(3, 1, 5)
        s: str = 'x'

    check_ranges(Demo())
    with pytest.raises(InputError, match=r'^Demo.n = 6 is outside \[1, 5\]$'):
        check_ranges(Demo(n=6))
    assert is_dataclass(Demo)


def test_former_flat_track_names_are_refused_with_the_new_name() -> None:
    with pytest.raises(InputError, match=r'odom0.track_mode was renamed to odom0.track.mode'):
        config_from_params(OdometryInputConfig, {'odom0.track_mode': 'distance'}, 'odom0.')
    with pytest.raises(InputError, match=r'track_length_m was renamed to odom1.track.length_m'):
        OdometryInputConfig.from_mapping('odom1', {'track_length_m': 5.0})
    with pytest.raises(InputError, match=r'swaths_per_track was renamed to track.swaths'):
        config_from_params(VoConfig, {'swaths_per_track': 2})
    cfg = OdometryInputConfig.from_mapping('odom1', {'track': {'mode': 'distance',
                                                               'length_m': 5.0}})
    assert cfg.track == TrackRules('distance', length_m=5.0)
    with pytest.raises(InputError, match='unknown track settings'):
        OdometryInputConfig.from_mapping('odom1', {'track': {'mode': 'distance', 'lenght_m': 5}})


def test_one_track_rules_for_vo_and_inputs() -> None:
    """The VO and the odometry inputs hold the same TrackRules type; only the mode's default
    differs (a survey of double swaths for the VO, one track for an odometry input)."""
    assert type(VoConfig().track) is type(OdometryInputConfig().track) is TrackRules
    assert replace(VoConfig().track, mode='none') == OdometryInputConfig().track == TrackRules()
    vo, _ = config_from_params(VoConfig, {'track.mode': 'distance', 'track.length_m': 30})
    assert vo.track == TrackRules('distance', length_m=30.0)


@pytest.mark.ros
def test_node_parameter_refused_with_the_dataclass_message() -> None:
    rclpy = pytest.importorskip('rclpy')
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from ga_ros.ros.params import declare_config

    expected = 'AlignerConfig.outlier_chi2_prob = 2.0 is outside [0, 1]'
    with pytest.raises(InputError) as direct:
        AlignerConfig(outlier_chi2_prob=2.0)
    assert str(direct.value) == expected
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = Node('ranges_probe', context=ctx, parameter_overrides=[
            Parameter('outlier_chi2_prob', value=2.0)])
        with pytest.raises(InputError) as declared:
            declare_config(node, AlignerConfig)
        assert str(declared.value) == f'parameter outlier_chi2_prob: {expected}'
        node.destroy_node()
        node = Node('former_names_probe', context=ctx, parameter_overrides=[
            Parameter('odom0.track_mode', value='distance')])
        with pytest.raises(InputError, match='odom0.track_mode was renamed to odom0.track.mode'):
            declare_config(node, OdometryInputConfig, prefix='odom0.')
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.ros
def test_calibrate_cameras_is_a_string_array_parameter() -> None:
    """``calibrate_cameras`` (a :func:`~ga_ros.core.config_ranges.string_list` field): a ROS
    ``STRING_ARRAY`` parameter (unset by default, the field's ``()``), one comma-separated
    string accepted too; the replay's parameter file reads a YAML list and a string alike; a
    number is refused."""
    rclpy = pytest.importorskip('rclpy')
    from rcl_interfaces.msg import ParameterType
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from ga_ros.ros.params import declare_config

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        for k, (given, want, kind) in enumerate([
                (None, (), ParameterType.PARAMETER_STRING_ARRAY),
                (['cam0', 'cam1'], ('cam0', 'cam1'), ParameterType.PARAMETER_STRING_ARRAY),
                (' cam0, cam2 ', ('cam0', 'cam2'), ParameterType.PARAMETER_STRING)]):
            over = [Parameter('calibrate', value=True)]
            if given is not None:
                over.append(Parameter('calibrate_cameras', value=given))
            node = Node(f'cameras_probe_{k}', context=ctx, parameter_overrides=over)
            cfg = declare_config(node, AlignerConfig)
            assert cfg.calibrate_cameras == want and cfg.camera_names == want
            assert node.describe_parameter('calibrate_cameras').type == kind
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    for value in (['cam0', 'cam1'], 'cam0,cam1'):
        cfg, _ = config_from_params(AlignerConfig, {'calibrate': True,
                                                    'calibrate_cameras': value})
        assert cfg.calibrate_cameras == ('cam0', 'cam1')
    with pytest.raises(InputError, match='list of names'):
        config_from_params(AlignerConfig, {'calibrate': True, 'calibrate_cameras': [1.0]})
