"""What ``vo_node`` and ``vo_lifecycle_node`` share outside the node itself: the ROS messages built from
a frame result (stamp, point cloud, debug image) and the entry point that runs a node (``--help``
without DDS, bad parameters and ROS arguments rcl cannot parse as exit 2 with one line, spin until Ctrl-C)."""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from typing import IO, Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2, PointField
from std_msgs.msg import Header

from epi_vo.core.config import VoConfig
from epi_vo.core.errors import ConfigError
from epi_vo.io import msgconv
from epi_vo.io.node_options import NodeOptions
from epi_vo.runner.outputs import OdometryRecord

RCLError, UnknownROSArgsError = rclpy_implementation.RCLError, rclpy_implementation.UnknownROSArgsError


def stamp_msg(stamp_ns: int) -> Time:
    """A frame result's stamp as a ROS time (results carry valid stamps only)."""
    sec, nanosec = msgconv.ns_to_ros_time(stamp_ns)
    return Time(sec=sec, nanosec=nanosec)


def header_msg(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=stamp_msg(stamp_ns), frame_id=frame_id)


def odometry_msg(odometry: OdometryRecord) -> Odometry:
    """nav_msgs/Odometry of one odometry record (pose of the child in the frame, twist in the child)."""
    s = odometry.sample
    msg = Odometry()
    msg.header = header_msg(s.stamp_ns, odometry.frame_id)
    msg.child_frame_id = odometry.child_frame_id
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = (float(v) for v in s.position)
    q.x, q.y, q.z, q.w = (float(v) for v in s.quat_xyzw)
    msg.pose.covariance = [float(v) for v in s.pose_covariance.ravel()]
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    lin.x, lin.y, lin.z = (float(v) for v in s.linear_velocity)
    ang.x, ang.y, ang.z = (float(v) for v in s.angular_velocity)
    msg.twist.covariance = [float(v) for v in s.twist_covariance.ravel()]
    return msg


def transform_msg(stamp: Time, parent: str, child: str, xyz: Any, quat_xyzw: Any) -> TransformStamped:
    """A TF message: ``child`` at ``xyz`` with orientation ``quat_xyzw`` in ``parent``."""
    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id, msg.child_frame_id = parent, child
    t = msg.transform.translation
    t.x, t.y, t.z = (float(v) for v in xyz)
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = (float(v) for v in quat_xyzw)
    return msg


def point_cloud_msg(header: Any, points: np.ndarray) -> PointCloud2:
    f = msgconv.point_cloud2_fields(points)
    msg = PointCloud2()
    msg.header = header
    msg.height, msg.width = f["height"], f["width"]
    msg.fields = [PointField(name=p.name, offset=p.offset, datatype=p.datatype, count=p.count) for p in f["fields"]]
    msg.is_bigendian, msg.point_step, msg.row_step = f["is_bigendian"], f["point_step"], f["row_step"]
    msg.data = bytes(f["data"])
    msg.is_dense = f["is_dense"]
    return msg


def bgr_image_msg(header: Any, img: np.ndarray) -> Image:
    msg = Image()
    msg.header = header
    msg.height, msg.width = img.shape[:2]
    msg.encoding = "bgr8"
    msg.step = img.shape[1] * 3
    msg.data = img.tobytes()
    return msg


def help_requested(argv: list[str]) -> bool:
    """``--help`` / ``-h`` before any ``--ros-args`` (after it, the arguments are ROS's)."""
    user_args = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    return "--help" in user_args or "-h" in user_args


class _HeldOutput:
    def __init__(self, file: IO[bytes]) -> None:
        self.file, self.keep = file, True

    def discard(self) -> None:
        self.keep = False


@contextlib.contextmanager
def _c_stderr_held() -> Iterator[_HeldOutput]:
    """What the C libraries write to stderr (file descriptor 2) in the block is held, and written out after
    it unless discarded: rcl logs its own line when it refuses the arguments, before rclpy raises."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        held = _HeldOutput(tmp)
        os.dup2(tmp.fileno(), 2)
        try:
            yield held
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            if held.keep:
                tmp.seek(0)
                sys.stderr.flush()
                os.write(2, tmp.read())


def ros_arguments_problem(exc: Exception) -> str:
    """One line from rcl's refusal of the ``--ros-args``: the rule it could not parse, without the parser's
    source locations."""
    if isinstance(exc, UnknownROSArgsError):
        return f"unknown ROS arguments {exc} (a value with spaces needs quotes: -p 'name:=a b')"
    text = str(exc).removeprefix("failed to initialize rcl: ")
    text = re.split(r"\. Error: |, at /", text)[0]
    return f"the ROS arguments cannot be used: {text}"


def run_node(make_node: Callable[[], Node], program: str, help_text: str, args: list[str] | None) -> None:
    """The entry point of vo_node and vo_lifecycle_node: ``--help`` prints ``help_text`` and the parameters
    and exits 0 before rclpy starts (no DDS touched); bad parameters exit 2 naming every one; else spin
    until Ctrl-C or an external shutdown."""
    argv = sys.argv[1:] if args is None else list(args)
    if help_requested(argv):
        from epi_vo.io.params import to_params_yaml

        sys.stdout.write(help_text + to_params_yaml(VoConfig(), node=NodeOptions()))
        sys.exit(0)
    refused = ""
    with _c_stderr_held() as held:
        try:
            rclpy.init(args=args)
        except (RCLError, UnknownROSArgsError) as exc:  # rcl refused the arguments themselves
            held.discard()  # rcl's own log line ("Failed to parse global arguments"): this one says more
            refused = ros_arguments_problem(exc)
    if refused:
        print(f"{program}: error: {refused}", file=sys.stderr)
        sys.exit(2)
    try:
        node = make_node()
    except ConfigError as exc:
        print(f"{program}: error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        sys.exit(2)
    except (KeyboardInterrupt, ExternalShutdownException):  # stopped while starting (Ctrl-C, launch): as in spin
        rclpy.try_shutdown()
        return
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # Ctrl-C (or launch's SIGINT) shut the context down while the executor was making its wait set: rcl
        # says the context is not valid. A stop like the others; any other rcl error is raised.
        if rclpy.ok():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
