"""vo_node's diagnostics as aggregators read them, live over DDS with a played bag.

``/diagnostics`` carries the node's health once a second (diagnostic_updater's rate), one status per concern
with a stable name and a stable message (numbers only as key/values), so diagnostic_aggregator and
rqt_robot_monitor can group and latch them; every frame's status, with the whole frame record, is on
``vo/frame_status``. Every process gets this test's loopback-only domain (test/ros_fixtures.py).
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from ros_fixtures import NodeProcess, ProbeBase, RosSession, bag_frame_count, rclpy_session

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "ground_robot" / "bag"
WAIT_S = 120.0  # bound on a wait for another process or DDS; it matters only when the condition never comes
CONCERNS = ("tracking", "input", "extrinsic", "scale")
# Every message each concern may say: a fixed set, no number in any (the aggregator groups and latches by them).
MESSAGES = {
    "tracking": {"no frame processed yet", "initializing: waiting for parallax, position held", "tracking",
                 "rotation only: position held", "static: the camera did not move", "lost: no pose",
                 "frames rejected: unusable input", "frames skipped: duplicate stamp"},
    "input": {"no image received yet", "receiving images", "stalled: no recent image",
              "dropping frames: queue_max_mb reached"},
    "extrinsic": {"pending: no image yet", "waiting for TF", "from TF", "from parameters",
                  "from parameters: TF not available"},
    "scale": {"VO units: no metric scale source", "not established: no frame processed yet",
              "not established: VO units, position held", "metres"},
}


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


def _stamp_s(stamp: Any) -> float:
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def test_diagnostics_once_a_second_stable_messages_and_every_frame_on_frame_status(ros: RosSession) -> None:
    n = bag_frame_count(BAG)
    probe = ProbeBase(ros, "probe_health")
    try:
        with NodeProcess(ros.env, "-p", "image_transport:=compressed", "-p", "process_every_frame:=true",
                         "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100", "-p", "scale_source:=ground_plane",
                         "-p", "camera_height_m:=0.45") as node:
            assert probe.spin_until(lambda: probe.node.count_subscribers("/camera/image_raw/compressed") > 0,
                                    WAIT_S), node.proc.stderr
            played = subprocess.run([sys.executable, "-m", "epi_vo.cli", "play", str(BAG), "--rate", "2"],
                                    env=ros.env, capture_output=True, text=True, timeout=10 * WAIT_S)
            assert played.returncode == 0, played.stderr
            assert probe.spin_until(lambda: len(probe.frame_status) >= n and len(probe.odom) >= n, WAIT_S), \
                (len(probe.frame_status), node.proc.stderr)
            k = len(probe.diag)
            assert probe.spin_until(lambda: len(probe.diag) >= k + 2, WAIT_S)  # the health after the last frame
        assert "Traceback" not in node.stderr
    finally:
        probe.close()

    # Every frame on vo/frame_status: one array per frame, its record, in order.
    frames = [s for a in probe.frame_status for s in a.status]
    assert len(probe.frame_status) == n and all(len(a.status) == 1 for a in probe.frame_status)
    assert [int({kv.key: kv.value for kv in s.values}["index"]) for s in frames] == list(range(n))
    assert {s.name for s in frames} == {"/vo_node: tracking"}

    # /diagnostics: at most one array a second (its stamps: the node's clock at each publication), each with
    # one status per concern under a stable name.
    arrays = [a for a in probe.diag if a.status and a.status[0].name.startswith("/vo_node: ")]
    span_s = _stamp_s(arrays[-1].header.stamp) - _stamp_s(arrays[0].header.stamp)
    assert span_s >= 5.0, span_s  # 20 s of bag time at rate 2 (and more on a loaded machine)
    assert len(arrays) <= span_s + 2, (len(arrays), span_s)
    for a in arrays:
        assert [s.name for s in a.status] == [f"/vo_node: {c}" for c in CONCERNS]

    # Stable messages: each concern says one of its few fixed messages, never a number.
    said = {(s.name.rpartition(": ")[2], s.message) for a in arrays for s in a.status}
    assert all(message in MESSAGES[concern] for concern, message in said), said
    assert not any(ch.isdigit() for _, message in said for ch in message)
    while_tracking = {(c, m) for a in arrays for c, m in ((s.name.rpartition(": ")[2], s.message) for s in a.status)
                      if any(s.message == "tracking" for s in a.status)}
    assert len(while_tracking) <= 6, while_tracking
    # The last health: metres from the floor, the frames all counted.
    last = {s.name.rpartition(": ")[2]: s for s in arrays[-1].status}
    assert last["scale"].message == "metres"
    assert {kv.key: kv.value for kv in last["tracking"].values}["frames_processed"] == str(n)
