"""The frame handler's odometry moved from outside between two frames (epi_vo.runner.frames): a camera
mounting that becomes known, or changes, while the robot drives, and a pose set (``set_pose``).

The ground_robot bag: a wheeled robot driving on a flat floor, its camera 0.45 m up and pitched 15 deg down
(bags/README.md). With the parameters' level camera the base seems to climb a 15 deg ramp; with the true
mounting it drives along its x on the floor.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from epi_vo.core.odometry import T_base_cam_from_params
from epi_vo.core.transforms import invert_T, make_T, rotation_angle_deg, rotation_from_quat_xyzw
from epi_vo.io import bagio
from epi_vo.runner.frames import FrameHandler, FrameInput, HandledFrame
from epi_vo.runner.outputs import OdometryRecord, OutputFrames

BAG = Path(__file__).resolve().parents[2] / "bags" / "ground_robot" / "bag"
N_FRAMES = 40
SWITCH_AT = 15  # the extrinsic arrives before this frame
PITCH = math.radians(15.0)
T_TRUE = T_base_cam_from_params([0.20, 0.0, 0.45], [0.0, PITCH, 0.0])
T_LEVEL = T_base_cam_from_params([0.20, 0.0, 0.45], [0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def inputs() -> list[FrameInput]:
    with bagio.open_camera_bag(BAG) as bag:
        frames = []
        for f in bag.iter_frames():
            frames.append(FrameInput(f.stamp_ns, f.image_msg, bag.image_is_compressed, f.camera_info_msg, f.problem))
            if len(frames) == N_FRAMES:
                return frames
    return frames


def _odometry(h: HandledFrame) -> OdometryRecord:
    """The motion: vo/odometry/vo_units while the units are VO units (vo/odometry holds its position then)."""
    odometry = h.outputs.odometry_vo_units or h.outputs.odometry
    assert odometry is not None
    return odometry


def _pose(h: HandledFrame) -> np.ndarray:
    s = _odometry(h).sample
    return make_T(rotation_from_quat_xyzw(s.quat_xyzw), s.position)


def _climb(handled: list[HandledFrame]) -> float:
    """The median of the twist's z over its x: how steeply the base seems to climb (tan of the slope)."""
    v = np.array([_odometry(h).sample.linear_velocity for h in handled])
    moving = np.abs(v[:, 0]) > 0.5 * np.median(np.abs(v[:, 0]))
    assert moving.sum() >= 0.8 * len(v)
    return float(np.median(v[moving, 2] / v[moving, 0]))


def test_an_extrinsic_that_arrives_late_is_switched_to_between_two_frames(inputs: list[FrameInput]) -> None:
    """The parameters' level camera for the first frames (the twist climbs at 15 deg), then TF's mounting
    pitched 15 deg down: from the next frame the twist is along base x on the floor, the odometry does not
    jump at the switch, and that frame's record says it."""
    handler = FrameHandler(frames=OutputFrames("odom", "base_link"), T_base_cam=T_LEVEL)
    before = [handler.handle(f) for f in inputs[:SWITCH_AT]]
    handler.set_mounting(T_TRUE, {"source": "tf", "detail": "arrived"})
    after = [handler.handle(f) for f in inputs[SWITCH_AT:]]
    assert all(h.result.has_pose for h in before[3:] + after)
    assert math.tan(PITCH) * 0.8 < _climb(before[3:]) < math.tan(PITCH) * 1.2
    assert abs(_climb(after[1:])) < 0.03  # within 1.7 deg of the floor
    # The first frame after the switch moved from the last one by one frame's motion, not by the change of
    # mounting (which would put base 0.45 m x sin(15 deg) / frame-motion away).
    step = invert_T(_pose(before[-1])) @ _pose(after[0])
    typical = np.linalg.norm((invert_T(_pose(before[-2])) @ _pose(before[-1]))[:3, 3])
    assert np.linalg.norm(step[:3, 3]) < 2.0 * typical and rotation_angle_deg(step[:3, :3]) < 2.0
    # Later motion is the camera's motion taken into base with the new mounting.
    rel_cam = invert_T(after[0].result.T_w_c) @ after[-1].result.T_w_c
    np.testing.assert_allclose(invert_T(_pose(after[0])) @ _pose(after[-1]),
                               T_TRUE @ rel_cam @ invert_T(T_TRUE), atol=1e-9)
    assert after[0].outputs.record["extrinsic"] == {"source": "tf", "detail": "arrived"}
    assert "extrinsic" in dict(after[0].outputs.status.values)
    assert not any("extrinsic" in h.outputs.record for h in before + after[1:])
    np.testing.assert_allclose(handler.output.T_base_cam, T_TRUE)


def test_a_moving_mounting_is_followed(inputs: list[FrameInput]) -> None:
    """A camera tilting on its mount frame by frame: the mounting given before each frame is the one the
    motion after it is taken into base with; the odometry stays continuous at every change."""
    handler = FrameHandler(frames=OutputFrames("odom", "base_link"), T_base_cam=T_TRUE)
    handled = [handler.handle(inputs[0])]
    mounts = [T_TRUE]
    for i, f in enumerate(inputs[1:20], start=1):
        mounts.append(T_base_cam_from_params([0.20, 0.0, 0.45], [0.0, PITCH + math.radians(0.5 * i), 0.0]))
        handler.set_mounting(mounts[-1])
        handled.append(handler.handle(f))
    for k in range(1, len(handled)):
        rel_cam = invert_T(handled[k - 1].result.T_w_c) @ handled[k].result.T_w_c
        M = mounts[k]
        np.testing.assert_allclose(invert_T(_pose(handled[k - 1])) @ _pose(handled[k]), M @ rel_cam @ invert_T(M),
                                   atol=1e-9)


def _cov(sigmas: list[float]) -> np.ndarray:
    return np.diag(np.square(sigmas))


def test_a_pose_set_is_the_next_frames_pose_and_later_motion_composes_from_it(inputs: list[FrameInput]) -> None:
    """set_pose between two frames: the next frame's odometry is the pose given, with the covariance given;
    the motion after it is the same as without the set pose (relative poses, twist); the covariance grows
    from the one given; the record of that frame (only) says it."""
    plain = FrameHandler(frames=OutputFrames("odom", "base_link"), T_base_cam=T_TRUE)
    ref = [plain.handle(f) for f in inputs[:30]]
    handler = FrameHandler(frames=OutputFrames("odom", "base_link"), T_base_cam=T_TRUE)
    got = [handler.handle(f) for f in inputs[:12]]
    T_set = make_T(rotation_from_quat_xyzw([0.0, 0.0, math.sin(0.6), math.cos(0.6)]), [5.0, -2.0, 0.1])
    cov_set = _cov([0.2, 0.2, 0.01, 0.01, 0.01, 0.05])
    handler.set_pose(T_set, cov_set, {"source": "set_pose"})
    got += [handler.handle(f) for f in inputs[12:30]]
    np.testing.assert_allclose(_pose(got[12]), T_set, atol=1e-9)
    np.testing.assert_allclose(_odometry(got[12]).sample.pose_covariance, cov_set, atol=1e-8)  # floored > 0
    for k in range(13, 30):
        np.testing.assert_allclose(invert_T(_pose(got[12])) @ _pose(got[k]), invert_T(_pose(ref[12])) @ _pose(ref[k]),
                                   atol=1e-9)
        np.testing.assert_allclose(_odometry(got[k]).sample.linear_velocity, _odometry(ref[k]).sample.linear_velocity,
                                   atol=1e-9)
        np.testing.assert_allclose(_odometry(got[k]).sample.angular_velocity,
                                   _odometry(ref[k]).sample.angular_velocity, atol=1e-9)
    # The twist across the set is the motion measured, not the jump to the pose given.
    np.testing.assert_allclose(_odometry(got[12]).sample.linear_velocity, _odometry(ref[12]).sample.linear_velocity,
                               atol=1e-9)
    diag = np.array([np.diag(_odometry(h).sample.pose_covariance) for h in got[12:]])
    assert np.all(diag >= np.diag(cov_set) - 1e-12) and np.all(diag[-1, :3] > diag[0, :3])
    # The set yaw's error moves base sideways by the lever arm of the distance driven since.
    dx = np.linalg.norm(_pose(got[-1])[:3, 3] - T_set[:3, 3])
    assert diag[-1, 0] + diag[-1, 1] - 0.08 >= 0.9 * cov_set[5, 5] * dx**2
    # Set with no rotation error, the growth is the motion's since the set: below the pipeline's own
    # covariance from the start (traces: the set yaw turns the along-track variance sideways).
    again = FrameHandler(frames=OutputFrames("odom", "base_link"), T_base_cam=T_TRUE)
    for f in inputs[:12]:
        again.handle(f)
    again.set_pose(T_set, _cov([0.2, 0.2, 0.01, 0.0, 0.0, 0.0]), {"source": "set_pose"})
    last = [again.handle(f) for f in inputs[12:30]][-1]
    grown = np.diag(_odometry(last).sample.pose_covariance) - np.square([0.2, 0.2, 0.01, 0.0, 0.0, 0.0])
    ref_diag = np.diag(_odometry(ref[29]).sample.pose_covariance)
    assert np.all(grown > 0.0)
    assert grown[:3].sum() < ref_diag[:3].sum() and grown[3:].sum() < ref_diag[3:].sum()
    assert got[12].outputs.record["set_pose"] == {"source": "set_pose"}
    assert [i for i, h in enumerate(got) if "set_pose" in h.outputs.record] == [12]


def test_without_metres_a_pose_set_is_where_vo_odometry_holds(inputs: list[FrameInput]) -> None:
    """scale_source none: vo/odometry holds its position with the 'unknown' variance; after set_pose it holds
    the position given (the orientation goes on as estimated), and vo/odometry/vo_units starts at the pose."""
    handler = FrameHandler(frames=OutputFrames("odom", "base_link"), T_base_cam=T_TRUE)
    before = [handler.handle(f) for f in inputs[:12]]
    assert before[-1].outputs.odometry is not None
    np.testing.assert_allclose(before[-1].outputs.odometry.sample.position, np.zeros(3))
    T_set = make_T(rotation_from_quat_xyzw([0.0, 0.0, math.sin(0.6), math.cos(0.6)]), [5.0, -2.0, 0.1])
    handler.set_pose(T_set, _cov([0.2, 0.2, 0.01, 0.01, 0.01, 0.05]), {"source": "set_pose"})
    after = [handler.handle(f) for f in inputs[12:20]]
    for h in after:
        held = h.outputs.odometry
        assert held is not None and h.outputs.odometry_vo_units is not None
        np.testing.assert_allclose(held.sample.position, T_set[:3, 3])
        assert np.all(np.diag(held.sample.pose_covariance)[:3] >= 1e3)  # the position is not known
    np.testing.assert_allclose(_pose(after[0]), T_set, atol=1e-9)
