"""Ground truth from anything: files of public datasets and bag topics, matched in time.

Files (:func:`read_ground_truth_file`)
    * TUM RGB-D (``timestamp x y z qx qy qz qw``, seconds): :func:`ga_ros.io.trajectory.read_tum`.
    * EuRoC MAV (``mav0/state_groundtruth_estimate0/data.csv``, also the Vicon/Leica files):
      comma-separated, ``#timestamp [ns], p_RS_R_x [m], p_RS_R_y, p_RS_R_z, q_RS_w [], q_RS_x,
      q_RS_y, q_RS_z`` then optional velocities and biases (ignored); the quaternion is
      ``w x y z``. Lines starting with ``#`` are comments.
    * KITTI odometry (``poses/NN.txt``: 12 numbers a line, row-major ``[R | t]``): the file has
      no stamps, so they come from a times file (``sequences/NN/times.txt``: one time in seconds
      a line, the same count as the poses) or a rate in Hz (pose ``k`` at ``k / rate``), plus
      ``start_s`` added to every stamp (KITTI's times start at 0; a bag's stamps are absolute).

    ``fmt='auto'`` tells them apart by the first data line: 12 fields is KITTI, a first field
    that is an integer (nanoseconds) of 13 or more digits or followed by a comma is EuRoC,
    anything else TUM.

Bag topics (:func:`read_ground_truth_topic`)
    ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``nav_msgs/Odometry`` (one
    pose a message, at its header stamp), ``nav_msgs/Path`` (the last message holds the whole
    trajectory, node ids from node frame ids ``ga/<track>/<node>`` when present) or a TF frame
    pair ``tf:PARENT:CHILD`` (the transforms ``PARENT -> CHILD`` on ``/tf`` and ``/tf_static``:
    a direct edge, no chaining); which topic a bag offers is decided with the replay's other
    topics (:func:`ga_ros.io.topic_plan.plan_ground_truth`).

Matching (:func:`match_stamps`)
    Each query stamp (a keyframe's acquisition time) gets the ground-truth pose at that time:
    the sample itself within :data:`EXACT_NS`, else interpolated between the two neighbouring
    samples (translation linear, rotation slerp ``R_a exp(a log(R_a' R_b))``) when they are at
    most ``tolerance`` apart, else, before the first or after the last sample, the end pose when
    it is at most ``tolerance`` away (held). Anything else is unmatched.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3, so3
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import (
    PATH,
    POSE_STAMPED,
    TF_TOPICS,
    path_msg_to_trajectory,
    pose_msg_to_matrix,
    stamp_to_ns,
)
from ga_ros.io.topic_plan import parse_tf_pair, plan_ground_truth
from ga_ros.io.trajectory import Trajectory, read_kitti, read_tum

_QUAT_TOL = 1e-3
#: Stamp difference (ns) within which a ground-truth sample is the query's own pose.
EXACT_NS = 1_000_000
#: Default largest gap (s) between two samples to interpolate across / distance to hold an end.
DEFAULT_TOLERANCE_S = 0.1
#: File formats of :func:`read_ground_truth_file`.
FILE_FORMATS = ('auto', 'tum', 'euroc', 'kitti')
#: Largest number of digits of an integer stamp (ns) in a file: int64 holds 18 safely.
_MAX_STAMP_DIGITS = 19


@dataclass(frozen=True)
class GroundTruth:
    """A ground-truth trajectory and where it came from.

    Attributes
    ----------
    trajectory : poses ``T_world_body`` sorted by stamp (ns), node ids when known.
    source : what it was read from, for messages (``'/gt (PoseStamped)'``, ``'gt.txt (TUM)'``).
    """

    trajectory: Trajectory
    source: str

    @property
    def rate_hz(self) -> float:
        """Median sample rate (Hz); 0 with fewer than two distinct stamps."""
        d = np.diff(np.unique(self.trajectory.stamps_ns))
        return float(1e9 / np.median(d)) if d.size else 0.0

    def describe(self) -> str:
        """``'/gt (PoseStamped, 100 Hz)'``."""
        rate = self.rate_hz
        head, sep, tail = self.source.partition(' (')
        where = f'{head} ({tail[:-1]}, ' if sep and tail.endswith(')') else f'{self.source} ('
        return where + (f'{rate:.3g} Hz)' if rate else f'{len(self.trajectory)} poses)')


@dataclass(frozen=True)
class GroundTruthMatch:
    """Ground-truth poses at the estimate's stamps (or node ids).

    Attributes
    ----------
    i_est : (k,) indices of the matched queries (estimate rows).
    T_world_gt : (k, 4, 4) their ground-truth poses.
    n_query : number of queries.
    n_exact, n_interpolated, n_held : how the matched ones were obtained (by node id counts as
        exact).
    """

    i_est: IntArray
    T_world_gt: FloatArray
    n_query: int
    n_exact: int = 0
    n_interpolated: int = 0
    n_held: int = 0

    @property
    def n_matched(self) -> int:
        return int(self.i_est.size)

    def describe(self, source: str, what: str = 'keyframes', by_node: bool = False) -> str:
        """One line: ``'ground truth: 116 of 116 keyframes matched from /gt (PoseStamped,
        100 Hz), interpolated'``."""
        how = ['by node id'] if by_node else []
        if not by_node:
            if self.n_interpolated:
                how.append('interpolated' if not self.n_exact else
                           f'{self.n_interpolated} interpolated')
            if self.n_exact and self.n_interpolated:
                how.append(f'{self.n_exact} at a sample')
            if self.n_held:
                how.append(f'{self.n_held} held at an end')
        return (f'ground truth: {self.n_matched} of {self.n_query} {what} matched from {source}'
                + (', ' + ', '.join(how) if how and self.n_matched else ''))


# --------------------------------------------------------------------------- files
def read_euroc_csv(path: str | os.PathLike) -> Trajectory:
    """Read an EuRoC ground-truth CSV (module doc) into a :class:`Trajectory` (frame ``world``).

    Raises
    ------
    FormatError
        ``file:line`` of a line with fewer than 8 fields, a non-number, a stamp out of range or
        a non-unit quaternion.
    """
    name = str(path)
    stamps: list[int] = []
    rows: list[list[float]] = []
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f'cannot read ground truth: {exc}', name) from None
    for k, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith('#'):
            continue
        fields = [f.strip() for f in text.split(',')]
        if len(fields) < 8:
            raise FormatError('expected at least 8 comma-separated fields '
                              '(timestamp, p x y z, q w x y z)', name, k)
        if not fields[0].isdigit() or len(fields[0]) > _MAX_STAMP_DIGITS:
            raise FormatError(f'timestamp {fields[0][:30]!r} is not a non-negative integer of '
                              f'at most {_MAX_STAMP_DIGITS} digits (ns)', name, k)
        stamp = int(fields[0])
        if stamp >= 2**63:
            raise FormatError('timestamp out of range (int64 ns)', name, k)
        try:
            row = [float(f) for f in fields[1:8]]
        except ValueError:
            raise FormatError(f'not a number in {text[:60]!r}', name, k) from None
        if not np.isfinite(row).all():
            raise FormatError('pose value is not finite', name, k)
        stamps.append(stamp)
        rows.append(row)
    if not rows:
        raise FormatError('no poses', name)
    a = np.asarray(rows)
    q = a[:, [4, 5, 6, 3]]  # w x y z -> x y z w
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > _QUAT_TOL)
    if bad.size:
        raise FormatError(f'quaternion of pose {bad[0] + 1} is not unit length '
                          f'(norm {norm[bad[0]]:.6g})', name)
    T = se3.from_pos_quat(a[:, :3], q / norm[:, None])
    return Trajectory(np.asarray(stamps, dtype=np.int64), T, frame_id='world')


def read_kitti_ground_truth(path: str | os.PathLike, times: str | os.PathLike | None = None,
                            rate_hz: float = 0.0, start_s: float = 0.0) -> Trajectory:
    """A KITTI pose file with stamps from ``times`` (seconds a line) or ``rate_hz``.

    Parameters
    ----------
    times : KITTI ``times.txt`` (one time in s a line, as many as poses); takes precedence.
    rate_hz : pose ``k`` at ``k / rate_hz`` s (used without ``times``).
    start_s : added to every stamp (s): the absolute time of KITTI's time 0.

    Raises
    ------
    InputError
        Neither ``times`` nor a positive ``rate_hz``, or counts that differ.
    """
    T = read_kitti(path)
    if times:
        rows = []
        try:
            text = Path(times).read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise FormatError(f'cannot read KITTI times: {exc}', str(times)) from None
        for k, line in enumerate(text.splitlines(), start=1):
            if line.strip():
                try:
                    rows.append(float(line.split()[0]))
                except ValueError:
                    raise FormatError(f'not a time in seconds: {line[:40]!r}', str(times),
                                      k) from None
        t = np.asarray(rows, dtype=float)
        if t.size != T.shape[0]:
            raise InputError(f'{times} has {t.size} times for the {T.shape[0]} poses of {path}')
    elif rate_hz > 0 and np.isfinite(rate_hz):
        t = np.arange(T.shape[0]) / float(rate_hz)
    else:
        raise InputError(f'{path} is a KITTI pose file, which has no stamps: give its times '
                         'file (--ground-truth-times sequences/NN/times.txt) or its rate '
                         '(--ground-truth-rate HZ)')
    t = t + float(start_s)
    if not np.isfinite(t).all() or (t < 0).any() or (t > 9.2e9).any():
        raise InputError(f'KITTI stamps of {path} are not finite times in [0, 9.2e9] s: check '
                         'the times file and --ground-truth-start')
    return Trajectory(np.round(t * 1e9).astype(np.int64), T, frame_id='world')


def file_format(path: str | os.PathLike) -> str:
    """``'tum'``, ``'euroc'`` or ``'kitti'`` from the first data line (module doc)."""
    try:
        with open(path, errors='replace') as f:
            first = next((ln for ln in f if ln.strip() and not ln.lstrip().startswith('#')), '')
    except OSError as exc:
        raise FormatError(f'cannot read ground truth: {exc.strerror or exc}', str(path)) from None
    fields = first.replace(',', ' ').split()
    if len(fields) == 12:
        return 'kitti'
    integer = bool(fields) and fields[0].isdigit() and len(fields[0]) <= _MAX_STAMP_DIGITS
    if integer and (len(fields[0]) >= 13 or ',' in first):
        return 'euroc'
    return 'tum'


def read_ground_truth_file(path: str | os.PathLike, fmt: str = 'auto',
                           times: str | os.PathLike | None = None, rate_hz: float = 0.0,
                           start_s: float = 0.0) -> GroundTruth:
    """A TUM, EuRoC or KITTI ground-truth file (module doc) -> :class:`GroundTruth`.

    Parameters
    ----------
    fmt : one of :data:`FILE_FORMATS`.
    times, rate_hz, start_s : stamps of a KITTI file (:func:`read_kitti_ground_truth`).

    Raises
    ------
    FormatError
        An unreadable or malformed file (naming the line).
    InputError
        An unknown format, or a KITTI file without times or rate.
    """
    if fmt not in FILE_FORMATS:
        raise InputError(f'ground-truth format must be one of {FILE_FORMATS}, got {fmt!r}')
    kind = file_format(path) if fmt == 'auto' else fmt
    if kind == 'euroc':
        traj = read_euroc_csv(path)
    elif kind == 'kitti':
        traj = read_kitti_ground_truth(path, times, rate_hz, start_s)
    else:
        traj = read_tum(path)
    if not len(traj):
        raise FormatError('no poses', str(path))
    return GroundTruth(_sorted(traj), f'{Path(path).name} ({kind.upper()})'
                       if kind != 'euroc' else f'{Path(path).name} (EuRoC)')


# --------------------------------------------------------------------------- bag topics
def read_ground_truth_topic(bag: BagReader, spec: str) -> GroundTruth | None:
    """The ground truth of an open bag on ``spec`` (a topic of
    :data:`ga_ros.io.bag_messages.GROUND_TRUTH_TYPES` or ``tf:PARENT:CHILD``); None if there is
    none (also when a truncated bag lost it: the main stream reports the cut).

    Raises
    ------
    FormatError
        A topic of another type, or a malformed pose.
    """
    assert bag.info is not None
    spec, _ = plan_ground_truth(bag.info, spec)
    if not spec:
        return None
    pair = parse_tf_pair(spec)
    stamps: list[int] = []
    poses: list[FloatArray] = []
    last = None
    if pair is not None:
        topics = [t for t in TF_TOPICS if bag.info.topic(t) is not None]
        kind = 'TF'
    else:
        topics = [spec]
        kind = bag.info.topic(spec).msgtype
    try:
        for m in bag.messages(topics):
            msg = m.msg
            if pair is not None:
                for tr in msg.transforms:
                    if (tr.header.frame_id.strip('/') == pair[0]
                            and tr.child_frame_id.strip('/') == pair[1]):
                        t, q = tr.transform.translation, tr.transform.rotation
                        stamps.append(stamp_to_ns(tr.header.stamp))
                        poses.append(se3.from_pos_quat(np.array([t.x, t.y, t.z]),
                                                       np.array([q.x, q.y, q.z, q.w])))
            elif kind == PATH:
                last = msg
            else:
                pose = msg.pose if kind == POSE_STAMPED else msg.pose.pose
                stamps.append(stamp_to_ns(msg.header.stamp))
                poses.append(pose_msg_to_matrix(pose))
    except FormatError:
        if bag.truncated is None:
            raise
    try:
        if kind == PATH:
            if last is None:
                return None
            traj = path_msg_to_trajectory(last)
        else:
            if not stamps:
                return None
            traj = Trajectory(np.asarray(stamps, dtype=np.int64), np.asarray(poses),
                              frame_id=pair[0] if pair else 'world')
    except InputError as exc:
        raise FormatError(f'ground truth on {spec}: {exc}', str(bag.path)) from exc
    if not np.isfinite(traj.T_world_node).all():
        raise FormatError(f'ground truth on {spec}: a pose is not finite', str(bag.path))
    label = (f'tf {pair[0]} -> {pair[1]} (TF)' if pair else
             f'{spec} ({kind.rsplit("/", 1)[-1]})')
    return GroundTruth(traj if kind == PATH else _sorted(traj), label)


# --------------------------------------------------------------------------- matching
def _sorted(traj: Trajectory) -> Trajectory:
    """Samples in stamp order, one per stamp (the last of equal stamps)."""
    s = traj.stamps_ns
    order = np.argsort(s, kind='stable')
    s_sorted = s[order]
    keep = np.append(s_sorted[1:] != s_sorted[:-1], True) if s.size else np.zeros(0, bool)
    idx = order[keep]
    return Trajectory(s[idx], traj.T_world_node[idx], traj.node_ids[idx], traj.track_ids[idx],
                      traj.frame_id)


def interpolate_pose(T_a: FloatArray, T_b: FloatArray, alpha: FloatArray) -> FloatArray:
    """Poses between ``T_a`` and ``T_b`` (both ``(k, 4, 4)``) at fractions ``alpha`` (k,):
    translation linear, rotation ``R_a exp(alpha log(R_a' R_b))`` (slerp)."""
    alpha = np.asarray(alpha, dtype=float).reshape(-1)
    T = np.zeros((alpha.size, 4, 4))
    T[:, 3, 3] = 1.0
    T[:, :3, 3] = (1.0 - alpha)[:, None] * T_a[:, :3, 3] + alpha[:, None] * T_b[:, :3, 3]
    R_ab = np.swapaxes(T_a[:, :3, :3], 1, 2) @ T_b[:, :3, :3]
    T[:, :3, :3] = T_a[:, :3, :3] @ so3.exp(alpha[:, None] * so3.log(R_ab))
    return T


def match_stamps(gt: Trajectory, query_ns: IntArray,
                 tolerance_s: float = DEFAULT_TOLERANCE_S) -> GroundTruthMatch:
    """Ground-truth poses at ``query_ns`` (module doc: exact, interpolated, held).

    Parameters
    ----------
    gt : ground truth (any order; sorted here).
    query_ns : (n,) stamps (ns); negative ones are never matched.
    tolerance_s : largest gap between two samples to interpolate across, and largest distance
        to the first / last sample to hold it (s).
    """
    if not np.isfinite(tolerance_s) or tolerance_s < 0:
        raise InputError(f'ground-truth tolerance must be >= 0 s, got {tolerance_s}')
    q = np.asarray(query_ns, dtype=np.int64).reshape(-1)
    g = _sorted(gt) if len(gt) else gt
    s = g.stamps_ns
    n = q.size
    empty = GroundTruthMatch(np.zeros(0, np.int64), np.zeros((0, 4, 4)), n)
    if not s.size or not n:
        return empty
    tol = int(round(tolerance_s * 1e9))
    hi = np.clip(np.searchsorted(s, q, side='left'), 0, s.size - 1)
    lo = np.clip(hi - 1, 0, s.size - 1)
    d_hi = np.abs(s[hi] - q)
    d_lo = np.abs(q - s[lo])
    nearest = np.where(d_lo <= d_hi, lo, hi)
    d_near = np.minimum(d_lo, d_hi)
    exact = (d_near <= EXACT_NS) & (q >= 0)
    inside = (q > s[0]) & (q < s[-1]) & ~exact & (q >= 0)
    interp = inside & ((s[hi] - s[lo]) <= tol)
    held = ~exact & ~inside & (d_near <= tol) & (q >= 0)
    T = np.zeros((n, 4, 4))
    T[exact | held] = g.T_world_node[nearest[exact | held]]
    if interp.any():
        a = (q[interp] - s[lo[interp]]) / (s[hi[interp]] - s[lo[interp]])
        T[interp] = interpolate_pose(g.T_world_node[lo[interp]], g.T_world_node[hi[interp]], a)
    ok = exact | interp | held
    idx = np.flatnonzero(ok)
    return GroundTruthMatch(idx.astype(np.int64), T[idx], n, int(exact.sum()),
                            int(interp.sum()), int(held.sum()))


def match_nodes(gt: Trajectory, node_ids: IntArray) -> GroundTruthMatch:
    """Ground-truth poses of the same node ids (ground truth with node ids, e.g. a simulated
    survey's ``nav_msgs/Path`` with node frame ids)."""
    ids = np.asarray(node_ids, dtype=np.int64).reshape(-1)
    lookup = {int(n): k for k, n in enumerate(gt.node_ids) if n >= 0}
    pairs = [(i, lookup[int(n)]) for i, n in enumerate(ids) if int(n) in lookup]
    if not pairs:
        return GroundTruthMatch(np.zeros(0, np.int64), np.zeros((0, 4, 4)), ids.size)
    a = np.array(pairs, dtype=np.int64)
    return GroundTruthMatch(a[:, 0], gt.T_world_node[a[:, 1]], ids.size, len(pairs))
