"""``set_pose`` and ``reset_pose`` of ``vo_node``: setting where base is in odom from outside.

``set_pose`` (geometry_msgs/PoseWithCovarianceStamped, relative name, reliable) is robot_localization's
input of the same name: the pose of ``child_frame_id`` in ``frame_id`` with its covariance.
``reset_pose`` (std_srvs/Trigger, like ``vo/reset``: the answer says what will happen) sets the identity
with zero covariance, where the odometry starts. The callbacks only check the message
(``epi_vo.io.set_pose``) and queue the request; the worker applies it between two frames
(``FrameHandler.set_pose``), so no frame is half-way when the pose moves. A refused message is logged at
WARN and said in the next frame's record and status (``set_pose_refused``).
"""

from __future__ import annotations

from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from epi_vo.io.msgconv import stamp_to_ns
from epi_vo.io.set_pose import PoseRequest, SetPoseError, identity_request, pose_request
from epi_vo.runner.frames import FrameHandler

SET_POSE_TOPIC, RESET_POSE_SERVICE = "set_pose", "reset_pose"


class PoseSetting:
    """The pose inputs of a VO session (mixed into ``VoNodeBase``: it uses the node's methods, options and
    ``_cv`` lock)."""

    _pose_pending: list[PoseRequest | str]

    def _create_pose_inputs(self) -> None:
        """The set_pose subscription and the reset_pose service of a session."""
        self._pose_pending = []  # requests and refusals, in arrival order, for the worker
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(PoseWithCovarianceStamped, SET_POSE_TOPIC, self._on_set_pose, qos)
        self.create_service(Trigger, RESET_POSE_SERVICE, self._on_reset_pose)

    def _queue_pose(self, item: PoseRequest | str) -> None:
        with self._cv:
            self._pose_pending.append(item)
            self._cv.notify()

    def _on_set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        try:
            request = pose_request(msg, self.opts.frame_id, SET_POSE_TOPIC)
        except SetPoseError as exc:
            self.get_logger().warning(f"set_pose refused: {exc}")
            self._queue_pose(str(exc))
            return
        xyz = " ".join(f"{v:.3f}" for v in request.T_odom_base[:3, 3])
        self.get_logger().info(f"set_pose: base at {xyz} m in {self.opts.frame_id} from the next frame")
        self._queue_pose(request)

    def _on_reset_pose(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        now_ns = stamp_to_ns(self.get_clock().now().to_msg())
        self._queue_pose(identity_request(now_ns, RESET_POSE_SERVICE))
        response.success = True
        response.message = f"base is at the origin of {self.opts.frame_id} from the next frame"
        return response

    def _take_pose_requests(self) -> list[PoseRequest | str]:
        """The requests and refusals since the last frame (call with ``_cv`` held)."""
        taken, self._pose_pending = self._pose_pending, []
        return taken


def apply_pose_requests(handler: FrameHandler, items: list[PoseRequest | str]) -> None:
    """Hand the queued requests to the frame handler (worker thread, between two frames): the last one
    wins (each replaces the pose); the refusals are said in the next frame's record."""
    refused = [item for item in items if isinstance(item, str)]
    requests = [item for item in items if not isinstance(item, str)]
    if refused:
        handler.note("set_pose_refused", "; ".join(refused))
    if requests:
        last = requests[-1]
        handler.set_pose(last.T_odom_base, last.covariance, last.record())
