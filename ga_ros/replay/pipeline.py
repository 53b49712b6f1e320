"""The offline replay: bag -> [stereo VO] -> track-window alignment -> output bag, TUM, PNG, JSON.

Runs as fast as the CPU allows (no real-time pacing) and without ROS. The aligner sees exactly
what the alignment node would see, in bag order, so a replay reproduces the live pipeline's
numbers.

Outputs (in ``out_dir``)
------------------------
``replay_bag/`` (mcap rosbag2: corrected path after every track update, corrected poses with
covariance, the measurements, markers, the F2F path and the ground truth when the input has it),
``trajectory_ga.tum`` (the final batch of everything read), ``trajectory_online.tum`` (the
online estimate, the live node's at the end), ``trajectory_f2f.tum`` (the odometry anchored as
GA), ``trajectory_gt.tum`` (the ground truth at the keyframe stamps) and
``trajectory_gt_raw.tum`` (its stream as read; both when ground truth is present),
``trajectory.png`` and ``summary.json``; with ``map`` (``--map``, stereo bags) ``map_ga.ply``
and ``map_f2f.ply`` (:mod:`ga_ros.replay.map_outputs`). Log times of the output bag follow the
input's (:mod:`ga_ros.replay.outputs`).

Ground truth comes from a file or a topic (:mod:`ga_ros.io.groundtruth`), matched to the
keyframes by node id when both have them, else by stamp with interpolation.

A bag cut short (a truncated mcap) is replayed up to the damage: the result then carries a
warning, not an error.

The stages live apart: the settings (:mod:`ga_ros.replay.config`), what is read
(:mod:`ga_ros.replay.plan`), the run loop (:mod:`ga_ros.replay.run`), the final outputs
(:mod:`ga_ros.replay.finish`), the summary (:mod:`ga_ros.replay.result`); this module holds the
one call that chains them.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

from ga_ros.core.calibration import check_cameras
from ga_ros.errors import FormatError
from ga_ros.io.bag import BagReader
from ga_ros.io.folder_bag import open_recording
from ga_ros.io.topic_plan import TopicPlan
from ga_ros.replay import map_outputs
from ga_ros.replay.aligner import AlignerFactory, aligner_config, default_aligner_factory
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.finish import (
    f2f_path,
    finish,
    finish_stationary,
    frames_summary,
    map_to_odom_summary,
)
from ga_ros.replay.outputs import ReplayOutputs
from ga_ros.replay.plan import ReplaySource, open_source, plan_replay
from ga_ros.replay.result import ReplayResult, plain_fields
from ga_ros.replay.run import ReplayRun


def replay(bag_path: str | Path, out_dir: str | Path, config: ReplayConfig = ReplayConfig(),
           aligner_factory: AlignerFactory | None = None,
           on_plan: Callable[[TopicPlan], None] | None = None) -> ReplayResult:
    """Replay a bag through the alignment pipeline and write the outputs.

    Parameters
    ----------
    bag_path : rosbag2 directory, ``.mcap`` / ``.db3`` / ROS 1 ``.bag`` file, or a EuRoC ASL /
        KITTI odometry folder (:func:`ga_ros.io.folder_bag.open_recording`).
    out_dir : output directory (created; files in it are replaced).
    config : see :class:`ReplayConfig`.
    aligner_factory : builds the aligner from the datum ``T_world_first`` (default:
        :class:`ga_ros.core.window.TrackWindowAligner` with ``config.aligner``).
    on_plan : called with the topic plan before processing starts (e.g. to print it).

    Returns
    -------
    ReplayResult

    Raises
    ------
    FormatError
        If the bag cannot be opened, lacks the needed topics (nothing is written then), or turns
        out truncated or corrupt half-way: then every output is still written, valid, with what
        was read before the failure, and the error (with ``.result`` attached) is raised at the
        end.
    """
    t0 = time.perf_counter()
    bag_path = Path(bag_path)
    with open_recording(bag_path) as bag:
        assert bag.info is not None
        plan, specs = plan_replay(bag.info, config)
        factory = aligner_factory or default_aligner_factory(aligner_config(config),
                                                             config.aligner_kind)
        if on_plan is not None:
            on_plan(plan)
        source = open_source(bag, plan, specs, config)
        named = getattr(source.items, 'source_names', None)
        if config.calibrate_cameras and named is not None:   # before reading anything
            check_cameras(config.calibrate_cameras, named, '--calibrate-camera')
        result = ReplayResult(str(bag_path), plan.source, str(out_dir))
        outputs = ReplayOutputs(out_dir, config.outputs)
        run = ReplayRun(config, factory, outputs, result, source.ground_truth, source.match_by)
        run.source = source.items
        if config.tf and hasattr(source.items, 'passthrough'):  # the input's TF copied
            source.items.passthrough = run.copy_tf
        maps = map_outputs.attach(run, config.map) if config.map is not None else None
        try:
            _read_all(run, source, bag)
            _conclude(run, source, bag_path)
            if maps is not None and result.corrected is not None:
                result.map = map_outputs.write_map_outputs(
                    run, maps, result.corrected, f2f_path(run, result.corrected))
        finally:
            outputs.close()
            result.seconds = time.perf_counter() - t0
            result.files = {k: str(v) for k, v in outputs.files.items()}
            result.output_counts = dict(outputs.bag.counts)
            outputs.summary(result.as_dict())
    if result.error is not None:
        exc = FormatError(f'{result.error} (partial outputs written to {out_dir})')
        exc.result = result  # type: ignore[attr-defined]
        raise exc
    return result


def _read_all(run: ReplayRun, source: ReplaySource, bag: BagReader) -> None:
    """Every item of the source through the run, with the progress bar when asked for; a bag
    cut short is used up to the damage (a warning), another read failure is the result's
    error."""
    bar = None
    counter, result = source.counter, run.result
    if run.config.progress:
        from tqdm import tqdm

        bar = tqdm(total=source.total, unit=source.unit, file=sys.stderr, mininterval=0.5,
                   desc=f'replay {Path(result.bag).name}')
    last = 0
    try:
        for item in source.items:
            run.step(item)
            if bar is not None and counter[0] != last:
                bar.update(counter[0] - last)
                last = counter[0]
    except FormatError as exc:
        if bag.truncated is None and 'truncated' not in str(exc):
            result.error = str(exc)
        else:  # a bag cut short: everything before the damage is used
            result.warnings.append(f'{exc}; replayed the {counter[0]} {source.unit}s before '
                                   'the damage')
    finally:
        if bar is not None:
            bar.update(counter[0] - last)  # what was read after the last item
            bar.close()


def _conclude(run: ReplayRun, source: ReplaySource, bag_path: Path) -> None:
    """After the last item: counts, frames and source statistics, the stationary or empty
    cases, and the final outputs (:func:`ga_ros.replay.finish.finish`)."""
    result, counter = run.result, source.counter
    result.n_inputs = counter[0]
    result.frames = frames_summary(run)
    stats = getattr(source.items, 'stats', None)
    if stats is not None:
        result.source_stats = plain_fields(stats)
    if run.aligner is None and result.error is None and run.stamps:
        finish_stationary(run)  # keyframes but no motion: the robot stood still
        if stats is not None and hasattr(stats, 'summary'):  # stereo: every reason
            result.notes.append(f'stereo: {stats.summary()}; if the camera did move, '
                                'lower the VO keyframe thresholds')
    elif run.aligner is None and result.error is None:
        examples = '; '.join(result.rejected_examples[:3])
        if stats is not None and hasattr(stats, 'summary'):  # stereo: every reason
            examples = f'stereo: {stats.summary()}'
        result.error = (f'{bag_path}: no valid measurements in {counter[0]} '
                        f'{source.unit}s' + (f' ({examples})' if examples else ''))
    finish(run)
    map_to_odom_summary(run)
    fix_stats = getattr(run.aligner, 'fix_stats', None)
    if fix_stats is not None and 'absolute' in result.source_stats:
        result.source_stats['absolute']['aligner'] = plain_fields(fix_stats)
