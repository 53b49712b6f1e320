"""Saving and restoring a :class:`~ga_ros.core.window.TrackWindowAligner` (its snapshot file):
its :class:`~ga_ros.core.window.state.WindowState`, written and read as a whole
(:func:`state_arrays`, :func:`state_of_arrays`), its config and its pending refinement.

File layout (little-endian), written atomically by :func:`ga_ros.safe_write.atomic_write`::

    MAGIC (12 bytes 'GAROS-STATE\\0') | version u32 | header length u64 | header CRC-32 u32
    | header (UTF-8 JSON: the scalar state and a table of arrays) | padding
    | array bytes, each 64-byte aligned, in the order of the table

The table gives each array's name, dtype, shape, offset and CRC-32, so a snapshot that was cut
short or garbled is detected (:class:`~ga_ros.errors.CorruptFileError`) instead of restoring a
wrong state. Arrays are read and written whole (no per-element access), so a full aerial survey
(5,100 nodes, ~30k connections) saves and loads in tens of milliseconds
(``python scripts/bench_persistence.py`` prints the figures).

A path that exists and is not a ga_ros state (neither this format nor the ``.npz`` snapshots of
version 1, which are still read) is refused (:class:`~ga_ros.errors.ForeignFileError`) and never
overwritten.
"""

from __future__ import annotations

import json
import os
import struct
import zipfile
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ga_ros.core.fixes import FixBook
from ga_ros.core.quality.online_variance import OnlineVarianceComponents, OnlineVarianceConfig
from ga_ros.core.solver.result import result_arrays, result_of_arrays
from ga_ros.core.window.admission import measurement_fingerprints
from ga_ros.core.window.aligner import TrackWindowAligner
from ga_ros.core.window.calibration import OnlineCalibration
from ga_ros.core.window.config import AlignerConfig
from ga_ros.core.window.state import WindowState
from ga_ros.core.window.storage import (
    IdIndex,
    Rows,
    SymArray,
    SymRows,
    TrackLists,
    TrackRanges,
    pack_sym6,
    zeros,
)
from ga_ros.errors import CorruptFileError, ForeignFileError, GaError, InputError
from ga_ros.safe_write import atomic_write, check_regular, open_nofollow

MAGIC = b'GAROS-STATE\x00'
FORMAT_VERSION = 4
#: Versions :func:`load_state` reads: 2 stored the covariances as full 6x6 matrices, 3 (since
#: the aligner keeps them compactly, ga_ros.core.window.storage) as their 21 upper-triangle values,
#: 4 the joint priors' information as its non-zero 6x6 blocks (block-banded priors) instead of
#: one dense matrix each.
READ_VERSIONS = (2, 3, 4)
_PREFIX = struct.Struct('<12sIQI')
_ALIGN = 64
_LEGACY_VERSION = 1  # the .npz snapshots written before this module
#: Prefix of the arrays of the last window adjustment (:func:`~ga_ros.core.solver.result.
#: result_arrays`).
_LAST = 'last_adj_'


@dataclass(frozen=True)
class SavedState:
    """A snapshot read back by :func:`load_state`.

    Attributes
    ----------
    aligner : the restored aligner (its last window adjustment recomputed).
    journal_records : number of measurement-journal records the snapshot contains (``None`` if
        the writer did not say).
    version : file format version.
    """

    aligner: TrackWindowAligner
    journal_records: int | None
    version: int


def is_state_file(path: str | os.PathLike) -> bool:
    """``True`` if ``path`` is a ga_ros state file (this format or a version-1 ``.npz``).

    Reads at most the first bytes (and, for a zip, its directory); never follows a symbolic link
    (raises :class:`~ga_ros.errors.UnsafePathError` for one).
    """
    fd = open_nofollow(path, os.O_RDONLY)
    with os.fdopen(fd, 'rb') as f:
        head = f.read(len(MAGIC))
        if head == MAGIC:
            return True
        if not head.startswith(b'PK\x03\x04'):
            return False
        try:
            f.seek(0)
            names = set(zipfile.ZipFile(f).namelist())
        except (zipfile.BadZipFile, OSError, ValueError):
            return False
    return {'meta.npy', 'ids.npy', 'ccov.npy'} <= names


def save_state(aligner: TrackWindowAligner, path: str | os.PathLike,
               journal_records: int | None = None) -> Path:
    """Write ``aligner``'s whole state to ``path`` atomically.

    Parameters
    ----------
    aligner : the aligner to save (not modified).
    path : target file. An existing file there must be a ga_ros state (it is replaced);
        anything else is refused with :class:`~ga_ros.errors.ForeignFileError` and left as it was.
    journal_records : how many measurement-journal records the state contains (stored in the
        file so that snapshot and count cannot disagree).
    """
    return atomic_write(path, state_chunks(aligner, journal_records), is_ours=is_state_file)


def state_chunks(aligner: TrackWindowAligner, journal_records: int | None = None
                 ) -> list[bytes | memoryview]:
    """The bytes of a state file of ``aligner`` (what :func:`save_state` writes), as chunks to
    write in order; e.g. the base a journal embeds (:func:`load_state_bytes` reads them)."""
    meta, arrays = _state_of(aligner)
    meta['journal_records'] = None if journal_records is None else int(journal_records)
    table, chunks, offset = [], [], 0
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        if a.dtype.byteorder == '>':
            a = a.astype(a.dtype.newbyteorder('<'))
        raw = memoryview(a.reshape(-1).view(np.uint8))
        table.append([name, a.dtype.str, list(a.shape), offset, a.nbytes, zlib.crc32(raw)])
        chunks.append(raw)
        pad = -a.nbytes % _ALIGN
        chunks.append(b'\0' * pad)
        offset += a.nbytes + pad
    header = json.dumps({'meta': meta, 'arrays': table}).encode()
    header += b' ' * (-(_PREFIX.size + len(header)) % _ALIGN)
    prefix = _PREFIX.pack(MAGIC, FORMAT_VERSION, len(header), zlib.crc32(header))
    return [prefix, header, *chunks]


def load_state(path: str | os.PathLike, config=None) -> SavedState:
    """Read a state written by :func:`save_state` (or a version-1 ``.npz`` snapshot).

    Parameters
    ----------
    path : the state file (never read through a symbolic link).
    config : optional :class:`~ga_ros.core.window.AlignerConfig` to use instead of the saved one
        (e.g. the node's current parameters); the window size must then allow the saved state.

    Raises
    ------
    ForeignFileError : the file is not a ga_ros state.
    CorruptFileError : checksum mismatch, cut short, or inconsistent content.
    """
    path = Path(path)
    check_regular(path)
    if not path.exists():
        raise InputError(f'no state file {path}')
    if not is_state_file(path):
        raise ForeignFileError(f'{path} is not a ga_ros state file; it is left untouched')
    try:
        fd = open_nofollow(path, os.O_RDONLY)
        with os.fdopen(fd, 'rb') as f:
            size = os.fstat(f.fileno()).st_size
            buf = bytearray(size)
            if f.readinto(buf) != size:
                raise CorruptFileError('file changed while reading', str(path))
    except OSError as exc:
        raise InputError(f'cannot read state file {path}: {exc}') from None
    return _load(buf, path, config)


def load_state_bytes(buf: bytes | bytearray, config=None, name: str = '<state bytes>'
                     ) -> SavedState:
    """:func:`load_state` of a state file's bytes (:func:`state_chunks` joined); ``name`` names
    them in errors. Raises :class:`CorruptFileError` for bytes that are not a sound state."""
    buf = bytearray(buf)
    if buf[:len(MAGIC)] != MAGIC:
        raise CorruptFileError('not a ga_ros state', name)
    return _load(buf, Path(name), config)


def _load(buf: bytearray, path: Path, config) -> SavedState:
    try:
        if buf[:len(MAGIC)] == MAGIC:
            meta, arrays, version = _parse(buf, path)
        else:
            meta, arrays, version = _parse_legacy(path)
        aligner = _restore(meta, arrays, config)
    except GaError:
        raise
    except (ValueError, KeyError, IndexError, TypeError, OSError, zipfile.BadZipFile,
            np.linalg.LinAlgError) as exc:
        raise CorruptFileError(f'inconsistent aligner state ({type(exc).__name__}: {exc})',
                               str(path)) from None
    records = meta.get('journal_records')
    return SavedState(aligner, None if records is None else int(records), version)


# ---------------------------------------------------------------------------- internals
def _state_of(al: TrackWindowAligner) -> tuple[dict, dict[str, np.ndarray]]:
    """The file's header fields and arrays of an aligner: its config, its pending refinement
    and its :class:`WindowState` (:func:`state_arrays`)."""
    meta, arrays = state_arrays(al.state)
    meta = {'config': asdict(al.config), **meta, 'refine_pending': al.refinement_state()}
    return meta, arrays


def state_arrays(st: WindowState) -> tuple[dict, dict[str, np.ndarray]]:
    """A :class:`WindowState` as header fields (JSON) and named arrays (inverse:
    :func:`state_of_arrays`); the caches (last adjustment, duplicate keys) are rebuilt on
    reading."""
    n = len(st.ids)
    meta = {
        'tracks': [int(t) for t in st.tracks],
        'finished': sorted(int(t) for t in st.finished),
        'open_track': None if st.open_track is None else int(st.open_track),
        'rejected': {str(k): int(v) for k, v in st.rejected.items()},
        'n_updates': int(st.n_updates), 'n_outliers': int(st.n_outliers),
        'n_failed_updates': int(st.n_failed_updates), 'last_failure': str(st.last_failure),
        'refine_retired': int(st.retired), 'refine_drift': float(st.refine_drift),
    }
    fix_meta, fix_arrays = st.fixes.arrays()  # absolute fixes (ga_ros.core.fixes)
    meta['fixes'] = fix_meta
    last_arrays = {}
    last = None if st.last_result is None else result_arrays(st.last_result)
    if last is not None:  # the last adjustment as it was (its normal matrix's values)
        meta['last_adjustment'] = last[0]
        last_arrays = {f'{_LAST}{k}': v for k, v in last[1].items()}
    vc_arrays = {}
    if st.variance is not None:  # the online variance components' book
        book = st.variance.arrays()
        meta['variance_groups'] = book['names']
        vc_arrays = {'vc_group': book['group'].astype(np.int64), 'vc_cost': book['cost'],
                     'vc_redundancy': book['redundancy'],
                     'vc_fix_group': book['fix_group'].astype(np.int64),
                     'vc_fix_cost': book['fix_cost'],
                     'vc_fix_redundancy': book['fix_redundancy'],
                     **{f'vcc_{k}': v for k, v in book['consistency'].items()
                        if k != 'names'}, 'vc_split': book['split']}
        meta['variance_consistency'] = book['consistency']['names']
        meta['variance_split'] = book['split_names']
    cal_arrays = {}
    if st.calibration is not None:  # the online calibration's book
        meta['calibration'], cal_arrays = st.calibration.arrays()
    arrays = dict(
        T_first=st.T_first, ids=st.idarr.a, track=st.trackarr.a, stamp=st.stamparr.a,
        T=st.T[:n], cov21=st.cov.packed[:n], frozen=st.frozen[:n], src=st.src.a,
        dst=st.dst.a, z=st.z.a, ccov21=st.ccov.packed, cross=st.cross.a,
        status=st.status.a.astype(np.int64), last_window=st.last_window.astype(np.int64),
        fingerprint=st.fp.a,
        weighted_idx=st.T_weighted[0].astype(np.int64), weighted_T=st.T_weighted[1],
        **_prior_arrays('prior', st.priors), **_prior_arrays('past', st.past), **fix_arrays,
        **vc_arrays, **cal_arrays, **last_arrays)
    return meta, arrays


def _prior_arrays(name: str, priors: list) -> dict[str, np.ndarray]:
    """Joint priors ``(node rows, mean, information)`` as arrays ``{name}_sizes``,
    ``{name}_idx``, ``{name}_mean`` and their information's non-zero 6x6 blocks."""
    cat = (lambda xs, shape: np.concatenate(xs) if xs else np.zeros((0,) + shape))  # noqa: E731
    blocks = [_info_blocks(info) for _, _, info in priors]
    return {f'{name}_sizes': np.array([idx.size for idx, _, _ in priors], dtype=np.int64),
            f'{name}_idx': cat([idx for idx, _, _ in priors], ()).astype(np.int64),
            f'{name}_mean': cat([mean for _, mean, _ in priors], (4, 4)),
            f'{name}_nblocks': np.array([b[0].size for b in blocks], dtype=np.int64),
            f'{name}_brow': cat([b[0] for b in blocks], ()).astype(np.int64),
            f'{name}_bcol': cat([b[1] for b in blocks], ()).astype(np.int64),
            f'{name}_blocks': cat([b[2] for b in blocks], (6, 6))}


def _priors_of(name: str, arrays: dict[str, np.ndarray]) -> list:
    """Inverse of :func:`_prior_arrays` (also the dense layout of versions 1-3)."""
    sizes = np.asarray(arrays[f'{name}_sizes'], dtype=np.int64)
    if not sizes.size:
        return []
    idx_cuts = np.cumsum(sizes)[:-1]
    if f'{name}_blocks' in arrays:  # version 4: non-zero 6x6 blocks of each information
        cuts = np.cumsum(np.asarray(arrays[f'{name}_nblocks'], dtype=np.int64))[:-1]
        infos = [_info_of_blocks(k, np.asarray(r, dtype=np.int64), np.asarray(c, dtype=np.int64),
                                 np.asarray(b, dtype=float))
                 for k, r, c, b in zip(sizes.tolist(), np.split(arrays[f'{name}_brow'], cuts),
                                       np.split(arrays[f'{name}_bcol'], cuts),
                                       np.split(arrays[f'{name}_blocks'], cuts))]
    else:  # versions 1-3: one dense information per prior
        infos = [np.array(info).reshape(6 * k, 6 * k) for k, info in zip(
            sizes.tolist(), np.split(arrays[f'{name}_info'], np.cumsum((6 * sizes) ** 2)[:-1]))]
    return [(np.array(idx, dtype=np.int64), np.array(mean), info)
            for idx, mean, info in zip(np.split(arrays[f'{name}_idx'], idx_cuts),
                                       np.split(arrays[f'{name}_mean'], idx_cuts), infos)]


def _info_blocks(info) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A prior's information as its non-zero 6x6 blocks: block rows, block columns and the
    blocks ``(b, 6, 6)`` (a dense matrix: every block)."""
    if sp.issparse(info):
        bsr = sp.bsr_matrix(info, blocksize=(6, 6))
        bsr.sort_indices()
        rows = np.repeat(np.arange(bsr.shape[0] // 6), np.diff(bsr.indptr))
        return rows, bsr.indices.astype(np.int64), np.asarray(bsr.data, dtype=float)
    k = info.shape[0] // 6
    rows, cols = np.divmod(np.arange(k * k), k)
    return rows, cols, np.asarray(info, dtype=float).reshape(k, 6, k, 6).transpose(0, 2, 1, 3
                                                                                ).reshape(-1, 6, 6)


def _info_of_blocks(k: int, rows: np.ndarray, cols: np.ndarray, blocks: np.ndarray):
    """Inverse of :func:`_info_blocks`: every block present gives the dense matrix back, a
    block-sparse information a BSR matrix."""
    if rows.size == k * k:
        dense = np.zeros((k, k, 6, 6))
        dense[rows, cols] = blocks
        return dense.transpose(0, 2, 1, 3).reshape(6 * k, 6 * k)
    order = np.lexsort((cols, rows))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=k))])
    return sp.bsr_matrix((np.array(blocks[order]), cols[order], indptr), shape=(6 * k, 6 * k))


def _parse(buf: bytearray, path: Path) -> tuple[dict, dict[str, np.ndarray], int]:
    if len(buf) < _PREFIX.size:
        raise CorruptFileError('state file cut short', str(path))
    _, version, hlen, hcrc = _PREFIX.unpack_from(buf)
    if version not in READ_VERSIONS:
        raise InputError(f'{path}: state format version {version}, this ga_ros reads versions '
                         f'{", ".join(map(str, READ_VERSIONS))} (and 1, .npz); use the ga_ros '
                         'version that wrote it, or delete the file to start a new survey')
    header = bytes(buf[_PREFIX.size:_PREFIX.size + hlen])
    if len(header) != hlen or zlib.crc32(header) != hcrc:
        raise CorruptFileError('state header fails its checksum', str(path))
    head = json.loads(header)
    base = _PREFIX.size + hlen
    arrays = {}
    for name, dtype, shape, offset, nbytes, crc in head['arrays']:
        start = base + int(offset)
        if start + nbytes > len(buf):
            raise CorruptFileError(f'state file cut short (array {name!r})', str(path))
        view = memoryview(buf)[start:start + nbytes]
        if zlib.crc32(view) != crc:
            raise CorruptFileError(f'array {name!r} fails its checksum', str(path))
        arrays[name] = np.frombuffer(buf, dtype=np.dtype(dtype), count=int(np.prod(shape)),
                                     offset=start).reshape(shape)
    return head['meta'], arrays, int(version)


def _parse_legacy(path: Path) -> tuple[dict, dict[str, np.ndarray], int]:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}   # each array decompressed once
    meta = json.loads(bytes(arrays.pop('meta')).decode())
    if meta.get('version') != _LEGACY_VERSION:
        raise InputError(f'{path}: unsupported state version {meta.get("version")}')
    priors = [(arrays[f'prior{p}_idx'], arrays[f'prior{p}_mean'], arrays[f'prior{p}_info'])
              for p in range(int(arrays['n_priors']))]
    arrays['prior_sizes'] = np.array([p[0].size for p in priors], dtype=np.int64)
    arrays['prior_idx'] = np.concatenate([p[0] for p in priors] or [np.zeros(0, np.int64)])
    arrays['prior_mean'] = np.concatenate([p[1] for p in priors] or [np.zeros((0, 4, 4))])
    arrays['prior_info'] = np.concatenate([p[2].ravel() for p in priors] or [np.zeros(0)])
    arrays['last_window'] = np.asarray(meta['last_window'], dtype=np.int64)
    return meta, arrays, _LEGACY_VERSION


def _restore(meta: dict, arrays: dict[str, np.ndarray], config) -> TrackWindowAligner:
    cfg = config if config is not None else AlignerConfig.from_dict(meta['config'])
    al = TrackWindowAligner.from_state(cfg, state_of_arrays(meta, arrays, cfg.window_tracks))
    al.resume_refinement(meta.get('refine_pending'))  # the pending background refinement
    return al


def state_of_arrays(meta: dict, arrays: dict[str, np.ndarray], window_tracks: int
                    ) -> WindowState:
    """The :class:`WindowState` of :func:`state_arrays`' output (also the layouts of versions
    1-3); the last window adjustment is recomputed on first use (over the last
    ``window_tracks`` finished tracks). Raises ``ValueError`` for inconsistent arrays."""
    T_first = np.array(arrays['T_first'], dtype=float)
    if T_first.shape != (4, 4) or not np.isfinite(T_first).all():
        raise InputError('T_world_first must be a finite 4x4 pose')
    ids = np.asarray(arrays['ids'], dtype=np.int64)
    track = np.asarray(arrays['track'], dtype=np.int64)
    n = ids.size
    src, dst = (np.asarray(arrays[k], dtype=np.int64) for k in ('src', 'dst'))
    m = src.size
    status = _checked(arrays, n, m, src, dst)
    cap = max(64, 2 * n)
    st = WindowState(T_first=T_first, index=IdIndex.of(ids), idarr=Rows.of(ids, np.int64),
                     trackarr=Rows.of(track, np.int64),
                     stamparr=Rows.of(arrays['stamp'], np.int64), T=zeros((cap, 4, 4)),
                     cov=SymArray(cap), frozen=zeros((cap,), bool),
                     track_nodes=TrackRanges.of(track))
    st.T[:n] = arrays['T']
    st.cov.packed[:n] = arrays['cov21']
    st.frozen[:n] = arrays['frozen']
    st.tracks = [int(t) for t in meta['tracks']]
    st.finished = {int(t) for t in meta['finished']}
    st.open_track = None if meta['open_track'] is None else int(meta['open_track'])
    st.src, st.dst = Rows.of(src, np.int64), Rows.of(dst, np.int64)
    st.z, st.ccov = Rows.of(arrays['z'], float), SymRows.of_packed(arrays['ccov21'])
    st.cross = Rows.of(arrays['cross'], bool)
    st.status = Rows.of(status, np.int8)
    if m:
        ts, td = track[src], track[dst]
        k = np.arange(m)
        two = ts != td
        st.track_conns = TrackLists.of(np.concatenate([ts, td[two]]),
                                       np.concatenate([k, k[two]]))
        fp = arrays.get('fingerprint')
        fp = (np.asarray(fp, dtype=np.uint32) if fp is not None and fp.shape == (m,) else
              np.array(measurement_fingerprints(st.z.a, st.ccov.a[:]), dtype=np.uint32))
        st.fp = Rows.of(fp, np.uint32)
        st.prune_pairs()
    st.priors = _priors_of('prior', arrays)
    if 'past_sizes' in arrays:  # the bounded refinement's past prior (older files: none)
        st.past = _priors_of('past', arrays)
        st.retired = int(meta.get('refine_retired', 0))
    # older files: none, so the next trigger refines
    st.refine_drift = float(meta.get('refine_drift', np.inf))
    if 'fix_rows' in arrays:  # absolute fixes (older files: none; the gate's level is set
        # from the config when the aligner attaches the state)
        st.fixes = FixBook.of_arrays(meta.get('fixes', {}), arrays, st.fixes.gate_prob)
    if 'vc_group' in arrays and np.shape(arrays['vc_group']) == (m,):
        # the online variance components' book (older files, or 'off': none; its mode is set
        # from the config when the aligner attaches the state)
        st.variance = OnlineVarianceComponents.from_arrays(
            OnlineVarianceConfig(), {'names': meta.get('variance_groups', []),
                                     'group': arrays['vc_group'], 'cost': arrays['vc_cost'],
                                     'redundancy': arrays['vc_redundancy'],
                                     'fix_group': arrays.get('vc_fix_group'),
                                     'fix_cost': arrays.get('vc_fix_cost'),
                                     'fix_redundancy': arrays.get('vc_fix_redundancy'),
                                     'consistency': _consistency_of(meta, arrays),
                                     'split_names': meta.get('variance_split', []),
                                     'split': arrays.get('vc_split', np.zeros((0, 2)))})
    if 'cal_source' in arrays and np.shape(arrays['cal_source']) == (m,):
        # the online calibration's book (older files, or calibration off: none)
        st.calibration = OnlineCalibration.from_arrays(meta.get('calibration', {}), arrays)
    st.rejected = {str(k): int(v) for k, v in meta['rejected'].items()}
    st.n_updates = int(meta['n_updates'])
    st.n_outliers = int(meta['n_outliers'])
    st.n_failed_updates = int(meta.get('n_failed_updates', 0))  # older files: not kept
    st.last_failure = str(meta.get('last_failure', ''))
    if 'last_adjustment' in meta:  # the last adjustment as it was
        st.last_window = np.array(arrays['last_window'], dtype=np.int64)
        st.last_result = result_of_arrays(meta['last_adjustment'], {
            k[len(_LAST):]: v for k, v in arrays.items() if k.startswith(_LAST)})
    elif np.asarray(arrays['last_window']).size:
        # older files: the last adjustment, recomputed when needed (its covariances then come
        # from a solve at the saved estimate, not from the matrix the update factored)
        window = st.finished_order()[-window_tracks:]
        st.last_window = np.array(sorted(i for t in window for i in st.track_nodes[t]),
                                  dtype=np.int64)
        st.last_pending = window
    if 'weighted_idx' in arrays:  # where the next update starts the weighted parameters
        st.T_weighted = (np.array(arrays['weighted_idx'], dtype=np.int64),
                         np.array(arrays['weighted_T'], dtype=float).reshape(-1, 4, 4))
    return st


def _checked(arrays: dict[str, np.ndarray], n: int, m: int, src: np.ndarray, dst: np.ndarray
             ) -> np.ndarray:
    """Check the arrays' shapes and ranges (``ValueError``), converting the covariances of
    versions 1-2 (full 6x6 matrices, symmetric) to 21 upper-triangle values; returns the
    connections' status."""
    for name in ('cov', 'ccov'):
        if name + '21' not in arrays:
            full = np.asarray(arrays[name], dtype=float)
            if full.shape[1:] != (6, 6):
                raise ValueError(f'array {name!r} has shape {full.shape}, expected (k, 6, 6)')
            arrays[name + '21'] = pack_sym6(full)
    shapes = {'T': (n, 4, 4), 'cov21': (n, 21), 'frozen': (n,), 'stamp': (n,), 'dst': (m,),
              'z': (m, 6), 'ccov21': (m, 21), 'cross': (m,), 'status': (m,)}
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            raise ValueError(f'array {name!r} has shape {arrays[name].shape}, expected {shape}')
    if m and (min(src.min(), dst.min()) < 0 or max(src.max(), dst.max()) >= n):
        raise ValueError('a connection refers to a node index out of range')
    status = np.asarray(arrays['status'])
    if m and (status.min() < 0 or status.max() > 2):
        raise ValueError('a connection status is not 0, 1 or 2')
    return status


def _consistency_of(meta: dict, arrays: dict) -> dict | None:
    """The sources' consistency of a snapshot's variance book (older files: None)."""
    if 'vcc_n' not in arrays:
        return None
    keys = ('n', 'dof', 'sum', 'sum2', 'lag', 'last_pair', 'last_value', 'pairs', 'pair_source',
            'z', 'cov')
    return {'names': meta.get('variance_consistency', []),
            **{k: arrays[f'vcc_{k}'] for k in keys},
            # the keyframes' stamps of the kept pairs (older files: none, the motions as is)
            **({'pair_stamp': arrays['vcc_pair_stamp']} if 'vcc_pair_stamp' in arrays else {})}
