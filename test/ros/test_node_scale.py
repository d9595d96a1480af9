"""vo_node with a metric scale source: it subscribes to the wheel odometry topic, hands the messages to the
pipeline on its worker thread, and publishes metres (the same poses as replay of the same bag).

The node runs in this process on a loopback-only domain of its own (test/ros_fixtures.py); its input
callbacks are called directly and its ``_publish`` is observed, so nothing depends on DDS timing.
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

    def record(r: FrameResult, stamp_msg: Any, gray: Any) -> None:
        with lock:
            published.append(r)
        real_publish(r, stamp_msg, gray)

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

    def record(r: FrameResult, stamp_msg: Any, gray: Any) -> None:
        with lock:
            published.append(r)
        real_publish(r, stamp_msg, gray)

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
