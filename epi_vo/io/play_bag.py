"""A rosbag2 bag opened for ``epi-vo play``: every topic ``vo_node`` consumes, as raw CDR bytes (no rclpy).

The topics are chosen as ``epi-vo replay`` chooses them (:mod:`epi_vo.io.bag_topics`):

- the image (sensor_msgs/Image or CompressedImage) and its camera_info: the only ones, or the named ones;
- the wheel odometry (nav_msgs/Odometry): the named one, else the only Odometry topic not named as ground
  truth (:func:`~epi_vo.io.bag_topics.is_ground_truth_name`), else none;
- ``/tf`` and ``/tf_static`` (tf2_msgs/TFMessage) when the bag has them: the camera extrinsic the node looks
  up (robot_state_publisher's static transforms, a moving camera mount).

:meth:`PlayBag.messages` yields them merged in the bag's order (log time), as they were recorded.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Self

from rosbags.highlevel import AnyReader

from epi_vo.core.errors import BagError
from epi_vo.io.bag_topics import (
    CAMERA_INFO_KIND,
    CAMERA_INFO_TYPE,
    COMPRESSED_IMAGE_TYPE,
    DECODE_ERRORS,
    IMAGE_KIND,
    ODOMETRY_TYPE,
    READ_ERRORS,
    TF_MESSAGE_TYPE,
    TYPESTORE,
    TopicKind,
    choose_topic,
    is_ground_truth_name,
    required_topic,
)
from epi_vo.io.paths import check_bag_path

if TYPE_CHECKING:
    from collections.abc import Iterator
    from types import TracebackType

TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
_WHEEL_KIND = TopicKind("nav_msgs/Odometry", frozenset({ODOMETRY_TYPE}), "--wheel-topic")


class BagMessage(NamedTuple):
    """One recorded message: log time (ns), bag topic, raw CDR bytes as stored."""

    log_time_ns: int
    topic: str
    rawdata: bytes


def _wheel_topic(topic_types: dict[str, str | None], explicit: str | None) -> str | None:
    """The wheel odometry topic: ``explicit``, else the only Odometry topic not named as ground truth."""
    if explicit is not None:
        return choose_topic(topic_types, _WHEEL_KIND, explicit)
    own = {k: v for k, v in topic_types.items() if not is_ground_truth_name(k)}
    return choose_topic(own, _WHEEL_KIND, None)


class PlayBag:
    """The topics of a bag that ``epi-vo play`` publishes (see the module doc): raw CDR bytes, no
    deserialisation. ``image_topic``, ``camera_info_topic`` always; ``wheel_topic`` and ``tf_topics`` when
    the bag has them (None, ()); ``counts`` the messages the bag announces on each.

    Raises BagError (one line, naming the bag) for a missing path, a bag that cannot be opened, a ROS 1
    bag, and missing, empty or ambiguous topics.
    """

    def __init__(self, path: str | Path, image_topic: str | None = None, camera_info_topic: str | None = None,
                 wheel_topic: str | None = None) -> None:
        self.path = check_bag_path(path)
        try:
            reader = AnyReader([self.path], default_typestore=TYPESTORE)
            reader.open()
        except READ_ERRORS as err:
            msg = f"cannot open bag {self.path}: {err}"
            raise BagError(msg) from err
        self._reader: AnyReader | None = reader
        try:
            if not reader.is2:
                msg = f"{self.path} is a ROS 1 bag; play publishes ROS 2 (rosbag2, CDR) bags only"
                raise BagError(msg)
            topic_types = {name: info.msgtype for name, info in reader.topics.items()}
            self.image_topic = required_topic(topic_types, IMAGE_KIND, image_topic)
            self.camera_info_topic = required_topic(topic_types, CAMERA_INFO_KIND, camera_info_topic,
                                                     sibling_of=self.image_topic)
            self.wheel_topic = _wheel_topic(topic_types, wheel_topic)
            self.tf_topics = tuple(t for t in (TF_TOPIC, TF_STATIC_TOPIC) if topic_types.get(t) == TF_MESSAGE_TYPE)
            self.counts = {t: int(reader.topics[t].msgcount) for t in self.topics}
            if self.counts[self.image_topic] == 0:
                msg = f"image topic {self.image_topic} in bag {self.path} has no messages"
                raise BagError(msg)
            self.image_msgtype = str(topic_types[self.image_topic])
            self._msgtypes = {t: str(topic_types[t]) for t in self.topics}
            self._connections = [c for c in reader.connections if c.topic in self.topics]
        except BaseException:
            self.close()
            raise

    @property
    def topics(self) -> tuple[str, ...]:
        """Every chosen topic: image, camera_info, then the wheel odometry and TF ones the bag has."""
        wheel = (self.wheel_topic,) if self.wheel_topic is not None else ()
        return (self.image_topic, self.camera_info_topic, *wheel, *self.tf_topics)

    @property
    def image_count(self) -> int:
        return self.counts[self.image_topic]

    @property
    def image_is_compressed(self) -> bool:
        return self.image_msgtype == COMPRESSED_IMAGE_TYPE

    def msgtype(self, topic: str) -> str:
        """ROS type name ('sensor_msgs/msg/CameraInfo') of a chosen topic."""
        return CAMERA_INFO_TYPE if topic == self.camera_info_topic else self._msgtypes[topic]

    def messages(self) -> Iterator[BagMessage]:
        """The chosen topics' messages in bag (log time) order; each call starts from the beginning."""
        if self._reader is None:
            msg = f"bag {self.path} is closed"
            raise BagError(msg)
        try:
            for connection, log_time_ns, rawdata in self._reader.messages(self._connections):
                yield BagMessage(int(log_time_ns), connection.topic, bytes(rawdata))
        except READ_ERRORS as err:
            msg = f"cannot read bag {self.path}: {err}"
            raise BagError(msg) from err

    def check_cdr(self, message: BagMessage) -> str | None:
        """Why ``message``'s bytes are no CDR message of its topic's type (None when they are one), for the
        messages published as recorded bytes (TF: tf2_msgs has no PyPI wheel, so no rclpy class to decode
        into may exist)."""
        try:
            TYPESTORE.deserialize_cdr(message.rawdata, self.msgtype(message.topic))
        except DECODE_ERRORS as err:
            return f"{type(err).__name__}: {err}"
        return None

    def close(self) -> None:
        """Close the reader; calling it again does nothing."""
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc_val: BaseException | None,
                 exc_tb: TracebackType | None) -> None:
        self.close()
