"""vo_node's frames between arrival and processing, live over DDS on loopback: the queue stays within its
memory bound with a publisher faster than the VO (drops counted, a WARN while they happen), and every image
gets a status within a bounded time when camera_info stamps are off the images' or camera_info never comes.

Every node here gets this test's loopback-only domain (test/ros_fixtures.py). The tests wait on
conditions (bounded generously), never a fixed time: the "faster publisher" is made so by holding the
node's worker on its first frame until the test has seen what it needs, not by the machine's speed.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from ros_fixtures import NodeProcess, ProbeBase, RosSession, bag_frames_rclpy, rclpy_session

from epi_vo.io.msgconv import stamp_to_ns

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "general_motion" / "bag"
N_FRAMES = 52
PERIOD_NS = 66_666_667  # the bag's frame period
WAIT_S = 120.0  # bound on a wait for another process or DDS; it matters only when the condition never comes
INPUT_ARGS = ["-p", "image_transport:=compressed", "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100"]


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


class Probe(ProbeBase):
    """Publishes camera frames (reliable, deep), collects the node's statuses."""

    def __init__(self, ros: RosSession, name: str) -> None:
        from sensor_msgs.msg import CameraInfo, CompressedImage

        super().__init__(ros, name)
        self.pub_img = self.node.create_publisher(CompressedImage, "camera/image_raw/compressed", self.qos)
        self.pub_info = self.node.create_publisher(CameraInfo, "camera/camera_info", self.qos)

    def wait_matched(self) -> None:
        assert self.spin_until(lambda: self.pub_img.get_subscription_count() > 0
                               and self.pub_info.get_subscription_count() > 0)

    def frame_statuses(self) -> list[dict[str, str]]:
        return [{"message": s.message, "level": _level(s), **{kv.key: kv.value for kv in s.values}}
                for a in self.frame_status for s in a.status if s.name.endswith(": tracking")]

    def summaries(self) -> list[dict[str, Any]]:
        """The input statuses of /diagnostics (once a second)."""
        return [{"message": s.message, "level": _level(s), **{kv.key: kv.value for kv in s.values}}
                for a in self.diag for s in a.status if s.name.endswith(": input")]


def _level(status: Any) -> int:
    return status.level[0] if isinstance(status.level, bytes) else int(status.level)


def _copy(msg: Any) -> Any:
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(msg), type(msg))


def _shift_ns(msg: Any, delta_ns: int) -> None:
    t = stamp_to_ns(msg.header.stamp) + delta_ns
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)


@pytest.mark.parametrize("camera_info", ["0.5 ms off", "never"])
def test_every_image_gets_a_status_when_camera_info_does_not_match(ros: RosSession, camera_info: str) -> None:
    from rclpy.duration import Duration

    frames = bag_frames_rclpy(BAG, N_FRAMES)
    stamps = [stamp_to_ns(img.header.stamp) for img, _ in frames]
    probe = Probe(ros, f"probe_info_{'off' if camera_info != 'never' else 'never'}")
    try:
        with NodeProcess(ros.env, *INPUT_ARGS, "-p", "process_every_frame:=true") as node:
            probe.wait_matched()
            if camera_info != "never":
                # The node's camera_info reader has matched once it acknowledged one: no image goes out before.
                # (Otherwise, on a loaded machine, its side of discovery can finish after the images'
                # NO_CAMERA_INFO_WAIT_S: they are then rejected for having none, rightly, but it is not this test.)
                first = _copy(frames[0][1])
                _shift_ns(first, -PERIOD_NS)
                probe.pub_info.publish(first)
                assert probe.pub_info.wait_for_all_acked(Duration(seconds=WAIT_S))
            for img, info in frames:
                if camera_info != "never":
                    _shift_ns(info, 500_000)
                    probe.pub_info.publish(info)
                probe.pub_img.publish(img)
            # Every image gets exactly one status, the last ones too (no newer image will ever come to push them
            # out): bounded by camera_info_wait_s (2 s before any camera_info) and the watchdog's tick.
            assert probe.spin_until(lambda: len(probe.frame_statuses()) >= N_FRAMES), \
                (len(probe.frame_statuses()), node.proc.stderr[-2000:])
            probe.spin_until(lambda: False, 0.5)  # nothing more may come
        statuses = probe.frame_statuses()
        assert sorted(int(s["stamp_ns"]) for s in statuses) == stamps
        if camera_info == "never":
            assert all(s["level"] == 2 and "no camera_info received yet on camera/camera_info" in s["message"]
                       for s in statuses)
        else:  # the camera_info is 0.5 ms off: used as the nearest one, the frames track
            assert sum(s["state"] == "tracking" for s in statuses) >= N_FRAMES - 10, \
                [(s["index"], s["state"], s["message"][:120]) for s in statuses]
            assert all(s["rejected"] == "False" for s in statuses)
        assert "Traceback" not in node.stderr
    finally:
        probe.close()


def test_a_publisher_faster_than_the_vo_is_bounded_by_queue_max_mb_and_the_drops_are_reported(
        ros: RosSession) -> None:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from epi_vo.ros.node import VoNode

    frames = bag_frames_rclpy(BAG, N_FRAMES)
    sizes = [len(img.data) for img, _ in frames]
    cap_mb = 4 * max(sizes) * 1e-6  # room for about four frames
    node = VoNode(context=ros.context, parameter_overrides=[
        Parameter("image_transport", value="compressed"), Parameter("qos_reliability", value="reliable"),
        Parameter("qos_depth", value=200), Parameter("process_every_frame", value=True),
        Parameter("queue_max_mb", value=cap_mb)])
    # The VO is held on its first frame until the test has seen the queue full: slower than any publisher.
    gate = threading.Event()
    process = node._process

    def held(item: Any) -> None:
        gate.wait()
        process(item)

    node._process = held  # type: ignore[method-assign]
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    probe = Probe(ros, "probe_queue")
    try:
        probe.wait_matched()
        for img, info in frames:
            probe.pub_info.publish(info)
            probe.pub_img.publish(img)

        def received() -> int:
            with node._lock:
                return node._frames.received

        assert probe.spin_until(lambda: received() == N_FRAMES), received()
        with node._lock:
            q = node._frames
            queued, held_bytes, dropped, overflow = len(q), q.held_bytes, q.dropped, q.overflow
            in_flight = int(node._busy) + q.pending  # held by the worker, or waiting for its camera_info
        assert held_bytes <= cap_mb * 1e6 and 1 <= queued <= 4
        assert dropped == overflow == N_FRAMES - queued - in_flight >= N_FRAMES - 6
        # The input status says so at WARN while it happens, with the counts.
        assert probe.spin_until(lambda: any(s["message"].startswith("dropping frames: ") for s in probe.summaries()))
        warn = next(s for s in probe.summaries() if s["message"].startswith("dropping frames: "))
        assert warn["level"] == 1 and warn["message"] == "dropping frames: queue_max_mb reached"
        assert f"queue_max_mb={cap_mb:g}" in warn["dropping"]
        assert int(warn["dropped_frames_over_limit"]) >= 1 and float(warn["queue_mb"]) <= cap_mb
        gate.set()
        # Every image is accounted for: a status for each one processed, the others counted as dropped.
        assert probe.spin_until(lambda: len(probe.frame_statuses()) >= N_FRAMES - dropped)
        n = len(probe.summaries())
        assert probe.spin_until(lambda: len(probe.summaries()) >= n + 2)
        last = probe.summaries()[-1]
        assert not last["message"].startswith("dropping frames") and int(last["dropped_frames"]) == dropped
        assert len(probe.frame_statuses()) + dropped == N_FRAMES
        assert int(last["queue_depth"]) == 0
    finally:
        gate.set()
        probe.close()
        executor.shutdown()
        node.destroy_node()
