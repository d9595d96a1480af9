"""config/ekf_epi_vo.yaml, robot_localization's EKF fed by epi_vo (docs/robot_localization.md).

robot_localization is C++ and not on PyPI: what can be checked here is (1) the file itself, against what
vo_node publishes and reads, and (2) the fusion it configures, with a small EKF in numpy in the model
robot_localization uses (omnidirectional, 2D: x, y, yaw and their rates, ``two_d_mode``): epi_vo's fields of
``odom0_config`` from a replay of the ground robot bag with the file's own ``vo_node`` parameters, their
published twist covariance, fused with the fields of ``odom1_config`` from wheel odometry simulated from the
ground truth with a known white noise.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from scipy.stats import chi2

from epi_vo.core.config import VoConfig
from epi_vo.core.transforms import make_T, rotation_from_quat_xyzw
from epi_vo.io import tum
from epi_vo.io.node_options import NodeOptions
from epi_vo.io.odometry_bag import OdometryTrack, read_odometry
from epi_vo.io.params import load_config, load_extrinsic, load_node_options
from epi_vo.tools.replay import run_replay

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "ekf_epi_vo.yaml"
BAG = REPO / "bags" / "ground_robot" / "bag"
FIELDS = ("x", "y", "z", "roll", "pitch", "yaw", "vx", "vy", "vz", "vroll", "vpitch", "vyaw", "ax", "ay", "az")
PLANAR_TWIST = ("vx", "vy", "vyaw")  # the rates two_d_mode estimates: the EKF's velocity state below
# The simulated wheels' white noise per image interval (1 sigma): vx, vy (the non-holonomic zero), vyaw.
WHEEL_SIGMA = np.array([0.02, 0.02, 0.005])
SEEDS = 20
# The EKF's process noise: the platform's accelerations (m/s^2, m/s^2, rad/s^2) as a velocity random walk,
# generous beside the measurements, so the rates come from them (robot_localization's default does the same).
ACCEL_SIGMA = np.array([0.5, 0.5, 0.5])
CHI2_99_3DOF = float(chi2.ppf(0.99, 3))


def _ekf() -> dict[str, Any]:
    return yaml.safe_load(CONFIG.read_text())["ekf_filter_node"]["ros__parameters"]


def _vo_node_publishes() -> set[str]:
    """The topics node.py publishes (string literals given to create_publisher / _create_output_publisher)."""
    tree = ast.parse((REPO / "epi_vo" / "ros" / "node.py").read_text())
    return {a.value for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
            and n.func.attr in ("create_publisher", "_create_output_publisher")
            for a in n.args if isinstance(a, ast.Constant) and isinstance(a.value, str)}


def test_the_file_names_what_vo_node_publishes_and_reads() -> None:
    ekf = _ekf()
    for source in ("odom0", "odom1", "imu0"):
        vector = ekf[f"{source}_config"]
        assert len(vector) == len(FIELDS) and all(isinstance(v, bool) for v in vector), source
        assert ekf[f"{source}_differential"] is False and ekf[f"{source}_relative"] is False  # no pose fused
        assert not any(vector[:6]), source  # twist (and the gyro), never a pose: two odometries in one frame
    assert ekf["odom0"] == "vo/odometry" and ekf["odom0"] in _vo_node_publishes()
    assert "vo/odometry/vo_units" in _vo_node_publishes()  # published, and fused by no source here
    assert not any(str(ekf[k]).endswith("vo_units") for k in ("odom0", "odom1", "imu0"))
    assert ekf["odom1"] == VoConfig().wheel_odometry_topic  # the wheels vo_node itself reads for metres
    opts = NodeOptions()
    assert (ekf["odom_frame"], ekf["base_link_frame"], ekf["world_frame"]) == (opts.frame_id, opts.child_frame_id,
                                                                              opts.frame_id)
    assert ekf["two_d_mode"] is True and ekf["publish_tf"] is True
    fused = {f for f, on in zip(FIELDS, ekf["odom0_config"], strict=True) if on}
    assert fused == set(PLANAR_TWIST)  # metres from the floor: the linear rates too (see the vo_node block)
    # The vo_node block is an epi_vo parameter file (epi_vo's own loader checks every name and value); its TF is
    # off while the EKF publishes odom -> base_link, and its metres do not come from the wheels the EKF fuses.
    cfg, node = load_config(CONFIG), load_node_options(CONFIG)
    assert cfg.scale_source == "ground_plane" and cfg.camera_height_m > 0
    assert node.publish_tf is False
    assert load_extrinsic(CONFIG) is not None


# ------------------------------------------------------------------------------------------------------------
# The fusion, in numpy.
def _wrap(a: Any) -> Any:
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def _planar(T: np.ndarray) -> np.ndarray:
    """x, y, yaw of base_link poses (N, 4, 4)."""
    return np.column_stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])])


def _body_rates(T: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """(N, 3) vx, vy, vyaw of base_link over each interval ending at a pose (row 0: zeros)."""
    rates = np.zeros((T.shape[0], 3))
    for k in range(1, T.shape[0]):
        D = np.linalg.inv(T[k - 1]) @ T[k]
        rates[k] = [D[0, 3] / dt[k - 1], D[1, 3] / dt[k - 1], math.atan2(D[1, 0], D[0, 0]) / dt[k - 1]]
    return rates


def fuse(dt: np.ndarray, measurements: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """A 2D EKF in robot_localization's omnidirectional model: state x, y, yaw, vx, vy, vyaw.

    At each image interval k the rates random-walk (ACCEL_SIGMA), are corrected by every source's measurement of
    that interval (``measurements``: (N, 3) rates and (N, 3, 3) covariances each), then move the pose over it
    (yaw at the interval's middle). Returns the poses (N, 3) and their covariances (N, 3, 3); pose 0 is the
    origin, known (odom is base_link at the first image)."""
    n = dt.size + 1
    x, P = np.zeros(6), np.diag([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])
    H = np.hstack([np.zeros((3, 3)), np.eye(3)])
    poses, covs = np.zeros((n, 3)), np.zeros((n, 3, 3))
    for k in range(1, n):
        h = dt[k - 1]
        P[3:, 3:] += np.diag(ACCEL_SIGMA**2) * h
        for z, R in measurements:
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R[k])
            x, P = x + K @ (z[k] - H @ x), (np.eye(6) - K @ H) @ P
        yaw = x[2] + 0.5 * x[5] * h
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = (c * x[3] - s * x[4]) * h, (s * x[3] + c * x[4]) * h
        F = np.eye(6)
        F[0, 2], F[1, 2], F[2, 5] = -dy, dx, h
        F[0, 3], F[0, 4], F[1, 3], F[1, 4] = c * h, -s * h, s * h, c * h
        F[0, 5], F[1, 5] = -0.5 * dy * h, 0.5 * dx * h
        x = x + np.array([dx, dy, x[5] * h, 0.0, 0.0, 0.0])
        x[2] = _wrap(x[2])
        P = F @ P @ F.T
        poses[k], covs[k] = x[:3], P[:3, :3]
    return poses, covs


def _errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    e = poses - truth
    e[:, 2] = _wrap(e[:, 2])
    return e


def with_h(source: tuple[np.ndarray, np.ndarray], fields: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """A source measuring some of the rates: padded to all three, the others with no weight."""
    n = source[0].shape[0]
    z = np.zeros((n, 3))
    R = np.tile(np.eye(3) * 1e12, (n, 1, 1))
    z[:, fields] = source[0]
    R[np.ix_(range(n), fields, fields)] = source[1]
    return z, R


def _planar_twist(odometry: OdometryTrack, fields: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The rates ``fields`` of PLANAR_TWIST an odometry track carries, and their published covariance."""
    twist = np.column_stack([odometry.linear_velocity[:, :2], odometry.angular_velocity[:, 2]])
    cov = odometry.twist_covariance[:, [0, 1, 5]][:, :, [0, 1, 5]]
    return twist[:, fields], cov[:, fields][:, :, fields]


def _fields(vector: list[bool]) -> list[int]:
    """Indices into PLANAR_TWIST of the planar rates a config vector fuses."""
    on = {f for f, v in zip(FIELDS, vector, strict=True) if v}
    return [i for i, f in enumerate(PLANAR_TWIST) if f in on]


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> tuple[OdometryTrack, np.ndarray]:
    """epi_vo's /vo/odometry of the ground robot bag with the file's vo_node parameters, and the ground-truth
    base_link poses (N, 4, 4) in odom at its stamps."""
    out = tmp_path_factory.mktemp("ekf")
    extrinsic = load_extrinsic(CONFIG)
    assert extrinsic is not None
    run_replay(BAG, out, load_config(CONFIG), extrinsic=extrinsic)
    odometry = read_odometry(out / "output.mcap")
    stamps, positions, quats = tum.read_tum(out / "groundtruth.tum")  # camera poses, relative to the first
    T_bc = extrinsic.T_base_cam
    rows = [int(np.argmin(np.abs(stamps - t))) for t in odometry.stamps_ns * 1e-9]
    truth = np.array([T_bc @ make_T(rotation_from_quat_xyzw(quats[j]), positions[j]) @ np.linalg.inv(T_bc)
                      for j in rows])
    assert np.allclose(np.abs(stamps[rows] - odometry.stamps_ns * 1e-9), 0.0, atol=1e-6)
    return odometry, truth


def test_the_fused_pose_is_inside_its_covariance_and_better_than_either_source(
        replayed: tuple[OdometryTrack, np.ndarray]) -> None:
    odometry, truth_T = replayed
    ekf = _ekf()
    dt = np.diff(odometry.stamps_ns) * 1e-9
    truth, rates = _planar(truth_T), _body_rates(truth_T, dt)
    n = truth.shape[0]
    # epi_vo: the fields odom0_config fuses, with the twist covariance it published (base_link, ROS order).
    vo_fields = _fields(ekf["odom0_config"])
    vo = _planar_twist(odometry, vo_fields)
    wheel_fields = _fields(ekf["odom1_config"])
    wheel_cov = np.tile(np.diag(WHEEL_SIGMA[wheel_fields] ** 2), (n, 1, 1))

    vo_m = with_h(vo, vo_fields)
    rms: dict[str, list[np.ndarray]] = {"fused": [], "vo": [], "wheels": []}
    nees: list[np.ndarray] = []
    for seed in range(SEEDS):
        noisy = rates + np.random.default_rng(seed).normal(size=rates.shape) * WHEEL_SIGMA
        wheel_m = with_h((noisy[:, wheel_fields], wheel_cov), wheel_fields)
        for name, sources in (("fused", [vo_m, wheel_m]), ("vo", [vo_m]), ("wheels", [wheel_m])):
            poses, covs = fuse(dt, sources)
            e = _errors(poses, truth)
            rms[name].append(np.sqrt(np.mean(np.column_stack([np.hypot(e[:, 0], e[:, 1]), e[:, 2]]) ** 2, axis=0)))
            if name == "fused":
                nees.append(np.einsum("ki,ki->k", e[1:], np.linalg.solve(covs[1:], e[1:, :, None])[..., 0]))
    # Inside its covariance: x, y, yaw within the chi-square 99 % bound at 99 % of the steps of every seed, and
    # on average near 3 (the errors of one run are integrated, so correlated: the band is for the mean of 20).
    all_nees = np.concatenate(nees)
    assert np.mean(all_nees < CHI2_99_3DOF) >= 0.99, np.mean(all_nees < CHI2_99_3DOF)
    assert 1.0 < float(np.mean(all_nees)) < 6.0, float(np.mean(all_nees))
    fused, vo_alone, wheels_alone = (np.mean(rms[k], axis=0) for k in ("fused", "vo", "wheels"))
    # Better than either alone: the position; the yaw than the wheels' (epi_vo's own yaw, integrated, is better
    # than its white-noise variance says: docs/robot_localization.md).
    assert fused[0] < vo_alone[0] and fused[0] < wheels_alone[0], (fused, vo_alone, wheels_alone)
    assert fused[1] < wheels_alone[1], (fused, wheels_alone)
    assert fused[0] < 0.02 and math.degrees(fused[1]) < 0.2  # metres and degrees over the 11 m drive


def test_with_scale_source_none_fusing_the_linear_rates_by_mistake_changes_nothing(
        tmp_path: Path, replayed: tuple[OdometryTrack, np.ndarray]) -> None:
    """The file's odom0_config on a replay with ``scale_source: none`` (a user who kept the config but not the
    metres): vo/odometry's linear rates are zero with the "unknown" variance, so the fused position is, within
    a millimetre, the one fusing its yaw rate only; the same fields of vo/odometry/vo_units (VO units with their
    tight covariance, what vo/odometry carried before) pull it metres away."""
    import dataclasses

    _, truth_T = replayed
    ekf = _ekf()
    cfg = dataclasses.replace(load_config(CONFIG), scale_source="none")
    run_replay(BAG, tmp_path, cfg, extrinsic=load_extrinsic(CONFIG))
    fusable = read_odometry(tmp_path / "output.mcap")
    vo_units = read_odometry(tmp_path / "output.mcap", "/vo/odometry/vo_units")
    np.testing.assert_array_equal(fusable.stamps_ns, vo_units.stamps_ns)
    dt = np.diff(fusable.stamps_ns) * 1e-9
    truth = _planar(truth_T)
    assert truth.shape[0] == fusable.stamps_ns.size
    wheel_fields = _fields(ekf["odom1_config"])
    n = truth.shape[0]
    noisy = _body_rates(truth_T, dt) + np.random.default_rng(0).normal(size=(n, 3)) * WHEEL_SIGMA
    wheels = with_h((noisy[:, wheel_fields], np.tile(np.diag(WHEEL_SIGMA[wheel_fields] ** 2), (n, 1, 1))),
                    wheel_fields)
    vo_fields = _fields(ekf["odom0_config"])
    yaw_rate = [PLANAR_TWIST.index("vyaw")]

    def fused(track: OdometryTrack, fields: list[int]) -> np.ndarray:
        return fuse(dt, [with_h(_planar_twist(track, fields), fields), wheels])[0]

    mistaken, intended = fused(fusable, vo_fields), fused(fusable, yaw_rate)
    assert float(np.max(np.hypot(*(mistaken - intended)[:, :2].T))) < 1e-3
    error = np.hypot(*_errors(intended, truth)[:, :2].T)
    assert float(np.max(error)) < 0.5  # the wheels' metres and epi_vo's yaw rate
    in_vo_units = np.hypot(*_errors(fused(vo_units, vo_fields), truth)[:, :2].T)
    assert float(np.max(in_vo_units)) > 1.0, float(np.max(in_vo_units))
