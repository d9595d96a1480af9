"""A pose set from outside, read by field name (epi_vo.io.set_pose): the pose and covariance it carries, and
every refusal with its reason (frame, position, orientation, covariance)."""

from __future__ import annotations

import math
import re
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from epi_vo.io.set_pose import SetPoseError, check_covariance, identity_request, pose_request


def _msg(frame: str = "odom", xyz: tuple[float, float, float] = (1.0, 2.0, 0.0),
         quat_xyzw: tuple[float, ...] = (0.0, 0.0, math.sin(0.25), math.cos(0.25)), cov: Any = None) -> Any:
    cov = list(np.diag([0.01, 0.02, 0.03, 0.001, 0.002, 0.003]).ravel()) if cov is None else cov
    x, y, z = xyz
    qx, qy, qz, qw = quat_xyzw
    return SimpleNamespace(
        header=SimpleNamespace(frame_id=frame, stamp=SimpleNamespace(sec=12, nanosec=500)),
        pose=SimpleNamespace(pose=SimpleNamespace(position=SimpleNamespace(x=x, y=y, z=z),
                                                  orientation=SimpleNamespace(x=qx, y=qy, z=qz, w=qw)),
                             covariance=cov))


def test_a_pose_message_is_base_in_odom_with_its_covariance() -> None:
    req = pose_request(_msg(), "odom")
    np.testing.assert_allclose(req.T_odom_base[:3, 3], [1.0, 2.0, 0.0])
    np.testing.assert_allclose(req.T_odom_base[:3, :3], [[math.cos(0.5), -math.sin(0.5), 0.0],
                                                         [math.sin(0.5), math.cos(0.5), 0.0], [0.0, 0.0, 1.0]],
                               atol=1e-12)
    np.testing.assert_allclose(np.diag(req.covariance), [0.01, 0.02, 0.03, 0.001, 0.002, 0.003])
    assert req.stamp_ns == 12_000_000_500 and req.source == "set_pose"
    rec = req.record()
    assert rec["position"] == [1.0, 2.0, 0.0] and rec["source"] == "set_pose"
    np.testing.assert_allclose(rec["quat_xyzw"], [0.0, 0.0, math.sin(0.25), math.cos(0.25)], atol=1e-12)
    # A quaternion within the printing tolerance of unit length is normalised.
    near = pose_request(_msg(quat_xyzw=(0.0, 0.0, 0.0, 1.0004)), "odom")
    np.testing.assert_allclose(near.T_odom_base[:3, :3], np.eye(3), atol=1e-12)


def test_reset_pose_is_the_origin_exactly() -> None:
    req = identity_request(7, "reset_pose")
    assert np.array_equal(req.T_odom_base, np.eye(4)) and not req.covariance.any() and req.source == "reset_pose"


@pytest.mark.parametrize(("kwargs", "reason"), [
    ({"frame": "map"}, "header.frame_id 'map' is not the odometry frame 'odom'"),
    ({"frame": ""}, "header.frame_id '' is not the odometry frame 'odom'"),
    ({"xyz": (1.0, math.nan, 0.0)}, "position [1.0, nan, 0.0] is not finite"),
    ({"xyz": (math.inf, 0.0, 0.0)}, "position [inf, 0.0, 0.0] is not finite"),
    ({"quat_xyzw": (0.0, 0.0, 0.0, 0.0)},
     "orientation quaternion (x y z w) [0.0, 0.0, 0.0, 0.0] has norm 0, not 1: it is no rotation"),
    ({"quat_xyzw": (0.0, 0.0, 0.0, 2.0)}, "orientation quaternion (x y z w) [0.0, 0.0, 0.0, 2.0] has norm 2, not 1"),
    ({"quat_xyzw": (0.0, 0.0, math.nan, 1.0)},
     "orientation quaternion (x y z w) [0.0, 0.0, nan, 1.0] has norm nan, not 1"),
    ({"cov": [0.0] * 35}, "covariance is not 36 numbers"),
    ({"cov": [math.nan] + [0.0] * 35}, "covariance has non-finite values"),
    ({"cov": [1.0, 0.5] + [0.0] * 34},
     "covariance is not symmetric (entries differ from their transposes by up to 0.5)"),
    ({"cov": list(np.diag([0.1, -0.2, 0.1, 0.1, 0.1, 0.1]).ravel())},
     "covariance has a negative variance (-0.2 on the diagonal at 1)"),
    ({"cov": [1.0, 2.0, 0, 0, 0, 0, 2.0, 1.0] + [0.0] * 28},
     "covariance is not positive semi-definite (an eigenvalue of -1)"),
])
def test_a_pose_that_cannot_be_set_is_refused_with_the_reason(kwargs: dict[str, Any], reason: str) -> None:
    with pytest.raises(SetPoseError, match="^" + re.escape(reason)):
        pose_request(_msg(**kwargs), "odom")


def test_a_covariance_is_made_exactly_symmetric() -> None:
    A = np.random.default_rng(3).normal(size=(6, 6))
    cov = A @ A.T
    cov[0, 1] += 1e-15  # rounding in a writer: not a different covariance
    out = check_covariance(cov.ravel())
    assert np.array_equal(out, out.T) and abs(out[0, 1] - cov[1, 0]) < 1e-14
