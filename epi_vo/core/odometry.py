"""From camera poses to what a robot stack consumes: odom -> base_link poses, twist, covariances.

Frames (REP-103 / REP-105):
- ``w``: the optical frame of the first camera pose (x right, y down, z forward); the pipeline's frame.
- ``odom``: the base frame at the first pose (x forward, y left, z up).
- ``T_base_cam``: the extrinsic, camera optical frame -> base frame (default: the usual optical-frame
  rotation, zero offset). Then ``T_odom_base = T_base_cam @ T_w_c @ inv(T_base_cam)``, since at the
  first frame ``T_w_c = I`` and base sits where it was.
Covariances are 6x6 over (x, y, z, rot_x, rot_y, rot_z), the ROS order. Numpy only; the node and the
replay both use this module so that the same bag gives the same odometry live and offline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.frame import FrameResult
from epi_vo.core.status import StatusPose
from epi_vo.core.transforms import invert_T, make_T, quat_xyzw_from_rotation

F64 = NDArray[np.float64]

# Optical frame (x right, y down, z forward) expressed in a body frame (x forward, y left, z up).
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

# Reported for twist when no motion estimate justifies it (finite, never 1e308: consumers square it).
UNKNOWN_TWIST_VARIANCE = 1.0e4


def default_T_base_cam() -> F64:
    return make_T(R_BASE_OPTICAL, np.zeros(3))


def T_base_cam_from_params(xyz: list[float] | tuple[float, ...], rpy: list[float] | tuple[float, ...]) -> F64:
    """Extrinsic from a translation and roll/pitch/yaw (rad, fixed axes X then Y then Z) of the camera
    *body* frame in base; the optical rotation is appended, as for a URDF ``camera_optical_frame``."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    R_base_body = np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])
    return make_T(R_base_body @ R_BASE_OPTICAL, np.asarray(xyz, dtype=np.float64))


def rotate_covariance(cov: F64, R: F64) -> F64:
    """Express a (position, rotation) covariance in a frame rotated by R (new = R @ old)."""
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    return A @ cov @ A.T


@dataclass(frozen=True)
class OdometrySample:
    """One odometry message's content (pose of base in odom, twist of base in base)."""

    stamp_ns: int
    position: F64
    quat_xyzw: F64
    pose_covariance: F64
    linear_velocity: F64
    angular_velocity: F64
    twist_covariance: F64
    # The map -> odom transform (REP-105) of a continuous converter: the product of every correction so far
    # (identity until one comes); None for a converter that moves the pose by them.
    T_map_odom: F64 | None = None

    def map_odom_xyz_quat(self) -> tuple[F64, F64] | None:
        """``T_map_odom`` as (translation, quaternion x y z w), the form a TF message carries; None without."""
        if self.T_map_odom is None:
            return None
        return self.T_map_odom[:3, 3].copy(), quat_xyzw_from_rotation(self.T_map_odom[:3, :3])


class OdometryConverter:
    """Turns successive camera poses T_w_c (with covariance) into odom -> base odometry samples.

    A frame may carry a correction (``FrameResult.correction``: the windowed adjustment moved the poses).
    ``continuous`` False: the odometry pose is the pipeline's, and jumps by the correction. True (REP-105,
    the node's ``map_frame_id``): the odometry pose moves only by the motion between frames, and the
    corrections gather in ``T_map_odom`` (map -> odom; the pipeline's corrected pose of base is
    ``T_map_odom @ T_odom_base``), which a node broadcasts as the map -> odom transform. The twist is the
    same either way."""

    def __init__(self, T_base_cam: F64 | None = None, *, continuous: bool = False) -> None:
        self.T_base_cam = default_T_base_cam() if T_base_cam is None else np.asarray(T_base_cam, np.float64)
        self._T_cam_base = invert_T(self.T_base_cam)
        self._prev: tuple[int, F64, F64] | None = None  # stamp, T_odom_base, pose covariance
        self.continuous = continuous
        self.T_map_odom = np.eye(4)
        self._T_odom_map = np.eye(4)

    def reset_twist(self) -> None:
        """Forget the previous pose (after a time jump) so no twist is differentiated across it."""
        self._prev = None

    def base_pose(self, T_w_c: F64) -> F64:
        """The pose of base in odom (``continuous``: with the corrections so far taken out)."""
        return self._T_odom_map @ self.T_base_cam @ T_w_c @ self._T_cam_base

    def odom_covariance(self, cov_w: F64) -> F64:
        """A pose covariance of the pipeline's frame, in odom."""
        return rotate_covariance(cov_w, self._T_odom_map[:3, :3] @ self.T_base_cam[:3, :3])

    def odom_points(self, points_w: F64) -> F64:
        """Points of the pipeline's frame (``FrameResult.points_w``, (N, 3)) in odom."""
        T = self._T_odom_map @ self.T_base_cam
        return points_w @ T[:3, :3].T + T[:3, 3]

    def convert(self, stamp_ns: int, T_w_c: F64, cov_w: F64, has_pose: bool,
                step_cov_w: F64 | None = None, correction_w: F64 | None = None) -> OdometrySample:
        """One odometry sample. ``step_cov_w`` (the frame's ``step_covariance``, odometry frame of the
        pipeline) is the covariance of the motion since the previous frame: the twist's covariance is
        it over dt^2, in the child frame. Without it, the pose covariance gained over the step is used.
        After a frame without a pose the twist is unknown (zero, ``UNKNOWN_TWIST_VARIANCE``).
        ``correction_w`` (the frame's ``correction``): the windowed adjustment moved the odometry frame's
        poses by it at this frame; the twist is the motion from the previous pose as moved, not the jump."""
        if correction_w is not None:
            C = self.T_base_cam @ np.asarray(correction_w, np.float64) @ self._T_cam_base
            if self.continuous:  # the published poses stay; map -> odom takes the correction
                self.T_map_odom = C @ self.T_map_odom
                self._T_odom_map = invert_T(self.T_map_odom)
            elif self._prev is not None:
                self._prev = (self._prev[0], C @ self._prev[1], self._prev[2])
        T_odom_base = self.base_pose(T_w_c)
        R_ob = T_odom_base[:3, :3]
        cov_odom = self.odom_covariance(cov_w)
        lin, ang = np.zeros(3), np.zeros(3)
        twist_cov = np.eye(6) * UNKNOWN_TWIST_VARIANCE
        if has_pose and self._prev is not None and stamp_ns > self._prev[0]:
            lin, ang, twist_cov = self._twist(stamp_ns, T_odom_base, cov_odom)
            dt = (stamp_ns - self._prev[0]) * 1e-9
            if step_cov_w is not None and np.all(np.isfinite(twist_cov)) and twist_cov[0, 0] < UNKNOWN_TWIST_VARIANCE:
                step_base = rotate_covariance(self.odom_covariance(step_cov_w), R_ob.T)
                step_twist = step_base / (dt * dt)
                if np.all(np.isfinite(step_twist)):
                    twist_cov = step_twist
        # No twist is differenced across a frame without a pose: what the camera did in between was not
        # measured (a blackout, a restart), and a difference over it claims a speed nothing saw.
        self._prev = (stamp_ns, T_odom_base, cov_odom) if has_pose else None
        return OdometrySample(stamp_ns, T_odom_base[:3, 3].copy(), quat_xyzw_from_rotation(R_ob), cov_odom, lin,
                              ang, twist_cov, self.T_map_odom.copy() if self.continuous else None)

    def convert_result(self, r: FrameResult) -> OdometrySample:
        """``convert`` of a pipeline result, with its step covariance and correction: what every front door
        publishes."""
        return self.convert(r.stamp_ns, r.T_w_c, r.covariance, r.has_pose, r.step_covariance, r.correction)

    def _twist(self, stamp_ns: int, T_odom_base: F64, cov_odom: F64) -> tuple[F64, F64, F64]:
        """Twist in the child frame by differencing with the previous pose; unknown when not finite."""
        assert self._prev is not None
        with np.errstate(all="ignore"):
            dt = (stamp_ns - self._prev[0]) * 1e-9
            T_prev = self._prev[1]
            T_prev_cur = invert_T(T_prev) @ T_odom_base  # motion expressed in the previous base frame
            lin = T_prev_cur[:3, 3] / dt
            ang = _log_so3(T_prev_cur[:3, :3]) / dt
            # Twist in the child (base) frame of the current pose.
            lin = T_prev_cur[:3, :3].T @ lin
            ang = T_prev_cur[:3, :3].T @ ang
            # Velocity variance from the pose variance gained over this step (first order): the
            # accumulated pose covariance grows by the relative motion's covariance each frame.
            step_var = np.maximum(np.diag(cov_odom) - np.diag(self._prev[2]), 1e-9)
            twist_cov = np.diag(step_var / (dt * dt))
            if not (np.all(np.isfinite(lin)) and np.all(np.isfinite(ang)) and np.all(np.isfinite(twist_cov))):
                # A step too short for the motion (nanoseconds apart): no usable velocity this frame.
                return np.zeros(3), np.zeros(3), np.eye(6) * UNKNOWN_TWIST_VARIANCE
        return lin, ang, twist_cov


def _log_so3(R: F64) -> F64:
    """Rotation vector (axis * angle) of R."""
    cos_a = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = math.acos(cos_a)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return 0.5 * w
    if math.pi - angle < 1e-6:
        # Near 180 deg: axis from the largest diagonal entry of (R + I) / 2.
        B = (R + np.eye(3)) / 2.0
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / math.sqrt(max(B[k, k], 1e-12))
        return axis * angle
    return w * (angle / (2.0 * math.sin(angle)))


def status_pose(converter: OdometryConverter, result: FrameResult, frame: str, child_frame: str) -> StatusPose:
    """The frame's pose as vo/odometry carries it (``child_frame`` in ``frame``, odom -> base_link), for
    its diagnostics status: one frame convention in the node, the replay and every tool."""
    T_odom_base = converter.base_pose(result.T_w_c)
    cov = converter.odom_covariance(result.covariance)
    return _status_pose(frame, child_frame, T_odom_base[:3, 3], quat_xyzw_from_rotation(T_odom_base[:3, :3]), cov)


def sample_status_pose(sample: OdometrySample, frame: str, child_frame: str) -> StatusPose:
    """``status_pose`` of the frame ``sample`` was converted from (``OdometryConverter.convert``): the same
    values, without converting the pose again."""
    return _status_pose(frame, child_frame, sample.position, sample.quat_xyzw, sample.pose_covariance)


def _status_pose(frame: str, child_frame: str, position: F64, quat_xyzw: F64, cov: F64) -> StatusPose:
    return StatusPose(frame, child_frame, tuple(float(v) for v in position),  # type: ignore[arg-type]
                      tuple(float(v) for v in quat_xyzw),  # type: ignore[arg-type]
                      tuple(float(v) for v in np.diag(cov)))
