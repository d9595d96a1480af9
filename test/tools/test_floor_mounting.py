"""``ground_plane`` claims metres only from a floor the declared mounting allows: the ground-robot bag with
its camera turned upside down (every image rotated by 180 deg, the floor above the image's middle).

The bag is written into tmp_path from bags/ground_robot: each JPEG decoded, rotated and encoded again, the
ground truth turned with the camera (a rotation by 180 deg about the optical axis).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from epi_vo.core.camera import CameraModelCache
from epi_vo.core.config import VoConfig
from epi_vo.core.odometry import T_base_cam_from_params
from epi_vo.core.pipeline import VoPipeline
from epi_vo.io import bagio, tum
from epi_vo.io.msgconv import decode_frame
from epi_vo.io.odometry_bag import read_odometry
from epi_vo.tools.replay import ReplaySummary, run_replay

REPO = Path(__file__).resolve().parents[2]
SOURCE = REPO / "bags" / "ground_robot" / "bag"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
GROUND_PLANE = dataclasses.replace(VoConfig(), scale_source="ground_plane", camera_height_m=0.45)
R_Z180 = np.diag([-1.0, -1.0, 1.0])  # the optical frame turned by 180 deg about its z (viewing) axis


def _turned_pose(msg: Any) -> None:
    """A camera pose of the ground truth (frame 0's optical frame) for the camera turned by R_Z180."""
    from epi_vo.core.transforms import quat_xyzw_from_rotation, rotation_from_quat_xyzw

    o, p = msg.pose.orientation, msg.pose.position
    R = R_Z180 @ rotation_from_quat_xyzw([o.x, o.y, o.z, o.w]) @ R_Z180
    o.x, o.y, o.z, o.w = (float(v) for v in quat_xyzw_from_rotation(R))
    p.x, p.y = -p.x, -p.y


@pytest.fixture(scope="module")
def upside_down_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """bags/ground_robot with every image rotated by 180 deg (the principal point is the image centre, so
    camera_info holds), its ground truth turned with it; the wheel topic copied as it is."""
    bag = tmp_path_factory.mktemp("upside_down") / "bag"
    with AnyReader([SOURCE], default_typestore=TYPESTORE) as reader, \
            Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=TYPESTORE) for c in reader.connections}
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == "sensor_msgs/msg/CompressedImage":
                gray = cv2.imdecode(np.asarray(msg.data), cv2.IMREAD_GRAYSCALE)
                ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(gray[::-1, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
                assert ok
                msg.data = buf.reshape(-1)
            elif conn.msgtype == "geometry_msgs/msg/PoseStamped":
                _turned_pose(msg)
            writer.write(conns[conn.topic], t, bytes(TYPESTORE.serialize_cdr(msg, conn.msgtype)))
    return bag


@pytest.fixture(scope="module")
def upside_down(upside_down_bag: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[ReplaySummary, Path]:
    out = tmp_path_factory.mktemp("upside_down_out")
    return run_replay(upside_down_bag, out, GROUND_PLANE), out


def test_an_upside_down_camera_claims_no_metres_and_says_why(upside_down: tuple[ReplaySummary, Path]) -> None:
    """Before: metres from frame 179 at 3.3x the true scale (step scale 3.297), no warning. The planes below
    the camera within 35 deg of its -y axis (the declared mounting: a level camera) have the walls above the
    real floor beneath them; the floor carries the scene, so none is the floor."""
    s, out = upside_down
    assert s.frames == 300 and s.tracked_percent >= 99.0  # the VO itself is fine upside down
    assert s.metric_from_frame is None and s.units == "vo"
    recs = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert not any(r["metric_scale"] for r in recs)
    # Nothing is published as metres: vo/odometry holds the position where tracking started with the 'unknown'
    # variance; the motion, in VO units, is on vo/odometry/vo_units (the records' poses).
    fused = read_odometry(out / "output.mcap")
    vo = read_odometry(out / "output.mcap", "/vo/odometry/vo_units")
    assert len(fused.stamps_ns) == len(vo.stamps_ns) == 300 and not fused.positions.any()
    assert np.all(fused.pose_covariance[:, 0, 0] >= 1e4) and np.all(fused.twist_covariance[:, 0, 0] >= 1e4)
    assert np.linalg.norm(vo.positions[-1]) > 1.0 and vo.frame_id == "odom_vo_units"
    assert all(r["units"] == "vo" for r in recs) and max(np.linalg.norm(r["position"]) for r in recs) > 1.0
    # Where a plane had the points a floor needs, the reason says what was wrong with it.
    said = [r for r in recs if "well beneath it; the floor carries the scene" in r["scale_reason"]]
    assert sum(r["is_keyframe"] for r in said) >= 5
    assert all("is the camera mounted as declared?" in r["scale_reason"] for r in said)
    assert all(r["scale_reason"].endswith("(VO units)") for r in recs)


def _replay_declared(bag: Path, T_base_cam: np.ndarray) -> tuple[list[float], list[float]]:
    """The pipeline over ``bag`` with the mounting declared (as vo_node does from TF or camera_rpy): the
    camera's step lengths where metres are published, and the ground truth's at the same frames."""
    pipe = VoPipeline(GROUND_PLANE)
    pipe.set_mounting(T_base_cam)
    cameras = CameraModelCache()
    positions: dict[int, np.ndarray] = {}
    with bagio.open_camera_bag(bag) as b:
        for f in b.iter_frames():
            r = pipe.process(decode_frame(f.image_msg, b.image_is_compressed), cameras.get(f.camera_info_msg),
                             f.stamp_ns)
            if r.scale.metric and r.has_pose:
                positions[r.stamp_ns] = r.position
    stamps_s, xyz, _ = tum.read_tum(REPO / "bags" / "ground_robot" / "groundtruth_tum.txt")
    keys = sorted(positions)
    gt = xyz[[int(np.argmin(np.abs(stamps_s - k * 1e-9))) for k in keys]]
    est = [float(np.linalg.norm(positions[b] - positions[a])) for a, b in itertools.pairwise(keys)]
    true = [float(np.linalg.norm(b - a)) for a, b in itertools.pairwise(gt)]
    return est, true


def test_an_upside_down_camera_declared_so_gets_metres(upside_down_bag: Path) -> None:
    """The same bag with the mounting declared upside down (camera_rpy roll 180 deg, and the bag's 15 deg
    pitch down): the floor is sought above the image's middle, and the metres are right."""
    est, true = _replay_declared(upside_down_bag, T_base_cam_from_params([0.0, 0.0, 0.45],
                                                                         [np.pi, np.radians(15.0), 0.0]))
    assert len(est) >= 250
    ratio = np.array(est) / np.maximum(np.array(true), 1e-9)
    assert float(np.median(ratio)) == pytest.approx(1.0, abs=0.03)
