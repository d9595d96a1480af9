"""``vo_node``: the ROS 2 front door. Wiring only: the work is done by the same
:class:`~epi_vo.core.pipeline.VoPipeline` that ``epi-vo replay`` drives, so a bag gives the same poses live
and offline. Of the pipeline's two front doors, this is the only one that imports rclpy (the other
ROS-facing tools, play, monitor and live_bench, do too; the core never does).

Topics (relative names, so namespaces and remapping work):
  in:  ``camera/image_raw`` (sensor_msgs/Image) or ``camera/image_raw/compressed`` (CompressedImage,
       ``image_transport: compressed``), ``camera/camera_info``
  out: ``vo/odometry`` (nav_msgs/Odometry, odom -> base_link, REP-105), ``vo/points`` (PointCloud2 of
       the points triangulated at keyframes, frame odom), ``vo/path`` (bounded nav_msgs/Path),
       ``/diagnostics`` (one status ``<node name>: tracking`` per frame, and from the watchdog),
       ``vo/debug_image`` (off by default); TF odom -> base_link when tf2_ros is importable.
  srv: ``vo/reset`` (std_srvs/Trigger): restart tracking from the last pose.
"""

from __future__ import annotations

import collections
import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_srvs.srv import Trigger

from epi_vo.core.camera import CameraModelCache
from epi_vo.core.config import VoConfig, config_fields, field_doc, from_dict, unknown_names_text
from epi_vo.core.debug_image import draw_matches
from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.errors import CameraModelError, ConfigError, EpiVoError
from epi_vo.core.frame import FrameResult
from epi_vo.core.odometry import OdometryConverter, T_base_cam_from_params
from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.status import frame_status
from epi_vo.io import msgconv
from epi_vo.io.association import CameraInfoAssociator, Ready


@dataclass(frozen=True)
class NodeOptions:
    """The node's own parameters (the pipeline's come from VoConfig)."""

    frame_id: str = "odom"
    child_frame_id: str = "base_link"
    camera_xyz: tuple[float, ...] = (0.0, 0.0, 0.0)
    camera_rpy: tuple[float, ...] = (0.0, 0.0, 0.0)
    image_transport: str = "raw"
    qos_reliability: str = "best_effort"
    qos_depth: int = 5
    queue_size: int = 2
    process_every_frame: bool = False
    publish_tf: bool = True
    publish_debug_image: bool = False
    path_max_length: int = 1000
    watchdog_timeout_s: float = 1.0
    camera_info_wait_s: float = 0.2
    hardware_id: str = "monocular_camera"


_NODE_DOCS = {
    "frame_id": "odometry frame (header.frame_id of vo/odometry, vo/points, vo/path)",
    "child_frame_id": "robot base frame (child_frame_id of vo/odometry)",
    "camera_xyz": "camera position in the base frame (m)",
    "camera_rpy": "camera body orientation in the base frame, roll pitch yaw (rad); the optical rotation is added",
    "image_transport": "'raw' (sensor_msgs/Image) or 'compressed' (sensor_msgs/CompressedImage)",
    "qos_reliability": "input QoS reliability: 'best_effort' (sensor data) or 'reliable'",
    "qos_depth": "input QoS history depth",
    "queue_size": "frames waiting for processing in live mode; older ones are dropped and counted",
    "process_every_frame": "never drop frames (bag playback); the queue grows instead",
    "publish_tf": "broadcast odom -> base_link when tf2_ros is available",
    "publish_debug_image": "publish vo/debug_image with tracks, inliers and epipolar lines",
    "path_max_length": "poses kept in vo/path",
    "watchdog_timeout_s": "no image for this long: diagnostics WARN (3x: STALE)",
    "camera_info_wait_s": "how long an image waits for its camera_info before the latest one is used",
    "hardware_id": "hardware_id of the diagnostics status",
}
_NODE_CHOICES = {"image_transport": ("raw", "compressed"), "qos_reliability": ("best_effort", "reliable")}


def _descriptor(doc: str, lo: float | None, hi: float | None, choices: tuple[str, ...] | None,
                is_int: bool) -> ParameterDescriptor:
    d = ParameterDescriptor(description=doc)
    if choices:
        d.additional_constraints = "one of: " + ", ".join(choices)
    if lo is not None and hi is not None:
        if is_int:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return d


class VoNode(Node):
    """Subscribes to a camera, runs the VO pipeline on a worker thread, publishes its results."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("vo_node", **kwargs)
        self.cfg, self.opts = self._declare_parameters()
        self._warn_undeclared_overrides()
        self._log_effective_parameters()
        self._pipeline = VoPipeline(self.cfg)
        self._converter = OdometryConverter(T_base_cam_from_params(self.opts.camera_xyz, self.opts.camera_rpy))
        self._assoc = CameraInfoAssociator(max_pending=5, max_wait_ns=int(self.opts.camera_info_wait_s * 1e9))
        self._lock = threading.Lock()  # guards the association and the queue
        self._cv = threading.Condition(self._lock)
        self._queue: collections.deque[Ready] = collections.deque()
        self._reset_requested = False
        self._running = True
        self._n_received = self._n_dropped = self._n_processed = 0
        self._arrivals: collections.deque[float] = collections.deque(maxlen=30)
        self._last_image_wall: float | None = None
        self._path: collections.deque[PoseStamped] = collections.deque(maxlen=self.opts.path_max_length)
        self._path_published = 0.0
        self._arrival: dict[int, float] = {}  # image stamp -> monotonic arrival time, for the latency figure
        self._last_latency_ms = math.nan
        self._cameras = CameraModelCache()
        self._warned: set[str] = set()
        self._wheel_pending: list[tuple[int, np.ndarray]] = []  # handed to the pipeline by the worker

        in_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.opts.qos_depth,
                            reliability=ReliabilityPolicy.RELIABLE if self.opts.qos_reliability == "reliable"
                            else ReliabilityPolicy.BEST_EFFORT)
        self._compressed = self.opts.image_transport == "compressed"
        image_type, image_topic = (CompressedImage, "camera/image_raw/compressed") if self._compressed \
            else (Image, "camera/image_raw")
        self.create_subscription(image_type, image_topic, self._on_image, in_qos)
        self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, in_qos)
        if self.cfg.scale_source == "wheel_odometry":
            self.create_subscription(Odometry, self.cfg.wheel_odometry_topic, self._on_wheel_odometry,
                                     QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100))
            self.get_logger().info(f"metric scale from wheel odometry on {self.cfg.wheel_odometry_topic}")
        self._pub_odom = self.create_publisher(Odometry, "vo/odometry", 10)
        self._pub_points = self.create_publisher(PointCloud2, "vo/points", 10)
        self._pub_path = self.create_publisher(Path, "vo/path", 10)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._pub_debug = self.create_publisher(Image, "vo/debug_image", 2) if self.opts.publish_debug_image else None
        self.create_service(Trigger, "vo/reset", self._on_reset)
        self._tf = self._make_tf_broadcaster()
        self.create_timer(0.5, self._watchdog)
        self._worker = threading.Thread(target=self._work, name="vo_worker", daemon=True)
        self._worker.start()

    # -- parameters ---------------------------------------------------------------------------------
    def _declare_parameters(self) -> tuple[VoConfig, NodeOptions]:
        """Declare every pipeline and node parameter; collect every bad one before failing."""
        problems: list[str] = []
        values: dict[str, Any] = {}
        for f in config_fields():
            lo, hi, choices = f.metadata.get("min"), f.metadata.get("max"), f.metadata.get("choices")
            desc = _descriptor(field_doc(f), lo, hi, choices, isinstance(f.default, int))
            values[f.name] = self._declare(f.name, f.default, desc, problems)
        node_values: dict[str, Any] = {}
        defaults = NodeOptions()
        for name, doc in _NODE_DOCS.items():
            default = getattr(defaults, name)
            if isinstance(default, tuple):
                default = list(default)
            desc = _descriptor(doc, None, None, _NODE_CHOICES.get(name), False)
            node_values[name] = self._declare(name, default, desc, problems)
        cfg = VoConfig()
        try:
            cfg = from_dict({k: v for k, v in values.items() if v is not None})
        except ConfigError as exc:
            problems.append(str(exc).removeprefix("invalid epi_vo parameters: "))
        for name, choices in _NODE_CHOICES.items():
            if node_values.get(name) is not None and node_values[name] not in choices:
                problems.append(f"{name}={node_values[name]!r} (choose one of {', '.join(choices)})")
        for name in ("camera_xyz", "camera_rpy"):
            v = node_values.get(name)
            if v is not None and (len(v) != 3 or not all(math.isfinite(x) for x in v)):
                problems.append(f"{name}={list(v)!r} (expected 3 finite numbers)")
        for name in ("qos_depth", "queue_size", "path_max_length"):
            v = node_values.get(name)
            if v is not None and v < 1:
                problems.append(f"{name}={v} (minimum 1)")
        for name in ("watchdog_timeout_s", "camera_info_wait_s"):
            v = node_values.get(name)
            if v is not None and not (math.isfinite(v) and v > 0):
                problems.append(f"{name}={v} (must be > 0)")
        if problems:
            raise ConfigError("invalid vo_node parameters: " + "; ".join(problems))
        opts = NodeOptions(**{k: tuple(v) if isinstance(v, list) else v for k, v in node_values.items()})
        return cfg, opts

    def _warn_undeclared_overrides(self) -> None:
        """ROS's rule stays (an override of a parameter the node does not declare is ignored), but a
        misspelt name must not pass unnoticed: warn once, naming them and the closest parameter."""
        # rclpy has no public accessor for the overrides it was given (--params-file, -p): read its
        # attribute, and say nothing when a future rclpy renames it.
        overrides = getattr(self, "_parameter_overrides", None) or {}
        unknown = sorted(n for n in overrides if not self.has_parameter(n) and not n.startswith("qos_overrides."))
        if not unknown:
            return
        self.get_logger().warning("ignoring parameter overrides that vo_node does not declare: "
                                  + unknown_names_text(unknown))

    def _declare(self, name: str, default: Any, desc: ParameterDescriptor, problems: list[str]) -> Any:
        try:
            return self.declare_parameter(name, default, desc).value
        except Exception as exc:  # rclpy raises several exception types for a bad override
            problems.append(f"{name}: {exc}")
            return None

    def _log_effective_parameters(self) -> None:
        lines = [f"{f.name}={getattr(self.cfg, f.name)!r}" for f in config_fields()]
        lines += [f"{k}={v!r}" for k, v in self.opts.__dict__.items()]
        self.get_logger().info("epi_vo parameters: " + ", ".join(lines))

    def _make_tf_broadcaster(self) -> Any:
        if not self.opts.publish_tf:
            return None
        try:
            from tf2_ros import TransformBroadcaster
        except ImportError:
            self.get_logger().info("TF odom -> base_link unavailable: tf2_ros is not importable "
                                   "(odometry is still published on vo/odometry)")
            return None
        return TransformBroadcaster(self)

    # -- input ----------------------------------------------------------------------------------------
    def _on_image(self, msg: Image | CompressedImage) -> None:
        stamp = msgconv.stamp_to_ns(msg.header.stamp)
        with self._cv:
            self._n_received += 1
            now = time.monotonic()
            self._arrivals.append(now)
            self._last_image_wall = now
            if len(self._arrival) > 1000:  # frames dropped or never paired must not grow this
                self._arrival.clear()
            self._arrival[stamp] = now
            self._enqueue(self._assoc.add_image(stamp, msg))

    def _on_camera_info(self, msg: CameraInfo) -> None:
        with self._cv:
            self._enqueue(self._assoc.add_info(msgconv.stamp_to_ns(msg.header.stamp), msg))

    def _on_wheel_odometry(self, msg: Odometry) -> None:
        problem = msgconv.stamp_problem(msg.header.stamp)
        if problem is not None:
            self.get_logger().warning(f"wheel odometry message ignored: {problem}", throttle_duration_sec=5.0)
            return
        p = msg.pose.pose.position
        with self._cv:
            self._wheel_pending.append((msgconv.stamp_to_ns(msg.header.stamp), np.array([p.x, p.y, p.z])))
            if len(self._wheel_pending) > 10000:  # the worker is stalled: keep the newest
                del self._wheel_pending[:5000]

    def _enqueue(self, ready: list[Ready]) -> None:
        """Called with the lock held. Live mode keeps only the newest ``queue_size`` frames."""
        for r in ready:
            self._queue.append(r)
            if not self.opts.process_every_frame:
                while len(self._queue) > self.opts.queue_size:
                    self._queue.popleft()
                    self._n_dropped += 1
        if ready:
            self._cv.notify()

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._cv:
            self._reset_requested = True
        response.success = True
        response.message = "tracking restarts at the next frame, from the last pose"
        return response

    # -- processing -------------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._cv:
                while self._running and not self._queue:
                    self._cv.wait(timeout=0.2)
                if not self._running:
                    return
                item = self._queue.popleft()
                reset, self._reset_requested = self._reset_requested, False
                wheel, self._wheel_pending = self._wheel_pending, []
            for stamp_ns, xyz in wheel:  # the pipeline is only touched by this thread
                self._pipeline.add_wheel_odometry(stamp_ns, xyz)
            if reset:
                self._pipeline.reset("reset service called: tracking restarted from the last pose")
            try:
                self._process(item)
            except EpiVoError as exc:
                # Bad input in this frame: it is accounted for like any other (held pose, reason).
                self.get_logger().warning(f"frame rejected: {exc}", throttle_duration_sec=5.0)
                r = self._pipeline.reject(item.stamp_ns, str(exc))
                self._publish(r, _stamp_msg(r.stamp_ns), None)
            except Exception as exc:  # never let one frame kill the node; say what happened
                # Not an input problem: a defect. The pipeline's state may be half-updated, so tracking
                # restarts from the held pose; the status says it was an internal error.
                self.get_logger().error(f"frame at {item.stamp_ns * 1e-9:.6f} s failed: {exc!r}")
                self._pipeline.reset(f"internal error in the previous frame ({type(exc).__name__}): tracking "
                                     "restarted from the last pose")
                r = self._pipeline.reject(item.stamp_ns, f"internal error: {exc!r}")
                self._publish(r, _stamp_msg(r.stamp_ns), None)

    def _process(self, item: Ready) -> None:
        stamp = item.stamp_ns
        problem = msgconv.stamp_problem(item.image.header.stamp)
        if problem is not None:
            # As in replay: a header stamp that is no ROS time is a rejected frame, tracking untouched.
            result = self._pipeline.skip(stamp, problem)
        else:
            if item.info is None:
                raise CameraModelError("no camera_info received yet on camera/camera_info")
            if item.first_mismatch:
                self.get_logger().warning("camera_info stamps do not match image stamps; using the latest "
                                          "camera_info")
            gray = msgconv.decode_frame(item.image, self._compressed)
            result = self._pipeline.process(gray, self._cameras.get(item.info), stamp)
        self._n_processed += 1
        if result.skipped:
            self.get_logger().warning(f"{result.reason} ({stamp * 1e-9:.6f} s)", throttle_duration_sec=5.0)
            self._publish_status(frame_status(result, self.get_name(), self.opts.hardware_id),
                                 _stamp_msg(result.stamp_ns))
            return
        if "time jumped backwards" in result.reason:
            self.get_logger().warning(result.reason)
            self._converter.reset_twist()
        self._publish(result, _stamp_msg(result.stamp_ns), gray)

    # -- output -------------------------------------------------------------------------------------------
    def _publish(self, r: FrameResult, stamp_msg: Any, gray: np.ndarray | None) -> None:
        s = self._converter.convert(r.stamp_ns, r.T_w_c, r.covariance, r.has_pose)
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
        with self._lock:
            arrived = self._arrival.pop(r.stamp_ns, None)
        if arrived is not None:
            self._last_latency_ms = (time.monotonic() - arrived) * 1e3
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
                tf = TransformStamped()
                tf.header = odom.header
                tf.child_frame_id = self.opts.child_frame_id
                tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = p.x, p.y, p.z
                tf.transform.rotation = q
                self._tf.sendTransform(tf)
        if r.points_w.shape[0]:
            T = self._converter.T_base_cam
            self._pub_points.publish(_point_cloud(odom.header, r.points_w @ T[:3, :3].T + T[:3, 3]))
        self._publish_status(frame_status(r, self.get_name(), self.opts.hardware_id), stamp_msg)
        if self._pub_debug is not None and gray is not None:
            self._pub_debug.publish(_bgr_image(odom.header, draw_matches(r, gray)))

    def _input_values(self) -> tuple[tuple[str, str], ...]:
        with self._lock:
            arrivals = list(self._arrivals)
            dropped, received, queued = self._n_dropped, self._n_received, len(self._queue)
            last = self._last_image_wall
        now = time.monotonic()
        rate = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0]) if len(arrivals) > 1 and \
            arrivals[-1] > arrivals[0] else 0.0
        since = now - last if last is not None else math.inf
        if since > 0.0:
            rate = min(rate, 1.0 / since)  # a stalled camera's rate decays instead of freezing
        return (("input_rate_hz", f"{rate:.2f}"), ("latency_ms", f"{self._last_latency_ms:.2f}"),
                ("frames_received", str(received)),
                ("dropped_frames", str(dropped)), ("queue_depth", str(queued)),
                ("time_since_last_image_s", f"{since:.3f}" if math.isfinite(since) else "never"))

    def _publish_status(self, status: DiagnosticStatusRecord, stamp_msg: Any) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = stamp_msg
        msg = DiagnosticStatus(level=bytes([int(status.level)]), name=status.name, message=status.message,
                               hardware_id=status.hardware_id)
        msg.values = [KeyValue(key=k, value=v) for k, v in status.values + self._input_values()]
        arr.status = [msg]
        self._pub_diag.publish(arr)

    def _watchdog(self) -> None:
        with self._lock:
            last = self._last_image_wall
        silent = math.inf if last is None else time.monotonic() - last
        timeout = self.opts.watchdog_timeout_s
        if silent < timeout:
            return
        level = DiagnosticLevel.STALE if silent >= 3 * timeout else DiagnosticLevel.WARN
        what = "no image received yet" if last is None else f"no image for {silent:.1f} s"
        self._publish_status(DiagnosticStatusRecord(level, f"{self.get_name()}: tracking", f"stalled: {what}",
                                                    self.opts.hardware_id), self.get_clock().now().to_msg())

    def destroy_node(self) -> None:
        with self._cv:
            self._running = False
            self._cv.notify_all()
        self._worker.join(timeout=2.0)
        super().destroy_node()


def _stamp_msg(stamp_ns: int) -> Time:
    """A frame result's stamp as a ROS time (results carry valid stamps only)."""
    sec, nanosec = msgconv.ns_to_ros_time(stamp_ns)
    return Time(sec=sec, nanosec=nanosec)


def _point_cloud(header: Any, points: np.ndarray) -> PointCloud2:
    f = msgconv.point_cloud2_fields(points)
    msg = PointCloud2()
    msg.header = header
    msg.height, msg.width = f["height"], f["width"]
    msg.fields = [PointField(name=p.name, offset=p.offset, datatype=p.datatype, count=p.count) for p in f["fields"]]
    msg.is_bigendian, msg.point_step, msg.row_step = f["is_bigendian"], f["point_step"], f["row_step"]
    msg.data = bytes(f["data"])
    msg.is_dense = f["is_dense"]
    return msg


def _bgr_image(header: Any, img: np.ndarray) -> Image:
    msg = Image()
    msg.header = header
    msg.height, msg.width = img.shape[:2]
    msg.encoding = "bgr8"
    msg.step = img.shape[1] * 3
    msg.data = img.tobytes()
    return msg


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    try:
        node = VoNode()
    except ConfigError as exc:
        print(f"vo_node: error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        sys.exit(2)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
