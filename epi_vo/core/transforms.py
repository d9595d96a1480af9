"""Rigid-body helpers: rotations, quaternions and 4x4 homogeneous transforms (numpy only).

Conventions used across epi_vo:

- ``R_a_b`` (3, 3) rotates vectors expressed in frame b into frame a; ``T_a_b`` (4, 4) maps
  homogeneous points from frame b into frame a: ``X_a = R_a_b @ X_b + t_a_b``.
- Quaternions are Hamilton, unit norm, stored ``quat_xyzw`` = (x, y, z, w) as in ROS
  ``geometry_msgs/Quaternion``. ``q`` and ``-q`` are the same rotation; functions returning a
  quaternion pick ``w >= 0``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from epi_vo.core.errors import EpiVoError

# A quaternion shorter than this cannot be normalised into a meaningful rotation.
_MIN_QUAT_NORM = 1e-12


def _as_finite(value: ArrayLike, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    """``value`` as a float64 array of ``shape``; EpiVoError naming ``name`` otherwise."""
    array = np.asarray(value, dtype=np.float64)
    if array.shape != shape:
        msg = f"{name} has shape {array.shape}, expected {shape}"
        raise EpiVoError(msg)
    if not np.all(np.isfinite(array)):
        msg = f"{name} contains non-finite values: {array.tolist()}"
        raise EpiVoError(msg)
    return array


def quat_xyzw_from_rotation(R_a_b: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w), ``w >= 0``, of the rotation matrix ``R_a_b`` (3, 3).

    Shepperd's method: build the quaternion from the largest of ``trace``, ``R00``, ``R11``,
    ``R22``, so the square root is always taken of a number >= 1 and the division never amplifies
    noise. This keeps 180-degree rotations (trace = -1, w = 0) exact, where the naive
    ``w = sqrt(1 + trace) / 2`` route divides by zero. Reference: Shepperd, "Quaternion from
    rotation matrix", J. Guidance and Control 1(3), 1978.

    ``R_a_b`` should be orthonormal; small deviations (accumulated rounding) are absorbed by the
    final normalisation. Raises EpiVoError for a wrong shape or non-finite entries.
    """
    R = _as_finite(R_a_b, (3, 3), "R_a_b")
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    pivot = int(np.argmax([trace, R[0, 0], R[1, 1], R[2, 2]]))
    if pivot == 0:
        s = 2.0 * np.sqrt(1.0 + trace)  # s = 4 w
        quat_xyzw = np.array(
            [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
        )
    elif pivot == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])  # s = 4 x
        quat_xyzw = np.array(
            [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
        )
    elif pivot == 2:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] + R[1, 1] - R[2, 2])  # s = 4 y
        quat_xyzw = np.array(
            [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
        )
    else:
        s = 2.0 * np.sqrt(1.0 - R[0, 0] - R[1, 1] + R[2, 2])  # s = 4 z
        quat_xyzw = np.array(
            [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
        )
    quat_xyzw /= np.linalg.norm(quat_xyzw)
    if quat_xyzw[3] < 0.0:
        quat_xyzw = -quat_xyzw
    return quat_xyzw


def rotation_from_quat_xyzw(quat_xyzw: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) of the quaternion (x, y, z, w); the quaternion is normalised first.

    Raises EpiVoError for a wrong shape, non-finite entries or a (near) zero-norm quaternion.
    """
    q = _as_finite(quat_xyzw, (4,), "quat_xyzw")
    norm = float(np.linalg.norm(q))
    if norm < _MIN_QUAT_NORM:
        msg = f"quat_xyzw {q.tolist()} has norm {norm:.3g}, cannot be normalised"
        raise EpiVoError(msg)
    x, y, z, w = q / norm
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
            [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
            [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
        ]
    )


def make_T(R_a_b: ArrayLike, t_a_b: ArrayLike) -> NDArray[np.float64]:
    """Homogeneous transform ``T_a_b`` (4, 4) from ``R_a_b`` (3, 3) and ``t_a_b`` (3,) or (3, 1).

    ``t_a_b`` is the origin of frame b expressed in frame a.
    """
    R = _as_finite(R_a_b, (3, 3), "R_a_b")
    t = _as_finite(np.asarray(t_a_b, dtype=np.float64).reshape(-1), (3,), "t_a_b")
    T_a_b = np.eye(4)
    T_a_b[:3, :3] = R
    T_a_b[:3, 3] = t
    return T_a_b


def invert_T(T_a_b: ArrayLike) -> NDArray[np.float64]:
    """``T_b_a`` (4, 4), the inverse of the rigid transform ``T_a_b``: ``R_b_a = R_a_b^T``,
    ``t_b_a = -R_a_b^T t_a_b`` (exact for a rigid transform, unlike a general matrix inverse)."""
    T = _as_finite(T_a_b, (4, 4), "T_a_b")
    R_b_a = T[:3, :3].T
    T_b_a = np.eye(4)
    T_b_a[:3, :3] = R_b_a
    T_b_a[:3, 3] = -R_b_a @ T[:3, 3]
    return T_b_a


def rotation_angle_deg(R_a_b: ArrayLike) -> float:
    """Angle in degrees, in [0, 180], of the rotation ``R_a_b`` (3, 3) about its axis.

    Uses ``atan2(|sin|, cos)`` with ``2 sin(angle) axis = vee(R - R^T)`` and
    ``2 cos(angle) = trace(R) - 1``: accurate for tiny angles, where ``arccos`` of a number near 1
    loses half the digits (that matters when thresholding the rotation between two frames).
    """
    R = _as_finite(R_a_b, (3, 3), "R_a_b")
    two_sin = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    two_cos = R[0, 0] + R[1, 1] + R[2, 2] - 1.0
    return float(np.degrees(np.arctan2(two_sin, two_cos)))
