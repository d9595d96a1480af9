"""``epi-vo monitor``: a live terminal view of a running ``vo_node``, from its diagnostics and its odometry.

Two parts, as the node / pipeline split:

- :class:`MonitorState` is an immutable snapshot with no rclpy: ``update_from_health`` (a status of the node's
  ``/diagnostics``), ``update_from_frame`` (a status of its ``vo/frame_status``) and ``update_from_odometry``
  return a new state, ``render_text`` gives the text shown by ``--once``, by non-TTY output and inside the
  live panel. Tests feed it plain values.
- :func:`run` owns rclpy: it subscribes to ``/diagnostics`` (the node's health, once a second: statuses
  ``<fully qualified node name>: tracking``, ``input``, ``extrinsic``, ``scale``, ``lifecycle``), to the
  node's ``vo/frame_status`` (one status per frame: the frame record) and to its odometry topic (relative,
  so it follows the user's namespace); it follows the VO node of the odometry topic's namespace
  (``/robot1/vo/odometry``: ``/robot1/<node>: ...`` and ``/robot1/vo/frame_status``), and shows the state
  with ``rich.live`` on a terminal, as plain snapshots once a second otherwise.

DDS settings (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE) come from the user's environment: this is
a user tool, it does not force loopback discovery.

The level and reason shown are an aggregator's: the worst of the node's health statuses, named by concern;
each concern's own level and message follow. The frame lines (state, matches, model, map) are the latest
frame's record; the input figures are those of the latest status that has them (a frame's, or the input
status when frames stop).

Units and scale. The node's ``scale_source`` (``none``, ``ground_plane``, ``wheel_odometry``) says where
metric scale comes from; the scale status (and every frame record) carries ``scale_source``, ``units``
(``m`` once a metric source is established, ``vo`` otherwise), ``metric_scale``, ``scale`` (metres per VO
unit of the first map), ``scale_rel_std``, the camera's pitch and roll to the floor (ground plane only) and
``scale_reason`` (why the source gave no measurement). The scale status says the configured source even
before the first frame (a node whose camera never delivered); the latest frame's numbers win when newer.
Data without these keys (an older node) is in VO units, source none.

Distance travelled is the sum of the odometry position steps, of the topic that carries the motion in the
units of the latest status: in metres ``vo/odometry``; in VO units (``scale_source: none``, or a metric
source not established yet: the scale of the map built at initialisation, a monocular VO has no metric
scale of its own) ``vo/odometry/vo_units``, since ``vo/odometry`` then holds its position (nothing in VO
units is published where a robot could fuse it as metres).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import math
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from types import FrameType, MappingProxyType
from typing import Any

from epi_vo.core import health
from epi_vo.core.diagnostics import DiagnosticLevel
from epi_vo.io import checks

FRAME_STATUS_TOPIC = "vo/frame_status"  # the node's per-frame statuses, relative to its namespace
VO_UNITS_TOPIC = "vo/odometry/vo_units"  # the node's motion in VO units, relative to its namespace
HISTORY_LENGTH = 8  # distinct warning/error reasons kept
SILENT_AFTER_S = 3.0  # no status for this long: the node (not only its camera) may be gone
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def level_value(level: int | bytes | bytearray) -> int:
    """``DiagnosticStatus.level`` as an int (rclpy gives a 1-byte ``bytes``)."""
    if isinstance(level, bytes | bytearray):
        return level[0] if level else 0
    return int(level)


def level_name(level: int) -> str:
    """OK / WARN / ERROR / STALE; an unknown value is shown, not refused (the monitor reads others' data)."""
    try:
        return DiagnosticLevel(level).name
    except ValueError:
        return f"LEVEL {level}"


def split_status_name(name: str) -> tuple[str, str] | None:
    """('/robot1/vo_node', 'tracking') of a VO node's status '/robot1/vo_node: tracking' (a concern of
    ``epi_vo.core.health``), None for any other status. An older node named its statuses after its bare
    name, taken as the root namespace's."""
    node, sep, concern = name.rpartition(": ")
    if not sep or concern not in health.CONCERNS or not node.strip("/"):
        return None
    return (node if node.startswith("/") else "/" + node), concern


def namespace_of(fq_name: str) -> str:
    """'/robot1' of '/robot1/vo_node' (or of a topic '/robot1/odom_vo'), '/' at the root."""
    return fq_name.rstrip("/").rsplit("/", 1)[0] or "/"


def odometry_namespace(topic: str) -> str:
    """The namespace of the node publishing a resolved odometry topic: '/robot1/vo/odometry' (the node's
    ``vo/odometry``) and '/robot1/odom_vo' (remapped) both give '/robot1'."""
    topic = "/" + topic.strip("/")
    return namespace_of(topic.removesuffix("/vo/odometry") + "/x" if topic.endswith("/vo/odometry") else topic)


def is_vo_status(name: str, node_name: str | None = None, namespace: str | None = None) -> bool:
    """Whether a status name is a VO node's (any concern), of ``node_name`` and in ``namespace`` when given.

    ``node_name`` absolute ('/robot1/vo_node') is compared with the status's fully qualified name, a bare
    one ('vo_node') with its last part; ``namespace`` ('/robot1') with the namespace of the status's node.
    """
    parts = split_status_name(name)
    if parts is None:
        return False
    node = parts[0]
    if node_name is not None:
        wanted = node_name.rstrip("/")
        if wanted.startswith("/") and node != wanted:
            return False
        if not wanted.startswith("/") and node.rsplit("/", 1)[-1] != wanted:
            return False
    return namespace is None or namespace_of(node) == "/" + namespace.strip("/")


def reason_key(message: str) -> str:
    """Warnings that differ only in their numbers ('no image for 1.5 s', '... 2.0 s') are one reason."""
    return _NUMBER.sub("#", message)


@dataclass(frozen=True)
class HistoryEntry:
    """One distinct warning/error reason: its latest wording and level, how often and when last seen."""

    key: str
    message: str
    level: int
    count: int
    first_s: float
    last_s: float


@dataclass(frozen=True)
class Concern:
    """The latest health status of one concern (tracking, input, extrinsic, scale, lifecycle)."""

    level: int
    message: str
    values: Mapping[str, str]
    t_s: float


def _mapping(values: Mapping[str, str] | Iterable[tuple[str, str]]) -> Mapping[str, str]:
    return MappingProxyType({str(k): str(v) for k, v in (values.items() if isinstance(values, Mapping) else values)})


@dataclass(frozen=True)
class MonitorState:
    """What the monitor knows of one VO node. Immutable: the ``update_*`` methods return a new state.

    ``health`` holds the latest status of each concern of the node's /diagnostics; ``frame`` the key/values
    of the latest per-frame status (the frame record: state, inliers, model, ...); ``latest`` those of the
    latest status carrying the input figures (a frame's, or the input status), so the input rate and image
    age stay current while the last frame's numbers stay on screen. Times are wall-clock seconds.
    """

    node_name: str | None = None  # follow only this node; None: the first VO node seen
    namespace: str | None = None  # follow only nodes of this namespace (the odometry topic's); None: any
    source: str | None = None  # the fully qualified name of the node followed
    hardware_id: str = ""
    health: Mapping[str, Concern] = dataclasses.field(default_factory=lambda: MappingProxyType({}))
    latest: Mapping[str, str] = dataclasses.field(default_factory=lambda: MappingProxyType({}))
    latest_s: float = math.nan
    frame: Mapping[str, str] = dataclasses.field(default_factory=lambda: MappingProxyType({}))
    frame_level: int = -1
    frame_message: str = ""
    n_statuses: int = 0
    n_frames: int = 0
    status_s: float = math.nan
    frame_s: float = math.nan
    other_sources: frozenset[str] = frozenset()
    history: tuple[HistoryEntry, ...] = ()  # most recent first
    distance: float = 0.0  # of vo/odometry (metres once established)
    position: tuple[float, float, float] | None = None
    vo_distance: float = 0.0  # of vo/odometry/vo_units (VO units)
    vo_position: tuple[float, float, float] | None = None
    n_odometry: int = 0
    odometry_s: float = math.nan

    @property
    def has_status(self) -> bool:
        return self.n_statuses > 0

    @property
    def has_health(self) -> bool:
        return bool(self.health)

    @property
    def snapshot_complete(self) -> bool:
        """The node's health is known, and a frame's record too unless the node has processed none (a managed
        node without a session has only its lifecycle status)."""
        tracking = self.health.get(health.TRACKING)
        if tracking is None:
            return health.LIFECYCLE in self.health
        return self.n_frames > 0 or tracking.values.get("frames_processed", "0") == "0"

    @property
    def level(self) -> int:
        """The worst level of the node's health (an aggregator's view); the latest frame's without any."""
        if self.health:
            return max(c.level for c in self.health.values())
        return self.frame_level

    @property
    def message(self) -> str:
        """'<concern>: <message>' of the worst health status (the first concern of equal levels)."""
        if not self.health:
            return self.frame_message
        worst = max(self.health.values(), key=lambda c: c.level)
        concern = next(k for k, c in self.health.items() if c is worst)
        return f"{concern}: {worst.message}"

    @property
    def units(self) -> str:
        """'m' or 'vo': of the latest scale figures (the scale status or a newer frame), 'vo' when none."""
        return self.scale_values().get("units", "vo")

    def scale_values(self) -> Mapping[str, str]:
        """The scale status's key/values (the configured source, even before a frame), with the latest
        frame's scale keys over them when that frame is newer."""
        scale = self.health.get(health.SCALE)
        values = dict(scale.values) if scale is not None else {}
        if "units" in self.frame and (scale is None or self.frame_s >= scale.t_s):
            values.update({k: self.frame[k] for k in _SCALE_KEYS if k in self.frame})
        return values

    def _follows(self, name: str) -> tuple[str, str] | None:
        """(node, concern) when ``name`` is a status of the node followed (or of the first one seen)."""
        if not is_vo_status(name, self.node_name, self.namespace):
            return None
        return split_status_name(name)

    def _noted(self, node: str, now_s: float, level: int, message: str, hardware_id: str) -> MonitorState:
        history = _add_history(self.history, message, level, now_s) if level >= DiagnosticLevel.WARN \
            else self.history
        return dataclasses.replace(self, source=node, hardware_id=hardware_id or self.hardware_id,
                                   n_statuses=self.n_statuses + 1, status_s=now_s, history=history)

    def update_from_health(self, name: str, level: int | bytes | bytearray, message: str,
                           values: Mapping[str, str] | Iterable[tuple[str, str]], now_s: float,
                           hardware_id: str = "") -> MonitorState:
        """Fold in one status of /diagnostics; statuses that are not this VO's are only noted by name."""
        parts = self._follows(name)
        if parts is None:
            return self
        node, concern = parts
        if self.source is not None and node != self.source:
            return dataclasses.replace(self, other_sources=self.other_sources | {node})
        lvl, kv = level_value(level), _mapping(values)
        state = self._noted(node, now_s, lvl, f"{concern}: {message}", hardware_id)
        changes: dict[str, Any] = {"health": MappingProxyType({**self.health, concern: Concern(lvl, message, kv,
                                                                                               now_s)})}
        if concern == health.INPUT:
            changes.update(latest=kv, latest_s=now_s)
        return dataclasses.replace(state, **changes)

    def update_from_frame(self, name: str, level: int | bytes | bytearray, message: str,
                          values: Mapping[str, str] | Iterable[tuple[str, str]], now_s: float,
                          hardware_id: str = "") -> MonitorState:
        """Fold in one per-frame status (vo/frame_status: '<node>: tracking' with the frame record)."""
        parts = self._follows(name)
        if parts is None:
            return self
        node = parts[0]
        if self.source is not None and node != self.source:
            return dataclasses.replace(self, other_sources=self.other_sources | {node})
        lvl, kv = level_value(level), _mapping(values)
        state = self._noted(node, now_s, lvl, message, hardware_id)
        return dataclasses.replace(state, frame=kv, frame_level=lvl, frame_message=message, frame_s=now_s,
                                   n_frames=self.n_frames + 1, latest=kv, latest_s=now_s)

    def update_from_odometry(self, position: Iterable[float], now_s: float, vo_units: bool = False) -> MonitorState:
        """Fold in one odometry position (x, y, z in the odometry frame) of vo/odometry, or with ``vo_units`` of
        vo/odometry/vo_units; the step length adds to that topic's distance."""
        p = tuple(float(v) for v in position)
        if len(p) != 3 or not all(math.isfinite(v) for v in p):
            return self  # a broken message must not poison the sum
        if vo_units:
            step = math.dist(p, self.vo_position) if self.vo_position is not None else 0.0
            return dataclasses.replace(self, vo_position=(p[0], p[1], p[2]), vo_distance=self.vo_distance + step,
                                       odometry_s=now_s)
        step = math.dist(p, self.position) if self.position is not None else 0.0
        return dataclasses.replace(self, position=(p[0], p[1], p[2]), distance=self.distance + step,
                                   n_odometry=self.n_odometry + 1, odometry_s=now_s)

    @property
    def travelled(self) -> tuple[float, tuple[float, float, float] | None]:
        """(distance, position) in :attr:`units`: vo/odometry's in metres, vo/odometry/vo_units' in VO units."""
        return (self.distance, self.position) if self.units == "m" else (self.vo_distance, self.vo_position)

    def render_text(self, now_s: float | None = None) -> str:
        """The snapshot as plain text. ``now_s`` (wall clock) dates the ages; default: the latest update."""
        if now_s is None:
            known = [t for t in (self.status_s, self.odometry_s) if math.isfinite(t)]
            now_s = max(known) if known else 0.0
        if not self.has_status:
            return (f"waiting for a VO status {_wanted(self.node_name, self.namespace)} on /diagnostics or "
                    f"{FRAME_STATUS_TOPIC} ...")
        f, lt = self.frame, self.latest
        lines = [f"{self.source}" + (f"  (hardware {self.hardware_id})" if self.hardware_id else "")]
        age = now_s - self.status_s
        if age >= SILENT_AFTER_S:
            lines.append(f"  !! no status for {age:.1f} s: is the node still running?")
        lines.append(f"  level       {level_name(self.level)}")
        lines.append(f"  reason      {self.message or 'n/a'}")
        if self.health:
            lines.append("  health      " + "  ".join(f"{k} {level_name(c.level)} ({c.message})"
                                                      for k, c in self.health.items()))
        state = f.get("state", "n/a")
        frame_line = f"  state       {state}  frame {_int(f, 'index')}  stamp {_float(f, 'stamp', 3)}"
        if f and self.frame_s < self.latest_s:
            frame_line += f"  (last frame {now_s - self.frame_s:.1f} s ago)"
        lines.append(frame_line)
        if f:  # the frame's own words (its reason), beside the health's fixed messages
            lines.append(f"  why         {self.frame_message or 'n/a'}")
        lines.append(f"  input       {_float(lt, 'input_rate_hz', 1, ' Hz')}  received {_int(lt, 'frames_received')}"
                     f"  dropped {_int(lt, 'dropped_frames')}  queue {_int(lt, 'queue_depth')}"
                     f"  last image {_float(lt, 'time_since_last_image_s', 2, ' s ago')}")
        lines.append(f"  latency     {_float(lt, 'latency_ms', 1, ' ms')}")
        lines.append(f"  matches     features {_int(f, 'n_features')}  tracked {_int(f, 'n_tracked')}"
                     f"  inliers {_int(f, 'n_inliers')}  inlier ratio {_float(f, 'inlier_ratio', 3)}")
        lines.append(f"  model       {f.get('model', 'n/a')}  RH {_float(f, 'rh', 3)}"
                     f"  parallax {_float(f, 'median_parallax_deg', 2, ' deg')}")
        lines.append(f"  map         keyframes {_int(f, 'n_keyframes')}  triangulated {_int(f, 'n_triangulated')}"
                     f"  reproj {_float(f, 'median_reproj_err_px', 2, ' px')}"
                     f"  depth>0 {_float(f, 'positive_depth_ratio', 2)}")
        lines.extend(_scale_lines(self.scale_values()))
        distance, position = self.travelled
        pos = " ".join(f"{v:.3f}" for v in position) if position is not None else "n/a"
        lines.append(f"  odometry    distance {distance:.3f} {units_label(self.units)}  position {pos}"
                     f"  messages {self.n_odometry}")
        lines.append(f"  updated     {_clock(self.status_s)}  ({age:.1f} s ago)  statuses {self.n_statuses}"
                     f"  frames {self.n_frames}")
        if self.other_sources:
            lines.append(f"  also seen   {', '.join(sorted(self.other_sources))} (choose with --node-name)")
        lines.append(f"recent warnings/errors (last {HISTORY_LENGTH} reasons)")
        if not self.history:
            lines.append("  none")
        for h in self.history:
            lines.append(f"  {level_name(h.level):<5}  x{h.count:<5} {h.message}   last {_clock(h.last_s)}"
                         f" ({now_s - h.last_s:.1f} s ago)")
        return "\n".join(lines)


_SCALE_KEYS = ("units", "scale_source", "metric_scale", "scale", "scale_rel_std", "floor_pitch_deg", "floor_roll_deg",
               "scale_reason")


def units_label(units: str) -> str:
    """How lengths are labelled: 'm' for metres, '(VO units)' otherwise."""
    return "m" if units == "m" else "(VO units)"


def _scale_lines(v: Mapping[str, str]) -> list[str]:
    """The ``scale`` line (source, metric or not, metres per VO unit and its relative std), the floor's
    pitch/roll when the source measures them, and why the source gave no measurement when it says."""
    source = v.get("scale_source", "none") or "none"
    metric = v.get("units") == "m"  # as metric_scale: established, positions are metres
    rel = _number(v, "scale_rel_std")
    rel_text = f" ±{100.0 * rel:.1f} %" if rel is not None else ""
    if metric:
        scale = _number(v, "scale")
        text = f"metric, {scale:.4g} m/unit{rel_text}" if scale is not None else "metric"
    elif source == "none":
        text = "VO units"
    else:
        text = "not established yet: VO units (position held)"
    lines = [f"  scale       {source}: {text}"]
    pitch, roll = _number(v, "floor_pitch_deg"), _number(v, "floor_roll_deg")
    if pitch is not None or roll is not None:
        lines.append(f"  floor       pitch {_float(v, 'floor_pitch_deg', 2, ' deg')}"
                     f"  roll {_float(v, 'floor_roll_deg', 2, ' deg')}")
    reason = v.get("scale_reason", "")
    if reason and reason != "None":
        lines.append(f"  scale note  {reason}")
    return lines


def _add_history(history: tuple[HistoryEntry, ...], message: str, level: int,
                 now_s: float) -> tuple[HistoryEntry, ...]:
    key = reason_key(message)
    old = next((h for h in history if h.key == key), None)
    entry = HistoryEntry(key, message, level, 1, now_s, now_s) if old is None else \
        dataclasses.replace(old, message=message, level=level, count=old.count + 1, last_s=now_s)
    rest = tuple(h for h in history if h.key != key)
    return (entry, *rest)[:HISTORY_LENGTH]


def _number(values: Mapping[str, str], key: str) -> float | None:
    """A key/value as a finite float; missing, 'None' (a non-finite record value) and 'nan' give None."""
    try:
        v = float(values[key])
    except (KeyError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _float(values: Mapping[str, str], key: str, digits: int, unit: str = "") -> str:
    v = _number(values, key)
    return "n/a" if v is None else f"{v:.{digits}f}{unit}"


def _int(values: Mapping[str, str], key: str) -> str:
    v = _number(values, key)
    return "n/a" if v is None else str(round(v))


def _clock(t: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(t)) if math.isfinite(t) else "n/a"


# -- display -----------------------------------------------------------------------------------------------
_LEVEL_STYLES = {"OK": "bold green", "WARN": "bold yellow", "ERROR": "bold red", "STALE": "bold magenta"}


def _rich_view(state: MonitorState, now_s: float) -> Any:
    """The snapshot text in a panel, level words coloured and the border in the colour of the level."""
    from rich.panel import Panel
    from rich.text import Text

    text = Text(state.render_text(now_s))
    for name, style in _LEVEL_STYLES.items():
        text.highlight_regex(rf"(?<![\w-]){name}(?![\w-])", style)
    text.highlight_regex(r"!!.*", "bold red")
    border = _LEVEL_STYLES.get(level_name(state.level), "blue").removeprefix("bold ")
    return Panel(text, title="epi-vo monitor", subtitle="Ctrl-C to quit", border_style=border, expand=False)


def _wanted(node_name: str | None, namespace: str | None) -> str:
    """The status names looked for, as shown to the user: '/robot1/<node>: tracking|input|...'."""
    concerns = "|".join(health.CONCERNS[:4]) + "|..."
    if node_name and node_name.startswith("/"):
        return f"'{node_name}: {concerns}'"
    node = node_name or "<node>"
    if namespace is None:
        return f"'{node}: {concerns}'"
    return f"'{('/' + namespace.strip('/')).rstrip('/')}/{node}: {concerns}'"


def frame_status_topic(node_name: str | None, namespace: str | None) -> str:
    """Where the followed node publishes its per-frame statuses: vo/frame_status in its namespace."""
    if node_name and node_name.startswith("/"):
        namespace = namespace_of(node_name.rstrip("/"))
    return f"{('/' + (namespace or '/').strip('/')).rstrip('/')}/{FRAME_STATUS_TOPIC}"


def _timeout_message(args: argparse.Namespace, namespace: str | None = None) -> str:
    who = _wanted(args.node_name, namespace)
    domain = os.environ.get("ROS_DOMAIN_ID", "unset (0)")
    discovery = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "unset")
    return (f"epi-vo monitor: no VO status {who} on /diagnostics within {args.timeout:g} s "
            f"(ROS_DOMAIN_ID={domain}, ROS_AUTOMATIC_DISCOVERY_RANGE={discovery}); is vo_node running?")


class _Subscriber:
    """The rclpy side: a node whose callbacks replace ``self.state`` (read by the display thread as a whole)."""

    def __init__(self, context: Any, args: argparse.Namespace) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        # Several monitors may run at once: a unique node name avoids the duplicate-name warning.
        self.node = Node(f"epi_vo_monitor_{os.getpid()}", context=context)
        # The VO node followed is the one in the namespace of the odometry topic watched (two cameras in
        # two namespaces do not mix); an absolute --node-name says it all by itself.
        self.odometry_topic = self.node.resolve_topic_name(args.odometry_topic)
        absolute = bool(args.node_name) and args.node_name.startswith("/")
        self.namespace = None if absolute else odometry_namespace(self.odometry_topic)
        self.state = MonitorState(node_name=args.node_name, namespace=self.namespace)
        # Reliable and deep, like the node's publishers: the warning counts should not miss statuses.
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, qos)
        self.node.create_subscription(DiagnosticArray, frame_status_topic(args.node_name, self.namespace),
                                      self._on_frame_status, qos)
        self.node.create_subscription(Odometry, args.odometry_topic, self._on_odometry, qos)
        # The node of that namespace publishes the motion in VO units beside it (its vo/odometry/vo_units).
        vo_units_topic = args.vo_units_topic
        if vo_units_topic is None:
            vo_units_topic = odometry_namespace(self.odometry_topic).rstrip("/") + "/" + VO_UNITS_TOPIC
        self.node.create_subscription(Odometry, vo_units_topic, self._on_vo_units, qos)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)

    def _on_diagnostics(self, msg: Any) -> None:
        self._take(msg, MonitorState.update_from_health)

    def _on_frame_status(self, msg: Any) -> None:
        self._take(msg, MonitorState.update_from_frame)

    def _take(self, msg: Any, update: Callable[..., MonitorState]) -> None:
        """Every status of a DiagnosticArray into the state, with ``update`` (the /diagnostics or the per-frame one)."""
        state, now = self.state, time.time()
        for s in msg.status:
            state = update(state, s.name, s.level, s.message, [(kv.key, kv.value) for kv in s.values], now,
                           s.hardware_id)
        self.state = state

    def _on_odometry(self, msg: Any) -> None:
        p = msg.pose.pose.position
        self.state = self.state.update_from_odometry((p.x, p.y, p.z), time.time())

    def _on_vo_units(self, msg: Any) -> None:
        p = msg.pose.pose.position
        self.state = self.state.update_from_odometry((p.x, p.y, p.z), time.time(), vo_units=True)

    def spin_until(self, predicate: Any, deadline: float, step_s: float = 0.1) -> bool:
        """Spin until ``predicate()`` (True) or the monotonic ``deadline`` (False)."""
        while not predicate():
            if time.monotonic() >= deadline:
                return False
            self.executor.spin_once(timeout_sec=min(step_s, max(0.0, deadline - time.monotonic())))
        return True

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def _show(sub: _Subscriber, deadline: float) -> int:
    """Live view until Ctrl-C; 1 when no VO status arrived before ``deadline``.

    On a terminal: rich.live redrawing at 4 Hz (in place, no alternate screen, so it works over SSH and
    the last view stays in the scrollback). Otherwise (a pipe, a log file, or rich not installed): a
    plain snapshot every second.
    """
    if sys.stdout.isatty() and importlib.util.find_spec("rich") is not None:
        from rich.console import Console
        from rich.live import Live

        with Live(get_renderable=lambda: _rich_view(sub.state, time.time()), console=Console(),
                  refresh_per_second=4, screen=False, transient=False):
            if not sub.spin_until(lambda: sub.state.has_status, deadline):
                return 1
            sub.spin_until(lambda: False, math.inf)
        return 0
    if not sub.spin_until(lambda: sub.state.has_status, deadline):
        return 1
    while True:
        sys.stdout.write(sub.state.render_text(time.time()) + "\n\n")
        sys.stdout.flush()
        sub.spin_until(lambda: False, time.monotonic() + 1.0)


def run(args: argparse.Namespace) -> int:
    """``epi-vo monitor``: 0 on Ctrl-C (or after the ``--once`` snapshot), 1 when ``--timeout`` expired."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    checks.topic_name(args.odometry_topic, "--odometry-topic")
    if args.vo_units_topic is not None:
        checks.topic_name(args.vo_units_topic, "--vo-units-topic")
    if args.node_name is not None:
        checks.node_name(args.node_name, "--node-name")
    if args.timeout is not None:
        checks.number(args.timeout, "--timeout", positive=True, maximum=threading.TIMEOUT_MAX)
    # As in `epi-vo play`: without rclpy's handlers, SIGINT/SIGTERM raise KeyboardInterrupt in the spin
    # loop and the context stays valid for a clean shutdown. Installed explicitly because a shell starts
    # background jobs with SIGINT ignored.
    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, _raise_keyboard_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    sub: _Subscriber | None = None
    timed_out = False
    try:
        sub = _Subscriber(context, args)
        deadline = time.monotonic() + args.timeout if args.timeout is not None else math.inf
        if args.once:
            # The snapshot waits for the node's health (once a second) and, if it has processed frames, one of
            # them; at the deadline whatever arrived is shown.
            complete = sub.spin_until(lambda: sub.state.snapshot_complete, deadline)
            timed_out = not complete and not sub.state.has_status
            if not timed_out:
                sys.stdout.write(sub.state.render_text(time.time()) + "\n")
        else:
            timed_out = _show(sub, deadline) != 0
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if sub is not None:
            sub.close()
        rclpy.try_shutdown(context=context)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if timed_out:
        print(_timeout_message(args, sub.namespace if sub is not None else None), file=sys.stderr)
        return 1
    return 0


def _raise_keyboard_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt
