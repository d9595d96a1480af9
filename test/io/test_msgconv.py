"""Tests for epi_vo.io.msgconv on plain objects carrying the message fields."""

from __future__ import annotations

import array
import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from epi_vo.core.errors import EpiVoError, ImageConversionError
from epi_vo.core.frame import clamp_stamp_ns
from epi_vo.io.msgconv import (
    POINT_FIELD_FLOAT32,
    POINT_FIELD_FLOAT64,
    ROS_TIME_MAX_NS,
    PointFieldSpec,
    compressed_to_gray,
    decode_frame,
    image_to_gray,
    ns_to_ros_time,
    point_cloud2_fields,
    read_points_xyz,
    stamp_problem,
    stamp_to_ns,
)


def _image(
    encoding: str,
    pixels: np.ndarray,
    *,
    step: int | None = None,
    is_bigendian: bool = False,
    pad_value: int = 0xEE,
) -> SimpleNamespace:
    """A sensor_msgs/Image-like object with ``pixels`` (H, W[, C]), rows ``step`` bytes apart.

    Padding bytes are filled with ``pad_value`` so a test notices if they leak into the result.
    """
    height, width = pixels.shape[:2]
    dtype = pixels.dtype.newbyteorder(">" if is_bigendian else "<")
    row_bytes = pixels[0].astype(dtype).tobytes()
    step = len(row_bytes) if step is None else step
    data = bytearray([pad_value]) * (step * height)
    for row in range(height):
        data[row * step : row * step + len(row_bytes)] = pixels[row].astype(dtype).tobytes()
    return SimpleNamespace(
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=is_bigendian,
        step=step,
        data=bytes(data),
    )


MONO8 = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
RED, GREEN, BLUE = (255, 0, 0), (0, 255, 0), (0, 0, 255)
# cv2 (ITU-R BT.601, fixed point) gray of pure red, green, blue: 0.299, 0.587, 0.114 of 255.
GRAY_OF_RED, GRAY_OF_GREEN, GRAY_OF_BLUE = 76, 150, 29


# --- image_to_gray: known answers ---------------------------------------------------------------


@pytest.mark.parametrize("encoding", ["mono8", "8UC1"])
def test_mono8_known_answer(encoding: str) -> None:
    np.testing.assert_array_equal(image_to_gray(_image(encoding, MONO8)), MONO8)


@pytest.mark.parametrize(
    "wrap",
    [
        bytes,
        bytearray,
        memoryview,
        lambda b: array.array("B", b),
        list,
        lambda b: np.frombuffer(b, np.uint8),
    ],
    ids=["bytes", "bytearray", "memoryview", "array.array", "list", "ndarray"],
)
def test_data_container_types(wrap) -> None:
    msg = _image("mono8", MONO8)
    msg.data = wrap(msg.data)
    gray = image_to_gray(msg)
    assert gray.dtype == np.uint8
    np.testing.assert_array_equal(gray, MONO8)


def test_mono8_without_padding_shares_the_message_buffer() -> None:
    msg = _image("mono8", MONO8)
    msg.data = np.frombuffer(msg.data, np.uint8).copy()
    assert np.shares_memory(image_to_gray(msg), msg.data)


@pytest.mark.parametrize("encoding", ["mono16", "16UC1"])
@pytest.mark.parametrize("is_bigendian", [False, True])
def test_mono16_keeps_high_byte(encoding: str, is_bigendian: bool) -> None:
    pixels = np.array([[0x0000, 0x00FF, 0x0100], [0x1234, 0xABCD, 0xFFFF]], dtype=np.uint16)
    gray = image_to_gray(_image(encoding, pixels, is_bigendian=is_bigendian))
    np.testing.assert_array_equal(gray, [[0x00, 0x00, 0x01], [0x12, 0xAB, 0xFF]])


def test_mono16_byte_order_matters() -> None:
    msg = _image("mono16", np.array([[0x1234]], dtype=np.uint16))  # little-endian bytes 34 12
    msg.is_bigendian = True
    np.testing.assert_array_equal(image_to_gray(msg), [[0x34]])


@pytest.mark.parametrize(
    ("encoding", "red", "green", "blue"),
    [
        ("rgb8", RED, GREEN, BLUE),
        ("bgr8", RED[::-1], GREEN[::-1], BLUE[::-1]),
        ("rgba8", (*RED, 7), (*GREEN, 7), (*BLUE, 7)),
        ("bgra8", (*RED[::-1], 7), (*GREEN[::-1], 7), (*BLUE[::-1], 7)),
    ],
)
def test_colour_known_answers(encoding: str, red: tuple, green: tuple, blue: tuple) -> None:
    channels = len(red)
    grey = (90,) * 3 + ((7,) if channels == 4 else ())
    pixels = np.array([[red, green], [blue, grey]], dtype=np.uint8)
    gray = image_to_gray(_image(encoding, pixels))
    np.testing.assert_array_equal(gray, [[GRAY_OF_RED, GRAY_OF_GREEN], [GRAY_OF_BLUE, 90]])


# --- image_to_gray: step and size -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("encoding", "pixels", "expected"),
    [
        ("mono8", MONO8, MONO8),
        ("mono16", MONO8.astype(np.uint16) << 8, MONO8),
        ("bgr8", np.repeat(MONO8[:, :, None], 3, axis=2), MONO8),
        ("rgba8", np.dstack([MONO8, MONO8, MONO8, np.full_like(MONO8, 9)]), MONO8),
    ],
)
def test_padded_step_skips_padding(encoding: str, pixels: np.ndarray, expected: np.ndarray) -> None:
    row_bytes = pixels[0].nbytes
    msg = _image(encoding, pixels, step=row_bytes + 7)
    gray = image_to_gray(msg)
    np.testing.assert_array_equal(gray, expected)
    assert gray.flags.c_contiguous


def test_data_longer_than_step_times_height_is_accepted() -> None:
    msg = _image("mono8", MONO8)
    msg.data = msg.data + b"\x00" * 5
    np.testing.assert_array_equal(image_to_gray(msg), MONO8)


# --- image_to_gray: bad input -------------------------------------------------------------------


def test_unsupported_encoding() -> None:
    msg = _image("mono8", MONO8)
    msg.encoding = "32FC1"
    with pytest.raises(
        ImageConversionError,
        match=r"unsupported image encoding '32FC1' \(supported: mono8, 8UC1, mono16",
    ):
        image_to_gray(msg)


def test_data_shorter_than_step_times_height() -> None:
    msg = _image("mono8", MONO8)
    msg.data = msg.data[:10]
    with pytest.raises(
        ImageConversionError, match=r"image data has 10 bytes, expected at least step\*height = 12"
    ):
        image_to_gray(msg)


def test_step_smaller_than_row() -> None:
    msg = _image("bgr8", np.zeros((2, 4, 3), np.uint8))
    msg.step = 8
    with pytest.raises(
        ImageConversionError, match=r"step 8 smaller than width\*bytes_per_pixel = 12"
    ):
        image_to_gray(msg)


@pytest.mark.parametrize(("height", "width"), [(0, 4), (3, 0), (0, 0)])
def test_zero_size(height: int, width: int) -> None:
    msg = SimpleNamespace(
        height=height, width=width, encoding="mono8", is_bigendian=False, step=width, data=b""
    )
    with pytest.raises(
        ImageConversionError, match=rf"zero size \(width {width}, height {height}\)"
    ):
        image_to_gray(msg)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (np.zeros(12, dtype=np.int64), "numpy array of dtype int64, expected uint8"),
        ([300] * 12, r"not a list of bytes \(0..255\)"),
        (array.array("H", [0] * 12), "array.array of typecode 'H'"),
        ("abcdefghijkl", "data of type str is not a byte buffer"),
    ],
)
def test_bad_data_containers(data: object, match: str) -> None:
    msg = _image("mono8", MONO8)
    msg.data = data
    with pytest.raises(ImageConversionError, match=match):
        image_to_gray(msg)


def test_conversion_error_is_a_type_error() -> None:
    """Like cv_bridge's CvBridgeError, so callers catching TypeError keep working."""
    assert issubclass(ImageConversionError, TypeError)
    assert issubclass(ImageConversionError, EpiVoError)


# --- compressed_to_gray -------------------------------------------------------------------------


def _compressed(fmt: str, data: bytes) -> SimpleNamespace:
    return SimpleNamespace(format=fmt, data=data)


def test_png_round_trip_is_exact() -> None:
    gray = np.random.default_rng(0).integers(0, 256, size=(24, 32), dtype=np.uint8)
    ok, encoded = cv2.imencode(".png", gray)
    assert ok
    np.testing.assert_array_equal(compressed_to_gray(_compressed("png", encoded.tobytes())), gray)


def test_colour_png_is_converted_to_gray() -> None:
    bgr = np.random.default_rng(1).integers(0, 256, size=(16, 16, 3), dtype=np.uint8)
    ok, encoded = cv2.imencode(".png", bgr)
    assert ok
    gray = compressed_to_gray(
        _compressed("bgr8; png compressed bgr8", bytearray(encoded.tobytes()))
    )
    np.testing.assert_allclose(gray, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), atol=1)


def test_jpeg_round_trip_is_close() -> None:
    ramp = np.tile(np.linspace(0, 255, 64).astype(np.uint8), (48, 1))
    ok, encoded = cv2.imencode(".jpg", ramp, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    gray = compressed_to_gray(_compressed("jpeg", np.asarray(encoded).reshape(-1)))
    assert gray.shape == ramp.shape
    assert gray.dtype == np.uint8
    assert np.abs(gray.astype(int) - ramp).max() <= 4


def test_corrupt_payload_raises() -> None:
    with pytest.raises(
        ImageConversionError, match=r"could not decode CompressedImage \(format 'jpeg', 7 bytes\)"
    ):
        compressed_to_gray(_compressed("jpeg", b"garbage"))


def test_truncated_jpeg_raises() -> None:
    ramp = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
    _, encoded = cv2.imencode(".jpg", ramp)
    with pytest.raises(ImageConversionError, match="could not decode CompressedImage"):
        compressed_to_gray(_compressed("jpeg", encoded.tobytes()[:20]))


def test_empty_payload_raises() -> None:
    with pytest.raises(ImageConversionError, match=r"\(format 'png', 0 bytes\)"):
        compressed_to_gray(_compressed("png", b""))


# --- PointCloud2 ---------------------------------------------------------------------------------


def test_point_cloud2_fields_layout() -> None:
    points_xyz = np.array([[1.0, 2.0, 3.0], [-4.5, 0.25, 1e3]])
    fields = point_cloud2_fields(points_xyz)
    assert fields["height"] == 1
    assert fields["width"] == 2
    assert fields["fields"] == [
        PointFieldSpec("x", 0, POINT_FIELD_FLOAT32, 1),
        PointFieldSpec("y", 4, POINT_FIELD_FLOAT32, 1),
        PointFieldSpec("z", 8, POINT_FIELD_FLOAT32, 1),
    ]
    assert fields["is_bigendian"] is False
    assert fields["point_step"] == 12
    assert fields["row_step"] == 24
    assert fields["is_dense"] is True
    assert fields["data"].dtype == np.uint8
    np.testing.assert_array_equal(
        np.frombuffer(fields["data"].tobytes(), "<f4").reshape(-1, 3), points_xyz
    )


def test_point_cloud2_round_trip() -> None:
    points_xyz = np.random.default_rng(4).normal(scale=20.0, size=(500, 3))
    cloud = SimpleNamespace(**point_cloud2_fields(points_xyz))
    read = read_points_xyz(cloud)
    assert read.dtype == np.float32
    np.testing.assert_array_equal(read, points_xyz.astype(np.float32))


def test_point_cloud2_drops_non_finite_points() -> None:
    points_xyz = np.array(
        [[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [0.0, np.inf, 1.0], [4.0, 5.0, 6.0]]
    )
    fields = point_cloud2_fields(points_xyz)
    assert fields["width"] == 2
    assert fields["row_step"] == 24
    np.testing.assert_array_equal(
        read_points_xyz(SimpleNamespace(**fields)), [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    )


def test_point_cloud2_empty() -> None:
    fields = point_cloud2_fields(np.zeros((0, 3)))
    assert fields["width"] == 0
    assert fields["data"].size == 0
    assert read_points_xyz(SimpleNamespace(**fields)).shape == (0, 3)


def test_point_cloud2_bad_shape() -> None:
    with pytest.raises(EpiVoError, match=r"points_xyz has shape \(4, 2\), expected \(N, 3\)"):
        point_cloud2_fields(np.zeros((4, 2)))


def test_read_points_with_foreign_layout() -> None:
    """Organised 2x2 cloud, big-endian float64 x y z after an intensity field, padded rows."""
    points_xyz = np.arange(12, dtype=np.float64).reshape(2, 2, 3) - 5.5
    point_step, row_step = 32, 2 * 32 + 8
    data = bytearray(row_step * 2)
    for row in range(2):
        for col in range(2):
            start = row * row_step + col * point_step
            data[start : start + 4] = np.float32(99.0).astype(">f4").tobytes()  # intensity
            data[start + 8 : start + 32] = points_xyz[row, col].astype(">f8").tobytes()
    cloud = SimpleNamespace(
        height=2,
        width=2,
        fields=[
            PointFieldSpec("intensity", 0, POINT_FIELD_FLOAT32, 1),
            PointFieldSpec("x", 8, POINT_FIELD_FLOAT64, 1),
            PointFieldSpec("y", 16, POINT_FIELD_FLOAT64, 1),
            PointFieldSpec("z", 24, POINT_FIELD_FLOAT64, 1),
        ],
        is_bigendian=True,
        point_step=point_step,
        row_step=row_step,
        data=bytes(data),
        is_dense=True,
    )
    np.testing.assert_array_equal(read_points_xyz(cloud), points_xyz.reshape(-1, 3))


def test_read_points_errors() -> None:
    cloud = SimpleNamespace(**point_cloud2_fields(np.ones((3, 3))))
    cloud.fields = cloud.fields[:2]
    with pytest.raises(EpiVoError, match=r"PointCloud2 has no field 'z' \(fields: \['x', 'y'\]\)"):
        read_points_xyz(cloud)

    cloud = SimpleNamespace(**point_cloud2_fields(np.ones((3, 3))))
    cloud.fields = [f._replace(datatype=2) if f.name == "y" else f for f in cloud.fields]
    with pytest.raises(EpiVoError, match="field 'y' has datatype 2, expected 7 or 8"):
        read_points_xyz(cloud)

    cloud = SimpleNamespace(**point_cloud2_fields(np.ones((3, 3))))
    cloud.data = cloud.data[:30]
    with pytest.raises(EpiVoError, match="PointCloud2 data has 30 bytes, expected at least 36"):
        read_points_xyz(cloud)


# --- stamps (builtin_interfaces/Time) --------------------------------------------------------------------
def _stamp(sec: object, nanosec: object) -> SimpleNamespace:
    return SimpleNamespace(sec=sec, nanosec=nanosec)


def test_ros_time_limit_equals_the_pipelines() -> None:
    from epi_vo.core.frame import MAX_STAMP_NS

    assert ROS_TIME_MAX_NS == MAX_STAMP_NS == (2**31 - 1) * 10**9 + 999_999_999


@pytest.mark.parametrize(("sec", "nanosec"), [(0, 0), (1, 999_999_999), (2**31 - 1, 999_999_999),
                                              (np.int32(5), np.uint32(7))])
def test_valid_stamps(sec: int, nanosec: int) -> None:
    stamp = _stamp(sec, nanosec)
    assert stamp_problem(stamp) is None
    ns = stamp_to_ns(stamp)
    assert ns == int(sec) * 10**9 + int(nanosec) and type(ns) is int
    assert ns_to_ros_time(ns) == (int(sec), int(nanosec))


@pytest.mark.parametrize(("sec", "nanosec", "ns"), [
    (-3, 5, -2_999_999_995),                                   # negative seconds
    (2**31 - 1, 1_500_000_000, (2**31 - 1) * 10**9 + 1_500_000_000),  # at the int32 limit, nanosec >= 1e9
    (7, 1_000_000_000, 8 * 10**9),                             # nanosec == 1e9: carries, but no valid ROS time
    (7, 2**32 - 1, 7 * 10**9 + 2**32 - 1),                     # uint32 max nanosec
    (2**31, 0, 2**31 * 10**9),                                 # beyond int32
])
def test_invalid_stamps_are_named_and_never_crash(sec: int, nanosec: int, ns: int) -> None:
    stamp = _stamp(sec, nanosec)
    problem = stamp_problem(stamp)
    assert problem == (f"header stamp sec {sec} nanosec {nanosec} is not a valid ROS time (sec 0..2147483647, "
                       "nanosec 0..999999999)")
    assert stamp_to_ns(stamp) == ns  # the plain sum, as the node normalises it
    clamped = clamp_stamp_ns(ns)
    assert 0 <= clamped <= ROS_TIME_MAX_NS
    sec_c, nsec_c = ns_to_ros_time(clamped)
    assert 0 <= sec_c <= 2**31 - 1 and 0 <= nsec_c < 10**9
    if not 0 <= ns <= ROS_TIME_MAX_NS:
        with pytest.raises(ValueError, match=rf"stamp {ns} ns is not a valid ROS time"):
            ns_to_ros_time(ns)


@pytest.mark.parametrize(("sec", "nanosec"), [(None, 0), (1.5, 0), ("1", 0), (1, math.nan), (True, 0)])
def test_non_integer_stamp_fields(sec: object, nanosec: object) -> None:
    stamp = _stamp(sec, nanosec)
    assert stamp_problem(stamp) is not None and "not a builtin_interfaces/Time" in stamp_problem(stamp)
    with pytest.raises(ImageConversionError, match="header stamp is not a builtin_interfaces/Time"):
        stamp_to_ns(stamp)
    assert "not a builtin_interfaces/Time" in (stamp_problem(None) or "")


@pytest.mark.parametrize("compressed", [False, True])
def test_decode_frame_of_a_missing_or_malformed_message_is_a_conversion_error(compressed: bool) -> None:
    with pytest.raises(ImageConversionError, match=r"no image message \(its bytes could not be decoded\)"):
        decode_frame(None, compressed)
    with pytest.raises(ImageConversionError, match="not a usable sensor_msgs/"):
        decode_frame(SimpleNamespace(encoding="mono8", height="x", width=2, step=2, data=b"ab", format="png"),
                     compressed=False) if not compressed else decode_frame(SimpleNamespace(), compressed=True)
