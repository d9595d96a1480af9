"""Conversion between ROS message fields and numpy arrays, by field name only.

Every function reads or fills plain attributes (``msg.height``, ``msg.data``, ...), so the same code
serves rclpy messages, rosbags messages and simple test objects. No ROS import here.
"""

from __future__ import annotations

import array
from dataclasses import dataclass
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from epi_vo.core.errors import EpiVoError, ImageConversionError, clipped, quoted
from epi_vo.core.frame import MAX_STAMP_NS
from epi_vo.io.image_header import declared_size


@dataclass(frozen=True)
class _PixelFormat:
    """Layout of one ``sensor_msgs/Image`` encoding."""

    bytes_per_channel: int  # 1 or 2
    channels: int
    to_gray: int | None  # cv2.cvtColor code, None when already single channel


_PIXEL_FORMATS: dict[str, _PixelFormat] = {
    "mono8": _PixelFormat(1, 1, None),
    "8UC1": _PixelFormat(1, 1, None),
    "mono16": _PixelFormat(2, 1, None),
    "16UC1": _PixelFormat(2, 1, None),
    "bgr8": _PixelFormat(1, 3, cv2.COLOR_BGR2GRAY),
    "rgb8": _PixelFormat(1, 3, cv2.COLOR_RGB2GRAY),
    "bgra8": _PixelFormat(1, 4, cv2.COLOR_BGRA2GRAY),
    "rgba8": _PixelFormat(1, 4, cv2.COLOR_RGBA2GRAY),
}

SUPPORTED_IMAGE_ENCODINGS: tuple[str, ...] = tuple(_PIXEL_FORMATS)

# sensor_msgs/PointField datatype constants used here.
POINT_FIELD_FLOAT32 = 7
POINT_FIELD_FLOAT64 = 8


class PointFieldSpec(NamedTuple):
    """Fields of one ``sensor_msgs/PointField``."""

    name: str
    offset: int
    datatype: int
    count: int  # type: ignore[assignment]  # PointField's name, over tuple.count


def _bytes_of(data: Any, what: str) -> NDArray[np.uint8]:
    """The message ``data`` field as a 1-D uint8 array, sharing memory whenever the type allows.

    bytes, bytearray, memoryview, ``array.array('B')`` (rclpy) and uint8 numpy arrays (rosbags) are
    wrapped without copying; a list (hand-built messages) has to be copied.
    """
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            msg = f"{what} data is a numpy array of dtype {data.dtype}, expected uint8"
            raise ImageConversionError(msg)
        return data.reshape(-1)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    if isinstance(data, array.array):
        if data.itemsize != 1:
            msg = f"{what} data is an array.array of typecode {data.typecode!r}, expected bytes"
            raise ImageConversionError(msg)
        return np.frombuffer(data, dtype=np.uint8)
    if isinstance(data, (list, tuple)):
        try:
            return np.array(data, dtype=np.uint8)
        except (OverflowError, TypeError, ValueError) as err:
            msg = f"{what} data list is not a list of bytes (0..255): {err}"
            raise ImageConversionError(msg) from None
    msg = f"{what} data of type {type(data).__name__} is not a byte buffer"
    raise ImageConversionError(msg)


def image_to_gray(msg: Any) -> NDArray[np.uint8]:
    """Gray image (H, W) uint8 from a ``sensor_msgs/Image``-like object.

    Reads ``height``, ``width``, ``encoding``, ``is_bigendian``, ``step`` and ``data``. Supported
    encodings: mono8 (also 8UC1), mono16 (also 16UC1), bgr8, rgb8, bgra8, rgba8.

    - Rows are ``step`` bytes apart; any padding beyond ``width * bytes_per_pixel`` is skipped.
    - mono16 is reduced to 8 bits by keeping the high byte (``value >> 8``); ``is_bigendian`` sets
      the byte order of the 16-bit samples.
    - Colour is converted with ``cv2.cvtColor`` (ITU-R BT.601 weights: 0.299 R + 0.587 G + 0.114 B).

    For mono8 without row padding the result is a view of ``msg.data`` (no copy); it is then
    read-only when ``data`` is immutable (bytes). Otherwise a new C-contiguous array is returned.

    Raises ImageConversionError for an unsupported encoding, zero size, ``step`` smaller than a
    row, or ``data`` shorter than ``step * height``.
    """
    encoding = str(msg.encoding)
    pixel_format = _PIXEL_FORMATS.get(encoding)
    if pixel_format is None:
        msg_text = (
            f"unsupported image encoding {quoted(encoding)} "
            f"(supported: {', '.join(SUPPORTED_IMAGE_ENCODINGS)})"
        )
        raise ImageConversionError(msg_text)

    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        msg_text = f"image has zero size (width {width}, height {height})"
        raise ImageConversionError(msg_text)
    bytes_per_pixel = pixel_format.bytes_per_channel * pixel_format.channels
    if step < width * bytes_per_pixel:
        msg_text = (
            f"step {step} smaller than width*bytes_per_pixel = {width * bytes_per_pixel} "
            f"({encoding}, width {width})"
        )
        raise ImageConversionError(msg_text)
    buffer = _bytes_of(msg.data, "image")
    if buffer.size < step * height:
        msg_text = (
            f"image data has {buffer.size} bytes, expected at least step*height = {step * height}"
        )
        raise ImageConversionError(msg_text)

    sample_dtype: np.dtype[Any] = np.dtype(np.uint8)
    if pixel_format.bytes_per_channel == 2:
        sample_dtype = np.dtype(">u2" if msg.is_bigendian else "<u2")
    # A strided view over the message buffer: rows `step` bytes apart, so padding is never read.
    pixels = np.ndarray(
        shape=(height, width, pixel_format.channels),
        dtype=sample_dtype,
        buffer=buffer,
        strides=(step, bytes_per_pixel, pixel_format.bytes_per_channel),
    )

    if pixel_format.bytes_per_channel == 2:
        return (pixels[:, :, 0] >> 8).astype(np.uint8)
    if pixel_format.to_gray is None:
        return np.ascontiguousarray(pixels[:, :, 0], dtype=np.uint8)
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels), pixel_format.to_gray), dtype=np.uint8)


# The most pixels a CompressedImage may declare: beyond every camera a VO runs on (8K is 33 Mpx), and a
# bound on what decoding allocates (OpenCV decodes colour first: ~200 MB at this size) that no payload,
# however small, can raise: a 1 MB PNG of one colour can declare 30000 x 30000 pixels.
MAX_DECODED_PIXELS = 1 << 26


def compressed_to_gray(msg: Any, expected_size: tuple[int, int] | None = None) -> NDArray[np.uint8]:
    """Gray image (H, W) uint8 decoded from a ``sensor_msgs/CompressedImage``-like object.

    Reads ``format`` (only for messages) and ``data``: a JPEG or a PNG (the formats of ROS's compressed
    transport), decoded with ``IMREAD_GRAYSCALE`` (16-bit PNG reduced to 8 bits) and
    ``IMREAD_IGNORE_ORIENTATION``: an EXIF orientation tag is not applied, as image_transport's compressed
    subscriber does not apply it (the pixels are the sensor's, as camera_info describes them).

    Before decoding, the size the header declares (:func:`epi_vo.io.image_header.declared_size`) must be
    at most ``MAX_DECODED_PIXELS`` and, with ``expected_size`` (width, height: camera_info's, after
    binning and roi), equal to it: a payload that would decode into more pixels is never decoded.
    Raises ImageConversionError (beginning "could not decode CompressedImage") for an empty, undecodable,
    oversized or mismatched payload; never returns None.
    """
    buffer = _bytes_of(msg.data, "CompressedImage")
    what = f"could not decode CompressedImage (format {quoted(msg.format)}, {buffer.size} bytes)"
    if not buffer.size:
        raise ImageConversionError(what)
    size = declared_size(buffer)
    if isinstance(size, str):
        raise ImageConversionError(f"{what}: {size}")
    if size.width * size.height > MAX_DECODED_PIXELS:
        msg_text = (f"{what}: its {size.format.upper()} header declares {size.width}x{size.height} pixels, more "
                    f"than the {MAX_DECODED_PIXELS} an image may have (not decoded)")
        raise ImageConversionError(msg_text)
    if expected_size is not None and (size.width, size.height) != tuple(expected_size):
        msg_text = (f"{what}: image size {size.width}x{size.height} does not match camera_info size "
                    f"{expected_size[0]}x{expected_size[1]} (declared by its {size.format.upper()} header, not "
                    "decoded)")
        raise ImageConversionError(msg_text)
    gray = None
    try:
        gray = cv2.imdecode(buffer, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error:
        gray = None
    if gray is None:
        raise ImageConversionError(what)
    if gray.shape != (size.height, size.width):  # decoded otherwise than declared: not what was checked
        msg_text = f"{what}: decoded {gray.shape[1]}x{gray.shape[0]}, its header declares {size.width}x{size.height}"
        raise ImageConversionError(msg_text)
    return np.asarray(gray, dtype=np.uint8)


def decode_frame(msg: Any, compressed: bool, expected_size: tuple[int, int] | None = None) -> NDArray[np.uint8]:
    """Grayscale pixels of a sensor_msgs/CompressedImage (``compressed``) or Image-like message.

    ``expected_size`` (width, height), camera_info's: a CompressedImage declaring another size is refused
    before it is decoded (see :func:`compressed_to_gray`; a raw Image's size is checked by the pipeline).
    Raises ImageConversionError for anything that is not a usable image message, also a missing
    message (None: its bytes could not be deserialised) or fields of the wrong type.
    """
    if msg is None:
        msg_text = "no image message (its bytes could not be decoded)"
        raise ImageConversionError(msg_text)
    try:
        return compressed_to_gray(msg, expected_size) if compressed else image_to_gray(msg)
    except ImageConversionError:
        raise
    except (AttributeError, TypeError, ValueError, OverflowError) as err:
        kind = "CompressedImage" if compressed else "Image"
        msg_text = f"not a usable sensor_msgs/{kind} message ({type(err).__name__}: {clipped(str(err), 200)})"
        raise ImageConversionError(msg_text) from None


# builtin_interfaces/Time: int32 sec (a ROS time is never negative), uint32 nanosec below one second.
ROS_TIME_MAX_SEC = 2**31 - 1
NS_PER_S = 1_000_000_000
# The largest stamp a ROS time can hold, in nanoseconds.
ROS_TIME_MAX_NS = MAX_STAMP_NS


def _stamp_fields(stamp: Any) -> tuple[int, int]:
    """(sec, nanosec) of a builtin_interfaces/Time-like object as ints; TypeError/ValueError if not integral."""
    sec, nanosec = stamp.sec, stamp.nanosec
    values = []
    for value in (sec, nanosec):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            # rclpy and rosbags give ints; a float or None here is not a stamp.
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                msg = f"not an integer: {value!r}"
                raise ValueError(msg)
        values.append(int(value))
    return values[0], values[1]


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (fields sec, nanosec) as integer nanoseconds: ``sec * 1e9 + nanosec``.

    Never checks the range (a nanosec >= 1e9 carries into the seconds, a negative sec gives a negative
    result): see :func:`stamp_problem` for whether the stamp is a valid ROS time. Raises
    ImageConversionError (an EpiVoError) when a field is not an integer.
    """
    try:
        sec, nanosec = _stamp_fields(stamp)
    except (AttributeError, ValueError) as err:
        msg = f"header stamp is not a builtin_interfaces/Time ({err})"
        raise ImageConversionError(msg) from None
    return sec * NS_PER_S + nanosec


def stamp_problem(stamp: Any) -> str | None:
    """Why a builtin_interfaces/Time is not a valid ROS time, or None when it is one.

    Valid: integer ``sec`` in [0, 2**31 - 1] and integer ``nanosec`` in [0, 1e9). Never raises.
    """
    try:
        sec, nanosec = _stamp_fields(stamp)
    except (AttributeError, ValueError) as err:
        return f"header stamp is not a builtin_interfaces/Time ({err})"
    if not 0 <= sec <= ROS_TIME_MAX_SEC or not 0 <= nanosec < NS_PER_S:
        return (f"header stamp sec {sec} nanosec {nanosec} is not a valid ROS time (sec 0..{ROS_TIME_MAX_SEC}, "
                f"nanosec 0..{NS_PER_S - 1})")
    return None


class WheelMessage(NamedTuple):
    """A wheel odometry message as the scale source takes it: its header stamp (None: no valid ROS time) and
    the position of its pose (m, in its fixed odom frame; NaN where a field is not a number)."""

    stamp_ns: int | None
    position_xyz: NDArray[np.float64]


def odometry_position(msg: Any) -> WheelMessage:
    """A nav_msgs/Odometry message as the wheel odometry buffer takes it (``epi_vo.core.scale.WheelOdometry``,
    the same for the node and the replay): its header stamp in ns, None when that is no valid ROS time, and
    its pose's position (NaN where a field is not a number). Never raises on a message's values."""
    stamp = msg.header.stamp
    stamp_ns = None if stamp_problem(stamp) is not None else stamp_to_ns(stamp)
    p = msg.pose.pose.position
    try:
        xyz = np.array([float(p.x), float(p.y), float(p.z)], dtype=np.float64)
    except (TypeError, ValueError):
        xyz = np.full(3, np.nan)
    return WheelMessage(stamp_ns, xyz)


def ns_to_ros_time(stamp_ns: int) -> tuple[int, int]:
    """(sec, nanosec) of a stamp in integer nanoseconds; ValueError unless 0 <= stamp_ns <= ROS_TIME_MAX_NS."""
    stamp_ns = int(stamp_ns)
    if not 0 <= stamp_ns <= ROS_TIME_MAX_NS:
        msg = f"stamp {stamp_ns} ns is not a valid ROS time (0..{ROS_TIME_MAX_NS} ns)"
        raise ValueError(msg)
    sec, nanosec = divmod(stamp_ns, NS_PER_S)
    return sec, nanosec




def point_cloud2_fields(points_xyz: ArrayLike) -> dict[str, Any]:
    """Field values of an unorganised ``sensor_msgs/PointCloud2`` holding ``points_xyz`` (N, 3).

    Returns a dict with keys ``height`` (1), ``width`` (N kept), ``fields`` (list of PointFieldSpec
    x, y, z: FLOAT32, offsets 0, 4, 8, count 1), ``is_bigendian`` (False), ``point_step`` (12),
    ``row_step`` (12 N), ``data`` (uint8 array of little-endian float32 x y z per point) and
    ``is_dense`` (True). The header is left to the caller.

    Rows with a coordinate that is not finite as float32 (NaN, inf, or beyond the float32 range) are
    dropped, so the cloud is dense as declared; ``width`` counts the points actually kept. Raises
    EpiVoError when ``points_xyz`` is not (N, 3).
    """
    points = np.asarray(points_xyz, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        msg = f"points_xyz has shape {points.shape}, expected (N, 3)"
        raise EpiVoError(msg)
    # Filter after the cast: a finite float64 beyond the float32 range (|x| > 3.4e38) becomes inf.
    with np.errstate(over="ignore"):
        as_f4 = points.astype("<f4")
    kept = as_f4[np.all(np.isfinite(as_f4), axis=1)]
    count = int(kept.shape[0])
    return {
        "height": 1,
        "width": count,
        "fields": [
            PointFieldSpec("x", 0, POINT_FIELD_FLOAT32, 1),
            PointFieldSpec("y", 4, POINT_FIELD_FLOAT32, 1),
            PointFieldSpec("z", 8, POINT_FIELD_FLOAT32, 1),
        ],
        "is_bigendian": False,
        "point_step": 12,
        "row_step": 12 * count,
        "data": np.ascontiguousarray(kept).view(np.uint8).reshape(-1),
        "is_dense": True,
    }


def read_points_xyz(msg: Any) -> NDArray[np.float32]:
    """Points (N, 3) float32 x, y, z from a ``sensor_msgs/PointCloud2``-like object.

    Uses ``fields`` (name, offset, datatype), ``point_step``, ``row_step``, ``height``, ``width``,
    ``is_bigendian`` and ``data``, so any field layout (extra fields, padding, organised clouds) is
    read. x, y, z must be FLOAT32 or FLOAT64. N = height * width; non-finite points are kept. Raises
    EpiVoError when a field is missing or of another type, or the data is too short.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    byte_order = ">" if msg.is_bigendian else "<"
    fields = {str(field.name): field for field in msg.fields}
    buffer = _bytes_of(msg.data, "PointCloud2")
    if height * width == 0:
        return np.zeros((0, 3), dtype=np.float32)
    if buffer.size < row_step * (height - 1) + point_step * width:
        msg_text = (
            f"PointCloud2 data has {buffer.size} bytes, expected at least "
            f"{row_step * (height - 1) + point_step * width} for {height}x{width} points "
            f"(point_step {point_step}, row_step {row_step})"
        )
        raise EpiVoError(msg_text)

    points = np.empty((height, width, 3), dtype=np.float32)
    for axis, name in enumerate("xyz"):
        field = fields.get(name)
        if field is None:
            msg_text = f"PointCloud2 has no field {name!r} (fields: {sorted(fields)})"
            raise EpiVoError(msg_text)
        if int(field.datatype) == POINT_FIELD_FLOAT32:
            dtype = np.dtype(f"{byte_order}f4")
        elif int(field.datatype) == POINT_FIELD_FLOAT64:
            dtype = np.dtype(f"{byte_order}f8")
        else:
            msg_text = f"PointCloud2 field {name!r} has datatype {field.datatype}, expected 7 or 8"
            raise EpiVoError(msg_text)
        if int(field.offset) + dtype.itemsize > point_step:
            msg_text = f"PointCloud2 field {name!r} ends beyond point_step {point_step}"
            raise EpiVoError(msg_text)
        points[:, :, axis] = np.ndarray(
            shape=(height, width),
            dtype=dtype,
            buffer=buffer,
            offset=int(field.offset),
            strides=(row_step, point_step),
        )
    return points.reshape(-1, 3)
