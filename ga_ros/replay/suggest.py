"""The command line for a bag the replay cannot read by default (first contact).

A bag without the ga_ros measurements topic and without a stereo pair (a Nav2 recording with
``/odom`` and ``/amcl_pose``, a ROS 1 bag of a SLAM system's poses, a wheel-odometry run) still
holds inputs the replay reads when named: odometry / pose streams (``--odom-topic``), absolute
fixes (``--absolute-topic``) and ground truth (``--ground-truth-topic``). :func:`suggest` picks
them from the bag's topic list by type and name, and :func:`no_usable_input_error` turns the
choice into the exact command, each topic with its message type.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass

from ga_ros.errors import NoUsableInputError
from ga_ros.inputs.absolute import ABSOLUTE_TYPES, NAVSAT
from ga_ros.inputs.messages import INPUT_TYPES, ODOMETRY, POSE_COV
from ga_ros.io.bag.summary import BagInfo, BagTopic
from ga_ros.io.bag_messages import GROUND_TRUTH_TYPES

#: Name fragments of topics that carry absolute fixes (AMCL, GNSS, USBL, motion capture).
FIX_WORDS = ('amcl', 'gps', 'gnss', 'fix', 'usbl', 'navsat')
#: Name fragments of pose topics that are commands, not measurements (RViz's ``/initialpose``,
#: Nav2's ``/goal_pose``): never suggested.
COMMAND_WORDS = ('initialpose', 'goal', 'waypoint', 'target')
#: Fewest messages of a stream worth suggesting as odometry.
MIN_STREAM_MESSAGES = 3
#: Name fragments of ground-truth topics.
GROUND_TRUTH_WORDS = ('ground_truth', 'groundtruth', 'gt', 'vicon', 'mocap', 'leica')


def _is_ground_truth(topic: str) -> bool:
    name = topic.lower()
    tokens = re.split(r'[/_\-]', name)
    return ('gt' in tokens or 'groundtruth' in tokens
            or any(w in name for w in GROUND_TRUTH_WORDS if w != 'gt'))


def _is_fix(topic: BagTopic) -> bool:
    if topic.msgtype == NAVSAT:
        return True
    return topic.msgtype in ABSOLUTE_TYPES and any(w in topic.name.lower() for w in FIX_WORDS)


@dataclass(frozen=True)
class Suggestion:
    """Inputs of a bag the replay reads when they are named on the command line.

    Attributes
    ----------
    odometry : the odometry / pose stream that defines the keyframes (``--odom-topic``).
    other_odometry : further odometry / pose streams (a second ``--odom-topic`` each).
    absolutes : absolute fixes (``--absolute-topic``, repeatable).
    ground_truth : a ground-truth topic ('' = none found; ``--ground-truth-topic``).
    types : message type of every topic named.
    """

    odometry: str
    other_odometry: tuple[str, ...] = ()
    absolutes: tuple[str, ...] = ()
    ground_truth: str = ''
    types: tuple[tuple[str, str], ...] = ()

    def arguments(self) -> list[str]:
        """The command-line options of the suggestion (without the bag)."""
        args = ['--odom-topic', self.odometry]
        for topic in self.absolutes:
            args += ['--absolute-topic', topic]
        if self.ground_truth:
            args += ['--ground-truth-topic', self.ground_truth]
        return args

    def command(self, bag: str) -> str:
        """``ga-ros replay BAG --odom-topic ... [--absolute-topic ...]``, shell-quoted."""
        return shlex.join(['ga-ros', 'replay', bag, *self.arguments()])


def suggest(info: BagInfo, measurements_topic: str = '') -> Suggestion | None:
    """The inputs of a bag to name on the command line, or None when it has no odometry or pose
    stream.

    The odometry is a ``nav_msgs/Odometry`` topic (one with "odom" in its name first), else a
    pose stream (``PoseStamped``, ``PoseWithCovarianceStamped``) that is neither a fix nor
    ground truth, of at least :data:`MIN_STREAM_MESSAGES` messages and not a command
    (:data:`COMMAND_WORDS`); fixes are ``NavSatFix`` topics and fix-named
    (:data:`FIX_WORDS`) pose or odometry topics (AMCL's ``/amcl_pose``); ground truth a pose
    topic named like one (:data:`GROUND_TRUTH_WORDS`). ``measurements_topic`` (the ga_ros
    encoding) is never suggested as odometry.
    """
    types = {t.name: t.msgtype for t in info.topics if t.count > 0}
    topics = [t for t in info.topics if t.count > 0 and t.name != measurements_topic]
    truth = [t.name for t in topics if t.msgtype in GROUND_TRUTH_TYPES
             and _is_ground_truth(t.name)]
    fixes = [t.name for t in topics if _is_fix(t) and t.name not in truth]
    streams = [t for t in topics if t.msgtype in INPUT_TYPES and t.name not in truth
               and t.name not in fixes and t.count >= MIN_STREAM_MESSAGES
               and not any(w in t.name.lower() for w in COMMAND_WORDS)]
    if not streams:
        return None

    def rank(t: BagTopic) -> tuple[int, int]:
        odom_named = 'odom' in t.name.lower()
        kind = {ODOMETRY: 0, POSE_COV: 1}.get(t.msgtype, 2)
        return (kind if odom_named else kind + 3, -t.count)

    ordered = sorted(streams, key=rank)
    named = [ordered[0].name, *fixes, *truth[:1]]
    return Suggestion(ordered[0].name, tuple(t.name for t in ordered[1:]), tuple(fixes),
                      truth[0] if truth else '',
                      tuple((n, types[n]) for n in named + [t.name for t in ordered[1:]]))


def suggestion_text(s: Suggestion, bag: str) -> str:
    """The command and one line per topic it names, with the topic's message type and role."""
    role = {s.odometry: 'odometry (defines the keyframes)', s.ground_truth: 'ground truth'}
    role.update({t: "absolute fixes (the map frame is then the fixes' frame)"
                 for t in s.absolutes})
    role.update({t: 'another odometry / pose stream: add --odom-topic ' + t + ' to measure '
                 'the motion between keyframes with it (with --variance-components apply, '
                 'each stream weighted by its own noise)' for t in s.other_odometry})
    width = max(len(n) for n, _ in s.types)
    twidth = max(len(t) for _, t in s.types)
    lines = [f'replay it with:\n  {s.command(bag)}']
    lines += [f'    {n:<{width}}  {t:<{twidth}}  {role[n]}' for n, t in s.types]
    return '\n'.join(lines)


def no_usable_input_error(info: BagInfo, reason: str,
                          measurements_topic: str = '') -> NoUsableInputError:
    """The error of a bag without a usable default input: ``reason`` (what is missing), then
    the command for the topics it has (:func:`suggest`), or what the replay reads."""
    bag = str(info.path)
    s = suggest(info, measurements_topic)
    if s is not None:
        return NoUsableInputError(f'{reason}\n{suggestion_text(s, bag)}', s.command(bag))
    return NoUsableInputError(
        f'{reason}\nthe replay reads: ga_ros measurements (nav_msgs/Odometry on '
        f'{measurements_topic or "/ga/measurements"}), a stereo pair (--left-image, '
        '--right-image, with CameraInfo or --calibration), odometry / pose streams '
        '(--odom-topic: nav_msgs/Odometry, PoseStamped, PoseWithCovarianceStamped) with '
        'absolute fixes (--absolute-topic: PoseWithCovarianceStamped, Odometry, NavSatFix), '
        'or a EuRoC / KITTI folder (ga-ros replay --help)', '')
