"""Replays of the bundled bags checked against their ground truth, and the replay's error paths."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from epi_vo.cli import main
from epi_vo.core.errors import BagError
from epi_vo.io import bagio
from epi_vo.io.msgconv import read_points_xyz
from epi_vo.tools.replay import ReplaySummary, format_summary, run_replay, with_next

REPO = Path(__file__).resolve().parents[2]
BAGS = REPO / "bags"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def _replay(name: str, tmp_path_factory: pytest.TempPathFactory) -> tuple[ReplaySummary, Path]:
    out = tmp_path_factory.mktemp(name)
    return run_replay(BAGS / name / "bag", out), out


@pytest.fixture(scope="module")
def general(tmp_path_factory: pytest.TempPathFactory) -> tuple[ReplaySummary, Path]:
    return _replay("general_motion", tmp_path_factory)


@pytest.fixture(scope="module")
def rotation(tmp_path_factory: pytest.TempPathFactory) -> tuple[ReplaySummary, Path]:
    return _replay("pure_rotation", tmp_path_factory)


@pytest.fixture(scope="module")
def planar(tmp_path_factory: pytest.TempPathFactory) -> tuple[ReplaySummary, Path]:
    return _replay("planar", tmp_path_factory)


def _records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


def test_general_motion_matches_ground_truth(general: tuple[ReplaySummary, Path]) -> None:
    s, _ = general
    assert s.metrics is not None, s.notes
    assert s.tracked_percent >= 95.0
    assert s.states.get("tracking", 0) >= 0.8 * s.frames
    assert s.metrics["ate_percent_of_path"] < 3.0
    assert s.metrics["rpe_rot_deg_per_frame"] < 0.1
    assert s.metrics["trans_direction_err_deg"] < 5.0
    assert s.models.get("E", 0) > s.models.get("H", 0)


def test_outputs_account_for_every_frame(general: tuple[ReplaySummary, Path]) -> None:
    s, out = general
    records = _records(out)
    assert [r["index"] for r in records] == list(range(s.frames))
    tum = np.loadtxt(out / "trajectory.tum", ndmin=2)
    assert tum.shape == (s.frames_with_pose, 8)
    assert sum(r["has_pose"] for r in records) == s.frames_with_pose
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-6)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames"] == s.frames and stats["ms_per_frame"] > 0
    for r in records:
        assert (r["state"] == "tracking" and not r["reason"]) or r["reason"], r  # a reason unless clean tracking
        assert all(math.isfinite(v) and v > 0 for v in r["covariance_diagonal"])


def test_output_bag_has_one_odometry_and_diagnostics_per_frame(general: tuple[ReplaySummary, Path]) -> None:
    s, out = general
    counts: dict[str, int] = {}
    n_points = 0
    with AnyReader([out / "output.mcap"], default_typestore=TYPESTORE) as reader:
        for con, _, raw in reader.messages():
            counts[con.topic] = counts.get(con.topic, 0) + 1
            msg = reader.deserialize(raw, con.msgtype)
            if con.topic == "/vo/odometry":
                q = np.array([msg.pose.pose.orientation.x, msg.pose.pose.orientation.y,
                              msg.pose.pose.orientation.z, msg.pose.pose.orientation.w])
                assert abs(np.linalg.norm(q) - 1.0) < 1e-6
                cov = np.asarray(msg.pose.covariance).reshape(6, 6)
                assert np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0) and np.all(np.diag(cov) < 1e12)
                assert msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
            elif con.topic == "/vo/points":
                pts = read_points_xyz(msg)
                assert pts.shape[0] > 0 and np.all(np.isfinite(pts))
                n_points += pts.shape[0]
            elif con.topic == "/vo/frame_status":
                (status,) = msg.status
                assert status.name == "epi_vo: tracking" and status.message
                keys = {kv.key for kv in status.values}
                assert {"state", "model", "rh", "n_inliers", "median_parallax_deg"} <= keys
    assert counts["/vo/odometry"] == s.frames
    assert counts["/vo/frame_status"] == s.frames
    assert counts["/vo/points"] == s.keyframes - 1 or counts["/vo/points"] >= 1
    assert n_points >= 50


def test_pure_rotation_invents_no_translation(rotation: tuple[ReplaySummary, Path]) -> None:
    s, out = rotation
    tum = np.loadtxt(out / "trajectory.tum", ndmin=2)
    assert s.tracked_percent == 100.0
    np.testing.assert_array_equal(tum[:, 1:4], 0.0)
    assert s.states.get("rotation_only", 0) >= 0.8 * s.frames
    assert s.models.get("H", 0) >= 0.9 * (s.frames - 1)
    assert s.metrics is not None and s.metrics["rpe_rot_deg_per_frame"] < 0.05
    rot_records = [r for r in _records(out) if r["state"] == "rotation_only"]
    assert all("pure rotation" in r["reason"] and r["rh"] > 0.45 for r in rot_records)


def test_planar_scene_chooses_homography_and_tracks(planar: tuple[ReplaySummary, Path]) -> None:
    s, out = planar
    assert s.models.get("H", 0) >= 0.8 * (s.frames - 1)
    assert s.states.get("tracking", 0) >= 0.6 * s.frames
    assert s.metrics is not None
    assert s.metrics["ate_percent_of_path"] < 6.0
    assert s.metrics["rpe_rot_deg_per_frame"] < 0.1
    assert any("planar" in r["reason"] for r in _records(out))


# --------------------------------------------------------------------------------------------------
def _write_bag(path: Path, images: list[object], infos: list[object]) -> None:
    Image = TYPESTORE.types["sensor_msgs/msg/Image"]
    Info = TYPESTORE.types["sensor_msgs/msg/CameraInfo"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/camera/image_raw", Image.__msgtype__, typestore=TYPESTORE)
        cc = w.add_connection("/camera/camera_info", Info.__msgtype__, typestore=TYPESTORE)
        for i, (img, info) in enumerate(zip(images, infos, strict=True)):
            t = 1_000_000_000 + i * 50_000_000
            w.write(ci, t, TYPESTORE.serialize_cdr(img, Image.__msgtype__))
            w.write(cc, t, TYPESTORE.serialize_cdr(info, Info.__msgtype__))


def _header(i: int) -> object:
    Header = TYPESTORE.types["std_msgs/msg/Header"]
    Time = TYPESTORE.types["builtin_interfaces/msg/Time"]
    return Header(stamp=Time(sec=1, nanosec=i * 50_000_000), frame_id="cam")


def _image(i: int, encoding: str, width: int, height: int, bpp: int) -> object:
    Image = TYPESTORE.types["sensor_msgs/msg/Image"]
    data = np.random.default_rng(i).integers(0, 255, width * height * bpp, dtype=np.uint8)
    return Image(header=_header(i), height=height, width=width, encoding=encoding, is_bigendian=0,
                 step=width * bpp, data=data)


def _info(i: int, width: int, height: int) -> object:
    Info = TYPESTORE.types["sensor_msgs/msg/CameraInfo"]
    RoI = TYPESTORE.types["sensor_msgs/msg/RegionOfInterest"]
    k = np.array([300.0, 0, width / 2, 0, 300.0, height / 2, 0, 0, 1])
    return Info(header=_header(i), height=height, width=width, distortion_model="plumb_bob", d=np.zeros(5), k=k,
                r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
                roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def test_unsupported_encoding_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "bad_encoding"
    _write_bag(bag, [_image(i, "32FC1", 64, 48, 4) for i in range(3)], [_info(i, 64, 48) for i in range(3)])
    rc = main(["replay", str(bag), "--output", str(tmp_path / "out"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 3  # ran, but frames were rejected
    assert "unsupported image encoding '32FC1'" in err and "3 of 3 frames rejected" in err and "frame 0" in err
    assert "Traceback" not in err
    records = [json.loads(line) for line in (tmp_path / "out" / "frames.jsonl").read_text().splitlines()]
    assert len(records) == 3 and not any(r["has_pose"] for r in records)
    assert all("unsupported image encoding" in r["reason"] and r["state"] == "lost" for r in records)


def test_camera_info_size_mismatch_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "bad_size"
    _write_bag(bag, [_image(i, "mono8", 64, 48, 1) for i in range(3)], [_info(i, 640, 480) for i in range(3)])
    rc = main(["replay", str(bag), "--output", str(tmp_path / "out"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 3
    assert "64x48" in err and "640x480" in err


def test_uncalibrated_camera_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "uncalibrated"
    info = _info(0, 64, 48)
    info.k = np.zeros(9)
    _write_bag(bag, [_image(0, "mono8", 64, 48, 1)], [info])
    assert main(["replay", str(bag), "--output", str(tmp_path / "out"), "--no-progress"]) == 3
    assert "uncalibrated" in capsys.readouterr().err


def test_raw_and_compressed_replays_agree(tmp_path: Path) -> None:
    """The same frames as mono8 Image (padded step) and as the bag's JPEG give the same poses."""
    src = BAGS / "pure_rotation" / "bag"
    images, infos = [], []
    Image = TYPESTORE.types["sensor_msgs/msg/Image"]
    with bagio.open_camera_bag(src) as bag:
        for frame in bag.iter_frames():
            if frame.index >= 15:
                break
            from epi_vo.io.msgconv import decode_frame

            gray = decode_frame(frame.image_msg, bag.image_is_compressed)
            h, w = gray.shape
            padded = np.zeros((h, w + 3), np.uint8)
            padded[:, :w] = gray
            images.append(Image(header=frame.image_msg.header, height=h, width=w, encoding="mono8",
                                is_bigendian=0, step=w + 3, data=padded.ravel()))
            infos.append(frame.camera_info_msg)
    _write_bag(tmp_path / "raw", images, infos)
    a = run_replay(tmp_path / "raw", tmp_path / "out_raw")
    assert a.frames == 15
    ta = np.loadtxt(tmp_path / "out_raw" / "trajectory.tum")
    run_replay(src, tmp_path / "out_jpeg")
    tb = np.loadtxt(tmp_path / "out_jpeg" / "trajectory.tum")[:15]
    np.testing.assert_allclose(ta, tb, atol=1e-9)


def test_end_to_end_rate_is_reported(general: tuple[ReplaySummary, Path]) -> None:
    s, out = general
    stats = json.loads((out / "stats.json").read_text())
    assert stats["wall_s"] > 0 and stats["end_to_end_fps"] == pytest.approx(s.frames / stats["wall_s"])
    assert ReplaySummary.from_json(stats) == s
    text = format_summary(s)
    assert "ms/frame median" in text and f"end to end    {s.end_to_end_fps:.1f} frames/s" in text


def test_stats_json_only_for_a_finished_replay(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """stats.json is written last: a replay into a directory that holds one from before removes it first, so a
    replay that stops early leaves none (what fleet replay's resume relies on)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "stats.json").write_text("{}")
    # A bag refused before anything is written (not found, a FIFO, an output on an input) leaves the directory
    # as it was.
    assert main(["replay", str(tmp_path / "missing_bag"), "--output", str(out), "--no-progress"]) == 2
    assert "bag not found" in capsys.readouterr().err
    assert (out / "stats.json").read_text() == "{}"
    # One that fails once the outputs are opened leaves no stats.json.
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"\x89MCAP0\r\n cut short")
    assert main(["replay", str(broken), "--output", str(out), "--no-progress"]) == 2
    assert "broken.mcap" in capsys.readouterr().err
    assert not (out / "stats.json").exists()
    assert not list(out.glob(".*.tmp"))


def test_the_lookahead_never_loses_a_frame_read_before_a_read_error() -> None:
    """Replay reads one frame ahead (its image is tracked into while the current one is processed); a bag
    that cannot be read further still gives every frame read before the error its turn."""
    def frames(n: int, fail: bool) -> Iterator[int]:
        yield from range(n)
        if fail:
            raise BagError("cannot read /camera/image_raw from bag: damaged record")

    assert list(with_next(frames(3, False))) == [(0, 1), (1, 2), (2, None)]
    assert list(with_next(frames(0, False))) == []
    got = []
    with pytest.raises(BagError, match="damaged record"):
        for pair in with_next(frames(3, True)):
            got.append(pair)
    assert got == [(0, 1), (1, 2), (2, None)]


def test_a_paced_replay_takes_the_bags_time_and_gives_the_same_outputs(general: tuple[ReplaySummary, Path],
                                                                        tmp_path: Path) -> None:
    """--rate 4: the 52 frames of 3.4 s arrive as a camera at 4x would hand them over (not sooner; a slow
    machine only makes it later), KLT in line, and the trajectory is the flat-out replay's."""
    stamps = [json.loads(line)["stamp"] for line in (general[1] / "frames.jsonl").read_text().splitlines()]
    t0 = time.monotonic()
    assert main(["replay", str(BAGS / "general_motion" / "bag"), "--output", str(tmp_path), "--rate", "4",
                 "--no-progress"]) == 0
    assert time.monotonic() - t0 >= (stamps[-1] - stamps[0]) / 4.0
    assert (tmp_path / "trajectory.tum").read_text() == (general[1] / "trajectory.tum").read_text()
    records = [json.loads(line) for line in (tmp_path / "frames.jsonl").read_text().splitlines()]
    assert len(records) == 52 and not any("klt_ahead" in r["timings_ms"] for r in records)


def test_pacing_waits_for_each_stamp_but_not_through_a_recording_pause() -> None:
    from epi_vo.tools.replay import PACE_MAX_GAP_S, Pace

    pace = Pace(rate=20.0)
    t0 = time.monotonic()
    for stamp_s in (0.0, 1.0, 2.0, 1000.0, 1001.0):  # 1 s apart, then a 998 s pause
        pace.wait(int(stamp_s * 1e9), lambda: False)
    waited = time.monotonic() - t0
    assert waited >= (3.0 + PACE_MAX_GAP_S) / 20.0  # every second (and the pause as its cap) at 20x
    assert waited < 998.0 / 20.0  # the pause itself is not waited for
    with pytest.raises(ValueError, match="rate must be a positive number"):
        Pace(rate=0.0)


def test_a_rate_that_is_no_positive_number_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(BAGS / "general_motion" / "bag"), "--output", str(tmp_path), "--rate", "0"]) == 2
    assert "--rate must be a positive number, not 0.0" in capsys.readouterr().err
    assert main(["replay", str(BAGS / "general_motion" / "bag"), str(BAGS / "planar" / "bag"), "--output",
                 str(tmp_path), "--rate", "1"]) == 2
    assert "a fleet replays flat out" in capsys.readouterr().err
