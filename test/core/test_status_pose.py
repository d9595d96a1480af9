"""core/status.py: the frame status's pose convention (position_frame)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from epi_vo.core.frame import FrameResult
from epi_vo.core.odometry import OdometryConverter, sample_status_pose, status_pose
from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.status import CAMERA_POSITION_FRAME, StatusPose, frame_status
from epi_vo.core.transforms import make_T


def _result() -> FrameResult:
    """A held-pose result whose camera stands at (1, 2, 3) in the pipeline's (optical) world frame."""
    r = VoPipeline().reject(1_700_000_000_000_000_000, "camera_info missing")
    return dataclasses.replace(r, T_w_c=make_T(np.eye(3), [1.0, 2.0, 3.0]),
                               covariance=np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]))


def test_without_a_pose_the_record_pose_is_named_camera_frame() -> None:
    values = dict(frame_status(_result(), "/vo_node", "cam").values)
    assert values["position"] == "1 2 3"
    assert values["position_frame"] == CAMERA_POSITION_FRAME
    assert values["covariance_diagonal"] == "1 2 3 0.1 0.2 0.3"


def test_with_the_odometry_pose_every_pose_key_is_in_odom_base_link() -> None:
    """Known answer: optical (x right, y down, z forward) -> base (x forward, y left, z up): camera at
    optical (1, 2, 3) is base (3, -1, -2); the covariance diagonal is permuted the same way."""
    r = _result()
    conv = OdometryConverter()
    s = conv.convert(r.stamp_ns, r.T_w_c, r.covariance, True)
    np.testing.assert_allclose(s.position, [3.0, -1.0, -2.0], atol=1e-12)
    pose = StatusPose("odom", "base_link", tuple(s.position), tuple(s.quat_xyzw),  # type: ignore[arg-type]
                      tuple(np.diag(s.pose_covariance)))
    status = frame_status(r, "/robot1/vo_node", "camera_optical_frame", pose)
    values = dict(status.values)
    assert status.name == "/robot1/vo_node: tracking" and status.hardware_id == "camera_optical_frame"
    assert values["position"] == "3 -1 -2"
    assert values["quat_xyzw"] == "0 0 0 1"
    assert values["covariance_diagonal"] == "3 1 2 0.3 0.1 0.2"
    assert values["position_frame"] == "odom -> base_link"
    keys = [k for k, _ in status.values]
    assert keys[: len(r.to_record())] == list(r.to_record())  # the record's keys, in order, kept
    # The record the caller already made (replay writes it to frames.jsonl) gives the same status and
    # stays as it was.
    record = r.to_record()
    assert frame_status(r, "/robot1/vo_node", "camera_optical_frame", pose, record) == status
    assert record == r.to_record()


def test_the_status_pose_of_a_converted_sample_is_the_frames_status_pose() -> None:
    """Replay takes the status pose from the odometry sample it converted (``sample_status_pose``): the
    values ``status_pose`` computes from the frame, to the bit, for a rotated, uncertain pose."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    r = dataclasses.replace(_result(), T_w_c=make_T(cv2.Rodrigues(np.array([0.3, -0.2, 0.9]))[0],
                                                    [1.5, -2.0, 0.25]), covariance=A @ A.T)
    conv = OdometryConverter()
    s = conv.convert(r.stamp_ns, r.T_w_c, r.covariance, True)
    assert sample_status_pose(s, "odom", "base_link") == status_pose(conv, r, "odom", "base_link")
