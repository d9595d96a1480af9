"""Bad input in ``epi-vo replay``: each case either continues with a per-frame reason in frames.jsonl or
exits non-zero with one clear line on stderr (never a traceback), and nothing recorded is lost.

Bags are written into tmp_path with rosbags from the real frames of bags/general_motion (640x480 JPEG,
decoded with ``epi_vo.io.msgconv.decode_frame``), so tracking is real and recovery after bad frames can be
checked.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from epi_vo.cli import main
from epi_vo.core.config import VoConfig
from epi_vo.io import bagio, outbag
from epi_vo.io.msgconv import decode_frame
from epi_vo.tools.replay import ReplaySummary, run_replay

REPO = Path(__file__).resolve().parents[2]
SOURCE_BAG = REPO / "bags" / "general_motion" / "bag"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
Image = TYPESTORE.types["sensor_msgs/msg/Image"]
CompressedImage = TYPESTORE.types["sensor_msgs/msg/CompressedImage"]
CameraInfo = TYPESTORE.types["sensor_msgs/msg/CameraInfo"]
Header = TYPESTORE.types["std_msgs/msg/Header"]
Time = TYPESTORE.types["builtin_interfaces/msg/Time"]
PERIOD_NS = 66_666_667  # the source bag's 15 Hz


@dataclasses.dataclass(frozen=True)
class Source:
    """One frame of the source bag: stamp, decoded gray image, its JPEG payload, its CameraInfo."""

    stamp_ns: int
    gray: np.ndarray
    jpeg: np.ndarray
    info: Any


@dataclasses.dataclass(frozen=True)
class Item:
    """One image to write (Image or CompressedImage message) and its camera_info (None: none written)."""

    image: Any
    info: Any | None


@pytest.fixture(scope="module")
def source() -> list[Source]:
    frames = []
    with bagio.open_camera_bag(SOURCE_BAG) as bag:
        assert bag.image_is_compressed
        for f in bag.iter_frames():
            frames.append(Source(f.stamp_ns, decode_frame(f.image_msg, True), np.asarray(f.image_msg.data).copy(),
                                 f.camera_info_msg))
    return frames


# --- message builders ------------------------------------------------------------------------------
def header(stamp_ns: int) -> Any:
    return Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="camera_optical_frame")


def raw(gray: np.ndarray, stamp_ns: int, *, encoding: str = "mono8", pad: int = 0) -> Any:
    """mono8 Image of ``gray`` with ``pad`` bytes of row padding (filled with 0xEE to be noticed)."""
    h, w = gray.shape
    rows = np.full((h, w + pad), 0xEE, np.uint8)
    rows[:, :w] = gray
    return Image(header=header(stamp_ns), height=h, width=w, encoding=encoding, is_bigendian=0, step=w + pad,
                 data=rows.ravel())


def raw_bytes(stamp_ns: int, width: int, height: int, encoding: str, bytes_per_pixel: float) -> Any:
    step = int(width * bytes_per_pixel)
    data = np.random.default_rng(stamp_ns % 2**32).integers(0, 256, step * height, dtype=np.uint8)
    return Image(header=header(stamp_ns), height=height, width=width, encoding=encoding, is_bigendian=0, step=step,
                 data=data)


def mono16_bigendian(gray: np.ndarray, stamp_ns: int) -> Any:
    """mono16 big-endian: the high byte is the gray value, the low byte noise (so byte order matters)."""
    noise = np.random.default_rng(stamp_ns % 2**32).integers(0, 256, gray.shape, dtype=np.uint16)
    samples = (gray.astype(np.uint16) << 8 | noise).astype(">u2")
    h, w = gray.shape
    return Image(header=header(stamp_ns), height=h, width=w, encoding="mono16", is_bigendian=1, step=2 * w,
                 data=np.frombuffer(samples.tobytes(), np.uint8).copy())


def compressed(payload: np.ndarray | bytes, stamp_ns: int) -> Any:
    return CompressedImage(header=header(stamp_ns), format="jpeg", data=np.frombuffer(bytes(payload), np.uint8).copy())


def jpeg_of(gray: np.ndarray, quality: int = 92) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.reshape(-1)


def info(src: Any, stamp_ns: int, **fields: Any) -> Any:
    """A copy of the CameraInfo ``src`` stamped ``stamp_ns``, with ``fields`` replaced."""
    values = {f.name: getattr(src, f.name) for f in dataclasses.fields(src)}
    values.update(header=header(stamp_ns), **fields)
    return CameraInfo(**values)


def scaled_info(src: Any, stamp_ns: int, width: int, height: int) -> Any:
    """The calibration of ``src`` for the image resized to width x height (cv2.resize pixel centres)."""
    sx, sy = width / src.width, height / src.height
    k = np.asarray(src.k, dtype=np.float64).copy()
    k[0], k[2] = k[0] * sx, (k[2] + 0.5) * sx - 0.5
    k[4], k[5] = k[4] * sy, (k[5] + 0.5) * sy - 0.5
    return info(src, stamp_ns, width=width, height=height, k=k)


def good_raw(s: Source, stamp_ns: int | None = None) -> Item:
    stamp = s.stamp_ns if stamp_ns is None else stamp_ns
    return Item(raw(s.gray, stamp), info(s.info, stamp))


def good_jpeg(s: Source, stamp_ns: int | None = None) -> Item:
    stamp = s.stamp_ns if stamp_ns is None else stamp_ns
    return Item(compressed(s.jpeg, stamp), info(s.info, stamp))


# --- bag writing and replay ------------------------------------------------------------------------
def write_bag(path: Path, items: Sequence[Item], *, image_topic: bool = True,
              damage: Mapping[tuple[str, int], Callable[[bytes], bytes]] | None = None) -> Path:
    """A rosbag2 MCAP bag: one Image or CompressedImage topic (from the first item) and camera_info.

    Messages are logged in list order (log time strictly increasing) whatever their header stamps: item i's
    camera_info at ``log_time(i)``, its image 1 ns later. ``damage[("image" | "info", i)]`` turns the CDR bytes
    of item i's message into the bytes written (a damaged message).
    """
    damage = damage or {}
    is_compressed = bool(items) and items[0].image.__msgtype__ == CompressedImage.__msgtype__
    image_type = CompressedImage if is_compressed else Image
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/camera/image_raw/compressed" if is_compressed else "/camera/image_raw",
                              image_type.__msgtype__, typestore=TYPESTORE) if image_topic else None
        cc = w.add_connection("/camera/camera_info", CameraInfo.__msgtype__, typestore=TYPESTORE)
        for i, item in enumerate(items):
            t = log_time(i)
            if item.info is not None:
                data = bytes(TYPESTORE.serialize_cdr(item.info, CameraInfo.__msgtype__))
                w.write(cc, t, damage.get(("info", i), bytes)(data))
            if ci is not None:
                data = bytes(TYPESTORE.serialize_cdr(item.image, image_type.__msgtype__))
                w.write(ci, t + 1, damage.get(("image", i), bytes)(data))
    return path


def log_time(i: int) -> int:
    """Log time (ns) of item i's camera_info in ``write_bag``."""
    return 1_000_000_000 + i * 1_000_000


def records(out: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


def replay(tmp_path: Path, items: Sequence[Item], cfg: VoConfig | None = None, name: str = "bag"
           ) -> tuple[ReplaySummary, list[dict[str, Any]], Path]:
    bag = write_bag(tmp_path / name, items)
    out = tmp_path / f"out_{name}"
    summary = run_replay(bag, out, cfg)
    recs = records(out)
    assert [r["index"] for r in recs] == list(range(len(items))), "one record per input frame"
    return summary, recs, out


def run_cli(args: Sequence[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    rc = main(["replay", *args, "--no-progress"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


def tum(out: Path) -> np.ndarray:
    return np.loadtxt(out / "trajectory.tum", ndmin=2)


def recovers(recs: list[dict[str, Any]], after: int) -> bool:
    """Tracking (with the map's scale) again at some frame after index ``after``."""
    return any(r["state"] == "tracking" and r["has_pose"] for r in recs[after + 1:])


def assert_rejected(recs: list[dict[str, Any]], idx: Sequence[int], text: str) -> None:
    for i in idx:
        r = recs[i]
        assert r["state"] == "lost" and not r["has_pose"], r
        assert "frame rejected: " in r["reason"] and text in r["reason"], r["reason"]


# ==================================================================================================
# Images
# ==================================================================================================
@pytest.mark.parametrize(("encoding", "bpp"), [("32FC1", 4), ("yuv422", 2)])
def test_unsupported_encoding_mid_stream(tmp_path: Path, source: list[Source], capsys: pytest.CaptureFixture[str],
                                         encoding: str, bpp: int) -> None:
    bad = range(10, 13)
    items = [Item(raw_bytes(s.stamp_ns, 640, 480, encoding, bpp), info(s.info, s.stamp_ns)) if i in bad
             else good_raw(s) for i, s in enumerate(source[:40])]
    bag = write_bag(tmp_path / "bag", items)
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3
    assert err.strip().count("\n") == 0 and f"unsupported image encoding '{encoding}'" in err
    assert "3 of 40 frames rejected" in err and "from frame 10" in err
    recs = records(tmp_path / "out")
    assert len(recs) == 40
    assert_rejected(recs, bad, f"unsupported image encoding '{encoding}' (supported: mono8")
    assert recovers(recs, 12)


def test_padded_step_gives_the_same_poses(tmp_path: Path, source: list[Source]) -> None:
    _, recs_a, out_a = replay(tmp_path, [good_raw(s) for s in source[:30]], name="plain")
    padded = [Item(raw(s.gray, s.stamp_ns, pad=13), info(s.info, s.stamp_ns)) for s in source[:30]]
    _, recs_b, out_b = replay(tmp_path, padded, name="padded")
    assert sum(r["state"] == "tracking" for r in recs_b) >= 20
    np.testing.assert_array_equal(tum(out_a), tum(out_b))
    assert [r["reason"] for r in recs_a] == [r["reason"] for r in recs_b]


def test_big_endian_mono16_works(tmp_path: Path, source: list[Source]) -> None:
    _, _, out_a = replay(tmp_path, [good_raw(s) for s in source[:30]], name="mono8")
    items = [Item(mono16_bigendian(s.gray, s.stamp_ns), info(s.info, s.stamp_ns)) for s in source[:30]]
    summary, recs, out_b = replay(tmp_path, items, name="mono16be")
    assert not summary.rejected and sum(r["state"] == "tracking" for r in recs) >= 20
    np.testing.assert_array_equal(tum(out_a), tum(out_b))  # the high byte is the mono8 image


def test_image_size_different_from_camera_info(tmp_path: Path, source: list[Source],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    items = [Item(raw(cv2.resize(s.gray, (320, 240)), s.stamp_ns), info(s.info, s.stamp_ns)) for s in source[:5]]
    rc, err = run_cli([str(write_bag(tmp_path / "bag", items)), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3 and "5 of 5 frames rejected" in err
    assert_rejected(records(tmp_path / "out"), range(5), "image size 320x240 does not match camera_info size 640x480")


def test_image_size_changing_mid_stream(tmp_path: Path, source: list[Source]) -> None:
    """From frame 15 the camera sends 320x240 with the old camera_info: rejected; back to 640x480: tracking."""
    small = range(15, 20)
    items = [Item(raw(cv2.resize(s.gray, (320, 240), interpolation=cv2.INTER_AREA), s.stamp_ns),
                  info(s.info, s.stamp_ns)) if i in small else good_raw(s) for i, s in enumerate(source[:45])]
    summary, recs, _ = replay(tmp_path, items)
    assert_rejected(recs, small, "image size 320x240 does not match camera_info size 640x480")
    assert all(r["has_pose"] for r in recs[:15])
    assert recovers(recs, 19)
    assert len(summary.rejected) == 1 and summary.rejected[0].startswith("5 frame(s) from frame 15")


def test_image_and_camera_info_size_changing_together(tmp_path: Path, source: list[Source]) -> None:
    """A consistent resolution change (image and camera_info): tracking restarts, nothing rejected."""
    items = [Item(raw(cv2.resize(s.gray, (320, 240), interpolation=cv2.INTER_AREA), s.stamp_ns),
                  scaled_info(s.info, s.stamp_ns, 320, 240)) if i >= 15 else good_raw(s)
             for i, s in enumerate(source[:45])]
    summary, recs, _ = replay(tmp_path, items)
    assert not summary.rejected
    assert "camera_info changed: tracking restarted" in recs[15]["reason"]
    assert recs[15]["position"] == recs[14]["position"]  # continues from the held pose
    assert recovers(recs, 15)


# ==================================================================================================
# Calibration
# ==================================================================================================
def _bad_info_case(name: str, src: Any, stamp: int) -> Any:
    k = np.asarray(src.k, dtype=np.float64).copy()
    d = np.asarray(src.d, dtype=np.float64).copy()
    if name == "uncalibrated":
        return info(src, stamp, k=np.zeros(9))
    if name == "nan_k":
        k[2] = math.nan
        return info(src, stamp, k=k)
    if name == "inf_k":
        k[0] = math.inf
        return info(src, stamp, k=k)
    if name == "nan_d":
        d[1] = math.nan
        return info(src, stamp, d=d)
    if name == "inf_d":
        d[0] = -math.inf
        return info(src, stamp, d=d)
    if name == "unknown_model":
        return info(src, stamp, distortion_model="kannala_brandt")
    if name == "d_length":
        return info(src, stamp, d=d[:3])
    raise AssertionError(name)


BAD_INFO = {
    "uncalibrated": "camera is uncalibrated: camera_info K[0] (fx) is 0",
    "nan_k": "camera_info K is not finite",
    "inf_k": "camera_info K is not finite",
    "nan_d": "camera_info D is not finite",
    "inf_d": "camera_info D is not finite",
    "unknown_model": "unknown distortion model 'kannala_brandt' (supported: plumb_bob, rational_polynomial, "
                     "equidistant)",
    "d_length": "distortion model 'plumb_bob' needs 4 or 5 coefficients, camera_info D has 3",
}


@pytest.mark.parametrize("case", sorted(BAD_INFO))
def test_bad_calibration_mid_stream(tmp_path: Path, source: list[Source], capsys: pytest.CaptureFixture[str],
                                    case: str) -> None:
    bad = range(10, 14)
    items = [Item(raw(s.gray, s.stamp_ns), _bad_info_case(case, s.info, s.stamp_ns)) if i in bad else good_raw(s)
             for i, s in enumerate(source[:40])]
    rc, err = run_cli([str(write_bag(tmp_path / "bag", items)), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3 and err.count("\n") == 1
    assert "4 of 40 frames rejected" in err and BAD_INFO[case] in err
    recs = records(tmp_path / "out")
    assert_rejected(recs, bad, BAD_INFO[case])
    # Frames without a pose hold the last pose; the 3rd in a row restarts tracking from it.
    assert all(r["position"] == recs[9]["position"] for r in recs[10:15])
    assert "re-initializing from the last pose" in recs[12]["reason"]
    assert recovers(recs, 13)


def test_whole_bag_uncalibrated(tmp_path: Path, source: list[Source], capsys: pytest.CaptureFixture[str]) -> None:
    items = [Item(raw(s.gray, s.stamp_ns), _bad_info_case("uncalibrated", s.info, s.stamp_ns)) for s in source[:4]]
    rc, err = run_cli([str(write_bag(tmp_path / "bag", items)), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3 and "4 of 4 frames rejected" in err and "uncalibrated" in err


def test_camera_info_never_arriving(tmp_path: Path, source: list[Source], capsys: pytest.CaptureFixture[str]) -> None:
    """Images but an empty camera_info topic: every frame rejected with the reason, rc 3."""
    items = [Item(raw(s.gray, s.stamp_ns), None) for s in source[:5]]
    rc, err = run_cli([str(write_bag(tmp_path / "bag", items)), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3 and "5 of 5 frames rejected" in err and "no camera_info on /camera/camera_info" in err
    assert_rejected(records(tmp_path / "out"), range(5), "no camera_info on /camera/camera_info")


def test_camera_info_changing_mid_stream(tmp_path: Path, source: list[Source]) -> None:
    """A new calibration from frame 20 on (principal point and distortion change): tracking restarts at
    frame 20 with the reason, from the held pose (no jump), and tracks again."""
    def changed(s: Source) -> Any:
        k = np.asarray(s.info.k, dtype=np.float64).copy()
        k[2] += 1.5
        return info(s.info, s.stamp_ns, k=k, d=np.asarray(s.info.d) * 1.01)

    items = [Item(raw(s.gray, s.stamp_ns), changed(s)) if i >= 20 else good_raw(s) for i, s in enumerate(source)]
    summary, recs, _ = replay(tmp_path, items)
    assert not summary.rejected
    assert "camera_info changed: tracking restarted" in recs[20]["reason"]
    assert recs[20]["is_keyframe"] and recs[20]["has_pose"]
    assert recs[20]["position"] == recs[19]["position"]
    assert recs[20]["quat_xyzw"] == recs[19]["quat_xyzw"]
    assert not any("camera_info changed" in r["reason"] for r in recs[21:])  # once, not every frame
    assert recovers(recs, 20)
    # The restarted trajectory continues in the old units (no jump): steps after stay like steps before.
    pos = np.array([r["position"] for r in recs])
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert steps[20:].max() < 5 * np.median(steps[1:19]) + 1e-9


# ==================================================================================================
# Time
# ==================================================================================================
def test_equal_stamp_is_skipped(tmp_path: Path, source: list[Source]) -> None:
    items = [good_raw(s) for s in source[:20]]
    items.insert(11, good_raw(source[11], source[10].stamp_ns))  # frame 11's image with frame 10's stamp
    summary, recs, out = replay(tmp_path, items)
    r = recs[11]
    assert r["skipped"] and not r["has_pose"] and r["reason"] == "duplicate image stamp: frame skipped"
    assert not any(x["skipped"] for x in recs[:11] + recs[12:])
    assert recs[12]["state"] == "tracking"  # the skip did not disturb tracking
    assert tum(out).shape[0] == summary.frames_with_pose == sum(x["has_pose"] for x in recs)


def test_backwards_stamp_restarts_from_the_held_pose(tmp_path: Path, source: list[Source]) -> None:
    """At frame 20 the clock jumps 5 s back (and runs on from there): tracking restarts at the held pose."""
    jump = 5 * 10**9
    items = [good_raw(s, s.stamp_ns - (jump if i >= 20 else 0)) for i, s in enumerate(source)]
    summary, recs, _ = replay(tmp_path, items)
    assert not summary.rejected
    r = recs[20]
    assert r["reason"].startswith("time jumped backwards by 4.933 s: tracking restarted from the last pose"), r
    assert r["has_pose"] and r["is_keyframe"] and r["position"] == recs[19]["position"]
    assert not any("backwards" in x["reason"] for x in recs[21:])
    assert recovers(recs, 20)


def test_large_gap(tmp_path: Path, source: list[Source]) -> None:
    """Ten frames missing (0.73 s): the pose still comes out, or a reason says why not, then tracking."""
    items = [good_raw(s) for i, s in enumerate(source) if not 20 <= i < 30]
    _, recs, _ = replay(tmp_path, items)
    after = recs[20:]
    for r in after:
        assert r["state"] == "tracking" or r["reason"], r
    assert recovers(recs, 20)
    pos = np.array([r["position"] for r in recs])
    assert np.all(np.isfinite(pos))


# ==================================================================================================
# Image content
# ==================================================================================================
@pytest.mark.parametrize("kind", ["black", "saturated", "textureless", "blurred"])
def test_degenerate_frames_are_lost_with_a_reason_then_recover(tmp_path: Path, source: list[Source],
                                                               kind: str) -> None:
    bad = range(15, 20)

    def spoil(g: np.ndarray) -> np.ndarray:
        if kind == "black":
            return np.zeros_like(g)
        if kind == "saturated":
            return np.full_like(g, 255)
        if kind == "textureless":  # a smooth gradient: no corner anywhere
            return np.tile(np.linspace(60, 200, g.shape[1]).astype(np.uint8), (g.shape[0], 1))
        return cv2.GaussianBlur(g, (0, 0), 25)

    items = [Item(raw(spoil(s.gray), s.stamp_ns), info(s.info, s.stamp_ns)) if i in bad else good_raw(s)
             for i, s in enumerate(source)]
    summary, recs, _ = replay(tmp_path, items)
    assert not summary.rejected  # bad content is not bad input: the geometry says what happened
    for r in recs[15:20]:
        assert r["state"] != "tracking" or r["reason"], r
    lost = [r for r in recs[15:21] if r["state"] == "lost"]
    assert lost, [r["state"] for r in recs[15:21]]
    assert all(r["reason"] for r in lost)
    assert any("too few tracked features" in r["reason"] or "tracking lost" in r["reason"] for r in lost)
    assert recovers(recs, 19)
    for r in recs:
        assert all(math.isfinite(v) for v in r["position"] + r["quat_xyzw"])


# ==================================================================================================
# 4K
# ==================================================================================================
@pytest.fixture(scope="module")
def bag_4k(tmp_path_factory: pytest.TempPathFactory, source: list[Source]) -> Path:
    items = []
    for s in source[:12]:
        big = cv2.resize(s.gray, (3840, 2160), interpolation=cv2.INTER_CUBIC)
        items.append(Item(compressed(jpeg_of(big), s.stamp_ns), scaled_info(s.info, s.stamp_ns, 3840, 2160)))
    return write_bag(tmp_path_factory.mktemp("4k") / "bag", items)


def test_4k_frames_downscaled_by_max_image_width(tmp_path: Path, bag_4k: Path) -> None:
    widths: list[float] = []
    summary = run_replay(bag_4k, tmp_path / "out", VoConfig(max_image_width=1280),
                         on_result=lambda r: widths.append(float(r.matches.pts_cur[:, 0].max(initial=0.0))))
    recs = records(tmp_path / "out")
    assert summary.frames == 12 and not summary.rejected
    assert sum(r["has_pose"] for r in recs) >= 10 and recs[-1]["state"] == "tracking"
    assert max(widths) < 1280  # features live in the downscaled image: memory and time bounded by it


def test_4k_frames_without_downscaling_still_work(tmp_path: Path, bag_4k: Path) -> None:
    summary = run_replay(bag_4k, tmp_path / "out", VoConfig())
    recs = records(tmp_path / "out")
    assert summary.frames == 12 and not summary.rejected
    assert sum(r["has_pose"] for r in recs) >= 10


# ==================================================================================================
# Bags
# ==================================================================================================
def test_corrupt_compressed_image(tmp_path: Path, source: list[Source], capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(7)
    bad = {8: rng.integers(0, 256, 5000, dtype=np.uint8), 9: np.zeros(0, np.uint8),
           10: source[10].jpeg[: len(source[10].jpeg) // 20]}  # random bytes, empty, truncated to 5 %
    items = [Item(compressed(bad[i], s.stamp_ns), info(s.info, s.stamp_ns)) if i in bad else good_jpeg(s)
             for i, s in enumerate(source[:35])]
    rc, err = run_cli([str(write_bag(tmp_path / "bag", items)), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3 and err.count("\n") == 1 and "could not decode CompressedImage" in err
    recs = records(tmp_path / "out")
    assert len(recs) == 35
    assert_rejected(recs, [8, 9], "could not decode CompressedImage (format 'jpeg'")
    # A truncated JPEG may decode partially (libjpeg fills the rest); it must at least not crash anything.
    assert recs[10]["state"] == "lost" or recs[10]["has_pose"]
    assert recovers(recs, 10)


def _assert_one_line_error(rc: int, err: str, *texts: str) -> None:
    assert rc == 2, err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("epi-vo: error: "), err
    for t in texts:
        assert t in lines[0], err


def test_empty_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_bag(tmp_path / "empty", [])
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    _assert_one_line_error(rc, err, "is empty (no messages)")


def test_bag_with_topics_but_no_images(tmp_path: Path, source: list[Source],
                                       capsys: pytest.CaptureFixture[str]) -> None:
    """The image connection exists but holds no message."""
    path = tmp_path / "no_images"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection("/camera/image_raw", Image.__msgtype__, typestore=TYPESTORE)
        cc = w.add_connection("/camera/camera_info", CameraInfo.__msgtype__, typestore=TYPESTORE)
        w.write(cc, 1, TYPESTORE.serialize_cdr(info(source[0].info, 1), CameraInfo.__msgtype__))
    rc, err = run_cli([str(path), "-o", str(tmp_path / "out")], capsys)
    _assert_one_line_error(rc, err, "image topic /camera/image_raw", "has no messages")


def test_bag_without_an_image_topic(tmp_path: Path, source: list[Source], capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_bag(tmp_path / "no_image_topic", [good_raw(s) for s in source[:3]], image_topic=False)
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    _assert_one_line_error(rc, err, "bag has no sensor_msgs/Image or CompressedImage topic",
                           "/camera/camera_info (sensor_msgs/msg/CameraInfo)")


@pytest.mark.parametrize("keep", [0.5, 0.97])
def test_truncated_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str], keep: float) -> None:
    data = (SOURCE_BAG / "bag.mcap").read_bytes()
    path = tmp_path / "truncated.mcap"
    path.write_bytes(data[: int(len(data) * keep)])
    rc, err = run_cli([str(path), "-o", str(tmp_path / "out")], capsys)
    _assert_one_line_error(rc, err, str(path))


# ==================================================================================================
# Nothing lost
# ==================================================================================================
def test_nothing_lost_with_injected_bad_frames(tmp_path: Path, source: list[Source]) -> None:
    """Corrupt JPEG, wrong size, NaN K and a duplicate stamp among good frames: every input frame has its
    record and its diagnostics status, every frame with a pose its trajectory line, every frame not
    skipped its odometry; all outputs read back; tracking resumes after the bad frames."""
    s = source
    items: list[Item] = [good_jpeg(x) for x in s[:10]]
    items.append(Item(compressed(np.random.default_rng(1).integers(0, 256, 3000, dtype=np.uint8), s[10].stamp_ns),
                      info(s[10].info, s[10].stamp_ns)))  # corrupt jpeg
    items += [good_jpeg(x) for x in s[11:16]]
    items.append(Item(compressed(jpeg_of(cv2.resize(s[16].gray, (320, 240))), s[16].stamp_ns),
                      info(s[16].info, s[16].stamp_ns)))  # wrong size
    items += [good_jpeg(x) for x in s[17:22]]
    k = np.asarray(s[22].info.k, dtype=np.float64).copy()
    k[4] = math.nan
    items.append(Item(compressed(s[22].jpeg, s[22].stamp_ns), info(s[22].info, s[22].stamp_ns, k=k)))  # NaN K
    items += [good_jpeg(x) for x in s[23:28]]
    items.append(good_jpeg(s[28], s[27].stamp_ns))  # duplicate stamp
    items += [good_jpeg(x) for x in s[29:]]
    n = len(items)
    bag = write_bag(tmp_path / "bag", items)
    summary = run_replay(bag, tmp_path / "out")
    out = tmp_path / "out"

    recs = records(out)
    assert [r["index"] for r in recs] == list(range(n))
    bad = {10: "could not decode CompressedImage", 16: "image size 320x240 does not match",
           22: "camera_info K is not finite"}
    for i, text in bad.items():
        assert_rejected(recs, [i], text)
    assert recs[28]["skipped"] and "duplicate image stamp" in recs[28]["reason"]
    for i in (*bad, 28):
        assert recovers(recs, i)
    assert recs[-1]["state"] == "tracking"
    assert summary.frames == n and len(summary.rejected) == 3

    stamps_pose = [r["stamp_ns"] for r in recs if r["has_pose"]]
    traj = tum(out)
    assert traj.shape == (len(stamps_pose), 8)
    np.testing.assert_allclose(traj[:, 0], np.array(stamps_pose) * 1e-9, atol=1e-9)
    assert np.all(np.isfinite(traj)) and np.allclose(np.linalg.norm(traj[:, 4:], axis=1), 1.0, atol=1e-6)

    diag_stamps, odom_stamps = [], []
    with AnyReader([out / "output.mcap"], default_typestore=TYPESTORE) as reader:
        for con, _, rawdata in reader.messages():
            msg = reader.deserialize(rawdata, con.msgtype)
            head = msg.transforms[0].header if con.topic == "/tf" else msg.header  # TFMessage: per transform
            stamp = head.stamp.sec * 10**9 + head.stamp.nanosec
            if con.topic == "/vo/frame_status":
                (status,) = msg.status
                diag_stamps.append(stamp)
                assert status.message
            elif con.topic == "/vo/odometry":
                odom_stamps.append(stamp)
                cov = np.asarray(msg.pose.covariance).reshape(6, 6)
                assert np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0)
    assert diag_stamps == [r["stamp_ns"] for r in recs]
    assert odom_stamps == [r["stamp_ns"] for r in recs if not r["skipped"]]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames"] == n


# ==================================================================================================
# SIGINT / SIGTERM during replay
# ==================================================================================================
@pytest.fixture(scope="module")
def long_bag(tmp_path_factory: pytest.TempPathFactory, source: list[Source]) -> Path:
    """~300 frames: the source played forward, backward, forward, ... with increasing stamps."""
    order = [*range(len(source)), *range(len(source) - 2, 0, -1)]
    items = []
    t0 = source[0].stamp_ns
    for i in range(300):
        s = source[order[i % len(order)]]
        items.append(good_jpeg(s, t0 + i * PERIOD_NS))
    return write_bag(tmp_path_factory.mktemp("long") / "bag", items)


def _count_lines(path: Path) -> int:
    try:
        return path.read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def _default_sigint() -> None:
    """In the child: SIGINT and SIGHUP handled as usual even when pytest runs as a background job (which ignores
    SIGINT) or under nohup (which ignores SIGHUP)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def _interrupt_replay(bag: Path, out: Path, sig: int, *, progress: bool = False, close_stderr: bool = False
                      ) -> subprocess.CompletedProcess[str]:
    """Replay ``bag`` in a child, send ``sig`` after 20 frames. ``close_stderr``: the reading end of the child's
    stderr (where the progress bar goes) is closed first, as when the terminal went away."""
    args = [sys.executable, "-m", "epi_vo.cli", "replay", str(bag), "-o", str(out), *([] if progress else
                                                                                     ["--no-progress"])]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, preexec_fn=_default_sigint)
    try:
        deadline = time.monotonic() + 60.0
        while _count_lines(out / "frames.jsonl") < 20:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "replay did not start"
            time.sleep(0.01)
        if close_stderr:
            assert proc.stderr is not None
            proc.stderr.close()
            proc.stderr = None
            # Let the bar write into the closed pipe before the signal: wait for a few more frames.
            seen = _count_lines(out / "frames.jsonl")
            while _count_lines(out / "frames.jsonl") < seen + 3 and proc.poll() is None:
                assert time.monotonic() < deadline + 60.0, "replay stalled after stderr was closed"
                time.sleep(0.01)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 130), (signal.SIGHUP, 129)],
                         ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_signal_during_replay_finalises_the_outputs(tmp_path: Path, long_bag: Path, sig: int, code: int) -> None:
    out = tmp_path / "out"
    done = _interrupt_replay(long_bag, out, sig)
    assert done.returncode == code, (done.returncode, done.stderr)
    assert "Traceback" not in done.stderr and "interrupted" in done.stderr
    _assert_consistent_outputs(out)


def test_sighup_with_the_terminal_gone_finalises_the_outputs(tmp_path: Path, long_bag: Path) -> None:
    """Terminal closed: the progress bar's stderr is gone (writes fail), then SIGHUP arrives. The replay still
    stops at a frame boundary with readable outputs and exit status 129."""
    out = tmp_path / "out"
    done = _interrupt_replay(long_bag, out, signal.SIGHUP, progress=True, close_stderr=True)
    assert done.returncode == 129, done.returncode
    _assert_consistent_outputs(out)


def _assert_consistent_outputs(out: Path) -> None:
    lines = (out / "frames.jsonl").read_text().splitlines()
    recs = [json.loads(line) for line in lines]  # every line parses: none half written
    assert 20 <= len(recs) < 300, "interrupted mid-run"
    assert [r["index"] for r in recs] == list(range(len(recs)))
    counts = {"/vo/frame_status": 0, "/vo/odometry": 0}
    with AnyReader([out / "output.mcap"], default_typestore=TYPESTORE) as reader:  # finalised: summary + index
        for con, _, rawdata in reader.messages():
            reader.deserialize(rawdata, con.msgtype)
            counts[con.topic] = counts.get(con.topic, 0) + 1
    # The replay stops between frames: every output agrees on the frames written.
    assert counts["/vo/frame_status"] == counts["/vo/odometry"] == len(recs), (counts, len(recs))
    assert tum(out).shape[0] == sum(r["has_pose"] for r in recs)


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGHUP, 129)], ids=["SIGINT", "SIGHUP"])
def test_interrupt_between_a_frames_writes_leaves_consistent_outputs(tmp_path: Path, source: list[Source],
                                                                     monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str],
                                                                     sig: int, code: int) -> None:
    """The signal arrives while frame 12's status is being written (deterministically, unlike the test above):
    the replay still stops at a frame boundary, so all outputs agree."""
    bag = write_bag(tmp_path / "bag", [good_jpeg(s) for s in source[:30]])
    original = outbag.OutputBag.write_diagnostics
    calls = {"n": 0}

    def write_diagnostics(self: outbag.OutputBag, stamp_ns: int, statuses: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 13:
            os.kill(os.getpid(), sig)  # without the replay's handler: KeyboardInterrupt / process ended
        original(self, stamp_ns, statuses)

    monkeypatch.setattr(outbag.OutputBag, "write_diagnostics", write_diagnostics)
    try:
        rc = main(["replay", str(bag), "-o", str(tmp_path / "out"), "--no-progress"])
    except KeyboardInterrupt:  # never let it reach pytest (it would end the session)
        rc = -1
    assert rc == code and "interrupted" in capsys.readouterr().err
    recs = records(tmp_path / "out")
    counts = {"/vo/frame_status": 0, "/vo/odometry": 0}
    with AnyReader([tmp_path / "out" / "output.mcap"], default_typestore=TYPESTORE) as reader:
        for con, _, _ in reader.messages():
            counts[con.topic] = counts.get(con.topic, 0) + 1
    assert counts["/vo/frame_status"] == counts["/vo/odometry"] == len(recs)
    assert tum(tmp_path / "out").shape[0] == sum(r["has_pose"] for r in recs)


def _damaged_mcap(tmp_path: Path, how: str) -> Path:
    """The source bag's MCAP with one image record of the middle chunk damaged (``opcode``: its opcode byte
    zeroed; ``length``: its length field absurd)."""
    import struct

    from mcap.reader import make_reader

    data = bytearray((SOURCE_BAG / "bag.mcap").read_bytes())
    with (SOURCE_BAG / "bag.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    image_channel = next(c.id for c in summary.channels.values() if c.topic.endswith("compressed"))
    chunk = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    assert chunk.compression == ""  # records are walked in place
    o = chunk.chunk_start_offset
    (comp_len,) = struct.unpack_from("<I", data, o + 37)
    (records_len,) = struct.unpack_from("<Q", data, o + 41 + comp_len)
    p = start = o + 41 + comp_len + 8
    images = []
    while p < start + records_len:  # records: opcode (1), length (8), body; Message body starts with channel id
        (length,) = struct.unpack_from("<Q", data, p + 1)
        if data[p] == 0x05 and struct.unpack_from("<H", data, p + 9)[0] == image_channel:
            images.append(p)
        p += 9 + length
    target = images[1]
    if how == "opcode":
        data[target] = 0
    else:
        data[target + 1: target + 9] = struct.pack("<Q", 2**40)
    path = tmp_path / f"damaged_{how}.mcap"
    path.write_bytes(bytes(data))
    return path


def test_damaged_record_mid_bag_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A record with an absurd length in the middle of the bag: one clear line naming the bag and the problem.

    (The chunk also holds camera_info messages, which are all read when the bag is opened, so the replay
    stops before the first frame.)
    """
    bag = _damaged_mcap(tmp_path, "length")
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    _assert_one_line_error(rc, err, f"from bag {bag}: Truncated record at offset")
    assert err.startswith("epi-vo: error: cannot read /camera/")


def test_silently_skipped_record_is_reported(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _damaged_mcap(tmp_path, "opcode")
    with bagio.open_camera_bag(bag) as b:
        assert b.frame_count == 52
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    n = len(records(tmp_path / "out"))
    assert n == 52 or (rc != 0 and "52" in err), (n, rc, err)


# ==================================================================================================
# Stamps that are no ROS time; every stamp written is one
# ==================================================================================================
MAX_STAMP_NS = (2**31 - 1) * 10**9 + 999_999_999


def with_stamp(item: Item, sec: int, nanosec: int) -> Item:
    """``item`` whose image header says (sec, nanosec), whatever they are (the bag stores int32 / uint32)."""
    item.image.header.stamp = Time(sec=sec, nanosec=nanosec)
    return item


def _valid_ros_time(sec: int, nanosec: int) -> bool:
    return 0 <= sec <= 2**31 - 1 and 0 <= nanosec < 10**9


def assert_every_written_stamp_is_a_ros_time(out: Path) -> dict[str, list[int]]:
    """Log / publish times and header stamps (also of Path poses) in output.mcap, trajectory.tum stamps (as
    written, digit by digit) and frames.jsonl stamps are valid ROS times. Returns topic -> header stamps (ns)."""
    from mcap.reader import make_reader

    with (out / "output.mcap").open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            for t in (message.log_time, message.publish_time):
                assert 0 <= t <= MAX_STAMP_NS, (channel.topic, t)
    stamps: dict[str, list[int]] = {}
    with AnyReader([out / "output.mcap"], default_typestore=TYPESTORE) as reader:
        for con, log_time_ns, rawdata in reader.messages():
            msg = reader.deserialize(rawdata, con.msgtype)
            # a TFMessage (/tf) has no header of its own: each of its transforms has one
            inner = [*getattr(msg, "poses", []), *getattr(msg, "transforms", [])]
            heads = ([] if con.topic == "/tf" else [msg.header.stamp]) + [p.header.stamp for p in inner]
            for st in heads:
                assert _valid_ros_time(st.sec, st.nanosec), (con.topic, st)
            assert heads[0].sec * 10**9 + heads[0].nanosec == log_time_ns
            stamps.setdefault(con.topic, []).append(log_time_ns)
    for line in (out / "trajectory.tum").read_text().splitlines():
        sec, frac = line.split()[0].split(".")
        assert len(frac) == 9 and _valid_ros_time(int(sec), int(frac)), line
    for r in records(out):
        assert 0 <= r["stamp_ns"] <= MAX_STAMP_NS and 0.0 <= r["stamp"] < 2.0**31, r
    return stamps


def test_header_stamps_that_are_no_ros_time_are_rejected_frames(tmp_path: Path, source: list[Source],
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A negative stamp, a nanosec >= 1e9 (also at the int32 seconds limit, where it used to end the run with a
    struct.error) and the largest uint32 nanosec: each frame is rejected with the reason, recorded under a valid
    stamp, and neither ends the replay nor disturbs the frames around it (no backwards jump, no restart)."""
    n = 30
    items = [good_jpeg(s) for s in source[:n]]
    sec_16 = source[16].stamp_ns // 10**9
    bad = {8: (-3, 5), 12: (2**31 - 1, 1_500_000_000), 16: (sec_16, 1_200_000_000), 20: (1000, 2**32 - 1)}
    for i, (sec, nanosec) in bad.items():
        with_stamp(items[i], sec, nanosec)
    bag = write_bag(tmp_path / "bag", items)
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3, err
    assert err.count("\n") == 1 and err.startswith(
        f"epi-vo: error: 4 of {n} frames rejected: 1 frame(s) from frame 8: image header stamp sec -3 nanosec 5 is "
        "not a valid ROS time (sec 0..2147483647, nanosec 0..999999999) (and 3 other problem(s))"), err
    recs = records(tmp_path / "out")
    assert [r["index"] for r in recs] == list(range(n))
    filed = {8: 0, 12: MAX_STAMP_NS, 16: sec_16 * 10**9 + 1_200_000_000, 20: 1000 * 10**9 + 2**32 - 1}
    for i, (sec, nanosec) in bad.items():
        r = recs[i]
        assert r["skipped"] and r["state"] == "lost" and not r["has_pose"], r
        assert r["reason"] == (f"frame rejected: image header stamp sec {sec} nanosec {nanosec} is not a valid ROS "
                               "time (sec 0..2147483647, nanosec 0..999999999); frame skipped (recorded at "
                               f"{filed[i]} ns, its header stamp clamped to a ROS time)")
        assert r["stamp_ns"] == filed[i]
        assert recs[i + 1]["state"] == "tracking" and recs[i + 1]["has_pose"], recs[i + 1]
    good = [r for i, r in enumerate(recs) if i not in bad]
    assert [r["stamp_ns"] for r in good] == [s.stamp_ns for i, s in enumerate(source[:n]) if i not in bad]
    assert not any("backwards" in r["reason"] or "restart" in r["reason"] for r in recs)
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["frames"] == n and stats["rejected_frames"] == 4
    stamps = assert_every_written_stamp_is_a_ros_time(tmp_path / "out")
    # (read back in log-time order) every frame has its status; a rejected stamp gets no odometry
    assert stamps["/vo/frame_status"] == sorted(r["stamp_ns"] for r in recs)
    assert stamps["/vo/odometry"] == sorted(r["stamp_ns"] for r in good)


def test_the_largest_ros_time_is_written_exactly(tmp_path: Path, source: list[Source],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A valid stamp at the int32 limit (2147483647.999999999 s) is a frame like any other; every output carries
    it exactly (a float formatting would round it to 2**31 s, which is no ROS time)."""
    items = [good_jpeg(s) for s in source[:12]]
    with_stamp(items[-1], 2**31 - 1, 999_999_999)
    rc, err = run_cli([str(write_bag(tmp_path / "bag", items)), "-o", str(tmp_path / "out")], capsys)
    assert rc == 0, err
    recs = records(tmp_path / "out")
    assert len(recs) == 12 and recs[-1]["stamp_ns"] == MAX_STAMP_NS and not recs[-1]["skipped"]
    assert recs[-1]["stamp"] < 2.0**31 and "frame rejected" not in recs[-1]["reason"]
    stamps = assert_every_written_stamp_is_a_ros_time(tmp_path / "out")
    assert stamps["/vo/odometry"][-1] == stamps["/vo/frame_status"][-1] == MAX_STAMP_NS
    if recs[-1]["has_pose"]:
        assert (tmp_path / "out" / "trajectory.tum").read_text().splitlines()[-1].startswith("2147483647.999999999 ")


# ==================================================================================================
# Messages whose CDR bytes are damaged
# ==================================================================================================
def truncated(n: int) -> Callable[[bytes], bytes]:
    return lambda data: data[:n]


def absurd_data_length(data: bytes) -> bytes:
    """The CompressedImage's data length word (the last uint32 before the payload) set to 2**31 - 1."""
    import struct

    for at in range(4, len(data) - 4):
        (value,) = struct.unpack_from("<I", data, at)
        if value == len(data) - at - 4:  # the sequence length: everything after it is the payload
            return data[:at] + struct.pack("<I", 2**31 - 1) + data[at + 4:]
    raise AssertionError("no data length word found")


def test_damaged_image_messages_are_rejected_frames(tmp_path: Path, source: list[Source],
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Three images whose CDR cannot be decoded (cut after the header, cut to 3 bytes, an absurd length word):
    each is a rejected frame recorded under its log time, and the replay reads every later frame."""
    n = 30
    items = [good_jpeg(s) for s in source[:n]]
    damage = {("image", 7): truncated(40), ("image", 13): truncated(3), ("image", 19): absurd_data_length}
    bag = write_bag(tmp_path / "bag", items, damage=damage)
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3, err
    assert err.count("\n") == 1 and err.startswith(f"epi-vo: error: 3 of {n} frames rejected: 1 frame(s) from frame "
                                                   "7: image message cannot be decoded: its 40 bytes of CDR are no "
                                                   "valid sensor_msgs/msg/CompressedImage ("), err
    recs = records(tmp_path / "out")
    assert [r["index"] for r in recs] == list(range(n))
    for i in (7, 13, 19):
        r = recs[i]
        assert r["skipped"] and r["state"] == "lost" and not r["has_pose"], r
        assert r["reason"].startswith("frame rejected: image message cannot be decoded: its "), r["reason"]
        assert r["reason"].endswith(f"frame skipped (recorded at {log_time(i) + 1} ns, its log time)"), r["reason"]
        assert r["stamp_ns"] == log_time(i) + 1
        assert recs[i + 1]["state"] == "tracking", recs[i + 1]  # the frames around it are not disturbed
    assert not any("backwards" in r["reason"] for r in recs)
    assert recs[-1]["state"] == "tracking"
    stamps = assert_every_written_stamp_is_a_ros_time(tmp_path / "out")
    assert len(stamps["/vo/frame_status"]) == n and len(stamps["/vo/odometry"]) == n - 3
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["frames"] == n and stats["rejected_frames"] == 3 and stats["skipped_messages"] == []


def test_damaged_camera_info_is_skipped_with_a_reason(tmp_path: Path, source: list[Source],
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Two camera_info messages that cannot be decoded: skipped and named; their images use the latest
    calibration before them, every frame is processed, and the run exits 3 saying what was skipped."""
    n = 30
    items = [good_jpeg(s) for s in source[:n]]
    bag = write_bag(tmp_path / "bag", items, damage={("info", 5): truncated(30), ("info", 6): truncated(2)})
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3
    assert err.count("\n") == 1 and err.startswith(
        f"epi-vo: error: 2 message(s) skipped: camera_info message at log time {log_time(5)} ns skipped: it cannot "
        "be decoded: its 30 bytes of CDR are no valid sensor_msgs/msg/CameraInfo ("), err
    assert "frames rejected" not in err
    recs = records(tmp_path / "out")
    assert len(recs) == n and not any("frame rejected" in r["reason"] for r in recs)
    assert all(r["has_pose"] for r in recs)
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["rejected_frames"] == 0 and len(stats["skipped_messages"]) == 2
    assert stats["skipped_messages"][1].startswith(f"camera_info message at log time {log_time(6)} ns skipped: it "
                                                   "cannot be decoded: its 2 bytes of CDR")


def test_every_camera_info_damaged(tmp_path: Path, source: list[Source], capsys: pytest.CaptureFixture[str]) -> None:
    items = [good_jpeg(s) for s in source[:5]]
    bag = write_bag(tmp_path / "bag", items, damage={("info", i): truncated(10) for i in range(5)})
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3 and err.count("\n") == 1
    assert err.startswith("epi-vo: error: 5 of 5 frames rejected: 5 frame(s) from frame 0: no usable camera_info on "
                          "/camera/camera_info (5 message(s) could not be decoded); 5 message(s) skipped: "), err
    assert_rejected(records(tmp_path / "out"), range(5), "no usable camera_info on /camera/camera_info")


def _set_image_count(bag: Path, count: int) -> None:
    import yaml

    meta_path = bag / "metadata.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    for topic in meta["rosbag2_bagfile_information"]["topics_with_message_count"]:
        if "image" in topic["topic_metadata"]["name"]:
            topic["message_count"] = count
    meta_path.write_text(yaml.safe_dump(meta))


def test_rejected_count_is_of_the_frames_read(tmp_path: Path, source: list[Source],
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """metadata.yaml announces 99 images, 10 are in the bag, 2 of them bad: '2 of 10 frames rejected' (it used to
    say '89 of 10'), and the missing messages are a problem of their own."""
    items = [good_jpeg(s) for s in source[:10]]
    bag = write_bag(tmp_path / "bag", items, damage={("image", 3): truncated(20), ("image", 6): truncated(20)})
    _set_image_count(bag, 99)
    rc, err = run_cli([str(bag), "-o", str(tmp_path / "out")], capsys)
    assert rc == 3 and err.count("\n") == 1, err
    assert err.startswith("epi-vo: error: 2 of 10 frames rejected: "), err
    assert err.rstrip().endswith("; 1 message(s) skipped: the bag announces 99 images on /camera/image_raw/compressed,"
                                 " 10 could be read (damaged records?)"), err
    assert len(records(tmp_path / "out")) == 10


def test_overstated_and_understated_image_counts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    for count, rc_expected in ((99, 3), (9, 0)):
        bag = tmp_path / f"bag_{count}"
        shutil.copytree(SOURCE_BAG, bag)
        _set_image_count(bag, count)
        rc = main(["replay", str(bag), "-o", str(tmp_path / f"out_{count}"), "--no-progress"])
        captured = capsys.readouterr()
        assert rc == rc_expected, captured.err
        assert "Traceback" not in captured.err and len(records(tmp_path / f"out_{count}")) == 52
        if count == 99:
            assert captured.err == ("epi-vo: error: 1 message(s) skipped: the bag announces 99 images on "
                                    "/camera/image_raw/compressed, 52 could be read (damaged records?)\n")
        else:
            assert captured.err == ""
            assert ("note: the bag announces 9 images on /camera/image_raw/compressed, 52 were read (its metadata "
                    "understates the count)") in captured.out
