"""``vo_node``: the ROS 2 front door. Wiring only: each frame goes through the same
:class:`~epi_vo.runner.frames.FrameHandler` as in ``epi-vo replay`` (decode, process, outputs as records), so
a bag gives the same outputs live and offline; the node turns those records into messages. Of the
pipeline's two front doors, this is the only one that imports rclpy (the other ROS-facing tools, play,
monitor and live_bench, do too; the core never does).

Topics (relative names, so namespaces and remapping work):
  in:  ``camera/image_raw`` (sensor_msgs/Image) and/or ``camera/image_raw/compressed`` (CompressedImage):
       ``image_transport: auto`` subscribes to both and keeps whichever delivers first (logged and in the
       diagnostics), ``raw`` / ``compressed`` to one; ``camera/camera_info``
  out: ``vo/odometry`` (nav_msgs/Odometry, odom -> base_link, REP-105: what a filter may fuse; metres once a
       metric scale source is established, else the position held with the "unknown" variance and the
       orientation as estimated), ``vo/odometry/vo_units`` (the motion in VO units while there are no metres,
       odom_vo_units -> base_link_vo_units: frames in no TF tree; ``epi_vo.runner.outputs``), ``vo/points``
       (PointCloud2 of the points triangulated at keyframes, in odom, or odom_vo_units in VO units),
       ``vo/path`` (bounded nav_msgs/Path, the same frame rule), ``vo/frame_status`` (DiagnosticArray per
       frame: ``<fully qualified node name>: tracking``, the frame record), ``/diagnostics`` (once a second:
       ``<node>: tracking``, ``input``, ``extrinsic``, ``scale``; ``epi_vo.ros.node_diagnostics``),
       ``vo/debug_image`` (off by default); TF odom -> base_link when
       tf2_ros is importable.
  srv: ``vo/reset`` (std_srvs/Trigger): restart tracking from the last pose.

Camera extrinsic: TF ``child_frame_id <- image frame_id`` when tf2_ros is importable, else the
``camera_xyz`` / ``camera_rpy`` parameters (``epi_vo.ros.node_tf``). Parameters: declared from VoConfig and
NodeOptions (``epi_vo.ros.node_params``); a pipeline knob changed at runtime is validated as at start-up
and applied at the next frame (a new map from the last pose), a parameter that needs a restart is
read-only. Diagnostics: every DiagnosticArray is stamped with the node's clock (ROS time, simulated
under use_sim_time); ages (image staleness, the watchdog) are measured on the steady clock, and the
watchdog and /diagnostics timers run on it, so they keep reporting when a simulated clock stops.

The wiring is :class:`VoNodeBase`, shared with the managed variant ``vo_lifecycle_node``
(``epi_vo.ros.lifecycle_node``), which runs the same session between configure and cleanup.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_srvs.srv import Trigger

from epi_vo.core.config import ScaleSourceKind, VoConfig, live_advice
from epi_vo.core.debug_image import draw_matches
from epi_vo.core.decisions import Decision
from epi_vo.core.errors import clipped
from epi_vo.core.health import TrackingHealth
from epi_vo.core.odometry import T_base_cam_from_params
from epi_vo.io import msgconv
from epi_vo.io.association import Ready
from epi_vo.io.frame_queue import NO_CAMERA_INFO_WAIT_S, FrameQueue
from epi_vo.io.msgconv import WheelMessage
from epi_vo.io.node_options import ImageTransport, NodeOptions, QosReliability, changed_names
from epi_vo.ros.node_diagnostics import NodeDiagnostics
from epi_vo.ros.node_params import check_change, declare_all, effective_parameters_text, warn_undeclared_overrides
from epi_vo.ros.node_run import (
    bgr_image_msg,
    header_msg,
    odometry_msg,
    point_cloud_msg,
    run_node,
    stamp_msg,
    transform_msg,
)
from epi_vo.ros.node_tf import Extrinsic, ExtrinsicResolver, TransformLookup, make_tf2_lookup, make_tf_broadcaster
from epi_vo.runner.frames import FrameHandler, FrameInput, HandledFrame
from epi_vo.runner.outputs import OutputFrames, OutputMaker, PathRecord

__all__ = ["NodeOptions", "VoNode", "main"]

RAW_TOPIC, COMPRESSED_TOPIC = "camera/image_raw", "camera/image_raw/compressed"
# Wheel messages waiting for the worker, which takes them at every frame and whenever woken: reached only
# when it is stuck in one frame (100 s at 100 Hz); the oldest half is then dropped and counted.
WHEEL_PENDING_MAX = 10000
RELIABILITY_POLICIES = {QosReliability.BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT,
                        QosReliability.RELIABLE: ReliabilityPolicy.RELIABLE}


class VoNodeBase(NodeDiagnostics):
    """The VO wiring shared by ``vo_node`` (:class:`VoNode`) and ``vo_lifecycle_node``
    (``epi_vo.ros.lifecycle_node``): mixed into an rclpy Node (it calls the node's own methods).

    One *session* is one configured life: :meth:`_start_session` makes the pipeline, the subscriptions,
    publishers, service and timers and starts the worker thread; :meth:`_stop_session` stops the worker
    and destroys what the session made, so a new session starts from nothing (a new map at the origin).
    While the session is not active (:meth:`_pause`), images are counted and ignored and the watchdog is
    silent; :meth:`_resume` takes images again, tracking restarting from the last pose.
    """

    def _start_session(self, cfg: VoConfig, opts: NodeOptions, tf_lookup: TransformLookup | None = None, *,
                       active: bool = True, announce: str = "") -> None:
        """Everything one configured life needs; ``announce`` is told in the first frame's reason."""
        self.cfg, self.opts = cfg, opts
        self._cfg_wanted = self.cfg  # the latest accepted config; the worker applies it at the next frame
        self._entities_before = self._entities()
        self._worker: threading.Thread | None = None
        self._status_name = self.get_fully_qualified_name()
        T_params = T_base_cam_from_params(self.opts.camera_xyz, self.opts.camera_rpy)
        # The per-frame rule (decode, process, outputs) is the replay's: the node only turns its records into
        # messages. Until the extrinsic is resolved, the parameters' stands (no frame is processed before).
        self._handler = FrameHandler(
            self.cfg, OutputFrames(self.opts.frame_id, self.opts.child_frame_id, self.opts.map_frame_id), T_params,
            path_max_length=self.opts.path_max_length, status_name=self._status_name, announce=announce)
        for advice in live_advice(self.cfg):
            self.get_logger().warning(advice)
        lookup = tf_lookup if tf_lookup is not None else make_tf2_lookup(self)
        self._resolver = ExtrinsicResolver(
            lookup, self.opts.child_frame_id, self.opts.tf_timeout_s, T_params,
            f"camera_xyz={list(self.opts.camera_xyz)} camera_rpy={list(self.opts.camera_rpy)} parameters")
        self._extrinsic: Extrinsic | None = None
        self._waiting = ""  # what the worker waits for before the first frame ('' when nothing)
        self._frames = FrameQueue(max_frames=self._max_frames(opts), max_bytes=self._max_bytes(opts),
                                  camera_info_wait_s=opts.camera_info_wait_s, no_info_wait_s=NO_CAMERA_INFO_WAIT_S)
        self._overflow_reported = 0  # the frame queue's overflow count at the last summary
        self._lock = threading.Lock()  # guards the frame queue, the wheel messages and the counters
        self._cv = threading.Condition(self._lock)
        self._reset_reason = ""  # a restart asked for (vo/reset, a re-activation), done by the worker
        self._running = True
        self._active = active  # images are processed only while active (always, in vo_node)
        self._busy = False  # the worker is processing a frame
        self._n_processed = self._n_ignored = 0
        # vo/path's poses as messages, the newest appended per frame (the handler's window, in its frame)
        self._path: collections.deque[PoseStamped] = collections.deque(maxlen=self.opts.path_max_length)
        self._path_frame = ""
        self._path_published = 0.0
        self._arrived_s: float | None = None  # steady clock arrival of the frame in flight (latency figure)
        self._last_latency_ms = math.nan
        # Wheel messages in arrival order, handed to the pipeline by the worker
        self._wheel_pending: list[WheelMessage] = []
        self._wheel_received = self._wheel_lost = 0  # wheel messages, and those the worker never took (stalled)
        self._camera_frame = ""  # header.frame_id of the first image
        self._tracking = TrackingHealth()  # the frames since /diagnostics was last published
        self._wheel_topic_name = ""
        self._changes: list[str] = []  # runtime changes applied, for the summary

        in_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.opts.qos_depth,
                            reliability=RELIABILITY_POLICIES[self.opts.qos_reliability])
        self._image_subs: dict[ImageTransport, Any] = {}
        if self.opts.image_transport in (ImageTransport.AUTO, ImageTransport.RAW):
            self._image_subs[ImageTransport.RAW] = self.create_subscription(Image, RAW_TOPIC, self._on_image, in_qos)
        if self.opts.image_transport in (ImageTransport.AUTO, ImageTransport.COMPRESSED):
            self._image_subs[ImageTransport.COMPRESSED] = self.create_subscription(
                CompressedImage, COMPRESSED_TOPIC, self._on_image, in_qos)
        self._image_topics = {k: sub.topic_name for k, sub in self._image_subs.items()}
        # The transport in use: None until the first image under AUTO
        self._transport: ImageTransport | None = \
            None if self.opts.image_transport is ImageTransport.AUTO else self.opts.image_transport
        self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, in_qos)
        if self.cfg.scale_source is ScaleSourceKind.WHEEL_ODOMETRY:
            wheel_sub = self.create_subscription(Odometry, self.cfg.wheel_odometry_topic, self._on_wheel_odometry,
                                                 QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100))
            self._wheel_topic_name = wheel_sub.topic_name
            self.get_logger().info(f"metric scale from wheel odometry on {self._wheel_topic_name}")
        self._pub_odom = self._create_output_publisher(Odometry, "vo/odometry", 10)
        self._pub_odom_vo_units = self._create_output_publisher(Odometry, "vo/odometry/vo_units", 10)
        self._pub_points = self._create_output_publisher(PointCloud2, "vo/points", 10)
        self._pub_path = self._create_output_publisher(Path, "vo/path", 10)
        self._pub_frame_status = self._create_output_publisher(DiagnosticArray, "vo/frame_status", 10)
        if getattr(self, "_pub_diag", None) is None:  # the managed node has one of its own, for every state
            self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._pub_debug = self._create_output_publisher(Image, "vo/debug_image", 2) \
            if self.opts.publish_debug_image else None
        self.create_service(Trigger, "vo/reset", self._on_reset)
        self._tf = None
        if self.opts.publish_tf:
            self._tf, why = make_tf_broadcaster(self)
            if self._tf is None:
                also = f" (nor {self.opts.map_frame_id} -> {self.opts.frame_id})" if self.opts.map_frame_id else ""
                self.get_logger().warning(f"publish_tf is true but no TF {self.opts.frame_id} -> "
                                          f"{self.opts.child_frame_id}{also} is broadcast: {why} (install tf2_ros, "
                                          "part of every ROS 2 install; vo/odometry is published either way)")
        if self.opts.map_frame_id and self._tf is None:
            self.get_logger().warning(f"map_frame_id is '{self.opts.map_frame_id}': vo/odometry stays continuous, and "
                                      "the windowed adjustment's corrections are in no published pose without the "
                                      f"{self.opts.map_frame_id} -> {self.opts.frame_id} TF (publish_tf and tf2_ros)")
        # Both timers on the steady clock: with use_sim_time a ROS-time timer stops with the simulated clock.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(0.5, self._watchdog, clock=steady)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self._worker = threading.Thread(target=self._work, name="vo_worker", daemon=True)
        self._worker.start()

    @staticmethod
    def _max_frames(opts: NodeOptions) -> int | None:
        return None if opts.process_every_frame else opts.queue_size

    @staticmethod
    def _max_bytes(opts: NodeOptions) -> int:
        return int(opts.queue_max_mb * 1e6)

    def _create_output_publisher(self, msg_type: Any, topic: str, depth: int) -> Any:
        """A publisher of the VO outputs (odometry, points, path, debug image): a plain one here, a lifecycle
        publisher (silent unless active) in the managed node."""
        return self.create_publisher(msg_type, topic, depth)

    def _destroy_output_publisher(self, publisher: Any) -> None:
        self.destroy_publisher(publisher)

    def _entities(self) -> dict[str, set[Any]]:
        return {"subscriptions": set(self.subscriptions), "publishers": set(self.publishers),
                "services": set(self.services), "timers": set(self.timers)}

    def _stop_worker(self, timeout_s: float) -> None:
        with self._cv:
            self._running = False
            self._cv.notify_all()
        if self._worker is not None:
            self._worker.join(timeout=timeout_s)

    def _stop_session(self, timeout_s: float = 10.0) -> None:
        """Stop the worker (bounded wait for a frame in flight) and destroy what the session made (its
        subscriptions, publishers, service, timers, the TF listener's): the node is as before the session.
        Also undoes a session whose start failed half-way (nothing it made is left behind)."""
        if self._worker is not None:
            self._stop_worker(timeout_s)
        now, before = self._entities(), self._entities_before
        for sub in now["subscriptions"] - before["subscriptions"]:
            self.destroy_subscription(sub)
        for pub in now["publishers"] - before["publishers"]:
            self._destroy_output_publisher(pub)
        for srv in now["services"] - before["services"]:
            self.destroy_service(srv)
        for timer in now["timers"] - before["timers"]:
            self.destroy_timer(timer)

    def _pause(self, timeout_s: float = 10.0) -> int:
        """Stop taking images: queued frames are dropped (counted as ignored) and the frame in flight, if any,
        is finished (bounded wait), so nothing is published after this returns. The frames dropped."""
        with self._cv:
            self._active = False
            dropped = len(self._frames)
            self._n_ignored += self._frames.clear()  # images waiting for their camera_info are dropped too
            deadline = time.monotonic() + timeout_s
            while self._busy and time.monotonic() < deadline:
                self._cv.wait(timeout=0.05)
        return dropped

    def _resume(self) -> None:
        """Take images again; after a pause, tracking restarts from the last pose (a new map, no jump)."""
        with self._cv:
            self._active = True
            if self._n_processed:
                self._reset_reason = "reactivated: tracking restarted from the last pose"

    # -- parameters ---------------------------------------------------------------------------------
    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """A runtime change: validated as at start-up; pipeline knobs are applied at the next frame."""
        with self._lock:
            result, cfg, opts = check_change(self._cfg_wanted, self.opts, parameters)
            if result.successful:
                self._cfg_wanted, self.opts = cfg, opts
                self._frames.set_limits(self._max_frames(opts), self._max_bytes(opts))
        if result.successful:
            names = ", ".join(f"{p.name}={p.value!r}" for p in parameters)
            self.get_logger().info(f"parameters accepted: {names} (pipeline knobs apply at the next frame)")
        else:
            self.get_logger().warning(f"parameters {result.reason}")
        return result

    # -- input ----------------------------------------------------------------------------------------
    def _on_image(self, msg: Image | CompressedImage) -> None:
        if not self._active:  # a managed node that is not active: counted, not processed
            with self._lock:
                self._n_ignored += 1
            return
        transport = ImageTransport.COMPRESSED if isinstance(msg, CompressedImage) else ImageTransport.RAW
        if transport is not self._transport and not self._choose_transport(transport):
            return
        stamp = msgconv.stamp_to_ns(msg.header.stamp)
        with self._cv:
            if not self._camera_frame:
                self._camera_frame = clipped(str(msg.header.frame_id))  # in every status: bounded
            if self._frames.add_image(stamp, msg, len(msg.data), time.monotonic()):
                self._cv.notify()

    def _choose_transport(self, transport: ImageTransport) -> bool:
        """image_transport auto: the first transport to deliver is kept, the other subscription dropped."""
        if self._transport is not None:  # already chosen: a message of the other one still in flight
            return False
        self._transport = transport
        other = ImageTransport.RAW if transport is ImageTransport.COMPRESSED else ImageTransport.COMPRESSED
        sub = self._image_subs.pop(other, None)
        if sub is not None:
            self.destroy_subscription(sub)
        self.get_logger().info(f"image_transport auto: using {transport} images from "
                               f"{self._image_topics[transport]} (the first to arrive)")
        return True

    def _on_camera_info(self, msg: CameraInfo) -> None:
        if not self._active:  # not listening (managed node): the association starts afresh at activation
            return
        with self._cv:
            if self._frames.add_info(msgconv.stamp_to_ns(msg.header.stamp), msg):
                self._cv.notify()

    def _on_wheel_odometry(self, msg: Odometry) -> None:
        """Queued in arrival order for the worker, which hands them to the pipeline: which are used, and
        why the others are not, is the pipeline's rule (``WheelOdometry.add``), the same as the replay's."""
        if not self._active:
            return
        sample = msgconv.odometry_position(msg)
        with self._cv:
            self._wheel_received += 1
            self._wheel_pending.append(sample)
            if len(self._wheel_pending) > WHEEL_PENDING_MAX:  # the worker is stalled: keep the newest
                self._wheel_lost += len(self._wheel_pending) - WHEEL_PENDING_MAX // 2
                del self._wheel_pending[:-(WHEEL_PENDING_MAX // 2)]
            self._cv.notify()

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._cv:
            self._reset_reason = "reset service called: tracking restarted from the last pose"
        response.success = True
        response.message = "tracking restarts at the next frame, from the last pose"
        return response

    # -- processing -------------------------------------------------------------------------------------
    @property
    def _converter(self) -> OutputMaker:
        """The outputs' mounting and map -> odom (``T_base_cam``, ``T_map_odom``), for the diagnostics."""
        return self._handler.output

    def _work(self) -> None:
        while True:
            with self._cv:
                while self._running and not len(self._frames) and not self._wheel_pending:
                    self._cv.wait(timeout=0.2)
                if not self._running:
                    return
                wheel, self._wheel_pending = self._wheel_pending, []
                head, item = self._frames.peek(), None
                # Before the first frame: the camera extrinsic (TF or parameters); the frame waits.
                if head is not None and self._extrinsic is not None:
                    item = self._frames.pop()
                    self._busy = True
                    reset, self._reset_reason = self._reset_reason, ""
                    wanted = self._cfg_wanted
            if item is not None and wanted is not self.cfg:
                self._apply_config(wanted)
            for stamp_ns, xyz in wheel:  # the pipeline is only touched by this thread
                self._handler.add_wheel_odometry(stamp_ns, xyz)
            if head is None:
                continue
            if item is None:
                self._resolve_extrinsic(head.image.header.frame_id)
                continue
            self._arrived_s = item.arrived_s
            if reset:
                self._handler.reset(reset)
            try:
                self._process(item)
            except Exception as exc:  # never let one frame kill the node; say what happened
                # Not an input problem (those are records): a defect. Tracking restarts from the held pose
                # and the status says it was an internal error.
                self.get_logger().error(f"frame at {item.stamp_ns * 1e-9:.6f} s failed: {exc!r}")
                self._publish(self._handler.internal_error(self._frame_input(item), exc, self._hardware_id()))
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def _resolve_extrinsic(self, frame_id: str) -> None:
        """One poll of the extrinsic (worker thread); while TF is awaited, frames queue (or are dropped as
        in live mode) and the diagnostics say what is awaited."""
        now = time.monotonic()
        extrinsic = self._resolver.poll(frame_id, now)
        if extrinsic is None:
            if not self._waiting:
                self.get_logger().info(f"waiting up to tf_timeout_s={self.opts.tf_timeout_s:g} s for TF "
                                       f"{self.opts.child_frame_id} <- {frame_id}")
            self._waiting = self._resolver.waiting_text(now)
            with self._cv:
                if self._running:
                    self._cv.wait(timeout=0.05)
            return
        self._waiting = ""
        self._handler.set_mounting(extrinsic.T_base_cam)  # the odometry, and the floor along the up it declares
        self._extrinsic = extrinsic
        (self.get_logger().warning if extrinsic.warn else self.get_logger().info)(extrinsic.text)

    def _apply_config(self, cfg: VoConfig) -> None:
        """A runtime change, between two frames (worker thread): a new pipeline with the new config,
        anchored at the pose (and covariance) the old one reached, so odometry stays continuous. Like a
        reset, the next frame starts a new map."""
        changed = changed_names(self.cfg, cfg)
        index = self._handler.last_pose.index
        text = ", ".join(changed) or "no knob changed"
        self._handler.apply_config(cfg, f"parameters changed ({text}): new map from the last pose")
        for advice in live_advice(cfg):
            self.get_logger().warning(advice)
        self.cfg = cfg
        self._changes.append(f"{text} (from frame {index + 1})")
        self.get_logger().info(f"parameters applied at frame {index + 1}: {text}; tracking restarts from the "
                               "last pose")

    def _frame_input(self, item: Ready) -> FrameInput:
        return FrameInput(item.stamp_ns, item.image, isinstance(item.image, CompressedImage), item.info,
                          no_camera_info="no camera_info received yet on camera/camera_info")

    def _next_frame(self) -> FrameInput | None:
        """Bag playback (``process_every_frame``) with frames waiting: the next one is processed next, so the
        handler decodes it now and the pipeline tracks into it while this frame is processed (the same
        results, sooner). Live, a waiting frame may still be dropped for a newer one: nothing is done ahead."""
        if not self.opts.process_every_frame:
            return None
        with self._lock:
            nxt = self._frames.peek()
        return None if nxt is None or nxt.info is None else self._frame_input(nxt)

    def _process(self, item: Ready) -> None:
        frame = self._frame_input(item)
        if item.first_mismatch:
            self.get_logger().warning("camera_info stamps do not match image stamps; using the latest camera_info")
        handled = self._handler.handle(frame, self._next_frame(), self._hardware_id())
        result = handled.result
        self._n_processed += 1
        if result.skipped:
            self.get_logger().warning(f"{result.reason} ({frame.stamp_ns * 1e-9:.6f} s)", throttle_duration_sec=5.0)
        elif result.rejected and handled.gray is None:
            self.get_logger().warning(f"frame rejected: {handled.problem}", throttle_duration_sec=5.0)
        elif Decision.TIME_JUMPED_BACK in result.decisions:
            self.get_logger().warning(result.reason)
        self._publish(handled)

    # -- output -------------------------------------------------------------------------------------------
    def _hardware_id(self) -> str:
        """The hardware_id parameter, else the camera's frame id (the image header.frame_id)."""
        return self.opts.hardware_id or self._camera_frame or "unknown camera"

    def _publish(self, handled: HandledFrame) -> None:
        """The frame's outputs as messages: odometry, path, points, TF, its status, the debug image."""
        out = handled.outputs
        if out.odometry_vo_units is not None:
            self._pub_odom_vo_units.publish(odometry_msg(out.odometry_vo_units))
        if out.odometry is not None:
            self._pub_odom.publish(odometry_msg(out.odometry))
            if self._arrived_s is not None:
                self._last_latency_ms = (time.monotonic() - self._arrived_s) * 1e3
        if out.path is not None:
            self._publish_path(out.path, out.result.is_keyframe)
        if out.transforms and self._tf is not None:
            stamp = stamp_msg(out.result.stamp_ns)
            self._tf.sendTransform([transform_msg(stamp, t.parent, t.child, t.xyz, t.quat_xyzw)
                                    for t in out.transforms])
        if out.points is not None:
            self._pub_points.publish(point_cloud_msg(header_msg(out.result.stamp_ns, out.points.frame_id),
                                                     out.points.points_xyz))
        self._publish_frame(out.status, out.result)
        if self._pub_debug is not None and handled.gray is not None and not out.result.skipped:
            self._pub_debug.publish(bgr_image_msg(header_msg(out.result.stamp_ns, self.opts.frame_id),
                                                  draw_matches(out.result, handled.gray)))

    def _publish_path(self, path: PathRecord, is_keyframe: bool) -> None:
        """vo/path grows to path_max_length poses: serialising it every frame would cost more than the VO
        itself, so it goes out at keyframes, at least once a second, and when its frame changes; its newest
        pose is appended every frame."""
        if path.frame_id != self._path_frame:  # a path in other units: a new one
            self._path.clear()
            self._path_frame = path.frame_id
            self._path_published = 0.0
        ps = PoseStamped()
        ps.header = header_msg(int(path.stamps_ns[-1]), path.frame_id)
        p, q = ps.pose.position, ps.pose.orientation
        p.x, p.y, p.z = (float(v) for v in path.positions[-1])
        q.x, q.y, q.z, q.w = (float(v) for v in path.quats_xyzw[-1])
        self._path.append(ps)
        now = time.monotonic()
        if is_keyframe or now - self._path_published >= 1.0:
            self._path_published = now
            msg = Path()
            msg.header = ps.header
            msg.poses = list(self._path)
            self._pub_path.publish(msg)


class VoNode(VoNodeBase, Node):
    """Subscribes to a camera, runs the VO pipeline on a worker thread, publishes its results.

    ``tf_lookup`` replaces the tf2_ros lookup of the camera extrinsic (tests give a fake buffer); by
    default one is made when tf2_ros is importable.
    """

    def __init__(self, *, tf_lookup: TransformLookup | None = None, **kwargs: Any) -> None:
        super().__init__("vo_node", **kwargs)
        cfg, opts = declare_all(self)
        warn_undeclared_overrides(self)
        self.get_logger().info(effective_parameters_text(cfg, opts))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._start_session(cfg, opts, tf_lookup)

    def destroy_node(self) -> None:
        self._stop_worker(timeout_s=2.0)
        super().destroy_node()


HELP_TEXT = """usage: vo_node [--ros-args --params-file FILE -p NAME:=VALUE -r FROM:=TO ...]

Monocular visual odometry node (epi_vo). Subscribes camera/image_raw (+ /compressed) and
camera/camera_info; publishes vo/odometry (metres, or the position held while the scale is unknown),
vo/odometry/vo_units (the motion in VO units), vo/points, vo/path, vo/frame_status, /diagnostics; service
vo/reset.
Its parameters, with their defaults (the same file as `epi-vo params` and config/epi_vo.yaml):

"""


def main(args: list[str] | None = None) -> None:
    run_node(VoNode, "vo_node", HELP_TEXT, args)


if __name__ == "__main__":
    main()
