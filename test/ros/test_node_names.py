"""Names and arguments the node cannot use: refused before anything is created, with one line naming them.

vo_node as a process: a topic parameter rcl would refuse (rclpy's own name validation), a frame name tf2
would refuse, a ``-p`` rule rcl cannot parse, all exit 2 with one line. vo_lifecycle_node: a configure that
fails says why (log, summary at ERROR) and leaves nothing behind, however often it is tried; a failure in
the middle of making the session (injected, in-process) undoes what was made, and a later configure works.

Every process gets this test's loopback-only domain (test/ros_fixtures.py) before rclpy starts.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest
from ros_fixtures import NodeProcess, ProbeBase, RosSession, call_service, rclpy_session

WAIT_S = 120.0  # bound on a wait for another process or DDS; it matters only when the condition never comes
BAD_TOPIC = "bad topic!"
BAD_TOPIC_LINE = ("wheel_odometry_topic='bad topic!' (not a valid ROS topic name: topic name must not contain "
                  "characters other than alphanumerics, '_', '~', '{', or '}')")


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


NAME_CASES = [
    (["-p", f"wheel_odometry_topic:={BAD_TOPIC}"], f"invalid vo_node parameters: {BAD_TOPIC_LINE}"),
    (["-p", "scale_source:=wheel_odometry", "-p", f"wheel_odometry_topic:={BAD_TOPIC}"],
     f"invalid vo_node parameters: {BAD_TOPIC_LINE}"),
    (["-p", "wheel_odometry_topic:=odom/{robot}"], "invalid vo_node parameters: wheel_odometry_topic='odom/{robot}' "
                                                   "(not a valid ROS topic name: unknown substitution: {robot})"),
    (["-p", "frame_id:=/odom", "-p", "child_frame_id:=base link"],
     "invalid vo_node parameters: frame_id='/odom' (not a frame name: tf2 frame ids must not start with '/'); "
     "child_frame_id='base link' (not a frame name: whitespace or a control character)"),
]
ARGUMENT_CASES = [
    (["-p", "queue_size:=[1,"], "the ROS arguments cannot be used: Couldn't parse parameter override rule: "
                                "'-p queue_size:=[1,'"),
    (["--params-file", "/nonexistent/params.yaml"], "the ROS arguments cannot be used: Couldn't parse params file: "
                                                    "'--params-file /nonexistent/params.yaml'"),
]


def _one_line_exit_2(ros: RosSession, module: str, args: list[str], line: str) -> None:
    program = "vo_lifecycle_node" if module.endswith("lifecycle_node") else "vo_node"
    proc = subprocess.run([sys.executable, "-m", module, "--ros-args", *args], env=ros.env, capture_output=True,
                          text=True, timeout=WAIT_S)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [f"{program}: error: {line}"]
    assert proc.stdout == ""


@pytest.mark.parametrize(("args", "line"), NAME_CASES)
def test_names_that_cannot_be_used_exit_2_with_one_line(ros: RosSession, args: list[str], line: str) -> None:
    _one_line_exit_2(ros, "epi_vo.ros.node", args, line)


@pytest.mark.parametrize(("args", "line"), ARGUMENT_CASES)
@pytest.mark.parametrize("module", ["epi_vo.ros.node", "epi_vo.ros.lifecycle_node"])
def test_ros_arguments_rcl_cannot_parse_exit_2_with_one_line(ros: RosSession, module: str, args: list[str],
                                                            line: str) -> None:
    _one_line_exit_2(ros, module, args, line)


def test_the_wheel_topic_is_relative_by_default_so_a_namespaced_node_reads_its_own(ros: RosSession) -> None:
    """Two robots in one graph: vo_node in /robot7 with wheel odometry and the default topic subscribes to
    /robot7/odom, not to a /odom every robot would share."""
    from rclpy.node import NodeNameNonExistentError

    probe = ProbeBase(ros, "probe_wheel_name")
    subscribed: dict[str, list[str]] = {}

    def has_wheel_subscription() -> bool:
        try:
            subscribed.update(probe.node.get_subscriber_names_and_types_by_node("vo_node", "/robot7"))
        except NodeNameNonExistentError:  # not discovered yet
            return False
        return "/robot7/camera/camera_info" in subscribed and any(t.endswith("odom") for t in subscribed)

    try:
        with NodeProcess(ros.env, "-r", "__ns:=/robot7", "-p", "scale_source:=wheel_odometry") as node:
            assert probe.spin_until(has_wheel_subscription, WAIT_S), (subscribed, node.proc.stderr)
        assert "Traceback" not in node.stderr
    finally:
        probe.close()
    assert subscribed["/robot7/odom"] == ["nav_msgs/msg/Odometry"]
    assert "/odom" not in subscribed


def test_a_node_stopped_while_it_starts_exits_quietly(ros: RosSession) -> None:
    """SIGINT (Ctrl-C, launch stopping a stack) can come while the node is still being made: an exit like one
    during spin, no traceback."""
    code = ("from epi_vo.ros.node_run import run_node\n"
            "def make():\n    raise KeyboardInterrupt\n"
            "run_node(make, 'vo_node', '', ['--ros-args'])\n")
    proc = subprocess.run([sys.executable, "-c", code], env=ros.env, capture_output=True, text=True, timeout=WAIT_S)
    assert (proc.returncode, proc.stderr) == (0, "")


class Probe(ProbeBase):
    def __init__(self, ros: RosSession, name: str) -> None:
        from lifecycle_msgs.srv import ChangeState

        super().__init__(ros, name)
        self.change_client = self.node.create_client(ChangeState, "/vo_node/change_state")

    def configure(self) -> bool:
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        request = ChangeState.Request()
        request.transition.id = Transition.TRANSITION_CONFIGURE
        return bool(call_service(self.executor, self.change_client, request, WAIT_S).success)

    def summaries(self) -> list[Any]:
        return [s for a in self.diag for s in a.status if s.name.endswith(": lifecycle")]


def test_a_bad_topic_fails_every_configure_with_the_reason_and_makes_nothing(ros: RosSession) -> None:
    probe = Probe(ros, "probe_bad_topic")
    tries = 3
    try:
        with NodeProcess(ros.env, "-p", "scale_source:=wheel_odometry", "-p", f"wheel_odometry_topic:={BAD_TOPIC}",
                         module="epi_vo.ros.lifecycle_node") as node:
            for _ in range(tries):
                assert not probe.configure(), node.proc.stderr
            n = len(probe.summaries())
            assert probe.spin_until(lambda: len(probe.summaries()) >= n + 2)
            last = probe.summaries()[-1]
            level = last.level[0] if isinstance(last.level, bytes) else int(last.level)
            assert level == 2 and last.message == "unconfigured: configure failed"
            assert {kv.key: kv.value for kv in last.values}["configure_error"] == \
                f"invalid vo_node parameters: {BAD_TOPIC_LINE}"
            for topic in ("/camera/camera_info", "/camera/image_raw", "/camera/image_raw/compressed"):
                assert probe.node.count_subscribers(topic) == 0, topic
            assert probe.node.count_publishers("/vo/odometry") == 0
        errors = [line for line in node.stderr.splitlines() if "configure failed" in line]
        assert len(errors) == tries and all(e.startswith("[ERROR]") and BAD_TOPIC_LINE in e for e in errors)
        assert "Traceback" not in node.stderr and node.proc.returncode == 0
    finally:
        probe.close()


def _entities(node: Any) -> tuple[int, int, int, int]:
    """The node's subscriptions, publishers, timers and services."""
    return (len(list(node.subscriptions)), len(list(node.publishers)), len(list(node.timers)),
            len(list(node.services)))


def test_a_configure_that_fails_half_way_undoes_what_it_made_and_a_later_one_works(
        ros: RosSession, monkeypatch: pytest.MonkeyPatch) -> None:
    from lifecycle_msgs.msg import State
    from rclpy.lifecycle import TransitionCallbackReturn
    from rclpy.parameter import Parameter

    import epi_vo.ros.node as node_module
    from epi_vo.core.diagnostics import DiagnosticLevel
    from epi_vo.ros.lifecycle_node import VoLifecycleNode

    def no_broadcaster(node: Any) -> Any:
        raise RuntimeError("injected: the TF broadcaster cannot be made")

    node = VoLifecycleNode(context=ros.context, parameter_overrides=[Parameter("image_transport", value="compressed")])
    try:
        before = _entities(node)
        monkeypatch.setattr(node_module, "make_tf_broadcaster", no_broadcaster)
        for _ in range(3):
            assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
            assert node._state_machine.current_state[0] == State.PRIMARY_STATE_UNCONFIGURED
            assert _entities(node) == before
        summary = node._lifecycle_status()
        assert summary.level == DiagnosticLevel.ERROR and summary.message == "unconfigured: configure failed"
        assert dict(summary.values)["configure_error"] == ("the session could not be started: RuntimeError: "
                                                           "injected: the TF broadcaster cannot be made")
        monkeypatch.undo()
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert node._state_machine.current_state[0] == State.PRIMARY_STATE_INACTIVE
        topics = {s.topic_name for s in node.subscriptions}
        assert {"/camera/camera_info", "/camera/image_raw/compressed"} <= topics
        assert _entities(node)[0] == before[0] + 2
        assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
        assert _entities(node) == before
    finally:
        node.destroy_node()
