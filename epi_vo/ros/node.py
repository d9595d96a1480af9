"""``vo_node``: the ROS 2 front door. Wiring only: the work is done by the same
:class:`~epi_vo.core.pipeline.VoPipeline` that ``epi-vo replay`` drives, so a bag gives the same poses live
and offline. Of the pipeline's two front doors, this is the only one that imports rclpy (the other
ROS-facing tools, play, monitor and live_bench, do too; the core never does).

Topics (relative names, so namespaces and remapping work):
  in:  ``camera/image_raw`` (sensor_msgs/Image) and/or ``camera/image_raw/compressed`` (CompressedImage):
       ``image_transport: auto`` subscribes to both and keeps whichever delivers first (logged and in the
       diagnostics), ``raw`` / ``compressed`` to one; ``camera/camera_info``
  out: ``vo/odometry`` (nav_msgs/Odometry, odom -> base_link, REP-105), ``vo/points`` (PointCloud2 of
       the points triangulated at keyframes, frame odom), ``vo/path`` (bounded nav_msgs/Path),
       ``vo/frame_status`` (DiagnosticArray per frame: ``<fully qualified node name>: tracking``, the frame
       record), ``/diagnostics`` (once a second: ``<node>: tracking``, ``input``, ``extrinsic``, ``scale``;
       ``epi_vo.ros.node_diagnostics``), ``vo/debug_image`` (off by default); TF odom -> base_link when
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
import dataclasses
import math
import threading
import time
from typing import Any

import numpy as np
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

from epi_vo.core import covariance as covm
from epi_vo.core.camera import CameraModelCache
from epi_vo.core.config import VoConfig, live_advice
from epi_vo.core.debug_image import draw_matches
from epi_vo.core.decisions import Decision
from epi_vo.core.diagnostics import DiagnosticStatusRecord
from epi_vo.core.errors import CameraModelError, EpiVoError, clipped
from epi_vo.core.frame import FrameResult
from epi_vo.core.health import TrackingHealth
from epi_vo.core.odometry import OdometryConverter, T_base_cam_from_params, status_pose
from epi_vo.core.status import frame_status
from epi_vo.core.transforms import invert_T
from epi_vo.io import msgconv
from epi_vo.io.association import Ready
from epi_vo.io.frame_queue import NO_CAMERA_INFO_WAIT_S, FrameQueue
from epi_vo.io.node_options import NodeOptions, changed_names
from epi_vo.ros.node_diagnostics import NodeDiagnostics
from epi_vo.ros.node_params import check_change, declare_all, effective_parameters_text, warn_undeclared_overrides
from epi_vo.ros.node_run import bgr_image_msg, point_cloud_msg, run_node, stamp_msg, transform_msg
from epi_vo.ros.node_tf import Extrinsic, ExtrinsicResolver, TransformLookup, make_tf2_lookup, make_tf_broadcaster
from epi_vo.runner import make_pipeline

__all__ = ["NodeOptions", "VoNode", "main"]

RAW_TOPIC, COMPRESSED_TOPIC = "camera/image_raw", "camera/image_raw/compressed"
# Wheel messages waiting for the worker, which takes them at every frame and whenever woken: reached only
# when it is stuck in one frame (100 s at 100 Hz); the oldest half is then dropped and counted.
WHEEL_PENDING_MAX = 10000


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
        self._pipeline = make_pipeline(self.cfg)
        for advice in live_advice(self.cfg):
            self.get_logger().warning(advice)
        T_params = T_base_cam_from_params(self.opts.camera_xyz, self.opts.camera_rpy)
        self._converter = OdometryConverter(T_params, continuous=bool(self.opts.map_frame_id))
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
        self._ahead: tuple[Ready, Any] | None = None  # the next queued frame and its image, decoded ahead
        self._n_processed = self._n_ignored = 0
        self._path: collections.deque[PoseStamped] = collections.deque(maxlen=self.opts.path_max_length)
        self._path_published = 0.0
        self._arrived_s: float | None = None  # steady clock arrival of the frame in flight (latency figure)
        self._last_latency_ms = math.nan
        self._cameras = CameraModelCache()
        # Wheel messages (stamp or None, position) in arrival order, handed to the pipeline by the worker
        self._wheel_pending: list[tuple[int | None, np.ndarray]] = []
        self._wheel_received = self._wheel_lost = 0  # wheel messages, and those the worker never took (stalled)
        self._camera_frame = ""  # header.frame_id of the first image
        self._tracking = TrackingHealth()  # the frames since /diagnostics was last published
        self._wheel_topic_name = ""
        # After a runtime change the pipeline is a new one, anchored at the pose the old one had reached.
        self._anchor: tuple[np.ndarray, np.ndarray, int] | None = None  # T_w_a, cov_w_a, index offset
        self._last_pose = (np.eye(4), np.zeros((6, 6)), -1)  # the last published T_w_c, covariance, index
        self._changes: list[str] = []  # runtime changes applied, for the summary
        self._announce_change = announce  # told in the reason of the first frame after a change

        in_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.opts.qos_depth,
                            reliability=ReliabilityPolicy.RELIABLE if self.opts.qos_reliability == "reliable"
                            else ReliabilityPolicy.BEST_EFFORT)
        self._image_subs: dict[str, Any] = {}
        if self.opts.image_transport in ("auto", "raw"):
            self._image_subs["raw"] = self.create_subscription(Image, RAW_TOPIC, self._on_image, in_qos)
        if self.opts.image_transport in ("auto", "compressed"):
            self._image_subs["compressed"] = self.create_subscription(CompressedImage, COMPRESSED_TOPIC,
                                                                      self._on_image, in_qos)
        self._image_topics = {k: sub.topic_name for k, sub in self._image_subs.items()}
        self._transport = "" if self.opts.image_transport == "auto" else self.opts.image_transport
        self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, in_qos)
        if self.cfg.scale_source == "wheel_odometry":
            wheel_sub = self.create_subscription(Odometry, self.cfg.wheel_odometry_topic, self._on_wheel_odometry,
                                                 QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100))
            self._wheel_topic_name = wheel_sub.topic_name
            self.get_logger().info(f"metric scale from wheel odometry on {self._wheel_topic_name}")
        self._pub_odom = self._create_output_publisher(Odometry, "vo/odometry", 10)
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
        transport = "compressed" if isinstance(msg, CompressedImage) else "raw"
        if transport != self._transport and not self._choose_transport(transport):
            return
        stamp = msgconv.stamp_to_ns(msg.header.stamp)
        with self._cv:
            if not self._camera_frame:
                self._camera_frame = clipped(str(msg.header.frame_id))  # in every status: bounded
            if self._frames.add_image(stamp, msg, len(msg.data), time.monotonic()):
                self._cv.notify()

    def _choose_transport(self, transport: str) -> bool:
        """image_transport auto: the first transport to deliver is kept, the other subscription dropped."""
        if self._transport:  # already chosen: a message of the other one still in flight
            return False
        self._transport = transport
        other = "raw" if transport == "compressed" else "compressed"
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
                self._pipeline.add_wheel_odometry(stamp_ns, xyz)
            if head is None:
                continue
            if item is None:
                self._resolve_extrinsic(head.image.header.frame_id)
                continue
            self._arrived_s = item.arrived_s
            if reset:
                self._pipeline.reset(reset)
            try:
                self._process(item)
            except EpiVoError as exc:
                # Bad input in this frame: it is accounted for like any other (held pose, reason).
                self.get_logger().warning(f"frame rejected: {exc}", throttle_duration_sec=5.0)
                r = self._anchored(self._pipeline.reject(item.stamp_ns, str(exc)))
                self._publish(r, stamp_msg(r.stamp_ns), None)
            except Exception as exc:  # never let one frame kill the node; say what happened
                # Not an input problem: a defect. The pipeline's state may be half-updated, so tracking
                # restarts from the held pose; the status says it was an internal error.
                self.get_logger().error(f"frame at {item.stamp_ns * 1e-9:.6f} s failed: {exc!r}")
                self._pipeline.reset(f"internal error in the previous frame ({type(exc).__name__}): tracking "
                                     "restarted from the last pose")
                r = self._anchored(self._pipeline.reject(item.stamp_ns, f"internal error: {exc!r}"))
                self._publish(r, stamp_msg(r.stamp_ns), None)
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
        self._converter = OdometryConverter(extrinsic.T_base_cam, continuous=bool(self.opts.map_frame_id))
        self._extrinsic = extrinsic
        self._pipeline.set_mounting(extrinsic.T_base_cam)  # the floor is sought along the up it declares
        (self.get_logger().warning if extrinsic.warn else self.get_logger().info)(extrinsic.text)

    def _apply_config(self, cfg: VoConfig) -> None:
        """A runtime change, between two frames (worker thread): a new pipeline with the new config,
        anchored at the pose (and covariance) the old one reached, so odometry stays continuous. Like a
        reset, the next frame starts a new map."""
        changed = changed_names(self.cfg, cfg)
        T_w_a, cov_w_a, index = self._last_pose
        self._pipeline = make_pipeline(cfg)
        if self._extrinsic is not None:
            self._pipeline.set_mounting(self._extrinsic.T_base_cam)
        for advice in live_advice(cfg):
            self.get_logger().warning(advice)
        self._anchor = (T_w_a, cov_w_a, index + 1)
        self.cfg = cfg
        text = ", ".join(changed) or "no knob changed"
        self._changes.append(f"{text} (from frame {index + 1})")
        self._announce_change = f"parameters changed ({text}): new map from the last pose"
        self.get_logger().info(f"parameters applied at frame {index + 1}: {text}; tracking restarts from the "
                               "last pose")

    def _anchored(self, r: FrameResult) -> FrameResult:
        """A result of the current pipeline in the odometry's world frame (after a runtime change)."""
        reason = r.reason
        if self._announce_change:
            reason = f"{self._announce_change}; {reason}" if reason else self._announce_change
            self._announce_change = ""
        if self._anchor is None:
            return r if reason == r.reason else dataclasses.replace(r, reason=reason)
        T_w_a, cov_w_a, offset = self._anchor
        T_a_c = r.T_w_c
        T_c_a = invert_T(T_a_c)
        cov = covm.compose(cov_w_a, T_w_a, r.covariance, T_c_a[:3, 3], T_c_a[:3, :3])
        points = r.points_w @ T_w_a[:3, :3].T + T_w_a[:3, 3] if r.points_w.shape[0] else r.points_w
        return dataclasses.replace(r, index=r.index + offset, T_w_c=T_w_a @ T_a_c, covariance=covm.floored(cov),
                                   points_w=points, reason=reason)

    def _look_ahead(self) -> None:
        """Bag playback (``process_every_frame``) with frames waiting: the next one is processed next, so
        its image is decoded now and the pipeline tracks into it while this frame is processed
        (``VoPipeline.announce_next``: the same results, sooner). Live, a waiting frame may still be
        dropped for a newer one: nothing is done ahead."""
        if not self.opts.process_every_frame:
            return
        with self._lock:
            nxt = self._frames.peek()
        if nxt is None or nxt.info is None or msgconv.stamp_problem(nxt.image.header.stamp) is not None:
            return
        try:
            camera = self._cameras.get(nxt.info)
            gray = msgconv.decode_frame(nxt.image, isinstance(nxt.image, CompressedImage),
                                        (camera.width, camera.height))
        except EpiVoError:
            return  # decoded again in its turn, and rejected there with the reason
        self._ahead = (nxt, gray)
        self._pipeline.announce_next(gray, camera)

    def _process(self, item: Ready) -> None:
        stamp = item.stamp_ns
        problem = msgconv.stamp_problem(item.image.header.stamp)
        gray = None
        if problem is not None:
            # As in replay: a header stamp that is no ROS time is a rejected frame, tracking untouched.
            result = self._pipeline.skip(stamp, problem)
        else:
            if item.info is None:
                raise CameraModelError("no camera_info received yet on camera/camera_info")
            if item.first_mismatch:
                self.get_logger().warning("camera_info stamps do not match image stamps; using the latest "
                                          "camera_info")
            ahead, self._ahead = self._ahead, None
            camera = self._cameras.get(item.info)  # first: a compressed image of another size is not decoded
            gray = ahead[1] if ahead is not None and ahead[0] is item else \
                msgconv.decode_frame(item.image, isinstance(item.image, CompressedImage), (camera.width, camera.height))
            self._look_ahead()
            result = self._pipeline.process(gray, camera, stamp)
        result = self._anchored(result)
        self._n_processed += 1
        if result.skipped:
            self.get_logger().warning(f"{result.reason} ({stamp * 1e-9:.6f} s)", throttle_duration_sec=5.0)
            self._publish_frame(result)
            return
        if Decision.TIME_JUMPED_BACK in result.decisions:
            self.get_logger().warning(result.reason)
            self._converter.reset_twist()
        self._publish(result, stamp_msg(result.stamp_ns), gray)

    # -- output -------------------------------------------------------------------------------------------
    def _hardware_id(self) -> str:
        """The hardware_id parameter, else the camera's frame id (the image header.frame_id)."""
        return self.opts.hardware_id or self._camera_frame or "unknown camera"

    def _frame_status(self, r: FrameResult) -> DiagnosticStatusRecord:
        """The frame's status; its pose is the odometry's (odom -> base_link), named by position_frame."""
        pose = status_pose(self._converter, r, self.opts.frame_id, self.opts.child_frame_id)
        return frame_status(r, self._status_name, self._hardware_id(), pose)

    def _publish(self, r: FrameResult, stamp_msg: Any, gray: np.ndarray | None) -> None:
        s = self._converter.convert_result(r)
        self._last_pose = (r.T_w_c, r.covariance, r.index)
        odom = Odometry()
        odom.header.stamp = stamp_msg
        odom.header.frame_id = self.opts.frame_id
        odom.child_frame_id = self.opts.child_frame_id
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        p.x, p.y, p.z = (float(v) for v in s.position)
        q.x, q.y, q.z, q.w = (float(v) for v in s.quat_xyzw)
        odom.pose.covariance = [float(v) for v in s.pose_covariance.ravel()]
        lin, ang = odom.twist.twist.linear, odom.twist.twist.angular
        lin.x, lin.y, lin.z = (float(v) for v in s.linear_velocity)
        ang.x, ang.y, ang.z = (float(v) for v in s.angular_velocity)
        odom.twist.covariance = [float(v) for v in s.twist_covariance.ravel()]
        self._pub_odom.publish(odom)
        if self._arrived_s is not None:
            self._last_latency_ms = (time.monotonic() - self._arrived_s) * 1e3
        if r.has_pose:
            ps = PoseStamped()
            ps.header = odom.header
            ps.pose = odom.pose.pose
            self._path.append(ps)
            now = time.monotonic()
            # The path grows to path_max_length poses: serialising it every frame would cost more than
            # the VO itself, so it goes out at keyframes and at least once a second.
            if r.is_keyframe or now - self._path_published >= 1.0:
                self._path_published = now
                path = Path()
                path.header = odom.header
                path.poses = list(self._path)
                self._pub_path.publish(path)
            if self._tf is not None:
                transforms = [transform_msg(stamp_msg, self.opts.frame_id, self.opts.child_frame_id, s.position,
                                            s.quat_xyzw)]
                if (map_odom := s.map_odom_xyz_quat()) is not None:  # map_frame_id: the corrections (REP-105)
                    transforms.append(transform_msg(stamp_msg, self.opts.map_frame_id, self.opts.frame_id, *map_odom))
                self._tf.sendTransform(transforms)
        if r.points_w.shape[0]:
            self._pub_points.publish(point_cloud_msg(odom.header, self._converter.odom_points(r.points_w)))
        self._publish_frame(r)
        if self._pub_debug is not None and gray is not None:
            self._pub_debug.publish(bgr_image_msg(odom.header, draw_matches(r, gray)))


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
camera/camera_info; publishes vo/odometry, vo/points, vo/path, vo/frame_status, /diagnostics; service vo/reset.
Its parameters, with their defaults (the same file as `epi-vo params` and config/epi_vo.yaml):

"""


def main(args: list[str] | None = None) -> None:
    run_node(VoNode, "vo_node", HELP_TEXT, args)


if __name__ == "__main__":
    main()
