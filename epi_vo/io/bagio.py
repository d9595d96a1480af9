"""Camera bags in: rosbag2 reading through rosbags (no rclpy).

``open_camera_bag`` opens a rosbag2 directory (MCAP or sqlite3 storage) or a bare ``.mcap`` /
``.db3`` file, picks the image, camera_info and ground-truth topics, and yields ``BagFrame`` records
in bag order. Messages are rosbags dataclasses; ``epi_vo.io.msgconv`` reads them by field name.
``epi_vo.io.play_bag`` gives the raw CDR bytes of the topics the node consumes (what ``epi-vo play`` republishes).
Writing results is ``epi_vo.io.outbag``; TUM trajectories ``epi_vo.io.tum``.

Every failure to read as asked is a BagError with a one-line message naming the bag and the reason
(the rosbags exception is chained, not leaked).
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Self

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader

from epi_vo.core.camera import CameraModelCache
from epi_vo.core.errors import BagError, EpiVoError
from epi_vo.core.frame import clamp_stamp_ns
from epi_vo.io.bag_topics import (
    CAMERA_INFO_KIND,
    COMPRESSED_IMAGE_TYPE,
    DECODE_ERRORS,
    IMAGE_KIND,
    READ_ERRORS,
    TYPESTORE,
    WHEEL_KIND,
    choose_topic,
    ground_truth_topic,
    required_topic,
)
from epi_vo.io.msgconv import (
    decode_frame,
    odometry_position,
    stamp_problem,
    stamp_to_ns,
)
from epi_vo.io.paths import BAG_STORAGE_SUFFIXES, check_bag_path

if TYPE_CHECKING:
    from collections.abc import Iterator
    from types import TracebackType

    from rosbags.interfaces import Connection


logger = logging.getLogger(__name__)

ODOMETRY_TOPIC = "/vo/odometry"
VO_UNITS_ODOMETRY_TOPIC = "/vo/odometry/vo_units"  # the motion in VO units (frames in no TF tree)
POINTS_TOPIC = "/vo/points"
PATH_TOPIC = "/vo/path"
FRAME_STATUS_TOPIC = "/vo/frame_status"  # the per-frame statuses, as vo_node publishes them
TF_TOPIC = "/tf"

# --------------------------------------------------------------------------------------------------
# Reading


@dataclass(frozen=True)
class BagFrame:
    """One image of the bag with its calibration message.

    ``index`` counts image messages from 0 in bag order (every message read, also one that cannot be
    decoded); ``stamp_ns`` is the image header stamp; ``camera_info_msg`` is the associated CameraInfo
    (see ``CameraBag.camera_info_for``) or None when the camera_info topic holds no message.

    ``problem`` says why the frame cannot be used whatever its pixels (None when it can): its CDR
    bytes cannot be decoded (``image_msg`` is then None) or its header stamp is not a valid ROS time.
    ``stamp_ns`` is then a valid ROS time to file the frame under: the header stamp clamped into
    [0, 2**31 s), or, when there is no header, the message's log time (clamped the same way).
    """

    index: int
    stamp_ns: int
    image_msg: Any
    camera_info_msg: Any | None
    problem: str | None = None
    log_time_ns: int = 0


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Ground-truth poses ``T_parent_child`` from a PoseStamped or Odometry topic, sorted by stamp.

    ``positions`` (N, 3) is the child origin in the parent frame ``frame_id`` (header.frame_id),
    ``quats_xyzw`` (N, 4) the child orientation in that frame, ``stamps_ns`` (N,) the header stamps.
    Arrays are read-only.
    """

    topic: str
    frame_id: str
    stamps_ns: NDArray[np.int64]
    positions: NDArray[np.float64]
    quats_xyzw: NDArray[np.float64]


def _message_count(path: Path, topics: Any, topic: str) -> int:
    """The message count the bag announces for ``topic``; BagError when its metadata says no number."""
    try:
        count = topics[topic].msgcount
        return int(count)
    except (*READ_ERRORS, AttributeError) as err:
        msg = f"bag {path} has malformed metadata: message count of {topic}: {err}"
        raise BagError(msg) from err


def _check_metadata_text(path: Path) -> None:
    """A bag directory's metadata.yaml must be UTF-8 text (rosbags would raise UnicodeDecodeError)."""
    metadata = path / "metadata.yaml"
    try:
        metadata.read_bytes().decode("utf-8")
    except OSError as err:
        msg = f"cannot read {metadata}: {err.strerror or err}"
        raise BagError(msg) from err
    except UnicodeDecodeError as err:
        msg = (
            f"{metadata} is not UTF-8 text (byte 0x{err.object[err.start]:02x} at offset "
            f"{err.start}): not a rosbag2 metadata file"
        )
        raise BagError(msg) from None


class CameraBag:
    """An open camera bag: chosen topics, frame count, frames and ground truth.

    Create it with ``open_camera_bag``; close it with ``close()`` or use it in a ``with`` block.
    """

    def __init__(
        self,
        path: Path,
        reader: AnyReader,
        image_topic: str,
        camera_info_topic: str,
        gt_topic: str | None,
        wheel_topic: str | None = None,
    ) -> None:
        """Wrap an open ``reader``; reads all camera_info messages (they are small) right away."""
        self.path = path
        self.image_topic = image_topic
        self.camera_info_topic = camera_info_topic
        self.gt_topic = gt_topic
        self.wheel_topic = wheel_topic
        self._reader: AnyReader | None = reader
        topics = reader.topics
        self._connections: dict[str, list[Connection]] = {
            name: list(topics[name].connections)
            for name in (image_topic, camera_info_topic, gt_topic, wheel_topic)
            if name is not None
        }
        self.image_is_compressed = topics[image_topic].msgtype == COMPRESSED_IMAGE_TYPE
        self.frame_count = _message_count(path, topics, image_topic)
        # Messages of the camera_info and ground-truth topics that could not be decoded (skipped),
        # one line each; images that cannot be decoded are frames with a problem instead.
        self.problems: list[str] = []
        self._cameras = CameraModelCache()  # for usable_gray: the size an image must have

        camera_infos = []
        for log_time_ns, msg, problem in self._read(camera_info_topic):
            if msg is None:
                self._skipped(f"camera_info message at log time {log_time_ns} ns skipped: it {problem}")
                continue
            try:
                camera_infos.append((stamp_to_ns(msg.header.stamp), msg))
            except EpiVoError as err:
                self._skipped(f"camera_info message at log time {log_time_ns} ns skipped: {err}")
        # Stable sort by header stamp: among equal stamps the last one is the latest recorded.
        camera_infos.sort(key=lambda item: item[0])
        self._camera_info_stamps_ns = [stamp for stamp, _ in camera_infos]
        self._camera_info_msgs = [msg for _, msg in camera_infos]

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc_val: BaseException | None,
        exc_tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying reader; calling it again does nothing."""
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()

    def _skipped(self, problem: str) -> None:
        logger.warning("bag %s: %s", self.path, problem)
        self.problems.append(problem)

    def _read(self, topic: str) -> Iterator[tuple[int, Any | None, str | None]]:
        """(log time ns, deserialised message, None) of ``topic`` in bag order.

        A message whose CDR bytes cannot be deserialised gives (log time, None, the reason) and reading
        goes on; a bag that cannot be read further (truncated, damaged record) raises BagError.
        """
        if self._reader is None:
            msg = f"bag {self.path} is closed"
            raise BagError(msg)
        reader = self._reader
        try:
            for connection, log_time_ns, rawdata in reader.messages(self._connections[topic]):
                try:
                    message = reader.deserialize(rawdata, connection.msgtype)
                except DECODE_ERRORS as err:
                    reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
                    yield (
                        int(log_time_ns),
                        None,
                        f"cannot be decoded: its {len(rawdata)} bytes of CDR are no valid "
                        f"{connection.msgtype} ({reason})",
                    )
                    continue
                yield int(log_time_ns), message, None
        except READ_ERRORS as err:
            msg = f"cannot read {topic} from bag {self.path}: {err}"
            raise BagError(msg) from err

    def camera_info_for(self, stamp_ns: int) -> Any | None:
        """CameraInfo for an image stamped ``stamp_ns``.

        The one with exactly that header stamp, else the latest with stamp <= ``stamp_ns``, else
        (info recorded only after the first images) the earliest; None when the topic is empty.
        """
        if not self._camera_info_msgs:
            return None
        # bisect_right lands after every stamp <= stamp_ns, so an exact match is the one taken.
        position = bisect.bisect_right(self._camera_info_stamps_ns, stamp_ns)
        return self._camera_info_msgs[max(position - 1, 0)]

    def usable_gray(self, frame: BagFrame) -> NDArray[np.uint8] | None:
        """The frame's grayscale pixels when the replay would process it, else None: a frame with a
        ``problem``, without camera_info, or whose pixels cannot be decoded (for tools that only need
        the frames the pipeline sees)."""
        if frame.problem is not None or frame.camera_info_msg is None:
            return None
        try:
            camera = self._cameras.get(frame.camera_info_msg)
            return decode_frame(frame.image_msg, self.image_is_compressed, (camera.width, camera.height))
        except EpiVoError:
            return None

    def iter_frames(self) -> Iterator[BagFrame]:
        """Images in bag order, each with ``camera_info_for`` its header stamp.

        Every image message read gives a frame: one that cannot be decoded, or whose header stamp is
        no valid ROS time, comes with its ``problem`` (see :class:`BagFrame`).
        """
        for index, (log_time_ns, image_msg, problem) in enumerate(self._read(self.image_topic)):
            if image_msg is None:
                stamp_ns = clamp_stamp_ns(log_time_ns)
                problem = f"image message {problem}"
                yield BagFrame(index, stamp_ns, None, None, problem, log_time_ns)
                continue
            stamp = getattr(getattr(image_msg, "header", None), "stamp", None)
            bad_stamp = stamp_problem(stamp)
            if bad_stamp is None:
                stamp_ns = stamp_to_ns(stamp)
            else:
                try:
                    stamp_ns = clamp_stamp_ns(stamp_to_ns(stamp))
                except EpiVoError:
                    stamp_ns = clamp_stamp_ns(log_time_ns)
                problem = f"image {bad_stamp}"
            yield BagFrame(
                index, stamp_ns, image_msg, self.camera_info_for(stamp_ns), problem, log_time_ns
            )

    def read_wheel_odometry(self) -> WheelOdometrySamples | None:
        """Positions of the wheel odometry topic (base in its odom frame) in the bag's order, which is the
        order they arrived in (the pipeline takes them so: ``epi_vo.core.scale.WheelOdometry``), or None
        when no wheel topic was chosen. Undecodable messages are skipped and listed in ``problems``."""
        if self.wheel_topic is None:
            return None
        stamps_ns: list[int] = []
        positions: list[np.ndarray] = []
        for log_time_ns, msg, problem in self._read(self.wheel_topic):
            if msg is None:
                self._skipped(f"wheel odometry message on {self.wheel_topic} at log time {log_time_ns} ns skipped: "
                              f"it {problem}")
                continue
            stamp_ns, xyz = odometry_position(msg)
            stamps_ns.append(NO_STAMP if stamp_ns is None else stamp_ns)
            positions.append(xyz)
        return WheelOdometrySamples(self.wheel_topic, np.asarray(stamps_ns, dtype=np.int64),
                                    np.asarray(positions, dtype=np.float64).reshape(-1, 3))

    def read_ground_truth(self) -> GroundTruth | None:
        """Poses of the ground-truth topic sorted by header stamp, or None when the bag has none."""
        if self.gt_topic is None:
            return None
        stamps_ns: list[int] = []
        positions: list[tuple[float, float, float]] = []
        quats_xyzw: list[tuple[float, float, float, float]] = []
        frame_id = ""
        for log_time_ns, msg, problem in self._read(self.gt_topic):
            if msg is None:
                self._skipped(
                    f"ground-truth message on {self.gt_topic} at log time {log_time_ns} ns skipped: "
                    f"it {problem}"
                )
                continue
            # PoseStamped has pose.position; Odometry has pose.pose.position (PoseWithCovariance).
            pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
            stamps_ns.append(stamp_to_ns(msg.header.stamp))
            positions.append((pose.position.x, pose.position.y, pose.position.z))
            o = pose.orientation
            quats_xyzw.append((o.x, o.y, o.z, o.w))
            frame_id = frame_id or str(msg.header.frame_id)
        order = np.argsort(np.asarray(stamps_ns, dtype=np.int64), kind="stable")
        arrays = (
            np.asarray(stamps_ns, dtype=np.int64)[order],
            np.asarray(positions, dtype=np.float64).reshape(-1, 3)[order],
            np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)[order],
        )
        for array in arrays:
            array.setflags(write=False)
        return GroundTruth(self.gt_topic, frame_id, *arrays)


def open_camera_bag(
    path: str | Path,
    image_topic: str | None = None,
    camera_info_topic: str | None = None,
    gt_topic: str | None = None,
    wheel_topic: str | None = None,
    *,
    no_ground_truth: bool = False,
) -> CameraBag:
    """Open a camera bag and choose its topics.

    ``path`` is a rosbag2 directory (metadata.yaml, MCAP or sqlite3 storage) or a single ``.mcap``
    or ``.db3`` file. Topics not given are discovered by type: images are sensor_msgs/Image or
    CompressedImage, calibration sensor_msgs/CameraInfo, ground truth geometry_msgs/PoseStamped or
    nav_msgs/Odometry (optional). A kind with exactly one topic is taken; with several, a
    camera_info in the image topic's namespace is taken, anything else is a BagError naming the
    candidates and the flag that chooses. A given topic must exist with a matching type. Ground
    truth (see :func:`is_ground_truth_name`): ``gt_topic`` when given, else the one PoseStamped /
    Odometry topic named as ground truth; never the wheel odometry topic (the scale source cannot judge
    itself); none with ``no_ground_truth``. ``wheel_topic`` (nav_msgs/Odometry, for the wheel odometry
    scale source) must exist when given: a BagError names it and the Odometry topics there are.

    Raises BagError for a missing path, a non-bag, an unreadable or truncated file, an empty bag, a
    missing image or camera_info topic, an image topic without messages and ambiguous topics.
    """
    path = check_bag_path(path)
    if path.is_dir() and not (path / "metadata.yaml").exists():
        files = sorted(x.name for x in path.iterdir() if x.suffix in BAG_STORAGE_SUFFIXES)
        hint = f"; to read a file in it, pass its path: {', '.join(files)}" if files else ""
        msg = f"{path} is a directory without metadata.yaml, not a rosbag2 bag{hint}"
        raise BagError(msg)
    if path.is_file() and path.suffix not in BAG_STORAGE_SUFFIXES:
        msg = f"{path} is not a rosbag2 bag: expected a bag directory, a .mcap or a .db3 file"
        raise BagError(msg)
    if path.is_dir():
        _check_metadata_text(path)

    try:
        reader = AnyReader([path], default_typestore=TYPESTORE)
        reader.open()
    except READ_ERRORS as err:
        msg = f"cannot open bag {path}: {err}"
        raise BagError(msg) from err

    try:
        try:
            # rosbags parses the metadata lazily: a field of the wrong type surfaces here.
            message_count = int(reader.message_count)
            topic_types = {name: info.msgtype for name, info in reader.topics.items()}
        except (*READ_ERRORS, AttributeError) as err:
            msg = f"bag {path} has malformed metadata: {err}"
            raise BagError(msg) from err
        if message_count == 0:
            msg = f"bag {path} is empty (no messages)"
            raise BagError(msg)
        chosen_image = required_topic(topic_types, IMAGE_KIND, image_topic)
        if _message_count(path, reader.topics, chosen_image) == 0:
            msg = f"image topic {chosen_image} in bag {path} has no messages"
            raise BagError(msg)
        chosen_info = required_topic(
            topic_types, CAMERA_INFO_KIND, camera_info_topic, sibling_of=chosen_image
        )
        if wheel_topic is not None:
            choose_topic(topic_types, WHEEL_KIND, wheel_topic)
        chosen_gt = None if no_ground_truth else ground_truth_topic(topic_types, gt_topic, wheel_topic)
        bag = CameraBag(path, reader, chosen_image, chosen_info, chosen_gt, wheel_topic)
    except BaseException:
        reader.close()
        raise
    logger.info(
        "bag %s: %d frames on %s, camera_info %s, ground truth %s",
        path,
        bag.frame_count,
        bag.image_topic,
        bag.camera_info_topic,
        bag.gt_topic or "(none)",
    )
    return bag


NO_STAMP = -1  # a wheel message's header stamp that is no ROS time (WheelOdometrySamples.stamps_ns)


class WheelOdometrySamples(NamedTuple):
    """Wheel odometry positions and header stamps (``NO_STAMP``: no ROS time), in the bag's order."""

    topic: str
    stamps_ns: NDArray[np.int64]
    positions: NDArray[np.float64]


def to_cdr(msg: Any) -> bytes:
    """The CDR bytes of a message read from a bag (a rosbags dataclass), e.g. to hand it to rclpy's
    ``deserialize_message``."""
    return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
