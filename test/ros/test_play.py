"""Tests for epi_vo.ros.play (``epi-vo play``): real DDS on loopback, values checked against the bag.

rclpy and epi_vo.ros.play (which imports it) are imported only after ``rclpy_session`` has set
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and this run's ROS_DOMAIN_ID; subprocesses get ``ros.env``.
"""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from ros_fixtures import RosSession, rclpy_session, spin_until

from epi_vo.core.errors import ConfigError
from epi_vo.io import bagio

if TYPE_CHECKING:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "pure_rotation" / "bag"
NS_PER_S = 1_000_000_000
WAIT_S = 120.0  # bound on waiting for another process or DDS: generous, a loaded machine is slow, not broken


@dataclass(frozen=True)
class BagImages:
    """What the bag holds on its image topic: header stamps, data bytes, log-time span (s)."""

    stamps_ns: list[int]
    data: list[bytes]
    log_times_ns: list[int]  # every image and camera_info message, bag order

    @property
    def duration_s(self) -> float:
        return (self.log_times_ns[-1] - self.log_times_ns[0]) / NS_PER_S


@pytest.fixture(scope="module")
def bag_images() -> BagImages:
    with bagio.open_camera_bag(BAG) as bag:
        frames = list(bag.iter_frames())
        assert bag.frame_count == len(frames)
    from rosbags.highlevel import AnyReader

    with AnyReader([BAG]) as reader:
        wanted = [c for c in reader.connections if c.topic in ("/camera/image_raw/compressed", "/camera/camera_info")]
        log_times = [t for _, t, _ in reader.messages(wanted)]
    return BagImages([f.stamp_ns for f in frames], [bytes(f.image_msg.data) for f in frames], log_times)


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


@dataclass
class Received:
    images: list[tuple[int, bytes, float]] = field(default_factory=list)  # stamp, data, arrival (monotonic)
    info_stamps: list[int] = field(default_factory=list)
    clocks_ns: list[int] = field(default_factory=list)


@dataclass
class Probe:
    node: Node
    executor: SingleThreadedExecutor
    received: Received


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


@pytest.fixture
def probe(ros: RosSession) -> Iterator[Probe]:
    """Reliable depth-100 subscribers on the default published topics (and /clock), in the root namespace."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, CompressedImage

    node = rclpy.create_node("play_probe", context=ros.context)
    received = Received()
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(
        CompressedImage, "camera/image_raw/compressed",
        lambda m: received.images.append((_stamp_ns(m.header.stamp), bytes(m.data), time.monotonic())), qos)
    node.create_subscription(CameraInfo, "camera/camera_info",
                             lambda m: received.info_stamps.append(_stamp_ns(m.header.stamp)), qos)
    node.create_subscription(Clock, "/clock", lambda m: received.clocks_ns.append(_stamp_ns(m.clock)),
                             QoSProfile(depth=300, reliability=ReliabilityPolicy.RELIABLE))
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(node)
    try:
        yield Probe(node, executor, received)
    finally:
        executor.shutdown()
        node.destroy_node()


def _play_subprocess(ros: RosSession, probe: Probe, n_images: int, *args: str) -> subprocess.CompletedProcess[str]:
    """Run ``epi-vo play BAG *args`` while spinning the probe; wait until every image and info arrived."""
    cmd = [sys.executable, "-m", "epi_vo.cli", "play", str(BAG), *args]
    with subprocess.Popen(cmd, env=ros.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        try:
            spin_until(probe.executor, lambda: proc.poll() is not None, timeout_s=WAIT_S)
        finally:
            if proc.poll() is None:
                proc.kill()
        stdout, stderr = proc.communicate()
    r = probe.received
    spin_until(probe.executor, lambda: len(r.images) >= n_images and len(r.info_stamps) >= n_images, timeout_s=WAIT_S)
    return subprocess.CompletedProcess(cmd, proc.returncode, stdout, stderr)


def test_play_publishes_every_image_as_recorded(ros: RosSession, probe: Probe, bag_images: BagImages) -> None:
    n = len(bag_images.stamps_ns)
    done = _play_subprocess(ros, probe, n, "--rate", "0")
    assert done.returncode == 0, done.stderr
    received = probe.received
    assert len(received.images) == n
    assert [stamp for stamp, _, _ in received.images] == bag_images.stamps_ns  # all, in stamp order
    assert bag_images.stamps_ns == sorted(bag_images.stamps_ns)
    assert [data for _, data, _ in received.images] == bag_images.data
    assert received.info_stamps == bag_images.stamps_ns
    assert received.clocks_ns == []  # no --clock
    summary = done.stdout.strip()
    assert "\n" not in summary
    assert re.match(rf"published {2 * n} messages \({n} on /camera/image_raw/compressed, {n} on "
                    rf"/camera/camera_info\) in [0-9.]+ s: bag time {bag_images.duration_s:.2f} s", summary), summary


def test_play_rate_scales_time(ros: RosSession, probe: Probe, bag_images: BagImages) -> None:
    n = len(bag_images.stamps_ns)
    done = _play_subprocess(ros, probe, n, "--rate", "2.0")
    assert done.returncode == 0, done.stderr
    images = probe.received.images
    assert [stamp for stamp, _, _ in images] == bag_images.stamps_ns
    # Wall time between images over bag time between them: about 0.5. Medians, because playback pauses
    # once when the probe's side of discovery completes late (see epi_vo.ros.play); loose for a loaded machine.
    wall_gaps = np.diff([arrival for _, _, arrival in images])
    bag_gaps = np.diff(bag_images.stamps_ns) / NS_PER_S
    assert 0.35 <= np.median(wall_gaps) / np.median(bag_gaps) <= 0.9
    summary = re.search(r"in ([0-9.]+) s.*effective rate ([0-9.]+)x", done.stdout)
    assert summary is not None, done.stdout
    assert 1.5 <= float(summary.group(2)) <= 2.5  # pauses excluded
    assert 0.35 * bag_images.duration_s <= float(summary.group(1))  # not faster than asked


def test_missing_bag_is_a_one_line_error(ros: RosSession, tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "epi_vo.cli", "play", str(tmp_path / "no_such_bag")]
    done = subprocess.run(cmd, env=ros.env, capture_output=True, text=True, timeout=WAIT_S)
    assert done.returncode != 0
    assert "Traceback" not in done.stderr
    assert done.stderr.strip() == f"epi-vo: error: bag not found: {tmp_path / 'no_such_bag'}"


def _play_in_thread(player: Any) -> tuple[threading.Thread, list[Any]]:
    """``player.play()`` in a thread (the test thread spins the probe); its summary lands in the list."""
    result: list[Any] = []
    thread = threading.Thread(target=lambda: result.append(player.play()), daemon=True)
    thread.start()
    return thread, result


def test_player_in_process_with_clock(ros: RosSession, probe: Probe, bag_images: BagImages) -> None:
    import rclpy

    from epi_vo.ros.play import BagPlayer, PlayOptions

    n = len(bag_images.stamps_ns)
    node = rclpy.create_node("player_clock", context=ros.context)
    try:
        with BagPlayer(node, BAG, PlayOptions(rate=0.0, clock=True)) as player:
            thread, result = _play_in_thread(player)
            r = probe.received
            assert spin_until(probe.executor, lambda: not thread.is_alive() and len(r.clocks_ns) >= 2 * n
                              and len(r.images) >= n, timeout_s=WAIT_S)
            thread.join()
    finally:
        node.destroy_node()
    (summary,) = result
    assert (summary.images, summary.camera_infos, summary.clocks, summary.passes) == (n, n, 2 * n, 1)
    assert not summary.interrupted
    assert [stamp for stamp, _, _ in r.images] == bag_images.stamps_ns
    # One /clock with the bag's log time before each message, in bag order.
    assert r.clocks_ns == bag_images.log_times_ns


def test_player_loop_until_stopped(ros: RosSession, probe: Probe, bag_images: BagImages) -> None:
    import rclpy

    from epi_vo.ros.play import BagPlayer, PlayOptions

    n = len(bag_images.stamps_ns)
    node = rclpy.create_node("player_loop", context=ros.context)
    try:
        with BagPlayer(node, BAG, PlayOptions(rate=20.0, loop=True)) as player:
            thread, result = _play_in_thread(player)
            r = probe.received
            assert spin_until(probe.executor, lambda: len(r.images) >= n + 5, timeout_s=WAIT_S)
            player.stop()
            assert spin_until(probe.executor, lambda: not thread.is_alive(), timeout_s=WAIT_S)
    finally:
        node.destroy_node()
    (summary,) = result
    assert summary.passes >= 2 and summary.interrupted
    stamps = [stamp for stamp, _, _ in r.images]
    assert stamps[:n] == bag_images.stamps_ns
    assert stamps[n:n + 5] == bag_images.stamps_ns[:5]  # the second pass starts over


def _write_image_bag(path: Path, frames: int, corrupt_info_at: int | None = None) -> Path:
    """sqlite3 rosbag2 with ``frames`` 4x6 mono8 Images (pixel value = index) and their CameraInfo."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types

    def header(stamp_ns: int) -> Any:
        stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // NS_PER_S, nanosec=stamp_ns % NS_PER_S)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")

    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        image_conn = writer.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        info_conn = writer.add_connection("/cam0/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        for i in range(frames):
            stamp = 5 * NS_PER_S + i * 50_000_000
            image = T["sensor_msgs/msg/Image"](header=header(stamp), height=4, width=6, encoding="mono8",
                                               is_bigendian=0, step=6, data=np.full(24, i, dtype=np.uint8))
            info = T["sensor_msgs/msg/CameraInfo"](
                header=header(stamp), height=4, width=6, distortion_model="plumb_bob", d=np.zeros(5),
                k=np.eye(3).reshape(-1), r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                          do_rectify=False))
            writer.write(image_conn, stamp, ts.serialize_cdr(image, "sensor_msgs/msg/Image"))
            raw_info = ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo")
            writer.write(info_conn, stamp, b"\x00\x01\x00\x00" if i == corrupt_info_at else raw_info)
    return path


def test_player_raw_image_bag(ros: RosSession, tmp_path: Path) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from epi_vo.ros.play import BagPlayer, PlayOptions

    bag = _write_image_bag(tmp_path / "raw", frames=5)
    sub_node = rclpy.create_node("raw_probe", context=ros.context)
    pub_node = rclpy.create_node("player_raw", context=ros.context)
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(sub_node)
    images: list[Any] = []
    sub_node.create_subscription(Image, "camera/image_raw", images.append,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    try:
        with BagPlayer(pub_node, bag, PlayOptions(rate=0.0)) as player:
            assert player.image_publisher.topic_name == "/camera/image_raw"
            thread, result = _play_in_thread(player)
            assert spin_until(executor, lambda: not thread.is_alive() and len(images) >= 5, timeout_s=WAIT_S)
    finally:
        executor.shutdown()
        sub_node.destroy_node()
        pub_node.destroy_node()
    assert result[0].images == 5
    assert [bytes(m.data) for m in images] == [bytes([i]) * 24 for i in range(5)]
    assert [(m.height, m.width, m.step, m.encoding) for m in images] == [(4, 6, 6, "mono8")] * 5
    assert [_stamp_ns(m.header.stamp) for m in images] == [5 * NS_PER_S + i * 50_000_000 for i in range(5)]


def test_player_corrupt_message_is_a_bag_error(ros: RosSession, tmp_path: Path) -> None:
    import rclpy

    from epi_vo.core.errors import BagError
    from epi_vo.ros.play import BagPlayer, PlayOptions

    bag = _write_image_bag(tmp_path / "corrupt", frames=3, corrupt_info_at=1)
    node = rclpy.create_node("player_corrupt", context=ros.context)
    try:
        with BagPlayer(node, bag, PlayOptions(rate=0.0, start_delay_s=0.0)) as player:
            with pytest.raises(BagError, match=r"cannot deserialise a sensor_msgs/msg/CameraInfo on "
                                               r"/cam0/camera_info at log time 5050000000 ns"):
                player.play()
            assert player.summary().images == 2  # what came before the bad message was published
    finally:
        node.destroy_node()


def test_published_names_are_relative_to_the_namespace(ros: RosSession) -> None:
    import rclpy

    from epi_vo.ros.play import BagPlayer, PlayOptions, Reliability

    node = rclpy.create_node("player_names", namespace="/robot", context=ros.context)
    try:
        with BagPlayer(node, BAG, PlayOptions(remap_image="cam0/image/compressed",
                                              qos_reliability=Reliability.BEST_EFFORT)) as player:
            assert player.image_publisher.topic_name == "/robot/cam0/image/compressed"
            assert player.camera_info_publisher.topic_name == "/robot/camera/camera_info"
            assert player.clock_publisher is None
    finally:
        node.destroy_node()


def test_bag_topic_choice_errors(ros: RosSession) -> None:
    from epi_vo.core.errors import BagError
    from epi_vo.io.play_bag import PlayBag

    with pytest.raises(BagError, match=r"--image-topic '/nope' is not in the bag"):
        PlayBag(BAG, image_topic="/nope")
    with pytest.raises(BagError, match=r"--camera-info-topic '/ground_truth/pose' has type geometry_msgs"):
        PlayBag(BAG, camera_info_topic="/ground_truth/pose")
    with PlayBag(BAG) as bag:
        assert (bag.image_topic, bag.camera_info_topic, bag.image_is_compressed) == (
            "/camera/image_raw/compressed", "/camera/camera_info", True)
        assert (bag.wheel_topic, bag.tf_topics) == (None, ())  # /ground_truth/pose is no wheel odometry


def test_bad_options_reported_together(ros: RosSession) -> None:
    from epi_vo.ros.play import PlayOptions

    with pytest.raises(ConfigError, match=r"rate must be .* got -1.0; qos_depth must be >= 1, got 0; start_delay"):
        PlayOptions(rate=-1.0, qos_depth=0, start_delay_s=float("nan"))


# ---------------------------------------------------------------------------------------------------------
# Every topic the node consumes: wheel odometry and TF, merged with the camera topics in the bag's order.
GROUND_ROBOT = REPO / "bags" / "ground_robot" / "bag"
GROUND_ROBOT_PATH_M = 11.24  # camera path length of the bag (bags/README.md)


def _write_robot_bag(path: Path, frames: int = 6) -> Path:
    """mcap rosbag2: ``frames`` tiny images with camera_info, /wheel/odom twice per image, /tf once per image,
    two /tf_static messages (as two static broadcasters give) before the first image, and an Odometry topic
    named as ground truth (never the wheels)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types

    def header(stamp_ns: int, frame_id: str) -> Any:
        stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // NS_PER_S, nanosec=stamp_ns % NS_PER_S)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def transform(stamp_ns: int, parent: str, child: str, x: float) -> Any:
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp_ns, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=x, y=0.0, z=0.5),
                                                       rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                                  w=1.0)))

    def odometry(stamp_ns: int, frame_id: str, x: float) -> Any:
        cov = np.zeros(36)
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=0.0, z=0.0),
                                             orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=cov)
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.5, y=0.0, z=0.0),
                                               angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
            covariance=cov)
        return T["nav_msgs/msg/Odometry"](header=header(stamp_ns, frame_id), child_frame_id="base_link", pose=pose,
                                          twist=twist)

    tf_type, odom_type = "tf2_msgs/msg/TFMessage", "nav_msgs/msg/Odometry"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        image_conn = writer.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        info_conn = writer.add_connection("/cam0/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        wheel_conn = writer.add_connection("/wheel/odom", odom_type, typestore=ts)
        gt_conn = writer.add_connection("/ground_truth/odom", odom_type, typestore=ts)
        tf_conn = writer.add_connection("/tf", tf_type, typestore=ts)
        static_conn = writer.add_connection("/tf_static", tf_type, typestore=ts)
        t0 = 5 * NS_PER_S
        for k, child in enumerate(("camera_link", "camera_optical_frame")):
            static = T[tf_type](transforms=[transform(t0, "base_link", child, 0.1 * (k + 1))])
            writer.write(static_conn, t0 - 10_000_000 + k, ts.serialize_cdr(static, tf_type))
        for i in range(frames):
            stamp = t0 + i * 50_000_000
            image = T["sensor_msgs/msg/Image"](header=header(stamp, "cam"), height=4, width=6, encoding="mono8",
                                               is_bigendian=0, step=6, data=np.full(24, i, dtype=np.uint8))
            info = T["sensor_msgs/msg/CameraInfo"](
                header=header(stamp, "cam"), height=4, width=6, distortion_model="plumb_bob", d=np.zeros(5),
                k=np.eye(3).reshape(-1), r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                          do_rectify=False))
            writer.write(image_conn, stamp, ts.serialize_cdr(image, "sensor_msgs/msg/Image"))
            writer.write(info_conn, stamp, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            for j in range(2):
                w = stamp + j * 25_000_000 + 1
                writer.write(wheel_conn, w, ts.serialize_cdr(odometry(w, "odom", 0.01 * (2 * i + j)), odom_type))
            writer.write(gt_conn, stamp + 2, ts.serialize_cdr(odometry(stamp, "world", 0.0), odom_type))
            moving = T[tf_type](transforms=[transform(stamp + 3, "odom", "base_link", 0.02 * i)])
            writer.write(tf_conn, stamp + 3, ts.serialize_cdr(moving, tf_type))
    return path


def _recorded(bag: Path, topic: str) -> list[tuple[int, bytes]]:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        return [(t, bytes(raw)) for _, t, raw in reader.messages([c for c in reader.connections if c.topic == topic])]


def test_play_publishes_wheel_odometry_and_tf_and_a_late_node_gets_every_static_transform(
        ros: RosSession, tmp_path: Path) -> None:
    """The wheels on odom (the node's default topic, relative), /tf and /tf_static as recorded, in the bag's order;
    a subscriber that joins after playback still gets both static messages (transient-local, as
    robot_state_publisher). tf2_msgs has no PyPI wheel: std_msgs/String stands in for its rclpy class, which
    only types the publishers (the recorded bytes are published; raw subscribers get them unchanged)."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from epi_vo.ros.play import BagPlayer, PlayOptions, format_summary

    bag = _write_robot_bag(tmp_path / "robot")
    sub_node = rclpy.create_node("tf_probe", namespace="/robot2", context=ros.context)
    pub_node = rclpy.create_node("player_tf", namespace="/robot2", context=ros.context)
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(sub_node)
    order: list[tuple[str, Any]] = []
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    sub_node.create_subscription(Odometry, "odom", lambda m: order.append(("wheel", m)), reliable)
    sub_node.create_subscription(String, "/tf", lambda m: order.append(("tf", m)), reliable, raw=True)
    sub_node.create_subscription(Image, "camera/image_raw", lambda m: order.append(("image", m)), reliable)
    clocks: list[int] = []
    sub_node.create_subscription(Clock, "/clock", lambda m: clocks.append(_stamp_ns(m.clock)), reliable)
    late: list[bytes] = []
    try:
        with BagPlayer(pub_node, bag, PlayOptions(rate=0.0, clock=True), tf_type=String) as player:
            assert player.wheel_publisher is not None and player.wheel_publisher.topic_name == "/robot2/odom"
            thread, result = _play_in_thread(player)
            assert spin_until(executor, lambda: not thread.is_alive() and len(order) >= 6 + 12 + 6
                              and len(clocks) >= 32, timeout_s=WAIT_S)
            summary = result[0]
            # Playback is over; a node that starts now subscribes to /tf_static as tf2's listener does.
            sub_node.create_subscription(String, "/tf_static", late.append,
                                         QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                                    durability=DurabilityPolicy.TRANSIENT_LOCAL), raw=True)
            assert spin_until(executor, lambda: len(late) >= 2, timeout_s=WAIT_S)
    finally:
        executor.shutdown()
        sub_node.destroy_node()
        pub_node.destroy_node()
    assert (summary.images, summary.wheel_messages, summary.tf_messages, summary.tf_static_messages) == (6, 12, 6, 2)
    assert summary.wheel_topic == "/robot2/odom" and summary.not_played == ()
    assert "12 on /robot2/odom, 6 on /tf, 2 on /tf_static" in format_summary(summary)
    # One schedule for all topics, in the bag's order: a /clock with each message's log time before it.
    played = ("/cam0/image_raw", "/cam0/camera_info", "/wheel/odom", "/tf", "/tf_static")
    assert clocks == sorted(t for topic in played for t, _ in _recorded(bag, topic))
    wheels = [m for kind, m in order if kind == "wheel"]
    assert [round(m.pose.pose.position.x, 6) for m in wheels] == [round(0.01 * k, 6) for k in range(12)]
    assert [m for kind, m in order if kind == "tf"] == [raw for _, raw in _recorded(bag, "/tf")]
    assert late == [raw for _, raw in _recorded(bag, "/tf_static")]


def test_without_tf2_msgs_tf_is_not_played_and_the_summary_says_so(ros: RosSession, tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    import rclpy

    import epi_vo.ros.play as play

    monkeypatch.setattr(play, "tf_message_class", lambda: None)
    bag = _write_robot_bag(tmp_path / "robot", frames=2)
    node = rclpy.create_node("player_no_tf", context=ros.context)
    try:
        with play.BagPlayer(node, bag, play.PlayOptions(rate=0.0, start_delay_s=0.0)) as player:
            assert player.tf_publisher("/tf") is None and player.tf_publisher("/tf_static") is None
            summary = player.play()
    finally:
        node.destroy_node()
    assert (summary.images, summary.wheel_messages, summary.tf_messages, summary.tf_static_messages) == (2, 4, 0, 0)
    assert summary.not_played == ("/tf (tf2_msgs is not installed)", "/tf_static (tf2_msgs is not installed)")
    assert play.format_summary(summary).endswith(
        "; not played: /tf (tf2_msgs is not installed); /tf_static (tf2_msgs is not installed)")


def test_wheel_topic_choice(ros: RosSession, tmp_path: Path) -> None:
    from epi_vo.core.errors import BagError
    from epi_vo.io.play_bag import PlayBag

    bag = _write_robot_bag(tmp_path / "robot", frames=1)
    with PlayBag(bag) as chosen:  # /ground_truth/odom is named as ground truth: not the wheels
        assert (chosen.wheel_topic, chosen.tf_topics) == ("/wheel/odom", ("/tf", "/tf_static"))
    with PlayBag(bag, wheel_topic="/ground_truth/odom") as chosen:  # named, it is played
        assert chosen.wheel_topic == "/ground_truth/odom"
    with pytest.raises(BagError, match=r"--wheel-topic '/cam0/camera_info' has type sensor_msgs/msg/CameraInfo, "
                                       r"expected nav_msgs/Odometry"):
        PlayBag(bag, wheel_topic="/cam0/camera_info")


def test_play_feeds_a_wheel_odometry_node_metres(ros: RosSession) -> None:
    """`epi-vo play` of the ground robot bag into a namespaced vo_node with scale_source wheel_odometry and the
    default wheel topic: the node gets the wheels (/robot4/odom) and its odometry is metres, the path as long
    as the ground truth's (without the wheels the position is held: no path at all)."""
    from nav_msgs.msg import Odometry
    from ros_fixtures import NodeProcess, ProbeBase, bag_frame_count, odom_pose

    probe = ProbeBase(ros, "probe_play_wheels", namespace="/robot4")
    positions: list[Any] = []
    probe.node.create_subscription(Odometry, "vo/odometry", lambda m: positions.append(odom_pose(m)[:3]), probe.qos)
    n = bag_frame_count(GROUND_ROBOT)
    try:
        with NodeProcess(ros.env, "-r", "__ns:=/robot4", "-p", "scale_source:=wheel_odometry",
                         "-p", "image_transport:=compressed", "-p", "process_every_frame:=true",
                         "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100") as node:
            assert probe.spin_until(lambda: probe.node.count_subscribers("/robot4/odom") > 0 and
                                    probe.node.count_subscribers("/robot4/camera/image_raw/compressed") > 0,
                                    WAIT_S), node.proc.stderr
            played = subprocess.run([sys.executable, "-m", "epi_vo.cli", "play", str(GROUND_ROBOT), "--rate", "0",
                                     "--namespace", "robot4"], env=ros.env, capture_output=True, text=True,
                                    timeout=10 * WAIT_S)
            assert played.returncode == 0, played.stderr
            assert probe.spin_until(lambda: len(positions) >= n, WAIT_S), (len(positions), node.proc.stderr)
        assert "Traceback" not in node.stderr
    finally:
        probe.close()
    assert "1027 on /robot4/odom" in played.stdout, played.stdout
    steps = np.linalg.norm(np.diff(np.array(positions), axis=0), axis=1)
    assert 0.9 * GROUND_ROBOT_PATH_M < float(steps.sum()) < 1.1 * GROUND_ROBOT_PATH_M, float(steps.sum())
