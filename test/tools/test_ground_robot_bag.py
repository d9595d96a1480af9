"""The bundled ``ground_robot`` bag: a wheeled robot's camera over a paved floor, with 50 Hz wheel odometry.

Read back with rosbags only (no ROS) and checked against what bags/README.md documents: the camera
mounting on base_link, the stamps and rates, and the wheel odometry error model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

REPO = Path(__file__).resolve().parents[2]
ROOT = REPO / "bags" / "ground_robot"
BAG = ROOT / "bag"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

IMAGE_TOPIC = "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
GROUND_TRUTH_TOPIC = "/ground_truth/pose"
WHEEL_TOPIC = "/wheel/odom"

# The mounting as documented in bags/README.md: camera optical frame in base_link.
CAMERA_XYZ = (0.20, 0.0, 0.45)
CAMERA_HEIGHT_M = 0.45
CAMERA_PITCH_DEG = 15.0
# The wheel odometry error model as documented.
SCALE_ERROR = 0.025
YAW_RATE_BIAS_DEG_S = 0.5


def _rot_y(a: float) -> NDArray[np.float64]:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _se3(R: NDArray[np.float64], t: tuple[float, ...] | NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# optical (x right, y down, z forward) in body (x forward, y left, z up), then the 15 deg pitch down
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BASE_CAMERA = _se3(_rot_y(math.radians(CAMERA_PITCH_DEG)) @ R_BODY_OPTICAL, CAMERA_XYZ)
T_CAMERA_BASE = np.linalg.inv(T_BASE_CAMERA)


def _quat_to_matrix(x: float, y: float, z: float, w: float) -> NDArray[np.float64]:
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@dataclass
class GroundRobotBag:
    image_stamps: list[int]
    image_formats: set[str]
    first_jpeg: bytes
    info_stamps: list[int]
    infos: list[object]
    gt_stamps: list[int]
    gt_frames: set[str]
    T_c0_ci: NDArray[np.float64]  # (N, 4, 4)
    wheel_stamps: NDArray[np.int64]  # (K,)
    wheel_frames: set[tuple[str, str]]
    wheel_pose: NDArray[np.float64]  # (K, 7) x y z qx qy qz qw
    wheel_twist: NDArray[np.float64]  # (K, 6) linear xyz, angular xyz
    wheel_pose_cov: NDArray[np.float64]  # (K, 36)
    wheel_twist_cov: NDArray[np.float64]  # (K, 36)
    record_equals_header: bool
    record_times: list[int]
    msgtypes: dict[str, str]


def _stamp(header: object) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


@pytest.fixture(scope="module")
def bag() -> GroundRobotBag:
    if not BAG.is_dir():
        pytest.fail(f"{BAG} is missing: regenerate it with .venv/bin/python bags/make_bags.py --only ground_robot")
    image_stamps, info_stamps, gt_stamps, infos, poses = [], [], [], [], []
    formats, gt_frames, wheel_frames = set(), set(), set()
    wheel_stamps, wheel_pose, wheel_twist, pose_cov, twist_cov = [], [], [], [], []
    first_jpeg, record_equals_header, record_times = b"", True, []
    with AnyReader([BAG], default_typestore=TYPESTORE) as reader:
        msgtypes = {c.topic: c.msgtype for c in reader.connections}
        for con, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, con.msgtype)
            stamp = _stamp(msg.header)
            record_equals_header &= stamp == timestamp
            record_times.append(timestamp)
            if con.topic == IMAGE_TOPIC:
                image_stamps.append(stamp)
                formats.add(msg.format)
                first_jpeg = first_jpeg or bytes(msg.data)
            elif con.topic == CAMERA_INFO_TOPIC:
                info_stamps.append(stamp)
                infos.append(msg)
            elif con.topic == GROUND_TRUTH_TOPIC:
                gt_stamps.append(stamp)
                gt_frames.add(msg.header.frame_id)
                p, q = msg.pose.position, msg.pose.orientation
                poses.append(_se3(_quat_to_matrix(q.x, q.y, q.z, q.w), (p.x, p.y, p.z)))
            elif con.topic == WHEEL_TOPIC:
                wheel_stamps.append(stamp)
                wheel_frames.add((msg.header.frame_id, msg.child_frame_id))
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                wheel_pose.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
                lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
                wheel_twist.append((lin.x, lin.y, lin.z, ang.x, ang.y, ang.z))
                pose_cov.append(np.asarray(msg.pose.covariance, dtype=np.float64))
                twist_cov.append(np.asarray(msg.twist.covariance, dtype=np.float64))
    return GroundRobotBag(
        image_stamps, formats, first_jpeg, info_stamps, infos, gt_stamps, gt_frames, np.array(poses),
        np.array(wheel_stamps, dtype=np.int64), wheel_frames, np.array(wheel_pose), np.array(wheel_twist),
        np.array(pose_cov), np.array(twist_cov), record_equals_header, record_times, msgtypes,
    )


def _base_poses_from_ground_truth(T_c0_ci: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_b0_bi`` (N, 4, 4): the base_link poses relative to the first one, via the documented mounting."""
    return np.array([T_BASE_CAMERA @ T @ T_CAMERA_BASE for T in T_c0_ci])


def _yaw(R: NDArray[np.float64]) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def _wheel_at(bag: GroundRobotBag, stamps: list[int]) -> NDArray[np.float64]:
    """Wheel odometry x, y, unwrapped yaw (N, 3) linearly interpolated at ``stamps``."""
    yaw = np.unwrap([_yaw(_quat_to_matrix(*q)) for q in bag.wheel_pose[:, 3:]])
    t = (bag.wheel_stamps - bag.wheel_stamps[0]).astype(np.float64)
    ts = (np.asarray(stamps) - bag.wheel_stamps[0]).astype(np.float64)
    return np.column_stack([np.interp(ts, t, bag.wheel_pose[:, 0]), np.interp(ts, t, bag.wheel_pose[:, 1]),
                            np.interp(ts, t, yaw)])


def _relative_to_first(xy_yaw: NDArray[np.float64]) -> NDArray[np.float64]:
    """Planar poses (N, 3) expressed in the frame of the first one."""
    x0, y0, yaw0 = xy_yaw[0]
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = xy_yaw[:, 0] - x0, xy_yaw[:, 1] - y0
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, xy_yaw[:, 2] - yaw0])


def _path_length(xy: NDArray[np.float64]) -> float:
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())


# --- images, calibration, ground truth ------------------------------------------------------------------


def test_topics_and_types(bag: GroundRobotBag) -> None:
    assert bag.msgtypes == {
        IMAGE_TOPIC: "sensor_msgs/msg/CompressedImage",
        CAMERA_INFO_TOPIC: "sensor_msgs/msg/CameraInfo",
        GROUND_TRUTH_TOPIC: "geometry_msgs/msg/PoseStamped",
        WHEEL_TOPIC: "nav_msgs/msg/Odometry",
    }
    assert bag.record_equals_header, "bag record time must equal the header stamp"
    assert bag.record_times == sorted(bag.record_times)


def test_frames_at_15_hz_each_with_camera_info_and_ground_truth(bag: GroundRobotBag) -> None:
    n = len(bag.image_stamps)
    assert n >= 270
    assert bag.image_stamps == sorted(set(bag.image_stamps))
    assert bag.info_stamps == bag.image_stamps
    assert bag.gt_stamps == bag.image_stamps
    assert np.allclose(np.diff(bag.image_stamps), 1e9 / 15, atol=1)
    assert bag.image_formats == {"jpeg"}
    image = cv2.imdecode(np.frombuffer(bag.first_jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (480, 640)
    assert bag.gt_frames == {"world"}


def test_camera_info_is_the_documented_pinhole(bag: GroundRobotBag) -> None:
    K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    for info in bag.infos:
        assert (info.width, info.height) == (640, 480)
        assert info.distortion_model == "plumb_bob"
        assert np.array_equal(np.asarray(info.k).reshape(3, 3), K)
        assert not np.any(np.asarray(info.d))


def test_ground_truth_starts_at_identity_and_is_finite(bag: GroundRobotBag) -> None:
    assert np.all(np.isfinite(bag.T_c0_ci))
    assert np.allclose(bag.T_c0_ci[0], np.eye(4), atol=1e-12)


def test_camera_stays_0_45_m_above_the_floor_pitched_15_deg_down(bag: GroundRobotBag) -> None:
    """With the documented mounting, the ground truth puts every base pose on the floor plane of the first,
    level, and the camera 0.45 m above it looking 15 deg down (no roll)."""
    T_b0_bi = _base_poses_from_ground_truth(bag.T_c0_ci)
    assert np.abs(T_b0_bi[:, 2, 3]).max() < 1e-6  # base origin on the floor
    assert np.abs(T_b0_bi[:, 2, 2] - 1.0).max() < 1e-9  # base z stays vertical: no roll, no pitch
    T_b0_ci = T_b0_bi @ T_BASE_CAMERA
    heights = T_b0_ci[:, 2, 3]
    assert np.abs(heights - CAMERA_HEIGHT_M).max() < 1e-6
    optical_axis = T_b0_ci[:, :3, 2]
    pitch_down = np.degrees(np.arcsin(-optical_axis[:, 2]))
    assert np.abs(pitch_down - CAMERA_PITCH_DEG).max() < 1e-6
    camera_x = T_b0_ci[:, :3, 0]  # optical x (image right) stays horizontal: no roll
    assert np.abs(camera_x[:, 2]).max() < 1e-9


def test_motion_is_a_ground_robot_at_walking_pace(bag: GroundRobotBag) -> None:
    base = _base_poses_from_ground_truth(bag.T_c0_ci)
    xy = base[:, :2, 3]
    dt = np.diff(bag.image_stamps) / 1e9
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / dt
    yaw = np.unwrap([_yaw(T[:3, :3]) for T in base])
    yaw_rate = np.degrees(np.diff(yaw)) / dt
    assert _path_length(xy) >= 10.0
    assert 0.39 <= speed.min() and speed.max() <= 0.71
    assert np.abs(yaw_rate).max() <= 26.0
    assert yaw_rate.max() > 10.0 and yaw_rate.min() < -10.0  # turns left and right
    assert np.abs(np.diff(speed)).max() / dt.mean() < 1.0  # smooth: below 1 m/s^2


def test_groundtruth_tum_file_matches_the_topic(bag: GroundRobotBag) -> None:
    rows = [line.split() for line in (ROOT / "groundtruth_tum.txt").read_text().splitlines()
            if not line.startswith("#")]
    assert len(rows) == len(bag.image_stamps)
    stamps = [round(float(r[0]) * 1e9) for r in rows]
    assert np.abs(np.array(stamps) - np.array(bag.image_stamps)).max() <= 1000  # float seconds
    t = np.array([[float(v) for v in r[1:4]] for r in rows])
    assert np.allclose(t, bag.T_c0_ci[:, :3, 3], atol=2e-9)


# --- wheel odometry -----------------------------------------------------------------------------------------


def test_wheel_stamps_50_hz_increasing_and_spanning_the_images(bag: GroundRobotBag) -> None:
    stamps = bag.wheel_stamps
    assert bag.wheel_frames == {("odom", "base_link")}
    assert np.all(np.diff(stamps) > 0)
    assert np.allclose(np.diff(stamps), 20_000_000, atol=1)
    rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)
    assert rate == pytest.approx(50.0, rel=1e-6)
    assert stamps[0] < bag.image_stamps[0] and stamps[-1] > bag.image_stamps[-1]
    assert not set(stamps.tolist()) & set(bag.image_stamps)  # not aligned with the images
    offsets = (stamps[:, None] - np.array(bag.image_stamps)[None, ::3]) % 20_000_000  # images every 200 ms
    assert np.all(offsets == 7_000_000)


def test_wheel_values_are_finite_planar_and_plausible(bag: GroundRobotBag) -> None:
    for array in (bag.wheel_pose, bag.wheel_twist, bag.wheel_pose_cov, bag.wheel_twist_cov):
        assert np.all(np.isfinite(array))
    assert np.array_equal(bag.wheel_pose[0], [0, 0, 0, 0, 0, 0, 1])  # odom = base_link at the first message
    assert not np.any(bag.wheel_pose[:, 2])  # z
    assert not np.any(bag.wheel_pose[:, 3:5])  # qx, qy: yaw only
    assert np.allclose(np.linalg.norm(bag.wheel_pose[:, 3:], axis=1), 1.0, atol=1e-12)
    assert not np.any(bag.wheel_twist[:, [1, 2, 3, 4]])  # twist in base_link: forward speed and yaw rate only
    assert 0.35 < bag.wheel_twist[:, 0].min() and bag.wheel_twist[:, 0].max() < 0.75
    for cov in (bag.wheel_pose_cov, bag.wheel_twist_cov):
        diagonal = cov[:, np.arange(6) * 7]
        assert np.all(diagonal > 0.0)
        off_diagonal = cov.copy()
        off_diagonal[:, np.arange(6) * 7] = 0.0
        assert not np.any(off_diagonal)
    xy_var = bag.wheel_pose_cov[:, 0]
    assert np.all(np.diff(xy_var) >= 0.0)  # the position uncertainty grows with the distance


def test_wheel_distance_error_matches_the_scale_error(bag: GroundRobotBag) -> None:
    """Over the image span, the wheel odometry travels +1..+5 % more than the ground truth (the model says
    +2.5 % plus 1 % noise per 20 ms step)."""
    wheel = _wheel_at(bag, bag.image_stamps)
    truth = _base_poses_from_ground_truth(bag.T_c0_ci)[:, :2, 3]
    error = _path_length(wheel[:, :2]) / _path_length(truth) - 1.0
    assert 0.01 < error < 0.05
    assert error == pytest.approx(SCALE_ERROR, abs=0.005)


def test_wheel_heading_drifts_left_with_the_bias(bag: GroundRobotBag) -> None:
    wheel = _relative_to_first(_wheel_at(bag, bag.image_stamps))
    base = _base_poses_from_ground_truth(bag.T_c0_ci)
    true_yaw = np.unwrap([_yaw(T[:3, :3]) for T in base])
    drift_deg = math.degrees(wheel[-1, 2] - true_yaw[-1])
    duration_s = (bag.image_stamps[-1] - bag.image_stamps[0]) / 1e9
    expected_deg = YAW_RATE_BIAS_DEG_S * duration_s
    assert drift_deg > 0.0  # a positive yaw-rate bias turns the odometry to the left
    assert 0.7 * expected_deg < drift_deg < 1.3 * expected_deg
    # the position error at the end follows: a few percent of the path, not more
    truth_xy = base[:, :2, 3]
    end_error = float(np.linalg.norm(wheel[-1, :2] - truth_xy[-1]))
    assert 0.01 * _path_length(truth_xy) < end_error < 0.15 * _path_length(truth_xy)


def test_wheel_tum_file_matches_the_topic(bag: GroundRobotBag) -> None:
    rows = [line.split() for line in (ROOT / "wheel_odom_tum.txt").read_text().splitlines()
            if not line.startswith("#")]
    assert len(rows) == len(bag.wheel_stamps)
    values = np.array([[float(v) for v in r[1:]] for r in rows])
    assert np.allclose(values[:, :3], bag.wheel_pose[:, :3], atol=2e-9)
    assert np.allclose(np.abs(values[:, 3:]), np.abs(bag.wheel_pose[:, 3:]), atol=2e-9)


# --- the generator (needs scikit-image, bags/requirements.txt) ------------------------------------------------


def test_spec_is_deterministic(make_bags: object) -> None:
    a, b = make_bags.ground_robot_spec(), make_bags.ground_robot_spec()
    assert np.array_equal(a.T_w_c, b.T_w_c)
    assert a.wheel_odom is not None and b.wheel_odom is not None
    for field in ("stamps_ns", "pose", "twist", "pose_covariance", "twist_covariance"):
        assert np.array_equal(getattr(a.wheel_odom, field), getattr(b.wheel_odom, field))
    assert a.quads == b.quads


def test_spec_matches_the_bag(make_bags: object, bag: GroundRobotBag) -> None:
    spec = make_bags.ground_robot_spec()
    assert np.allclose(make_bags.poses_relative_to_first(spec.T_w_c), bag.T_c0_ci, atol=1e-12)
    assert np.array_equal(spec.wheel_odom.stamps_ns, bag.wheel_stamps)
    assert np.array_equal(make_bags.base_camera_transform(), T_BASE_CAMERA)


def test_floor_flow_and_structure_clearance(make_bags: object) -> None:
    """A visible floor point moves at most 40 px between frames (KLT with a 15 px window and 3 levels
    follows it); walls, boxes and pillars stay >= 2 m from the camera and the robot."""
    spec = make_bags.ground_robot_spec()
    assert make_bags.max_floor_flow_px(spec.camera, spec.T_w_c, spec.floor_y_m) <= 40.0
    structures = [q for q in spec.quads if q.texture != make_bags.PAVING_TEXTURE]
    assert len(structures) == len(spec.quads) - 1
    assert make_bags.min_clearance_m(structures, spec.T_w_c) >= 2.0
    base_w = spec.T_w_c[:, :3, 3] + spec.T_w_c[:, :3, :3] @ T_CAMERA_BASE[:3, 3]  # base origin in the world
    assert min(make_bags.quad_distance(q, p) for p in base_w for q in structures) >= 2.0
