"""Whole replays of bags whose image or calibration messages carry what decoding must not trust: frames that
declare more pixels than camera_info (refused before decoding, each with its record), JPEGs tagged with an
EXIF orientation (not applied: replayed as recorded), and megabyte strings in encoding / distortion_model
(cut in the reasons, never copied into every record)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from bag_copies import BAGS, TYPESTORE, copy_frames
from encoded_images import big_png, with_exif_orientation
from rosbags.rosbag2 import StoragePlugin, Writer

from epi_vo.cli import main
from epi_vo.io import msgconv

GENERAL = BAGS / "general_motion" / "bag"


def _records(out: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


def test_frames_declaring_too_many_pixels_get_records_and_are_never_decoded(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Three frames whose PNG declares 10000 x 10000 pixels (camera_info: 640 x 480) among good ones."""
    huge = np.frombuffer(big_png(10000, 10000), np.uint8)

    def swap(msg: Any) -> Any:
        if msg.header.stamp.nanosec % 3 == 0 and len(swapped) < 3:
            swapped.append(msg.header.stamp)
            return dataclasses.replace(msg, format="png", data=huge)
        return msg

    swapped: list[Any] = []
    bag = copy_frames(GENERAL, tmp_path / "bag", 20, image=swap)
    assert len(swapped) == 3
    decoded: list[tuple[int, ...]] = []
    real = cv2.imdecode
    monkeypatch.setattr(msgconv.cv2, "imdecode", lambda buf, flags: _spy(real, decoded, buf, flags))
    assert main(["replay", str(bag), "-o", str(tmp_path / "out"), "--no-progress"]) == 3
    assert all(shape == (480, 640) for shape in decoded) and len(decoded) >= 17  # the good frames only
    refused = [r for r in _records(tmp_path / "out") if "declared by its PNG header" in r["reason"]
               or "declares 10000x10000" in r["reason"]]
    assert len(refused) == 3 and not any(r["has_pose"] for r in refused)
    assert all("not decoded" in r["reason"] for r in refused)


def _spy(real: Any, decoded: list[tuple[int, ...]], buf: Any, flags: int) -> Any:
    out = real(buf, flags)
    if out is not None:
        decoded.append(out.shape)
    return out


def test_jpegs_with_an_exif_orientation_replay_as_recorded(tmp_path: Path) -> None:
    """A camera mounted rotated, its driver tagging "rotate 90": image_transport ignores the tag, so does the
    replay; every frame is tracked, as the untagged bag's."""
    def tag(msg: Any) -> Any:
        data = with_exif_orientation(bytes(msg.data), 6)
        return dataclasses.replace(msg, data=np.frombuffer(data, np.uint8))

    plain = copy_frames(GENERAL, tmp_path / "plain", 20)
    tagged = copy_frames(GENERAL, tmp_path / "tagged", 20, image=tag)
    assert main(["replay", str(plain), "-o", str(tmp_path / "a"), "--no-progress"]) == 0
    assert main(["replay", str(tagged), "-o", str(tmp_path / "b"), "--no-progress"]) == 0
    a, b = _records(tmp_path / "a"), _records(tmp_path / "b")
    assert not any(r["rejected"] for r in b) and sum(r["has_pose"] for r in b) >= 18
    np.testing.assert_allclose([r["position"] for r in b], [r["position"] for r in a], atol=1e-9)


def _raw_bag(path: Path, n: int, encoding: str, distortion_model: str) -> Path:
    image_t = TYPESTORE.types["sensor_msgs/msg/Image"]
    info_t = TYPESTORE.types["sensor_msgs/msg/CameraInfo"]
    header_t = TYPESTORE.types["std_msgs/msg/Header"]
    time_t = TYPESTORE.types["builtin_interfaces/msg/Time"]
    roi_t = TYPESTORE.types["sensor_msgs/msg/RegionOfInterest"]
    gray = (np.arange(48 * 64).reshape(48, 64) * 7 % 251).astype(np.uint8)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_img = w.add_connection("/camera/image_raw", image_t.__msgtype__, typestore=TYPESTORE)
        c_info = w.add_connection("/camera/camera_info", info_t.__msgtype__, typestore=TYPESTORE)
        for i in range(n):
            t = 10**9 + i * 66_666_667
            header = header_t(stamp=time_t(sec=t // 10**9, nanosec=t % 10**9), frame_id="cam")
            info = info_t(header=header, height=48, width=64, distortion_model=distortion_model,
                          d=np.zeros(5), k=np.array([60.0, 0, 32, 0, 60, 24, 0, 0, 1]), r=np.eye(3).ravel(),
                          p=np.zeros(12), binning_x=0, binning_y=0,
                          roi=roi_t(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            img = image_t(header=header, height=48, width=64, encoding=encoding, is_bigendian=0, step=64,
                          data=gray.ravel())
            w.write(c_info, t, TYPESTORE.serialize_cdr(info, info_t.__msgtype__))
            w.write(c_img, t, TYPESTORE.serialize_cdr(img, image_t.__msgtype__))
    return path


@pytest.mark.parametrize(("encoding", "model", "said"), [
    ("x" * 2**20, "plumb_bob", "unsupported image encoding 'xxxx"),
    ("mono8", "y" * 2**20, "unknown distortion model 'yyyy"),
])
def test_megabyte_strings_are_not_copied_into_every_record(tmp_path: Path, encoding: str, model: str,
                                                           said: str) -> None:
    bag = _raw_bag(tmp_path / "bag", 20, encoding, model)
    out = tmp_path / "out"
    assert main(["replay", str(bag), "-o", str(out), "--no-progress"]) == 3
    records = _records(out)
    assert len(records) == 20 and all(said in r["reason"] and "(1048576 characters)" in r["reason"]
                                      for r in records)
    for name in ("frames.jsonl", "output.mcap", "stats.json"):
        assert (out / name).stat().st_size < 200_000, name  # 20 copies of the string: over 20 MB
