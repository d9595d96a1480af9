"""vo_lifecycle_node end to end: a real node process driven through the lifecycle_msgs services
(/vo_node/change_state, /vo_node/get_state), bags played into it with ``epi-vo play``, over real DDS on
loopback.

Every process here gets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and this test's own ROS_DOMAIN_ID
(test/ros_fixtures.py) before rclpy starts. "Nothing arrives" is checked after a condition that proves
the node had the chance: it counted the frames it ignored (its summary says how many), and a further
summary came after that.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator
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

from epi_vo.io.msgconv import stamp_to_ns

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "general_motion" / "bag"
PLAYBACK_ARGS = ["-p", "image_transport:=compressed", "-p", "process_every_frame:=true",
                 "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100"]
WAIT_S = 120.0  # bound on a wait for another process or DDS; it matters only when the condition never comes
NEW_MAP = "configured again after cleanup: new map from the origin"


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


LIFECYCLE = "epi_vo.ros.lifecycle_node"


class Probe(ProbeBase):
    """The test side: lifecycle and parameter clients of /vo_node, subscriptions to its outputs, camera
    publishers (reliable, deep queues: nothing may be lost)."""

    def __init__(self, ros: RosSession, name: str) -> None:
        from lifecycle_msgs.srv import ChangeState, GetState
        from rcl_interfaces.srv import SetParameters
        from sensor_msgs.msg import CameraInfo, CompressedImage

        super().__init__(ros, name)
        self.pub_img = self.node.create_publisher(CompressedImage, "camera/image_raw/compressed", self.qos)
        self.pub_info = self.node.create_publisher(CameraInfo, "camera/camera_info", self.qos)
        self.change_client = self.node.create_client(ChangeState, "/vo_node/change_state")
        self.get_client = self.node.create_client(GetState, "/vo_node/get_state")
        self.set_client = self.node.create_client(SetParameters, "/vo_node/set_parameters")

    def change(self, transition_id: int) -> bool:
        """One lifecycle transition through /vo_node/change_state: its success. A transition runs once: if
        its response is lost (ros_fixtures.RESEND_S) and the state has moved, the state it reached says."""
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        goal = {Transition.TRANSITION_CONFIGURE: "inactive", Transition.TRANSITION_CLEANUP: "unconfigured",
                Transition.TRANSITION_ACTIVATE: "active", Transition.TRANSITION_DEACTIVATE: "inactive",
                Transition.TRANSITION_UNCONFIGURED_SHUTDOWN: "finalized",
                Transition.TRANSITION_INACTIVE_SHUTDOWN: "finalized",
                Transition.TRANSITION_ACTIVE_SHUTDOWN: "finalized"}[transition_id]
        request = ChangeState.Request()
        request.transition.id = transition_id
        before = self.state()
        response = call_service(self.executor, self.change_client, request, WAIT_S,
                                took_effect=lambda: self.state() != before)
        return self.state() == goal if response is None else bool(response.success)

    def state(self) -> str:
        from lifecycle_msgs.srv import GetState

        return str(call_service(self.executor, self.get_client, GetState.Request(), WAIT_S).current_state.label)

    def statuses(self, suffix: str) -> list[Any]:
        return [s for a in self.diag for s in a.status if s.name.endswith(suffix)]

    def frame_statuses(self) -> list[Any]:
        return [s for a in self.frame_status for s in a.status if s.name.endswith(": tracking")]

    def summaries(self) -> list[dict[str, Any]]:
        """The lifecycle statuses of /diagnostics (once a second, in every state)."""
        return [{"message": s.message, "level": _level(s), **{kv.key: kv.value for kv in s.values}}
                for s in self.statuses(": lifecycle")]

    def ignored(self) -> int:
        """The latest count of images the node ignored while inactive (its lifecycle status), -1 before any."""
        counts = [int(s["frames_ignored_inactive"]) for s in self.summaries() if "frames_ignored_inactive" in s]
        return counts[-1] if counts else -1

    def wait_further_summaries(self, k: int = 2) -> None:
        n = len(self.summaries())
        assert self.spin_until(lambda: len(self.summaries()) >= n + k)

    def send_until(self, frames: list[tuple[Any, Any]], predicate: Callable[[], bool]) -> None:
        """Publish (camera_info, image) pairs, cycling, until ``predicate`` holds (e.g. the node counted them)."""
        i = 0

        def publish_and_check() -> bool:
            nonlocal i
            info, img = frames[i % len(frames)][1], frames[i % len(frames)][0]
            self.pub_info.publish(info)
            self.pub_img.publish(img)
            i += 1
            self.executor.spin_once(timeout_sec=0.03)
            return predicate()

        assert self.spin_until(publish_and_check), i

    def send(self, frames: list[tuple[Any, Any]]) -> None:
        """Publish (camera_info, image) pairs once each."""
        for img, info in frames:
            self.pub_info.publish(info)
            self.pub_img.publish(img)
            self.executor.spin_once(timeout_sec=0.03)


def _level(status: Any) -> int:
    return status.level[0] if isinstance(status.level, bytes) else int(status.level)


def _play(env: dict[str, str], *args: str) -> None:
    played = subprocess.run([sys.executable, "-m", "epi_vo.cli", "play", str(BAG), "--rate", "1.0", *args], env=env,
                            capture_output=True, text=True, timeout=2 * WAIT_S)
    assert played.returncode == 0, played.stderr


@pytest.fixture(scope="module")
def offline(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[int, np.ndarray]]:
    """Odometry of the offline replay of the same bag, by topic and stamp: vo/odometry (VO units: the position
    held) and vo/odometry/vo_units (the motion)."""
    out = tmp_path_factory.mktemp("offline")
    return {"vo/odometry": replay_odometry(BAG, out),
            "vo/odometry/vo_units": replay_odometry(BAG, out, "/vo/odometry/vo_units", run=False)}



def _assert_equals_offline(odom: list[Any], vo_units: list[Any], offline: dict[str, dict[int, np.ndarray]],
                           n: int) -> None:
    """The live odometry of one play of the bag is the offline replay's, frame by frame, from its origin, on
    both topics; the motion (in VO units) is on vo/odometry/vo_units."""
    for msgs, by_stamp in ((odom, offline["vo/odometry"]), (vo_units, offline["vo/odometry/vo_units"])):
        assert len(msgs) == n
        assert [stamp_to_ns(m.header.stamp) for m in msgs] == sorted(by_stamp)
        for m in msgs:
            pose = odom_pose(m)
            assert np.all(np.isfinite(pose))
            np.testing.assert_allclose(pose, by_stamp[stamp_to_ns(m.header.stamp)], atol=1e-6)
    assert np.linalg.norm(odom_pose(vo_units[-1])[:3] - odom_pose(vo_units[0])[:3]) > 1.0  # it moved


def test_configure_activate_deactivate_cleanup_shutdown(ros: RosSession,
                                                        offline: dict[str, dict[int, np.ndarray]]) -> None:
    from lifecycle_msgs.msg import Transition

    n = bag_frame_count(BAG)
    probe = Probe(ros, "probe_lifecycle")
    still = bag_frames_rclpy(BAG, 10)  # published by the probe while the node is inactive
    later = bag_frames_rclpy(BAG, 20, shift_s=100)  # after a deactivate / activate: the same scene 100 s later
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS, module=LIFECYCLE) as node:
            # Unconfigured: the lifecycle services and the lifecycle status, no VO endpoints.
            assert probe.state() == "unconfigured", node.proc.stderr
            assert probe.spin_until(lambda: any(s["lifecycle_state"] == "unconfigured" for s in probe.summaries()))
            assert probe.node.count_publishers("/vo/odometry") == 0
            assert probe.node.count_subscribers("/camera/camera_info") == 0

            # Configure: inactive; the endpoints exist, images are counted and ignored.
            assert probe.change(Transition.TRANSITION_CONFIGURE)
            assert probe.state() == "inactive"
            assert probe.spin_until(lambda: probe.node.count_publishers("/vo/odometry") == 1
                                    and probe.pub_img.get_subscription_count() >= 1)
            probe.send_until(still, lambda: probe.ignored() >= len(still))
            probe.wait_further_summaries()
            assert not probe.odom and not probe.frame_statuses()
            inactive = probe.summaries()[-1]
            assert inactive["lifecycle_state"] == "inactive" and inactive["message"].startswith("inactive: ")

            # Activate: the whole bag, as the plain node and the offline replay give it.
            assert probe.change(Transition.TRANSITION_ACTIVATE)
            assert probe.state() == "active"
            send_calibration(probe, BAG)  # the first frames are not rejected if the player's camera_info is late
            _play(ros.env)
            assert probe.spin_until(lambda: len(probe.odom) >= n and len(probe.odom_vo_units) >= n
                                    and len(probe.frame_statuses()) >= n), len(probe.odom)
            _assert_equals_offline(probe.odom, probe.odom_vo_units, offline, n)
            assert [int(dict((kv.key, kv.value) for kv in s.values)["index"]) for s in probe.frame_statuses()] == \
                list(range(n))

            # Deactivate: the bag again, every frame reaches the node and is ignored; nothing comes out.
            assert probe.change(Transition.TRANSITION_DEACTIVATE)
            assert probe.state() == "inactive"
            ignored = probe.ignored()
            _play(ros.env)
            assert probe.spin_until(lambda: probe.ignored() >= ignored + n), (probe.ignored(), ignored)
            probe.wait_further_summaries()
            assert len(probe.odom) == len(probe.odom_vo_units) == n and len(probe.frame_statuses()) == n

            # Activate again (no cleanup): tracking restarts from the last pose, odometry continuous.
            assert probe.change(Transition.TRANSITION_ACTIVATE)
            last = odom_pose(probe.odom_vo_units[-1])  # VO units: the motion is on vo/odometry/vo_units
            probe.send(later)  # each once (the subscription matched long ago, reliable): one odometry each
            assert probe.spin_until(lambda: len(probe.odom) >= n + len(later)
                                    and len(probe.odom_vo_units) >= n + len(later)), len(probe.odom)
            assert probe.spin_until(lambda: len(probe.frame_statuses()) >= n + len(later))
            assert len(probe.odom[n:]) == len(later)
            resumed = probe.odom_vo_units[n:]
            assert len(resumed) == len(later)
            first_status = probe.frame_statuses()[n]
            assert "reactivated: tracking restarted from the last pose" in first_status.message
            assert stamp_to_ns(resumed[0].header.stamp) == stamp_to_ns(later[0][0].header.stamp)
            np.testing.assert_allclose(odom_pose(resumed[0])[:3], last[:3], atol=1e-6)
            assert np.linalg.norm(last[:3]) > 1.0  # held at the last pose, far from the origin
            assert all(np.all(np.isfinite(odom_pose(m))) for m in resumed)

            # Cleanup: the session is gone; configure + activate starts a new map from the origin.
            assert probe.change(Transition.TRANSITION_DEACTIVATE)
            assert probe.change(Transition.TRANSITION_CLEANUP)
            assert probe.state() == "unconfigured"
            assert probe.spin_until(lambda: probe.node.count_publishers("/vo/odometry") == 0
                                    and probe.node.count_subscribers("/camera/camera_info") == 0)
            assert probe.change(Transition.TRANSITION_CONFIGURE)
            assert probe.change(Transition.TRANSITION_ACTIVATE)
            before, statuses_before = len(probe.odom), len(probe.frame_statuses())
            assert len(probe.odom_vo_units) == before
            assert probe.spin_until(lambda: probe.node.count_publishers("/vo/odometry") == 1)
            send_calibration(probe, BAG)
            _play(ros.env)
            assert probe.spin_until(lambda: len(probe.odom) >= before + n and len(probe.odom_vo_units) >= before + n
                                    and len(probe.frame_statuses()) >= statuses_before + n), len(probe.odom)
            _assert_equals_offline(probe.odom[before:], probe.odom_vo_units[before:], offline, n)
            first = probe.frame_statuses()[statuses_before]
            assert NEW_MAP in first.message
            assert dict((kv.key, kv.value) for kv in first.values)["index"] == "0"
            assert probe.spin_until(lambda: probe.summaries()[-1]["configurations"] == "2")

            # Shutdown from active: finalized, the VO endpoints gone, the process still answers get_state.
            assert probe.change(Transition.TRANSITION_ACTIVE_SHUTDOWN)
            assert probe.state() == "finalized"
            assert probe.spin_until(lambda: probe.summaries()[-1]["message"].startswith("finalized"))
            assert probe.spin_until(lambda: probe.node.count_publishers("/vo/odometry") == 0
                                    and probe.node.count_subscribers("/camera/camera_info") == 0)
            assert len(probe.odom) == before + n
            assert not probe.change(Transition.TRANSITION_CONFIGURE)  # finalized is terminal
            assert node.proc.poll() is None
        assert node.proc.returncode == 0, node.stderr
        assert "Traceback" not in node.stderr
    finally:
        probe.close()


def test_bad_parameter_fails_configure_with_the_reason_and_can_be_fixed(ros: RosSession) -> None:
    from lifecycle_msgs.msg import Transition
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    probe = Probe(ros, "probe_lifecycle_bad")
    reason = "frontend='sift' (choose one of klt, orb)"
    try:
        with NodeProcess(ros.env, "-p", "frontend:=sift", "-p", "hardware_id:=front_cam", module=LIFECYCLE) as node:
            assert not probe.change(Transition.TRANSITION_CONFIGURE), node.proc.stderr
            assert probe.state() == "unconfigured"
            assert probe.spin_until(lambda: any(reason in s["configure_error"] for s in probe.summaries()))
            failed = next(s for s in probe.summaries() if reason in s["configure_error"])
            assert failed["level"] == 2 and failed["message"] == "unconfigured: configure failed"
            assert failed["lifecycle_state"] == "unconfigured" and failed["configurations"] == "0"
            assert probe.node.count_publishers("/vo/odometry") == 0

            # Unconfigured, the value can be fixed; configure checks it again and succeeds.
            request = SetParameters.Request(parameters=[Parameter("frontend", value="klt").to_parameter_msg()])
            (result,) = call_service(probe.executor, probe.set_client, request, WAIT_S).results
            assert result.successful, result.reason
            assert probe.change(Transition.TRANSITION_CONFIGURE)
            assert probe.state() == "inactive"
            assert probe.spin_until(lambda: probe.summaries()[-1]["lifecycle_state"] == "inactive"
                                    and probe.summaries()[-1]["configurations"] == "1")
            assert probe.summaries()[-1]["level"] == 0

            # Configured, a runtime change is checked as vo_node checks it.
            request = SetParameters.Request(parameters=[Parameter("frontend", value="sift").to_parameter_msg()])
            (refused,) = call_service(probe.executor, probe.set_client, request, WAIT_S).results
            assert not refused.successful and reason in refused.reason

            assert probe.change(Transition.TRANSITION_INACTIVE_SHUTDOWN)
            assert probe.state() == "finalized"
        errors = [line for line in node.stderr.splitlines() if "configure failed" in line]
        assert len(errors) == 1 and errors[0].startswith("[ERROR]") and reason in errors[0]
        assert "Traceback" not in node.stderr
    finally:
        probe.close()


def test_a_transition_the_state_has_not_is_refused_and_shutdown_from_unconfigured_finalizes(ros: RosSession) -> None:
    from lifecycle_msgs.msg import Transition

    probe = Probe(ros, "probe_lifecycle_shutdown")
    try:
        with NodeProcess(ros.env, module=LIFECYCLE) as node:
            assert probe.state() == "unconfigured", node.proc.stderr
            # rclpy's own service would raise (and the node die): the node answers success false instead.
            assert not probe.change(Transition.TRANSITION_ACTIVATE)
            assert probe.state() == "unconfigured"
            assert probe.change(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
            assert probe.state() == "finalized"
            assert probe.spin_until(lambda: bool(probe.summaries())
                                    and probe.summaries()[-1]["lifecycle_state"] == "finalized")
        assert node.proc.returncode == 0, node.stderr
        refused = [line for line in node.stderr.splitlines() if "refused in state unconfigured" in line]
        assert len(refused) == 1 and refused[0].startswith("[WARN]")
    finally:
        probe.close()


def test_vo_lifecycle_node_help_prints_the_parameters_and_never_starts_dds() -> None:
    """As vo_node's: run with a DDS environment that would fail (an invalid domain id), it still succeeds."""
    env = {**os.environ, "ROS_DOMAIN_ID": "not-a-domain", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    out = subprocess.run([sys.executable, "-m", "epi_vo.ros.lifecycle_node", "--help"], env=env, capture_output=True,
                         text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: vo_lifecycle_node")
    assert "/vo_node/change_state" in out.stdout
    for line in ("    max_features:", "    image_transport: auto", "    frontend: klt", "    tf_timeout_s:"):
        assert line in out.stdout
    assert "rcl" not in out.stderr.lower()
