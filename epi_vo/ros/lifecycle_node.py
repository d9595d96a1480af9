"""``vo_lifecycle_node``: ``vo_node`` as a managed (lifecycle) node, driven through the standard
``/<node>/change_state`` and ``/<node>/get_state`` services (``ros2 lifecycle set /vo_node configure``, a
lifecycle manager, or launch's lifecycle events).

The work is :class:`~epi_vo.ros.node.VoNodeBase`'s, the same as vo_node's: configure starts its session,
cleanup ends it. What each state means here:

* **unconfigured** (at start, after cleanup, after a failed configure): no camera subscriptions, no VO
  publishers, no worker. Only the ``<node>: lifecycle`` status on ``/diagnostics`` once a second, saying
  the state (and why the last configure failed, at ERROR).
* **configure**: declares the parameters (at the first configure; later ones read their current values)
  and checks them all, as vo_node does at start-up. A bad value fails the transition (the service answers
  ``success: false``), the state stays unconfigured, and the reason, naming every bad parameter, is
  logged at ERROR and put in the lifecycle status. A parameter that is not read-only can be fixed with
  ``set_parameters`` while unconfigured (nothing is checked until configure) and configure tried again.
  A configure that fails after the checks (rcl refuses something the session makes) undoes what it made:
  failed configures leave no subscription, publisher or timer behind, and say why in the same way.
  Then the session is made: pipeline, subscriptions, *lifecycle* publishers (silent until activate),
  ``vo/reset``, watchdog: the node is **inactive**.
* **inactive**: images that arrive are counted and ignored (the lifecycle status says how many); nothing is
  published on ``vo/*``; the watchdog is silent (not receiving on purpose).
* **activate**: the publishers are enabled, then images are processed. After a deactivate, tracking
  restarts from the last pose: odometry stays continuous, the first frame's status says "reactivated".
* **deactivate**: no more images taken; frames still queued are dropped (counted as ignored) and the
  frame in flight is finished before the publishers are disabled, so nothing is published afterwards.
* **cleanup**: the session is destroyed (pipeline, map, path, pose, counters, subscriptions,
  publishers). A following configure + activate starts a **new map at the origin** (frame index 0), as
  a fresh node would; its first frame's status says so. (A pause that keeps the pose is deactivate.)
* **shutdown** (from unconfigured, inactive or active): as cleanup, then **finalized**; one last lifecycle
  status says so. The process stays up (get_state answers ``finalized``) until it is stopped, as rclcpp's
  lifecycle nodes do; launch or a supervisor decides what follows.
"""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter

from epi_vo.core.diagnostics import DiagnosticStatusRecord
from epi_vo.core.errors import ConfigError
from epi_vo.core.health import lifecycle_status
from epi_vo.ros.node import VoNodeBase
from epi_vo.ros.node_params import declare_all, effective_parameters_text, warn_undeclared_overrides
from epi_vo.ros.node_run import run_node
from epi_vo.ros.node_tf import TransformLookup

__all__ = ["VoLifecycleNode", "main"]

RCLError = rclpy_implementation.RCLError
NEW_MAP_AFTER_CLEANUP = "configured again after cleanup: new map from the origin"


class VoLifecycleNode(VoNodeBase, LifecycleNode):
    """vo_node's pipeline behind the ROS 2 lifecycle (see the module doc for each state).

    ``tf_lookup`` replaces the tf2_ros lookup of the camera extrinsic, as in :class:`~epi_vo.ros.node.VoNode`.
    """

    def __init__(self, *, tf_lookup: TransformLookup | None = None, **kwargs: Any) -> None:
        super().__init__("vo_node", **kwargs)
        self._tf_lookup = tf_lookup
        self._state = "unconfigured"
        self._session = False  # a configured session exists (inactive or active)
        self._configurations = 0  # successful configures so far
        self._configure_error = ""  # why the last configure failed ('' once one succeeds)
        # /diagnostics is published in every state (the session uses this publisher too): a monitor sees
        # an unconfigured or inactive node as such rather than as a silent one.
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.add_on_set_parameters_callback(self._on_set_parameters_managed)
        self._guard_change_state()
        self._state_timer = self.create_timer(1.0, self._publish_lifecycle_alone,
                                              clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info("vo_node (managed) is unconfigured: configure it to declare and check its "
                               "parameters, activate it to track")

    def _guard_change_state(self) -> None:
        """rclpy's change_state service raises on a transition the current state does not have (activate
        while unconfigured, anything once finalized), and the exception ends the node's spin: the node
        would die of a wrong ``ros2 lifecycle set``. Answer ``success: false`` instead, as rclcpp does."""
        # rclpy keeps the service in a private attribute: leave it as it is when a future rclpy renames it.
        service = getattr(self, "_service_change_state", None)
        if service is None:
            return
        answer = service.callback

        def guarded(request: Any, response: Any) -> Any:
            try:
                return answer(request, response)
            except RCLError as exc:
                self.get_logger().warning(f"transition {request.transition.id} {request.transition.label!r} "
                                          f"refused in state {self._state}: {exc}")
                response.success = False
                return response

        service.callback = guarded

    # -- transitions --------------------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            cfg, opts = declare_all(self)
        except ConfigError as exc:
            return self._configure_failed(str(exc))
        if not self._configurations:
            warn_undeclared_overrides(self)
        self.get_logger().info(effective_parameters_text(cfg, opts))
        announce = NEW_MAP_AFTER_CLEANUP if self._configurations else ""
        try:
            self._start_session(cfg, opts, self._tf_lookup, active=False, announce=announce)
        except Exception as exc:  # rcl refused something the session makes (or a defect): undo what it made
            self._stop_session(timeout_s=2.0)
            return self._configure_failed(f"the session could not be started: {type(exc).__name__}: {exc}")
        self._session = True
        self._configurations += 1
        self._configure_error = ""
        self._state = "inactive"
        self.get_logger().info("configured (inactive): activate to track")
        return super().on_configure(state)

    def _configure_failed(self, reason: str) -> TransitionCallbackReturn:
        """The node stays unconfigured, as before the attempt; the reason (one line) is logged and in the
        lifecycle status (ERROR) until a configure succeeds."""
        self._configure_error = " ".join(reason.split())
        self.get_logger().error(f"configure failed, the node stays unconfigured: {self._configure_error}")
        return TransitionCallbackReturn.FAILURE

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = super().on_activate(state)  # the publishers first, then the frames
        self._resume()
        self._state = "active"
        self.get_logger().info("active: tracking")
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        dropped = self._pause()
        self._state = "inactive"
        self.get_logger().info(f"inactive: images are ignored ({dropped} queued frames dropped)")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._end_session()
        self._state = "unconfigured"
        self.get_logger().info("cleaned up (unconfigured): the next configure starts a new map from the origin")
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._end_session()
        self._state = "finalized"
        self.destroy_timer(self._state_timer)
        self._publish_lifecycle_alone()  # the last status: finalized
        self.get_logger().info(f"shut down from {state.label}: finalized")
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        # A transition raised (a defect): drop the session so the node is back to unconfigured, clean.
        self.get_logger().error(f"error in a transition from {state.label}: back to unconfigured")
        self._end_session()
        self._state = "unconfigured"
        return super().on_error(state)

    def _end_session(self) -> None:
        if self._session:
            self._pause()
            self._stop_session()
            self._session = False

    # -- VoNodeBase hooks -----------------------------------------------------------------------------------
    def _create_output_publisher(self, msg_type: Any, topic: str, depth: int) -> Any:
        return self.create_lifecycle_publisher(msg_type, topic, depth)

    def _destroy_output_publisher(self, publisher: Any) -> None:
        self.destroy_lifecycle_publisher(publisher)  # a plain one (TF's) is destroyed as such

    def _extra_statuses(self) -> tuple[DiagnosticStatusRecord, ...]:
        return (self._lifecycle_status(),)

    def _lifecycle_status(self) -> DiagnosticStatusRecord:
        ignored = self._n_ignored if self._session else 0
        hardware_id = self.get_parameter("hardware_id").value if self.has_parameter("hardware_id") else ""
        return lifecycle_status(self.get_fully_qualified_name(), hardware_id or "unknown camera", self._state,
                                self._configure_error, (("configurations", str(self._configurations)),
                                                        ("frames_ignored_inactive", str(ignored))))

    # -- parameters and diagnostics without a session -----------------------------------------------------
    def _on_set_parameters_managed(self, parameters: list[Parameter]) -> SetParametersResult:
        """Configured: checked as vo_node checks a runtime change. Unconfigured: accepted (configure checks
        every value), so a bad value can be fixed before the next configure."""
        if self._session:
            return self._on_set_parameters(parameters)
        return SetParametersResult(successful=True, reason="")

    def _publish_lifecycle_alone(self) -> None:
        """The lifecycle status while there is no session (the session's /diagnostics carry it while configured)."""
        if self._session:
            return
        self._pub_diag.publish(self._array([self._lifecycle_status()]))

    def _input_values(self) -> tuple[tuple[str, str], ...]:
        return super()._input_values() if self._session else ()

    def destroy_node(self) -> None:
        if self._session:
            self._pause(timeout_s=2.0)
            self._stop_worker(timeout_s=2.0)
        super().destroy_node()


HELP_TEXT = """usage: vo_lifecycle_node [--ros-args --params-file FILE -p NAME:=VALUE -r FROM:=TO ...]

Monocular visual odometry node (epi_vo), managed: vo_node behind the ROS 2 lifecycle. It starts
unconfigured; drive it through /vo_node/change_state (`ros2 lifecycle set /vo_node configure`, then
`activate`; `deactivate` pauses, `cleanup` forgets the map, `shutdown` finalizes). Configure declares
and checks the parameters below (a bad one fails configure, naming it); while active it subscribes
camera/image_raw (+ /compressed) and camera/camera_info and publishes vo/odometry, vo/points, vo/path;
/diagnostics in every state; service vo/reset while configured.
Its parameters, with their defaults (the same file as `epi-vo params` and config/epi_vo.yaml):

"""


def main(args: list[str] | None = None) -> None:
    run_node(VoLifecycleNode, "vo_lifecycle_node", HELP_TEXT, args)


if __name__ == "__main__":
    main()
