"""What a replay source yields: measurements (or rejections) in bag order, with their bag time."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.io.bag import BagReader
from ga_ros.pipeline.inputs import decode_measurement


@dataclass(frozen=True)
class SourceItem:
    """One step of a measurement source: a measurement (or a rejection) and its bag time.

    ``data`` is the raw CDR of the measurement when it was read from the bag; ``node_stamps``
    gives acquisition times of nodes the source knows (e.g. the first VO keyframe).
    """

    measurement: Measurement | None
    log_ns: int
    data: bytes | None = None
    error: str | None = None
    node_stamps: dict[int, int] | None = None
    fixes: tuple = ()  # absolute fixes (ga_ros.pipeline.absolute.ResolvedFix) ready now


def bag_measurements(bag: BagReader, topic: str, counter: list[int],
                     covariance_policy: str = 'reject') -> Iterator[SourceItem]:
    """Measurements read from ``topic`` (the ga_ros Odometry encoding); bad ones as rejections.

    ``counter[0]`` counts the messages read (the source's inputs); ``covariance_policy``:
    ``'reject'`` or ``'repair'`` a covariance that is not positive definite
    (:func:`ga_ros.pipeline.inputs.decode_measurement`).
    """
    for bm in bag.messages([topic]):
        counter[0] += 1
        try:
            m = decode_measurement(bm.msg, covariance_policy)
        except InputError as exc:
            yield SourceItem(None, bm.log_ns, error=f'decode: {exc}')
            continue
        yield SourceItem(m, bm.log_ns, data=bm.data)
