"""vo_node with a metric scale source: it subscribes to the wheel odometry topic, hands the messages to the
pipeline on its worker thread, and publishes metres (the same poses as replay of the same bag).

The node runs in this process on a loopback-only domain of its own (test/ros_fixtures.py); its input
callbacks are called directly and its ``_publish`` (of each frame's handled outputs) is observed, so nothing
depends on DDS timing.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_fixtures import RosSession, rclpy_session, wait_until

from epi_vo.core.config import VoConfig
from epi_vo.core.frame import FrameResult
from epi_vo.io import bagio
from epi_vo.runner.frames import HandledFrame
from epi_vo.tools.replay import run_replay

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "ground_robot" / "bag"
N_FRAMES = 60


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


def _ros_messages() -> tuple[list[tuple[int, Any, Any]], list[Any]]:
    """The bag's first N_FRAMES (image, camera_info) pairs and its wheel messages as rclpy messages."""
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo, CompressedImage

    frames, wheels = [], []
    with bagio.open_camera_bag(BAG, wheel_topic="/wheel/odom") as bag:
        for frame in bag.iter_frames():
            if len(frames) == N_FRAMES:
                break
            src, info_src = frame.image_msg, frame.camera_info_msg
            img = CompressedImage(format=src.format, data=bytes(src.data))
            img.header.stamp.sec, img.header.stamp.nanosec = src.header.stamp.sec, src.header.stamp.nanosec
            info = CameraInfo(height=info_src.height, width=info_src.width, distortion_model=info_src.distortion_model,
                              d=[float(x) for x in info_src.d], k=[float(x) for x in info_src.k])
            info.header.stamp = img.header.stamp
            frames.append((frame.stamp_ns, img, info))
        w = bag.read_wheel_odometry()
        assert w is not None
        for stamp, xyz in zip(w.stamps_ns, w.positions, strict=True):
            msg = Odometry()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp), 1_000_000_000)
            msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = (float(v) for v in xyz)
            wheels.append((int(stamp), msg))
    return frames, wheels


def test_node_takes_metres_from_the_wheel_topic(ros: RosSession, tmp_path: Path) -> None:
    from rclpy.parameter import Parameter

    from epi_vo.ros.node import VoNode

    node = VoNode(context=ros.context, parameter_overrides=[
        Parameter("scale_source", value="wheel_odometry"), Parameter("wheel_odometry_topic", value="/wheel/odom"),
        Parameter("image_transport", value="compressed"), Parameter("process_every_frame", value=True)])
    published: list[FrameResult] = []
    lock = threading.Lock()
    real_publish = node._publish

    def record(handled: HandledFrame) -> None:
        with lock:
            published.append(handled.result)
        real_publish(handled)

    node._publish = record
    frames, wheels = _ros_messages()
    try:
        assert "/wheel/odom" in [s.topic_name for s in node.subscriptions]
        w = 0
        for i, (stamp, img, info) in enumerate(frames):
            # As a live robot would: the wheel messages up to this image arrive before it.
            while w < len(wheels) and wheels[w][0] <= stamp:
                node._on_wheel_odometry(wheels[w][1])
                w += 1
            node._on_camera_info(info)
            node._on_image(img)
            assert wait_until(lambda n=i + 1: len(published) >= n, 120.0), f"frame {i} not published"
    finally:
        node.destroy_node()
    assert len(published) == N_FRAMES and all(r.has_pose for r in published)
    metric = [r for r in published if r.scale.metric]
    assert len(metric) >= N_FRAMES - 25 and metric[-1].scale.units == "m"
    # Metres: the camera travelled about 0.55 m/s * 4 s; compare with the replay of the same frames.
    cfg = dataclasses.replace(VoConfig(), scale_source="wheel_odometry", wheel_odometry_topic="/wheel/odom")
    replayed: list[FrameResult] = []
    run_replay(BAG, tmp_path / "replay", cfg, on_result=replayed.append)
    ref = replayed[N_FRAMES - 1]
    assert ref.scale.metric
    np.testing.assert_allclose(published[-1].position, ref.position, atol=0.05)
    assert 1.0 < float(np.linalg.norm(published[-1].position)) < 4.0


def _upside_down(frames: list[tuple[int, Any, Any]]) -> list[tuple[int, Any, Any]]:
    """The same frames with every image rotated by 180 deg (a camera mounted upside down)."""
    import cv2
    from sensor_msgs.msg import CompressedImage

    out = []
    for stamp, img, info in frames:
        gray = cv2.imdecode(np.frombuffer(bytes(img.data), np.uint8), cv2.IMREAD_GRAYSCALE)
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(gray[::-1, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert ok
        turned = CompressedImage(format="jpeg", data=buf.tobytes())
        turned.header = img.header
        out.append((stamp, turned, info))
    return out


@pytest.mark.parametrize("declared", [True, False])
def test_node_seeks_the_floor_along_the_mounting_it_declares(ros: RosSession, declared: bool) -> None:
    """The extrinsic the node uses (here camera_rpy: rolled 180 deg, pitched 15 deg down, as the camera is)
    gives the floor search its up: an upside-down camera declared so gets metres from its floor; declared
    level (the default), its floor is above the camera and no plane below it carries the scene: no metres."""
    from rclpy.parameter import Parameter

    from epi_vo.ros.node import VoNode

    rpy = [float(np.pi), float(np.radians(15.0)), 0.0] if declared else [0.0, 0.0, 0.0]
    node = VoNode(context=ros.context, parameter_overrides=[
        Parameter("scale_source", value="ground_plane"), Parameter("camera_height_m", value=0.45),
        Parameter("camera_rpy", value=rpy), Parameter("tf_timeout_s", value=0.0),
        Parameter("image_transport", value="compressed"), Parameter("process_every_frame", value=True)])
    published: list[FrameResult] = []
    lock = threading.Lock()
    real_publish = node._publish

    def record(handled: HandledFrame) -> None:
        with lock:
            published.append(handled.result)
        real_publish(handled)

    node._publish = record
    frames = _upside_down(_ros_messages()[0][:40])
    try:
        for i, (_, img, info) in enumerate(frames):
            node._on_camera_info(info)
            node._on_image(img)
            assert wait_until(lambda n=i + 1: len(published) >= n, 120.0), f"frame {i} not published"
    finally:
        node.destroy_node()
    metric = [r for r in published if r.scale.metric]
    if declared:
        assert len(metric) >= 30
        # 39 frames at 0.42-0.65 m/s: 1.1-1.7 m from the start, in metres.
        assert 1.0 < float(np.linalg.norm(published[-1].position)) < 1.9
    else:
        assert not metric and all(r.scale.units == "vo" for r in published)


# ---------------------------------------------------------------------------------------------------------
# One wheel rule for both doors, live over DDS: a stream whose every third message is stamped 0.3 s early
# gives the node and the replay the same messages used, the same counts, the same odometry.
WHEEL_TOPIC = "/wheel/odom"
WHEEL_CHUNK = 50  # below the node's wheel subscription depth (100): a chunk never overwrites what it holds
LIVE_FRAMES = 150
WAIT_S = 120.0  # bound on a wait for another process or DDS; it matters only when the condition never comes


def _wheel_messages(bag: Path) -> list[Any]:
    """The bag's wheel odometry messages as rclpy messages, in the bag's order."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([bag], default_typestore=ts) as reader:
        conns = [c for c in reader.connections if c.topic == WHEEL_TOPIC]
        return [deserialize_message(bytes(raw), Odometry) for _, _, raw in reader.messages(conns)]


def _summary_values(probe: Any) -> dict[str, str]:
    """The key/values of the node's latest scale status (/diagnostics, once a second)."""
    summaries = [s for a in probe.diag for s in a.status if s.name.endswith(": scale")]
    return {kv.key: kv.value for kv in summaries[-1].values} if summaries else {}


def test_node_and_replay_take_the_same_wheel_messages_from_a_disordered_stream(ros: RosSession,
                                                                                 tmp_path: Path) -> None:
    import subprocess
    import sys

    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from ros_fixtures import NodeProcess, ProbeBase, odom_pose
    from wheel_streams import every_third_early, write_wheel_variant

    from epi_vo.io.msgconv import stamp_to_ns
    from epi_vo.io.odometry_bag import read_odometry

    bag = write_wheel_variant(BAG, tmp_path / "bag", every_third_early, n_images=LIVE_FRAMES)
    cfg = dataclasses.replace(VoConfig(), scale_source="wheel_odometry", wheel_odometry_topic=WHEEL_TOPIC)
    summary = run_replay(bag, tmp_path / "replay", cfg)
    replayed = read_odometry(tmp_path / "replay" / "output.mcap")
    offline = {int(t): np.concatenate([p, q]) for t, p, q in zip(replayed.stamps_ns, replayed.positions,
                                                                   replayed.quats_xyzw, strict=True)}
    wheel = _wheel_messages(bag)
    assert summary.wheel_odometry is not None
    assert summary.wheel_odometry["received"] == len(wheel) > 300
    assert summary.wheel_odometry["out_of_order"] == len(wheel) // 3  # every third, as written
    assert summary.units == "m"

    from nav_msgs.msg import Odometry

    probe = ProbeBase(ros, "probe_wheel_rule")
    pub = probe.node.create_publisher(Odometry, WHEEL_TOPIC, QoSProfile(depth=1000,
                                                                         reliability=ReliabilityPolicy.RELIABLE))
    try:
        with NodeProcess(ros.env, "-p", "scale_source:=wheel_odometry", "-p", f"wheel_odometry_topic:={WHEEL_TOPIC}",
                         "-p", "image_transport:=compressed", "-p", "process_every_frame:=true",
                         "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100") as node:
            assert probe.spin_until(lambda: pub.get_subscription_count() > 0, WAIT_S), node.proc.stderr
            # The whole wheel stream first, in its order, a chunk at a time (each taken before the next).
            for k in range(0, len(wheel), WHEEL_CHUNK):
                for msg in wheel[k: k + WHEEL_CHUNK]:
                    pub.publish(msg)
                sent = min(k + WHEEL_CHUNK, len(wheel))
                assert probe.spin_until(
                    lambda s=sent: int(_summary_values(probe).get("wheel_messages_received", -1)) >= s, WAIT_S), \
                    (sent, _summary_values(probe))
            played = subprocess.run([sys.executable, "-m", "epi_vo.cli", "play", str(bag), "--rate", "0"],
                                    env=ros.env, capture_output=True, text=True, timeout=4 * WAIT_S)
            assert played.returncode == 0, played.stderr

            def statuses() -> list[dict[str, str]]:
                return [{kv.key: kv.value for kv in s.values} for a in probe.frame_status for s in a.status
                        if s.name.endswith(": tracking")]

            assert probe.spin_until(lambda: len(probe.odom) >= LIVE_FRAMES and len(statuses()) >= LIVE_FRAMES,
                                    WAIT_S), len(probe.odom)
        assert "Traceback" not in node.stderr
        assert int(_summary_values(probe)["wheel_messages_lost"]) == 0
    finally:
        probe.close()
    # The same messages used and dropped, and said so in every frame's status ...
    last = statuses()[-1]["wheel_messages"]
    assert last == " ".join(f"{k}={v}" for k, v in summary.wheel_odometry.items()), last
    # ... and the same odometry, in metres, frame by frame.
    assert len(probe.odom) == LIVE_FRAMES == len(offline)
    for m in probe.odom:
        np.testing.assert_allclose(odom_pose(m), offline[stamp_to_ns(m.header.stamp)], atol=1e-6)
    assert float(np.linalg.norm(odom_pose(probe.odom[-1])[:3])) > 2.0
