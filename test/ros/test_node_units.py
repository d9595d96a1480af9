"""vo_node live over DDS: no VO units that a robot can fuse by mistake (docs/node.md, Units).

The ground robot bag (a wheeled robot at 0.42-0.65 m/s, 300 frames) is played into a real node process on a
loopback-only domain of this test's own (test/ros_fixtures.py). With ``scale_source: none`` vo/odometry holds
the position with the "unknown" variance and has no linear velocity, while vo/odometry/vo_units moves, in
frames no TF tree has; with ``ground_plane`` vo/odometry is metres once the floor established them.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_fixtures import NodeProcess, ProbeBase, RosSession, bag_frame_count, odom_pose, rclpy_session

from epi_vo.core.config import VoConfig
from epi_vo.core.odometry import UNKNOWN_TWIST_VARIANCE
from epi_vo.io import tum

BAGS = Path(__file__).resolve().parents[2] / "bags"
BAG = BAGS / "ground_robot" / "bag"
PLAYBACK_ARGS = ["-p", "image_transport:=compressed", "-p", "process_every_frame:=true",
                 "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100"]
WAIT_S = 240.0  # bound on each wait for the node (300 frames on a loaded machine); matters only on failure
UNKNOWN_POSITION_VARIANCE = VoConfig().lost_position_variance


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


def _stamp(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


def _twist(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v, w = msg.twist.twist.linear, msg.twist.twist.angular
    return (np.array([v.x, v.y, v.z]), np.array([w.x, w.y, w.z]),
            np.asarray(msg.twist.covariance, dtype=np.float64).reshape(6, 6))


def _pose_cov(msg: Any) -> np.ndarray:
    return np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)


def _play_into_node(ros: RosSession, name: str, *params: str) -> ProbeBase:
    """The whole bag through a node started with ``params``: a probe holding every output."""
    n = bag_frame_count(BAG)
    probe = ProbeBase(ros, name)
    try:
        with NodeProcess(ros.env, *PLAYBACK_ARGS, *params) as node:
            assert probe.spin_until(lambda: probe.node.count_publishers("vo/odometry") > 0, WAIT_S), node.proc.stderr
            played = subprocess.run([sys.executable, "-m", "epi_vo.cli", "play", str(BAG), "--rate", "0"],
                                    env=ros.env, capture_output=True, text=True, timeout=2 * WAIT_S)
            assert played.returncode == 0, played.stderr
            assert probe.spin_until(lambda: len(probe.odom) >= n, WAIT_S), (len(probe.odom), node.proc.stderr)
            probe.spin_until(lambda: False, 1.0)  # the last vo_units messages
    except BaseException:
        probe.close()
        raise
    return probe


def test_in_vo_units_the_fusable_odometry_holds_and_the_vo_unit_topic_moves(ros: RosSession) -> None:
    """scale_source none on a robot driving 11 m at ~0.55 m/s: every vo/odometry has the position where
    tracking started with the "unknown" variance and a zero linear velocity with the "unknown" variance,
    while its orientation and angular velocity are estimated (a tight covariance, the vo_units topic's);
    vo/odometry/vo_units carries the motion, in frames that are not the fusable ones."""
    probe = _play_into_node(ros, "probe_units_none")
    try:
        n = bag_frame_count(BAG)
        assert len(probe.odom) == n and probe.spin_until(lambda: len(probe.odom_vo_units) >= n, WAIT_S)
        vo_by_stamp = {_stamp(m): m for m in probe.odom_vo_units}
        assert set(vo_by_stamp) == {_stamp(m) for m in probe.odom}
        for msg in probe.odom:
            assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "base_link")
            np.testing.assert_array_equal(odom_pose(msg)[:3], np.zeros(3))
            cov = _pose_cov(msg)
            np.testing.assert_array_equal(np.diag(cov)[:3], [UNKNOWN_POSITION_VARIANCE] * 3)
            lin, ang, tcov = _twist(msg)
            np.testing.assert_array_equal(lin, np.zeros(3))
            np.testing.assert_array_equal(np.diag(tcov)[:3], [UNKNOWN_TWIST_VARIANCE] * 3)
            vo = vo_by_stamp[_stamp(msg)]
            np.testing.assert_allclose(odom_pose(msg)[3:], odom_pose(vo)[3:], atol=1e-12)  # the same orientation
            np.testing.assert_allclose(ang, _twist(vo)[1], atol=1e-12)
            np.testing.assert_allclose(cov[3:, 3:], _pose_cov(vo)[3:, 3:], atol=1e-15)
        tracked = probe.odom[10:]
        assert np.median([_pose_cov(m)[5, 5] for m in tracked]) < 1e-3  # yaw known within ~2 deg
        assert np.median([_twist(m)[2][5, 5] for m in tracked]) < 1.0  # and its rate
        assert max(abs(_twist(m)[1][2]) for m in tracked) > 0.05  # the robot turns: yaw rate seen (rad/s)
        for vo in probe.odom_vo_units:
            assert (vo.header.frame_id, vo.child_frame_id) == ("odom_vo_units", "base_link_vo_units")
        last = probe.odom_vo_units[-1]
        assert float(np.linalg.norm(odom_pose(last)[:3])) > 1.0  # it moved (VO units)
        speeds = [float(np.linalg.norm(_twist(m)[0])) for m in probe.odom_vo_units[10:]]
        assert np.median(speeds) > 0.0 and np.median([_twist(m)[2][0, 0] for m in probe.odom_vo_units[10:]]) < 1.0
        # Every frame's status says VO units, and so does the node's scale status on /diagnostics.
        units = [{kv.key: kv.value for kv in s.values}.get("units") for a in probe.frame_status for s in a.status]
        assert len(units) == n and set(units) == {"vo"}

        def scale_statuses() -> list[dict[str, str]]:
            return [{kv.key: kv.value for kv in s.values} for a in probe.diag for s in a.status
                    if s.name.endswith(": scale")]

        assert probe.spin_until(lambda: any("metric_scale" in v for v in scale_statuses()), WAIT_S)  # after a frame
        assert {v["units"] for v in scale_statuses()} == {"vo"}
    finally:
        probe.close()


def test_with_the_floor_the_fusable_odometry_is_metres_once_established(ros: RosSession) -> None:
    """ground_plane (camera 0.45 m above the floor): vo/odometry holds the position until the floor gave
    metres, then carries the motion in metres: its speed is the robot's 0.42-0.65 m/s and its end point is
    the ground truth's within 5 %; nothing in VO units is published after that, and only then."""
    probe = _play_into_node(ros, "probe_units_floor", "-p", "scale_source:=ground_plane",
                            "-p", "camera_height_m:=0.45")
    try:
        vo_stamps = {_stamp(m) for m in probe.odom_vo_units}
        held = [m for m in probe.odom if _stamp(m) in vo_stamps]
        metric = [m for m in probe.odom if _stamp(m) not in vo_stamps]
        assert 1 <= len(held) <= 30 and len(metric) >= 270
        assert max(_stamp(m) for m in held) < min(_stamp(m) for m in metric)  # VO units only before metres
        for m in held:
            np.testing.assert_array_equal(odom_pose(m)[:3], np.zeros(3))
            assert _pose_cov(m)[0, 0] == UNKNOWN_POSITION_VARIANCE
        assert all(_pose_cov(m)[0, 0] < 1.0 for m in metric)
        speeds = [float(np.linalg.norm(_twist(m)[0])) for m in metric[1:]]
        assert 0.42 <= float(np.median(speeds)) <= 0.65, np.median(speeds)
        gt = tum.read_tum(BAGS / "ground_robot" / "groundtruth_tum.txt")
        travelled = float(np.linalg.norm(gt[1][-1] - gt[1][0]))
        end = float(np.linalg.norm(odom_pose(metric[-1])[:3]))
        assert end == pytest.approx(travelled, rel=0.05), (end, travelled)
    finally:
        probe.close()
