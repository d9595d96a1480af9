"""vo_node end to end: a real node process, bags played into it over real DDS on loopback.

Every process here gets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and this test's own ROS_DOMAIN_ID
(test/ros_fixtures.py) before rclpy starts.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_fixtures import (
    NodeProcess,
    ProbeBase,
    RosSession,
    bag_frame_count,
    bag_frames_rclpy,
    call_service,
    odom_pose,
    rclpy_session,
    replay_odometry,
    send_calibration,
)

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "general_motion" / "bag"
PLAYBACK_ARGS = ["-p", "image_transport:=compressed", "-p", "process_every_frame:=true",
                 "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100"]
# Bound on every wait for another process (node start-up, outputs, a service): generous, because a loaded
# machine is slow, not broken. The tests wait on the condition itself; the bound matters only on failure.
WAIT_S = 120.0


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


class Probe(ProbeBase):
    """A test-side node subscribing to the VO outputs: odometry and diagnostics, points and path."""

    def __init__(self, ros: RosSession, name: str) -> None:
        from nav_msgs.msg import Path
        from sensor_msgs.msg import PointCloud2

        super().__init__(ros, name)
        self.points: list[Any] = []
        self.paths: list[Any] = []
        self.node.create_subscription(PointCloud2, "vo/points", self.points.append, self.qos)
        self.node.create_subscription(Path, "vo/path", self.paths.append, self.qos)

    def wait_for_node(self, timeout_s: float = WAIT_S) -> bool:
        return self.spin_until(lambda: self.node.count_publishers("vo/odometry") > 0, timeout_s)

    def frame_statuses(self) -> list[Any]:
        """Per-frame tracking statuses (vo/frame_status)."""
        return [s for a in self.frame_status for s in a.status if s.name.endswith(": tracking")]

    def health(self, concern: str) -> list[Any]:
        """The node's statuses of one concern on /diagnostics ('input', 'tracking', ...)."""
        return [s for a in self.diag for s in a.status if s.name.endswith(f": {concern}")]


def _play(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epi_vo.cli", "play", str(BAG), *args], env=env,
                          capture_output=True, text=True, timeout=2 * WAIT_S)


@pytest.fixture(scope="module")
def offline(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[int, Any]]:
    """Odometry of the offline replay of the same bag, by topic and stamp: vo/odometry (VO units: the position
    held) and vo/odometry/vo_units (the motion)."""
    out = tmp_path_factory.mktemp("offline")
    return {"vo/odometry": replay_odometry(BAG, out),
            "vo/odometry/vo_units": replay_odometry(BAG, out, "/vo/odometry/vo_units", run=False),
            "frames": {r["stamp_ns"]: r for r in map(json.loads, (out / "frames.jsonl").read_text().splitlines())}}



@pytest.mark.parametrize("rate", ["1.0", "0"])
def test_live_playback_equals_offline_replay(ros: RosSession, offline: dict[str, dict[int, Any]],
                                            rate: str) -> None:
    """At the bag's rate, and at rate 0 (as fast as the node's subscription acknowledges: frames wait in
    its queue, and with ``process_every_frame`` the next one is decoded and tracked into while the current
    one is processed, ``klt_ahead`` in the frame's timings). Either way the odometry is the offline replay's."""
    n = bag_frame_count(BAG)
    probe = Probe(ros, f"probe_playback_{rate.replace('.', '_')}")
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS) as node:
            assert probe.wait_for_node(), node.proc.stderr
            send_calibration(probe, BAG)
            played = _play(ros.env, "--rate", rate)
            assert played.returncode == 0, played.stderr
            assert probe.spin_until(lambda: len(probe.odom) >= n and len(probe.frame_statuses()) >= n
                                    and len(probe.odom_vo_units) >= n), \
                (len(probe.odom), len(probe.frame_statuses()), len(probe.odom_vo_units))
            probe.spin_until(lambda: False, 0.5)  # nothing extra may arrive
        assert len(probe.odom) == len(probe.odom_vo_units) == n
        assert len(probe.frame_statuses()) == n
        if rate == "0":
            timings = [next(kv.value for kv in st.values if kv.key == "timings_ms") for st in probe.frame_statuses()]
            assert sum("klt_ahead=" in t for t in timings) >= 1, timings[:5]
        vo_frames = ("odom_vo_units", "base_link_vo_units")
        for topic, msgs, frames in (("vo/odometry", probe.odom, ("odom", "base_link")),
                                    ("vo/odometry/vo_units", probe.odom_vo_units, vo_frames)):
            for msg in msgs:
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                assert np.allclose(odom_pose(msg), offline[topic][stamp], rtol=0.0, atol=1e-6), \
                    _first_difference(probe, offline, topic)
                assert (msg.header.frame_id, msg.child_frame_id) == frames
                cov = np.asarray(msg.pose.covariance).reshape(6, 6)
                assert np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0)
        levels = [s.level[0] if isinstance(s.level, bytes) else s.level for s in probe.frame_statuses()]
        assert levels.count(0) >= 0.8 * n  # OK while tracking
        assert probe.points, "no point cloud published"
        _assert_points_in_front(probe)
        # The path (published at keyframes and at least once a second) holds the poses so far, in VO units.
        assert probe.paths and len(probe.paths[-1].poses) >= 10
        assert probe.paths[-1].header.frame_id == "odom_vo_units"
        by_stamp = {(m.header.stamp.sec, m.header.stamp.nanosec): odom_pose(m) for m in probe.odom_vo_units}
        for ps in probe.paths[-1].poses:
            p, q = ps.pose.position, ps.pose.orientation
            np.testing.assert_allclose([p.x, p.y, p.z, q.x, q.y, q.z, q.w],
                                       by_stamp[(ps.header.stamp.sec, ps.header.stamp.nanosec)], atol=1e-9)
    finally:
        probe.close()


def _first_difference(probe: Probe, offline: dict[str, Any], topic: str) -> str:
    """Where the live odometry on ``topic`` first parts from the offline replay's, with what the node and the
    replay said of that frame and of every frame before it (their state and reason)."""
    msgs = probe.odom if topic == "vo/odometry" else probe.odom_vo_units
    live = {}
    for status in probe.frame_statuses():
        values = {kv.key: kv.value for kv in status.values}
        live[int(values["stamp_ns"])] = (f"{status.message} (dropped {values.get('dropped_frames')}, waiting for "
                                         f"camera_info {values.get('waiting_for_camera_info')})")
    lines = []
    for msg in sorted(msgs, key=lambda m: (m.header.stamp.sec, m.header.stamp.nanosec)):
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        rec = offline["frames"].get(stamp, {})
        lines.append(f"{stamp}: live {odom_pose(msg).round(6).tolist()} '{live.get(stamp)}'; offline "
                     f"{offline[topic][stamp].round(6).tolist()} {rec.get('state')} '{rec.get('reason')}'")
        if not np.allclose(odom_pose(msg), offline[topic][stamp], rtol=0.0, atol=1e-6):
            break
    return f"{topic}: live and offline part at the last frame below\n" + "\n".join(lines)


def test_images_ahead_of_their_late_camera_info_take_the_calibration_received(
        ros: RosSession, offline: dict[str, dict[int, np.ndarray]]) -> None:
    """What the live tests rely on (``send_calibration``): with the bag's calibration received, the first images,
    whose own camera_info comes only after the node has processed them (a reader that discovered its publisher
    late), are processed with it: every pose is the offline replay's. Without it they are rejected (no
    camera_info yet) and tracking starts later."""
    from sensor_msgs.msg import CompressedImage

    n = bag_frame_count(BAG)
    frames = bag_frames_rclpy(BAG, n)
    probe = Probe(ros, "probe_late_info")
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS) as node:
            assert probe.wait_for_node(), node.proc.stderr
            pub_info = send_calibration(probe, BAG)
            pub_img = probe.node.create_publisher(CompressedImage, "camera/image_raw/compressed", probe.qos)
            assert probe.spin_until(lambda: pub_img.get_subscription_count() > 0)
            for img, _ in frames[:2]:
                pub_img.publish(img)
            # Their camera_info only once the node has processed both (a frame status each).
            assert probe.spin_until(lambda: len(probe.frame_statuses()) >= 2), node.proc.stderr
            for i, (img, info) in enumerate(frames):
                pub_info.publish(info)
                if i >= 2:
                    pub_img.publish(img)
            assert probe.spin_until(lambda: len(probe.odom) >= n), len(probe.odom)
        assert len(probe.odom) == n
        for msg in probe.odom:
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            np.testing.assert_allclose(odom_pose(msg), offline["vo/odometry"][stamp], atol=1e-6)
        assert not any("no camera_info" in st.message for st in probe.frame_statuses())
    finally:
        probe.close()


MOUNT_XYZ, MOUNT_RPY = (0.2, -0.05, 0.4), (0.03, 0.26, -0.1)  # a camera pitched 15 deg down, off centre


def test_live_playback_equals_offline_replay_with_a_mounted_camera(ros: RosSession, tmp_path: Path) -> None:
    """A camera mounted off base_link, pitched down (``camera_xyz`` / ``camera_rpy``, as the node takes them
    without TF): the replay given the same parameter file publishes the node's odometry, pose and twist,
    and it is not the default mounting's; on both topics (vo/odometry: the position held, the orientation and
    angular velocity as the mounting makes them; vo/odometry/vo_units: the motion)."""
    from epi_vo.cli import main
    from epi_vo.io.odometry_bag import read_odometry

    params = tmp_path / "mounted.yaml"
    params.write_text("/**:\n  ros__parameters:\n    tf_timeout_s: 0.0\n"
                      f"    camera_xyz: {list(MOUNT_XYZ)}\n    camera_rpy: {list(MOUNT_RPY)}\n")
    assert main(["replay", str(BAG), "--output", str(tmp_path / "mounted"), "--params", str(params),
                 "--no-progress"]) == 0
    assert main(["replay", str(BAG), "--output", str(tmp_path / "level"), "--no-progress"]) == 0
    def rows(run: str, topic: str) -> dict[int, tuple[np.ndarray, ...]]:
        odo = read_odometry(tmp_path / run / "output.mcap", "/" + topic)
        return {int(t): (p, q, v, w) for t, p, q, v, w in zip(*_odometry_rows(odo), strict=True)}

    topics = ("vo/odometry", "vo/odometry/vo_units")
    n = bag_frame_count(BAG)
    probe = Probe(ros, "probe_mounted")
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS, "--params-file", str(params)) as node:
            assert probe.wait_for_node(), node.proc.stderr
            send_calibration(probe, BAG)
            played = _play(ros.env, "--rate", "0")
            assert played.returncode == 0, played.stderr
            assert probe.spin_until(lambda: len(probe.odom) >= n and len(probe.odom_vo_units) >= n), len(probe.odom)
    finally:
        probe.close()
    for topic, msgs in zip(topics, (probe.odom, probe.odom_vo_units), strict=True):
        offline, level = rows("mounted", topic), rows("level", topic)
        assert len(msgs) == n == len(offline)
        differs = 0
        for msg in msgs:
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            p, q, v, w = offline[stamp]
            np.testing.assert_allclose(odom_pose(msg), np.concatenate([p, q]), atol=1e-6)
            lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
            np.testing.assert_allclose([lin.x, lin.y, lin.z, ang.x, ang.y, ang.z], np.concatenate([v, w]),
                                       atol=1e-6)
            differs += not np.allclose(np.concatenate([p, q, v, w]), np.concatenate(level[stamp]), atol=1e-3)
        assert differs >= n - 2, topic  # the mounting moves every pose (bar the first, at the origin) and twist


def _odometry_rows(odo: Any) -> tuple[Any, ...]:
    return odo.stamps_ns, odo.positions, odo.quats_xyzw, odo.linear_velocity, odo.angular_velocity


def _assert_points_in_front(probe: Probe) -> None:
    """Point clouds are finite and in front of the camera that triangulated them (camera z > 0)."""
    from epi_vo.core.odometry import default_T_base_cam
    from epi_vo.core.transforms import invert_T, make_T, rotation_from_quat_xyzw
    from epi_vo.io.msgconv import read_points_xyz

    odom_by_stamp = {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in probe.odom_vo_units}
    T_cam_base = invert_T(default_T_base_cam())
    for cloud in probe.points:
        assert cloud.header.frame_id == "odom_vo_units"  # VO units: the points are in the vo_units frame
        pts = read_points_xyz(cloud).astype(np.float64)
        assert pts.shape[0] > 0 and np.all(np.isfinite(pts))
        pose = odom_pose(odom_by_stamp[(cloud.header.stamp.sec, cloud.header.stamp.nanosec)])
        T_odom_base = make_T(rotation_from_quat_xyzw(pose[3:]), pose[:3])
        T_cam_odom = T_cam_base @ invert_T(T_odom_base)
        z = (pts @ T_cam_odom[:3, :3].T + T_cam_odom[:3, 3])[:, 2]
        assert np.mean(z > 0) >= 0.99


def test_reset_service_mid_stream_continues_from_last_pose(ros: RosSession) -> None:
    from std_srvs.srv import Trigger

    n = bag_frame_count(BAG)
    probe = Probe(ros, "probe_reset")
    client = probe.node.create_client(Trigger, "vo/reset")

    def reset_index() -> int | None:
        return next((i for i, s in enumerate(probe.frame_statuses()) if "reset service called" in s.message), None)

    def tracking_after_reset() -> bool:
        i = reset_index()
        return i is not None and len(probe.odom) > i and any(
            s.message.startswith("tracking") for s in probe.frame_statuses()[i + 5:])

    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS) as node:
            assert probe.wait_for_node(), node.proc.stderr
            assert client.wait_for_service(timeout_sec=WAIT_S)
            # --loop: frames keep coming after the reset however long the call takes on a loaded machine.
            player = subprocess.Popen([sys.executable, "-m", "epi_vo.cli", "play", str(BAG), "--rate", "0.5",
                                       "--loop"], env=ros.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True)
            try:
                assert probe.spin_until(lambda: len(probe.odom) >= n // 2)
                # A reset must run once: if its response is lost, the reset's frame status says it ran.
                response = call_service(probe.executor, client, Trigger.Request(), WAIT_S,
                                        took_effect=lambda: reset_index() is not None)
                assert response is None or response.success
                assert probe.spin_until(tracking_after_reset), [s.message for s in probe.frame_statuses()]
            finally:
                _stop(player)
        reset_statuses = [s for s in probe.frame_statuses() if "reset service called" in s.message]
        assert len(reset_statuses) == 1
        i = reset_index()
        assert i is not None and i >= n // 2
        # in VO units the motion is on vo/odometry/vo_units (vo/odometry holds the position)
        before = odom_pose(probe.odom_vo_units[i - 1])[:3]  # the frame processed just before the reset
        after = odom_pose(probe.odom_vo_units[i])[:3]
        assert np.linalg.norm(after - before) < 0.5  # held at the last pose, not back at the origin
        assert np.linalg.norm(before) > 1.0
    finally:
        probe.close()


def _stop(proc: subprocess.Popen[str]) -> None:
    """SIGINT (a clean stop of ``epi-vo play``), then kill."""
    if proc.poll() is None:
        proc.send_signal(2)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    proc.communicate()


def test_late_camera_info_and_params_file(ros: RosSession, tmp_path: Path) -> None:
    """camera_info published after its image still pairs; a parameter file is honoured (with use_sim_time:
    outputs are stamped with the image stamps, so no /clock is needed for them)."""
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    max_features: 120\n    frame_id: my_odom\n"
                      "    image_transport: compressed\n    process_every_frame: true\n"
                      "    qos_reliability: reliable\n    qos_depth: 50\n    use_sim_time: true\n"
                      "    publish_debug_image: true\n")
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    probe = Probe(ros, "probe_late")
    debug_images: list[Any] = []
    probe.node.create_subscription(Image, "vo/debug_image", debug_images.append,
                                   QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    pub_img, pub_info = _camera_publishers(probe)
    frames = bag_frames_rclpy(BAG, 12)
    try:
        with NodeProcess(ros.env, "--params-file", str(params)) as node:
            assert probe.wait_for_node(), node.proc.stderr
            _wait_matched(probe, pub_img, pub_info)
            for img, info in frames:
                pub_img.publish(img)
                probe.spin_until(lambda: False, 0.03)
                pub_info.publish(info)  # after its image
                probe.spin_until(lambda: False, 0.03)
            assert probe.spin_until(lambda: len(probe.odom) >= len(frames)), len(probe.odom)
        assert all(m.header.frame_id == "my_odom" for m in probe.odom)
        assert debug_images and debug_images[-1].encoding == "bgr8"
        assert (debug_images[-1].width, debug_images[-1].height) == (640, 480)
        stamps = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in probe.odom]
        assert stamps == [(i.header.stamp.sec, i.header.stamp.nanosec) for i, _ in frames]
        for s in probe.frame_statuses():
            values = {kv.key: kv.value for kv in s.values}
            assert int(values["n_features"]) <= 120
    finally:
        probe.close()


def _camera_publishers(probe: Probe, depth: int = 100) -> tuple[Any, Any]:
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, CompressedImage

    qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
    return (probe.node.create_publisher(CompressedImage, "camera/image_raw/compressed", qos),
            probe.node.create_publisher(CameraInfo, "camera/camera_info", qos))


def _wait_matched(probe: Probe, pub_img: Any, pub_info: Any) -> None:
    assert probe.spin_until(lambda: pub_img.get_subscription_count() > 0 and pub_info.get_subscription_count() > 0)
    # Usually enough for the node's side of matching too; when it is not, reliable delivery still catches up
    # (at the writer's next heartbeat, within seconds), and every test waits for its outputs.
    probe.spin_until(lambda: False, 0.3)


def test_equal_and_backward_stamps_are_reported_and_odometry_stays_continuous(ros: RosSession) -> None:
    probe = Probe(ros, "probe_stamps")
    pub_img, pub_info = _camera_publishers(probe)
    frames = bag_frames_rclpy(BAG, 30)
    # 0..19, then frame 19 again (equal stamp), then frames 20..29 stamped 5 s in the past.
    sequence = [*frames[:20], frames[19]]
    for img, info in frames[20:]:
        img, info = _to_rclpy_copy(img), _to_rclpy_copy(info)
        for m in (img, info):
            m.header.stamp.sec -= 5
        sequence.append((img, info))
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS) as node:
            assert probe.wait_for_node(), node.proc.stderr
            _wait_matched(probe, pub_img, pub_info)
            for img, info in sequence:
                pub_info.publish(info)
                pub_img.publish(img)
                probe.spin_until(lambda: False, 0.02)
            assert probe.spin_until(lambda: len(probe.frame_statuses()) >= len(sequence))
        messages = [s.message for s in probe.frame_statuses()]
        assert sum("duplicate image stamp" in m for m in messages) == 1
        assert sum("time jumped backwards by 4.9" in m for m in messages) == 1
        assert len(probe.odom) == len(sequence) - 1  # the duplicate is reported, not processed
        # VO units: the motion is on vo/odometry/vo_units (vo/odometry holds its position)
        assert probe.spin_until(lambda: len(probe.odom_vo_units) >= len(sequence) - 1)
        moved = probe.odom_vo_units
        jump = np.linalg.norm(odom_pose(moved[20])[:3] - odom_pose(moved[19])[:3])
        assert np.linalg.norm(odom_pose(moved[19])[:3]) > 0.3
        assert jump < 0.05  # tracking restarted at the held pose: odometry continuous
    finally:
        probe.close()


def test_live_mode_drops_oldest_frames_and_counts_them(ros: RosSession) -> None:
    probe = Probe(ros, "probe_drops")
    pub_img, pub_info = _camera_publishers(probe)
    frames = bag_frames_rclpy(BAG, 40)
    try:
        with NodeProcess(ros.env, "-p", "image_transport:=compressed", "-p", "qos_reliability:=reliable",
                         "-p", "qos_depth:=100", "-p", "queue_size:=1") as node:
            assert probe.wait_for_node(), node.proc.stderr
            _wait_matched(probe, pub_img, pub_info)
            for img, info in frames:  # as fast as possible: far faster than the VO
                pub_info.publish(info)
                pub_img.publish(img)
            last = frames[-1][0].header.stamp
            last_ns = str(last.sec * 10**9 + last.nanosec)
            # The newest frame is always kept: wait for its odometry and its status (published after all
            # drops were counted; the frame's stamp is in its values), however long a loaded machine takes.
            assert probe.spin_until(lambda: any(m.header.stamp == last for m in probe.odom)
                                    and any(kv.key == "stamp_ns" and kv.value == last_ns
                                            for s in probe.frame_statuses() for kv in s.values)), len(probe.odom)
        statuses = probe.frame_statuses()
        dropped = max(int({kv.key: kv.value for kv in s.values}["dropped_frames"]) for s in statuses)
        assert dropped > 0
        assert len(probe.odom) + dropped == len(frames)
        stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in probe.odom]
        assert stamps == sorted(stamps)  # newest kept, order preserved
        assert stamps[-1] == last.sec * 10**9 + last.nanosec
    finally:
        probe.close()


def test_namespace_and_remapping(ros: RosSession) -> None:
    probe = Probe(ros, "probe_ns")
    try:
        with NodeProcess(ros.env, "-r", "__ns:=/robot1", "-r", "vo/odometry:=odom_vo") as node:
            for check in (lambda: probe.node.count_publishers("/robot1/odom_vo") > 0,
                          lambda: probe.node.count_subscribers("/robot1/camera/image_raw") > 0,
                          lambda: probe.node.count_publishers("/robot1/vo/points") > 0,
                          lambda: probe.node.count_publishers("/robot1/vo/frame_status") > 0,
                          lambda: probe.node.count_publishers("/diagnostics") > 0):
                assert probe.spin_until(check), node.proc.stderr
    finally:
        probe.close()


def _to_rclpy_copy(msg: Any) -> Any:
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(msg), type(msg))


def test_bad_parameters_are_refused_with_every_name(ros: RosSession) -> None:
    proc = subprocess.run([sys.executable, "-m", "epi_vo.ros.node", "--ros-args", "-p", "max_features:=-5",
                           "-p", "essential_method:=foo", "-p", "image_transport:=mjpeg"],
                          env=ros.env, capture_output=True, text=True, timeout=WAIT_S)
    assert proc.returncode != 0
    for name in ("max_features", "essential_method", "image_transport"):
        assert name in proc.stderr
    assert "Traceback" not in proc.stderr


def test_watchdog_reports_a_stalled_camera(ros: RosSession) -> None:
    probe = Probe(ros, "probe_watchdog")
    try:
        with NodeProcess(ros.env, "-p", "watchdog_timeout_s:=0.3") as node:
            assert probe.wait_for_node(), node.proc.stderr
            assert probe.spin_until(lambda: any(s.level in (b"\x03", 3) for s in probe.health("input"))), \
                node.proc.stderr
        stale = [s for s in probe.health("input") if s.level in (b"\x03", 3)]
        assert stale[-1].message == "no image received yet" and stale[-1].name == "/vo_node: input"
    finally:
        probe.close()


def test_node_killed_and_restarted_mid_stream_tracks_again(ros: RosSession) -> None:
    probe = Probe(ros, "probe_restart")
    # --loop: the stream goes on however long the second node takes to start on a loaded machine.
    player = subprocess.Popen([sys.executable, "-m", "epi_vo.cli", "play", str(BAG), "--rate", "0.5", "--loop"],
                              env=ros.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS) as first:
            assert probe.wait_for_node(), first.proc.stderr
            assert probe.spin_until(lambda: len(probe.odom) >= 10)
            assert player.poll() is None  # the kill happens mid-stream
            first.proc.kill()  # no clean shutdown
            first.proc.wait()
        # The second node's statuses carry a hardware_id of their own: statuses of the first node still on
        # their way to the probe cannot be mistaken for them.
        with NodeProcess(ros.env, *PLAYBACK_ARGS, "-p", "hardware_id:=restarted") as second:
            assert probe.spin_until(lambda: any(s.hardware_id == "restarted" and s.message.startswith("tracking")
                                                for s in probe.frame_statuses())), second.proc.stderr
            assert second.proc.poll() is None
    finally:
        _stop(player)
        probe.close()


def test_bad_frames_and_a_stalled_camera_keep_the_node_up(ros: RosSession) -> None:
    """Corrupt JPEG, an image whose size differs from camera_info, a NaN calibration: each gets a status
    with the reason and a held (never NaN) odometry; after a stall the watchdog reports STALE; when images
    resume, tracking comes back."""
    probe = Probe(ros, "probe_bad")
    pub_img, pub_info = _camera_publishers(probe)
    frames = bag_frames_rclpy(BAG, 40)
    good = frames[:15]
    bad = []
    for i, (img, info) in enumerate(frames[15:18]):
        img, info = _to_rclpy_copy(img), _to_rclpy_copy(info)
        if i == 0:
            img.data = bytes(np.random.default_rng(0).integers(0, 255, 2000, dtype=np.uint8))  # corrupt jpeg
        elif i == 1:
            info.width, info.height = 320, 240  # does not match the 640x480 image
        else:
            info.k[0] = float("nan")
        bad.append((img, info))
    after = frames[18:]
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS, "-p", "watchdog_timeout_s:=0.3") as node:
            assert probe.wait_for_node(), node.proc.stderr
            _wait_matched(probe, pub_img, pub_info)
            for img, info in good + bad:
                pub_info.publish(info)
                probe.spin_until(lambda: False, 0.01)  # a bad calibration must pair with its own image
                pub_img.publish(img)
                probe.spin_until(lambda: False, 0.03)
            # The stall: every frame so far processed, then STALE for lack of images (not the STALE "no image
            # received yet" of the start-up).
            assert probe.spin_until(lambda: len(probe.odom) >= len(good) + len(bad) and any(
                s.level in (b"\x03", 3) and s.message == "stalled: no recent image" for s in probe.health("input")))
            n_before = len(probe.odom)
            for img, info in after:
                pub_info.publish(info)
                pub_img.publish(img)
                probe.spin_until(lambda: False, 0.03)
            assert probe.spin_until(lambda: len(probe.odom) >= len(good) + len(bad) + len(after))
            assert node.proc.poll() is None  # still running
        messages = [s.message for s in probe.frame_statuses()]
        assert any("could not decode CompressedImage" in m for m in messages)
        assert any("does not match camera_info size 320x240" in m for m in messages)
        assert any("K is not finite" in m for m in messages)
        for m in probe.odom:
            pose = odom_pose(m)
            assert np.all(np.isfinite(pose)) and abs(np.linalg.norm(pose[3:]) - 1.0) < 1e-6
            assert np.all(np.isfinite(np.asarray(m.pose.covariance)))
        assert n_before == len(good) + len(bad)
        assert any(s.message.startswith("tracking") for s in probe.frame_statuses()[-10:])
    finally:
        probe.close()


def _raw(gray: np.ndarray, stamp: Any, encoding: str = "mono8", pad: int = 0, big_endian: bool = False) -> Any:
    """A sensor_msgs/Image of ``gray`` in the given encoding (mono8, mono16, 32FC1, yuv422) and padding."""
    from sensor_msgs.msg import Image

    h, w = gray.shape
    if encoding == "mono16":
        pix = (gray.astype(np.uint16) << 8).astype(">u2" if big_endian else "<u2").view(np.uint8).reshape(h, 2 * w)
    elif encoding == "32FC1":
        pix = gray.astype(np.float32).view(np.uint8).reshape(h, 4 * w)
    elif encoding == "yuv422":
        pix = np.repeat(gray, 2, axis=1)
    else:
        pix = gray
    rows = np.zeros((h, pix.shape[1] + pad), np.uint8)
    rows[:, :pix.shape[1]] = pix
    msg = Image()
    msg.header.stamp = stamp
    msg.height, msg.width, msg.encoding = h, w, encoding
    msg.is_bigendian = int(big_endian)
    msg.step = rows.shape[1]
    msg.data = rows.tobytes()
    return msg


def test_raw_image_inputs_good_and_bad(ros: RosSession) -> None:
    """Raw-image inputs through the node: padded step, big-endian mono16 and a 4K frame (downscaled by
    max_image_width) work; 32FC1, yuv422, an uncalibrated K, an unknown distortion model, a D of the
    wrong length and an image size change each get a status with the reason; the node stays up and
    publishes one valid odometry per image."""
    import cv2
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    from epi_vo.io.msgconv import decode_frame

    probe = Probe(ros, "probe_raw")
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    pub_img = probe.node.create_publisher(Image, "camera/image_raw", qos)
    pub_info = probe.node.create_publisher(CameraInfo, "camera/camera_info", qos)
    src = bag_frames_rclpy(BAG, 24)
    grays = [decode_frame(img, True) for img, _ in src]

    def info_of(i: int, **change: Any) -> Any:
        info = _to_rclpy_copy(src[i][1])
        for k, v in change.items():
            setattr(info, k, v)
        return info

    seq: list[tuple[Any, Any, str]] = []
    for i in range(12):
        seq.append((_raw(grays[i], src[i][0].header.stamp, pad=7 if i % 2 else 0), info_of(i), ""))
    seq.append((_raw(grays[12], src[12][0].header.stamp, "mono16", big_endian=True), info_of(12), ""))
    cases = [("32FC1", {}, "unsupported image encoding '32FC1'"),
             ("yuv422", {}, "unsupported image encoding 'yuv422'"),
             ("mono8", {"k": [0.0] * 9}, "uncalibrated"),
             ("mono8", {"distortion_model": "kannala"}, "unknown distortion model 'kannala'"),
             ("mono8", {"d": [0.1, 0.0, 0.0]}, "camera_info D has 3"),
             ("mono8", {"width": 320, "height": 240}, "does not match camera_info size 320x240")]
    for j, (enc, change, reason) in enumerate(cases):
        i = 13 + j
        seq.append((_raw(grays[i], src[i][0].header.stamp, enc), info_of(i, **change), reason))
    big = cv2.resize(grays[19], (3840, 2880), interpolation=cv2.INTER_LINEAR)
    K4 = np.asarray(src[19][1].k, np.float64) * np.array([6, 1, 6, 1, 6, 6, 1, 1, 1.0])
    K4[2] = (src[19][1].k[2] + 0.5) * 6 - 0.5
    K4[5] = (src[19][1].k[5] + 0.5) * 6 - 0.5
    seq.append((_raw(big, src[19][0].header.stamp), info_of(19, width=3840, height=2880, k=list(K4)), ""))
    for i in range(20, 24):
        seq.append((_raw(grays[i], src[i][0].header.stamp), info_of(i), ""))
    try:
        with NodeProcess(ros.env, "-p", "process_every_frame:=true", "-p", "qos_reliability:=reliable",
                         "-p", "qos_depth:=100", "-p", "max_image_width:=640") as node:
            assert probe.wait_for_node(), node.proc.stderr
            assert probe.spin_until(lambda: pub_img.get_subscription_count() > 0
                                    and pub_info.get_subscription_count() > 0)
            probe.spin_until(lambda: False, 0.3)  # as in _wait_matched
            for img, info, _ in seq:
                pub_info.publish(info)
                probe.spin_until(lambda: False, 0.01)  # each bad calibration must pair with its own image
                pub_img.publish(img)
                probe.spin_until(lambda: False, 0.05)
            assert probe.spin_until(lambda: len(probe.frame_statuses()) >= len(seq)), \
                (len(probe.frame_statuses()), len(seq))
            assert node.proc.poll() is None
        statuses = probe.frame_statuses()
        assert len(statuses) == len(seq) == len(probe.odom)
        for (_, _, reason), status in zip(seq, statuses, strict=True):
            if reason:
                assert reason in status.message, (reason, status.message)
            else:
                assert "rejected" not in status.message, status.message
        for m in probe.odom:
            pose = odom_pose(m)
            assert np.all(np.isfinite(pose)) and abs(np.linalg.norm(pose[3:]) - 1.0) < 1e-6
        assert statuses[12].message.startswith("tracking")  # big-endian mono16 tracked like mono8
    finally:
        probe.close()
