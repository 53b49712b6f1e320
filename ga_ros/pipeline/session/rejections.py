"""The typed reasons of the inputs a session rejects, and the errors of the gap healer's
refusals."""

from __future__ import annotations

from ga_ros.core.gaps import Route
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError, Reason


def rejection_reason(exc: BaseException) -> Reason:
    """The typed reason of a rejection (``Reason.INVALID`` when the error names none)."""
    try:
        return Reason(getattr(exc, 'reason', Reason.INVALID))
    except ValueError:
        return Reason.INVALID


def unknown_source(m: Measurement) -> InputError:
    return InputError(f'source node {m.src_id} of track {m.src_track} is unknown and that track '
                      'can no longer take new nodes (a later track has begun)',
                      reason=Reason.UNKNOWN_SOURCE)


def refused(m: Measurement, route: Route) -> InputError:
    if route is Route.DUPLICATE:
        return InputError(f'measurement {m.src_id}->{m.dst_id} was already received (and taken '
                          'reversed)', reason=Reason.DUPLICATE)
    return unknown_source(m)
