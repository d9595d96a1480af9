"""Offline replay: drive the same :class:`~epi_vo.core.pipeline.VoPipeline` as the node over a recorded bag.

Writes into the output directory:
- ``trajectory.tum``: ``stamp tx ty tz qx qy qz qw`` per frame that has a pose, the camera optical
  frame relative to the first frame (the pipeline's ``T_w_c``), stamp = image header stamp in seconds;
- ``frames.jsonl``: one JSON object per input frame (:meth:`FrameResult.to_record`), flushed per line;
- ``output.mcap``: what vo_node publishes, stamped with the image stamps: /vo/odometry (what a robot may
  fuse: metres, or the position held with the "unknown" variance), /vo/odometry/vo_units (the motion in VO
  units, while it is in VO units), /vo/points, /vo/path, /tf, /vo/frame_status (``epi_vo.runner.outputs``);
- ``stats.json``: run totals, per-stage median times and, with ground truth, evo metrics;
- ``groundtruth.tum``: the ground truth used (when there is one), in the same TUM form.

Every image message read gives exactly one record, also one that cannot be used (undecodable CDR,
header stamp that is no valid ROS time, bad pixels or calibration): that frame is rejected with the
reason and the replay goes on. Every stamp written is a valid ROS time.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import json
import logging
import math
import signal
import threading
import time
import typing
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.config import ScaleSourceKind, VoConfig
from epi_vo.core.errors import BagError, EpiVoError, Interrupted, OutputError
from epi_vo.core.frame import FrameResult
from epi_vo.core.scale import Units
from epi_vo.io import bag_topics, bagio, outbag, tum
from epi_vo.io.node_options import CameraExtrinsic
from epi_vo.io.paths import check_bag_path, refuse_special_file
from epi_vo.io.trajectory import StampedPoses
from epi_vo.io.wheel_feed import WheelFeed
from epi_vo.runner.frames import FrameHandler, FrameInput
from epi_vo.runner.outputs import FrameOutputs, OutputFrames
from epi_vo.tools.consistency import OdometryLog, consistency_metrics, format_consistency
from epi_vo.tools.json_check import fields_problem
from epi_vo.tools.replay_outputs import (
    FRAMES_FILE,
    OUTPUT_BAG,
    OUTPUT_FLUSH_FRAMES,
    TRAJECTORY_FILE,
    PathLength,
    check_outputs_clear,
    ensure_output_dir,
    open_output,
    os_reason,
    output_paths,
    remove_stats,
    tum_stamp,
    write_stats,
)

if TYPE_CHECKING:
    from epi_vo.tools.evaluation import TrajectoryMetrics

_log = logging.getLogger(__name__)

ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
PATH_MAX_POSES = 1000
STATUS_NAME, HARDWARE_ID = "epi_vo", "replay"  # the frame statuses are "epi_vo: tracking", hardware "replay"


GT_AUTO = "auto"
GT_NONE = "none"


def gt_choice(gt_tum: str | Path | None = None, gt_topic: str | None = None, no_gt: bool = False) -> str:
    """``ReplaySummary.gt_choice`` of a run given these options."""
    if no_gt:
        return GT_NONE
    if gt_tum is not None:
        return f"file {gt_tum}"
    return f"topic {gt_topic}" if gt_topic is not None else GT_AUTO


@dataclass(frozen=True)
class ReplaySummary:
    """Totals of one replay run (what ``stats.json`` holds)."""

    bag: str
    image_topic: str
    camera_info_topic: str
    frames: int
    frames_with_pose: int
    tracked_percent: float
    keyframes: int
    states: dict[str, int]
    models: dict[str, int]
    ms_per_frame: float
    stage_ms: dict[str, float]
    path_length: float  # in ``units`` (``PathLength``)
    metrics: dict[str, Any] | None = None
    gt_source: str = ""
    output_dir: str = ""
    notes: list[str] = field(default_factory=list)
    parameters: dict[str, Any] = field(default_factory=dict)  # the pipeline config of the run
    rejected: list[str] = field(default_factory=list)  # one line per distinct problem of rejected frames
    rejected_frames: int = 0  # frames (image messages read) that were rejected
    scale_source: str = "none"
    units: str = "vo"  # of the trajectory at the end of the run: 'm' once a metric scale source is established
    metric_from_frame: int | None = None  # first frame whose position was metric
    # Poses published before metric scale was established (held, VO units): not in the metrics
    # (see epi_vo.tools.evaluation.metric_poses)
    poses_before_metric: int = 0
    skipped_messages: list[str] = field(default_factory=list)  # camera_info / ground truth not decodable,
    # image messages announced by the bag but not read
    wall_s: float = 0.0  # run_replay from start to finish (opening the bag .. evaluation), seconds
    end_to_end_fps: float = 0.0  # frames / wall_s: reading, decoding, VO, writing, evaluation (process start-up
    # and imports excluded)
    gt_choice: str = GT_AUTO  # how ground truth was chosen: GT_AUTO (the topic named so), GT_NONE (--no-gt),
    # 'topic <name>' (--gt-topic), 'file <path>' (--gt)
    map_frame_id: str = ""  # vo_node's map_frame_id: '' the odometry carries the window's corrections; else
    # it stays continuous and /tf carries them as map_frame_id -> odom
    # scale_source wheel_odometry: the messages of its topic and what became of them (WheelInputCounts)
    wheel_odometry: dict[str, int] | None = None
    # The camera extrinsic of /vo/odometry (:func:`extrinsic_record`): declared by the parameters, or the default
    # (camera level at base_link, no offset: the base frame is the camera's); None in an older stats.json
    extrinsic: dict[str, Any] | None = None

    @property
    def has_problems(self) -> bool:
        """Frames rejected or messages skipped: ``epi-vo replay`` exits 3."""
        return bool(self.rejected_frames or self.rejected or self.skipped_messages)

    def to_json(self) -> dict[str, Any]:
        return _jsonable(asdict(self))

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ReplaySummary:
        """The summary a ``stats.json`` holds (keys it does not know are ignored; a field missing from an
        older file takes its default). Raises OutputError when a required field is missing."""
        names = {f.name for f in fields(cls)}
        missing = sorted(f.name for f in fields(cls)
                         if f.name not in data and f.default is MISSING and f.default_factory is MISSING)
        if missing:
            raise OutputError(f"not a stats.json of epi-vo replay: no {', '.join(missing)}")
        problem = stats_problem(data)
        if problem:
            raise OutputError(problem)
        values = {k: v for k, v in data.items() if k in names}
        for name in ("ms_per_frame", "tracked_percent", "path_length", "wall_s", "end_to_end_fps"):
            if name in values and values[name] is None:  # written as null when it was not finite
                values[name] = math.nan
        return cls(**values)

    def problem_line(self) -> str:
        """One line: how many of the frames read were rejected and the first problem, then what was skipped
        (empty when there was no problem)."""
        parts = []
        if self.rejected:
            others = f" (and {len(self.rejected) - 1} other problem(s))" if len(self.rejected) > 1 else ""
            parts.append(f"{self.rejected_frames} of {self.frames} frames rejected: {self.rejected[0]}{others}")
        if self.skipped_messages:
            parts.append(f"{len(self.skipped_messages)} message(s) skipped: {self.skipped_messages[0]}")
        return " ".join("; ".join(parts).split())


@functools.cache
def _stats_types() -> dict[str, Any]:
    """The JSON type of every field of stats.json (a float may be null: written so when not finite)."""
    def nullable(tp: Any) -> Any:
        if tp is float:
            return float | None
        if typing.get_origin(tp) is dict:
            key, value = typing.get_args(tp)
            return dict[key, nullable(value)]  # type: ignore[valid-type,misc]
        return tp

    return {k: nullable(v) for k, v in typing.get_type_hints(ReplaySummary).items()}


def stats_problem(data: dict[str, Any], where: str = "stats.json") -> str | None:
    """Why the fields of a ``stats.json`` (those present) do not have the types :class:`ReplaySummary` gives
    them, in one line naming the field; None when they do."""
    return fields_problem(data, _stats_types(), where)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


PACE_MAX_GAP_S = 2.0  # a paced replay waits at most this long between two frames (a recording's pause)


class Pace:
    """Holds each frame back until its stamp's time, at ``rate`` times real time, has come."""

    def __init__(self, rate: float) -> None:
        if not (math.isfinite(rate) and rate > 0.0):
            raise ValueError(f"rate must be a positive number, not {rate}")
        self.rate = rate
        self._origin: tuple[int, float] | None = None  # (stamp ns, wall s) the schedule counts from
        self._last_ns: int | None = None

    def wait(self, stamp_ns: int, stop: Callable[[], bool]) -> None:
        now = time.monotonic()
        gap_s = (stamp_ns - self._last_ns) * 1e-9 if self._last_ns is not None else 0.0
        self._last_ns = stamp_ns
        if self._origin is None or not 0.0 <= gap_s <= PACE_MAX_GAP_S:  # start, or a jump: a new schedule
            self._origin = (stamp_ns, now + min(max(gap_s, 0.0), PACE_MAX_GAP_S) / self.rate)
        due = self._origin[1] + (stamp_ns - self._origin[0]) * 1e-9 / self.rate
        while not stop() and (left := due - time.monotonic()) > 0.0:
            time.sleep(min(left, 0.1))


def run_replay(bag_path: str | Path, output_dir: str | Path, cfg: VoConfig | None = None, *,
               image_topic: str | None = None, camera_info_topic: str | None = None,
               gt_tum: str | Path | None = None, progress: bool = False,
               on_result: Callable[[FrameResult], None] | None = None,
               on_open: Callable[[int], None] | None = None, lookahead: bool = True,
               rate: float | None = None, map_frame_id: str = "", gt_topic: str | None = None,
               no_gt: bool = False, inputs: Sequence[str | Path] = (),
               extrinsic: CameraExtrinsic | None = None,
               camera_info_edit: Callable[[Any], Any] | None = None) -> ReplaySummary:
    """Replay every image of a bag through the pipeline and write the outputs (see module doc).

    A frame that cannot be used (undecodable message or image, header stamp that is no ROS time,
    unsupported encoding, unusable calibration, no camera_info) is recorded with its reason
    (``FrameResult`` of state lost) and replay goes on; ``ReplaySummary.rejected`` lists the problems,
    ``rejected_frames`` counts those frames, ``skipped_messages`` lists camera_info / ground-truth
    messages that could not be decoded and images the bag announces but that could not be read.
    ``on_result`` is called with each frame's result once its outputs are written (an exception it raises
    ends the replay with the outputs finalised), ``on_open`` with the bag's announced frame count.
    ``lookahead``: the next image is decoded first and tracked into on a worker thread while the current
    one is processed (``VoPipeline.announce_next``): the same outputs, ~15 % more frames/s on 2 cores; the
    records' ``total`` is then this thread's time and ``klt_ahead`` the worker's. Off: KLT in line, as a
    live node runs it (the benchmark's per-frame times).
    ``rate``: frames are handed to the pipeline at ``rate`` times the pace of their stamps, as a camera
    would deliver them (KLT in line, no lookahead), so work beside the frame loop (the windowed
    adjustment's worker) has the time it would have live; a gap between stamps counts at most
    ``PACE_MAX_GAP_S``. None: as fast as possible. The outputs are the same either way.
    ``map_frame_id``: as vo_node's (its parameter file may set it): '' /vo/odometry is the pipeline's pose,
    which jumps by the windowed adjustment's corrections; a frame name keeps /vo/odometry continuous and
    puts the corrections into the ``map_frame_id -> odom`` transform on /tf (beside ``odom -> base_link``,
    written at every frame with a pose either way), as the node broadcasts them.
    Ground truth: ``gt_tum`` (a TUM file) when given, else the bag's ``gt_topic``, else its one topic named
    as ground truth (:func:`epi_vo.io.bag_topics.is_ground_truth_name`); none with ``no_gt``. ``inputs``: other
    files the run reads (a parameter file), which no output may overwrite either. ``extrinsic``: the camera
    mounting the parameters declare (``camera_xyz`` / ``camera_rpy``), used as vo_node uses it without TF (for
    /vo/odometry, /tf and the floor search); None: the default (camera level at base_link), as the node's
    defaults give. ``stats.json`` records which (``extrinsic``). ``camera_info_edit``: every CameraInfo passes
    through it before the pipeline sees it (the benchmark's imperceptibly perturbed calibration); None: as recorded.

    Raises:
        BagError: unreadable or empty bag, missing or ambiguous topics, a bag that is no regular file or
            directory (a FIFO, a device).
        OutputError: an output would overwrite an input or write into a bag directory (checked before
            anything is written), or the output directory or a file in it cannot be created or written.
        Interrupted: SIGINT, SIGTERM or SIGHUP arrived; raised between two frames, outputs finalised.
    """
    started = time.perf_counter()
    cfg = cfg or VoConfig()
    check_bag_path(bag_path)
    if gt_tum is not None:
        refuse_special_file(gt_tum, tum.TUM_FILE)
    check_outputs_clear([bag_path, gt_tum, *inputs], output_paths(Path(output_dir)))
    out = ensure_output_dir(output_dir)
    remove_stats(out)  # stats.json is written last: without it the directory holds no finished replay
    handler = FrameHandler(cfg, OutputFrames(ODOM_FRAME, BASE_FRAME, map_frame_id),
                           None if extrinsic is None else extrinsic.T_base_cam, path_max_length=PATH_MAX_POSES,
                           status_name=STATUS_NAME)
    results_pose: list[tuple[float, np.ndarray, np.ndarray]] = []
    metric_stamps: list[dict[str, Any]] = []  # the poses published in metres (see evaluation.metric_poses)
    states: collections.Counter[str] = collections.Counter()
    models: collections.Counter[str] = collections.Counter()
    stage_times: dict[str, list[float]] = collections.defaultdict(list)
    rejected: collections.Counter[str] = collections.Counter()
    first_rejected: dict[str, int] = {}
    n_frames = n_pose = n_kf = 0
    focal_ratios: list[float] = []  # frames that fit a pure rotation under another focal length
    path = PathLength()
    metric_from: int | None = None
    units = Units.VO
    odo_log: OdometryLog | None = None  # with ground truth

    try:
        with stop_on_signals() as stop, \
                bagio.open_camera_bag(bag_path, image_topic, camera_info_topic, gt_topic,
                                      wheel_topic=_wheel_topic(cfg), no_ground_truth=no_gt or gt_tum is not None
                                      ) as bag, \
                open_output(out / FRAMES_FILE) as frames_f, open_output(out / TRAJECTORY_FILE) as tum_f, \
                outbag.OutputBag(out / OUTPUT_BAG, overwrite=True) as obag, \
                _Progress(progress, bag.frame_count) as bar:
            if on_open is not None:
                on_open(bag.frame_count)
            gt = _ground_truth(bag, gt_tum)
            if gt is not None:  # kept beside the estimate so that reports can be made from DIR alone
                tum.write_tum(out / "groundtruth.tum", *gt[1])
                odo_log = OdometryLog()  # what /vo/odometry carried, for the covariance's consistency
            wheel = WheelFeed(bag.read_wheel_odometry(), handler.pipeline, cfg.wheel_odometry_timeout_s)
            pace = Pace(rate) if rate is not None else None
            for frame, next_frame in with_next(bag.iter_frames()):
                wheel.up_to(frame.stamp_ns)
                if pace is not None:
                    pace.wait(frame.stamp_ns, lambda: stop.requested)
                if stop.requested:  # a signal arrived during the previous frame: all its outputs are written
                    raise Interrupted(stop.signum)
                ahead = next_frame if lookahead and pace is None and next_frame is not None else None
                handled = handler.handle(frame_input(bag, frame, camera_info_edit),
                                         None if ahead is None else frame_input(bag, ahead, camera_info_edit),
                                         HARDWARE_ID)
                result, problem, outputs = handled.result, handled.problem, handled.outputs
                if problem is not None:
                    rejected[problem] += 1
                    first_rejected.setdefault(problem, frame.index)
                n_frames += 1
                if result.scale.metric and metric_from is None:
                    metric_from = frame.index
                units = result.scale.units
                states[result.state.value] += 1
                models[result.model.value] += 1
                n_kf += int(result.is_keyframe)
                if math.isfinite(result.focal_ratio):
                    focal_ratios.append(result.focal_ratio)
                for k, v in result.timings_ms.items():
                    stage_times[k].append(v)
                record = outputs.record
                frames_f.write(json.dumps(record) + "\n")
                frames_f.flush()
                if result.has_pose:
                    n_pose += 1
                    p, q = result.position, result.quat_xyzw
                    tum_f.write(f"{tum_stamp(result.stamp_ns)} " + " ".join(f"{v:.9f}" for v in (*p, *q)) + "\n")
                    tum_f.flush()  # as frames.jsonl: what a kill leaves holds every frame written
                    results_pose.append((result.stamp_ns * 1e-9, p.copy(), q.copy()))
                    if result.scale.metric:
                        metric_stamps.append({"stamp_ns": result.stamp_ns, "metric_scale": True})
                    path.add(p, result.scale.units)
                write_outputs(obag, outputs)  # a skipped frame gets its record and status, but no pose
                if odo_log is not None and (estimate := outputs.estimate) is not None:
                    odo_log.add(estimate.sample, record)  # the motion as estimated, in its own units
                if n_frames % OUTPUT_FLUSH_FRAMES == 0:
                    obag.flush()  # a complete chunk on disk: what epi-vo recover can copy after a kill
                bar.update()
                if on_result is not None:
                    on_result(result)
            wheel_counts = wheel.counts()
    except OSError as exc:  # reading is wrapped in BagError by bagio: this is an output file
        raise OutputError(f"cannot write the outputs in {out}: {os_reason(exc)}") from exc

    if n_frames == 0:
        raise BagError(f"bag {bag_path} has no image messages on {bag.image_topic}")
    skipped = list(bag.problems)
    notes: list[str] = []
    if n_frames < bag.frame_count:
        # rosbags skips a damaged record silently; the bag's summary still counts it.
        skipped.append(f"the bag announces {bag.frame_count} images on {bag.image_topic}, {n_frames} could be "
                       "read (damaged records?)")
    elif n_frames > bag.frame_count:
        notes.append(f"the bag announces {bag.frame_count} images on {bag.image_topic}, {n_frames} were read "
                     "(its metadata understates the count)")
    if wheel_counts is not None and (wheel_counts.dropped or wheel_counts.used < 2):
        notes.append(f"wheel odometry on {bag.wheel_topic}: {wheel_counts.text()}")
    if focal_ratios:
        notes.append(f"{CALIBRATION_NOTE}: {len(focal_ratios)} frames fit a pure rotation under a "
                     f"focal length {np.median(focal_ratios):.3f} x camera_info's (median; per frame: focal_ratio)")
    metrics, gt_source, held = None, "", 0
    if gt is not None:
        gt_source = gt[0]
        try:
            m, held = _evaluate(results_pose, metric_stamps, gt[1])
            metrics = asdict(m)
        except EpiVoError as exc:
            notes.append(f"evaluation skipped: {exc}")
        if metrics is not None and odo_log is not None:
            try:
                metrics.update(consistency_metrics(odo_log, gt[1], ODOM_FRAME, BASE_FRAME,
                                                   handler.output.T_base_cam))
            except EpiVoError as exc:
                notes.append(f"covariance consistency not evaluated: {exc}")
    totals = stage_times.get("total", [0.0])
    wall_s = time.perf_counter() - started
    summary = ReplaySummary(
        bag=str(bag_path), image_topic=bag.image_topic, camera_info_topic=bag.camera_info_topic,
        frames=n_frames, frames_with_pose=n_pose, tracked_percent=100.0 * n_pose / n_frames, keyframes=n_kf,
        states=dict(states), models=dict(models), ms_per_frame=float(np.median(totals)),
        stage_ms={k: float(np.median(v)) for k, v in stage_times.items()}, path_length=path.length(units),
        metrics=metrics, gt_source=gt_source, output_dir=str(out), notes=notes, parameters=asdict(cfg),
        rejected=[f"{n} frame(s) from frame {first_rejected[r]}: {r}" for r, n in rejected.items()],
        rejected_frames=sum(rejected.values()), skipped_messages=skipped, scale_source=cfg.scale_source,
        units=units, metric_from_frame=metric_from, poses_before_metric=held, wall_s=wall_s,
        end_to_end_fps=n_frames / max(wall_s, 1e-9), map_frame_id=map_frame_id,
        wheel_odometry=None if wheel_counts is None else wheel_counts.record(),
        extrinsic=extrinsic_record(extrinsic, handler.output.T_base_cam),
        gt_choice=gt_choice(gt_tum, gt_topic, no_gt))
    write_stats(out, summary.to_json())
    return summary


CALIBRATION_NOTE = "check the camera calibration"  # how the note on rotation-only frames under another focal begins


def extrinsic_record(extrinsic: CameraExtrinsic | None, T_base_cam: NDArray[np.float64]) -> dict[str, Any]:
    """``stats.json``'s ``extrinsic``: ``source`` ('parameters' or 'default'), the parameters (zeros for the
    default) and ``T_base_cam`` (4x4 rows, camera optical frame -> base_link, as /vo/odometry was made with)."""
    return {"source": "default" if extrinsic is None else "parameters",
            "camera_xyz": [0.0] * 3 if extrinsic is None else [float(v) for v in extrinsic.camera_xyz],
            "camera_rpy": [0.0] * 3 if extrinsic is None else [float(v) for v in extrinsic.camera_rpy],
            "T_base_cam": [[float(v) for v in row] for row in T_base_cam]}


def _wheel_topic(cfg: VoConfig) -> str | None:
    """The bag topic of the wheel odometry: the node's parameter as a node in the root namespace resolves it."""
    if cfg.scale_source is not ScaleSourceKind.WHEEL_ODOMETRY:
        return None
    return bag_topics.recorded_topic_name(cfg.wheel_odometry_topic)




class _Progress:
    """tqdm bar over the frames, when asked for; a terminal that went away (SIGHUP) ends the bar, never the
    replay."""

    def __init__(self, enabled: bool, total: int) -> None:
        self._bar: Any = None
        if enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=total if total > 0 else None, unit="frame", desc="replay", leave=False)

    def __enter__(self) -> _Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        bar, self._bar = self._bar, None
        if bar is not None:
            with contextlib.suppress(OSError, ValueError):
                bar.close()

    def update(self) -> None:
        if self._bar is None:
            return
        try:
            self._bar.update(1)
        except (OSError, ValueError):  # stderr closed or gone
            self._bar = None


def frame_input(bag: bagio.CameraBag, frame: bagio.BagFrame,
                camera_info_edit: Callable[[Any], Any] | None = None) -> FrameInput:
    """A bag frame as the frame handler takes it (the same rule as vo_node's frames); ``camera_info_edit``
    replaces the frame's CameraInfo by what it returns for it (the benchmark's perturbed calibration)."""
    filed = "its log time" if frame.image_msg is None else "its header stamp clamped to a ROS time"
    info = frame.camera_info_msg
    if camera_info_edit is not None and info is not None:
        info = camera_info_edit(info)
    return FrameInput(frame.stamp_ns, frame.image_msg, bag.image_is_compressed, info, frame.problem,
                      f"recorded at {frame.stamp_ns} ns, {filed}" if frame.problem is not None else "",
                      no_camera_info=_no_camera_info(bag))


def with_next(frames: Iterable[bagio.BagFrame]) -> Iterator[tuple[bagio.BagFrame, bagio.BagFrame | None]]:
    """Each frame with the one after it (None for the last). A read error on the next frame is raised
    only after the current one was yielded: nothing read is lost to the lookahead."""
    it = iter(frames)
    cur = next(it, None)
    while cur is not None:
        try:
            nxt = next(it, None)
        except Exception as exc:
            yield cur, None
            raise exc
        yield cur, nxt
        cur = nxt


def _no_camera_info(bag: bagio.CameraBag) -> str:
    skipped = sum(p.startswith("camera_info") for p in bag.problems)
    if skipped:
        return f"no usable camera_info on {bag.camera_info_topic} ({skipped} message(s) could not be decoded)"
    return f"no camera_info on {bag.camera_info_topic}"


class StopRequest:
    """Set by :func:`stop_on_signals` when a stop was asked for, with the signal."""

    requested = False
    signum = signal.SIGINT


@contextlib.contextmanager
def stop_on_signals() -> Iterator[StopRequest]:
    """SIGINT / SIGTERM / SIGHUP during a replay stop it between frames, never between a frame's writes.

    Each frame writes a record, a trajectory line and several bag messages; an interrupt raised in the
    middle would leave the outputs disagreeing about the last frame, and SIGHUP's default action (the
    terminal closed, SSH dropped) would end the process before output.mcap gets its summary. The replay
    then raises :class:`~epi_vo.core.errors.Interrupted` (with the signal) at the next frame boundary, and
    every output is finalised on the way out. Outside the main thread (where signals cannot be
    handled) nothing changes.
    """
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def request(signum: int, frame: object) -> None:
        if not stop.requested:
            stop.signum = signal.Signals(signum)
        stop.requested = True

    signals = [signal.SIGINT, signal.SIGTERM, *([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])]
    saved = {sig: signal.signal(sig, request) for sig in signals}
    try:
        yield stop
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


def write_outputs(obag: outbag.OutputBag, outputs: FrameOutputs) -> None:
    """One frame's outputs into output.mcap, as vo_node publishes them (each message at the image stamp)."""
    stamp = outputs.result.stamp_ns
    for odom, topic in ((outputs.odometry, bagio.ODOMETRY_TOPIC),
                        (outputs.odometry_vo_units, bagio.VO_UNITS_ODOMETRY_TOPIC)):
        if odom is not None:
            s = odom.sample
            obag.write_odometry(stamp, odom.frame_id, odom.child_frame_id, s.position, s.quat_xyzw, s.pose_covariance,
                                s.linear_velocity, s.angular_velocity, s.twist_covariance, topic)
    if outputs.points is not None:
        obag.write_points(stamp, outputs.points.frame_id, outputs.points.points_xyz)
    if (path := outputs.path) is not None:
        obag.write_path(stamp, path.frame_id, path.stamps_ns, path.positions, path.quats_xyzw)
    if outputs.transforms:
        obag.write_tf(stamp, [(t.parent, t.child, t.xyz, t.quat_xyzw) for t in outputs.transforms])
    obag.write_diagnostics(stamp, [outputs.status])


def _ground_truth(bag: bagio.CameraBag, gt_tum: str | Path | None
                  ) -> tuple[str, StampedPoses] | None:
    if gt_tum is not None:
        return str(gt_tum), tum.read_tum(gt_tum)
    gt = bag.read_ground_truth()
    if gt is None:
        return None
    stamps_s = np.asarray(gt.stamps_ns * 1e-9, dtype=np.float64)
    return gt_topic_source(gt.topic), StampedPoses(stamps_s, gt.positions, gt.quats_xyzw)


def gt_topic_source(topic: str) -> str:
    """``stats.json``'s ``gt_source`` for ground truth read from a bag topic."""
    return f"bag topic {topic}"


def _evaluate(poses: list[tuple[float, np.ndarray, np.ndarray]], metric_stamps: list[dict[str, Any]],
              gt: StampedPoses) -> tuple[TrajectoryMetrics, int]:
    """The metrics of the run's poses (its metric ones once it established metres) and how many poses
    were left out (held before metric scale)."""
    from epi_vo.tools.evaluation import evaluate_trajectory, metric_poses  # evo: only with ground truth

    stamps = np.array([s for s, _, _ in poses])
    pos = np.array([p for _, p, _ in poses]).reshape(-1, 3)
    quat = np.array([q for _, _, q in poses]).reshape(-1, 4)
    est, held = metric_poses(StampedPoses(stamps, pos, quat), metric_stamps)
    return evaluate_trajectory(est, gt), held


def format_summary(s: ReplaySummary) -> str:
    """The one-screen summary printed by ``epi-vo replay``."""
    lines = [
        f"epi_vo replay: {s.bag}",
        f"  topics        {s.image_topic} + {s.camera_info_topic}",
        f"  frames        {s.frames}   with pose {s.frames_with_pose} ({s.tracked_percent:.1f} %)   "
        f"keyframes {s.keyframes}",
        "  states        " + ", ".join(f"{k} {v}" for k, v in sorted(s.states.items())),
        "  models        " + ", ".join(f"{k} {v}" for k, v in sorted(s.models.items())),
        f"  time          {s.ms_per_frame:.2f} ms/frame median (" +
        ", ".join(f"{k} {v:.2f}" for k, v in s.stage_ms.items() if k != "total") + ")",
        f"  end to end    {s.end_to_end_fps:.1f} frames/s ({s.wall_s:.2f} s: reading, decoding, VO, writing)",
        f"  path length   {s.path_length:.3f} {'m' if s.units == Units.METRES else '(VO units)'}",
        f"  scale         {s.scale_source}: " + (f"metric from frame {s.metric_from_frame}"
                                                  if s.metric_from_frame is not None else "VO units"),
    ]
    if s.metrics is not None:
        m = s.metrics
        lines.append(f"  vs GT ({s.gt_source}): ATE {_f(m['ate_rmse'])} ({_f(m['ate_percent_of_path'])} % of path, "
                     f"Sim3)  RPE rot {_f(m['rpe_rot_deg_per_frame'])} deg/frame  trans-dir "
                     f"{_f(m['trans_direction_err_deg'])} deg  ({m['matched_poses']} poses"
                     + (f"; {s.poses_before_metric} held before metric scale not evaluated" if s.poses_before_metric
                        else "") + ")")
        if s.units == Units.METRES:
            lines.append(f"  metric        step scale {_f(m['step_scale_median'])} (estimate / GT, median)  ATE "
                         f"{_f(m['ate_se3_percent_of_path'])} % of path with SE(3) alignment only")
        line = format_consistency(m)
        if line is not None:
            lines.append(line)
    lines.extend(f"  note: {n}" for n in s.notes)
    lines.extend(f"  rejected: {r}" for r in s.rejected)
    lines.extend(f"  skipped: {m}" for m in s.skipped_messages)
    lines.append(f"  outputs       {s.output_dir}/{{trajectory.tum, frames.jsonl, output.mcap, stats.json}}")
    return "\n".join(lines)


def _f(x: float | None) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.4g}"

