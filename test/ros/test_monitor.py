"""``epi-vo monitor``: the pure MonitorState fed plain values, and the command against a real vo_node.

The integration tests start every rclpy process (vo_node, ``epi-vo play``, ``epi-vo monitor`` and this
test's probe) with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and this test's own ROS_DOMAIN_ID
(test/ros_fixtures.py): ``epi-vo monitor`` itself takes them from its environment.
"""

from __future__ import annotations

import math
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from ros_fixtures import RosSession, rclpy_session, ros_test_env, spin_until, wait_until

from epi_vo.ros.monitor import (
    HISTORY_LENGTH,
    MonitorState,
    is_vo_status,
    level_name,
    odometry_namespace,
    reason_key,
)

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "general_motion" / "bag"
NAME = "vo_node: tracking"  # a per-frame status (vo/frame_status) of a node named by its bare name (the root's)
NODE = "/vo_node"  # what a running vo_node (root namespace) is, the snapshot's first line
WAIT_S = 120.0  # bound on waiting for another process: generous, a loaded machine is slow, not broken


def _record(**over: str) -> dict[str, str]:
    """Key/values of a per-frame status as the node publishes them (frame record + input figures)."""
    values = {"index": "41", "stamp": "1700000002.7", "stamp_ns": "1700000002700000000", "state": "tracking",
              "has_pose": "True", "is_keyframe": "False", "model": "E", "rh": "0.183", "n_features": "300",
              "n_tracked": "200", "n_inliers": "170", "inlier_ratio": "0.85", "median_parallax_deg": "2.91",
              "n_triangulated": "0", "positive_depth_ratio": "None", "median_reproj_err_px": "None",
              "relative_scale": "1", "n_keyframes": "4", "position": "1 2 3", "quat_xyzw": "0 0 0 1",
              "n_points": "0", "timings_ms": "track=3.2", "reason": "",
              "input_rate_hz": "15.02", "latency_ms": "12.34", "frames_received": "42", "dropped_frames": "1",
              "queue_depth": "0", "time_since_last_image_s": "0.031"}
    values.update(over)
    return values


def _tracking_session() -> MonitorState:
    """Three initialising frames (WARN, numbers differing), then a tracking one, odometry in 3-4-5 steps (on
    vo/odometry and on vo/odometry/vo_units alike)."""
    s = MonitorState()
    for i, parallax in enumerate(("0.21", "0.35", "0.48")):
        s = s.update_from_frame(NAME, b"\x01", f"initializing: low parallax ({parallax} deg < 0.5)",
                                 _record(state="initializing", index=str(i), model="none", rh="None"), 100.0 + i)
    s = s.update_from_frame(NAME, b"\x00", "tracking", _record(), 103.0, "monocular_camera")
    for t, p in enumerate([(0.0, 0.0, 0.0), (3.0, 4.0, 0.0), (6.0, 8.0, 0.0), (6.0, 8.0, 0.0), (6.0, 4.0, -3.0)]):
        s = s.update_from_odometry(p, 100.0 + t).update_from_odometry(p, 100.0 + t, vo_units=True)
    return s


def test_snapshot_shows_level_state_reason_and_numbers() -> None:
    text = _tracking_session().render_text(103.5)
    assert text.startswith("/vo_node  (hardware monocular_camera)")
    assert re.search(r"level\s+OK\b", text)
    assert re.search(r"reason\s+tracking\b", text)
    assert re.search(r"^  why\s+tracking$", text, re.MULTILINE)  # the latest frame's own words
    assert re.search(r"state\s+tracking\s+frame 41\b", text)
    for part in ("inliers 170", "inlier ratio 0.850", "tracked 200", "features 300", "RH 0.183",
                 "parallax 2.91 deg", "model       E", "keyframes 4", "15.0 Hz", "dropped 1", "received 42",
                 "latency     12.3 ms", "last image 0.03 s ago", "reproj n/a"):
        assert part in text, part


def test_distance_is_the_sum_of_odometry_steps() -> None:
    s = _tracking_session()
    assert s.distance == 15.0  # 5 + 5 + 0 + 5: 3-4-5 triangles, exact in floating point
    assert "distance 15.000 (VO units)" in s.render_text()
    assert "position 6.000 4.000 -3.000" in s.render_text()
    assert s.update_from_odometry((math.nan, 0.0, 0.0), 110.0) is s  # a broken message is ignored
    assert s.update_from_odometry((math.nan, 0.0, 0.0), 110.0, vo_units=True) is s


def test_the_distance_is_of_the_topic_that_carries_the_motion_in_the_status_units() -> None:
    """In VO units vo/odometry holds its position (the node publishes no VO units where a robot could fuse
    them): the distance and position shown are vo/odometry/vo_units'; in metres, vo/odometry's."""
    s = MonitorState().update_from_frame(NAME, 0, "tracking", _record(**VO_UNITS), 100.0)
    for t, p in enumerate([(0.0, 0.0, 0.0), (3.0, 4.0, 0.0), (6.0, 8.0, 0.0)]):
        s = s.update_from_odometry((0.0, 0.0, 0.0), 100.0 + t).update_from_odometry(p, 100.0 + t, vo_units=True)
    assert (s.distance, s.vo_distance, s.n_odometry) == (0.0, 10.0, 3)
    assert "distance 10.000 (VO units)  position 6.000 8.000 0.000  messages 3" in s.render_text()
    s = s.update_from_frame(NAME, 0, "tracking", _record(**METRIC), 104.0)
    s = s.update_from_odometry((0.0, 0.0, 0.0), 104.0).update_from_odometry((0.0, 1.5, 2.0), 105.0)
    assert "distance 2.500 m  position 0.000 1.500 2.000  messages 5" in s.render_text()


METRIC = {"units": "m", "scale_source": "ground_plane", "metric_scale": "True", "scale": "0.997",
          "scale_rel_std": "0.0123", "floor_pitch_deg": "15.74", "floor_roll_deg": "-0.386", "scale_reason": ""}
VO_UNITS = {"units": "vo", "scale_source": "none", "metric_scale": "False", "scale": "1", "scale_rel_std": "None",
            "floor_pitch_deg": "None", "floor_roll_deg": "None", "scale_reason": ""}


def _line(text: str, label: str) -> str:
    """The snapshot line whose label (the 12-character column after the indent) is ``label``."""
    (line,) = [ln for ln in text.splitlines() if ln[2:14].strip() == label]
    return line


def test_metric_status_shows_metres_scale_and_floor() -> None:
    s = _tracking_session().update_from_frame(NAME, 0, "tracking", _record(**METRIC), 104.0)
    assert s.units == "m"
    text = s.render_text(104.0)
    assert _line(text, "scale") == "  scale       ground_plane: metric, 0.997 m/unit ±1.2 %"
    assert _line(text, "floor") == "  floor       pitch 15.74 deg  roll -0.39 deg"
    assert "distance 15.000 m  position 6.000 4.000 -3.000" in text
    assert "VO units" not in text and "scale note" not in text
    # An input status carries no record: the units and scale of the last frame stay.
    s = s.update_from_health("vo_node: input", 1, "stalled: no recent image", {"time_since_last_image_s": "1.1"},
                             105.0)
    assert s.units == "m" and "distance 15.000 m " in s.render_text(105.0)
    assert "ground_plane: metric, 0.997 m/unit" in s.render_text(105.0)


def test_vo_units_status_and_a_source_not_yet_established() -> None:
    s = _tracking_session().update_from_frame(NAME, 0, "tracking", _record(**VO_UNITS), 104.0)
    text = s.render_text(104.0)
    assert s.units == "vo"
    assert _line(text, "scale") == "  scale       none: VO units"
    assert "distance 15.000 (VO units)" in text and "floor" not in text and "m/unit" not in text
    # A metric source that has not measured yet: VO units, the position held, and why.
    why = "ground plane not seen yet: scale unknown (VO units)"
    s = s.update_from_frame(NAME, 0, "tracking", _record(**dict(METRIC, units="vo", metric_scale="False", scale="1",
                                                                 scale_rel_std="None", floor_pitch_deg="None",
                                                                 floor_roll_deg="None", scale_reason=why)), 105.0)
    text = s.render_text(105.0)
    assert _line(text, "scale") == "  scale       ground_plane: not established yet: VO units (position held)"
    assert f"  scale note  {why}" in text.splitlines()
    assert "distance 15.000 (VO units)" in text and "floor" not in text
    # A status of a node older than the scale sources has no scale keys: VO units, source none.
    assert _line(_tracking_session().render_text(), "scale") == "  scale       none: VO units"


def test_warning_history_groups_reasons_with_counts() -> None:
    s = _tracking_session()
    assert len(s.history) == 1
    entry = s.history[0]
    assert (entry.count, entry.level, entry.last_s) == (3, 1, 102.0)
    assert entry.message == "initializing: low parallax (0.48 deg < 0.5)"  # the latest wording
    text = s.render_text(103.5)
    assert re.search(r"WARN\s+x3\s+initializing: low parallax \(0\.48 deg < 0\.5\)\s+last \d\d:\d\d:\d\d "
                     r"\(1\.5 s ago\)", text), text


def test_history_keeps_the_most_recent_distinct_reasons() -> None:
    s = MonitorState()
    for i in range(HISTORY_LENGTH + 3):
        s = s.update_from_frame(NAME, 2, f"lost: problem kind {chr(ord('a') + i)}", _record(state="lost"), float(i))
    s = s.update_from_frame(NAME, 2, "lost: problem kind k", _record(state="lost"), 50.0)
    assert len(s.history) == HISTORY_LENGTH
    assert [h.message[-1] for h in s.history[:3]] == ["k", "j", "i"]  # most recent first
    assert s.history[0].count == 2
    assert all(h.message[-1] not in "abc" for h in s.history)  # the oldest fell out
    assert re.search(r"ERROR\s+x2\s+lost: problem kind k", s.render_text())


def test_watchdog_status_is_stale_and_keeps_the_last_frame() -> None:
    s = _tracking_session()
    for t, gap in ((104.0, "1.1"), (105.0, "2.1"), (106.0, "3.1")):
        level = 3 if float(gap) >= 3.0 else 1
        s = s.update_from_health("vo_node: input", bytes([level]), "stalled: no recent image",
                                 {"input_rate_hz": "0.00", "time_since_last_image_s": gap, "frames_received": "42",
                                  "dropped_frames": "1", "queue_depth": "0", "latency_ms": "12.34"}, t)
        s = s.update_from_health("vo_node: tracking", 0, "tracking", {"frames_processed": "42"}, t)
    text = s.render_text(106.0)
    assert re.search(r"level\s+STALE\b", text)
    assert re.search(r"reason\s+input: stalled: no recent image", text)  # the worst concern, named
    assert "health      input STALE (stalled: no recent image)  tracking OK (tracking)" in text
    assert "(last frame 3.0 s ago)" in text and "inliers 170" in text  # the last frame's numbers stay
    assert "last image 3.10 s ago" in text and "0.0 Hz" in text  # the input figures are the latest
    assert re.search(r"STALE\s+x3\s+input: stalled: no recent image", text)  # one reason, its latest level
    assert "no status for" not in text
    assert "!! no status for 4.0 s" in s.render_text(110.0)  # the node itself went silent


def test_a_stalled_node_shows_the_scale_source_it_was_given() -> None:
    """A ground_plane node whose camera never delivered: no frame record, but its scale status says the source
    (not 'none'), not established, and why the frames are missing."""
    from epi_vo.core import health

    scale = health.scale_status("/vo_node", "cam", "ground_plane", None)
    stall = health.input_status("/vo_node", "cam", health.InputState(stall=health.DiagnosticLevel.STALE))
    tracking = health.TrackingHealth().status("/vo_node", "cam")
    s = MonitorState()
    for st in (tracking, stall, scale):
        s = s.update_from_health(st.name, int(st.level), st.message, st.values, 10.0, st.hardware_id)
    assert s.snapshot_complete  # --once prints it: the node has processed no frame to wait for
    text = s.render_text(10.0)
    assert _line(text, "scale") == "  scale       ground_plane: not established yet: VO units (position held)"
    assert re.search(r"level\s+STALE\b", text) and "input: no image received yet" in text
    assert "scale WARN (not established: no frame processed yet)" in text
    assert s.units == "vo" and "distance 0.000 (VO units)" in text


def test_other_nodes_and_other_statuses() -> None:
    s = MonitorState().update_from_health("camera_driver", 2, "fault", {}, 1.0)
    assert not s.has_status and "waiting for a VO status" in s.render_text()
    s = s.update_from_frame(NAME, 0, "tracking", _record(), 2.0)
    s = s.update_from_frame("vo_other: tracking", 2, "lost", _record(state="lost"), 3.0)
    assert s.source == NODE and s.level == 0 and s.n_statuses == 1
    assert "also seen   /vo_other" in s.render_text()
    chosen = MonitorState(node_name="/robot1/vo_other").update_from_frame(NAME, 0, "tracking", _record(), 1.0)
    chosen = chosen.update_from_frame("/robot2/vo_other: tracking", 0, "tracking", _record(), 1.5)
    assert not chosen.has_status
    chosen = chosen.update_from_frame("/robot1/vo_other: tracking", 2, "lost", _record(state="lost"), 2.0)
    assert chosen.source == "/robot1/vo_other" and re.search(r"level\s+ERROR", chosen.render_text())
    assert is_vo_status(NAME) and is_vo_status(NAME, "vo_node") and not is_vo_status(NAME, "vo")
    assert not is_vo_status("vo_node: tracking extra") and not is_vo_status(": tracking")
    assert not is_vo_status("/vo_node: summary") and is_vo_status("/vo_node: scale")


def test_statuses_are_picked_by_namespace() -> None:
    """Two cameras, two namespaces, one node name: the monitor follows the namespace of its odometry topic."""
    assert [odometry_namespace(t) for t in ("/robot1/vo/odometry", "/vo/odometry", "/robot1/odom_vo",
                                            "/a/b/vo/odometry")] == ["/robot1", "/", "/robot1", "/a/b"]
    assert is_vo_status("/robot1/vo_node: tracking", namespace="/robot1")
    assert not is_vo_status("/robot2/vo_node: tracking", namespace="/robot1")
    assert not is_vo_status("/robot1/sub/vo_node: tracking", namespace="/robot1")
    assert is_vo_status("/vo_node: tracking", namespace="/") and is_vo_status("vo_node: tracking", namespace="/")
    assert is_vo_status("/robot1/vo_node: tracking", "/robot1/vo_node", "/robot1")
    assert not is_vo_status("/robot2/vo_node: tracking", "vo_node", "/robot1")
    s = MonitorState(namespace="/robot2")
    assert "'/robot2/<node>: tracking|input|extrinsic|scale|...'" in s.render_text()
    s = s.update_from_frame("/robot1/vo_node: tracking", 2, "lost", _record(state="lost"), 1.0)
    assert not s.has_status
    s = s.update_from_frame("/robot2/vo_node: tracking", 0, "tracking", _record(n_inliers="77"), 2.0)
    s = s.update_from_frame("/robot1/vo_node: tracking", 2, "lost", _record(state="lost"), 3.0)
    assert s.source == "/robot2/vo_node" and s.level == 0 and "inliers 77" in s.render_text()
    assert not s.other_sources  # the other namespace's node is not even a candidate


def test_state_is_immutable_and_odd_values_are_shown_not_refused() -> None:
    s0 = MonitorState()
    s1 = s0.update_from_frame(NAME, 7, "odd level", {"state": "tracking", "n_inliers": "nan", "rh": "x"}, 1.0)
    assert s0.n_statuses == 0 and s1.n_statuses == 1
    text = s1.render_text()
    assert "level       LEVEL 7" in text and "inliers n/a" in text and "RH n/a" in text
    assert [level_name(v) for v in range(4)] == ["OK", "WARN", "ERROR", "STALE"]
    assert reason_key("no image for 1.5 s") == reason_key("no image for 12 s")
    assert reason_key("lost: 3 inliers") != reason_key("tracking")


def test_real_frame_records_render_their_numbers() -> None:
    """The keys the monitor reads are the ones the node publishes (status.frame_status of real frames)."""
    from epi_vo.core.camera import CameraModel
    from epi_vo.core.pipeline import VoPipeline
    from epi_vo.core.status import frame_status
    from epi_vo.io import bagio
    from epi_vo.io.msgconv import decode_frame

    pipe = VoPipeline()
    s = MonitorState()
    with bagio.open_camera_bag(BAG) as bag:
        for f in bag.iter_frames():
            if f.index >= 12:
                break
            r = pipe.process(decode_frame(f.image_msg, bag.image_is_compressed),
                             CameraModel.from_camera_info(f.camera_info_msg), f.stamp_ns)
            st = frame_status(r, "vo_node", "cam")
            s = s.update_from_frame(st.name, int(st.level), st.message, st.values, float(f.index))
    assert r.n_inliers > 0 and math.isfinite(r.inlier_ratio)
    text = s.render_text()
    assert f"state       {r.state.value}  frame {r.index}" in text
    assert f"inliers {r.n_inliers}  inlier ratio {r.inlier_ratio:.3f}" in text
    assert f"model       {r.model.value}" in text
    assert f"keyframes {r.n_keyframes}" in text
    assert f"features {r.n_features}" in text


def test_real_metric_frame_records_render_their_scale() -> None:
    """The scale keys the monitor reads are the ones the node publishes, with a ground-plane scale source."""
    import dataclasses

    from epi_vo.core.camera import CameraModel
    from epi_vo.core.config import VoConfig
    from epi_vo.core.pipeline import VoPipeline
    from epi_vo.core.status import frame_status
    from epi_vo.io import bagio
    from epi_vo.io.msgconv import decode_frame

    pipe = VoPipeline(dataclasses.replace(VoConfig(), scale_source="ground_plane", camera_height_m=0.45))
    s = MonitorState()
    seen_vo = False
    with bagio.open_camera_bag(REPO / "bags" / "ground_robot" / "bag") as bag:
        for f in bag.iter_frames():
            r = pipe.process(decode_frame(f.image_msg, bag.image_is_compressed),
                             CameraModel.from_camera_info(f.camera_info_msg), f.stamp_ns)
            st = frame_status(r, "vo_node", "cam")
            s = s.update_from_frame(st.name, int(st.level), st.message, st.values, float(f.index))
            if not r.scale.metric:
                assert "ground_plane: not established yet" in s.render_text() and s.units == "vo"
                seen_vo = True
            if (r.scale.metric and math.isfinite(r.scale.floor_pitch_deg)) or f.index >= 30:
                break
    assert seen_vo and r.scale.metric, "metric scale from the floor within the first frames of ground_robot"
    text = s.render_text()
    assert s.units == "m"
    assert (f"  scale       ground_plane: metric, {r.scale.scale:.4g} m/unit ±{100 * r.scale.rel_std:.1f} %"
            in text.splitlines())
    assert f"pitch {r.scale.floor_pitch_deg:.2f} deg  roll {r.scale.floor_roll_deg:.2f} deg" in text


# -- the command, against real processes ------------------------------------------------------------------

def _monitor(env: dict[str, str], *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epi_vo.cli", "monitor", *args], env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.parametrize("mode", [["--once"], []], ids=["once", "live"])
def test_no_node_times_out_with_one_line(mode: list[str]) -> None:
    with ros_test_env() as ros_env:
        proc = _monitor(ros_env.env, *mode, "--timeout", "2")
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert "no VO status" in lines[0] and "within 2 s" in lines[0] and f"ROS_DOMAIN_ID={ros_env.domain_id}" in lines[0]


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _ints(text: str, label: str) -> list[int]:
    return [int(v) for v in re.findall(rf"\b{label}\s+(\d+)\b", text)]


def _floats(text: str, label: str) -> list[float]:
    return [float(v) for v in re.findall(rf"\b{label}\s+(-?\d+\.\d+)", text)]


def test_monitor_against_a_running_node(ros: RosSession) -> None:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    probe = rclpy.create_node("probe_monitor", context=ros.context)
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(probe)
    statuses: list[Any] = []
    probe.create_subscription(DiagnosticArray, "vo/frame_status", lambda m: statuses.extend(m.status),
                              QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))

    def frame_records() -> list[dict[str, str]]:
        return [{kv.key: kv.value for kv in s.values} for s in statuses if s.name == f"{NODE}: tracking"]

    # A long watchdog timeout: the gap between loops of the player must not turn the input status 'stalled'.
    # --loop keeps frames coming however slow start-up is.
    node = subprocess.Popen([sys.executable, "-m", "epi_vo.ros.node", "--ros-args", "-p", "image_transport:=compressed",
                             "-p", "process_every_frame:=true", "-p", "qos_reliability:=reliable",
                             "-p", "watchdog_timeout_s:=60.0"],
                            env=ros.env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True)
    player = subprocess.Popen([sys.executable, "-m", "epi_vo.cli", "play", str(BAG), "--rate", "1.0", "--loop"],
                              env=ros.env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True)
    live: subprocess.Popen[str] | None = None
    try:
        assert spin_until(executor, lambda: len(frame_records()) >= 3, WAIT_S), "no frame status from vo_node"

        once = _monitor(ros.env, "--once", "--timeout", str(WAIT_S), timeout=2 * WAIT_S)
        assert once.returncode == 0, once.stderr
        assert "Traceback" not in once.stderr
        out = once.stdout
        assert out.startswith(NODE) and re.search(r"level\s+(OK|WARN)\b", out), out
        assert re.search(r"health\s+tracking (OK|WARN) \(.*\)  input OK \(receiving images\)  extrinsic ", out), out
        assert re.search(r"state\s+(tracking|initializing|rotation_only)\s+frame \d+", out), out
        state_line = re.search(r"^  state\s+\S+\s+frame (\d+)", out, re.MULTILINE)
        assert state_line is not None, out
        index, (features,) = int(state_line.group(1)), _ints(out, "features")
        assert 50 <= features <= 2000
        assert 0.0 < _floats(out, "input")[0]  # Hz: the player's rate as the node measured it
        # The numbers are those the node published for that frame (once the probe has its status too).
        spin_until(executor, lambda: any(r["index"] == str(index) for r in frame_records()), WAIT_S)
        published = [r for r in frame_records() if r["index"] == str(index)]
        assert any(int(r["n_features"]) == features and f"inliers {r['n_inliers']}  " in out
                   for r in published), (out, published)

        # Live mode, stdout not a terminal: plain snapshots (one a second) until Ctrl-C, then exit 0. Ctrl-C
        # comes once the snapshots show what is checked below (or after WAIT_S), however slow the machine.
        live = subprocess.Popen([sys.executable, "-m", "epi_vo.cli", "monitor", "--timeout", str(WAIT_S)],
                                env=ros.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        reader = _Reader(live)
        wait_until(lambda: _live_view_complete(_snapshots(reader.text())) or live.poll() is not None, WAIT_S)
        live.send_signal(signal.SIGINT)
        returncode = live.wait(timeout=WAIT_S)
        stdout, stderr = reader.finish()
        assert returncode == 0, stderr
        assert "Traceback" not in stderr
        snapshots = _snapshots(stdout)
        assert len(snapshots) >= LIVE_SNAPSHOTS, stdout
        assert any(re.search(r"state\s+tracking\b", s) for s in snapshots), stdout
        inliers = [v for s in snapshots for v in _ints(s, "inliers")]
        ratios = [v for s in snapshots for v in _floats(s, "inlier ratio")]
        assert inliers and max(inliers) >= 30 and all(0.0 <= r <= 1.0 for r in ratios)
        assert _floats(snapshots[-1], "distance")[0] > 0.0  # odometry arrived and moved
        assert _ints(snapshots[-1], "messages")[0] >= 2
    finally:
        if live is not None:
            _stop(live)
        _stop(player)
        _stop(node)
        executor.shutdown()
        probe.destroy_node()


LIVE_SNAPSHOTS = 3


def _snapshots(stdout: str) -> list[str]:
    """The complete snapshots of the live monitor's plain output (each ends with an empty line)."""
    return [s for s in stdout.split("\n\n")[:-1] if s.startswith(NODE)]


def _live_view_complete(snapshots: list[str]) -> bool:
    """Enough snapshots, one of them tracking with inliers, and the latest with odometry that moved."""
    if len(snapshots) < LIVE_SNAPSHOTS or not any(re.search(r"state\s+tracking\b", s) for s in snapshots):
        return False
    if max((v for s in snapshots for v in _ints(s, "inliers")), default=0) < 30:
        return False
    distance, messages = _floats(snapshots[-1], "distance"), _ints(snapshots[-1], "messages")
    return bool(distance and distance[0] > 0.0 and messages and messages[0] >= 2)


class _Reader:
    """Collects a child's stdout and stderr in threads while it runs (``text()``: stdout so far)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self._parts: dict[str, list[str]] = {"out": [], "err": []}
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._pump, args=(stream, key), daemon=True)
                         for stream, key in ((proc.stdout, "out"), (proc.stderr, "err"))]
        for t in self._threads:
            t.start()

    def _pump(self, stream: Any, key: str) -> None:
        for line in iter(stream.readline, ""):
            with self._lock:
                self._parts[key].append(line)

    def text(self) -> str:
        with self._lock:
            return "".join(self._parts["out"])

    def finish(self) -> tuple[str, str]:
        """After the child exited: everything it wrote (stdout, stderr)."""
        for t in self._threads:
            t.join(timeout=WAIT_S)
        with self._lock:
            return "".join(self._parts["out"]), "".join(self._parts["err"])


def test_monitor_follows_the_namespace_of_its_odometry_topic(ros: RosSession) -> None:
    """Two nodes named vo_node in /robot1 and /robot2: `--odometry-topic /robot2/vo/odometry` shows robot2's
    health (/diagnostics) and frames (/robot2/vo/frame_status), and the other one is not mistaken for it (nor
    listed)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    probe = rclpy.create_node("probe_monitor_ns", context=ros.context)
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(probe)
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    pub = probe.create_publisher(DiagnosticArray, "/diagnostics", qos)
    frame_pubs = {ns: probe.create_publisher(DiagnosticArray, f"{ns}/vo/frame_status", qos)
                  for ns in ("/robot1", "/robot2")}

    def status(name: str, level: int, hardware_id: str, values: dict[str, str]) -> Any:
        st = DiagnosticStatus(level=bytes([level]), name=name, message="tracking", hardware_id=hardware_id)
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        return st

    def publish() -> None:
        health = DiagnosticArray()
        for ns, level, inliers in (("/robot1", 2, "11"), ("/robot2", 0, "222")):
            health.status.append(status(f"{ns}/vo_node: tracking", level, f"{ns[1:]}_camera",
                                        {"frames_processed": "5"}))
            frame = DiagnosticArray()
            frame.status.append(status(f"{ns}/vo_node: tracking", level, f"{ns[1:]}_camera",
                                       _record(n_inliers=inliers)))
            frame_pubs[ns].publish(frame)
        pub.publish(health)

    probe.create_timer(0.1, publish)
    monitor = subprocess.Popen([sys.executable, "-m", "epi_vo.cli", "monitor", "--once", "--timeout", str(WAIT_S),
                                "--odometry-topic", "/robot2/vo/odometry"], env=ros.env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        assert spin_until(executor, lambda: monitor.poll() is not None, 2 * WAIT_S)
        out, err = monitor.communicate()
        assert monitor.returncode == 0, err
        assert out.startswith("/robot2/vo_node  (hardware robot2_camera)"), out
        assert "inliers 222" in out and "robot1" not in out
    finally:
        _stop(monitor)
        executor.shutdown()
        probe.destroy_node()


def test_monitor_once_on_a_stalled_ground_plane_node_prints_its_scale_source(ros: RosSession) -> None:
    """A vo_node with scale_source ground_plane whose camera never delivers: `epi-vo monitor --once` says the
    source it was given and that it is not established, and that no image came (not 'scale none')."""
    from ros_fixtures import NodeProcess

    with NodeProcess(ros.env, "-p", "scale_source:=ground_plane", "-p", "camera_height_m:=0.45",
                     "-p", "watchdog_timeout_s:=0.3") as node:
        once = _monitor(ros.env, "--once", "--timeout", str(WAIT_S), timeout=2 * WAIT_S)
    assert once.returncode == 0, (once.stderr, node.stderr)
    out = once.stdout
    assert "  scale       ground_plane: not established yet: VO units (position held)" in out.splitlines(), out
    assert re.search(r"input (WARN|STALE) \(no image received yet\)", out), out
    assert re.search(r"state\s+n/a", out) and "Traceback" not in once.stderr
