"""Offline replay: drive the same :class:`~epi_vo.pipeline.VoPipeline` as the node over a recorded bag.

Writes into the output directory:
- ``trajectory.tum``: ``stamp tx ty tz qx qy qz qw`` per frame that has a pose, the camera optical
  frame relative to the first frame (the pipeline's ``T_w_c``), stamp = image header stamp in seconds;
- ``frames.jsonl``: one JSON object per input frame (:meth:`FrameResult.to_record`), flushed per line;
- ``output.mcap``: /vo/odometry, /vo/points, /vo/path, /diagnostics stamped with the image stamps;
- ``stats.json``: run totals, per-stage median times and, with ground truth, evo metrics;
- ``groundtruth.tum``: the ground truth used (when there is one), in the same TUM form.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import math
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from epi_vo import bagio
from epi_vo.camera import CameraModelCache
from epi_vo.config import VoConfig
from epi_vo.errors import BagError, EpiVoError
from epi_vo.evaluation import TrajectoryMetrics, evaluate_trajectory
from epi_vo.msgconv import decode_frame
from epi_vo.odometry import OdometryConverter
from epi_vo.pipeline import FrameResult, VoPipeline
from epi_vo.status import frame_status

_log = logging.getLogger(__name__)

ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
PATH_MAX_POSES = 1000


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
    path_length: float
    metrics: dict[str, Any] | None = None
    gt_source: str = ""
    output_dir: str = ""
    notes: list[str] = field(default_factory=list)
    parameters: dict[str, Any] = field(default_factory=dict)  # the pipeline config of the run
    rejected: list[str] = field(default_factory=list)  # one line per distinct problem of rejected frames

    def to_json(self) -> dict[str, Any]:
        return _jsonable(asdict(self))


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def run_replay(bag_path: str | Path, output_dir: str | Path, cfg: VoConfig | None = None, *,
               image_topic: str | None = None, camera_info_topic: str | None = None,
               gt_tum: str | Path | None = None, progress: bool = False,
               on_result: Callable[[FrameResult], None] | None = None) -> ReplaySummary:
    """Replay every image of a bag through the pipeline and write the outputs (see module doc).

    A frame that cannot be used (undecodable image, unsupported encoding, unusable calibration, no
    camera_info) is recorded with its reason (``FrameResult`` of state lost) and replay goes on;
    ``ReplaySummary.rejected`` lists the problems.

    Raises:
        BagError: unreadable or empty bag, missing or ambiguous topics.
    """
    cfg = cfg or VoConfig()
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    pipeline = VoPipeline(cfg)
    converter = OdometryConverter()
    cameras = CameraModelCache()
    results_pose: list[tuple[float, np.ndarray, np.ndarray]] = []
    path_poses: collections.deque[tuple[int, np.ndarray, np.ndarray]] = collections.deque(maxlen=PATH_MAX_POSES)
    states: collections.Counter[str] = collections.Counter()
    models: collections.Counter[str] = collections.Counter()
    stage_times: dict[str, list[float]] = collections.defaultdict(list)
    rejected: collections.Counter[str] = collections.Counter()
    first_rejected: dict[str, int] = {}
    n_frames = n_pose = n_kf = 0
    path_length = 0.0
    last_pos: np.ndarray | None = None

    with _interrupts_at_frame_boundaries() as stop, \
            bagio.open_camera_bag(bag_path, image_topic, camera_info_topic) as bag, \
            (out / "frames.jsonl").open("w") as frames_f, (out / "trajectory.tum").open("w") as tum_f, \
            bagio.OutputBag(out / "output.mcap", overwrite=True) as obag:
        gt = _ground_truth(bag, gt_tum)
        if gt is not None:  # kept beside the estimate so that reports can be made from DIR alone
            bagio.write_tum(out / "groundtruth.tum", *gt[1])
        frames = bag.iter_frames()
        if progress:
            from tqdm import tqdm

            frames = tqdm(frames, total=bag.frame_count, unit="frame", desc="replay", leave=False)
        for frame in frames:
            if stop.requested:  # a signal arrived during the previous frame: all its outputs are written
                raise KeyboardInterrupt
            try:
                if frame.camera_info_msg is None:
                    raise BagError(f"no camera_info on {bag.camera_info_topic}")
                gray = decode_frame(frame.image_msg, bag.image_is_compressed)
                camera = cameras.get(frame.camera_info_msg)
                result = pipeline.process(gray, camera, frame.stamp_ns)
            except EpiVoError as exc:
                # Bad input in one frame: the frame is recorded with the reason and replay goes on.
                result = pipeline.reject(frame.stamp_ns, str(exc))
                rejected[str(exc)] += 1
                first_rejected.setdefault(str(exc), frame.index)
            n_frames += 1
            states[result.state.value] += 1
            models[result.model.value] += 1
            n_kf += int(result.is_keyframe)
            for k, v in result.timings_ms.items():
                stage_times[k].append(v)
            frames_f.write(json.dumps(result.to_record()) + "\n")
            frames_f.flush()
            if result.has_pose:
                n_pose += 1
                p, q = result.position, result.quat_xyzw
                stamp_s = result.stamp_ns * 1e-9
                tum_f.write(f"{stamp_s:.9f} " + " ".join(f"{v:.9f}" for v in (*p, *q)) + "\n")
                results_pose.append((stamp_s, p.copy(), q.copy()))
                if last_pos is not None:
                    path_length += float(np.linalg.norm(p - last_pos))
                last_pos = p.copy()
            if not result.skipped:  # a duplicate stamp gets its record and status, but no second pose
                _write_outputs(obag, converter, result, path_poses)
            else:
                obag.write_diagnostics(result.stamp_ns, [frame_status(result, "epi_vo", "replay")])
            if on_result is not None:
                on_result(result)

    if n_frames == 0:
        raise BagError(f"bag {bag_path} has no image messages on {bag.image_topic}")
    if n_frames != bag.frame_count:
        # rosbags skips a damaged record silently; the bag's summary still counts it.
        missing = f"the bag announces {bag.frame_count} images on {bag.image_topic}, {n_frames} could be read " \
                  "(damaged records?)"
        rejected[missing] += abs(bag.frame_count - n_frames)
        first_rejected.setdefault(missing, n_frames)
    metrics, gt_source, notes = None, "", []
    if gt is not None:
        gt_source = gt[0]
        try:
            m = _evaluate(results_pose, gt[1])
            metrics = asdict(m)
        except EpiVoError as exc:
            notes.append(f"evaluation skipped: {exc}")
    totals = stage_times.get("total", [0.0])
    summary = ReplaySummary(
        bag=str(bag_path), image_topic=bag.image_topic, camera_info_topic=bag.camera_info_topic,
        frames=n_frames, frames_with_pose=n_pose, tracked_percent=100.0 * n_pose / n_frames, keyframes=n_kf,
        states=dict(states), models=dict(models), ms_per_frame=float(np.median(totals)),
        stage_ms={k: float(np.median(v)) for k, v in stage_times.items()}, path_length=path_length,
        metrics=metrics, gt_source=gt_source, output_dir=str(out), notes=notes, parameters=asdict(cfg),
        rejected=[f"{n} frame(s) from frame {first_rejected[r]}: {r}" for r, n in rejected.items()])
    (out / "stats.json").write_text(json.dumps(summary.to_json(), indent=2) + "\n")
    return summary


class _StopRequest:
    requested = False


@contextlib.contextmanager
def _interrupts_at_frame_boundaries() -> Iterator[_StopRequest]:
    """SIGINT / SIGTERM during a replay stop it between frames, never between a frame's writes.

    Each frame writes a record, a trajectory line and several bag messages; an interrupt raised in the
    middle would leave the outputs disagreeing about the last frame. Outside the main thread (where
    signals cannot be handled) nothing changes.
    """
    stop = _StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def request(signum: int, frame: object) -> None:
        stop.requested = True

    saved = {sig: signal.signal(sig, request) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


def _write_outputs(obag: bagio.OutputBag, converter: OdometryConverter, result: FrameResult,
                   path_poses: collections.deque[tuple[int, np.ndarray, np.ndarray]]) -> None:
    sample = converter.convert(result.stamp_ns, result.T_w_c, result.covariance, result.has_pose)
    obag.write_odometry(result.stamp_ns, ODOM_FRAME, BASE_FRAME, sample.position, sample.quat_xyzw,
                        sample.pose_covariance, sample.linear_velocity, sample.angular_velocity,
                        sample.twist_covariance)
    if result.points_w.shape[0]:
        # Points are in the pipeline frame w (first optical frame); publish them in odom.
        T = converter.T_base_cam
        pts_odom = result.points_w @ T[:3, :3].T + T[:3, 3]
        obag.write_points(result.stamp_ns, ODOM_FRAME, pts_odom)
    if result.has_pose:
        path_poses.append((result.stamp_ns, sample.position, sample.quat_xyzw))
        stamps = [s for s, _, _ in path_poses]
        obag.write_path(result.stamp_ns, ODOM_FRAME, stamps, np.array([p for _, p, _ in path_poses]),
                        np.array([q for _, _, q in path_poses]))
    obag.write_diagnostics(result.stamp_ns, [frame_status(result, "epi_vo", "replay")])


def _ground_truth(bag: bagio.CameraBag, gt_tum: str | Path | None
                  ) -> tuple[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
    if gt_tum is not None:
        return str(gt_tum), bagio.read_tum(gt_tum)
    gt = bag.read_ground_truth()
    if gt is None:
        return None
    return f"bag topic {bag.gt_topic}", (gt.stamps_ns * 1e-9, gt.positions, gt.quats_xyzw)


def _evaluate(poses: list[tuple[float, np.ndarray, np.ndarray]],
              gt: tuple[np.ndarray, np.ndarray, np.ndarray]) -> TrajectoryMetrics:
    stamps = np.array([s for s, _, _ in poses])
    pos = np.array([p for _, p, _ in poses]).reshape(-1, 3)
    quat = np.array([q for _, _, q in poses]).reshape(-1, 4)
    return evaluate_trajectory((stamps, pos, quat), gt)


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
        f"  path length   {s.path_length:.3f} (VO units)",
    ]
    if s.metrics is not None:
        m = s.metrics
        lines.append(f"  vs GT ({s.gt_source}): ATE {_f(m['ate_rmse'])} ({_f(m['ate_percent_of_path'])} % of path, "
                     f"Sim3)  RPE rot {_f(m['rpe_rot_deg_per_frame'])} deg/frame  trans-dir "
                     f"{_f(m['trans_direction_err_deg'])} deg  ({m['matched_poses']} poses)")
    lines.extend(f"  note: {n}" for n in s.notes)
    lines.extend(f"  rejected: {r}" for r in s.rejected)
    lines.append(f"  outputs       {s.output_dir}/{{trajectory.tum, frames.jsonl, output.mcap, stats.json}}")
    return "\n".join(lines)


def _f(x: float | None) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.4g}"

