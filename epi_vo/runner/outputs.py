"""What a frame's result becomes on the way out, the same for both front doors: plain records (no rclpy, no
bag writer) that ``vo_node`` turns into messages and ``epi-vo replay`` writes into output.mcap.

:class:`OutputMaker` keeps what the outputs remember between frames: the odometry converter (the previous
pose for the twist, the windowed adjustment's corrections as map -> odom), the window of ``vo/path`` and
the position a robot may fuse. Every frame that is not skipped gives odometry, a path pose when it has one,
the points it triangulated, the TF transforms and its status; a skipped frame gives its status only.

**No VO units that can be fused by mistake.** ``vo/odometry`` (``frame_id`` -> ``child_frame_id``, odom ->
base_link) is what a filter may fuse, and TF odom -> base_link follows it. It never carries a length in VO
units with a confident covariance: once a metric scale source is established (``FrameResult.scale.metric``)
its position and linear velocity are metres; before that (``scale_source: none``, or metres not measured
yet) its position is held, at the last metric position or where tracking started, with the "unknown"
variance (``lost_position_variance``), and its linear velocity is zero with the "unknown" variance
(``UNKNOWN_TWIST_VARIANCE``), while its orientation and angular velocity, which no scale touches, are
published as estimated with their covariance. The motion in VO units goes on ``vo/odometry/vo_units``,
between frames that exist in no TF tree (``<frame_id>_vo_units`` -> ``<child_frame_id>_vo_units``), so no
filter can transform, hence fuse, it by accident; ``vo/path`` and ``vo/points`` are in the frame whose units
they carry (``frame_id`` in metres, ``<frame_id>_vo_units`` otherwise). When the units change (metres
established, or a new pipeline back in VO units) the twist is not differenced across the change, the path
starts afresh and map -> odom starts from the identity.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.decisions import Decision
from epi_vo.core.diagnostics import DiagnosticStatusRecord
from epi_vo.core.frame import FrameResult
from epi_vo.core.odometry import (
    UNKNOWN_TWIST_VARIANCE,
    OdometryConverter,
    OdometrySample,
    sample_status_pose,
)
from epi_vo.core.scale import Units
from epi_vo.core.status import frame_status
from epi_vo.core.transforms import quat_xyzw_from_rotation

F64 = NDArray[np.float64]

VO_UNITS_SUFFIX = "_vo_units"  # of the frames of vo/odometry/vo_units, which no TF tree has


@dataclass(frozen=True)
class OutputFrames:
    """The frame ids of the outputs (vo_node's ``frame_id``, ``child_frame_id``, ``map_frame_id``)."""

    frame_id: str = "odom"
    child_frame_id: str = "base_link"
    map_frame_id: str = ""  # '' the odometry carries the window's corrections; else map -> odom does

    def of(self, units: Units) -> tuple[str, str]:
        """The (frame, child frame) of a pose in ``units``: the fusable ones in metres, else their
        ``_vo_units`` names, which exist in no TF tree."""
        if units is Units.METRES:
            return self.frame_id, self.child_frame_id
        return self.frame_id + VO_UNITS_SUFFIX, self.child_frame_id + VO_UNITS_SUFFIX


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
    ``odometry`` carries it); ``odometry`` vo/odometry (fusable: metres or held, module doc),
    ``odometry_vo_units`` vo/odometry/vo_units (while the units are VO units); ``transforms`` the TF of a frame
    with a pose.
    """

    result: FrameResult
    record: dict[str, Any]
    status: DiagnosticStatusRecord
    odometry: OdometryRecord | None = None
    path: PathRecord | None = None
    points: PointsRecord | None = None
    transforms: tuple[TransformRecord, ...] = field(default=())
    odometry_vo_units: OdometryRecord | None = None

    @property
    def estimate(self) -> OdometryRecord | None:
        """The motion as estimated, in its own units: vo/odometry/vo_units while in VO units, else
        vo/odometry (what a covariance's consistency is judged on)."""
        return self.odometry_vo_units if self.odometry_vo_units is not None else self.odometry


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


def held(sample: OdometrySample, position: F64, position_variance: float) -> OdometrySample:
    """``sample`` with its position held at ``position`` (variance ``position_variance`` on each axis) and no
    linear velocity (zero, ``UNKNOWN_TWIST_VARIANCE``): what is left of a pose whose lengths are in no unit a
    robot knows. The orientation, the angular velocity and their covariances, which no scale touches, stay;
    their correlation with the lengths is dropped."""
    pose_cov = np.zeros((6, 6))
    pose_cov[:3, :3] = np.eye(3) * position_variance
    pose_cov[3:, 3:] = sample.pose_covariance[3:, 3:]
    twist_cov = np.zeros((6, 6))
    twist_cov[:3, :3] = np.eye(3) * UNKNOWN_TWIST_VARIANCE
    twist_cov[3:, 3:] = sample.twist_covariance[3:, 3:]
    return OdometrySample(sample.stamp_ns, np.array(position, dtype=np.float64), sample.quat_xyzw, pose_cov,
                          np.zeros(3), sample.angular_velocity, twist_cov)


class OutputMaker:
    """Turns each frame's result into its outputs (module doc). ``T_base_cam``: the camera mounting (camera
    optical frame -> base; None: the default, a level camera at base); ``unknown_position_variance``: the
    variance of a held position (``VoConfig.lost_position_variance``)."""

    def __init__(self, frames: OutputFrames | None = None, T_base_cam: F64 | None = None, *,
                 path_max_length: int = 1000, unknown_position_variance: float = 1.0e4) -> None:
        self.frames = frames or OutputFrames()
        self._converter = OdometryConverter(T_base_cam, continuous=bool(self.frames.map_frame_id))
        self._path = PathWindow(path_max_length)
        self.unknown_position_variance = unknown_position_variance
        self._units: Units | None = None  # of the last frame's pose
        self._held_position = np.zeros(3)  # where vo/odometry holds: the last metric position, or the start

    @property
    def T_base_cam(self) -> F64:
        """The camera mounting the odometry is made with (4x4, camera optical frame -> base)."""
        return self._converter.T_base_cam

    @property
    def T_map_odom(self) -> F64:
        """map -> odom: the windowed adjustment's corrections so far (identity without ``map_frame_id``)."""
        return self._converter.T_map_odom

    def set_mounting(self, T_base_cam: F64) -> None:
        """A new camera mounting (the extrinsic, once resolved, before the first frame's outputs)."""
        self._converter = OdometryConverter(T_base_cam, continuous=bool(self.frames.map_frame_id))

    def _fusable(self, sample: OdometrySample, units: Units) -> OdometrySample:
        """vo/odometry's content for ``sample`` (module doc)."""
        if units is Units.METRES:
            return sample
        return held(sample, self._held_position, self.unknown_position_variance)

    def outputs(self, result: FrameResult, status_name: str, hardware_id: str) -> FrameOutputs:
        """The outputs of one frame; ``status_name`` / ``hardware_id`` name its status (``<status_name>:
        tracking``)."""
        record = result.to_record()
        f = self.frames
        units = result.scale.units
        if result.skipped:  # its record and status, no pose: the converter does not see it
            T = self._converter.base_pose(result.T_w_c)
            sample = OdometrySample(result.stamp_ns, T[:3, 3].copy(), quat_xyzw_from_rotation(T[:3, :3]),
                                    self._converter.odom_covariance(result.covariance), np.zeros(3), np.zeros(3),
                                    np.eye(6) * UNKNOWN_TWIST_VARIANCE)
            pose = sample_status_pose(self._fusable(sample, units), f.frame_id, f.child_frame_id)
            return FrameOutputs(result, record, frame_status(result, status_name, hardware_id, pose, record))
        if self._units is not None and units is not self._units:
            # Other units from here on: nothing is differenced or composed across the change.
            self._converter = OdometryConverter(self._converter.T_base_cam, continuous=self._converter.continuous)
            self._path.clear()
        self._units = units
        if Decision.TIME_JUMPED_BACK in result.decisions:
            self._converter.reset_twist()  # no twist is differenced across the jump
        sample = self._converter.convert_result(result)  # in the pipeline's units
        if units is Units.METRES and result.has_pose:
            self._held_position = sample.position.copy()
        fusable = self._fusable(sample, units)
        status = frame_status(result, status_name, hardware_id,
                              sample_status_pose(fusable, f.frame_id, f.child_frame_id), record)
        odometry = OdometryRecord(f.frame_id, f.child_frame_id, fusable)
        vo_units = None if units is Units.METRES else OdometryRecord(*f.of(units), sample)
        frame = f.of(units)[0]
        path = points = None
        transforms: tuple[TransformRecord, ...] = ()
        if result.points_w.shape[0]:
            # The points are in the pipeline's frame w (the first optical frame); published in odom (its units).
            points = PointsRecord(frame, self._converter.odom_points(result.points_w))
        if result.has_pose:
            self._path.append(result.stamp_ns, sample.position, sample.quat_xyzw)
            path = PathRecord(frame, *self._path.window())
            transforms = (TransformRecord(f.frame_id, f.child_frame_id, fusable.position, fusable.quat_xyzw),)
            map_odom = sample.map_odom_xyz_quat()
            if map_odom is not None and units is Units.METRES:  # map_frame_id: the corrections (REP-105)
                transforms += (TransformRecord(f.map_frame_id, f.frame_id, *map_odom),)
        return FrameOutputs(result, record, status, odometry, path, points, transforms, vo_units)
