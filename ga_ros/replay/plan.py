"""What a replay reads from its bag: the topic plan, the ground truth, the source of inputs.

The source is one of :func:`ga_ros.replay.source.bag_measurements` (measurement-encoded bags),
:class:`ga_ros.replay.inputs.InputSource` (standard odometry / pose inputs, the same
``InputFrontEnd`` as the node's) or :class:`ga_ros.replay.stereo.StereoSource` (images through
the stereo front end ``vo_node`` wraps).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from ga_ros.errors import FormatError
from ga_ros.io.bag import BagInfo, BagReader
from ga_ros.io.groundtruth import GroundTruth, read_ground_truth_file, read_ground_truth_topic
from ga_ros.io.topic_plan import TopicConfig, TopicPlan, plan_topics
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.inputs import InputSource, plan_inputs
from ga_ros.replay.source import bag_measurements
from ga_ros.replay.suggest import no_usable_input_error


@dataclass
class ReplaySource:
    """The inputs of one replay.

    Attributes
    ----------
    items : iterable of :class:`ga_ros.replay.source.SourceItem` in bag order (the source
        object: its ``stats``, ``warnings``, ``front`` are read when it has them).
    counter : ``counter[0]`` counts the inputs read so far (messages or stereo pairs).
    total : inputs in the bag (for the progress bar).
    unit : ``'msg'`` or ``'pair'``.
    ground_truth : the ground truth (bag topic or file), or None.
    match_by : ``'node'`` (measurement bags whose ground truth carries node ids) or
        ``'stamp'``: how the ground truth is matched to the keyframes.
    """

    items: Any
    counter: list[int]
    total: int
    unit: str
    ground_truth: GroundTruth | None
    match_by: str


def plan_or_hint(info: BagInfo, topics: TopicConfig) -> TopicPlan:
    """:func:`plan_topics`; when the bag has no usable default input, a
    :class:`ga_ros.errors.NoUsableInputError` with the command for the topics it has
    (:mod:`ga_ros.replay.suggest`)."""
    try:
        return plan_topics(info, topics)
    except FormatError as exc:
        if ('no usable input' not in str(exc) or topics.source != 'auto' or topics.left_image
                or topics.right_image):  # the options named an input: their own error
            raise
        raise no_usable_input_error(
            info, f'{info.path}: no usable input: neither a measurements topic '
            f'({topics.measurements}) nor a left/right image pair',
            topics.measurements) from None


def plan_replay(info: BagInfo, config: ReplayConfig) -> tuple[TopicPlan, tuple[Any, ...]]:
    """The topic plan of a replay and the specs of its standard inputs (empty without them).

    A ground-truth file replaces the bag's ground-truth topic in the plan.

    Raises
    ------
    FormatError
        If the bag lacks the topics the configuration needs.
    """
    specs: tuple[Any, ...] = ()
    if config.inputs.inputs:
        plan, specs = plan_inputs(info, config.inputs, config.topics.ground_truth)
    else:
        plan = plan_or_hint(info, config.topics)
    if config.ground_truth_file:  # the file replaces the topic
        plan = replace(plan, ground_truth='', notes=tuple(
            n for n in plan.notes if not n.startswith('ground truth:')) + (
            f'ground truth: {config.ground_truth_file} (file)',))
    return plan, specs


def read_replay_ground_truth(bag: BagReader, plan: TopicPlan,
                             config: ReplayConfig) -> GroundTruth | None:
    """The ground truth of the plan's topic, or of ``config.ground_truth_file`` (which replaces
    it); None without either."""
    gt = read_ground_truth_topic(bag, plan.ground_truth) if plan.ground_truth else None
    if config.ground_truth_file:
        gt = read_ground_truth_file(config.ground_truth_file, config.ground_truth_format,
                                    config.ground_truth_times, config.ground_truth_rate_hz,
                                    config.ground_truth_start_s)
    return gt


def open_source(bag: BagReader, plan: TopicPlan, specs: tuple[Any, ...],
                config: ReplayConfig) -> ReplaySource:
    """The ground truth and the source of inputs of a planned replay (nothing read yet but the
    ground truth)."""
    assert bag.info is not None
    gt = read_replay_ground_truth(bag, plan, config)
    counter = [0]
    items: Any
    if specs:
        total = sum(bag.info.topic(t).count for t in config.inputs.topics)
        items = InputSource(bag, specs, config.inputs, counter)
        unit = 'msg'
    elif plan.source == 'stereo':
        from ga_ros.replay.stereo import StereoSource

        total = bag.info.topic(plan.left_image).count
        items = StereoSource(bag, plan, config.vo, counter)
        unit = 'pair'
    else:
        total = bag.info.topic(plan.measurements).count
        items = bag_measurements(bag, plan.measurements, counter, config.covariance_policy)
        unit = 'msg'
    match_by = 'stamp'
    if plan.source == 'measurements' and gt is not None and len(gt.trajectory) and (
            gt.trajectory.node_ids >= 0).all():
        match_by = 'node'
    return ReplaySource(items, counter, total, unit, gt, match_by)
