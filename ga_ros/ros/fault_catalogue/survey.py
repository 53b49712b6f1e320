"""The data of a fault case: the survey it feeds, what it gets (:class:`Ctx`), the row it
returns (:class:`Row`) and the reference paths it compares with."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ga_ros import topics
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import odometry_to_measurement
from ga_ros.replay.samples import aerial_sample, write_measurement_bag


@dataclass
class Survey:
    """The measurements of a case, the bag that holds them and the reference path.

    Attributes
    ----------
    measurements : in publication order.
    bag : a measurements bag of them (for the cases that play it).
    T_ref : ``(n, 4, 4)`` reference path, ``T_world_node``: the aligner fed every measurement,
        then a track end.
    """

    measurements: list[Measurement]
    bag: Path
    T_ref: np.ndarray = field(repr=False)

    @property
    def n_nodes(self) -> int:
        return len(self.T_ref)


def reference(ms: list[Measurement]) -> np.ndarray:
    """The path of an aligner (defaults) fed ``ms`` then a track end."""
    aligner = TrackWindowAligner(AlignerConfig())
    aligner.add_measurements(ms)
    aligner.finish_track()
    return aligner.corrected_path().T_world_node


def small_survey(work: Path, seed: int = 12) -> Survey:
    """A simulated survey of 3 tracks (48 nodes, about 220 measurements; ``seed``: its
    noise)."""
    ms = aerial_sample(n_tracks=3, positions_per_swath=8, seed=seed).measurements
    return Survey(ms, write_measurement_bag(work / 'small_bag', ms, None), reference(ms))


def bag_survey(bag: Path) -> Survey:
    """The measurements of a bag's ``/ga/measurements`` topic."""
    with BagReader(bag) as reader:
        ms = [odometry_to_measurement(bm.msg)
              for bm in reader.messages(['/' + topics.MEASUREMENTS])]
    return Survey(ms, Path(bag), reference(ms))


@dataclass
class Row:
    """One case: survived, counted, nodes expected / kept, time to recover (s), note."""

    name: str
    survived: str
    counted: str
    expected: int
    kept: int
    recover_s: float | None = None
    note: str = ''

    @property
    def lost(self) -> int:
        return self.expected - self.kept


@dataclass
class Ctx:
    """What a case gets: its work directory, ROS domain, survey and the ``time.monotonic()``
    by which it must be done (its waits fail at once after it; default none)."""

    work: Path
    dom: int
    survey: Survey
    deadline: float = math.inf

    @property
    def ms(self) -> list[Measurement]:
        return self.survey.measurements

    def remaining(self, seconds: float) -> float:
        """A timeout of ``seconds``, cut to what is left before :attr:`deadline` (at least
        1 s, so that a late wait still fails by its timeout rather than blocking)."""
        return max(1.0, min(seconds, self.deadline - time.monotonic()))


#: A case: runs in its context and returns its row.
Case = Callable[[Ctx], Row]


def nodes_kept(ref: np.ndarray, got: np.ndarray) -> int:
    """Reference nodes present in the path within 1 mm of their reference position."""
    k = min(len(ref), len(got))
    if not k:
        return 0
    err = np.linalg.norm(ref[:k, :3, 3] - got[:k, :3, 3], axis=1)
    return int(np.count_nonzero(err <= 1e-3))


def finish_after(ms: list[Measurement], k: int) -> np.ndarray:
    """The path of an aligner fed ms[:k], a track end, the rest (refused ones dropped), then
    the last track end."""
    aligner = TrackWindowAligner(AlignerConfig())
    for j, m in enumerate(ms):
        if j == k:
            aligner.finish_track()
        try:
            aligner.add_measurement(m)
        except InputError:
            pass
    aligner.finish_track()
    return aligner.corrected_path().T_world_node


def mid(ms: list[Measurement]) -> int:
    """An index inside track 1."""
    return next(k for k, m in enumerate(ms) if m.dst_track == 1) + 5
