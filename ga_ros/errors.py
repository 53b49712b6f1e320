"""Exception hierarchy of ga_ros.

Every error raised on bad input derives from :class:`GaError`, so nodes can catch one type,
warn and drop the sample, and the CLI can map it to exit code 1 with a one-line message
(:class:`UsageError`: exit code 2, as for a command line argparse refuses).
"""

from __future__ import annotations

from enum import StrEnum


class Reason(StrEnum):
    """Why a measurement was rejected: the key the diagnostics count (``rejected/<reason>``).

    A :class:`str` enum, so the keys compare equal to (and print as) their plain strings.
    """

    SELF_LOOP = 'self_loop'
    FROZEN = 'frozen'
    DUPLICATE = 'duplicate'
    OUT_OF_ORDER = 'out_of_order'
    BAD_COVARIANCE = 'bad_covariance'
    NON_FINITE = 'non_finite'
    BAD_ID = 'bad_id'
    BAD_KIND = 'bad_kind'
    BAD_QUATERNION = 'bad_quaternion'
    BAD_STAMP = 'bad_stamp'
    BAD_SHAPE = 'bad_shape'
    TRACK_MISMATCH = 'track_mismatch'
    ID_JUMP = 'id_jump'
    TRACK_JUMP = 'track_jump'
    UNKNOWN_SOURCE = 'unknown_source'
    INVALID = 'invalid'
    INTERNAL = 'internal'


class GaError(Exception):
    """Base class of all ga_ros errors."""


class InputError(GaError, ValueError):
    """Input data (a measurement, a covariance, a file) is malformed; nothing was changed.

    ``reason`` (a :class:`Reason`, default ``INVALID``) says why, for counting rejections
    without reading the message text.
    """

    reason: str = Reason.INVALID

    def __init__(self, *args: object, reason: str | None = None) -> None:
        super().__init__(*args)
        if reason is not None:
            self.reason = Reason(reason)


class UsageError(InputError):
    """Options of a command line that contradict each other (e.g. a settings section for an
    input the command line does not give); the CLI exits with code 2, as argparse does."""


class NetworkError(InputError):
    """The connection network is inconsistent (unknown node, self-loop, disconnected part)."""


class DegenerateGeometryError(GaError):
    """The problem is singular or ill-posed (e.g. a normal matrix that cannot be factored)."""


class SolverError(GaError):
    """The solver failed (diverged, produced non-finite values); the previous estimate stands."""


class FormatError(InputError):
    """A file could not be read; the message names the file and line."""

    def __init__(self, message: str, path: str | None = None, line: int | None = None) -> None:
        where = ''
        if path is not None:
            where = f'{path}:{line}: ' if line is not None else f'{path}: '
        super().__init__(where + message)
        self.path = path
        self.line = line


class UnsafePathError(InputError):
    """A path is a symbolic link or not a regular file: it is never opened, replaced or deleted.

    Remove the link (or choose another path) if it is not meant to be there.
    """


class ForeignFileError(InputError):
    """A file exists where ga_ros would write its own (a state file, a journal), but it is not one
    of ga_ros's: it is left untouched. Choose another path or move the file away."""


class CorruptFileError(FormatError):
    """A ga_ros file (state snapshot, journal) fails its checksum or is cut short; whatever is
    intact is kept and the file is moved aside, never deleted."""


class UnknownExtrinsicError(InputError):
    """A sensor's pose in the robot's base frame is not known (no transform on ``/tf_static``,
    no parameter): nothing is computed in a wrong frame. Publish the transform, set the
    extrinsic parameter, or say explicitly that the sensor frame is the base frame (the
    message names the parameters)."""


class PersistenceError(GaError):
    """The state file or its journal cannot be used or written (a full disk, a read-only
    directory, a path under a regular file). The node then runs without persistence, unless
    told to refuse to start (parameter ``state_required``): fix the path or free space."""


class NoUsableInputError(FormatError):
    """A bag has no input the replay reads without being told (no ga_ros measurements, no
    stereo pair); the message gives the command for the topics it has. ``command`` is that
    command ('' when the bag has no odometry or pose stream). The CLI exits with code 2."""

    def __init__(self, message: str, command: str = '') -> None:
        super().__init__(message)
        self.command = command
