"""A pose set from outside: ``set_pose`` (geometry_msgs/PoseWithCovarianceStamped, as robot_localization
takes it) and ``reset_pose`` (to the identity), read by field name, checked, as one :class:`PoseRequest`.

The request says where base is in odom now: the node hands it to its frame handler, which applies it at the
next frame (``OdometryConverter.set_pose_next``). A message that cannot be that pose is refused with
:class:`SetPoseError`, whose message names what is wrong (the frame, a non-finite or non-unit orientation,
a covariance that is not finite, symmetric and positive semi-definite). No ROS import here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.errors import EpiVoError, clipped, quoted
from epi_vo.core.transforms import make_T, quat_xyzw_from_rotation, rotation_from_quat_xyzw
from epi_vo.io.msgconv import stamp_to_ns

F64 = NDArray[np.float64]

# A unit quaternion written with float32 arithmetic or 4-6 printed digits (a YAML file, `ros2 topic pub`) has a
# norm within 1e-3 of 1 and is normalised; one farther off is not a rotation someone meant (a default
# all-zero quaternion, a forgotten w) and is refused rather than guessed.
QUAT_NORM_TOLERANCE = 1.0e-3
# Symmetry and positive semi-definiteness of the covariance, relative to its largest entry: float64 values
# computed as A @ A.T and printed with their full precision meet this; a covariance whose negative direction
# is larger than this claims a negative variance.
COVARIANCE_REL_TOLERANCE = 1.0e-9


class SetPoseError(EpiVoError):
    """A pose message that cannot be set: the message names the problem."""


@dataclass(frozen=True)
class PoseRequest:
    """Base's pose in odom to set: ``T_odom_base`` (4x4), ``covariance`` (6x6 over x y z rot_x rot_y rot_z,
    odom), ``stamp_ns`` (the message's), ``source`` (the topic or service it came by)."""

    T_odom_base: F64
    covariance: F64
    stamp_ns: int
    source: str

    def record(self) -> dict[str, Any]:
        """The frame record's ``set_pose`` entry of the frame it was applied at."""
        return {"source": self.source, "position": [float(v) for v in self.T_odom_base[:3, 3]],
                "quat_xyzw": [float(v) for v in quat_xyzw_from_rotation(self.T_odom_base[:3, :3])],
                "covariance_diagonal": [float(v) for v in np.diag(self.covariance)]}


def identity_request(stamp_ns: int, source: str = "reset_pose") -> PoseRequest:
    """Base back at the origin of odom, exactly (zero covariance): where the odometry starts."""
    return PoseRequest(np.eye(4), np.zeros((6, 6)), stamp_ns, source)


def check_covariance(values: Any) -> F64:
    """The 36 values of a ROS pose covariance (row-major, position first) as a 6x6 matrix; SetPoseError
    unless it is finite, symmetric, with no negative variance and no negative direction."""
    try:
        cov = np.asarray(values, dtype=np.float64).reshape(6, 6)
    except (TypeError, ValueError) as exc:
        msg = f"covariance is not 36 numbers ({exc})"
        raise SetPoseError(msg) from None
    if not np.all(np.isfinite(cov)):
        msg = "covariance has non-finite values"
        raise SetPoseError(msg)
    tol = COVARIANCE_REL_TOLERANCE * max(float(np.max(np.abs(cov))), 1.0)
    asym = float(np.max(np.abs(cov - cov.T)))
    if asym > tol:
        msg = f"covariance is not symmetric (entries differ from their transposes by up to {asym:.3g})"
        raise SetPoseError(msg)
    if np.any(np.diag(cov) < 0.0):
        i = int(np.argmin(np.diag(cov)))
        msg = f"covariance has a negative variance ({cov[i, i]:.3g} on the diagonal at {i})"
        raise SetPoseError(msg)
    least = float(np.linalg.eigvalsh(0.5 * (cov + cov.T))[0])
    if least < -tol:
        msg = f"covariance is not positive semi-definite (an eigenvalue of {least:.3g})"
        raise SetPoseError(msg)
    return 0.5 * (cov + cov.T)


def pose_request(msg: Any, odom_frame: str, source: str = "set_pose") -> PoseRequest:
    """A geometry_msgs/PoseWithCovarianceStamped (by field name) as the pose of base in ``odom_frame``;
    SetPoseError naming the problem when it cannot be (module doc)."""
    frame = str(msg.header.frame_id)
    if frame != odom_frame:
        msg_ = (f"header.frame_id {quoted(clipped(frame))} is not the odometry frame {quoted(odom_frame)}: the pose "
                "set is base's in that frame")
        raise SetPoseError(msg_)
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    xyz = [float(p.x), float(p.y), float(p.z)]
    quat = [float(q.x), float(q.y), float(q.z), float(q.w)]
    if not all(math.isfinite(v) for v in xyz):
        msg_ = f"position {xyz} is not finite"
        raise SetPoseError(msg_)
    norm = math.sqrt(sum(v * v for v in quat)) if all(math.isfinite(v) for v in quat) else math.nan
    if not abs(norm - 1.0) <= QUAT_NORM_TOLERANCE:
        msg_ = f"orientation quaternion (x y z w) {quat} has norm {norm:.6g}, not 1: it is no rotation"
        raise SetPoseError(msg_)
    cov = check_covariance(msg.pose.covariance)
    try:
        stamp_ns = stamp_to_ns(msg.header.stamp)
    except EpiVoError:
        stamp_ns = 0  # the stamp says nothing the pose needs: it is set at the next frame whatever it says
    return PoseRequest(make_T(rotation_from_quat_xyzw(quat), xyz), cov, stamp_ns, source)
