"""What a frame's result becomes on the way out, the same for both front doors: plain records (no rclpy, no
bag writer) that ``vo_node`` turns into messages and ``epi-vo replay`` writes into output.mcap.

:class:`OutputMaker` keeps what the outputs remember between frames: the odometry converter (the previous
pose for the twist, the windowed adjustment's corrections as map -> odom) and the window of ``vo/path``.
Every frame that is not skipped gives odometry, a path pose when it has one, the points it triangulated,
the TF transforms and its status; a skipped frame gives its status only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.decisions import Decision
from epi_vo.core.diagnostics import DiagnosticStatusRecord
from epi_vo.core.frame import FrameResult
from epi_vo.core.odometry import OdometryConverter, OdometrySample, sample_status_pose, status_pose
from epi_vo.core.status import frame_status

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class OutputFrames:
    """The frame ids of the outputs (vo_node's ``frame_id``, ``child_frame_id``, ``map_frame_id``)."""

    frame_id: str = "odom"
    child_frame_id: str = "base_link"
    map_frame_id: str = ""  # '' the odometry carries the window's corrections; else map -> odom does


@dataclass(frozen=True)
class OdometryRecord:
    """One nav_msgs/Odometry: ``sample`` (pose of ``child_frame_id`` in ``frame_id``, twist in the child)."""

    frame_id: str
    child_frame_id: str
    sample: OdometrySample


@dataclass(frozen=True)
class PathRecord:
    """One nav_msgs/Path in ``frame_id``: the last poses, ``stamps_ns`` (M,), ``positions`` (M, 3),
    ``quats_xyzw`` (M, 4) (views into the window: valid until the next frame)."""

    frame_id: str
    stamps_ns: NDArray[np.int64]
    positions: F64
    quats_xyzw: F64


@dataclass(frozen=True)
class PointsRecord:
    """One sensor_msgs/PointCloud2: ``points_xyz`` (N, 3) in ``frame_id``."""

    frame_id: str
    points_xyz: F64


@dataclass(frozen=True)
class TransformRecord:
    """One geometry_msgs/TransformStamped: ``child`` in ``parent``, ``xyz`` (3,) and ``quat_xyzw`` (4,)."""

    parent: str
    child: str
    xyz: F64
    quat_xyzw: F64


@dataclass(frozen=True)
class FrameOutputs:
    """Everything one frame publishes (None / empty: nothing of that kind this frame).

    ``record`` is the frame record (``FrameResult.to_record``), ``status`` its diagnostics status (pose as
    ``odometry`` carries it); ``transforms`` the TF of a frame with a pose.
    """

    result: FrameResult
    record: dict[str, Any]
    status: DiagnosticStatusRecord
    odometry: OdometryRecord | None = None
    path: PathRecord | None = None
    points: PointsRecord | None = None
    transforms: tuple[TransformRecord, ...] = field(default=())


class PathWindow:
    """The last ``size`` poses of vo/path (stamp, position, quat_xyzw) as contiguous arrays without a copy per
    frame: rows are appended into a buffer twice the window, shifted back to the start when it is full."""

    def __init__(self, size: int) -> None:
        self._size = size
        self._stamps = np.zeros(2 * size, dtype=np.int64)
        self._poses = np.zeros((2 * size, 7))  # x y z, qx qy qz qw
        self._end = 0

    def __len__(self) -> int:
        return min(self._end, self._size)

    def clear(self) -> None:
        self._end = 0

    def append(self, stamp_ns: int, position: F64, quat_xyzw: F64) -> None:
        if self._end == len(self._stamps):
            keep = self._size - 1
            self._stamps[:keep] = self._stamps[self._end - keep:self._end]
            self._poses[:keep] = self._poses[self._end - keep:self._end]
            self._end = keep
        self._stamps[self._end] = stamp_ns
        self._poses[self._end, :3] = position
        self._poses[self._end, 3:] = quat_xyzw
        self._end += 1

    def window(self) -> tuple[NDArray[np.int64], F64, F64]:
        """stamps_ns (M,), positions (M, 3), quats_xyzw (M, 4) of the last M <= size poses (views)."""
        start = max(self._end - self._size, 0)
        poses = self._poses[start:self._end]
        return self._stamps[start:self._end], poses[:, :3], poses[:, 3:]


class OutputMaker:
    """Turns each frame's result into its outputs (module doc). ``T_base_cam``: the camera mounting (camera
    optical frame -> base; None: the default, a level camera at base)."""

    def __init__(self, frames: OutputFrames | None = None, T_base_cam: F64 | None = None, *,
                 path_max_length: int = 1000) -> None:
        self.frames = frames or OutputFrames()
        self._converter = OdometryConverter(T_base_cam, continuous=bool(self.frames.map_frame_id))
        self._path = PathWindow(path_max_length)
        self._pose_note: dict[str, Any] | None = None  # the record entry of a pose set, until it is applied

    @property
    def T_base_cam(self) -> F64:
        """The camera mounting the odometry is made with (4x4, camera optical frame -> base)."""
        return self._converter.T_base_cam

    @property
    def T_map_odom(self) -> F64:
        """map -> odom: the windowed adjustment's corrections so far (identity without ``map_frame_id``)."""
        return self._converter.T_map_odom

    def set_mounting(self, T_base_cam: F64, T_w_c: F64 | None = None) -> None:
        """A new camera mounting: before the first frame's outputs (``T_w_c`` None), or while the odometry
        runs, at the pose ``T_w_c`` last output, where base stays (``OdometryConverter.set_mounting``)."""
        if T_w_c is None:
            self._converter = OdometryConverter(T_base_cam, continuous=bool(self.frames.map_frame_id))
        else:
            self._converter.set_mounting(T_base_cam, T_w_c)

    def set_pose(self, T_odom_base: F64, covariance: F64, note: dict[str, Any]) -> None:
        """Base's pose in odom becomes ``T_odom_base`` (``covariance``: 6x6 in odom) at the next frame that is
        not skipped, whose record says ``note`` under ``set_pose``."""
        self._converter.set_pose_next(T_odom_base, covariance)
        self._pose_note = note

    def outputs(self, result: FrameResult, status_name: str, hardware_id: str,
                notes: dict[str, Any] | None = None) -> FrameOutputs:
        """The outputs of one frame; ``status_name`` / ``hardware_id`` name its status (``<status_name>:
        tracking``); ``notes``: entries added to its record (what the runner did at this frame boundary)."""
        record = result.to_record()
        record.update(notes or {})
        f = self.frames
        if result.skipped:  # its record and status, no pose: the converter does not see it
            pose = status_pose(self._converter, result, f.frame_id, f.child_frame_id)
            return FrameOutputs(result, record, frame_status(result, status_name, hardware_id, pose, record))
        if Decision.TIME_JUMPED_BACK in result.decisions:
            self._converter.reset_twist()  # no twist is differenced across the jump
        sample = self._converter.convert_result(result)
        if self._pose_note is not None:  # the pose set is in this frame's sample
            record["set_pose"], self._pose_note = self._pose_note, None
        status = frame_status(result, status_name, hardware_id,
                              sample_status_pose(sample, f.frame_id, f.child_frame_id), record)
        odometry = OdometryRecord(f.frame_id, f.child_frame_id, sample)
        path = points = None
        transforms: tuple[TransformRecord, ...] = ()
        if result.points_w.shape[0]:
            # The points are in the pipeline's frame w (the first optical frame); published in odom.
            points = PointsRecord(f.frame_id, self._converter.odom_points(result.points_w))
        if result.has_pose:
            self._path.append(result.stamp_ns, sample.position, sample.quat_xyzw)
            path = PathRecord(f.frame_id, *self._path.window())
            transforms = (TransformRecord(f.frame_id, f.child_frame_id, sample.position, sample.quat_xyzw),)
            if (map_odom := sample.map_odom_xyz_quat()) is not None:  # map_frame_id: the corrections (REP-105)
                transforms += (TransformRecord(f.map_frame_id, f.frame_id, *map_odom),)
        return FrameOutputs(result, record, status, odometry, path, points, transforms)
