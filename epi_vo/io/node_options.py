"""The ROS node's own parameters (frame ids, extrinsics, transport, QoS, ...), without rclpy.

The pipeline's knobs live in :class:`epi_vo.core.config.VoConfig`; these are the ones only ``vo_node``
reads. They sit here, below the ROS layer, so that ``epi-vo params`` can print them (with their doc
lines) into ``config/epi_vo.yaml`` and the offline tools can accept them in a parameter file, while
``epi_vo.ros.node`` declares them as ROS parameters from the same table.

Parameters that decide what the node subscribes to, publishes or how (topics, transport, QoS, frame
ids, extrinsics, ...) need a restart: the node declares them read-only. The others (``RUNTIME_OPTIONS``,
and every pipeline knob but ``RESTART_PIPELINE_KNOBS``) may be changed while it runs, through
:func:`apply_changes`, the same validation as at start-up.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import Any

from numpy.typing import NDArray

from epi_vo.core.config import PIPELINE_NAMES, VoConfig, choices_of, from_dict, shown
from epi_vo.core.errors import ConfigError
from epi_vo.core.odometry import T_base_cam_from_params


class ImageTransport(enum.StrEnum):
    """Which image topics the node subscribes to (converted from the parameter's text once, in NodeOptions)."""

    AUTO = "auto"  # both; the first to deliver is kept
    RAW = "raw"  # camera/image_raw (sensor_msgs/Image)
    COMPRESSED = "compressed"  # camera/image_raw/compressed (sensor_msgs/CompressedImage)


class QosReliability(enum.StrEnum):
    """The input subscriptions' QoS reliability (the node maps it onto rclpy's ReliabilityPolicy)."""

    BEST_EFFORT = "best_effort"  # sensor data
    RELIABLE = "reliable"


IMAGE_TRANSPORTS = choices_of(ImageTransport)
QOS_RELIABILITIES = choices_of(QosReliability)


@dataclass(frozen=True)
class NodeOptions:
    """The node's own parameters (the pipeline's come from VoConfig); ``NODE_DOCS`` says what each does."""

    frame_id: str = "odom"
    child_frame_id: str = "base_link"
    map_frame_id: str = ""
    camera_xyz: tuple[float, ...] = (0.0, 0.0, 0.0)
    camera_rpy: tuple[float, ...] = (0.0, 0.0, 0.0)
    tf_timeout_s: float = 2.0
    image_transport: ImageTransport = ImageTransport.AUTO
    qos_reliability: QosReliability = QosReliability.BEST_EFFORT
    qos_depth: int = 5
    queue_size: int = 2
    process_every_frame: bool = False
    queue_max_mb: float = 256.0
    publish_tf: bool = True
    publish_debug_image: bool = False
    path_max_length: int = 1000
    watchdog_timeout_s: float = 1.0
    camera_info_wait_s: float = 0.2
    hardware_id: str = ""

    def __post_init__(self) -> None:
        """A mode given as its text becomes its member (a text no member has is left for
        :func:`node_option_problems` to name)."""
        for name, mode in _NODE_MODES.items():
            value = getattr(self, name)
            if isinstance(value, str) and not isinstance(value, mode) and value in choices_of(mode):
                object.__setattr__(self, name, mode(value))


_NODE_MODES: dict[str, type[enum.StrEnum]] = {"image_transport": ImageTransport, "qos_reliability": QosReliability}


@dataclass(frozen=True)
class CameraExtrinsic:
    """A camera mounting declared by ``camera_xyz`` / ``camera_rpy`` (what vo_node takes when TF has none), for
    the offline tools: the replay's odometry and floor search use it as the node does."""

    camera_xyz: tuple[float, ...]
    camera_rpy: tuple[float, ...]

    @property
    def T_base_cam(self) -> NDArray[Any]:
        """4x4, camera optical frame -> base (the optical rotation appended)."""
        return T_base_cam_from_params(self.camera_xyz, self.camera_rpy)


NODE_DOCS: dict[str, str] = {
    "frame_id": "odometry frame (header.frame_id of vo/odometry, vo/points, vo/path, and the parent of the TF)",
    "map_frame_id": "with the windowed adjustment on: '' publishes its corrections in vo/odometry's pose (it "
                    "jumps at adjusted keyframes); a frame name (e.g. 'map') keeps vo/odometry continuous and "
                    "broadcasts the corrections as the map_frame_id -> frame_id TF (REP-105; needs tf2_ros and "
                    "publish_tf)",
    "child_frame_id": "robot base frame (child_frame_id of vo/odometry); the camera extrinsic is looked up "
                      "from it",
    "camera_xyz": "camera position in child_frame_id (m); used when TF has no child_frame_id <- image "
                  "frame_id transform",
    "camera_rpy": "camera body orientation in child_frame_id, roll pitch yaw (rad; the optical rotation is "
                  "added); used as camera_xyz",
    "tf_timeout_s": "how long the first image waits for TF child_frame_id <- its header.frame_id before "
                    "camera_xyz / camera_rpy are used; a TF that comes later or moves is followed after "
                    "(s; 0: never look up TF)",
    "image_transport": "'auto' (subscribe to raw and compressed, use whichever arrives first), 'raw' "
                       "(sensor_msgs/Image) or 'compressed' (sensor_msgs/CompressedImage)",
    "qos_reliability": "input QoS reliability: 'best_effort' (sensor data) or 'reliable'",
    "qos_depth": "input QoS history depth",
    "queue_size": "frames waiting for processing in live mode; older ones are dropped and counted",
    "process_every_frame": "keep every frame (bag playback): the queue grows instead of dropping, up to "
                           "queue_max_mb",
    "queue_max_mb": "memory the frames waiting for processing may take, in either mode (MB of received images); "
                    "beyond it the oldest waiting frame is dropped, counted and reported (diagnostics WARN)",
    "publish_tf": "broadcast frame_id -> child_frame_id on /tf (needs tf2_ros)",
    "publish_debug_image": "publish vo/debug_image with tracks, inliers and epipolar lines",
    "path_max_length": "poses kept in vo/path",
    "watchdog_timeout_s": "no image for this long: diagnostics WARN (3x: STALE)",
    "camera_info_wait_s": "how long an image waits for its camera_info (s, in image stamps or on the node's "
                          "clock) before the nearest earlier one is used",
    "hardware_id": "hardware_id of the diagnostics statuses ('': the image's header.frame_id)",
}
NODE_CHOICES: dict[str, tuple[str, ...]] = {name: choices_of(mode) for name, mode in _NODE_MODES.items()}
NODE_OPTION_NAMES: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(NodeOptions))

# Node options that may change while the node runs (applied at once); every other one is read-only.
RUNTIME_OPTIONS: tuple[str, ...] = ("queue_size", "process_every_frame", "queue_max_mb", "watchdog_timeout_s")
# Pipeline knobs that decide a subscription (wheel odometry): read-only too. The other knobs may change
# while the node runs; they are applied at the next frame.
RESTART_PIPELINE_KNOBS: tuple[str, ...] = ("scale_source", "wheel_odometry_topic")
_VECTORS = ("camera_xyz", "camera_rpy")


def is_read_only(name: str) -> bool:
    """Whether changing ``name`` needs a restart of the node (declared read-only)."""
    if name in NODE_OPTION_NAMES:
        return name not in RUNTIME_OPTIONS
    return name in RESTART_PIPELINE_KNOBS


def frame_name_problem(name: object) -> str | None:
    """Why ``name`` cannot be a TF frame id, or None. tf2's own rules (not empty, no leading '/': tf2 refuses
    such ids in every lookup), and no whitespace or control character, which no frame id has and which
    RViz and the tf2 tools cannot name."""
    if not isinstance(name, str) or not name:
        return "empty" if name == "" else "not a string"
    if name.startswith("/"):
        return "tf2 frame ids must not start with '/'"
    if any(c.isspace() or not c.isprintable() for c in name):
        return "whitespace or a control character"
    return None


def node_option_problems(values: dict[str, Any]) -> list[str]:
    """Every bad value among ``{name: value}`` of node options (unknown names are not looked at)."""
    problems: list[str] = []
    for name, choices in NODE_CHOICES.items():
        v = values.get(name)
        if v is not None and v not in choices:
            problems.append(f"{name}={v!r} (choose one of {', '.join(choices)})")
    for name in _VECTORS:
        v = values.get(name)
        if v is None:
            continue
        try:
            shown: object = list(v)
            ok = len(v) == 3 and all(not isinstance(x, bool) and math.isfinite(float(x)) for x in v)
        except (TypeError, ValueError):
            shown, ok = v, False
        if isinstance(v, str):
            shown, ok = v, False
        if not ok:
            problems.append(f"{name}={shown!r} (expected 3 finite numbers)")
    for name in ("qos_depth", "queue_size", "path_max_length"):
        v = values.get(name)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            problems.append(f"{name}={v!r} (an integer, minimum 1)")
    for name in ("watchdog_timeout_s", "camera_info_wait_s", "queue_max_mb"):
        v = values.get(name)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v)
                                                                                           and v > 0)):
            problems.append(f"{name}={v!r} (must be > 0)")
    v = values.get("tf_timeout_s")
    if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v)
                                                                                       and 0 <= v <= 3600)):
        problems.append(f"tf_timeout_s={v!r} (0 to 3600 s)")
    for name in ("frame_id", "child_frame_id"):
        v = values.get(name)
        if v is not None and (why := frame_name_problem(v)) is not None:
            problems.append(f"{name}={v!r} (not a frame name: {why})")
    v = values.get("map_frame_id")
    if v is not None and v != "":
        if (why := frame_name_problem(v)) is not None:
            problems.append(f"map_frame_id={v!r} ('' or a frame name: {why})")
        elif v in (values.get("frame_id", NodeOptions.frame_id),
                   values.get("child_frame_id", NodeOptions.child_frame_id)):
            problems.append(f"map_frame_id={v!r} (must differ from frame_id and child_frame_id)")
    return problems


def make_node_options(values: dict[str, Any], base: NodeOptions | None = None) -> NodeOptions:
    """NodeOptions from ``{name: value}`` (lists become tuples); ConfigError naming every bad value."""
    problems = node_option_problems(values)
    if problems:
        raise ConfigError("invalid vo_node parameters: " + "; ".join(problems))
    kwargs = {}
    for k, v in values.items():
        if k in _VECTORS:  # a list from YAML, an array.array from rclpy
            v = tuple(float(x) for x in v)
        elif isinstance(getattr(NodeOptions, k, None), float) and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        kwargs[k] = v
    return dataclasses.replace(base or NodeOptions(), **kwargs)


def apply_changes(cfg: VoConfig, opts: NodeOptions, changes: dict[str, Any]) -> tuple[VoConfig, NodeOptions]:
    """The config and node options after a runtime change ``{name: value}``, validated as at start-up.

    Raises :class:`ConfigError` naming every refused change: a read-only parameter (needs a restart), a
    value out of range or not among the choices. Names that are neither pipeline knobs nor node options
    (``use_sim_time``, ...) are left to ROS and ignored here.
    """
    fixed = sorted(n for n in changes if is_read_only(n))
    problems = [f"{n} is read-only (restart the node to change it)" for n in fixed]
    knobs = {k: v for k, v in changes.items() if k in PIPELINE_NAMES and k not in fixed}
    node = {k: v for k, v in changes.items() if k in NODE_OPTION_NAMES and k not in fixed}
    new_cfg = cfg
    try:
        new_cfg = from_dict(knobs, base=cfg)
    except ConfigError as exc:
        problems.append(str(exc).removeprefix("invalid epi_vo parameters: "))
    problems += node_option_problems(node)
    if problems:
        raise ConfigError("; ".join(problems))
    return new_cfg, make_node_options(node, opts)


def changed_names(old: VoConfig, new: VoConfig) -> list[str]:
    """'name=value' for every knob that differs between two configs, in declaration order."""
    return [f"{n}={shown(getattr(new, n))}" for n in PIPELINE_NAMES if getattr(old, n) != getattr(new, n)]
