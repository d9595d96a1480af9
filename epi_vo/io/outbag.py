"""VO results out: ``OutputBag`` writes one self-contained ``.mcap`` file (no rclpy).

Profile ``ros2``, channels ``cdr``, schemas ``ros2msg`` with the full message definition text,
``offered_qos_profiles`` and the RIHS01 ``topic_type_hash`` in the channel metadata, statistics and
indexes. That is the layout rosbag2's MCAP storage plugin reads, so rosbags, ``ros2 bag info/play``
and Foxglove open it directly. It is written with the ``mcap`` library, not rosbags' Writer, because
the latter always creates a bag directory (``DIR/DIR.mcap`` + ``metadata.yaml``) and we want a
single file. Every failure to write as asked is a BagError naming the file and the reason.
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path
from typing import TYPE_CHECKING, Self

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from numpy.typing import ArrayLike, NDArray
from rosbags.typesys import Stores, get_typestore

from epi_vo.core.errors import BagError
from epi_vo.io.bag_topics import DIAGNOSTIC_ARRAY_TYPE, ODOMETRY_TYPE, PATH_TYPE, POINT_CLOUD2_TYPE, TF_MESSAGE_TYPE
from epi_vo.io.bagio import (
    FRAME_STATUS_TOPIC,
    ODOMETRY_TOPIC,
    PATH_TOPIC,
    POINTS_TOPIC,
    TF_TOPIC,
    VO_UNITS_ODOMETRY_TOPIC,
)
from epi_vo.io.msgconv import (
    NS_PER_S,
    ROS_TIME_MAX_NS,
    ns_to_ros_time,
    point_cloud2_fields,
)

if TYPE_CHECKING:
    from collections.abc import Sequence
    from types import TracebackType

    from epi_vo.core.diagnostics import DiagnosticStatusRecord

logger = logging.getLogger(__name__)


_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

# --------------------------------------------------------------------------------------------------
# Writing


# Offered QoS of every output channel. Empty on purpose: rosbag2 parses a non-empty profile list as
# integers (metadata v8, the default when the file has no rosbag2 metadata record) or as names (v9),
# so no text suits every distro, while '' means "none recorded" everywhere and ``ros2 bag play``
# then publishes with rclcpp's default profile (reliable, volatile, keep last 10).
_OFFERED_QOS_PROFILES = ""

# The MCAP header's library of every file OutputBag writes: how a fleet tells an epi_vo output from a bag.
OUTPUT_LIBRARY = "epi_vo"

_OUTPUT_TOPICS: dict[str, str] = {
    ODOMETRY_TOPIC: ODOMETRY_TYPE,
    VO_UNITS_ODOMETRY_TOPIC: ODOMETRY_TYPE,
    POINTS_TOPIC: POINT_CLOUD2_TYPE,
    PATH_TOPIC: PATH_TYPE,
    FRAME_STATUS_TOPIC: DIAGNOSTIC_ARRAY_TYPE,
    TF_TOPIC: TF_MESSAGE_TYPE,
}


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_MCAP_HEADER_OPCODE = 0x01


def is_output_bag(path: str | Path) -> bool:
    """Whether ``path`` is a regular file written by :class:`OutputBag` (its MCAP header names
    ``OUTPUT_LIBRARY``): a replay's output, never a camera bag. Reads the first bytes only; a FIFO or
    device is not opened."""
    path = Path(path)
    try:
        if not path.is_file():
            return False
        with path.open("rb") as f:
            head = f.read(512)
    except OSError:
        return False
    # Magic, then the Header record: opcode (1 byte), length (uint64), profile and library (uint32 length +
    # UTF-8 each), little-endian.
    if not head.startswith(_MCAP_MAGIC) or len(head) < 21 or head[8] != _MCAP_HEADER_OPCODE:
        return False
    at = 17
    (profile_len,) = struct.unpack_from("<I", head, at)
    at += 4 + profile_len
    if at + 4 > len(head):
        return False
    (library_len,) = struct.unpack_from("<I", head, at)
    return head[at + 4:at + 4 + library_len] == OUTPUT_LIBRARY.encode()


def checked_array(
    value: ArrayLike, shape: tuple[int | None, ...], name: str
) -> NDArray[np.float64]:
    """``value`` as float64 of ``shape`` (None = any length); BagError naming ``name`` otherwise."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != len(shape) or any(
        want is not None and want != have for want, have in zip(shape, array.shape, strict=True)
    ):
        expected = ", ".join("N" if x is None else str(x) for x in shape)
        expected = f"({expected},)" if len(shape) == 1 else f"({expected})"
        msg = f"{name} has shape {array.shape}, expected {expected}"
        raise BagError(msg)
    return array


class _Cdr:
    """Little-endian CDR as rosbags' ``serialize_cdr`` writes it (byte for byte; test_bagio checks it): the
    encapsulation header ``00 01 00 00``, then every primitive aligned to its size counted from the end of
    that header, strings as uint32 length (with the NUL) + UTF-8 + NUL, sequences as a uint32 count + items.

    Built by hand because building rosbags message objects and serialising them cost more than the whole
    VO per frame (a /vo/path of 1000 poses: ~12 ms); the layout of our four output types is fixed.
    """

    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")

    def align(self, n: int) -> None:
        pad = -(len(self.buf) - 4) % n
        if pad:
            self.buf += bytes(pad)

    def u8(self, value: int) -> None:
        self.buf.append(value)

    def u32(self, value: int) -> None:
        self.align(4)
        self.buf += _U32.pack(value)

    def string(self, text: str) -> None:
        data = text.encode()
        self.u32(len(data) + 1)
        self.buf += data
        self.buf.append(0)

    def header(self, stamp_ns: int, frame_id: str) -> None:
        """std_msgs/Header: builtin_interfaces/Time (int32 sec, uint32 nanosec), frame_id."""
        sec, nanosec = divmod(stamp_ns, NS_PER_S)
        self.align(4)
        self.buf += _TIME.pack(sec, nanosec)
        self.string(frame_id)

    def f64(self, values: NDArray[np.float64]) -> None:
        """Consecutive float64 fields (or a float64 array), in the order of ``values`` (flattened)."""
        self.align(8)
        self.buf += np.ascontiguousarray(values, dtype="<f8").tobytes()

    def poses_stamped(self, stamps_ns: NDArray[np.int64], frame_id: str, poses: NDArray[np.float64]) -> None:
        """The items of a geometry_msgs/PoseStamped sequence (count written before): header, then the 7
        float64 of the pose (x y z, qx qy qz qw) per row of ``poses`` (M, 7)."""
        if not len(stamps_ns):
            return
        # The first item may start 4 mod 8; every later one starts 8-aligned (the previous ends with a float64),
        # so from the second on all items have one layout and are written as rows of one array.
        self.header(int(stamps_ns[0]), frame_id)
        self.f64(poses[0])
        rest = len(stamps_ns) - 1
        if not rest:
            return
        item = _Cdr()
        item.buf = bytearray(4)  # offset 0 mod 8 relative to the payload, as the later items
        item.header(0, frame_id)
        item.f64(np.zeros(7))
        template = np.frombuffer(bytes(item.buf[4:]), dtype=np.uint8)
        size = template.size
        rows = np.empty((rest, size), dtype=np.uint8)
        rows[:] = template
        sec, nanosec = np.divmod(stamps_ns[1:], NS_PER_S)
        rows[:, 0:4] = sec.astype("<i4")[:, None].view(np.uint8)
        rows[:, 4:8] = nanosec.astype("<u4")[:, None].view(np.uint8)
        rows[:, size - 56:] = np.ascontiguousarray(poses[1:], dtype="<f8").view(np.uint8)
        self.buf += rows.tobytes()


_U32 = struct.Struct("<I")
_TIME = struct.Struct("<iI")


class OutputBag:
    """Write VO results to one MCAP file with the ROS 2 profile (see the module docstring).

    Topics: /vo/odometry and /vo/odometry/vo_units (nav_msgs/Odometry), /vo/points
    (sensor_msgs/PointCloud2), /vo/path (nav_msgs/Path), /vo/frame_status (diagnostic_msgs/DiagnosticArray),
    /tf (tf2_msgs/TFMessage); all six channels are declared up front. Stamps are integer nanoseconds; each
    message is logged at its header stamp (a TFMessage's transforms all carry it). A stamp that is no valid
    ROS time (outside [0, (2**31 - 1) s + 999999999 ns]) is refused with a BagError before anything of that
    message is written (the file stays valid and readable).

    Use as a context manager: leaving the block, also by an exception or KeyboardInterrupt, writes
    the summary and index so the file stays readable.
    """

    def __init__(self, path: str | Path, *, overwrite: bool = False) -> None:
        """Create ``path`` (must end in .mcap; parent directories are made); refuse to replace an
        existing file unless ``overwrite``."""
        self.path = Path(path)
        if self.path.suffix != ".mcap":
            msg = f"output bag {self.path} must be a .mcap file"
            raise BagError(msg)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._stream = self.path.open("wb" if overwrite else "xb")
        except FileExistsError:
            msg = f"output bag {self.path} exists already (pass overwrite=True to replace it)"
            raise BagError(msg) from None
        except OSError as err:
            msg = f"cannot create output bag {self.path}: {err}"
            raise BagError(msg) from err

        writer = McapWriter(self._stream, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library=OUTPUT_LIBRARY)
        schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        for topic, msgtype in _OUTPUT_TOPICS.items():
            if msgtype not in schema_ids:
                msgdef, _ = _TYPESTORE.generate_msgdef(msgtype, ros_version=2)
                schema_ids[msgtype] = writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=msgdef.encode()
                )
            self._channel_ids[topic] = writer.register_channel(
                topic=topic,
                message_encoding="cdr",
                schema_id=schema_ids[msgtype],
                metadata={
                    "offered_qos_profiles": _OFFERED_QOS_PROFILES,
                    "topic_type_hash": _TYPESTORE.hash_rihs01(msgtype),
                },
            )
        self._writer: McapWriter | None = writer

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
        """Write the summary and close the file; calling it again does nothing."""
        writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            writer.finish()
        except OSError as err:
            msg = f"cannot write output bag {self.path}: {err.strerror or err}"
            raise BagError(msg) from err
        finally:
            self._stream.close()

    def flush(self) -> None:
        """Close the chunk in progress and hand everything written so far to the OS: a process killed later
        leaves a file whose chunks up to here are complete (``epi-vo recover`` copies them into a readable
        file; without the summary no reader opens the killed file itself)."""
        if self._writer is None:
            msg = f"output bag {self.path} is closed"
            raise BagError(msg)
        try:
            self._writer.flush()
        except OSError as err:
            msg = f"cannot write output bag {self.path}: {err.strerror or err}"
            raise BagError(msg) from err

    def _check_time(self, topic: str, stamp_ns: int) -> int:
        """``stamp_ns`` as int when it is a valid ROS time; BagError naming the topic otherwise."""
        if self._writer is None:
            msg = f"output bag {self.path} is closed"
            raise BagError(msg)
        try:
            ns_to_ros_time(stamp_ns)
        except (ValueError, TypeError) as err:
            msg = f"{topic}: {err}: message not written to {self.path}"
            raise BagError(msg) from None
        return int(stamp_ns)

    def _write(self, topic: str, stamp_ns: int, message: _Cdr) -> None:
        """Add the serialised ``message`` (its stamp checked by the caller before it was built)."""
        assert self._writer is not None  # checked with the stamp
        try:
            self._writer.add_message(
                self._channel_ids[topic], log_time=int(stamp_ns), data=bytes(message.buf), publish_time=int(stamp_ns)
            )
        except OSError as err:
            msg = f"cannot write output bag {self.path}: {err.strerror or err}"
            raise BagError(msg) from err

    def write_odometry(
        self,
        stamp_ns: int,
        frame_id: str,
        child_frame_id: str,
        position: ArrayLike,
        quat_xyzw: ArrayLike,
        pose_covariance: ArrayLike,
        linear_velocity: ArrayLike,
        angular_velocity: ArrayLike,
        twist_covariance: ArrayLike,
        topic: str = ODOMETRY_TOPIC,
    ) -> None:
        """nav_msgs/Odometry on ``topic`` (/vo/odometry, or /vo/odometry/vo_units).

        Pose ``T_frame_child``: ``position`` (3,) and ``quat_xyzw`` (4,) of ``child_frame_id`` in
        ``frame_id``; twist (3,) + (3,) in ``child_frame_id``; covariances (6, 6) in the ROS order
        (x, y, z, rot x, rot y, rot z), written row-major.
        """
        if topic not in (ODOMETRY_TOPIC, VO_UNITS_ODOMETRY_TOPIC):
            msg = f"{topic} is no odometry topic of an output bag"
            raise BagError(msg)
        stamp_ns = self._check_time(topic, stamp_ns)
        values = (
            checked_array(position, (3,), "position"),
            checked_array(quat_xyzw, (4,), "quat_xyzw"),
            checked_array(pose_covariance, (6, 6), "pose_covariance").reshape(36),
            checked_array(linear_velocity, (3,), "linear_velocity"),
            checked_array(angular_velocity, (3,), "angular_velocity"),
            checked_array(twist_covariance, (6, 6), "twist_covariance").reshape(36),
        )
        message = _Cdr()
        message.header(stamp_ns, frame_id)
        message.string(child_frame_id)
        # PoseWithCovariance (pose: point, quaternion; covariance) then TwistWithCovariance (twist: linear,
        # angular; covariance): 85 float64 fields with nothing between them.
        message.f64(np.concatenate(values))
        self._write(topic, stamp_ns, message)

    def write_tf(self, stamp_ns: int, transforms: Sequence[tuple[str, str, ArrayLike, ArrayLike]]) -> None:
        """tf2_msgs/TFMessage on /tf: one geometry_msgs/TransformStamped per ``(parent, child, xyz (3,),
        quat_xyzw (4,))``, each stamped ``stamp_ns``: ``child`` in ``parent``."""
        stamp_ns = self._check_time(TF_TOPIC, stamp_ns)
        rows = [(parent, child, np.concatenate([checked_array(xyz, (3,), "xyz"),
                                                checked_array(quat, (4,), "quat_xyzw")]))
                for parent, child, xyz, quat in transforms]
        message = _Cdr()
        message.u32(len(rows))
        for parent, child, values in rows:
            message.header(stamp_ns, parent)
            message.string(child)
            message.f64(values)  # Transform: translation (x y z), rotation (x y z w)
        self._write(TF_TOPIC, stamp_ns, message)

    def write_points(self, stamp_ns: int, frame_id: str, points_xyz: ArrayLike) -> None:
        """sensor_msgs/PointCloud2 (x, y, z float32) on /vo/points; ``points_xyz`` (N, 3) in
        ``frame_id``. Points with a non-finite coordinate are dropped (see point_cloud2_fields)."""
        stamp_ns = self._check_time(POINTS_TOPIC, stamp_ns)
        cloud = point_cloud2_fields(checked_array(points_xyz, (None, 3), "points_xyz"))
        message = _Cdr()
        message.header(stamp_ns, frame_id)
        message.u32(cloud["height"])
        message.u32(cloud["width"])
        message.u32(len(cloud["fields"]))
        for name, offset, datatype, count in cloud["fields"]:
            message.string(name)
            message.u32(offset)
            message.u8(datatype)
            message.u32(count)
        message.u8(bool(cloud["is_bigendian"]))
        message.u32(cloud["point_step"])
        message.u32(cloud["row_step"])
        data = np.ascontiguousarray(cloud["data"], dtype=np.uint8)
        message.u32(data.size)
        message.buf += data.tobytes()
        message.u8(bool(cloud["is_dense"]))
        self._write(POINTS_TOPIC, stamp_ns, message)

    def write_path(
        self,
        stamp_ns: int,
        frame_id: str,
        stamps_ns: ArrayLike,
        positions: ArrayLike,
        quats_xyzw: ArrayLike,
    ) -> None:
        """nav_msgs/Path on /vo/path: M poses of the camera in ``frame_id``, ``stamps_ns`` (M,),
        ``positions`` (M, 3), ``quats_xyzw`` (M, 4)."""
        stamp_ns = self._check_time(PATH_TOPIC, stamp_ns)
        stamps = self._checked_stamps(PATH_TOPIC, stamps_ns)
        xyz = checked_array(positions, (len(stamps), 3), "positions")
        quats = checked_array(quats_xyzw, (len(stamps), 4), "quats_xyzw")
        message = _Cdr()
        message.header(stamp_ns, frame_id)
        message.u32(len(stamps))
        message.poses_stamped(stamps, frame_id, np.hstack((xyz, quats)))
        self._write(PATH_TOPIC, stamp_ns, message)

    def _checked_stamps(self, topic: str, stamps_ns: ArrayLike) -> NDArray[np.int64]:
        """``stamps_ns`` (M,) as int64 when every one is a valid ROS time; BagError naming the first that is
        not (as ``_check_time``) otherwise."""
        array = np.asarray(stamps_ns).reshape(-1)
        if array.dtype.kind == "i" or (array.dtype.kind == "u" and array.dtype.itemsize < 8):
            stamps = array.astype(np.int64)
            bad = np.flatnonzero((stamps < 0) | (stamps > ROS_TIME_MAX_NS))
            if bad.size:
                self._check_time(topic, int(stamps[bad[0]]))
            return stamps
        # Other types (floats, Python ints beyond int64): one by one, as ints, with the same checks.
        return np.array([self._check_time(topic, int(x)) for x in array], dtype=np.int64)

    def write_diagnostics(self, stamp_ns: int, statuses: Sequence[DiagnosticStatusRecord]) -> None:
        """diagnostic_msgs/DiagnosticArray on /vo/frame_status (as vo_node publishes each frame's), one
        DiagnosticStatus per record."""
        stamp_ns = self._check_time(FRAME_STATUS_TOPIC, stamp_ns)
        message = _Cdr()
        message.header(stamp_ns, "")
        message.u32(len(statuses))
        for record in statuses:
            message.u8(int(record.level))
            message.string(record.name)
            message.string(record.message)
            message.string(record.hardware_id)
            message.u32(len(record.values))
            for key, value in record.values:
                message.string(key)
                message.string(value)
        self._write(FRAME_STATUS_TOPIC, stamp_ns, message)
