"""Admitting a measurement into the track-window aligner: validation, the rejection reasons,
and storing an accepted measurement in the :class:`~ga_ros.core.window.state.WindowState`.

Measurement policy (what :meth:`TrackWindowAligner.add_measurement
<ga_ros.core.window.TrackWindowAligner.add_measurement>` rejects with
:class:`~ga_ros.errors.InputError`, whose ``reason`` names the rule, leaving the state
unchanged): non-finite values or a covariance that is not symmetric positive definite or outside
the configured eigenvalue range and condition number (``bad_covariance``); a self-loop; ids
outside ``[0, 2**63)``; a new node or track id far above the largest seen (``id_jump``,
``track_jump``); an unknown ``kind``; an unknown source node (every measurement after the first
must start at a known node); a new node of an older track than the current one (out of order);
a re-delivered identical measurement; an endpoint on a frozen track.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.core.network import check_covariances
from ga_ros.core.window.config import AlignerConfig
from ga_ros.core.window.state import WindowState
from ga_ros.errors import InputError
from ga_ros.geometry import se3

_EYE6 = np.eye(6)
_potrf = sla.get_lapack_funcs('potrf', (_EYE6,))
#: Size of the duplicate-key set below which it is never pruned
#: (:meth:`~ga_ros.core.window.state.WindowState.prune_pairs`).
PAIRS_MIN = 4096


def measurement_fingerprints(z: FloatArray, cov: FloatArray) -> list[int]:
    """CRC-32 of each measurement's values (rows of ``z`` (m, 6) and ``cov`` (m, 6, 6)), the
    third part of the duplicate-test key ``(low id, high id, fingerprint)``; two different
    measurements between the same two nodes share it with probability 2**-32."""
    rows = np.ascontiguousarray(np.concatenate(
        [np.reshape(z, (-1, 6)), np.reshape(cov, (-1, 36))], axis=1, dtype=np.float64))
    flat = memoryview(rows.reshape(-1).view(np.uint8))
    return [zlib.crc32(flat[k:k + 336]) for k in range(0, flat.nbytes, 336)]


@dataclass(frozen=True)
class Admitted:
    """A measurement that passed every check (:func:`check_measurement`), as it is stored.

    Attributes
    ----------
    src, dst : node ids; z : (6,) measured motion ``[t, rotvec]`` (m, rad) from ``src`` to
        ``dst``; cov : (6, 6) its symmetrised covariance ``[x y z rx ry rz]``.
    first : the survey's first measurement (its source node is the datum).
    ends_track : a new node of a newer track: the open track ends first.
    key : the duplicate-test key ``(low id, high id, fingerprint)``.
    rows : the rows of ``src`` and ``dst`` (``None``: a new node).
    """

    src: int
    dst: int
    z: FloatArray
    cov: FloatArray
    first: bool
    ends_track: bool
    key: tuple[int, int, int]
    rows: tuple[int | None, int | None]


def rejection(reason: str, text: str) -> InputError:
    """The :class:`InputError` of a rejected measurement, with its ``reason``."""
    err = InputError(text)
    err.reason = reason
    return err


def check_measurement(state: WindowState, config: AlignerConfig, m: Measurement,
                      checked_cov: FloatArray | None = None) -> Admitted:
    """Validate ``m`` against the policy of the module docstring; ``checked_cov``: its
    covariance when already checked (:func:`check_covariances_batch`). Raises the
    :class:`InputError` of the first rule broken (:func:`rejection`); changes nothing."""
    bad = rejection
    for name in ('src_id', 'dst_id', 'src_track', 'dst_track'):
        v = getattr(m, name)
        if type(v) is int:  # the common case, without the conversions below
            ok = 0 <= v < 2**63
        else:
            try:
                ok = int(v) == v and 0 <= int(v) < 2**63
            except (TypeError, ValueError, OverflowError):
                ok = False
        if not ok:
            raise bad('bad_id', f'{name} must be an integer in [0, 2**63), got {v!r}')
    src, dst = int(m.src_id), int(m.dst_id)
    try:
        ok = int(m.stamp_ns) == m.stamp_ns and -2**63 <= int(m.stamp_ns) < 2**63
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise bad('bad_stamp', f'stamp_ns must be an integer (ns), got {m.stamp_ns!r}')
    if m.kind not in KINDS:
        raise bad('bad_kind', f'kind must be one of {KINDS}, got {m.kind!r}')
    z = np.asarray(m.z, dtype=float).reshape(-1)
    cov = np.asarray(m.cov, dtype=float)
    if z.shape != (6,) or cov.shape != (6, 6):
        raise bad('bad_shape', 'a measurement needs z of 6 values and a 6x6 covariance')
    if not np.isfinite(z).all():
        raise bad('non_finite', f'measurement {src}->{dst} has NaN or inf values')
    if checked_cov is None:
        cov = check_covariance(config, cov, f'covariance of {src}->{dst}')
    else:
        cov = checked_cov
    if src == dst:
        raise bad('self_loop', f'measurement from node {src} to itself')
    index, tracks = state.index, state.trackarr.a
    i_src, i_dst = index.get(src), index.get(dst)
    if i_src is not None and int(m.src_track) != tracks[i_src]:
        raise bad('track_mismatch', f'node {src} belongs to track '
                  f'{tracks[i_src]}, not {m.src_track}')
    if i_dst is not None and int(m.dst_track) != tracks[i_dst]:
        raise bad('track_mismatch', f'node {dst} belongs to track '
                  f'{tracks[i_dst]}, not {m.dst_track}')
    first = state.idarr.n == 0
    if not first and i_src is None:
        raise bad('unknown_source', f'source node {src} is unknown: every measurement must '
                  'start at a node that an earlier measurement introduced')
    for node, k in ((src, i_src), (dst, i_dst)):
        if k is not None and state.frozen[k]:
            key = (min(src, dst), max(src, dst), zlib.crc32(z.tobytes() + cov.tobytes()))
            if state.received.contains(state, key):
                raise bad('duplicate', f'measurement {src}->{dst} was already received (its '
                          'track is frozen)')
            raise bad('frozen', f'node {node} belongs to a frozen track (outside the window '
                      f'of {config.window_tracks} tracks)')
    ends_track = False
    new_nodes = ([src] if first and i_src is None else []) + ([dst] if i_dst is None else [])
    for node in new_nodes:
        track = int(m.dst_track) if node == dst else int(m.src_track)
        if track in state.finished:
            raise bad('out_of_order', f'new node {node} of track {track} is out of order: '
                      'that track has finished')
        if state.open_track is not None and track != state.open_track:
            if track in state.track_nodes or track < state.open_track:
                raise bad('out_of_order', f'new node {node} of track {track} arrives after '
                          f'track {state.open_track} began (out of order)')
            ends_track = True
    check_jumps(state, config, m, new_nodes)
    key = (min(src, dst), max(src, dst), zlib.crc32(z.tobytes() + cov.tobytes()))
    if key in state.pairs:
        raise bad('duplicate', f'measurement {src}->{dst} was already received')
    return Admitted(src, dst, z, cov, first, ends_track, key, (i_src, i_dst))


def check_jumps(state: WindowState, config: AlignerConfig, m: Measurement,
                new_nodes: list[int]) -> None:
    """New node and track ids must be within the configured jump of the largest seen."""
    cfg = config
    bad = rejection
    max_id, max_track = state.seen_max()
    ref_id = max(max_id, int(m.src_id))
    for node in new_nodes:
        if cfg.max_node_id_jump and node - ref_id > cfg.max_node_id_jump:
            raise bad('id_jump', f'new node id {node} is {node - ref_id} above the largest '
                      f'seen ({ref_id}); max_node_id_jump is {cfg.max_node_id_jump}')
    ref_track = max_track if max_track >= 0 else int(m.src_track)
    for track in {int(m.src_track), int(m.dst_track)}:
        if cfg.max_track_jump and track - ref_track > cfg.max_track_jump:
            raise bad('track_jump', f'track id {track} is {track - ref_track} above the '
                      f'largest seen ({ref_track}); max_track_jump is {cfg.max_track_jump}')


def check_covariances_batch(config: AlignerConfig, ms: list[Measurement]) -> FloatArray | None:
    """Symmetrised covariances of ``ms`` that pass every covariance check, NaN-filled rows
    for the others (checked again one by one, for the exact reason); ``None`` if the stack
    cannot be formed."""
    cfg = config
    try:
        cov = np.array([m.cov for m in ms], dtype=float).reshape(len(ms), 6, 6)
    except (TypeError, ValueError):
        return None
    with np.errstate(all='ignore'):
        amax = np.abs(cov).max(axis=(1, 2), initial=0.0)
        ok = np.isfinite(cov).all(axis=(1, 2)) & (amax <= cfg.cov_max_eigenvalue)
        ok &= (np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2), initial=0.0)
               <= 1e-6 * np.maximum(amax, 1e-300))
        sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        sym[~ok] = np.eye(6)
        ev = np.linalg.eigvalsh(sym)
        ok &= (ev[:, 0] > 1e-12 * np.maximum(amax, 1e-300))
        ok &= (ev[:, 0] >= cfg.cov_min_eigenvalue)
        ok &= (ev[:, -1] <= cfg.cov_max_condition * ev[:, 0])
    sym[~ok] = np.nan
    return sym


def check_covariance(config: AlignerConfig, cov: FloatArray, what: str) -> FloatArray:
    """Finite, symmetric, positive definite, and within the configured eigenvalue range and
    condition number (``bad_covariance`` otherwise); returns the symmetrised matrix."""
    sym = covariance_within_limits(config, cov)
    if sym is not None:
        return sym
    cfg = config
    bad = rejection
    if not np.isfinite(cov).all():
        raise bad('bad_covariance', f'{what} has NaN or inf entries')
    if np.abs(cov).max() > cfg.cov_max_eigenvalue:  # >= one eigenvalue that large
        raise bad('bad_covariance', f'{what} has entries up to {np.abs(cov).max():.3g}, above '
                  f'cov_max_eigenvalue {cfg.cov_max_eigenvalue:.3g} (a placeholder for '
                  '"unknown"?); send a real covariance or raise the limit')
    try:
        cov = check_covariances(cov[None], what=what)[0]
    except InputError as exc:
        raise bad('bad_covariance', str(exc)) from None
    ev = np.linalg.eigvalsh(cov)
    if ev[0] < cfg.cov_min_eigenvalue:
        raise bad('bad_covariance', f'{what} has an eigenvalue {ev[0]:.3g} below '
                  f'cov_min_eigenvalue {cfg.cov_min_eigenvalue:.3g}: too small to be '
                  'solved with; check the units or raise the limit')
    if ev[-1] > cfg.cov_max_condition * ev[0]:
        raise bad('bad_covariance', f'{what} has condition number {ev[-1] / ev[0]:.3g}, '
                  f'above cov_max_condition {cfg.cov_max_condition:.3g}')
    return cov


def covariance_within_limits(config: AlignerConfig, cov: FloatArray) -> FloatArray | None:
    """The symmetrised 6x6 covariance if it passes every check of
    :func:`check_covariance` with a margin, decided by one Cholesky attempt (a few
    microseconds, against two eigen-decompositions); ``None`` when undecided (the exact
    checks then run and name the reason).

    ``sym - c I`` positive definite means ``eig_min(sym) > c``; with ``c`` the largest of
    the three lower bounds on ``eig_min`` (``1e-12`` of the largest entry,
    ``cov_min_eigenvalue``, and ``6 max|entry| / cov_max_condition``, since ``eig_max`` is
    at most 6 times the largest entry), slightly raised against round-off, every test
    passes.
    """
    cfg = config
    amax = abs(cov).max()
    if not amax <= cfg.cov_max_eigenvalue:  # also NaN or inf
        return None
    if not abs(cov - cov.T).max() <= 1e-6 * max(amax, 1e-300):
        return None
    sym = 0.5 * (cov + cov.T)
    # eig_max <= 6 max |entry| bounds the condition number as the trace would
    shift = max(1e-12 * amax, cfg.cov_min_eigenvalue, 6.0 * amax / cfg.cov_max_condition)
    _, info = _potrf(sym - (shift * (1.0 + 1e-9) + 1e-13 * amax) * _EYE6)
    return sym if info == 0 else None


def apply_measurement(state: WindowState, m: Measurement, plan: Admitted) -> None:
    """Store an admitted measurement (and its new node) in ``state``."""
    src, dst = plan.src, plan.dst
    i, j = plan.rows  # None: a new node (finish_track, run between, adds none)
    if plan.first:
        i = state.add_node(src, int(m.src_track), int(m.stamp_ns), state.T_first)
    if j is None:
        T_src = state.T[i]
        T_meas = se3.from_translation_rotvec(plan.z[:3], plan.z[3:])
        j = state.add_node(dst, int(m.dst_track), int(m.stamp_ns), T_src @ T_meas)
    k = state.src.append(i)
    state.dst.append(j)
    state.z.append(plan.z)
    state.ccov.append(plan.cov)
    state.cross.append(m.kind == 'cross')  # a bridge is a (predicted) motion
    state.status.append(0)
    state.fp.append(plan.key[2])
    state.track_conns.add({int(state.track[i]), int(state.track[j])}, k)
    state.pairs.add(plan.key)
    if len(state.pairs) > max(PAIRS_MIN, 2 * state.pairs_kept):
        state.prune_pairs()
