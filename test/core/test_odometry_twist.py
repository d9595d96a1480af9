"""The published twist is the motion since the previous frame, also where the window moved the poses."""

from __future__ import annotations

import numpy as np
import pytest

from epi_vo.core.odometry import OdometryConverter
from epi_vo.core.transforms import make_T


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def test_a_correction_moves_the_previous_pose_so_the_twist_is_the_motion_not_the_jump() -> None:
    """Camera poses (pipeline frame, z forward, y down): 0.1 m forward and 2 deg of yaw per 0.1 s. At the
    third frame the window moves the poses by a correction (0.5 deg, 3 cm): the pose published there is
    the corrected one; its twist is still 1 m/s and 20 deg/s about the base's z axis."""
    step = make_T(_rot_y(2.0), np.array([0.0, 0.0, 0.1]))  # T_prev_cur
    C = make_T(_rot_y(0.5), np.array([0.03, 0.0, -0.01]))
    cov = np.eye(6) * 1e-6
    for corrected in (False, True):
        conv = OdometryConverter()
        T = np.eye(4)
        samples = []
        for i in range(3):
            T = T @ step if i else T
            last = i == 2
            samples.append(conv.convert(1_000_000_000 + i * 100_000_000, C @ T if last else T, cov, True,
                                        correction_w=C if (last and corrected) else None))
        s = samples[-1]
        w_deg = np.degrees(s.angular_velocity)
        if corrected:
            assert abs(np.linalg.norm(s.linear_velocity) - 1.0) < 1e-9
            # the camera's yaw (about its y, down) is the base's yaw about z, up: the opposite sign
            np.testing.assert_allclose(w_deg, [0.0, 0.0, -20.0], atol=1e-9)
            # the same step as the frame before, which had no correction
            np.testing.assert_allclose(s.linear_velocity, samples[1].linear_velocity, atol=1e-9)
            np.testing.assert_allclose(s.angular_velocity, samples[1].angular_velocity, atol=1e-9)
        else:  # without the correction the jump is in the twist: 5 deg/s and 0.3 m/s too much
            assert abs(w_deg[2] + 25.0) < 1e-6
            assert np.linalg.norm(s.linear_velocity - [1.0, 0.0, 0.0]) > 0.2


def test_a_correction_before_any_pose_is_ignored() -> None:
    conv = OdometryConverter()
    s = conv.convert(1_000, np.eye(4), np.eye(6) * 1e-6, True, correction_w=make_T(np.eye(3), np.ones(3)))
    assert np.all(s.linear_velocity == 0.0) and np.all(s.angular_velocity == 0.0)


def test_the_record_says_how_far_the_window_moved_the_poses() -> None:
    import dataclasses

    from epi_vo.core.pipeline import VoPipeline

    r = VoPipeline().reject(1_000, "camera_info missing")
    assert r.to_record()["window_correction"] is None and r.to_record()["window_correction_deg"] is None
    rec = dataclasses.replace(r, correction=make_T(_rot_y(0.5), np.array([0.03, 0.0, -0.04]))).to_record()
    assert abs(rec["window_correction"] - 0.05) < 1e-12 and abs(rec["window_correction_deg"] - 0.5) < 1e-9
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(AssertionError, match="correction"):
        dataclasses.replace(r, correction=bad)


def test_a_continuous_converter_keeps_the_pose_and_puts_the_corrections_into_map_to_odom() -> None:
    """REP-105 (the node's ``map_frame_id``): with two corrections along a path, the continuous converter's
    odometry pose moves only by each frame's motion (its step between frames equals the true step, also at
    the corrected frames), ``T_map_odom`` is the product of the corrections in the base frame (identity
    before the first), ``T_map_odom @ pose`` is the pipeline's corrected pose exactly as the jumping
    converter publishes it, the twist and the covariance's size are the same, and points follow odom."""
    from epi_vo.core.transforms import invert_T, rotation_angle_deg

    step = make_T(_rot_y(2.0), np.array([0.0, 0.0, 0.1]))
    C1 = make_T(_rot_y(0.5), np.array([0.03, 0.0, -0.01]))
    C2 = make_T(_rot_y(-0.3), np.array([-0.02, 0.01, 0.02]))
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    jumping, continuous = OdometryConverter(), OdometryConverter(continuous=True)
    T, moved = np.eye(4), np.eye(4)  # the pipeline's pose; the corrections so far
    outs = []
    for i in range(8):
        T = T @ step if i else T
        corr = C1 if i == 3 else C2 if i == 6 else None
        if corr is not None:
            moved = corr @ moved
        T_pub = moved @ T  # the pipeline publishes the corrected pose
        a = jumping.convert(1_000_000_000 + i * 100_000_000, T_pub, cov, True, correction_w=corr)
        b = continuous.convert(1_000_000_000 + i * 100_000_000, T_pub, cov, True, correction_w=corr)
        outs.append((a, b))
    base_step = jumping.base_pose(step)  # the true step as a base motion (T_base_cam @ step @ T_cam_base)

    def pose(s: object) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        return make_T(Rotation.from_quat(s.quat_xyzw).as_matrix(), s.position)  # type: ignore[attr-defined]

    for i, (a, b) in enumerate(outs):
        assert a.T_map_odom is None and b.T_map_odom is not None
        expect_moved = 0 if i < 3 else 1 if i < 6 else 2
        assert (rotation_angle_deg(b.T_map_odom[:3, :3]) > 0.1) == (expect_moved > 0)
        np.testing.assert_allclose(b.T_map_odom @ pose(b), pose(a), atol=1e-12)
        np.testing.assert_allclose(b.linear_velocity, a.linear_velocity, atol=1e-12)
        np.testing.assert_allclose(b.angular_velocity, a.angular_velocity, atol=1e-12)
        assert np.trace(b.pose_covariance) == pytest.approx(np.trace(a.pose_covariance), rel=1e-12)
        if i:
            np.testing.assert_allclose(invert_T(pose(outs[i - 1][1])) @ pose(b), base_step, atol=1e-12)
    # the jumping converter's pose jumps at the corrected frames
    jump = invert_T(pose(outs[2][0])) @ pose(outs[3][0])
    assert np.linalg.norm(jump[:3, 3] - base_step[:3, 3]) > 0.02
    np.testing.assert_allclose(continuous.T_map_odom, jumping.base_pose(C2 @ C1), atol=1e-12)
    pts_w = np.array([[0.0, 0.0, 5.0], [1.0, -0.5, 7.0]])
    odom_pts = continuous.odom_points(pts_w)
    map_pts = odom_pts @ continuous.T_map_odom[:3, :3].T + continuous.T_map_odom[:3, 3]
    np.testing.assert_allclose(map_pts, jumping.odom_points(pts_w), atol=1e-12)
