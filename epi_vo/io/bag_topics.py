"""Which topic of a rosbag2 bag is which, and what every reader of one needs (no rclpy): the message type
names, the type store (message definitions for bags recorded without them, and for writing), the errors
rosbags raises, and the choice of a topic of each kind (the only candidate, or the one named).

``epi_vo.io.bagio`` (the replay's reader) and ``epi_vo.io.play_bag`` (the player's) choose topics the same way.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from rosbags.highlevel import AnyReaderError
from rosbags.rosbag2 import ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from epi_vo.core.errors import BagError

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
POINT_CLOUD2_TYPE = "sensor_msgs/msg/PointCloud2"
PATH_TYPE = "nav_msgs/msg/Path"
DIAGNOSTIC_ARRAY_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
TF_MESSAGE_TYPE = "tf2_msgs/msg/TFMessage"


# Message definitions for serialising output and for bags recorded without them (old sqlite3).
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

# What rosbags raises for a missing, truncated or corrupt bag (it wraps most parser errors in its own;
# a metadata.yaml that is not UTF-8, or holds a field of the wrong type, comes out as the builtin errors).
READ_ERRORS = (
    AnyReaderError,
    ReaderError,
    SerdeError,
    OSError,
    UnicodeDecodeError,
    KeyError,
    TypeError,
    ValueError,
)
# What deserialising the CDR bytes of one damaged message can raise (AnyReader.deserialize wraps
# rosbags' SerdeError in AnyReaderError): that message is bad input, the bag goes on.
DECODE_ERRORS = (
    AnyReaderError,
    SerdeError,
    ValueError,
    TypeError,
    IndexError,
    KeyError,
    AttributeError,
    OverflowError,
    struct.error,
)


@dataclass(frozen=True)
class TopicKind:
    """A kind of topic a reader looks for: its message types and the flag (or parameter) that names it."""

    label: str  # for messages: 'sensor_msgs/Image or CompressedImage'
    msgtypes: frozenset[str]
    flag: str  # command-line flag that chooses the topic


IMAGE_KIND = TopicKind(
    "sensor_msgs/Image or CompressedImage",
    frozenset({IMAGE_TYPE, COMPRESSED_IMAGE_TYPE}),
    "--image-topic",
)
CAMERA_INFO_KIND = TopicKind(
    "sensor_msgs/CameraInfo", frozenset({CAMERA_INFO_TYPE}), "--camera-info-topic"
)
GT_KIND = TopicKind(
    "geometry_msgs/PoseStamped or nav_msgs/Odometry",
    frozenset({POSE_STAMPED_TYPE, ODOMETRY_TYPE}),
    "--gt-topic",
)


WHEEL_KIND = TopicKind("nav_msgs/Odometry", frozenset({ODOMETRY_TYPE}), "wheel_odometry_topic")


def describe_topics(topic_types: dict[str, str | None]) -> str:
    if not topic_types:
        return "(none)"
    return ", ".join(
        f"{name} ({msgtype or 'mixed types'})" for name, msgtype in topic_types.items()
    )


def camera_namespace(topic: str) -> str:
    """'/cam0/image_raw', '/cam0/image_raw/compressed' and '/cam0/camera_info' all give '/cam0'."""
    topic = topic.rstrip("/")
    topic = topic.removesuffix("/compressed")
    return topic.rsplit("/", 1)[0]


def choose_topic(
    topic_types: dict[str, str | None],
    kind: TopicKind,
    explicit: str | None,
    sibling_of: str | None = None,
) -> str | None:
    """The topic of ``kind``: ``explicit`` if given, else the only candidate; None if none.

    With several candidates and ``sibling_of`` set, the single candidate in the same namespace is
    taken (image_transport pairs '/cam0/image_raw' with '/cam0/camera_info'); otherwise BagError
    lists them.
    """
    if explicit is not None:
        if explicit not in topic_types:
            msg = (
                f"{kind.flag} {explicit!r} is not in the bag; "
                f"topics: {describe_topics(topic_types)}"
            )
            raise BagError(msg)
        if topic_types[explicit] not in kind.msgtypes:
            msg = (
                f"{kind.flag} {explicit!r} has type {topic_types[explicit]}, expected {kind.label}"
            )
            raise BagError(msg)
        return explicit

    candidates = [name for name, msgtype in topic_types.items() if msgtype in kind.msgtypes]
    if len(candidates) <= 1:
        return candidates[0] if candidates else None
    if sibling_of is not None:
        siblings = [x for x in candidates if camera_namespace(x) == camera_namespace(sibling_of)]
        if len(siblings) == 1:
            return siblings[0]
    msg = (
        f"bag has several {kind.label} topics: {', '.join(candidates)}; choose one with {kind.flag}"
    )
    raise BagError(msg)


def recorded_topic_name(name: str, node_name: str = "vo_node") -> str:
    """The name a node's topic parameter has in a bag recorded from the root namespace: a relative name
    resolves there ('odom' is '/odom'), a private one under the node ('~/odom' is '/vo_node/odom'), as rcl
    expands them for a node ``node_name`` in '/'. A bag stores fully qualified names only."""
    if name.startswith("/"):
        return name
    if name == "~" or name.startswith("~/"):
        return f"/{node_name}{name[1:]}"
    return f"/{name}"


_GT_WORDS = ("gt", "groundtruth")


def is_ground_truth_name(topic: str) -> bool:
    """Whether a topic is named as ground truth: a part of its name (between '/', '_' or '-', any case) is
    ``gt`` or ``groundtruth``, or two neighbouring parts are ``ground`` and ``truth`` (``/ground_truth/pose``,
    ``/gt/odom``, ``/mocap/pose_gt``). A pose topic named otherwise (``/wheel/odom``, ``/odom``,
    ``/vicon/pose``) is the robot's own estimate or a sensor as far as a bag can tell: ground truth only
    when chosen with ``--gt-topic``."""
    words = [w for w in re.split(r"[/_\-]+", topic.lower()) if w]
    pairs = ("".join(words[i:i + 2]) for i in range(len(words) - 1))
    return any(w in _GT_WORDS for w in words) or "groundtruth" in pairs


def ground_truth_topic(topic_types: dict[str, str | None], explicit: str | None,
                        wheel_topic: str | None) -> str | None:
    """The ground-truth topic (see :func:`open_camera_bag`); None when the bag has none."""
    if explicit is not None:
        choose_topic(topic_types, GT_KIND, explicit)
        if explicit == wheel_topic:
            msg = (f"--gt-topic {explicit!r} is the wheel odometry topic, the scale source: ground truth must "
                   "be independent of what it judges")
            raise BagError(msg)
        return explicit
    named = {k: v for k, v in topic_types.items() if k != wheel_topic and is_ground_truth_name(k)}
    return choose_topic(named, GT_KIND, None)


def required_topic(
    topic_types: dict[str, str | None],
    kind: TopicKind,
    explicit: str | None,
    sibling_of: str | None = None,
) -> str:
    """``choose_topic`` for a kind the bag must have."""
    topic = choose_topic(topic_types, kind, explicit, sibling_of)
    if topic is None:
        msg = f"bag has no {kind.label} topic; topics: {describe_topics(topic_types)}"
        raise BagError(msg)
    return topic
