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
from pathlib import Path
from typing import TYPE_CHECKING, Any, Self

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from numpy.typing import ArrayLike, NDArray
from rosbags.typesys import Stores, get_typestore

from epi_vo.core.errors import BagError
from epi_vo.io.bagio import (
    DIAGNOSTIC_ARRAY_TYPE,
    DIAGNOSTICS_TOPIC,
    ODOMETRY_TOPIC,
    ODOMETRY_TYPE,
    PATH_TOPIC,
    PATH_TYPE,
    POINT_CLOUD2_TYPE,
    POINTS_TOPIC,
    POSE_STAMPED_TYPE,
)
from epi_vo.io.msgconv import (
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

_OUTPUT_TOPICS: dict[str, str] = {
    ODOMETRY_TOPIC: ODOMETRY_TYPE,
    POINTS_TOPIC: POINT_CLOUD2_TYPE,
    PATH_TOPIC: PATH_TYPE,
    DIAGNOSTICS_TOPIC: DIAGNOSTIC_ARRAY_TYPE,
}


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


def _ros_time(stamp_ns: int) -> Any:
    """builtin_interfaces/Time of integer nanoseconds (numpy integers accepted).

    BagError when ``stamp_ns`` is no valid ROS time (negative, or beyond int32 seconds): such a stamp
    is refused rather than written wrapped or failing inside the serialiser.
    """
    try:
        sec, nanosec = ns_to_ros_time(stamp_ns)
    except (ValueError, TypeError) as err:
        raise BagError(str(err)) from None
    Time = _TYPESTORE.types["builtin_interfaces/msg/Time"]
    return Time(sec=sec, nanosec=nanosec)


def _header(stamp_ns: int, frame_id: str) -> Any:
    return _TYPESTORE.types["std_msgs/msg/Header"](stamp=_ros_time(stamp_ns), frame_id=frame_id)


def _pose(position: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> Any:
    types = _TYPESTORE.types
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in quat_xyzw)
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )


def _vector3(vector: NDArray[np.float64]) -> Any:
    x, y, z = (float(v) for v in vector)
    return _TYPESTORE.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


class OutputBag:
    """Write VO results to one MCAP file with the ROS 2 profile (see the module docstring).

    Topics: /vo/odometry (nav_msgs/Odometry), /vo/points (sensor_msgs/PointCloud2), /vo/path
    (nav_msgs/Path), /diagnostics (diagnostic_msgs/DiagnosticArray); all four channels are declared
    up front. Stamps are integer nanoseconds; each message is logged at its header stamp. A stamp
    that is no valid ROS time (outside [0, (2**31 - 1) s + 999999999 ns]) is refused with a BagError
    before anything of that message is written (the file stays valid and readable).

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
        writer.start(profile="ros2", library="epi_vo")
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

    def _write(self, topic: str, stamp_ns: int, message: object) -> None:
        stamp_ns = self._check_time(topic, stamp_ns)
        assert self._writer is not None  # checked above
        data = _TYPESTORE.serialize_cdr(message, _OUTPUT_TOPICS[topic], little_endian=True)
        try:
            self._writer.add_message(
                self._channel_ids[topic], log_time=stamp_ns, data=bytes(data), publish_time=stamp_ns
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
    ) -> None:
        """nav_msgs/Odometry on /vo/odometry.

        Pose ``T_frame_child``: ``position`` (3,) and ``quat_xyzw`` (4,) of ``child_frame_id`` in
        ``frame_id``; twist (3,) + (3,) in ``child_frame_id``; covariances (6, 6) in the ROS order
        (x, y, z, rot x, rot y, rot z), written row-major.
        """
        types = _TYPESTORE.types
        self._check_time(ODOMETRY_TOPIC, stamp_ns)
        pose = _pose(
            checked_array(position, (3,), "position"),
            checked_array(quat_xyzw, (4,), "quat_xyzw"),
        )
        twist = types["geometry_msgs/msg/Twist"](
            linear=_vector3(checked_array(linear_velocity, (3,), "linear_velocity")),
            angular=_vector3(checked_array(angular_velocity, (3,), "angular_velocity")),
        )
        message = types[ODOMETRY_TYPE](
            header=_header(stamp_ns, frame_id),
            child_frame_id=child_frame_id,
            pose=types["geometry_msgs/msg/PoseWithCovariance"](
                pose=pose,
                covariance=checked_array(pose_covariance, (6, 6), "pose_covariance").reshape(36),
            ),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](
                twist=twist,
                covariance=checked_array(twist_covariance, (6, 6), "twist_covariance").reshape(36),
            ),
        )
        self._write(ODOMETRY_TOPIC, stamp_ns, message)

    def write_points(self, stamp_ns: int, frame_id: str, points_xyz: ArrayLike) -> None:
        """sensor_msgs/PointCloud2 (x, y, z float32) on /vo/points; ``points_xyz`` (N, 3) in
        ``frame_id``. Points with a non-finite coordinate are dropped (see point_cloud2_fields)."""
        types = _TYPESTORE.types
        self._check_time(POINTS_TOPIC, stamp_ns)
        cloud = point_cloud2_fields(checked_array(points_xyz, (None, 3), "points_xyz"))
        PointField = types["sensor_msgs/msg/PointField"]
        message = types[POINT_CLOUD2_TYPE](
            header=_header(stamp_ns, frame_id),
            height=cloud["height"],
            width=cloud["width"],
            fields=[PointField(*field) for field in cloud["fields"]],
            is_bigendian=cloud["is_bigendian"],
            point_step=cloud["point_step"],
            row_step=cloud["row_step"],
            data=cloud["data"],
            is_dense=cloud["is_dense"],
        )
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
        types = _TYPESTORE.types
        self._check_time(PATH_TOPIC, stamp_ns)
        stamps = [int(x) for x in np.asarray(stamps_ns).reshape(-1)]
        for stamp in stamps:
            self._check_time(PATH_TOPIC, stamp)
        xyz = checked_array(positions, (len(stamps), 3), "positions")
        quats = checked_array(quats_xyzw, (len(stamps), 4), "quats_xyzw")
        PoseStamped = types[POSE_STAMPED_TYPE]
        poses = [
            PoseStamped(header=_header(int(stamp), frame_id), pose=_pose(position, quat))
            for stamp, position, quat in zip(stamps, xyz, quats, strict=True)
        ]
        message = types[PATH_TYPE](header=_header(stamp_ns, frame_id), poses=poses)
        self._write(PATH_TOPIC, stamp_ns, message)

    def write_diagnostics(self, stamp_ns: int, statuses: Sequence[DiagnosticStatusRecord]) -> None:
        """diagnostic_msgs/DiagnosticArray on /diagnostics, one DiagnosticStatus per record."""
        types = _TYPESTORE.types
        self._check_time(DIAGNOSTICS_TOPIC, stamp_ns)
        KeyValue = types["diagnostic_msgs/msg/KeyValue"]
        status = [
            types["diagnostic_msgs/msg/DiagnosticStatus"](
                level=int(record.level),
                name=record.name,
                message=record.message,
                hardware_id=record.hardware_id,
                values=[KeyValue(key=key, value=value) for key, value in record.values],
            )
            for record in statuses
        ]
        message = types[DIAGNOSTIC_ARRAY_TYPE](header=_header(stamp_ns, ""), status=status)
        self._write(DIAGNOSTICS_TOPIC, stamp_ns, message)
