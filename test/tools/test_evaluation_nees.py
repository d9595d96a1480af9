"""Covariance consistency (NEES) of epi_vo.tools.evaluation: Monte Carlo on seeded synthetic trajectories whose
errors are drawn from known covariances, wrong covariances, alignment invariance, the replay wiring (frame
records, /vo/odometry read back from an MCAP, ground truth of the camera optical frame) and bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from epi_vo.core.errors import BagError, EvaluationError
from epi_vo.core.geometry import skew
from epi_vo.core.odometry import OdometryConverter, rotate_covariance
from epi_vo.io.odometry_bag import read_odometry
from epi_vo.io.outbag import OutputBag
from epi_vo.tools.evaluation import (
    CHI2_3DOF_99,
    AlignmentAnchor,
    conditioned_on,
    covariance_consistency,
    poses_from_xyz_quat,
    replay_dir_nees,
    replay_nees,
    rotation_vectors,
)

F64 = NDArray[np.float64]


def test_chi2_bound_is_the_3dof_99_percent_quantile() -> None:
    assert CHI2_3DOF_99 == pytest.approx(chi2.ppf(0.99, 3), abs=1e-3)


def test_rotation_vectors_known_answers() -> None:
    rv = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [0.0, 0.0, math.pi - 1e-9], [1e-10, 0.0, 0.0]])
    R = Rotation.from_rotvec(rv).as_matrix()
    out = rotation_vectors(R)
    np.testing.assert_allclose(out[:2], rv[:2], atol=1e-12)
    assert np.linalg.norm(out[2]) == pytest.approx(math.pi, abs=1e-8)
    np.testing.assert_allclose(out[3], rv[3], atol=1e-15)


# --------------------------------------------------------------------------------------------------
# Synthetic trajectories with errors drawn from a known covariance


def gt_path(n: int, rng: np.random.Generator) -> F64:
    """(n, 4, 4) ground-truth body poses in g: a wavy 3-D path, turning."""
    t = np.linspace(0.0, 4.0 * np.pi, n)
    p = np.column_stack([3.0 * np.cos(0.5 * t), 2.0 * np.sin(0.7 * t), 0.5 * t]) + rng.normal(0, 0.01, (n, 3))
    rv = np.column_stack([0.3 * np.sin(t), 0.2 * np.cos(0.6 * t), 0.5 * t])
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rv).as_matrix()
    T[:, :3, 3] = p
    return T


def random_covariances(n: int, rng: np.random.Generator) -> F64:
    """(n, 6, 6) full SPD covariances (position ~ cm, rotation ~ mrad, with cross terms), anchor row tiny."""
    A = rng.normal(size=(n, 6, 6)) * np.r_[[0.02] * 3, [0.002] * 3][None, :, None]
    A *= rng.uniform(0.3, 3.0, size=(n, 1, 1))  # a different size every frame
    P = A @ A.transpose(0, 2, 1) + np.diag([1e-6] * 3 + [1e-8] * 3)
    P[0] = np.eye(6) * 1e-12  # the odometry origin: known exactly
    return P


def perturb(T_true: F64, delta: F64) -> F64:
    """The estimate whose error is ``delta`` (n, 6): p_true = p_est + d_p, R_true = Exp(d_th) R_est."""
    T = T_true.copy()
    T[:, :3, 3] = T_true[:, :3, 3] - delta[:, :3]
    T[:, :3, :3] = Rotation.from_rotvec(-delta[:, 3:]).as_matrix() @ T_true[:, :3, :3]
    return T


def sim3(s: float, R: F64, t: F64) -> tuple[float, F64, F64]:
    return s, R, t


def to_frame(T_g: F64, cov_g: F64, s: float, R: F64, t: F64) -> tuple[F64, F64]:
    """Poses and covariances given in g expressed in o, where p_g = s R p_o + t, R_g = R R_o."""
    T_o = T_g.copy()
    T_o[:, :3, 3] = (T_g[:, :3, 3] - t) @ R / s
    T_o[:, :3, :3] = np.einsum("ji,njk->nik", R, T_g[:, :3, :3])
    A = np.zeros((6, 6))
    A[:3, :3] = R.T / s
    A[3:, 3:] = R.T
    return T_o, A @ cov_g @ A.T


S_ODOM = sim3(0.37, Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix(), np.array([5.0, -2.0, 1.0]))


def independent_run(n: int = 1000, seed: int = 3, cov_factor: float = 1.0) -> tuple[F64, F64, F64]:
    """Errors drawn independently each frame from its covariance; the estimate and its covariance published
    in an odometry frame o (another origin, orientation and scale than g). Returns (T_o_est, cov_o * factor,
    T_g_gt)."""
    rng = np.random.default_rng(seed)
    T_gt = gt_path(n, rng)
    P = random_covariances(n, rng)
    delta = np.array([rng.multivariate_normal(np.zeros(6), Pi) for Pi in P])
    delta[0] = 0.0
    T_o, cov_o = to_frame(perturb(T_gt, delta), P, *S_ODOM)
    return T_o, cov_o * cov_factor, T_gt


@pytest.mark.parametrize("anchor", list(AlignmentAnchor))
def test_errors_drawn_from_the_covariance_give_nees_3(anchor: AlignmentAnchor) -> None:
    T_o, cov_o, T_gt = independent_run()
    # Not the origin itself: its error is zero by definition, and Umeyama would put one on it.
    r = covariance_consistency(T_o, cov_o, T_gt, np.arange(len(T_o)) > 0, anchor=anchor)
    assert r.alignment == "sim3" and r.evaluated == 999
    assert r.scale == pytest.approx(0.37, rel=5e-3)  # o -> g units
    # Mean of 1000 chi-square(3) samples: 3 +- 0.08 (1 sigma); 99 % inside +- 0.3 %.
    assert r.mean_nees_pos == pytest.approx(3.0, abs=0.3)
    assert 98.0 <= r.inside_pos_percent <= 100.0
    if anchor is AlignmentAnchor.ORIGIN:
        assert r.mean_nees_rot == pytest.approx(3.0, abs=0.3)
        assert 98.0 <= r.inside_rot_percent <= 100.0
    else:  # Umeyama's rotation comes from the noisy positions: its own error adds to every frame's
        assert 3.2 < r.mean_nees_rot < 4.5


def test_random_walk_errors_with_their_accumulated_covariance_give_nees_3() -> None:
    """What odometry does: each step adds an error; the covariance published is the sum of the steps'
    (zero at the origin). Anchored at the origin, NEES is chi-square(3) again: rotation, and position with
    metric scale (SE(3)). Under Sim(3) the fitted scale absorbs part of the along-track drift, so the
    position NEES comes out lower (about 2.5). 400 runs of 30 frames (one run's frames are correlated)."""
    rng = np.random.default_rng(11)
    pos_se3, pos_sim3, rot, inside = [], [], [], []
    R_o = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    n = 30
    T_gt = gt_path(n, rng)
    for _ in range(400):
        A = rng.normal(size=(n, 6, 6)) * np.r_[[0.005] * 3, [0.0005] * 3][None, :, None]
        Q = A @ A.transpose(0, 2, 1) + np.diag([1e-6] * 3 + [1e-8] * 3)
        Q[0] = 0.0
        steps = np.einsum("nij,nj->ni", np.linalg.cholesky(Q[1:]), rng.normal(size=(n - 1, 6)))
        steps = np.vstack([np.zeros(6), steps])
        P = np.cumsum(Q, axis=0) + np.eye(6) * 1e-12
        T_o, cov_o = to_frame(perturb(T_gt, np.cumsum(steps, axis=0)), P, 1.0, R_o, np.array([5.0, -2.0, 1.0]))
        r = covariance_consistency(T_o, cov_o, T_gt, np.arange(n) > 0, metric=True)
        pos_se3.append(r.nees_pos)
        rot.append(r.nees_rot)
        inside.append(r.inside_pos_percent)
        pos_sim3.append(covariance_consistency(T_o, cov_o, T_gt, np.arange(n) > 0).nees_pos)
    assert float(np.mean(pos_se3)) == pytest.approx(3.0, abs=0.3)
    assert float(np.mean(rot)) == pytest.approx(3.0, abs=0.3)
    assert float(np.mean(inside)) >= 96.5
    assert 2.0 < float(np.mean(pos_sim3)) < 2.9


@pytest.mark.parametrize(("factor", "expected"), [(0.01, 300.0), (100.0, 0.03)])
def test_a_wrong_covariance_shows_in_the_nees(factor: float, expected: float) -> None:
    T_o, cov_o, T_gt = independent_run(cov_factor=factor)
    r = covariance_consistency(T_o, cov_o, T_gt, np.arange(len(T_o)) > 0)
    assert r.mean_nees_pos == pytest.approx(expected, rel=0.1)
    assert r.mean_nees_rot == pytest.approx(expected, rel=0.1)
    if factor < 1:  # 100x too confident: chi-square(3) * 100 is rarely below 11.3
        assert r.inside_pos_percent < 10.0 and r.inside_rot_percent < 10.0
    else:
        assert r.inside_pos_percent == r.inside_rot_percent == 100.0


@pytest.mark.parametrize("anchor", list(AlignmentAnchor))
def test_nees_is_invariant_to_a_sim3_of_the_estimate_or_of_the_ground_truth(anchor: AlignmentAnchor) -> None:
    T_o, cov_o, T_gt = independent_run(n=200, seed=5)
    mask = (np.arange(200) % 7 != 3) & (np.arange(200) > 0)
    base = covariance_consistency(T_o, cov_o, T_gt, mask, anchor=anchor)
    S = (4.2, Rotation.from_rotvec([-2.0, 0.3, 0.9]).as_matrix(), np.array([-30.0, 4.0, 12.0]))
    T_o2, cov_o2 = to_frame(T_o, cov_o, *S)  # the same estimate published in another odometry frame
    moved = covariance_consistency(T_o2, cov_o2, T_gt, mask, anchor=anchor)
    np.testing.assert_allclose(moved.nees_pos, base.nees_pos, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(moved.nees_rot, base.nees_rot, rtol=1e-6, atol=1e-9)
    assert moved.scale == pytest.approx(base.scale * 4.2, rel=1e-9)
    T_gt2, _ = to_frame(T_gt, np.zeros((200, 6, 6)), *S)  # ground truth in another world and units
    moved_gt = covariance_consistency(T_o, cov_o, T_gt2, mask, anchor=anchor)
    np.testing.assert_allclose(moved_gt.nees_pos, base.nees_pos, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(moved_gt.nees_rot, base.nees_rot, rtol=1e-6, atol=1e-9)
    assert base.frame_index.tolist() == np.flatnonzero(mask).tolist()
    assert 2.5 < base.mean_nees_pos < 3.5  # and the values are the consistent ones


def test_metric_estimates_get_no_scale() -> None:
    """SE(3): a metric estimate 10 % too long is inconsistent; the same one read as VO units (Sim(3)) is not."""
    rng = np.random.default_rng(8)
    n = 300
    T_gt = gt_path(n, rng)
    P = random_covariances(n, rng)
    delta = np.array([rng.multivariate_normal(np.zeros(6), Pi) for Pi in P])
    delta[0] = 0.0
    R = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    T_o, cov_o = to_frame(perturb(T_gt, delta), P, 1.0, R, np.array([1.0, 2.0, 3.0]))
    right = covariance_consistency(T_o, cov_o, T_gt, np.ones(n, bool), metric=True)
    assert right.alignment == "se3" and right.scale == 1.0
    assert right.mean_nees_pos == pytest.approx(3.0, abs=0.5)
    long, cov_long = to_frame(T_o, cov_o, 1.0 / 1.1, np.eye(3), T_o[0, :3, 3])  # 10 % longer, from the origin
    wrong = covariance_consistency(long, cov_long, T_gt, np.ones(n, bool), metric=True)
    assert wrong.mean_nees_pos > 100.0
    vo_units = covariance_consistency(long, cov_long, T_gt, np.ones(n, bool))
    assert vo_units.scale == pytest.approx(1.0 / 1.1, rel=2e-3)
    assert vo_units.mean_nees_pos == pytest.approx(right.mean_nees_pos, rel=0.05)
    np.testing.assert_allclose(wrong.nees_rot, right.nees_rot)  # the scale does not touch the rotation


def test_an_estimate_that_never_moves_has_no_position_nees() -> None:
    n = 20
    T_gt = gt_path(n, np.random.default_rng(1))
    T_o = np.tile(np.eye(4), (n, 1, 1))
    r = covariance_consistency(T_o, np.tile(np.eye(6) * 1e-4, (n, 1, 1)), T_gt, np.ones(n, bool))
    assert math.isnan(r.scale) and np.isnan(r.nees_pos).all() and math.isnan(r.mean_nees_pos)
    assert math.isnan(r.inside_pos_percent)
    assert np.isfinite(r.nees_rot).all() and r.nees_rot[0] == pytest.approx(0.0, abs=1e-12)


def test_bad_input_is_an_evaluation_error() -> None:
    T = np.tile(np.eye(4), (5, 1, 1))
    cov = np.tile(np.eye(6), (5, 1, 1))
    with pytest.raises(EvaluationError, match=r"expected \(N, 4, 4\) poses"):
        covariance_consistency(T, cov[:4], T, np.ones(5, bool))
    bad = cov.copy()
    bad[2, 0, 0] = np.nan
    with pytest.raises(EvaluationError, match="covariances of the evaluated frames have non-finite"):
        covariance_consistency(T, bad, T, np.ones(5, bool))
    covariance_consistency(T, bad, T, np.arange(5) != 2)  # a frame not evaluated may be anything
    with pytest.raises(EvaluationError, match="anchor_row 7"):
        covariance_consistency(T, cov, T, np.ones(5, bool), anchor_row=7)


# --------------------------------------------------------------------------------------------------
# A replay: frame records, /vo/odometry in output.mcap, ground truth of the camera


STAMP0_NS = 1_000_000_000_000
DT_NS = 50_000_000


def write_replay(tmp: Path, states: list[str], seed: int = 2, metric_from: int | None = None) -> tuple[Path, dict]:
    """A replay output directory as epi-vo replay writes it: camera poses T_w_c with covariance in w, through
    the same OdometryConverter into output.mcap; ground truth of the camera optical frame in groundtruth.tum."""
    rng = np.random.default_rng(seed)
    n = len(states)
    T_g_b = gt_path(n, rng)
    T_g_c = T_g_b @ OdometryConverter().T_base_cam  # the ground-truth camera: body then optical rotation
    P = random_covariances(n, rng)
    delta = np.array([rng.multivariate_normal(np.zeros(6), Pi) for Pi in P])
    delta[0] = 0.0
    S = (0.5, Rotation.from_rotvec([0.3, 0.1, -0.2]).as_matrix(), np.array([0.4, 0.0, -1.0]))
    T_w_c, cov_w = to_frame(perturb(T_g_c, delta), P, *S)  # left errors in g, expressed in the camera world w
    tmp.mkdir(parents=True, exist_ok=True)
    conv = OdometryConverter()
    stamps = [STAMP0_NS + i * DT_NS for i in range(n)]
    with OutputBag(tmp / "output.mcap") as bag:
        for i in range(n):
            if i == 3:
                continue  # a skipped frame: a record but no odometry
            s = conv.convert(stamps[i], T_w_c[i], cov_w[i], True)
            bag.write_odometry(stamps[i], "odom", "base_link", s.position, s.quat_xyzw, s.pose_covariance,
                               s.linear_velocity, s.angular_velocity, s.twist_covariance)
    recs = [{"index": i, "stamp_ns": stamps[i], "stamp": stamps[i] * 1e-9, "state": st,
             "metric_scale": metric_from is not None and i >= metric_from} for i, st in enumerate(states)]
    (tmp / "frames.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    rows = [f"{stamps[i] * 1e-9:.9f} " + " ".join(f"{v:.12f}" for v in (*T_g_c[i, :3, 3],
            *Rotation.from_matrix(T_g_c[i, :3, :3]).as_quat())) for i in range(n) if i != n - 2]  # no GT for n-2
    (tmp / "groundtruth.tum").write_text("\n".join(rows) + "\n")
    expected = {"T_w_c": T_w_c, "cov_w": cov_w, "T_g_c": T_g_c, "stamps": stamps}
    return tmp, expected


def test_read_odometry_gives_back_what_was_published(tmp_path: Path) -> None:
    states = ["tracking"] * 12
    d, exp = write_replay(tmp_path / "run", states)
    odo = read_odometry(d / "output.mcap")
    assert odo.frame_id == "odom" and odo.child_frame_id == "base_link"
    assert odo.stamps_ns.tolist() == [s for i, s in enumerate(exp["stamps"]) if i != 3]
    R_bc = OdometryConverter().T_base_cam[:3, :3]
    np.testing.assert_allclose(odo.pose_covariance[4], rotate_covariance(exp["cov_w"][5], R_bc), rtol=1e-12)
    T = poses_from_xyz_quat(odo.positions, odo.quats_xyzw)
    np.testing.assert_allclose(T[4], OdometryConverter().base_pose(exp["T_w_c"][5]), atol=1e-12)
    with pytest.raises(BagError, match=r"has no topic /vo/path2 \(odometry topics: /vo/odometry, "
                       r"/vo/odometry/vo_units\)"):
        read_odometry(d / "output.mcap", "/vo/path2")
    with pytest.raises(BagError, match="not nav_msgs/msg/Odometry"):
        read_odometry(d / "output.mcap", "/vo/path")
    with pytest.raises(BagError, match="bag not found"):
        read_odometry(d / "nothing.mcap")


def test_replay_nees_skips_what_is_not_tracking_and_agrees_with_the_camera_frame(tmp_path: Path) -> None:
    n = 400
    states = ["initializing"] * 5 + ["tracking"] * (n - 5)
    states[100:110] = ["lost"] * 10
    states[200:230] = ["static"] * 30
    states[300:304] = ["rotation_only"] * 4
    d, exp = write_replay(tmp_path / "run", states)
    r = replay_dir_nees(d)
    assert r is not None
    assert r.skipped == {"initializing": 5, "lost": 10, "static": 30, "rotation_only": 4, "no ground truth": 1}
    # Frame 3 is initializing (also without odometry); frame n-2 has no ground truth.
    tracked = [i for i, s in enumerate(states) if s == "tracking" and i != n - 2]
    assert r.frame_index.tolist() == tracked and r.evaluated == n - 50
    assert r.alignment == "sim3" and r.anchor is AlignmentAnchor.ORIGIN
    assert r.scale == pytest.approx(0.5, rel=5e-3)
    # The same numbers as in the camera's own frame w, with the pipeline's covariance (odom differs by a rotation).
    mask = np.zeros(n, bool)
    mask[tracked] = True
    direct = covariance_consistency(exp["T_w_c"], exp["cov_w"], exp["T_g_c"], mask)
    np.testing.assert_allclose(r.nees_pos, direct.nees_pos, rtol=1e-6)
    np.testing.assert_allclose(r.nees_rot, direct.nees_rot, rtol=1e-6)
    assert r.mean_nees_pos == pytest.approx(3.0, abs=0.5) and r.mean_nees_rot == pytest.approx(3.0, abs=0.5)
    assert replay_dir_nees(tmp_path / "no_gt") is None


def test_replay_nees_with_metric_scale_uses_se3_on_the_metric_frames(tmp_path: Path) -> None:
    d, _ = write_replay(tmp_path / "run", ["initializing"] * 2 + ["tracking"] * 38, metric_from=10)
    recs = [json.loads(line) for line in (d / "frames.jsonl").read_text().splitlines()]
    r = replay_nees(recs, read_odometry(d / "output.mcap"), _tum(d / "groundtruth.tum"))
    assert r.alignment == "se3" and r.scale == 1.0
    assert r.skipped == {"initializing": 2, "no odometry message": 1, "metric scale not established": 7,
                         "no ground truth": 1}
    assert r.frame_index[0] == 10
    # This estimate is in units of 0.5 GT units: claimed as metres it is far off its covariance.
    assert r.mean_nees_pos > 1000.0


def test_replay_nees_needs_odometry_paired_with_ground_truth(tmp_path: Path) -> None:
    d, _ = write_replay(tmp_path / "run", ["tracking"] * 10)
    recs = [json.loads(line) for line in (d / "frames.jsonl").read_text().splitlines()]
    stamps, p, q = _tum(d / "groundtruth.tum")
    with pytest.raises(EvaluationError, match=r"no odometry message has a ground-truth pose within 0\.01 s"):
        replay_nees(recs, read_odometry(d / "output.mcap"), (stamps + 5.0, p, q))
    (d / "output.mcap").write_bytes(b"not a bag")
    with pytest.raises(EvaluationError, match="cannot read the replay output for the covariance check"):
        replay_dir_nees(d)


def _tum(path: Path) -> tuple[F64, F64, F64]:
    a = np.loadtxt(path)
    return a[:, 0], a[:, 1:4], a[:, 4:8]


def test_vectorised_pose_helpers_equal_the_per_pose_transforms() -> None:
    """poses_from_xyz_quat and rotation_vectors (vectorised for the replay's own NEES) give what
    transforms.make_T / rotation_from_quat_xyzw / quat_xyzw_from_rotation give pose by pose, near 0 and pi
    and for unnormalised quaternions too; bad input is an error naming the problem."""
    from epi_vo.core.errors import EpiVoError
    from epi_vo.core.transforms import make_T, quat_xyzw_from_rotation, rotation_from_quat_xyzw

    rng = np.random.default_rng(5)
    q = rng.normal(size=(200, 4)) * rng.uniform(0.1, 3.0, size=(200, 1))
    p = rng.normal(size=(200, 3))
    T = poses_from_xyz_quat(p, q)
    for i in range(200):
        np.testing.assert_allclose(T[i], make_T(rotation_from_quat_xyzw(q[i]), p[i]), atol=1e-14)
    rv = rng.normal(size=(300, 3))
    rv *= (rng.uniform(0.0, math.pi, size=(300, 1)) / np.linalg.norm(rv, axis=1, keepdims=True))
    rv[:20] *= 1e-9  # near zero
    rv[20:40] *= (math.pi - 1e-7) / np.linalg.norm(rv[20:40], axis=1, keepdims=True)  # near pi
    R = Rotation.from_rotvec(rv).as_matrix()
    out = rotation_vectors(R)
    for i in range(300):
        qi = quat_xyzw_from_rotation(R[i])
        n = np.linalg.norm(qi[:3])
        expect = 2.0 * qi[:3] if n < 1e-12 else qi[:3] * (2.0 * math.atan2(n, qi[3]) / n)
        np.testing.assert_allclose(out[i], expect, atol=1e-12)
    with pytest.raises(EpiVoError, match="zero norm"):
        poses_from_xyz_quat(p[:2], np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]]))
    with pytest.raises(EpiVoError, match="non-finite"):
        poses_from_xyz_quat(np.array([[np.nan, 0.0, 0.0]]), q[:1])


def chain_run(n: int, rng: np.random.Generator, T_gt: F64) -> tuple[F64, F64]:
    """Odometry as the pipeline chains it: each frame's error (world frame, left) is the previous one's
    moved by the lever arm plus a new step, e_i = F_i e_(i-1) + w_i, F_i = [[I, -[p_i - p_(i-1)]x], [0, I]];
    the published covariance propagates the same way. Returns (T_est, P) in g."""
    p = T_gt[:, :3, 3]
    e, P = np.zeros((n, 6)), np.zeros((n, 6, 6))
    for i in range(1, n):
        A = rng.normal(size=(6, 6)) * np.r_[[0.004] * 3, [0.0008] * 3][:, None]
        Q = A @ A.T + np.diag([1e-7] * 3 + [1e-9] * 3)
        F = np.eye(6)
        F[:3, 3:] = -skew(p[i] - p[i - 1])
        e[i] = F @ e[i - 1] + rng.multivariate_normal(np.zeros(6), Q)
        P[i] = F @ P[i - 1] @ F.T + Q
    P[0] = np.eye(6) * 1e-12
    return perturb(T_gt, e), P


def test_conditioned_on_recovers_the_motion_since_the_anchor() -> None:
    """P_i = J P_a J^T + Q (J the lever arm from a to i): conditioned on a, what is left is Q."""
    rng = np.random.default_rng(5)
    T = gt_path(20, rng)
    P_a = random_covariances(2, rng)[1]
    Q = random_covariances(20, rng)
    Q[7] = 0.0  # the anchor's own covariance is P_a
    P = np.empty_like(Q)
    for i in range(20):
        J = np.eye(6)
        J[:3, 3:] = -skew(T[i, :3, 3] - T[7, :3, 3])
        P[i] = J @ P_a @ J.T + Q[i]
    C = conditioned_on(T, P, 7)
    np.testing.assert_allclose(C[8:], Q[8:], rtol=1e-9, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(C) > 0.0)  # floored, as published covariances are


def test_nees_from_a_later_anchor_is_chi_square_when_the_chain_is() -> None:
    """Errors that accumulate along the chain, judged from frame 10 on (anchored there, each covariance
    given frame 10's): NEES 3 for position and rotation. The covariance as published (from the origin)
    would claim the error frame 10 already had: 1.3 (position) and 1.4 (rotation) instead of 3."""
    rng = np.random.default_rng(8)
    n, a = 30, 10
    T_gt = gt_path(n, rng)
    pos, rot, raw_pos = [], [], []
    for _ in range(300):
        T_est, P = chain_run(n, rng, T_gt)
        mask = np.arange(n) > a
        r = covariance_consistency(T_est, conditioned_on(T_est, P, a), T_gt, mask, metric=True, anchor_row=a)
        pos.append(r.mean_nees_pos)
        rot.append(r.mean_nees_rot)
        raw_pos.append(covariance_consistency(T_est, P, T_gt, mask, metric=True, anchor_row=a).mean_nees_pos)
    assert float(np.mean(pos)) == pytest.approx(3.0, abs=0.3)
    assert float(np.mean(rot)) == pytest.approx(3.0, abs=0.3)
    assert float(np.mean(raw_pos)) < 2.0


def test_replay_nees_from_a_stamp_anchors_there_and_skips_what_is_before(tmp_path: Path) -> None:
    d, exp = write_replay(tmp_path / "run", ["initializing"] * 2 + ["tracking"] * 38)
    r = replay_dir_nees(d, from_ns=exp["stamps"][10])
    assert r is not None
    # frames 2..9 tracking before it (3 has no odometry), frame 10 the anchor, n-2 has no ground truth
    assert r.skipped == {"initializing": 2, "no odometry message": 1, "before the checked ground truth": 7,
                         "anchor": 1, "no ground truth": 1}
    assert r.frame_index[0] == 11 and r.evaluated == 28
    recs = [json.loads(line) for line in (d / "frames.jsonl").read_text().splitlines()]
    with pytest.raises(EvaluationError, match="no tracking frame with ground truth at or after"):
        replay_nees(recs, read_odometry(d / "output.mcap"), _tum(d / "groundtruth.tum"), from_ns=exp["stamps"][-1] + 1)
