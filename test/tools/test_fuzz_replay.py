"""Property-based fuzzing (hypothesis) of whole ``epi-vo replay`` runs on small generated bags.

Each example is a small rosbag2 bag (MCAP or sqlite3 storage) of 4 to 8 images (64x48 to 160x120 frames
of bags/general_motion downscaled, or a synthetic texture moving across the view; one in six tiny, 1x1
to 8x8, or small, up to 47 px a side, cropped) with their camera_info, randomly corrupted in:

* CameraInfo fields: K, D, distortion_model, width / height, binning, roi, P, R (zero, negative,
  non-finite and absurd values such as fx = 1e-300 or 1e300), or a consistent binning / roi (valid);
* Image fields: encoding, step, width / height against the data, data truncated or extended, byte
  order, CompressedImage payload and format;
* the serialized CDR bytes of single messages (bits flipped, truncated, extended, length words);
* header stamps (negative, duplicated, backwards, zero, sec at int32 max, nanosec >= 1e9) and the
  stamps of camera_info;
* message order (shuffled, camera_info before / after the images, only the first / last / some
  camera_info, an empty camera_info topic, no camera_info topic at all);
* a wheel odometry stream (nav_msgs/Odometry on /wheel/odom at 50 Hz, the bag then replayed with
  ``scale_source: wheel_odometry``): messages stamped early or late, shuffled, with the stamp of the one
  before, NaN / infinite positions, stamps that are no ROS time, gaps.

The bag is replayed in-process with ``epi_vo.cli.main(["replay", BAG, "--output", OUT])`` and every
example must satisfy:

1. no uncaught exception, no "Traceback" on stdout / stderr, no log record carrying an exception;
2. exit code in {0, 2, 3}; exit code 2 ("the bag itself cannot be read") only for a bag without a
   camera_info topic: the generated bags are always readable containers, a corrupt message is bad input
   in one frame (docs/bad_input.md), not a reason to abandon the replay;
3. exit code 0 or 3: frames.jsonl has exactly one JSON line per image message written, indexed 0..N-1;
4. nothing non-finite (NaN / inf, also as the strings "NaN" / "Infinity") and every quaternion of unit
   norm (within 1e-6) in trajectory.tum, frames.jsonl and output.mcap (Odometry pose / twist /
   covariances, PointCloud2 points, Path poses, DiagnosticArray values that parse as numbers); every
   header stamp and log / publish time in output.mcap a valid ROS time (sec in [0, 2^31-1],
   nanosec < 1e9); output.mcap readable;
5. a clean bag (every message well formed and consistent with docs/bad_input.md's rules, valid stamps, a
   consistent binning / roi allowed) exits 0 with no rejected frame;
6. a frame docs/bad_input.md says cannot be used (unsupported encoding, data shorter than step x height, size
   different from camera_info's after binning / roi, smaller than the KLT frontend can use, K[0] == 0,
   non-finite K or D, unknown distortion model, non-zero D of the wrong length, implausible intrinsics,
   no camera_info message) has no pose, and the replay exits 3;
7. a record saying "frame rejected" means the replay exits 3 (docs/tools.md: rejected frames -> exit 3);
8. with a wheel stream, exit code 0 or 3: ``stats.json``'s ``wheel_odometry`` counts every message written
   and what became of it as the one rule says (messages in the bag's order, used only when stamped after
   every message used before; ``_wheel_expected`` is a model of it), every record's ``wheel_messages`` is
   such a count, and a note names the wheel topic whenever a message was dropped.

Every example of the run is replayed and checked (a failure does not stop the run); failures are grouped
in classes (the invariant and a normalised key, e.g. ``exit-2-on-readable-bag: epi-vo: error: cannot
read /camera/image_raw``, or the exception type and the epi_vo function it escaped from), and the test
fails with one report listing every class, how many examples fell in it and its smallest example.

Runtime: the default run is 40 derandomized examples, under 10 s on a 2-core machine. A larger run is
behind a pytest option (conftest.py); it also shrinks one example per class with hypothesis::

    .venv/bin/python -m pytest test/test_fuzz_replay.py                       # default: 40 examples
    .venv/bin/python -m pytest test/test_fuzz_replay.py --fuzz-examples 300   # 300 examples + shrinking

Each example is printed as a ``BagPlan``; ``check_replay(plan, directory)`` writes that bag again,
replays it and checks it (the report shows the one-liner), ``build_bag(plan, directory)`` only writes it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import math
import re
import signal
import sys
import tempfile
import traceback
from collections.abc import Iterator, Sequence
from functools import cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, note, settings
from hypothesis import strategies as st
from hypothesis.errors import InvalidArgument
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from epi_vo.cli import main
from epi_vo.core.config import VoConfig

REPO = Path(__file__).resolve().parents[2]
SOURCE_BAG = REPO / "bags" / "general_motion" / "bag"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
Image = TYPESTORE.types["sensor_msgs/msg/Image"]
CompressedImage = TYPESTORE.types["sensor_msgs/msg/CompressedImage"]
CameraInfo = TYPESTORE.types["sensor_msgs/msg/CameraInfo"]
RegionOfInterest = TYPESTORE.types["sensor_msgs/msg/RegionOfInterest"]
Header = TYPESTORE.types["std_msgs/msg/Header"]
Time = TYPESTORE.types["builtin_interfaces/msg/Time"]
Odometry = TYPESTORE.types["nav_msgs/msg/Odometry"]
WHEEL_TOPIC = "/wheel/odom"
WHEEL_PERIOD_NS = 20_000_000  # 50 Hz

DEFAULT_EXAMPLES = 40
REPLAY_TIMEOUT_S = 120  # one replay of <= 8 small frames taking longer than this is a hang
INT32_MAX = 2**31 - 1
UINT32_MAX = 2**32 - 1
NS = 1_000_000_000
T0_NS = 1_700_000_000 * NS
PERIOD_NS = 66_666_667
IMAGE_TOPIC_RAW = "/camera/image_raw"
IMAGE_TOPIC_COMPRESSED = "/camera/image_raw/compressed"
INFO_TOPIC = "/camera/camera_info"

# The documented encodings (docs/bad_input.md) and their bytes per pixel; other accepted spellings are
# neither required nor forbidden, so frames using them are of unknown validity.
README_ENCODINGS = {"mono8": 1, "mono16": 2, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4}
ENCODING_ALIASES = {"8UC1", "16UC1"}
# docs/bad_input.md: an image smaller than the frontend can use (KLT: 2 x klt_window_px + 2) is rejected.
MIN_IMAGE_SIDE = 2 * VoConfig().klt_window_px + 2
DISTORTION_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,), "equidistant": (4,)}


# ==================================================================================================
# Source frames
# ==================================================================================================
@cache
def _source() -> tuple[np.ndarray, Any]:
    """The gray frames (N, 480, 640) of bags/general_motion and its first CameraInfo."""
    frames: list[np.ndarray] = []
    info = None
    with AnyReader([SOURCE_BAG], default_typestore=TYPESTORE) as reader:
        for con, _, raw in reader.messages():
            msg = reader.deserialize(raw, con.msgtype)
            if con.msgtype == CompressedImage.__msgtype__:
                frames.append(cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE))
            elif con.msgtype == CameraInfo.__msgtype__ and info is None:
                info = msg
    assert frames and info is not None
    return np.stack(frames), info


@cache
def _texture(seed: int) -> np.ndarray:
    """A 256x256 gray texture: blobs at several scales plus fine noise (trackable corners)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((256, 256), np.float64)
    for cells, weight in ((4, 1.0), (16, 0.6), (64, 0.35)):
        img += weight * cv2.resize(rng.random((cells, cells)), (256, 256), interpolation=cv2.INTER_CUBIC)
    img += 0.15 * rng.random((256, 256))
    img = (img - img.min()) / (np.ptp(img) + 1e-12)
    return (img * 255).astype(np.uint8)


# ==================================================================================================
# The plan of one bag
# ==================================================================================================
@dataclasses.dataclass(frozen=True)
class BagPlan:
    """Everything that defines one generated bag; ``build_bag`` turns it into files.

    Modifications are tuples whose last element is the scope: ``"all"`` or a tuple of frame indices.
    """

    n: int = 4
    width: int = 64
    height: int = 48
    scene: str = "bag"  # "bag": frames of general_motion; "texture": a synthetic texture sliding by
    start: int = 0  # first source frame (or texture seed)
    step: int = 1  # source frames between images (or texture shift per image, px)
    transport: str = "raw"  # raw Image or CompressedImage
    encoding: str = "mono8"  # raw: one of README_ENCODINGS; compressed: "jpeg" / "png"
    pad: int = 0  # raw: row padding bytes
    bigendian: bool = False  # raw mono16: byte order
    storage: str = "mcap"
    binning: tuple[int, int, int, int, int, int, bool] | None = None  # bx, by, rx, ry, extra w, extra h, roi 0
    info_mods: tuple[tuple[Any, ...], ...] = ()
    image_mods: tuple[tuple[Any, ...], ...] = ()
    cdr_mods: tuple[tuple[Any, ...], ...] = ()  # (target, frame, kind, amount, seed)
    stamp_mods: tuple[tuple[Any, ...], ...] = ()  # (frame, kind, value)
    info_stamps: str = "same"  # same as the image's final stamp / base (uncorrupted) / zero / offset
    presence: str = "all"  # which camera_info messages are written
    order: str = "info_first"
    seed: int = 0  # for shuffles, subsets, byte flips
    wheel: tuple[tuple[Any, ...], ...] | None = None  # None: no wheel topic; else its stream's modifications

    def __repr__(self) -> str:  # only what differs from a clean default bag: readable falsifying examples
        default = BagPlan.__new__(BagPlan)
        for f in dataclasses.fields(BagPlan):
            object.__setattr__(default, f.name, f.default)
        parts = [f"{f.name}={_py(getattr(self, f.name))}" for f in dataclasses.fields(self)
                 if getattr(self, f.name) != getattr(default, f.name)]
        return f"BagPlan({', '.join(parts)})"


def _py(x: Any) -> str:
    """repr that Python can evaluate back, non-finite floats included."""
    if isinstance(x, float) and not math.isfinite(x):
        return f"float('{x}')"
    if isinstance(x, tuple):
        return "(" + ", ".join(_py(v) for v in x) + ("," if len(x) == 1 else "") + ")"
    if isinstance(x, list):
        return "[" + ", ".join(_py(v) for v in x) + "]"
    return repr(x)


@dataclasses.dataclass
class BuiltBag:
    """A bag written from a plan, with what the oracles need to know about it."""

    path: Path
    n_images: int
    image_order: list[int]  # frame index of the k-th image message in the bag
    has_info_topic: bool
    frame_class: list[str]  # per frame: "good", "bad" (docs/bad_input.md: cannot be used) or "unknown"
    frame_why: list[str]
    clean: bool  # every frame good, valid stamps, nothing corrupted: must exit 0 with nothing rejected
    why_not_clean: str
    wheel_expected: dict[str, int] | None = None  # what the replay must count of the wheel stream


def _in_scope(scope: Any, i: int) -> bool:
    return scope == "all" or i in scope


def _stamps(plan: BagPlan) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(base stamps, final image stamps) as (sec, nanosec) pairs."""
    base = [divmod(T0_NS + i * PERIOD_NS, NS) for i in range(plan.n)]
    final = list(base)
    for i in range(plan.n):
        for frame, kind, value in plan.stamp_mods:
            if frame % plan.n != i:
                continue
            prev = final[i - 1] if i > 0 else final[i]
            if kind == "negative":
                final[i] = (-1 - value % INT32_MAX, value % NS)
            elif kind == "dup":
                final[i] = prev
            elif kind == "backwards":
                ns = max(prev[0] * NS + prev[1] - 1 - value, 0)
                final[i] = divmod(ns, NS)
            elif kind == "int32max":
                final[i] = (INT32_MAX, value)
            elif kind == "nanosec_overflow":
                final[i] = (final[i][0], value)
            elif kind == "zero":
                final[i] = (0, 0)
            elif kind == "jump":
                final[i] = (min(final[i][0] + value, INT32_MAX), final[i][1])
            else:
                raise AssertionError(kind)
    return base, final


def _valid_ros_time(sec: int, nanosec: int) -> bool:
    return 0 <= sec <= INT32_MAX and 0 <= nanosec < NS


def _gray_frames(plan: BagPlan) -> list[np.ndarray]:
    """The plan's frames: downscaled; below 32 px a side cropped instead (keeping sharp corners)."""
    w, h = plan.width, plan.height
    crop = min(w, h) < 32
    if plan.scene == "texture" and crop:
        tex = _texture(plan.start)
        return [tex[60 + i * plan.step: 60 + i * plan.step + h, 60 + i * plan.step: 60 + i * plan.step + w].copy()
                for i in range(plan.n)]
    if plan.scene == "texture":
        tex = _texture(plan.start)
        out = []
        for i in range(plan.n):
            x0, y0 = 40 + i * plan.step, 40 + (i * plan.step) // 2
            crop = tex[y0: y0 + 120, x0: x0 + 160]
            out.append(cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA))
        return out
    frames, _ = _source()
    idx = [min(plan.start + i * plan.step, len(frames) - 1) for i in range(plan.n)]
    if crop:
        return [frames[j][200: 200 + h, 280: 280 + w].copy() for j in idx]
    return [cv2.resize(frames[j], (w, h), interpolation=cv2.INTER_AREA) for j in idx]


def _header(stamp: tuple[int, int]) -> Any:
    return Header(stamp=Time(sec=stamp[0], nanosec=stamp[1]), frame_id="camera_optical_frame")


def _base_info(plan: BagPlan) -> Any:
    """The source calibration for the W x H image, as a full-sensor calibration with binning / roi when
    the plan asks for a consistent one (image = roi reduced by binning, as image_geometry reads it)."""
    _, src = _source()
    w, h = plan.width, plan.height
    sx, sy = w / src.width, h / src.height
    k = np.asarray(src.k, np.float64).copy()
    k[0], k[2] = k[0] * sx, (k[2] + 0.5) * sx - 0.5
    k[4], k[5] = k[4] * sy, (k[5] + 0.5) * sy - 0.5
    fields: dict[str, Any] = {"width": w, "height": h, "binning_x": 0, "binning_y": 0,
                              "roi": RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)}
    if plan.binning is not None:
        bx, by, rx, ry, ex, ey, roi_zero = plan.binning
        fx_, fy_ = max(bx, 1), max(by, 1)
        rw, rh = w * fx_, h * fy_
        if roi_zero:
            rx = ry = ex = ey = 0
        k[0], k[4] = k[0] * fx_, k[4] * fy_
        k[2], k[5] = k[2] * fx_ + rx, k[5] * fy_ + ry
        roi = RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False) if roi_zero else \
            RegionOfInterest(x_offset=rx, y_offset=ry, height=rh, width=rw, do_rectify=False)
        fields = {"width": rx + rw + ex, "height": ry + rh + ey, "binning_x": bx, "binning_y": by, "roi": roi}
    p = np.zeros(12)
    p[[0, 2, 5, 6, 10]] = k[0], k[2], k[4], k[5], 1.0
    return CameraInfo(header=_header((0, 0)), distortion_model="plumb_bob", d=np.asarray(src.d, np.float64).copy(),
                      k=k, r=np.eye(3).reshape(9), p=p, **fields)


def _info_content(msg: Any) -> tuple[Any, ...]:
    roi = msg.roi
    return (msg.width, msg.height, msg.distortion_model, tuple(np.asarray(msg.d).tolist()),
            tuple(np.asarray(msg.k).tolist()), tuple(np.asarray(msg.r).tolist()), tuple(np.asarray(msg.p).tolist()),
            msg.binning_x, msg.binning_y, roi.x_offset, roi.y_offset, roi.width, roi.height, roi.do_rectify)


def _same_content(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    return repr(a) == repr(b)  # NaN-safe


def _apply_info_mods(info: Any, mods: Sequence[tuple[Any, ...]], i: int) -> Any:
    values = {f.name: getattr(info, f.name) for f in dataclasses.fields(info)}
    values["k"], values["d"] = np.asarray(values["k"]).copy(), np.asarray(values["d"]).copy()
    values["p"], values["r"] = np.asarray(values["p"]).copy(), np.asarray(values["r"]).copy()
    roi = {f.name: getattr(info.roi, f.name) for f in dataclasses.fields(info.roi)}
    for mod in mods:
        field, *args, scope = mod
        if not _in_scope(scope, i):
            continue
        if field in ("k", "p", "r"):
            idx, value = args
            values[field][idx % values[field].size] = value
        elif field == "d":
            values["d"] = np.asarray(args[0], np.float64)
        elif field == "d_item":
            idx, value = args
            if values["d"].size:
                values["d"][idx % values["d"].size] = value
        elif field in ("width", "height", "binning_x", "binning_y", "distortion_model"):
            values[field] = args[0]
        elif field == "roi":
            (roi["x_offset"], roi["y_offset"], roi["width"], roi["height"]), roi["do_rectify"] = args
        else:
            raise AssertionError(field)
    values["roi"] = RegionOfInterest(**roi)
    return CameraInfo(**values)


def _encode_raw(gray: np.ndarray, encoding: str, pad: int, bigendian: bool, seed: int) -> tuple[np.ndarray, int]:
    """(data, step) of ``gray`` in ``encoding`` with ``pad`` bytes of row padding."""
    if encoding in ("mono8", "8UC1"):
        px = gray[:, :, None]
    elif encoding in ("mono16", "16UC1"):
        noise = np.random.default_rng(seed).integers(0, 256, gray.shape, dtype=np.uint16)
        samples = (gray.astype(np.uint16) << 8 | noise).astype(">u2" if bigendian else "<u2")
        px = np.frombuffer(samples.tobytes(), np.uint8).reshape(*gray.shape, 2)
    elif encoding in ("bgr8", "rgb8"):
        px = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    else:
        px = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGRA)
    h, w, c = px.shape
    rows = np.full((h, w * c + pad), 0xEE, np.uint8)
    rows[:, : w * c] = px.reshape(h, w * c)
    return rows.reshape(-1), w * c + pad


def _apply_image_mods(msg: Any, mods: Sequence[tuple[Any, ...]], i: int, seed: int) -> Any:
    values = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
    data = bytearray(np.asarray(values["data"], np.uint8).tobytes())
    raw = "encoding" in values
    for mod in mods:
        field, *args, scope = mod
        if not _in_scope(scope, i):
            continue
        if field == "encoding":
            values["encoding" if raw else "format"] = args[0]
        elif field in ("step", "width", "height") and raw:
            values[field] = args[0]
        elif field == "swap_wh" and raw:
            values["width"], values["height"] = values["height"], values["width"]
        elif field == "bigendian" and raw:
            values["is_bigendian"] = 1 - int(values["is_bigendian"])
        elif field == "truncate":
            data = data[: len(data) * args[0] // 1000]
        elif field == "extend":
            data += np.random.default_rng(seed + i).integers(0, 256, args[0], dtype=np.uint8).tobytes()
        elif field == "flip" and data:
            rng = np.random.default_rng(seed + 7 * i)
            for j in rng.integers(0, len(data), args[0]):
                data[j] = int(rng.integers(0, 256))
    values["data"] = np.frombuffer(bytes(data), np.uint8).copy()
    return type(msg)(**values)


def _corrupt_cdr(data: bytes, kind: str, amount: int, seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    b = bytearray(data)
    if len(b) < 16 and kind in ("flip", "flip_head", "length"):  # (after an earlier truncation)
        kind = "extend"
    if kind == "flip":  # random bits anywhere
        for _ in range(amount):
            j = int(rng.integers(0, len(b)))
            b[j] ^= 1 << int(rng.integers(0, 8))
    elif kind == "flip_head":  # random bytes among the header, stamps, lengths and sizes
        for _ in range(amount):
            j = int(rng.integers(0, min(len(b), 96)))
            b[j] = int(rng.integers(0, 256))
    elif kind == "length":  # one aligned 32-bit word of the first 96 bytes made absurd
        j = 4 + 4 * int(rng.integers(0, (min(len(b), 96) - 4) // 4))
        b[j: j + 4] = int(rng.choice([0, 0x7FFFFFFF, 0xFFFFFFFF, len(b), len(b) + 1])).to_bytes(4, "little")
    elif kind == "truncate":
        b = b[: len(b) * amount // 1000]
    elif kind == "extend":
        b += rng.integers(0, 256, amount, dtype=np.uint8).tobytes()
    else:
        raise AssertionError(kind)
    return bytes(b)


def _expected_size(info: Any) -> tuple[int, int] | None:
    """The image size a CameraInfo announces (roi reduced by binning, as image_geometry reads it);
    None when the roi is not inside the calibrated image (no well-defined answer)."""
    bx, by = int(info.binning_x) or 1, int(info.binning_y) or 1
    roi = info.roi
    rx, ry, rw, rh = int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)
    if (rx, ry, rw, rh) == (0, 0, 0, 0):
        rw, rh = int(info.width), int(info.height)
    elif rw == 0 or rh == 0 or rx + rw > info.width or ry + rh > info.height:
        return None
    return rw // bx, rh // by


def _info_problem(info: Any) -> str | None:
    """Why docs/bad_input.md ("Calibration") says this CameraInfo cannot be used, or
    None. The plausibility limits are checked only without binning / roi (then the documented "image side"
    is unambiguous)."""
    k = np.asarray(info.k, np.float64)
    d = np.asarray(info.d, np.float64)
    if not np.all(np.isfinite(k)):
        return "K not finite"
    if k[0] == 0.0:
        return "uncalibrated (fx = 0)"
    if not np.all(np.isfinite(d)):
        return "D not finite"
    if info.distortion_model not in DISTORTION_MODELS:
        return f"unknown distortion model {info.distortion_model!r}"
    if np.any(d != 0.0) and d.size not in DISTORTION_MODELS[info.distortion_model]:
        return f"D of length {d.size} for {info.distortion_model}"
    if d.size and float(np.max(np.abs(d))) > 1e4:
        return "implausible distortion coefficient (|D| > 1e4)"
    roi = info.roi
    if int(info.binning_x) > 1 or int(info.binning_y) > 1 or (roi.x_offset, roi.y_offset, roi.width, roi.height) != (
            0, 0, 0, 0):
        return None
    w, h = int(info.width), int(info.height)
    side = max(w, h)
    for name, f in (("fx", k[0]), ("fy", k[4])):
        if not 0.02 * side <= f <= 100.0 * side:
            return f"implausible focal length {name} = {f:g} for a {w}x{h} image"
    for name, c, size in (("cx", k[2], w), ("cy", k[5], h)):
        if not -size <= c <= 2 * size:
            return f"implausible principal point {name} = {c:g} for a {w}x{h} image"
    return None


def _image_problem(msg: Any) -> tuple[str, str]:
    """("good" / "bad" / "unknown", why) for a raw Image message by the documented rules (docs/bad_input.md)."""
    enc = msg.encoding
    if enc in ENCODING_ALIASES:
        return "unknown", f"encoding alias {enc}"
    if enc not in README_ENCODINGS:
        return "bad", f"unsupported encoding {enc!r}"
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    if w == 0 or h == 0:
        return "bad", f"empty image {w}x{h}"
    if step < w * README_ENCODINGS[enc]:
        return "bad", f"step {step} < width x bytes per pixel"
    if len(msg.data) < step * h:
        return "bad", f"data {len(msg.data)} bytes < step x height {step * h}"
    return "good", ""


def build_bag(plan: BagPlan, directory: Path) -> BuiltBag:
    """Write the bag of ``plan`` into ``directory / "bag"`` and classify its frames."""
    base_stamps, stamps = _stamps(plan)
    grays = _gray_frames(plan)
    base_info = _base_info(plan)
    good_info = _info_content(base_info)

    images: list[Any] = []
    for i, gray in enumerate(grays):
        if plan.transport == "raw":
            data, step = _encode_raw(gray, plan.encoding, plan.pad, plan.bigendian, plan.seed + i)
            msg = Image(header=_header(stamps[i]), height=gray.shape[0], width=gray.shape[1], encoding=plan.encoding,
                        is_bigendian=int(plan.bigendian and plan.encoding in ("mono16", "16UC1")), step=step, data=data)
        else:
            msg = CompressedImage(header=_header(stamps[i]), format=plan.encoding,
                                  data=np.frombuffer(_compressed(gray, plan.encoding), np.uint8).copy())
        images.append(_apply_image_mods(msg, plan.image_mods, i, plan.seed))

    infos: list[Any] = []
    for i in range(plan.n):
        if plan.info_stamps == "same":
            st_i = stamps[i]
        elif plan.info_stamps == "base":
            st_i = base_stamps[i]
        elif plan.info_stamps == "zero":
            st_i = (0, 0)
        else:  # offset: half a period later
            st_i = divmod(base_stamps[i][0] * NS + base_stamps[i][1] + PERIOD_NS // 2, NS)
        msg = dataclasses.replace(base_info, header=_header(st_i))
        infos.append(_apply_info_mods(msg, plan.info_mods, i))

    rng = np.random.default_rng(plan.seed)
    written_infos = {"all": list(range(plan.n)), "first": [0], "last": [plan.n - 1],
                     "subset": sorted(rng.choice(plan.n, max(1, plan.n // 2), replace=False).tolist()),
                     "empty_topic": [], "no_topic": []}[plan.presence]
    entries: list[tuple[str, int]] = []  # (kind, frame) in write (= log time) order
    img_entries = [("image", i) for i in range(plan.n)]
    info_entries = [("info", i) for i in written_infos]
    if plan.order in ("info_first", "image_first"):
        for i in range(plan.n):
            pair = [("info", i)] if i in written_infos else []
            pair = [*pair, ("image", i)] if plan.order == "info_first" else [("image", i), *pair]
            entries += pair
    elif plan.order == "infos_first":
        entries = info_entries + img_entries
    elif plan.order == "infos_last":
        entries = img_entries + info_entries
    else:  # shuffle
        entries = img_entries + info_entries
        entries = [entries[j] for j in rng.permutation(len(entries))]

    payload: dict[tuple[str, int], bytes] = {}
    for i in range(plan.n):
        image_type = Image if plan.transport == "raw" else CompressedImage
        payload["image", i] = bytes(TYPESTORE.serialize_cdr(images[i], image_type.__msgtype__))
        payload["info", i] = bytes(TYPESTORE.serialize_cdr(infos[i], CameraInfo.__msgtype__))
    corrupted: set[tuple[str, int]] = set()
    for target, frame, kind, amount, seed in plan.cdr_mods:
        key = (target, frame % plan.n)
        if target == "info" and key[1] not in written_infos:
            continue
        payload[key] = _corrupt_cdr(payload[key], kind, amount, seed)
        corrupted.add(key)

    path = directory / "bag"
    storage = StoragePlugin.MCAP if plan.storage == "mcap" else StoragePlugin.SQLITE3
    has_info_topic = plan.presence != "no_topic"
    with Writer(path, version=9, storage_plugin=storage) as w:
        if plan.transport == "raw":
            ci = w.add_connection(IMAGE_TOPIC_RAW, Image.__msgtype__, typestore=TYPESTORE)
        else:
            ci = w.add_connection(IMAGE_TOPIC_COMPRESSED, CompressedImage.__msgtype__, typestore=TYPESTORE)
        cc = w.add_connection(INFO_TOPIC, CameraInfo.__msgtype__, typestore=TYPESTORE) if has_info_topic else None
        for k, (kind, i) in enumerate(entries):
            w.write(ci if kind == "image" else cc, 1_000_000_000 + k * 1_000_000, payload[kind, i])
        wheel_expected = None
        if plan.wheel is not None:
            wheel = _wheel_stream(plan)
            cw = w.add_connection(WHEEL_TOPIC, Odometry.__msgtype__, typestore=TYPESTORE)
            for j, msg in enumerate(wheel):  # the topic's own order is its log times' (its arrival order)
                w.write(cw, 1_000_000_500 + j * 1_000, bytes(TYPESTORE.serialize_cdr(msg, Odometry.__msgtype__)))
            wheel_expected = _wheel_expected(wheel)

    # --- what the documented rules say about each frame ------------------------------------------
    contents = [_info_content(infos[i]) for i in written_infos]
    uniform = bool(contents) and all(_same_content(c, contents[0]) for c in contents)
    info_cdr_corrupted = any(t == "info" for t, _ in corrupted)
    info_state, info_why, info_size = "unknown", "camera_info differs between messages", None
    if not written_infos:
        info_state, info_why = ("bad", "no camera_info message") if has_info_topic else ("unknown", "no topic")
    elif info_cdr_corrupted:
        info_why = "a camera_info message's CDR is corrupted"
    elif all(_info_problem(infos[i]) for i in written_infos):
        info_state, info_why = "bad", "; ".join(sorted({str(_info_problem(infos[i])) for i in written_infos}))
    elif uniform:
        info_size = _expected_size(infos[written_infos[0]])
        if _same_content(contents[0], good_info):
            info_state, info_why = "good", ""
        else:
            info_why = "camera_info modified"
    frame_class, frame_why = [], []
    for i, img in enumerate(images):
        size: tuple[int, int] | None = None
        if ("image", i) in corrupted:
            cls, why = "unknown", "image CDR corrupted"
        elif plan.transport == "raw":
            (cls, why), size = _image_problem(img), (int(img.width), int(img.height))
        else:
            unchanged = img.format == plan.encoding and img.data.tobytes() == _compressed(grays[i], plan.encoding)
            cls, why = ("good", "") if unchanged else ("unknown", "compressed payload or format modified")
            size = (grays[i].shape[1], grays[i].shape[0]) if unchanged else None
        if cls == "good" and size is not None and min(size) < MIN_IMAGE_SIDE:
            cls, why = "bad", f"image {size[0]}x{size[1]} smaller than the KLT frontend can use ({MIN_IMAGE_SIDE} px)"
        if cls != "bad" and info_state == "bad":
            cls, why = "bad", info_why
        elif cls != "bad" and info_size is not None and size is not None and size != info_size:
            cls, why = "bad", f"image size {size[0]}x{size[1]} != camera_info size {info_size[0]}x{info_size[1]}"
        if cls == "good" and info_state != "good":
            cls, why = "unknown", info_why
        frame_class.append(cls)
        frame_why.append(why)

    reasons = []
    if any(c != "good" for c in frame_class):
        reasons.append("frames " + ", ".join(f"{i}:{c}" for i, c in enumerate(frame_class) if c != "good"))
    bad_stamps = [i for i in range(plan.n) if not _valid_ros_time(*stamps[i])]
    if bad_stamps:
        reasons.append(f"invalid image stamps at {bad_stamps}")
    if plan.info_stamps == "same" and any(not _valid_ros_time(*stamps[i]) for i in written_infos):
        reasons.append("invalid camera_info stamps")
    if corrupted:
        reasons.append(f"corrupted CDR {sorted(corrupted)}")
    if not written_infos:
        reasons.append("no camera_info")
    image_order = [i for kind, i in entries if kind == "image"]
    return BuiltBag(path, plan.n, image_order, has_info_topic, frame_class, frame_why, not reasons,
                    "; ".join(reasons), wheel_expected)


def _wheel_stream(plan: BagPlan) -> list[Any]:
    """The plan's wheel messages in arrival order: 50 Hz from 0.2 s before the first image to 0.2 s after the
    last, 0.5 m/s along x, then modified."""
    t0 = T0_NS - 200_000_000
    n = (plan.n * PERIOD_NS + 400_000_000) // WHEEL_PERIOD_NS
    stamps: list[tuple[int, int]] = [divmod(t0 + j * WHEEL_PERIOD_NS, NS) for j in range(n)]
    xs = [0.5 * j * WHEEL_PERIOD_NS / NS for j in range(n)]
    keep = [True] * n
    order = list(range(n))
    for kind, a, b in plan.wheel or ():
        j = a % n
        if kind == "every":  # every a-th message (a >= 2) stamped b ns early (b < 0: late)
            for k in range(a - 1, n, max(a, 2)):
                stamps[k] = divmod(max(stamps[k][0] * NS + stamps[k][1] - b, 0), NS)
        elif kind == "dup":
            stamps[j] = stamps[j - 1] if j else stamps[j]
        elif kind == "nan":  # b messages from j
            for k in range(j, min(n, j + b)):
                xs[k] = [math.nan, math.inf, -math.inf][k % 3]
        elif kind == "gap":
            for k in range(j, min(n, j + b)):
                keep[k] = False
        elif kind == "invalid":
            stamps[j] = (-1 - b % INT32_MAX, 0) if b % 2 else (stamps[j][0], NS + b % (UINT32_MAX - NS))
        elif kind == "shuffle":
            order = [order[k] for k in np.random.default_rng(b).permutation(n)]
        else:
            raise AssertionError(kind)
    msgs = []
    for k in order:
        if not keep[k]:
            continue
        msg = Odometry(header=_header(stamps[k]), child_frame_id="base_link", pose=_odometry_pose(xs[k]),
                       twist=_ZERO_TWIST)
        msgs.append(msg)
    return msgs


def _geometry(name: str, **fields: Any) -> Any:
    return TYPESTORE.types[f"geometry_msgs/msg/{name}"](**fields)


def _odometry_pose(x: float) -> Any:
    pose = _geometry("Pose", position=_geometry("Point", x=x, y=0.0, z=0.0),
                     orientation=_geometry("Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
    return _geometry("PoseWithCovariance", pose=pose, covariance=np.zeros(36))


_ZERO = _geometry("Vector3", x=0.0, y=0.0, z=0.0)
_ZERO_TWIST = _geometry("TwistWithCovariance", twist=_geometry("Twist", linear=_ZERO, angular=_ZERO),
                        covariance=np.zeros(36))


def _wheel_expected(msgs: list[Any]) -> dict[str, int]:
    """The counts the documented wheel rule gives (a model of it, written from the rule, not from the code)."""
    counts = dict.fromkeys(("received", "used", "out_of_order", "duplicate_stamp", "non_finite", "invalid_stamp"), 0)
    newest = None
    for msg in msgs:
        counts["received"] += 1
        sec, nanosec = int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)
        p = msg.pose.pose.position
        if not _valid_ros_time(sec, nanosec):
            counts["invalid_stamp"] += 1
        elif not all(math.isfinite(v) for v in (p.x, p.y, p.z)):
            counts["non_finite"] += 1
        elif newest is not None and sec * NS + nanosec < newest:
            counts["out_of_order"] += 1
        elif sec * NS + nanosec == newest:
            counts["duplicate_stamp"] += 1
        else:
            counts["used"] += 1
            newest = sec * NS + nanosec
    return counts


def _compressed(gray: np.ndarray, fmt: str) -> bytes:
    ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", gray)
    assert ok
    return buf.tobytes()


# ==================================================================================================
# Strategies
# ==================================================================================================
_SPECIAL_FLOATS = [0.0, -0.0, 1e-300, 1e300, -1.0, math.nan, math.inf, -math.inf, 5e-324, 1.7976931348623157e308,
                   -500.0, 1e-6, 1e9, 2.0]
_ABSURD_FINITE = [1e-300, 1e300, 5e-324, 1.7976931348623157e308, 1e-12, 1e12, 1e-3, 1e5, -1e-300, -1e300, -1.0,
                  1e150, 1e-150]
_FLOATS = st.sampled_from(_SPECIAL_FLOATS) | st.floats(allow_nan=True, allow_infinity=True)
_UINTS = st.sampled_from([0, 1, 2, 3, 7, 47, 64, 160, 640, 2**16, INT32_MAX, UINT32_MAX]) | st.integers(0, 4096)
_TEXT = st.text(alphabet=st.characters(codec="utf-8"), max_size=10)


def _scope(n: int) -> st.SearchStrategy[Any]:
    return st.just("all") | st.lists(st.integers(0, n - 1), min_size=1, max_size=n, unique=True).map(
        lambda xs: tuple(sorted(xs)))


def _info_mod(n: int) -> st.SearchStrategy[tuple[Any, ...]]:
    scope = _scope(n)
    return st.one_of(
        st.tuples(st.just("k"), st.sampled_from([0, 4, 2, 5]), st.sampled_from(_ABSURD_FINITE), scope),
        st.tuples(st.just("k"), st.sampled_from([0, 0, 2, 4, 5, 1, 3, 8]), _FLOATS, scope),
        st.tuples(st.just("d"), st.lists(_FLOATS | st.floats(-1, 1), max_size=14), scope),
        st.tuples(st.just("d_item"), st.integers(0, 7), _FLOATS, scope),
        st.tuples(st.just("distortion_model"),
                  st.sampled_from(["", "plumb_bob", "rational_polynomial", "equidistant", "fisheye", "kannala_brandt",
                                   "PLUMB_BOB"]) | _TEXT, scope),
        st.tuples(st.sampled_from(["width", "height"]), _UINTS, scope),
        st.tuples(st.sampled_from(["binning_x", "binning_y"]), _UINTS, scope),
        st.tuples(st.just("roi"), st.tuples(_UINTS, _UINTS, _UINTS, _UINTS), st.booleans(), scope),
        st.tuples(st.just("p"), st.integers(0, 11), _FLOATS, scope),
        st.tuples(st.just("r"), st.integers(0, 8), _FLOATS, scope),
    )


def _image_mod(n: int) -> st.SearchStrategy[tuple[Any, ...]]:
    scope = _scope(n)
    return st.one_of(
        st.tuples(st.just("encoding"), st.sampled_from([*README_ENCODINGS, *ENCODING_ALIASES, "32FC1", "yuv422",
                                                         "bayer_rggb8", "MONO8", "jpeg", "png", ""]) | _TEXT, scope),
        st.tuples(st.sampled_from(["step", "width", "height"]), _UINTS, scope),
        st.tuples(st.just("swap_wh"), scope),
        st.tuples(st.just("bigendian"), scope),
        st.tuples(st.just("truncate"), st.integers(0, 999), scope),
        st.tuples(st.just("extend"), st.integers(1, 5000), scope),
        st.tuples(st.just("flip"), st.integers(1, 64), scope),
    )


def _cdr_mod(n: int) -> st.SearchStrategy[tuple[Any, ...]]:
    return st.tuples(st.sampled_from(["image", "info"]), st.integers(0, n - 1),
                     st.sampled_from(["flip", "flip_head", "length", "truncate", "extend"]), st.integers(1, 999),
                     st.integers(0, 2**32 - 1))


def _stamp_mod(n: int) -> st.SearchStrategy[tuple[Any, ...]]:
    frame = st.integers(0, n - 1)
    return st.one_of(
        st.tuples(frame, st.just("negative"), st.integers(0, INT32_MAX)),
        st.tuples(frame, st.just("dup"), st.just(0)),
        st.tuples(frame, st.just("backwards"), st.sampled_from([0, 1, PERIOD_NS, 10 * NS]) | st.integers(0, 10 * NS)),
        st.tuples(frame, st.just("int32max"),
                  st.sampled_from([0, NS - 1, NS, UINT32_MAX]) | st.integers(0, UINT32_MAX)),
        st.tuples(frame, st.just("nanosec_overflow"), st.sampled_from([NS, UINT32_MAX]) | st.integers(NS, UINT32_MAX)),
        st.tuples(frame, st.just("zero"), st.just(0)),
        st.tuples(frame, st.just("jump"), st.sampled_from([1, 10**6, INT32_MAX])),
    )


def _wheel_mod() -> st.SearchStrategy[tuple[Any, ...]]:
    return st.one_of(
        st.tuples(st.just("every"), st.integers(2, 5), st.sampled_from([300_000_000, 1, WHEEL_PERIOD_NS, -NS])
                  | st.integers(-10 * NS, 10 * NS)),
        st.tuples(st.just("dup"), st.integers(0, 60), st.just(0)),
        st.tuples(st.just("nan"), st.integers(0, 60), st.integers(1, 60)),
        st.tuples(st.just("gap"), st.integers(0, 60), st.integers(1, 60)),
        st.tuples(st.just("invalid"), st.integers(0, 60), st.integers(0, UINT32_MAX)),
        st.tuples(st.just("shuffle"), st.just(0), st.integers(0, 2**32 - 1)),
    )


@st.composite
def bag_plans(draw: st.DrawFn) -> BagPlan:
    n = draw(st.integers(4, 8))
    # Every choice shrinks towards a clean 64x48 bag: a rare variant is the largest value of its draw.
    if draw(st.integers(0, 5)) == 5:  # tiny (1x1 to 8x8) or below the frontend's minimum side
        width, height = draw(st.integers(1, 8) | st.integers(9, 47)), draw(st.integers(1, 8) | st.integers(9, 47))
    else:
        width, height = draw(st.integers(64, 160)), draw(st.integers(48, 120))
    scene = draw(st.sampled_from(["bag", "texture"]))
    step = draw(st.integers(1, 3)) if scene == "bag" else draw(st.integers(1, 4))
    start = draw(st.integers(0, 52 - 1 - (n - 1) * step)) if scene == "bag" else draw(st.integers(0, 3))
    transport = draw(st.sampled_from(["raw", "compressed"]))
    if transport == "raw":
        encoding = draw(st.sampled_from(list(README_ENCODINGS)))
        pad = draw(st.sampled_from([0, 0, 1, 3, 64]))
        bigendian = encoding == "mono16" and draw(st.booleans())
    else:
        encoding, pad, bigendian = draw(st.sampled_from(["jpeg", "png"])), 0, False
    binning = None
    if draw(st.integers(0, 4)) == 4:
        binning = (draw(st.integers(0, 3)), draw(st.integers(0, 3)), draw(st.integers(0, 50)),
                   draw(st.integers(0, 50)), draw(st.integers(0, 30)), draw(st.integers(0, 30)), draw(st.booleans()))

    def maybe(strategy: st.SearchStrategy[tuple[Any, ...]], odds: int) -> tuple[tuple[Any, ...], ...]:
        if draw(st.integers(1, odds)) != odds:
            return ()
        return tuple(draw(st.lists(strategy, min_size=1, max_size=3)))

    return BagPlan(
        n=n, width=width, height=height, scene=scene, start=start, step=step, transport=transport,
        encoding=encoding, pad=pad, bigendian=bigendian, storage=draw(st.sampled_from(["mcap", "sqlite3"])),
        binning=binning, info_mods=maybe(_info_mod(n), 3), image_mods=maybe(_image_mod(n), 4),
        cdr_mods=maybe(_cdr_mod(n), 6), stamp_mods=maybe(_stamp_mod(n), 3),
        info_stamps=draw(st.sampled_from(["same", "base", "zero", "offset"])),
        presence=draw(st.sampled_from(["all", "all", "first", "last", "subset", "empty_topic", "no_topic"])),
        order=draw(st.sampled_from(["info_first", "image_first", "infos_first", "infos_last", "shuffle"])),
        seed=draw(st.integers(0, 2**32 - 1)),
        # One bag in three has a wheel stream, clean or modified (shrinks towards none).
        wheel=tuple(draw(st.lists(_wheel_mod(), max_size=3))) if draw(st.integers(0, 2)) == 2 else None,
    )


# ==================================================================================================
# Replay and the invariants
# ==================================================================================================
class ReplayTimeout(Exception):  # noqa: N818 - raised from the alarm handler, reported as is
    """The replay ran longer than REPLAY_TIMEOUT_S."""


class InvariantError(AssertionError):
    """One broken invariant: ``rule`` names it, ``key`` (numbers and paths normalised away) separates its
    causes, the message says everything about this example. ``others``: further invariants broken by the
    same example."""

    def __init__(self, rule: str, key: str, message: str, others: Sequence[InvariantError] = ()) -> None:
        more = "".join(f"\n  and [{e.rule}] {e.args[0].split('] ', 1)[-1]}" for e in others)
        super().__init__(f"[{rule}] {message}{more}")
        self.rule = rule
        self.key = _normalise(key)
        self.others = list(others)

    @property
    def signature(self) -> str:
        return f"{self.rule}: {self.key}"


def _normalise(text: str) -> str:
    text = re.sub(r"/tmp/\S+", "<tmp>", text)
    text = re.sub(r"\[\d+\]|#\d+", "", text)
    return re.sub(r"[-+]?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?", "#", text)[:110]


# While check_replay runs, the violations of the later invariants are collected (so that one broken
# invariant does not hide another in the same example); outside it every check raises at once.
_COLLECTED: list[InvariantError] | None = None


def _check(ok: bool, rule: str, key: str, message: str) -> None:
    if ok:
        return
    error = InvariantError(rule, key, message)
    if _COLLECTED is None:
        raise error
    if all((e.rule, e.key) != (rule, error.key) for e in _COLLECTED):
        _COLLECTED.append(error)


def _fatal(ok: bool, rule: str, key: str, message: str) -> None:
    """A check after whose failure the later ones make no sense."""
    if not ok:
        raise InvariantError(rule, key, message)


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _on_alarm(signum: int, frame: object) -> None:
    raise ReplayTimeout(f"replay still running after {REPLAY_TIMEOUT_S} s")


@contextlib.contextmanager
def _alarm(seconds: float) -> Iterator[None]:
    old = signal.signal(signal.SIGALRM, _on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def run_replay_cli(bag: Path, out: Path, params: Path | None = None) -> tuple[int, str, list[logging.LogRecord]]:
    """``epi-vo replay BAG --output OUT [--params PARAMS]`` in this process: (exit code, stdout + stderr, log
    records).

    An exception other than SystemExit propagates: it is an uncaught exception of the CLI."""
    stdout, stderr = io.StringIO(), io.StringIO()
    handler = _Records()
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with _alarm(REPLAY_TIMEOUT_S), contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            try:
                rc = main(["replay", str(bag), "--output", str(out), "--no-progress",
                           *(["--params", str(params)] if params is not None else [])])
            except SystemExit as exc:
                rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        root.removeHandler(handler)
    return rc, stdout.getvalue() + stderr.getvalue(), handler.records


def _finite_number(s: str) -> bool | None:
    """True / False when ``s`` parses as a float (finite or not), None when it is not a number."""
    try:
        return math.isfinite(float(s))
    except ValueError:
        return None


def _check_json_values(x: Any, where: str) -> None:
    if isinstance(x, dict):
        for k, v in x.items():
            _check_json_values(v, f"{where}.{k}")
    elif isinstance(x, list):
        for j, v in enumerate(x):
            _check_json_values(v, f"{where}[{j}]")
    elif isinstance(x, float):
        _check(math.isfinite(x), "non-finite", where, f"non-finite number {x} at {where}")
    elif isinstance(x, str):
        _check(_finite_number(x) is not False, "non-finite", where, f"non-finite number as a string {x!r} at {where}")


def _check_unit_quaternion(q: Sequence[float], where: str) -> None:
    q = [float(v) for v in q]
    norm = math.sqrt(sum(v * v for v in q)) if all(math.isfinite(v) for v in q) else math.nan
    _check(abs(norm - 1.0) <= 1e-6, "quaternion", where, f"quaternion {q} of norm {norm} at {where}")


class _JsonConstant(Exception):  # noqa: N818 - internal signal, never escapes
    pass


def _reject_constant(token: str) -> Any:
    raise _JsonConstant(token)


def check_frames_jsonl(out: Path, expect_lines: int | None) -> list[dict[str, Any]]:
    """Every line a JSON object with finite numbers and a unit quaternion; with ``expect_lines``, exactly
    that many lines indexed 0..N-1."""
    path = out / "frames.jsonl"
    if not path.exists():
        _fatal(expect_lines is None, "record-count", "no frames.jsonl", "exit 0/3 without frames.jsonl")
        return []
    recs = []
    for j, line in enumerate(path.read_text().splitlines()):
        try:
            rec = json.loads(line, parse_constant=_reject_constant)
        except _JsonConstant as exc:
            field = re.search(r'"(\w+)": \[?[^"]*' + re.escape(str(exc)), line)
            where = f"frames.jsonl.{field.group(1) if field else '?'}"
            raise InvariantError("non-finite", where, f"frames.jsonl line {j}: JSON constant {exc} "
                                                          f"({where}): {line[:400]}") from None
        except json.JSONDecodeError as exc:
            raise InvariantError("record-count", "line not JSON", f"frames.jsonl line {j} is not JSON ({exc}): "
                                                                      f"{line[:400]}") from None
        _check_json_values(rec, "frames.jsonl")
        if "quat_xyzw" in rec:
            _check_unit_quaternion(rec["quat_xyzw"], "frames.jsonl.quat_xyzw")
        recs.append(rec)
    if expect_lines is not None:
        _fatal(len(recs) == expect_lines, "record-count", "lines",
               f"frames.jsonl has {len(recs)} lines for {expect_lines} image messages")
        _fatal([r.get("index") for r in recs] == list(range(expect_lines)), "record-count", "indices",
               f"frames.jsonl indices {[r.get('index') for r in recs]} are not 0..{expect_lines - 1}")
    return recs


def check_tum(out: Path) -> None:
    path = out / "trajectory.tum"
    if not path.exists():
        return
    for j, line in enumerate(path.read_text().splitlines()):
        if not line.strip() or line.startswith("#"):
            continue
        tokens = line.split()
        values = [_finite_number(t) for t in tokens]
        _check(len(tokens) == 8 and None not in values, "tum-format", "", f"trajectory.tum line {j}: {line}")
        _check(all(values), "non-finite", "trajectory.tum", f"trajectory.tum line {j} not finite: {line}")
        _check_unit_quaternion([float(t) for t in tokens[4:]], "trajectory.tum")


def _walk_message(x: Any, where: str) -> None:
    """Every float finite, every Time valid, every Quaternion of unit norm, in a deserialized message."""
    msgtype = getattr(x, "__msgtype__", None)
    if msgtype == "builtin_interfaces/msg/Time":
        _check(_valid_ros_time(int(x.sec), int(x.nanosec)), "invalid-time", where,
               f"invalid ROS time sec={x.sec} nanosec={x.nanosec} at {where}")
        return
    if msgtype == "geometry_msgs/msg/Quaternion":
        _check_unit_quaternion((x.x, x.y, x.z, x.w), where)
    if msgtype == "sensor_msgs/msg/PointCloud2":
        _check_cloud(x, where)
    if msgtype == "diagnostic_msgs/msg/KeyValue":
        if x.key != "reason":  # prose; every other value is numbers, words or k=v lists
            for token in re.split(r"[\s=,]+", x.value):
                _check(_finite_number(token) is not False, "non-finite", f"{where.split('.')[0]} {x.key}",
                       f"non-finite value {x.value!r} of {x.key!r} at {where}")
        return
    if dataclasses.is_dataclass(x):
        for f in dataclasses.fields(x):
            _walk_message(getattr(x, f.name), f"{where}.{f.name}")
    elif isinstance(x, list):
        for j, v in enumerate(x):
            _walk_message(v, f"{where}[{j}]")
    elif isinstance(x, np.ndarray):
        if x.dtype.kind == "f":
            bad = np.flatnonzero(~np.isfinite(x))
            _check(bad.size == 0, "non-finite", where,
                   f"non-finite values {x.reshape(-1)[bad[:6]].tolist()} at {where}[{bad[:6].tolist()}]")
    elif isinstance(x, float):
        _check(math.isfinite(x), "non-finite", where, f"non-finite {x} at {where}")


def _check_cloud(msg: Any, where: str) -> None:
    n = int(msg.width) * int(msg.height)
    data = np.asarray(msg.data, np.uint8)
    _check(data.size >= n * int(msg.point_step), "cloud-layout", where,
           f"PointCloud2 data {data.size} bytes for {n} points at {where}")
    rows = data[: n * msg.point_step].reshape(n, msg.point_step) if n else np.zeros((0, msg.point_step), np.uint8)
    for fld in msg.fields:
        dt = {7: "f4", 8: "f8"}.get(int(fld.datatype))
        if dt is None:
            continue
        dtype = np.dtype((">" if msg.is_bigendian else "<") + dt)
        vals = np.ascontiguousarray(rows[:, fld.offset: fld.offset + dtype.itemsize]).view(dtype).reshape(-1)
        _check(bool(np.all(np.isfinite(vals))), "non-finite", f"{where}.{fld.name}",
               f"non-finite PointCloud2 {fld.name} values at {where}")


def check_output_mcap(out: Path) -> dict[str, int]:
    from mcap.reader import make_reader

    path = out / "output.mcap"
    counts: dict[str, int] = {}
    if not path.exists():
        return counts
    try:
        with path.open("rb") as f:
            messages = list(make_reader(f).iter_messages())
    except Exception as exc:  # any failure to read is the finding
        raise InvariantError("output-unreadable", type(exc).__name__,
                                 f"output.mcap is not readable: {type(exc).__name__}: {exc}") from None
    for j, (schema, channel, message) in enumerate(messages):
        where = f"output.mcap {channel.topic} #{j}"
        for name in ("log_time", "publish_time"):
            t = int(getattr(message, name))
            _check(0 <= t <= INT32_MAX * NS + NS - 1, "invalid-time", f"output.mcap {name}",
                   f"{name} {t} ns is not a valid ROS time at {where}")
        msg = TYPESTORE.deserialize_cdr(message.data, schema.name)
        _walk_message(msg, f"output.mcap {channel.topic} #{j} ")
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


_NOTES: list[str] = []


def _note(text: str) -> None:
    """Kept for the failure report; also hypothesis.note inside a test, stderr outside one."""
    _NOTES.append(text)
    try:
        note(text)
    except InvalidArgument:
        sys.stderr.write(text + "\n")


def _rejected(rec: dict[str, Any]) -> bool:
    return "frame rejected" in (rec.get("reason") or "")


def check_replay(plan: BagPlan, directory: Path) -> None:
    """Build the bag of ``plan`` in ``directory``, replay it and check every invariant (module doc).

    Raises InvariantError for the first broken invariant (``others``: the rest); any other exception
    escaped the CLI."""
    global _COLLECTED
    built = build_bag(plan, directory)
    out = directory / "out"
    _note(f"frames: {list(zip(built.frame_class, built.frame_why, strict=True))}; image order {built.image_order}; "
          f"clean: {built.clean} ({built.why_not_clean})")
    params = None
    if built.wheel_expected is not None:
        params = directory / "wheels.yaml"
        params.write_text(f"/**:\n  ros__parameters:\n    scale_source: wheel_odometry\n"
                          f"    wheel_odometry_topic: {WHEEL_TOPIC}\n")
    rc, text, logs = run_replay_cli(built.path, out, params)
    _note(f"exit code {rc}; output:\n{text[-2000:]}")
    last_line = text.strip().splitlines()[-1] if text.strip() else ""

    # 1. No traceback, no exception in the logs.
    _fatal("Traceback" not in text, "traceback", "", f"traceback in the output:\n{text[-3000:]}")
    logged = [r for r in logs if r.exc_info or "Traceback" in r.getMessage()]
    _fatal(not logged, "exception-logged", logged[0].getMessage() if logged else "",
           f"exception logged: {logged[0].getMessage() if logged else ''}")
    # 2. Exit codes; 2 only for a bag without camera_info topic.
    _fatal(rc in (0, 2, 3), "exit-code", str(rc), f"exit code {rc}: {last_line}")
    _COLLECTED = collected = []
    try:
        if rc == 2:
            topic = re.search(r"cannot read (\S+) from bag", last_line)
            key = f"cannot read a {'camera_info' if 'camera_info' in topic.group(1) else 'image'} message" if topic \
                else last_line.split(" from bag")[0]
            _check(not built.has_info_topic, "exit-2-on-readable-bag", key,
                   f"exit 2 (replay abandoned) on a readable bag: {last_line}")
        # 3. One record per image message.
        recs = check_frames_jsonl(out, built.n_images if rc in (0, 3) else None)
        # 4. Finite outputs, unit quaternions, valid times.
        check_tum(out)
        _note(f"output.mcap messages: {check_output_mcap(out)}")
        if rc != 2:
            _check_frames(built, rc, recs, last_line)
        if rc != 2 and built.wheel_expected is not None:
            _check_wheel(built.wheel_expected, out, recs)
    finally:
        _COLLECTED = None
    if collected:
        first = collected[0]
        raise InvariantError(first.rule, first.key, first.args[0].split("] ", 1)[-1], collected[1:])


def _check_frames(built: BuiltBag, rc: int, recs: list[dict[str, Any]], last_line: str) -> None:
    """Invariants 5 to 7 (exit code 0 or 3, one record per image)."""
    # 5. A clean bag: exit 0, nothing rejected.
    if built.clean:
        rejected = [(j, r["reason"]) for j, r in enumerate(recs) if _rejected(r)]
        _check(rc == 0 and not rejected, "clean-bag-not-accepted", rejected[0][1].split(";")[0] if rejected else "",
               f"clean bag: exit {rc}, rejected frames {rejected[:3]}; {last_line}")
    # 6. Frames docs/bad_input.md says cannot be used: no pose, exit 3.
    bad = [i for i, c in enumerate(built.frame_class) if c == "bad"]
    if bad:
        why = built.frame_why[bad[0]]
        for k, i in enumerate(built.image_order):
            if built.frame_class[i] == "bad":
                _check(not recs[k]["has_pose"], "bad-frame-has-pose", built.frame_why[i],
                       f"frame {i} (record {k}) cannot be used ({built.frame_why[i]}) but has a pose: "
                       f"{recs[k]['reason']}")
        _check(rc == 3, "bad-frame-but-exit-0", why, f"frames {bad} cannot be used ({why}) but exit code {rc}")
    # 7. Records and exit code agree about rejected frames.
    said = [(j, r["reason"]) for j, r in enumerate(recs) if _rejected(r)]
    if said:
        _check(rc == 3, "rejected-record-but-exit-0", said[0][1].split(";")[0],
               f"record {said[0][0]} says {said[0][1]!r} but exit code {rc}")


def _check_wheel(expected: dict[str, int], out: Path, recs: list[dict[str, Any]]) -> None:
    """Invariant 8: the wheel stream's messages counted as the rule says, and said."""
    stats = json.loads((out / "stats.json").read_text())
    got = stats.get("wheel_odometry")
    _check(got == expected, "wheel-counts", "stats.json wheel_odometry",
           f"stats.json wheel_odometry {got} != {expected} (the arrival-order rule)")
    dropped = expected["received"] - expected["used"]
    said = [n for n in stats.get("notes", []) if n.startswith(f"wheel odometry on {WHEEL_TOPIC}: ")]
    _check(bool(said) == bool(dropped or expected["used"] < 2), "wheel-note", "",
           f"{dropped} wheel message(s) dropped, notes {stats.get('notes')}")
    for j, rec in enumerate(recs):
        counts = rec.get("wheel_messages")
        ok = isinstance(counts, dict) and set(counts) == set(expected) and counts["received"] == sum(
            v for k, v in counts.items() if k != "received") and counts["received"] <= expected["received"]
        _check(ok, "wheel-record", "wheel_messages", f"frames.jsonl line {j}: wheel_messages {counts}")


# ==================================================================================================
# Driver: survey every example, then (larger runs) shrink one example per failure class
# ==================================================================================================
@dataclasses.dataclass
class FailureClass:
    plan: BagPlan
    detail: str
    notes: list[str]
    count: int = 1
    shrunk: bool = False


def _crash_signature(exc: BaseException) -> str:
    tb = traceback.extract_tb(exc.__traceback__)
    inner = next((f for f in reversed(tb) if "/epi_vo/" in f.filename), tb[-1] if tb else None)
    where = f" in {Path(inner.filename).name}:{inner.name}" if inner is not None else ""
    return f"uncaught {type(exc).__name__}{where}: {_normalise(str(exc).splitlines()[0] if str(exc) else '')}"


def _run_one(plan: BagPlan) -> list[tuple[str, str]]:
    """(failure class, detail) of every failure of one example; empty when every invariant holds."""
    _NOTES.clear()
    with tempfile.TemporaryDirectory(prefix="epi_vo_fuzz_replay_") as tmp:
        try:
            check_replay(plan, Path(tmp))
        except InvariantError as exc:
            return [(e.signature, str(e).split("\n  and ")[0]) for e in (exc, *exc.others)]
        except Exception as exc:  # escaped the CLI (or a bug of this file: the traceback says which)
            return [(_crash_signature(exc), "".join(traceback.format_exception(exc))[-4000:])]
    return []


class _Target(Exception):  # noqa: N818 - the failure class being shrunk
    pass


@dataclasses.dataclass
class _Survey:
    target: str | None = None
    found: dict[str, FailureClass] = dataclasses.field(default_factory=dict)
    last: FailureClass | None = None


def _probe(state: _Survey, cfg: settings) -> Any:
    """The same test function (so the same derandomized examples) for the survey and for each shrink."""

    @cfg
    @given(bag_plans())
    def probe(plan: BagPlan) -> None:
        for sig, detail in _run_one(plan):
            if state.target is None:
                old = state.found.get(sig)
                if old is None or len(repr(plan)) < len(repr(old.plan)):
                    state.found[sig] = FailureClass(plan, detail, list(_NOTES), 1 + (old.count if old else 0))
                else:
                    old.count += 1
            elif sig == state.target:
                state.last = FailureClass(plan, detail, list(_NOTES), shrunk=True)
                raise _Target(sig)

    return probe


def _settings(n: int, phases: Sequence[Phase]) -> settings:
    return settings(max_examples=n, deadline=None, derandomize=True, database=None, phases=phases,
                    print_blob=False, report_multiple_bugs=False, suppress_health_check=list(HealthCheck))


def find_failure_classes(n: int, shrink: bool) -> dict[str, FailureClass]:
    """Run ``n`` generated bags; one entry per distinct failure class with its smallest example (shrunk
    by hypothesis when ``shrink``)."""
    survey = _Survey()
    _probe(survey, _settings(n, [Phase.generate]))()
    if not shrink:
        return survey.found
    for sig, found in survey.found.items():
        state = _Survey(target=sig)
        with contextlib.suppress(Exception):
            _probe(state, _settings(n, [Phase.generate, Phase.shrink]))()
        if state.last is not None:
            state.last.count = found.count
            survey.found[sig] = state.last
    return survey.found


def format_failure_classes(found: dict[str, FailureClass], n: int) -> str:
    lines = [f"{len(found)} failure class(es) in {n} generated bags. Reproduce one with:",
             "  .venv/bin/python -c 'import sys, tempfile, pathlib; sys.path.insert(0, \"test\"); "
             "from test_fuzz_replay import *; check_replay(PLAN, pathlib.Path(tempfile.mkdtemp()))'", ""]
    for k, (sig, f) in enumerate(sorted(found.items()), 1):
        lines.append(f"--- [{k}] {sig}   ({f.count} of {n} examples; {'shrunk' if f.shrunk else 'smallest seen'})")
        lines.append(f"PLAN = {f.plan!r}")
        lines.append(f.detail.strip()[-2500:])
        lines.extend(note_text.strip()[-1200:] for note_text in f.notes[:2])
        lines.append("")
    return "\n".join(lines)


# ==================================================================================================
# The test
# ==================================================================================================
def test_replay_of_generated_bags_keeps_the_invariants(pytestconfig: pytest.Config) -> None:
    requested = pytestconfig.getoption("--fuzz-examples", default=None)
    n = int(requested) if requested else DEFAULT_EXAMPLES
    found = find_failure_classes(n, shrink=bool(requested))
    if found:
        pytest.fail(format_failure_classes(found, n), pytrace=False)
