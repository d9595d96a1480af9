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
