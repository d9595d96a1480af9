"""vo_node in-process: an internal error is reported as one (not as a duplicate stamp), a misspelt
parameter override is warned about with the closest name, and published stamps are valid ROS times.

The node runs in this process on a loopback-only domain of its own (test/ros_fixtures.py); its input
callbacks are called directly and its ``_publish`` (of each frame's handled outputs) is observed, so nothing
depends on DDS timing.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from ros_fixtures import RosSession, rclpy_session

from epi_vo.core.decisions import Decision
from epi_vo.core.frame import FrameResult
from epi_vo.runner.frames import HandledFrame


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


def _image(stamp_ns: int, seed: int = 0) -> tuple[Any, Any]:
    from sensor_msgs.msg import CameraInfo, Image

    rng = np.random.default_rng(seed)
    gray = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    img = Image(height=120, width=160, encoding="mono8", step=160, data=gray.tobytes())
    img.header.stamp.sec, img.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    info = CameraInfo(height=120, width=160, distortion_model="plumb_bob", d=[0.0] * 5,
                      k=[150.0, 0.0, 80.0, 0.0, 150.0, 60.0, 0.0, 0.0, 1.0])
    info.header.stamp = img.header.stamp
    return img, info


class _Recorder:
    """Forwards to the node's logger and keeps the warnings."""

    def __init__(self, real: Any) -> None:
        self.real = real
        self.warnings: list[str] = []

    def warning(self, msg: str, **kwargs: Any) -> None:
        self.warnings.append(msg)
        self.real.warning(msg)  # one call site for every warning: rclpy refuses mixed throttle filters there

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)


def _make_node(ros: RosSession, overrides: list[Any] | None = None) -> Any:
    from epi_vo.ros.node import VoNode

    class RecordingNode(VoNode):
        def get_logger(self) -> Any:
            if "_recorder" not in self.__dict__:
                self.__dict__["_recorder"] = _Recorder(super().get_logger())
            return self.__dict__["_recorder"]

    return RecordingNode(context=ros.context, parameter_overrides=overrides or [])


def _wait(predicate: Any, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_misspelt_override_is_warned_with_the_closest_name(ros: RosSession) -> None:
    from rclpy.parameter import Parameter

    node = _make_node(ros, [Parameter("max_featurs", value=50), Parameter("frame_idd", value="odom"),
                            Parameter("max_features", value=120)])
    try:
        assert node.cfg.max_features == 120
        warned = [w for w in node.get_logger().warnings if "does not declare" in w]
        assert len(warned) == 1
        assert "max_featurs (did you mean max_features?)" in warned[0]
        assert "frame_idd (did you mean frame_id?)" in warned[0]
    finally:
        node.destroy_node()


def test_no_warning_without_unknown_overrides(ros: RosSession) -> None:
    from rclpy.parameter import Parameter

    node = _make_node(ros, [Parameter("max_features", value=120), Parameter("use_sim_time", value=False)])
    try:
        assert not [w for w in node.get_logger().warnings if "does not declare" in w]
    finally:
        node.destroy_node()


def test_internal_error_is_reported_as_such_and_tracking_restarts(ros: RosSession) -> None:
    node = _make_node(ros)
    published: list[tuple[FrameResult, Any]] = []
    lock = threading.Lock()
    real_publish = node._publish

    def record(handled: HandledFrame) -> None:
        with lock:
            published.append((handled.result, handled.outputs.odometry))
        real_publish(handled)

    node._publish = record
    from epi_vo.core import step as step_module

    real_tracked = step_module._tracked
    calls = {"n": 0}

    def failing_once(*args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("simulated defect")
        return real_tracked(*args, **kwargs)

    step_module._tracked = failing_once  # type: ignore[assignment]
    try:
        for i in range(4):
            img, info = _image(1_000_000_000 + i * 33_000_000, seed=i)
            node._on_camera_info(info)
            node._on_image(img)
            assert _wait(lambda n=i + 1: len(published) >= n), f"frame {i} was not published"
    finally:
        step_module._tracked = real_tracked  # type: ignore[assignment]
        node.destroy_node()
    reasons = [r.reason for r, _ in published]
    assert "internal error: RuntimeError('simulated defect')" in reasons[1]
    assert all("duplicate" not in x for x in reasons)
    assert not published[1][0].has_pose
    assert "internal error in the previous frame" in reasons[2]
    for r, odometry in published:
        assert odometry is not None and odometry.sample.stamp_ns == r.stamp_ns


def test_header_stamp_that_is_no_ros_time_is_a_rejected_frame(ros: RosSession) -> None:
    """As in replay: nanosec >= 1e9 is no valid ROS time; the frame gets a status with the reason and no
    odometry, and the frames after it track on (the bad stamp was not booked)."""
    node = _make_node(ros)
    statuses: list[Any] = []  # the DiagnosticArrays of vo/frame_status
    published: list[FrameResult] = []
    real_status, real_publish = node._pub_frame_status.publish, node._publish
    node._pub_frame_status.publish = lambda arr: (statuses.append(arr), real_status(arr))
    node._publish = lambda h: (published.append(h.result) if not h.result.skipped else None, real_publish(h))
    try:
        img, info = _image(0)
        img.header.stamp.sec, img.header.stamp.nanosec = 5, 1_500_000_000
        info.header.stamp = img.header.stamp
        node._on_camera_info(info)
        node._on_image(img)
        assert _wait(lambda: len(statuses) >= 1)
        img, info = _image(5_100_000_000, seed=1)
        node._on_camera_info(info)
        node._on_image(img)
        assert _wait(lambda: len(published) >= 1)
    finally:
        node.destroy_node()
    (status,) = statuses[0].status
    assert "header stamp sec 5 nanosec 1500000000 is not a valid ROS time" in status.message
    assert 0 <= statuses[0].header.stamp.nanosec < 1_000_000_000
    assert published[0].stamp_ns == 5_100_000_000 and Decision.TIME_JUMPED_BACK not in published[0].decisions
