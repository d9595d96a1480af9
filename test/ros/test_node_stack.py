"""vo_node in a robot stack: camera extrinsic from TF (fake buffer) or the parameters, runtime parameter
changes, image_transport auto, diagnostics named by namespace with one time base.

Real DDS on loopback with this test's own domain (test/ros_fixtures.py); in-process nodes share the
test's rclpy context, subprocess nodes get its environment.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_fixtures import NodeProcess, ProbeBase, RosSession, bag_frames_rclpy, call_service, rclpy_session

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "general_motion" / "bag"
WAIT_S = 120.0  # bound on a wait for another process or DDS; it matters only when the condition never comes
CAMERA_FRAME = "camera_optical_frame"  # the bag's image header.frame_id
# A camera 0.1 m forward, 0.05 m right and 0.3 m up of base_link, looking forward (optical -> base rotation).
TF_XYZ = (0.1, -0.05, 0.3)
SEND_BATCH = 50  # frames published before waiting for their odometry: under the node's qos_depth (100)


@pytest.fixture(scope="module")
def ros() -> Iterator[RosSession]:
    with rclpy_session() as session:
        yield session


# -- the extrinsic resolver with a fake tf2 buffer (no DDS) ----------------------------------------------------
class FakeBuffer:
    """tf2_ros.Buffer's lookup_transform: 'not available' (LookupError) until ``ready``; records the calls."""

    def __init__(self, ready: bool = False) -> None:
        self.ready = ready
        self.calls: list[tuple[str, str]] = []

    def lookup_transform(self, target: str, source: str, time: Any) -> Any:
        from geometry_msgs.msg import TransformStamped

        from epi_vo.core.odometry import R_BASE_OPTICAL
        from epi_vo.core.transforms import quat_xyzw_from_rotation

        self.calls.append((target, source))
        if not self.ready or source != CAMERA_FRAME:
            msg = f'"{target}" passed to lookupTransform argument target_frame does not exist'
            raise LookupError(msg)
        ts = TransformStamped()
        ts.header.frame_id, ts.child_frame_id = target, source
        t = ts.transform.translation
        t.x, t.y, t.z = TF_XYZ
        q = ts.transform.rotation
        q.x, q.y, q.z, q.w = (float(v) for v in quat_xyzw_from_rotation(R_BASE_OPTICAL))
        return ts


def _lookup(buffer: FakeBuffer) -> Any:
    from epi_vo.ros.node_tf import BufferLookup

    return BufferLookup(buffer, (LookupError,), lambda: None)


T_PARAMS = np.diag([1.0, 1.0, 1.0, 1.0])


def test_resolver_uses_tf_once_it_arrives_within_the_bound() -> None:
    from epi_vo.core.odometry import R_BASE_OPTICAL
    from epi_vo.ros.node_tf import ExtrinsicResolver

    buf = FakeBuffer()
    res = ExtrinsicResolver(_lookup(buf), "base_link", 2.0, T_PARAMS, "camera_xyz parameters")
    assert res.waiting_text(10.0) == ""
    assert res.poll(CAMERA_FRAME, 10.0) is None
    assert res.poll(CAMERA_FRAME, 11.5) is None
    assert res.waiting_text(11.5) == "waiting for TF base_link <- camera_optical_frame (1.5 s of tf_timeout_s=2 s)"
    buf.ready = True
    ext = res.poll(CAMERA_FRAME, 11.9)
    assert ext is not None and ext.source == "tf" and not ext.warn
    np.testing.assert_allclose(ext.T_base_cam[:3, 3], TF_XYZ, atol=1e-12)
    np.testing.assert_allclose(ext.T_base_cam[:3, :3], R_BASE_OPTICAL, atol=1e-12)
    assert ext.text == "camera extrinsic from TF base_link <- camera_optical_frame (xyz 0.100 -0.050 0.300 m)"
    assert buf.calls == [("base_link", CAMERA_FRAME)] * 3


@pytest.mark.parametrize(("lookup", "frame_id", "timeout_s", "why", "warn"), [
    ("none", CAMERA_FRAME, 2.0, "tf2_ros is not importable", True),
    ("never", CAMERA_FRAME, 2.0, "no TF base_link <- camera_optical_frame within tf_timeout_s=2 s; TF is still "
                                 "looked up at every frame", True),
    ("never", "", 2.0, "the image header.frame_id is empty: no TF frame to look up", True),
    ("ready", CAMERA_FRAME, 0.0, "tf_timeout_s is 0: TF not looked up", False),
])
def test_resolver_falls_back_to_the_parameters_saying_why(lookup: str, frame_id: str, timeout_s: float, why: str,
                                                          warn: bool) -> None:
    from epi_vo.ros.node_tf import ExtrinsicResolver

    buf = FakeBuffer(ready=lookup == "ready")
    res = ExtrinsicResolver(None if lookup == "none" else _lookup(buf), "base_link", timeout_s, T_PARAMS,
                            "camera_xyz=[0.0, 0.0, 0.0] parameters")
    ext = res.poll(frame_id, 100.0)
    if ext is None:  # waiting for TF: the bound decides
        assert res.poll(frame_id, 101.99) is None
        ext = res.poll(frame_id, 102.0)
    assert ext is not None and ext.source == "parameters" and ext.warn is warn
    assert ext.T_base_cam is T_PARAMS
    assert ext.text == f"camera extrinsic from camera_xyz=[0.0, 0.0, 0.0] parameters ({why})"
    if timeout_s == 0.0:
        assert buf.calls == []  # not even asked


def test_transform_message_to_matrix() -> None:
    from geometry_msgs.msg import Transform

    from epi_vo.ros.node_tf import T_from_transform

    t = Transform()
    t.translation.x, t.translation.y, t.translation.z = 1.0, 2.0, 3.0
    t.rotation.z, t.rotation.w = np.sin(np.pi / 4), np.cos(np.pi / 4)  # 90 deg about z
    T = T_from_transform(t)
    np.testing.assert_allclose(T, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-12)


# -- helpers for the DDS tests -----------------------------------------------------------------------------------
class Probe(ProbeBase):
    """A test-side node: camera publishers and subscriptions to the VO outputs (reliable, deep queues)."""

    def __init__(self, ros: RosSession, name: str, namespace: str = "") -> None:
        from sensor_msgs.msg import CameraInfo, CompressedImage, PointCloud2

        super().__init__(ros, name, namespace)
        self.points: list[Any] = []
        self.node.create_subscription(PointCloud2, "vo/points", self.points.append, self.qos)
        self.pub_img = self.node.create_publisher(CompressedImage, "camera/image_raw/compressed", self.qos)
        self.pub_info = self.node.create_publisher(CameraInfo, "camera/camera_info", self.qos)

    def statuses(self, suffix: str) -> list[Any]:
        return [s for a in self.diag for s in a.status if s.name.endswith(suffix)]

    def frame_statuses(self) -> list[Any]:
        return [s for a in self.frame_status for s in a.status if s.name.endswith(": tracking")]

    def summaries(self) -> list[dict[str, str]]:
        """Each /diagnostics array of the node as one dict: every concern's key/values, its message as
        '<concern>_message', the hardware id."""
        merged = []
        for a in self.diag:
            d: dict[str, str] = {}
            for st in a.status:
                concern = st.name.rpartition(": ")[2]
                d.update({kv.key: kv.value for kv in st.values}, hardware_id=st.hardware_id)
                d[f"{concern}_message"] = st.message
            merged.append(d)
        return merged

    def send(self, frames: list[tuple[Any, Any]]) -> None:
        """Publish (image, camera_info) pairs once both publishers are matched."""
        self.publish_pairs(self.pub_img, self.pub_info, frames)


def _values(status: Any) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def _position(msg: Any) -> np.ndarray:
    p = msg.pose.pose.position
    return np.array([p.x, p.y, p.z])


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def _assert_status_pose_is_the_odometry(probe: Probe) -> None:
    """The `position` of every frame status is the odometry's (odom -> base_link), and says so."""
    by_stamp = {_stamp_ns(m.header.stamp): m for m in probe.odom}
    n = 0
    for s in probe.frame_statuses():
        v = _values(s)
        m = by_stamp.get(int(v["stamp_ns"]))
        if m is None:
            continue
        assert v["position_frame"] == "odom -> base_link"
        np.testing.assert_allclose([float(x) for x in v["position"].split()], _position(m), rtol=1e-5, atol=1e-6)
        n += 1
    assert n >= 5


def _assert_points_in_front(probe: Probe, T_base_cam: np.ndarray) -> None:
    """Every cloud, taken back into the camera with this extrinsic, lies in front of it (z > 0)."""
    from epi_vo.core.transforms import invert_T, make_T, rotation_from_quat_xyzw
    from epi_vo.io.msgconv import read_points_xyz

    # Each cloud is in the frame of its units: odom in metres, odom_vo_units (vo/odometry/vo_units') otherwise.
    assert probe.spin_until(lambda: len(probe.odom_vo_units) >= len(probe.odom))
    by_frame = {"odom": probe.odom, "odom_vo_units": probe.odom_vo_units}
    assert probe.points
    for cloud in probe.points:
        pts = read_points_xyz(cloud).astype(np.float64)
        m = {_stamp_ns(m.header.stamp): m for m in by_frame[cloud.header.frame_id]}[_stamp_ns(cloud.header.stamp)]
        q = m.pose.pose.orientation
        T_odom_base = make_T(rotation_from_quat_xyzw([q.x, q.y, q.z, q.w]), _position(m))
        T_cam_odom = invert_T(T_base_cam) @ invert_T(T_odom_base)
        z = (pts @ T_cam_odom[:3, :3].T + T_cam_odom[:3, 3])[:, 2]
        assert np.mean(z > 0) >= 0.99


def _in_process_node(ros: RosSession, buffer: FakeBuffer, **params: Any) -> Any:
    from rclpy.parameter import Parameter

    from epi_vo.ros.node import VoNode

    overrides = [Parameter(k, value=v) for k, v in {
        "image_transport": "compressed", "process_every_frame": True, "qos_reliability": "reliable",
        "qos_depth": 100, "camera_xyz": [0.2, 0.0, 0.5], **params}.items()]
    return VoNode(tf_lookup=_lookup(buffer), context=ros.context, parameter_overrides=overrides)


# -- TF lookup through a real node -----------------------------------------------------------------------------
def test_node_waits_for_tf_says_so_then_uses_it(ros: RosSession) -> None:
    from epi_vo.core.odometry import R_BASE_OPTICAL
    from epi_vo.core.transforms import make_T

    buf = FakeBuffer()
    node = _in_process_node(ros, buf, tf_timeout_s=600.0)
    probe = Probe(ros, "probe_tf_wait")
    probe.executor.add_node(node)
    frames = bag_frames_rclpy(BAG, 25)
    try:
        probe.send(frames[:1])
        waiting = "waiting for TF base_link <- camera_optical_frame"
        assert probe.spin_until(lambda: any(waiting in s["detail"] for s in probe.summaries())), probe.summaries()
        assert not probe.odom and buf.calls  # no frame goes through before the extrinsic is known
        s = next(s for s in probe.summaries() if waiting in s["detail"])
        assert s["extrinsic_source"] == "pending" and s["camera_frame"] == CAMERA_FRAME
        assert s["extrinsic_message"] == "waiting for TF"
        buf.ready = True
        probe.send(frames[1:])
        assert probe.spin_until(lambda: len(probe.odom) >= len(frames)), len(probe.odom)
        assert probe.spin_until(lambda: bool(probe.summaries()) and probe.summaries()[-1]["extrinsic_source"] == "tf")
        assert probe.summaries()[-1]["camera_xyz"] == "0.1 -0.05 0.3"
        assert probe.summaries()[-1]["extrinsic_message"] == "from TF"
        _assert_status_pose_is_the_odometry(probe)
        _assert_points_in_front(probe, make_T(R_BASE_OPTICAL, TF_XYZ))
        assert all(s.hardware_id == CAMERA_FRAME for s in probe.frame_statuses())  # the camera's frame id
    finally:
        probe.executor.remove_node(node)
        node.destroy_node()
        probe.close()


def test_node_falls_back_to_the_parameters_when_tf_never_comes(ros: RosSession) -> None:
    from epi_vo.core.odometry import T_base_cam_from_params

    buf = FakeBuffer()
    node = _in_process_node(ros, buf, tf_timeout_s=0.3, hardware_id="front_cam")
    probe = Probe(ros, "probe_tf_fallback")
    probe.executor.add_node(node)
    frames = bag_frames_rclpy(BAG, 20)
    try:
        probe.send(frames)
        assert probe.spin_until(lambda: len(probe.odom) >= len(frames)), len(probe.odom)
        assert probe.spin_until(lambda: probe.summaries() and probe.summaries()[-1]["extrinsic_source"]
                                == "parameters")
        assert probe.summaries()[-1]["camera_xyz"] == "0.2 0 0.5"
        assert probe.summaries()[-1]["extrinsic_message"] == "from parameters: TF not available"
        assert buf.calls and set(buf.calls) == {("base_link", CAMERA_FRAME)}
        _assert_points_in_front(probe, T_base_cam_from_params([0.2, 0.0, 0.5], [0.0, 0.0, 0.0]))
        assert all(s.hardware_id == "front_cam" for s in probe.statuses(""))  # the parameter overrides it
    finally:
        probe.executor.remove_node(node)
        node.destroy_node()
        probe.close()


class RecordingBroadcaster:
    """tf2_ros.TransformBroadcaster's sendTransform: keeps every TransformStamped sent."""

    def __init__(self) -> None:
        self.sent: list[Any] = []

    def sendTransform(self, transforms: Any) -> None:
        self.sent.extend(transforms if isinstance(transforms, list) else [transforms])


def test_map_frame_id_keeps_the_odometry_continuous_and_broadcasts_the_corrections(
        ros: RosSession, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """REP-105 with the window on (4 keyframes, in line: the replay's poses) in metres (the ground robot's
    camera 0.45 m above the floor, scale from the floor): with ``map_frame_id: map`` every frame's TF is
    odom -> base_link, and map -> odom with it once the odometry is metric (a correction in VO units moves
    no robot's map); map -> odom is the identity until the window's first correction and moves at it;
    map -> odom x vo/odometry is, frame by frame, the pose the replay publishes (which jumps by the
    corrections), and vo/odometry's own step at a corrected frame is not that jump. The summary says how far
    map is from odom. tf2_ros is not on PyPI: a recording broadcaster stands in."""
    import dataclasses
    import json

    from epi_vo.core.config import VoConfig
    from epi_vo.core.transforms import invert_T, make_T, rotation_angle_deg, rotation_from_quat_xyzw
    from epi_vo.io.odometry_bag import read_odometry
    from epi_vo.ros import node as node_module
    from epi_vo.tools.replay import run_replay

    bag = REPO / "bags" / "ground_robot" / "bag"
    params = {"ba_window_keyframes": 4, "ba_solver": "inline", "scale_source": "ground_plane",
              "camera_height_m": 0.45}
    run_replay(bag, tmp_path, dataclasses.replace(VoConfig(), **params))
    ref = read_odometry(tmp_path / "output.mcap")
    expected = {int(st): make_T(rotation_from_quat_xyzw(q), p)
                for st, p, q in zip(ref.stamps_ns, ref.positions, ref.quats_xyzw, strict=True)}
    records = [json.loads(line) for line in (tmp_path / "frames.jsonl").read_text().splitlines()]
    metric = {int(r["stamp_ns"]) for r in records if r["units"] == "m" and r["has_pose"]}
    n = len(records)
    assert len(metric) >= 200
    tf = RecordingBroadcaster()
    monkeypatch.setattr(node_module, "make_tf_broadcaster", lambda node: (tf, ""))
    node = _in_process_node(ros, FakeBuffer(), tf_timeout_s=0.0, camera_xyz=[0.0, 0.0, 0.0], map_frame_id="map",
                            **params)
    probe = Probe(ros, "probe_map_odom")
    probe.executor.add_node(node)
    try:
        frames = bag_frames_rclpy(bag, n)
        for i in range(0, n, SEND_BATCH):  # no more at once than the node's subscription queue holds
            probe.send(frames[i:i + SEND_BATCH])
            sent = min(i + SEND_BATCH, n)
            assert probe.spin_until(lambda sent=sent: len(probe.odom) >= sent), (len(probe.odom), sent)
        assert probe.spin_until(lambda: any("map_to_odom" in s for s in probe.summaries()))
    finally:
        probe.executor.remove_node(node)
        node.destroy_node()
        probe.close()

    def T_of(t: Any) -> np.ndarray:
        r, q = t.transform.translation, t.transform.rotation
        return make_T(rotation_from_quat_xyzw([q.x, q.y, q.z, q.w]), [r.x, r.y, r.z])

    map_odom = {_stamp_ns(t.header.stamp): T_of(t) for t in tf.sent
                if (t.header.frame_id, t.child_frame_id) == ("map", "odom")}
    odom_base = {_stamp_ns(t.header.stamp) for t in tf.sent
                 if (t.header.frame_id, t.child_frame_id) == ("odom", "base_link")}
    assert set(map_odom) == metric  # map -> odom in metres only
    poses = []
    for m in probe.odom:
        st = _stamp_ns(m.header.stamp)
        q = m.pose.pose.orientation
        T = make_T(rotation_from_quat_xyzw([q.x, q.y, q.z, q.w]), _position(m))
        assert st in odom_base
        if st not in metric:
            np.testing.assert_array_equal(T[:3, 3], np.zeros(3))  # held where tracking started
            np.testing.assert_array_equal(expected[st][:3, 3], np.zeros(3))
            continue
        np.testing.assert_allclose(map_odom[st] @ T, expected[st], atol=1e-6)
        poses.append((st, T, map_odom[st]))
    moved = [rotation_angle_deg(M[:3, :3]) > 1e-6 or np.linalg.norm(M[:3, 3]) > 1e-9 for _, _, M in poses]
    assert not moved[0] and sum(moved) >= 30, sum(moved)
    first = moved.index(True)
    (s0, T0, _), (s1, T1, M1) = poses[first - 1], poses[first]
    own_step = invert_T(T0) @ T1
    published_step = invert_T(expected[s0]) @ expected[s1]  # the replay's, with the jump in it
    assert np.linalg.norm(own_step[:3, 3] - published_step[:3, 3]) > 0.5 * np.linalg.norm(M1[:3, 3])
    last = [s for s in probe.summaries() if "map_to_odom" in s][-1]["map_to_odom"]
    assert "(the status's units)" in last and float(last.split()[0]) > 0.0


# -- subprocess nodes -------------------------------------------------------------------------------------------
def test_auto_transport_namespace_extrinsic_fallback_and_warnings(ros: RosSession) -> None:
    """Defaults in a namespace: the status names the topics it waits on; compressed images are picked up
    (and said); statuses are named by the fully qualified node name with the camera frame as hardware id;
    without tf2_ros the parameters give the extrinsic and publish_tf is refused, each said once at WARN."""
    probe = Probe(ros, "probe_auto", namespace="/robot1")
    frames = bag_frames_rclpy(BAG, 15)
    try:
        with NodeProcess(ros.env, "-r", "__ns:=/robot1", "-p", "camera_xyz:=[0.2, 0.0, 0.5]",
                         "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100",
                         "-p", "process_every_frame:=true") as node:
            waiting = "/robot1/camera/image_raw or /robot1/camera/image_raw/compressed"
            assert probe.spin_until(lambda: any(s["input_message"] == "no image received yet" and s["image_topic"]
                                                == waiting and s["image_transport"] == "auto (none received yet)"
                                                for s in probe.summaries())), probe.summaries()
            probe.send(frames)
            assert probe.spin_until(lambda: len(probe.odom) >= len(frames)
                                    and len(probe.frame_statuses()) >= len(frames)), len(probe.odom)
            assert probe.spin_until(lambda: bool(probe.summaries())
                                    and probe.summaries()[-1]["image_transport"] == "compressed")
            summary = probe.summaries()[-1]
            assert summary["image_topic"] == "/robot1/camera/image_raw/compressed"
            assert summary["extrinsic_source"] == "parameters" and summary["camera_xyz"] == "0.2 0 0.5"
            assert summary["hardware_id"] == CAMERA_FRAME
            # The raw subscription is dropped once compressed images came first.
            assert probe.spin_until(lambda: probe.node.count_subscribers("/robot1/camera/image_raw") == 0)
        names = {s.name for s in probe.statuses("")}
        assert names == {f"/robot1/vo_node: {c}" for c in ("tracking", "input", "extrinsic", "scale")}
        assert {s.name for a in probe.frame_status for s in a.status} == {"/robot1/vo_node: tracking"}
        assert {s.hardware_id for s in probe.frame_statuses()} == {CAMERA_FRAME}
        _assert_status_pose_is_the_odometry(probe)
        err = node.stderr
        assert "Traceback" not in err
        fallback = [line for line in err.splitlines() if "camera extrinsic from camera_xyz=" in line]
        assert len(fallback) == 1 and fallback[0].startswith("[WARN]") and "(tf2_ros is not importable)" in fallback[0]
        no_tf = [line for line in err.splitlines() if "publish_tf is true" in line]
        assert len(no_tf) == 1 and no_tf[0].startswith("[WARN]") and "tf2_ros is not importable" in no_tf[0]
        assert err.count("image_transport auto: using compressed images from /robot1/camera/image_raw/compressed") == 1
    finally:
        probe.close()


def _set(probe: Probe, client: Any, **values: Any) -> Any:
    """Call vo_node's set_parameters service with one or more parameters; the list of results."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    req = SetParameters.Request()
    req.parameters = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
    return call_service(probe.executor, client, req, WAIT_S).results  # setting a value twice is harmless


def test_runtime_parameter_changes_are_validated_and_applied_at_the_next_frame(ros: RosSession) -> None:
    from rcl_interfaces.srv import GetParameters, SetParameters

    probe = Probe(ros, "probe_params")
    set_client = probe.node.create_client(SetParameters, "/vo_node/set_parameters")
    get_client = probe.node.create_client(GetParameters, "/vo_node/get_parameters")
    frames = bag_frames_rclpy(BAG, 40)
    try:
        with NodeProcess(ros.env, "-p", "image_transport:=compressed", "-p", "process_every_frame:=true",
                         "-p", "qos_reliability:=reliable", "-p", "qos_depth:=100") as node:
            assert set_client.wait_for_service(timeout_sec=WAIT_S), node.proc.stderr
            probe.send(frames[:15])
            assert probe.spin_until(lambda: len(probe.odom) >= 15)

            (ok,) = _set(probe, set_client, max_features=300)
            assert ok.successful, ok.reason
            (sift,) = _set(probe, set_client, frontend="sift")
            assert not sift.successful and "frontend='sift' (choose one of klt, orb)" in sift.reason
            (frame,) = _set(probe, set_client, frame_id="map")
            assert not frame.successful and "read-only" in frame.reason.lower()
            (low,) = _set(probe, set_client, max_features=5)
            assert not low.successful and low.reason
            (even,) = _set(probe, set_client, klt_window_px=16)
            assert not even.successful and "klt_window_px=16 (must be odd)" in even.reason
            req = GetParameters.Request(names=["max_features", "frontend", "frame_id", "klt_window_px"])
            got = call_service(probe.executor, get_client, req, WAIT_S).values
            assert (got[0].integer_value, got[1].string_value, got[2].string_value, got[3].integer_value) == \
                (300, "klt", "odom", 15)

            probe.send(frames[15:])
            # Each frame's status follows its odometry: wait for both.
            assert probe.spin_until(lambda: len(probe.odom) >= len(frames)
                                    and len(probe.frame_statuses()) >= len(frames)), len(probe.odom)
            assert probe.spin_until(lambda: bool(probe.summaries())
                                    and "max_features=300" in probe.summaries()[-1]["parameter_changes"])
        statuses = probe.frame_statuses()
        assert len(statuses) == len(frames)
        features = [int(_values(s)["n_features"]) for s in statuses]
        assert max(features[:15]) <= 200  # before the change
        changed = [i for i, s in enumerate(statuses) if "parameters changed (max_features=300)" in s.message]
        assert changed == [15], [s.message for s in statuses]  # applied at the next frame, once
        assert max(features[16:]) > 200  # the new limit is in force
        assert [int(_values(s)["index"]) for s in statuses] == list(range(len(frames)))
        # A new map from the last pose: odometry does not jump.
        np.testing.assert_allclose(_position(probe.odom[15]), _position(probe.odom[14]), atol=1e-9)
        assert any(s.message.startswith("tracking") for s in statuses[25:])
        assert "parameters applied at frame 15: max_features=300" in node.stderr
    finally:
        probe.close()


def test_watchdog_keeps_reporting_when_the_simulated_clock_stops(ros: RosSession) -> None:
    """use_sim_time and a /clock that stops: statuses keep coming (steady-clock timers), stamped with the
    node's (stopped) clock, the one time base of its diagnostics."""
    from builtin_interfaces.msg import Time
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    probe = Probe(ros, "probe_simtime")
    pub_clock = probe.node.create_publisher(Clock, "/clock", QoSProfile(depth=10,
                                                                        reliability=ReliabilityPolicy.RELIABLE))
    try:
        with NodeProcess(ros.env, "-p", "use_sim_time:=true", "-p", "watchdog_timeout_s:=0.3") as node:
            def sim_stamped() -> list[Any]:
                return [a for a in probe.diag if a.header.stamp.sec == 1234]

            def clock_and_check() -> bool:
                pub_clock.publish(Clock(clock=Time(sec=1234, nanosec=500_000_000)))
                return bool(sim_stamped())

            assert probe.spin_until(clock_and_check), node.proc.stderr
            n = len(probe.diag)
            # The clock has stopped: /diagnostics (once a second, steady clock) goes on.
            assert probe.spin_until(lambda: len(probe.diag) >= n + 3)
            later = probe.diag[n:]
            assert all(_stamp_ns(a.header.stamp) == 1234_500_000_000 for a in later)
            names = {s.name for a in later for s in a.status}
            assert names == {f"/vo_node: {c}" for c in ("tracking", "input", "extrinsic", "scale")}
            assert all(s.message == "no image received yet" for a in later for s in a.status
                       if s.name.endswith(": input"))
    finally:
        probe.close()


def test_vo_node_help_prints_the_parameters_and_never_starts_dds() -> None:
    """``vo_node --help`` prints every parameter with its default and exits 0 before rclpy starts: run
    with a DDS environment that would fail (an invalid domain id), it still succeeds."""
    env = {**os.environ, "ROS_DOMAIN_ID": "not-a-domain", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    out = subprocess.run([sys.executable, "-m", "epi_vo.ros.node", "--help"], env=env, capture_output=True,
                         text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: vo_node")
    for line in ("    max_features:", "    image_transport: auto", "    tf_timeout_s:", "    scale_source: none"):
        assert line in out.stdout
    assert "rcl" not in out.stderr.lower()
