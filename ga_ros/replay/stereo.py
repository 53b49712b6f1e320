"""Stereo source of the replay: a loop over bag messages driving the stereo front end.

The same :class:`ga_ros.pipeline.stereo.StereoFrontEnd` as ``vo_node``, fed in bag order: every
``CameraInfo`` and image message goes to it as the node's callbacks would hand it over; each
pair's keyframe motion is yielded (and stepped into the aligner by the replay) before the
cross-track matching of that keyframe runs, and the corrected path of every alignment update
is given back to the front end (:meth:`StereoSource.on_corrected`), as ``vo_node`` gets the
alignment node's corrected path.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.extrinsic import TransformTree
from ga_ros.errors import GaError, InputError
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import CAMERA_INFO
from ga_ros.io.topic_plan import TopicPlan
from ga_ros.pipeline.stereo import FrameOutput, FrontEndConfig, StereoFrontEnd, StereoStats
from ga_ros.replay.source import SourceItem
from ga_ros.vo.calibration import read_stereo_calibration
from ga_ros.vo.odometry import VoConfig


def front_end_config(config: FrontEndConfig | VoConfig | None) -> FrontEndConfig:
    """The front end settings of a replay (a bare :class:`VoConfig` keeps the other defaults)."""
    if isinstance(config, FrontEndConfig):
        return config
    return FrontEndConfig(vo=config) if config is not None else FrontEndConfig()


class StereoSource:
    """Iterates a bag's stereo pairs through the front end and yields :class:`SourceItem`.

    Parameters
    ----------
    bag : open bag; ``plan`` : its topic plan (``source == 'stereo'``).
    config : :class:`FrontEndConfig` (or a :class:`VoConfig`; None = defaults).
    counter : ``counter[0]`` is incremented per processed pair (progress).
    """

    def __init__(self, bag: BagReader, plan: TopicPlan, config: Any, counter: list[int]) -> None:
        self.bag = bag
        self.plan = plan
        self.front = StereoFrontEnd(front_end_config(config))
        self.counter = counter
        self.tf_static = TransformTree()
        #: called with each ``/tf_static`` message of the bag (topic, type, CDR, message, log
        #: time), e.g. to copy them into the output bag; None: not read.
        self.passthrough: Callable[[str, str, bytes | None, Any, int], None] | None = None
        #: called with each processed pair that made a keyframe (its ``FrameOutput``, images
        #: included), e.g. to collect the keyframe clouds of ``--map``; None: nobody asks.
        self.on_keyframe: Callable[[FrameOutput], None] | None = None
        if plan.calibration:  # a bag without CameraInfo (e.g. EuRoC): calibration files
            models = read_stereo_calibration(list(plan.calibration))
            self.front.set_camera_models(models.left, models.right)
        self._resolve_extrinsic()

    @property
    def source_names(self) -> tuple[str, ...]:
        """The source every measurement of this replay carries: the camera's."""
        return (self.front.config.source,)

    @property
    def stats(self) -> StereoStats:
        """The front end's counts."""
        return self.front.stats

    def on_corrected(self, node_ids: IntArray, T_world_node: FloatArray) -> None:
        """Feedback of the aligner (what vo_node gets from the alignment node's path)."""
        self.front.set_corrected(node_ids, T_world_node)

    def _resolve_extrinsic(self) -> None:
        """The camera's extrinsic, before any work: the bag's ``/tf_static`` (``base_frame ->``
        the configured ``camera_frame``, else the first left image's frame), else the
        parameters, else the identity when said so (``assume_identity_extrinsic``).

        Raises
        ------
        UnknownExtrinsicError
            None of them gives it (the message says how to).
        """
        assert self.bag.info is not None
        if self.bag.info.topic('/tf_static') is not None:
            for bm in self.bag.messages(['/tf_static']):
                self.tf_static.add_message(bm.msg)
        cfg = self.front.config.extrinsic
        camera = cfg.camera_frame
        if not camera:
            images = self.bag.messages([self.plan.left_image])
            try:
                first = next(images, None)
            finally:
                images.close()
            if first is None:
                return  # no image: nothing to do
            camera = str(first.msg.header.frame_id)
        self.front.set_extrinsic(cfg.resolve(
            self.tf_static.lookup(cfg.base_frame, camera), camera,
            parameter='--vo T_base_camera=...', identity='--vo assume_identity_extrinsic=true',
            in_bag=True))

    def __iter__(self) -> Iterator[SourceItem]:
        p = self.plan
        sides = {p.left_image: 'left', p.right_image: 'right'}
        infos = {p.left_info: 'left', p.right_info: 'right'}
        log_ns = 0
        assert self.bag.info is not None
        tf = ['/tf_static'] if (self.passthrough is not None
                                and self.bag.info.topic('/tf_static') is not None) else []
        for bm in self.bag.messages(p.topics + tuple(tf)):
            log_ns = bm.log_ns
            if bm.topic in tf:
                if self.passthrough is not None and bm.data is not None:  # not from ROS 1
                    self.passthrough(bm.topic, bm.msgtype, bm.data, bm.msg, bm.log_ns)
                continue
            if bm.topic in infos and bm.msgtype == CAMERA_INFO:
                try:
                    self.front.set_camera_info(infos[bm.topic], bm.msg)
                except InputError as exc:  # counted and skipped, as vo_node does
                    yield SourceItem(None, bm.log_ns, error=f'stereo: CameraInfo rejected: {exc}')
                    continue
                for pair in self.front.release_held():  # pairs that came before it
                    yield from self._items(self.front.process_pair(pair), bm.log_ns)
                continue
            if bm.topic not in sides:
                continue
            for frame in self.front.add_image(sides[bm.topic], bm.msg):
                yield from self._items(frame, bm.log_ns)
        for pair in self.front.release_held(final=True):  # never calibrated: counted
            yield from self._items(self.front.process_pair(pair), log_ns)

    def _items(self, frame: FrameOutput, log_ns: int) -> Iterator[SourceItem]:
        """What one processed pair gives: its motion (or why none), then the cross-track
        connections of its keyframe."""
        self.counter[0] += 1
        if frame.result is None:
            yield SourceItem(None, log_ns, error=frame.error)
            return
        if self.on_keyframe is not None and frame.result.keyframe is not None:
            self.on_keyframe(frame)
        stamps = frame.node_stamps or None
        if frame.measurement is not None:
            yield SourceItem(frame.measurement, log_ns, node_stamps=stamps)
            stamps = None
        elif stamps:
            yield SourceItem(None, log_ns, node_stamps=stamps)
        try:
            attempts = self.front.match(frame)
        except GaError as exc:
            yield SourceItem(None, log_ns, error=f'stereo: cross-track: {exc}')
            return
        for a in attempts:
            if a.accepted and a.measurement is not None:
                yield SourceItem(a.measurement, log_ns, node_stamps=stamps)
