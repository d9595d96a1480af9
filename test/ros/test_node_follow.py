"""vo_node live over DDS, its odometry moved from outside: a camera extrinsic that arrives after the wait
ran out (a late robot_state_publisher) and then moves, and a pose set on ``set_pose`` / ``reset_pose``.

The node runs in this process (its TF lookup is a fake tf2 buffer: tf2_ros is not on PyPI) on a
loopback-only domain of its own (test/ros_fixtures.py); the test's probe publishes the ground_robot bag's
images and the poses over DDS and reads vo/odometry and the statuses from DDS. The frames the node handled
are also observed (its ``_publish``), for the camera poses the odometry is checked against.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_fixtures import ProbeBase, RosSession, bag_frames_rclpy, call_service, rclpy_session

from epi_vo.core.odometry import T_base_cam_from_params
from epi_vo.core.transforms import (
    invert_T,
    make_T,
    quat_xyzw_from_rotation,
    rotation_angle_deg,
    rotation_from_quat_xyzw,
)

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "ground_robot" / "bag"
CAMERA_FRAME = "camera_optical_frame"
PITCH = math.radians(15.0)  # the bag's camera, 0.45 m up and pitched 15 deg down (bags/README.md)
CAMERA_XYZ = [0.20, 0.0, 0.45]
T_TRUE = T_base_cam_from_params(CAMERA_XYZ, [0.0, PITCH, 0.0])


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


class FakeTfBuffer:
    """tf2_ros.Buffer's lookup_transform: ``T`` (None: 'does not exist', as tf2 raises it) as the transform
    base_link <- camera_optical_frame."""

    def __init__(self) -> None:
        self.T: np.ndarray | None = None

    def lookup_transform(self, target: str, source: str, time: Any) -> Any:
        from geometry_msgs.msg import TransformStamped

        T = self.T
        if T is None or (target, source) != ("base_link", CAMERA_FRAME):
            msg = f'"{target}" passed to lookupTransform argument target_frame does not exist'
            raise LookupError(msg)
        ts = TransformStamped()
        ts.header.frame_id, ts.child_frame_id = target, source
        t, q = ts.transform.translation, ts.transform.rotation
        t.x, t.y, t.z = (float(v) for v in T[:3, 3])
        q.x, q.y, q.z, q.w = (float(v) for v in quat_xyzw_from_rotation(T[:3, :3]))
        return ts


class Probe(ProbeBase):
    """Camera and pose publishers; the frame statuses (on /diagnostics or vo/frame_status, wherever the node
    puts them) by frame index."""

    def __init__(self, ros: RosSession, name: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from sensor_msgs.msg import CameraInfo, CompressedImage

        super().__init__(ros, name)
        self.frame_status: list[Any] = []
        self.node.create_subscription(DiagnosticArray, "vo/frame_status", self.frame_status.append, self.qos)
        self.pub_img = self.node.create_publisher(CompressedImage, "camera/image_raw/compressed", self.qos)
        self.pub_info = self.node.create_publisher(CameraInfo, "camera/camera_info", self.qos)
        self.pub_pose = self.node.create_publisher(PoseWithCovarianceStamped, "set_pose", self.qos)

    def statuses(self) -> dict[int, dict[str, str]]:
        """Every frame's status values by frame index."""
        out = {}
        for arr in self.diag + self.frame_status:
            for s in arr.status:
                values = {kv.key: kv.value for kv in s.values}
                if s.name.endswith(": tracking") and "index" in values:
                    out[int(values["index"])] = {"message": s.message, **values}
        return out

    def send(self, frames: list[tuple[Any, Any]], until: int) -> None:
        """Publish (image, camera_info) pairs, then wait until ``until`` vo/odometry messages came (one a frame)."""
        self.publish_pairs(self.pub_img, self.pub_info, frames)
        assert self.spin_until(lambda: len(self.odom) >= until), len(self.odom)


def _node(ros: RosSession, buffer: FakeTfBuffer, **params: Any) -> Any:
    from rclpy.parameter import Parameter

    from epi_vo.ros.node import VoNode
    from epi_vo.ros.node_tf import BufferLookup

    overrides = [Parameter(k, value=v) for k, v in {
        "image_transport": "compressed", "process_every_frame": True, "qos_reliability": "reliable",
        "qos_depth": 100, "camera_xyz": CAMERA_XYZ, **params}.items()]
    return VoNode(tf_lookup=BufferLookup(buffer, (LookupError,), lambda: None), context=ros.context,
                  parameter_overrides=overrides)


def _observe(node: Any) -> list[Any]:
    """The frames the node publishes (HandledFrame), in order."""
    handled: list[Any] = []
    lock = threading.Lock()
    real = node._publish

    def record(h: Any) -> None:
        with lock:
            handled.append(h)
        real(h)

    node._publish = record
    return handled


def _T(msg: Any) -> np.ndarray:
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return make_T(rotation_from_quat_xyzw([q.x, q.y, q.z, q.w]), [p.x, p.y, p.z])


def _climb(msgs: list[Any]) -> float:
    """The median of the twist's z over its x: how steeply base seems to climb (tan of the slope)."""
    v = np.array([[m.twist.twist.linear.x, m.twist.twist.linear.z] for m in msgs])
    moving = np.abs(v[:, 0]) > 0.5 * np.median(np.abs(v[:, 0]))
    assert moving.sum() >= 0.8 * len(v)
    return float(np.median(v[moving, 1] / v[moving, 0]))


def test_a_late_tf_replaces_the_parameters_and_a_moving_one_is_followed(ros: RosSession) -> None:
    """tf_timeout_s runs out: the parameters' level camera, and base seems to climb a 15 deg ramp. TF then
    arrives (the true mounting): from the next frame base drives on the floor along its x, the odometry does
    not jump, and the frame's status, the log and the diagnostics say it. TF then tilts the camera 5 deg
    more: followed, base now seems to go down a 5 deg slope."""
    buffer = FakeTfBuffer()
    node = _node(ros, buffer, tf_timeout_s=0.2, camera_rpy=[0.0, 0.0, 0.0])
    probe = Probe(ros, "probe_tf_follow")
    probe.executor.add_node(node)
    frames = bag_frames_rclpy(BAG, 36)
    try:
        probe.send(frames[:12], 12)
        buffer.T = T_TRUE
        probe.send(frames[12:24], 24)
        buffer.T = T_base_cam_from_params(CAMERA_XYZ, [0.0, PITCH + math.radians(5.0), 0.0])
        probe.send(frames[24:], 36)
        assert probe.spin_until(lambda: len(probe.statuses()) >= 36 and len(probe.odom_vo_units) >= 36)
        assert probe.spin_until(lambda: any(
            {kv.key: kv.value for kv in s.values}.get("extrinsic_source") == "tf"
            for a in probe.diag[-3:] for s in a.status))
    finally:
        probe.executor.remove_node(node)
        node.destroy_node()
        probe.close()
    odom = probe.odom_vo_units  # the motion (scale_source none: vo/odometry holds its position)
    assert [m.header.stamp for m in odom] == [img.header.stamp for img, _ in frames]
    assert math.tan(PITCH) * 0.8 < _climb(odom[3:12]) < math.tan(PITCH) * 1.2
    assert abs(_climb(odom[13:24])) < 0.03  # within 1.7 deg of the floor
    assert -math.tan(math.radians(5.0)) * 1.3 < _climb(odom[25:]) < -math.tan(math.radians(5.0)) * 0.7
    for k in (12, 24):  # one frame's motion at each switch, not a jump
        step = invert_T(_T(odom[k - 1])) @ _T(odom[k])
        usual = np.linalg.norm((invert_T(_T(odom[k - 2])) @ _T(odom[k - 1]))[:3, 3])
        assert np.linalg.norm(step[:3, 3]) < 2.0 * usual and rotation_angle_deg(step[:3, :3]) < 2.0
    statuses = probe.statuses()
    said = sorted(i for i, v in statuses.items() if "extrinsic" in v)
    assert said == [12, 24], said
    assert "source=tf" in statuses[12]["extrinsic"] and "replacing the camera_xyz" in statuses[12]["extrinsic"]
    assert "the camera moved on base by 0.0 mm, 5.00 deg" in statuses[24]["extrinsic"]


def _pose_msg(frame: str, T: np.ndarray, cov: np.ndarray) -> Any:
    from geometry_msgs.msg import PoseWithCovarianceStamped

    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = (float(v) for v in T[:3, 3])
    q.x, q.y, q.z, q.w = (float(v) for v in quat_xyzw_from_rotation(T[:3, :3]))
    msg.pose.covariance = [float(v) for v in cov.ravel()]
    return msg


def test_set_pose_moves_the_odometry_and_later_motion_composes_from_it(ros: RosSession) -> None:
    """Metres from the floor (ground_plane). A pose in the wrong frame is refused (said in the next frame's
    status); a pose in odom is the next frame's odometry, with its covariance, and the motion after it is the
    camera's, in metres, from there; reset_pose puts base back at the origin."""
    from std_srvs.srv import Trigger

    node = _node(ros, FakeTfBuffer(), tf_timeout_s=0.0, camera_rpy=[0.0, PITCH, 0.0], scale_source="ground_plane",
                 camera_height_m=0.45)
    handled = _observe(node)
    probe = Probe(ros, "probe_set_pose")
    probe.executor.add_node(node)
    reset = probe.node.create_client(Trigger, "reset_pose")
    frames = bag_frames_rclpy(BAG, 40)
    T_set = make_T(rotation_from_quat_xyzw([0.0, 0.0, math.sin(0.6), math.cos(0.6)]), [5.0, -2.0, 0.0])
    cov_set = np.diag([0.04, 0.04, 1e-4, 1e-4, 1e-4, 0.0025])
    try:
        probe.send(frames[:15], 15)
        assert handled[14].result.scale.metric  # metres before the pose is set
        assert probe.spin_until(lambda: probe.pub_pose.get_subscription_count() > 0)
        probe.pub_pose.publish(_pose_msg("map", T_set, cov_set))
        probe.pub_pose.publish(_pose_msg("odom", T_set, cov_set))
        assert probe.spin_until(lambda: len(node._pose_pending) == 2)  # both received before the next frame
        probe.send(frames[15:30], 30)
        response = call_service(probe.executor, reset, Trigger.Request())
        assert response.success and response.message == "base is at the origin of odom from the next frame"
        probe.send(frames[30:], 40)
        assert probe.spin_until(lambda: len(probe.statuses()) >= 40)
    finally:
        probe.executor.remove_node(node)
        node.destroy_node()
        probe.close()
    odom = probe.odom  # metres: vo/odometry carries the motion
    np.testing.assert_allclose(_T(odom[15]), T_set, atol=1e-9)
    np.testing.assert_allclose(np.reshape(odom[15].pose.covariance, (6, 6)), cov_set, atol=1e-8)
    T_bc = T_TRUE
    for j in range(16, 30):  # the camera's motion since the set, taken into base
        rel_cam = invert_T(handled[15].result.T_w_c) @ handled[j].result.T_w_c
        np.testing.assert_allclose(invert_T(_T(odom[15])) @ _T(odom[j]), T_bc @ rel_cam @ invert_T(T_bc), atol=1e-6)
    driven = np.linalg.norm(_T(odom[29])[:3, 3] - T_set[:3, 3])
    assert 0.5 < driven < 1.2, driven  # metres: 14 frames at about 0.56 m/s and 15 Hz
    assert abs(_T(odom[29])[2, 3]) < 0.05  # on the floor of odom
    np.testing.assert_allclose(_T(odom[30]), np.eye(4), atol=1e-9)  # reset_pose
    statuses = probe.statuses()
    assert sorted(i for i, v in statuses.items() if "set_pose" in v) == [15, 30]
    assert statuses[15]["set_pose_refused"] == ("header.frame_id 'map' is not the odometry frame 'odom': the pose "
                                                "set is base's in that frame")
    assert "source=set_pose" in statuses[15]["set_pose"] and "source=reset_pose" in statuses[30]["set_pose"]
    assert [i for i, v in statuses.items() if "set_pose_refused" in v] == [15]
