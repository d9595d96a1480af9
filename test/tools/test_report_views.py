"""epi_vo.tools.report_views: the report's trajectory views, base_link in odom when the run knows the camera
extrinsic, the first camera's optical frame otherwise. Known answers on a synthetic run, and the bundled ground
robot bag (a flat drive with a camera pitched 15 degrees down) replayed with its extrinsic."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from exact_calibration import exact
from scipy.spatial.transform import Rotation

from epi_vo.core.errors import ReportError
from epi_vo.core.odometry import T_base_cam_from_params
from epi_vo.io import tum
from epi_vo.io.node_options import CameraExtrinsic
from epi_vo.io.odometry_bag import read_odometry
from epi_vo.tools.replay import extrinsic_record, run_replay
from epi_vo.tools.report_data import load_run
from epi_vo.tools.report_views import ODOM_FRAME, OPTICAL_FRAME, trajectory_views

REPO = Path(__file__).resolve().parents[2]
# The ground robot's mounting (bags/README.md): 0.2 m ahead of and 0.45 m above base_link, pitched 15 deg down.
MOUNTING = CameraExtrinsic((0.2, 0.0, 0.45), (0.0, math.radians(15.0), 0.0))
N = 20


def _synthetic(directory: Path, extrinsic: CameraExtrinsic | None) -> tuple[np.ndarray, np.ndarray]:
    """A run of N camera poses T_w_c (a curve, rotating about the optical y axis), its ground truth equal to
    it, and stats.json recording ``extrinsic``. Returns the poses (N, 4, 4) and the record indices."""
    directory.mkdir(parents=True)
    stamps = 10.0 + np.arange(N) / 15.0
    s = np.arange(N, dtype=float)
    pos = np.column_stack([np.sin(0.2 * s), 0.3 * np.cos(0.3 * s), 0.5 * s])
    rot = Rotation.from_rotvec(np.outer(0.03 * s, [0.0, 1.0, 0.0]))
    tum.write_tum(directory / "trajectory.tum", stamps, pos, rot.as_quat())
    tum.write_tum(directory / "groundtruth.tum", stamps, pos, rot.as_quat())
    records = [{"index": i, "stamp": float(stamps[i]), "stamp_ns": round(stamps[i] * 1e9), "state": "tracking",
                "has_pose": True, "is_keyframe": i % 5 == 0, "model": "E", "rh": 0.1, "n_features": 200,
                "n_tracked": 190, "n_inliers": 150, "inlier_ratio": 0.8, "median_parallax_deg": 1.0,
                "n_triangulated": 0, "positive_depth_ratio": None, "median_reproj_err_px": None,
                "timings_ms": {"total": 10.0}, "reason": "", "units": "m", "scale_source": "ground_plane",
                "metric_scale": True} for i in range(N)]
    (directory / "frames.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    T_base_cam = np.eye(4) if extrinsic is None else extrinsic.T_base_cam
    (directory / "stats.json").write_text(json.dumps({"extrinsic": extrinsic_record(extrinsic, T_base_cam)}))
    T = np.tile(np.eye(4), (N, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = rot.as_matrix(), pos
    return T, np.arange(N)


def test_with_the_extrinsic_the_views_are_base_link_in_odom(tmp_path: Path) -> None:
    T_w_c, _ = _synthetic(tmp_path / "run", MOUNTING)
    views = trajectory_views(load_run(tmp_path / "run"))
    T_bc = T_base_cam_from_params(MOUNTING.camera_xyz, MOUNTING.camera_rpy)
    T_odom_base = T_bc @ T_w_c @ np.linalg.inv(T_bc)  # REP-105: odom is base_link at the first image
    p, R = T_odom_base[:, :3, 3], T_odom_base[:, :3, :3]
    np.testing.assert_allclose(views.top.est, p[:, [0, 1]], atol=1e-9)  # x forward, y left
    np.testing.assert_allclose(views.side.est, p[:, [0, 2]], atol=1e-9)  # x forward, z up
    np.testing.assert_allclose(views.top.heading, R[:, [0, 1], 0], atol=1e-9)  # base_link's x axis
    np.testing.assert_allclose(views.side.heading, R[:, [0, 2], 0], atol=1e-9)
    np.testing.assert_allclose(views.top.keyframes, p[::5, :2], atol=1e-9)
    # The ground truth is the estimate: through the alignment and the extrinsic it lands on it.
    np.testing.assert_allclose(views.top.gt, views.top.est, atol=1e-6)
    np.testing.assert_allclose(views.side.gt, views.side.est, atol=1e-6)
    assert views.frame == ODOM_FRAME and views.heading_label == "heading (base_link x, forward)"
    assert (views.top.xlabel, views.top.ylabel, views.side.ylabel) == ("x (forward) [m]", "y (left) [m]",
                                                                       "z (up) [m]")


def test_without_the_extrinsic_the_views_stay_in_the_optical_frame(tmp_path: Path) -> None:
    T_w_c, _ = _synthetic(tmp_path / "run", None)
    views = trajectory_views(load_run(tmp_path / "run"))
    p = T_w_c[:, :3, 3]
    np.testing.assert_allclose(views.top.est, p[:, [0, 2]], atol=1e-12)  # x right, z forward
    np.testing.assert_allclose(views.side.est, np.column_stack([p[:, 2], -p[:, 1]]), atol=1e-12)  # z, -y up
    np.testing.assert_allclose(views.top.heading, T_w_c[:, [0, 2], 2], atol=1e-12)  # the optical axis
    assert views.frame == OPTICAL_FRAME and views.heading_label == "heading (optical axis)"


def test_a_broken_extrinsic_record_is_a_report_error(tmp_path: Path) -> None:
    _synthetic(tmp_path / "run", MOUNTING)
    stats = json.loads((tmp_path / "run" / "stats.json").read_text())
    stats["extrinsic"]["T_base_cam"][0][0] = 3.0  # no rotation
    (tmp_path / "run" / "stats.json").write_text(json.dumps(stats))
    with pytest.raises(ReportError, match=r"stats.json: extrinsic.T_base_cam is no rigid 4x4 transform"):
        trajectory_views(load_run(tmp_path / "run"))


def test_a_flat_drive_with_a_pitched_camera_plots_flat(tmp_path: Path) -> None:
    """ground_robot replayed with its mounting declared (the parameters a user gives): the replay records the
    extrinsic, publishes base_link in odom with it, and the report draws the flat drive flat (height range
    under 1 % of the distance covered); in the camera's optical frame the same run climbs a 15 degree ramp."""
    cfg = exact(scale_source="ground_plane", camera_height_m=0.45)  # the bag's camera is exact
    summary = run_replay(REPO / "bags" / "ground_robot" / "bag", tmp_path / "out", cfg, extrinsic=MOUNTING)
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["extrinsic"]["source"] == "parameters"
    assert stats["extrinsic"]["camera_rpy"] == [0.0, math.radians(15.0), 0.0]
    np.testing.assert_allclose(stats["extrinsic"]["T_base_cam"], MOUNTING.T_base_cam, atol=1e-12)
    run = load_run(tmp_path / "out")
    views = trajectory_views(run)
    extent = float(np.ptp(views.top.est, axis=0).max())
    assert extent > 8.0 and summary.units == "m"
    assert np.ptp(views.side.est[:, 1]) < 0.01 * extent, (np.ptp(views.side.est[:, 1]), extent)
    assert np.ptp(views.side.gt[:, 1]) < 0.01 * extent
    optical = trajectory_views(dataclasses.replace(run, stats=None))
    assert np.ptp(optical.side.est[:, 1]) > 0.2 * float(np.ptp(optical.top.est, axis=0).max())
    # /vo/odometry is base_link in odom with that extrinsic: flat too; its covariance judged with it.
    odometry = read_odometry(tmp_path / "out" / "output.mcap")
    assert np.ptp(odometry.positions[:, 2]) < 0.01 * extent
    assert summary.metrics is not None and 1.0 < summary.metrics["nees_pos"] < 10.0
