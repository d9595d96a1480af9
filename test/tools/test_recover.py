"""What survives a replay killed with SIGKILL, and ``epi-vo recover``: the complete chunks of output.mcap
copied into a readable file (the damaged one kept beside, byte for byte), frames.jsonl and trajectory.tum
holding every frame written."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from bag_copies import BAGS, REPO, copy_frames
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from epi_vo.cli import main
from epi_vo.io.odometry_bag import read_odometry

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
FLUSH_FRAMES = 30  # epi_vo.tools.replay_outputs.OUTPUT_FLUSH_FRAMES (imported in the tests: absent on old code)
WAIT_BOUND_S = 600  # only a replay that never writes its frames reaches it


def _lines(path: Path) -> list[bytes]:
    try:
        return path.read_bytes().splitlines(keepends=True)
    except FileNotFoundError:
        return []


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def long_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """general_motion played forward and backward: ~1000 frames of 15 Hz camera, ~66 s of bag time."""
    return copy_frames(BAGS / "general_motion" / "bag", tmp_path_factory.mktemp("long") / "long", 52, repeat=10)


def test_a_killed_replay_is_recovered(long_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from epi_vo.tools.replay_outputs import OUTPUT_FLUSH_FRAMES

    assert OUTPUT_FLUSH_FRAMES == FLUSH_FRAMES
    out = tmp_path / "out"
    # Paced at the camera's rate: the replay cannot reach the end of the bag (over a minute) before the kill,
    # however fast or slow the machine; the kill comes once three chunks' worth of frames were written.
    proc = subprocess.Popen([sys.executable, "-m", "epi_vo.cli", "replay", str(long_bag), "-o", str(out),
                             "--no-progress", "--rate", "1"], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        deadline = time.monotonic() + WAIT_BOUND_S
        while len(_lines(out / "frames.jsonl")) < 3 * FLUSH_FRAMES + 5:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the replay wrote no frames"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    bag = out / "output.mcap"
    damaged_sha = _sha(bag)
    assert not (out / "stats.json").exists()
    with pytest.raises(Exception):  # noqa: B017 - whatever the reader raises: the killed file cannot be read
        read_odometry(bag)

    # What survived: every frame written is in frames.jsonl and, with its pose, in trajectory.tum.
    records = [json.loads(line) for line in _lines(out / "frames.jsonl") if line.endswith(b"\n")]
    assert [r["index"] for r in records] == list(range(len(records)))
    poses = np.loadtxt(out / "trajectory.tum", ndmin=2)
    with_pose = [r for r in records if r["has_pose"]]
    assert len(with_pose) - 1 <= poses.shape[0] <= len(with_pose)  # the kill may fall between the two writes
    np.testing.assert_allclose(poses[:, 0], [r["stamp_ns"] * 1e-9 for r in with_pose[:poses.shape[0]]], atol=1e-6)

    assert main(["recover", str(out)]) == 0
    line = capsys.readouterr().out
    assert "recovered" in line and "kept as output.mcap.damaged" in line
    assert _sha(out / "output.mcap.damaged") == damaged_sha  # the damaged file, untouched
    odometry = read_odometry(bag, "/vo/odometry/vo_units")  # readable now, by our reader and by rosbags (VO units:
    # the motion is on vo_units, vo/odometry holds the position)
    assert not read_odometry(bag).positions.any()
    n = len(odometry.stamps_ns)
    assert n % FLUSH_FRAMES == 0 and FLUSH_FRAMES * 3 <= n <= len(records)
    # The messages recovered are those of the first n frames, in order, with their poses.
    assert list(odometry.stamps_ns) == [r["stamp_ns"] for r in records[:n]]
    optical = np.array([r["position"] for r in records[:n]])  # the camera's optical frame: odom is x fwd, y left
    np.testing.assert_allclose(odometry.positions, np.c_[optical[:, 2], -optical[:, 0], -optical[:, 1]], atol=1e-9)
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        topics = [c.topic for c, _, _ in reader.messages()]
    assert topics.count("/vo/odometry") == topics.count("/vo/odometry/vo_units") == n
    assert topics.count("/vo/frame_status") == n
    # Again: nothing to do, nothing changed; the report reads the recovered directory.
    sha = _sha(bag)
    assert main(["recover", str(out)]) == 0
    assert "complete, nothing to recover" in capsys.readouterr().out and _sha(bag) == sha


def test_recover_refuses_what_it_cannot_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "frames.jsonl").write_text("")
    (out / "output.mcap").write_bytes(b"not an mcap at all")
    assert main(["recover", str(out)]) == 2
    err = capsys.readouterr().err
    assert "is not an MCAP file" in err and "Traceback" not in err
    assert (out / "output.mcap").read_bytes() == b"not an mcap at all"
    assert main(["recover", str(tmp_path / "nothing")]) == 2
