"""``epi-vo play``: publish a bag's topics that vo_node consumes over ROS 2, in real time or scaled (a ros2
bag play stand-in).

The ros2 command-line tools do not install from PyPI, so this publishes what the VO node subscribes to:
the image topic (sensor_msgs/Image or CompressedImage) and its camera_info, the wheel odometry
(nav_msgs/Odometry) and ``/tf`` / ``/tf_static`` when the bag has them, optionally /clock.

- Topics are chosen in the bag as ``epi-vo replay`` chooses them (``epi_vo.io.play_bag``): the only image and
  camera_info topics, or ``image_topic`` / ``camera_info_topic``; the wheel odometry ``wheel_topic``, else the
  only Odometry topic not named as ground truth.
- Published names: the node's defaults, relative (the player's namespace applies): ``camera/image_raw`` (or
  ``.../compressed``), ``camera/camera_info``, ``odom`` (vo_node's ``wheel_odometry_topic``); the ``remap_*``
  options rename them. ``/tf`` and ``/tf_static`` keep their absolute names. /tf is reliable with depth 100,
  as tf2_ros's TransformBroadcaster; /tf_static is transient-local, as robot_state_publisher's static
  broadcaster, and keeps every static message of the bag, so a node started after playback still gets them.
- Messages are published as recorded: the raw CDR bytes of the bag are deserialised straight into the
  rclpy message types (``rclpy.serialization.deserialize_message``), no field-by-field copy. TF messages
  are published as the recorded bytes themselves, once rosbags has checked they decode: tf2_msgs has no
  PyPI wheel, so its rclpy class may be missing (then /tf and /tf_static are not played, and the summary
  says so); the publisher needs the class only for its type.
- All topics are merged in the bag's order (log time), one schedule for all.
- Timing follows the bag's log time relative to the first message, on a monotonic clock, divided by
  ``rate``; ``rate`` 0 publishes as fast as possible, still in bag order. With ``clock``,
  rosgraph_msgs/Clock carrying the message's log time is published on /clock before each message.
- Reliable publishers are flow-controlled: every ``qos_depth`` messages on a topic the player waits
  (bounded) until reliable subscribers acknowledged them, so KEEP_LAST history never drops a message a
  subscriber has not received. That matters at ``rate`` 0, and at start-up at any rate: a subscriber's
  side of discovery can complete seconds after the player's (a lost discovery packet waits for the next
  heartbeat), and until then it ignores the data; the wait holds the samples until it has caught up.
  A wait that leaves playback more than ``_PAUSE_TOLERANCE_S`` behind schedule pauses it (the schedule
  shifts, no catch-up burst; ``PlaySummary.paused_s``). At the end the player waits (bounded) for the
  last acknowledgements before its publishers go away.

:class:`BagPlayer` takes an rclpy Node (usable in-process, e.g. from tests); :func:`run_play` owns the
rclpy lifecycle for the command line. DDS settings (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE) come
from the environment.
"""

from __future__ import annotations

import enum
import math
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, Self

import rclpy
from builtin_interfaces.msg import Time
from nav_msgs.msg import Odometry
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from epi_vo.core.errors import BagError, ConfigError
from epi_vo.io import checks
from epi_vo.io.bag_topics import CAMERA_INFO_TYPE, COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, ODOMETRY_TYPE
from epi_vo.io.play_bag import TF_STATIC_TOPIC, TF_TOPIC, BagMessage, PlayBag

NODE_NAME = "epi_vo_player"
IMAGE_OUT_TOPIC = "camera/image_raw"  # relative: the node namespace applies
COMPRESSED_IMAGE_OUT_TOPIC = "camera/image_raw/compressed"
CAMERA_INFO_OUT_TOPIC = "camera/camera_info"
WHEEL_OUT_TOPIC = "odom"  # vo_node's default wheel_odometry_topic
CLOCK_TOPIC = "/clock"

_MSG_CLASSES: dict[str, type[Any]] = {
    IMAGE_TYPE: Image,
    COMPRESSED_IMAGE_TYPE: CompressedImage,
    CAMERA_INFO_TYPE: CameraInfo,
    ODOMETRY_TYPE: Odometry,
}
# tf2_ros's TransformBroadcaster publishes /tf reliable with this depth; its static broadcaster /tf_static
# reliable and transient-local.
TF_DEPTH = 100
_NS_PER_S = 1_000_000_000
# The slowest playback: one second of bag then lasts over a quarter of an hour. Slower is a typing mistake
# (1e-300 would make the first wait longer than the platform can wait), not a use.
MIN_RATE = 1e-3
# Bound on waiting for reliable subscribers' acknowledgements. Fast DDS readers acknowledge on a writer
# heartbeat: one comes with the data when the history fills up, otherwise every 3 s; and a reader whose
# side of discovery completes late acknowledges only then (seen up to ~3 s on loopback). Long enough for
# both, short enough that a subscriber that died without unmatching stalls playback only briefly.
_ACK_TIMEOUT_S = 5.0
# Acknowledgements of healthy subscribers take milliseconds (they fit in the gap between frames); a wait
# that puts playback further behind than this is a pause, and the schedule shifts by it.
_PAUSE_TOLERANCE_S = 0.1
_SUBSCRIBER_POLL_S = 0.01
# After the image topic is matched, how long to give the camera_info and wheel subscribers (usually the same
# node, discovered a moment later) so that they start together.
_CAMERA_INFO_GRACE_S = 0.5


class Reliability(enum.Enum):
    """QoS reliability of the published topics."""

    RELIABLE = "reliable"  # matches reliable and best-effort subscribers
    BEST_EFFORT = "best_effort"  # matches best-effort subscribers only

    @property
    def policy(self) -> ReliabilityPolicy:
        return ReliabilityPolicy.RELIABLE if self is Reliability.RELIABLE else ReliabilityPolicy.BEST_EFFORT


@dataclass(frozen=True)
class PlayOptions:
    """How to play a bag; every field has a default. Bad values raise ConfigError naming all of them."""

    rate: float = 1.0  # playback speed multiplier of bag time; 0: as fast as subscribers acknowledge
    image_topic: str | None = None  # bag topic of the images (default: the only Image/CompressedImage topic)
    camera_info_topic: str | None = None  # bag topic of the calibration (default: the only/sibling one)
    remap_image: str | None = None  # published name (default camera/image_raw, or .../compressed)
    remap_camera_info: str | None = None  # published name of camera_info (default camera/camera_info)
    wheel_topic: str | None = None  # bag topic of the wheel odometry (default: the only Odometry not named as GT)
    remap_wheel: str | None = None  # published name of the wheel odometry (default odom)
    clock: bool = False  # publish rosgraph_msgs/Clock (bag log time) on /clock before each message
    qos_reliability: Reliability = Reliability.RELIABLE
    qos_depth: int = 10  # KEEP_LAST history depth of the publishers
    start_delay_s: float | None = None  # seconds to wait before playing; None: until an image subscriber
    subscriber_wait_s: float = 5.0  # start_delay_s None: give up waiting for a subscriber after this
    loop: bool = False  # replay from the start until stopped

    def __post_init__(self) -> None:
        problems = []
        if not (math.isfinite(self.rate) and self.rate >= 0.0):
            problems.append(f"rate must be a finite number >= 0, got {self.rate}")
        elif 0.0 < self.rate < MIN_RATE:
            problems.append(f"rate must be 0 (as fast as acknowledged) or at least {MIN_RATE:g}, got {self.rate:g}")
        if self.qos_depth < 1:
            problems.append(f"qos_depth must be >= 1, got {self.qos_depth}")
        if self.start_delay_s is not None and not (math.isfinite(self.start_delay_s) and self.start_delay_s >= 0):
            problems.append(f"start_delay must be a finite number >= 0, got {self.start_delay_s}")
        elif self.start_delay_s is not None and self.start_delay_s > threading.TIMEOUT_MAX:
            problems.append(f"start_delay must be at most {threading.TIMEOUT_MAX:g} s (the longest wait the platform "
                            f"can make), got {self.start_delay_s:g}")
        if not (math.isfinite(self.subscriber_wait_s) and self.subscriber_wait_s >= 0):
            problems.append(f"subscriber_wait_s must be a finite number >= 0, got {self.subscriber_wait_s}")
        if not isinstance(self.qos_reliability, Reliability):
            problems.append(f"qos_reliability must be a Reliability, got {self.qos_reliability!r}")
        for name in ("remap_image", "remap_camera_info", "remap_wheel"):
            value = getattr(self, name)
            if value is not None:
                try:
                    checks.topic_name(value, name)
                except ConfigError as exc:
                    problems.append(str(exc))
        if problems:
            raise ConfigError("invalid play options: " + "; ".join(problems))


@dataclass(frozen=True)
class PlaySummary:
    """Totals of a play run. ``bag_s`` is the bag time covered (summed over loop passes)."""

    bag: str
    image_topic: str  # published (fully qualified) names
    camera_info_topic: str
    images: int
    camera_infos: int
    clocks: int
    passes: int  # passes started (loop)
    wall_s: float  # from the first published message to the last
    bag_s: float
    paused_s: float  # of wall_s, playback held for subscribers' acknowledgements (rate > 0)
    interrupted: bool
    wheel_topic: str = ""  # published name of the wheel odometry ('' when the bag has none)
    wheel_messages: int = 0
    tf_messages: int = 0  # on /tf
    tf_static_messages: int = 0  # on /tf_static
    not_played: tuple[str, ...] = ()  # bag topics the player could not publish, with why

    @property
    def messages(self) -> int:
        return self.images + self.camera_infos + self.wheel_messages + self.tf_messages + self.tf_static_messages

    @property
    def effective_rate(self) -> float:
        """Bag time per wall time outside pauses (nan when nothing or a single instant was played)."""
        playing_s = self.wall_s - self.paused_s
        return self.bag_s / playing_s if playing_s > 0 and self.bag_s > 0 else math.nan


def format_summary(summary: PlaySummary) -> str:
    """One line for the terminal."""
    clock = f" + {summary.clocks} /clock" if summary.clocks else ""
    others = [(n, t) for n, t in ((summary.wheel_messages, summary.wheel_topic), (summary.tf_messages, TF_TOPIC),
                                  (summary.tf_static_messages, TF_STATIC_TOPIC)) if n]
    also = "".join(f", {n} on {t}" for n, t in others)
    skipped = f"; not played: {'; '.join(summary.not_played)}" if summary.not_played else ""
    passes = f", {summary.passes} passes" if summary.passes > 1 else ""
    paused = f" ({summary.paused_s:.2f} s paused for acknowledgements)" if summary.paused_s > 0 else ""
    stopped = " (interrupted)" if summary.interrupted else ""
    rate = "n/a" if math.isnan(summary.effective_rate) else f"{summary.effective_rate:.2f}x"
    return (f"published {summary.messages} messages ({summary.images} on {summary.image_topic}, "
            f"{summary.camera_infos} on {summary.camera_info_topic}{also}{clock}) in {summary.wall_s:.2f} s"
            f"{paused}{passes}: "
            f"bag time {summary.bag_s:.2f} s, effective rate {rate}{stopped}{skipped}")


def tf_message_class() -> type[Any] | None:
    """tf2_msgs/msg/TFMessage's rclpy class; None where tf2_msgs is not installed (a PyPI-only environment:
    it has no wheel there; every ROS 2 install has it)."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return TFMessage


class BagPlayer:
    """Publishes a bag's topics that vo_node consumes (and /clock) from ``node`` (see module doc).

    Opens the bag and creates the publishers at construction; ``play()`` plays (from any thread),
    ``stop()`` ends a running ``play()`` between messages, ``close()`` closes the bag (the publishers
    belong to the node). Raises BagError for a bag that cannot be played, ConfigError for bad options.
    ``tf_type``: the rclpy class the /tf and /tf_static publishers are made with (default
    :func:`tf_message_class`); the recorded bytes are published whatever it is.
    """

    def __init__(self, node: Node, bag_path: str | Path, options: PlayOptions | None = None, *,
                 tf_type: type[Any] | None = None) -> None:
        self.options = options or PlayOptions()
        self._node = node
        self.bag = PlayBag(bag_path, self.options.image_topic, self.options.camera_info_topic,
                           self.options.wheel_topic)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.options.qos_depth,
                         reliability=self.options.qos_reliability.policy, durability=DurabilityPolicy.VOLATILE)
        default_image_out = COMPRESSED_IMAGE_OUT_TOPIC if self.bag.image_is_compressed else IMAGE_OUT_TOPIC
        self._publishers: dict[str, Publisher] = {
            self.bag.image_topic: node.create_publisher(
                _MSG_CLASSES[self.bag.image_msgtype], self.options.remap_image or default_image_out, qos),
            self.bag.camera_info_topic: node.create_publisher(
                CameraInfo, self.options.remap_camera_info or CAMERA_INFO_OUT_TOPIC, qos),
        }
        if self.bag.wheel_topic is not None:
            self._publishers[self.bag.wheel_topic] = node.create_publisher(
                Odometry, self.options.remap_wheel or WHEEL_OUT_TOPIC, qos)
        self.not_played: tuple[str, ...] = ()
        self._raw_topics = frozenset(self.bag.tf_topics)  # published as the recorded bytes
        tf_type = tf_type or tf_message_class()
        if tf_type is None and self.bag.tf_topics:
            self.not_played = tuple(f"{t} (tf2_msgs is not installed)" for t in self.bag.tf_topics)
            node.get_logger().warning(f"{' and '.join(self.bag.tf_topics)} not played: tf2_msgs is not installed "
                                      "(part of every ROS 2 install; it has no PyPI wheel)")
        elif tf_type is not None:
            for topic in self.bag.tf_topics:
                self._publishers[topic] = node.create_publisher(tf_type, topic, self._tf_qos(topic))
        self.clock_publisher = node.create_publisher(Clock, CLOCK_TOPIC, qos) if self.options.clock else None
        self._stop = threading.Event()
        self._counts = dict.fromkeys(self.bag.topics, 0)
        self._clocks = 0
        self._passes = 0
        self._bag_ns = 0
        self._paused_s = 0.0
        self._first_publish: float | None = None
        self._last_publish: float | None = None

    @property
    def image_publisher(self) -> Publisher:
        return self._publishers[self.bag.image_topic]

    @property
    def camera_info_publisher(self) -> Publisher:
        return self._publishers[self.bag.camera_info_topic]

    @property
    def wheel_publisher(self) -> Publisher | None:
        return self._publishers.get(self.bag.wheel_topic) if self.bag.wheel_topic is not None else None

    def tf_publisher(self, topic: str) -> Publisher | None:
        """The publisher of /tf or /tf_static; None when the bag has no such topic or it is not played."""
        return self._publishers.get(topic) if topic in self._raw_topics else None

    def _tf_qos(self, topic: str) -> QoSProfile:
        """/tf as tf2_ros's TransformBroadcaster offers it; /tf_static transient-local as its static broadcaster,
        deep enough to keep every static message of the bag for subscribers that join later."""
        if topic == TF_STATIC_TOPIC:
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(1, self.bag.counts[topic]),
                              reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=TF_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc_val: BaseException | None,
                 exc_tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        self.bag.close()

    def stop(self) -> None:
        """Make a running ``play()`` return after the message being published (thread-safe)."""
        self._stop.set()

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a subscriber on the image topic (then briefly on camera_info and the
        wheel odometry, which a VO node without a wheel scale source does not subscribe to).

        True when the image topic is matched. Discovery runs in DDS threads: no spinning needed.
        """
        deadline = time.monotonic() + timeout_s
        while self._context_ok() and self.image_publisher.get_subscription_count() == 0:
            if time.monotonic() >= deadline or self._stop.wait(_SUBSCRIBER_POLL_S):
                return False
        grace_end = min(deadline, time.monotonic() + _CAMERA_INFO_GRACE_S)
        others = [p for p in (self.camera_info_publisher, self.wheel_publisher) if p is not None]
        while (self._context_ok() and any(p.get_subscription_count() == 0 for p in others)
               and time.monotonic() < grace_end):
            if self._stop.wait(_SUBSCRIBER_POLL_S):
                break
        return True

    def _context_ok(self) -> bool:
        """True while the node's context is up; ExternalShutdownException once it was shut down."""
        if not rclpy.ok(context=self._node.context):
            raise ExternalShutdownException
        return True

    def play(self) -> PlaySummary:
        """Wait as ``start_delay_s`` says, play once (or until ``stop()`` with ``loop``); return the totals.

        Raises ExternalShutdownException when the node's context is shut down (Ctrl-C under rclpy's
        signal handler) and BagError for a message that cannot be read; ``summary()`` then still gives
        what was published. Each loop pass restarts the schedule, and /clock jumps back to the start.
        """
        self._stop.clear()
        if self.options.start_delay_s is None:
            if not self.wait_for_subscribers(self.options.subscriber_wait_s):
                self._node.get_logger().warning(
                    f"no subscriber on {self.image_publisher.topic_name} after "
                    f"{self.options.subscriber_wait_s:g} s; publishing anyway")
        elif self.options.start_delay_s > 0:
            self._stop.wait(self.options.start_delay_s)
        while not self._stop.is_set():
            self._play_pass()
            if not self.options.loop:
                break
        self._wait_acked(_ACK_TIMEOUT_S)
        return self.summary()

    def summary(self, interrupted: bool = False) -> PlaySummary:
        """Totals so far."""
        wall_s = 0.0
        if self._first_publish is not None and self._last_publish is not None:
            wall_s = self._last_publish - self._first_publish
        wheel = self.wheel_publisher
        return PlaySummary(
            bag=str(self.bag.path), image_topic=self.image_publisher.topic_name,
            camera_info_topic=self.camera_info_publisher.topic_name,
            images=self._counts[self.bag.image_topic], camera_infos=self._counts[self.bag.camera_info_topic],
            clocks=self._clocks, passes=self._passes, wall_s=wall_s, bag_s=self._bag_ns / _NS_PER_S,
            paused_s=self._paused_s, interrupted=interrupted or self._stop.is_set(),
            wheel_topic=wheel.topic_name if wheel is not None else "",
            wheel_messages=self._counts[self.bag.wheel_topic] if self.bag.wheel_topic is not None else 0,
            tf_messages=self._counts.get(TF_TOPIC, 0), tf_static_messages=self._counts.get(TF_STATIC_TOPIC, 0),
            not_played=self.not_played)

    def _play_pass(self) -> None:
        """One pass over the bag: the schedule restarts at the first message."""
        self._passes += 1
        rate = self.options.rate
        first_log_ns: int | None = None
        start = time.monotonic()  # wall time of the pass's first message; shifted by pauses
        since_ack: dict[str, int] = {}  # messages published per topic since the last acknowledgement wait
        covered_ns = 0  # bag time of this pass already added to self._bag_ns
        for message in self.bag.messages():
            if first_log_ns is None:
                first_log_ns = message.log_time_ns
            elapsed_bag_ns = message.log_time_ns - first_log_ns
            if rate > 0:
                delay = start + elapsed_bag_ns / _NS_PER_S / rate - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
            if self._stop.is_set() or not self._context_ok():
                return
            waited_s = self._publish(message, since_ack)
            if rate > 0 and waited_s > 0:
                behind_s = time.monotonic() - (start + elapsed_bag_ns / _NS_PER_S / rate)
                if behind_s > _PAUSE_TOLERANCE_S:
                    start += behind_s
                    self._paused_s += behind_s
            # Counted per message, so an interrupted pass reports the bag time it covered.
            self._bag_ns += elapsed_bag_ns - covered_ns
            covered_ns = elapsed_bag_ns

    def _publish(self, message: BagMessage, since_ack: dict[str, int]) -> float:
        """Publish /clock (option) and the message; return the seconds spent waiting for acknowledgements."""
        waited_s = 0.0
        publisher = self._publishers.get(message.topic)
        if publisher is None:  # a TF topic that cannot be played here (said once, and in the summary)
            return waited_s
        msg = self._message(message)
        if self.clock_publisher is not None:
            sec, nanosec = divmod(message.log_time_ns, _NS_PER_S)
            self.clock_publisher.publish(Clock(clock=Time(sec=sec, nanosec=nanosec)))
            self._clocks += 1
            waited_s += self._flow_control(self.clock_publisher, CLOCK_TOPIC, since_ack)
        publisher.publish(msg)
        now = time.monotonic()
        if self._first_publish is None:
            self._first_publish = now
        self._last_publish = now
        self._counts[message.topic] += 1
        return waited_s + self._flow_control(publisher, message.topic, since_ack)

    def _message(self, message: BagMessage) -> Any:
        """What to publish for a recorded message: its rclpy message, or (TF) its checked CDR bytes."""
        msgtype = self.bag.msgtype(message.topic)
        if message.topic in self._raw_topics:
            problem = self.bag.check_cdr(message)
            if problem is None:
                return message.rawdata
        else:
            try:
                return deserialize_message(message.rawdata, _MSG_CLASSES[msgtype])
            except RuntimeError as err:  # rclpy's RMWError: the bytes are not a CDR message of this type
                problem = str(err)
        text = (f"cannot deserialise a {msgtype} on {message.topic} at log time {message.log_time_ns} ns "
                f"in bag {self.bag.path}: {problem}")
        raise BagError(text)

    def _flow_control(self, publisher: Publisher, key: str, since_ack: dict[str, int]) -> float:
        """Every ``qos_depth`` messages on ``key``, wait (bounded) until reliable subscribers acknowledged all.

        A KEEP_LAST writer drops its oldest sample once ``depth`` are unacknowledged, even one a reliable
        subscriber has not received yet. The history is then full, which makes Fast DDS send a heartbeat
        with the data, so healthy subscribers acknowledge within milliseconds. Returns at once for
        best-effort publishers. Returns the seconds waited.
        """
        since_ack[key] = since_ack.get(key, 0) + 1
        if since_ack[key] < self.options.qos_depth:
            return 0.0
        since_ack[key] = 0
        started = time.monotonic()
        if not publisher.wait_for_all_acked(Duration(seconds=_ACK_TIMEOUT_S)):
            self._node.get_logger().warning(
                f"{publisher.topic_name}: subscribers did not acknowledge within {_ACK_TIMEOUT_S:g} s; "
                "older messages may be lost to them")
        return time.monotonic() - started

    def _wait_acked(self, timeout_s: float) -> None:
        publishers = [*self._publishers.values(), *([self.clock_publisher] if self.clock_publisher else [])]
        for publisher in publishers:
            if not publisher.wait_for_all_acked(Duration(seconds=timeout_s)):
                self._node.get_logger().warning(
                    f"{publisher.topic_name}: not every message was acknowledged within {timeout_s:g} s")


def run_play(bag_path: str | Path, options: PlayOptions | None = None, namespace: str = "") -> PlaySummary:
    """Initialise rclpy, play the bag from a node ``epi_vo_player`` in ``namespace``, shut down.

    Ctrl-C ends playback cleanly: the summary then has ``interrupted`` set.
    """
    # Without rclpy's signal handlers, SIGINT and SIGTERM raise KeyboardInterrupt wherever playback is (a
    # sleep, the subscriber wait), and the context is still valid for the summary and the shutdown.
    # Installed explicitly: a shell starts background jobs with SIGINT ignored.
    checks.namespace(namespace, "namespace")
    previous_handlers = {}
    if threading.current_thread() is threading.main_thread():
        previous_handlers = {sig: signal.signal(sig, _raise_keyboard_interrupt)
                             for sig in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node: Node | None = None
    try:
        node = Node(NODE_NAME, namespace=namespace)
        with BagPlayer(node, bag_path, options) as player:
            try:
                return player.play()
            except (KeyboardInterrupt, ExternalShutdownException):
                return player.summary(interrupted=True)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous_handlers.items():
            signal.signal(sig, handler)


def _raise_keyboard_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt
