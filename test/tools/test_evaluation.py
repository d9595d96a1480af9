"""Tests of epi_vo.tools.evaluation on seeded synthetic trajectories with known answers."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from epi_vo.core.errors import EvaluationError
from epi_vo.io.trajectory import StampedPoses
from epi_vo.tools.evaluation import (
    TrajectoryMetrics,
    evaluate_trajectory,
    metric_poses,
    translation_direction_error,
)


def make_gt(
    n: int = 80, seed: int = 7, planar: bool = False, rate_hz: float = 20.0
) -> StampedPoses:
    """A smooth 3D path of camera poses T_w_c: sums of sinusoids for position and rotation vector."""
    rng = np.random.default_rng(seed)
    stamps_s = 100.0 + np.arange(n) / rate_hz
    t = np.linspace(0.0, 2.0 * np.pi, n)
    amp = rng.uniform(0.5, 2.0, size=3)
    freq = rng.uniform(0.5, 1.5, size=3)
    phase = rng.uniform(0.0, 2.0 * np.pi, size=3)
    positions_xyz = amp * np.sin(freq * t[:, None] + phase) + np.outer(
        t, [0.4, 0.2, 0.1]
    )
    if planar:
        positions_xyz[:, 2] = 1.5
    rotvecs = 0.6 * np.sin(
        rng.uniform(0.3, 1.0, size=3) * t[:, None] + rng.uniform(0, 6, size=3)
    )
    quats_xyzw = Rotation.from_rotvec(
        rotvecs
    ).as_quat()  # scipy: scalar-last, x, y, z, w
    return StampedPoses(stamps_s, positions_xyz, quats_xyzw)


def transform_sim3(
    poses: StampedPoses,
    scale: float,
    R_a_w: NDArray[np.float64],
    t_a_w: NDArray[np.float64],
) -> StampedPoses:
    """Express the poses in another world frame a, at another scale: T_a_c = S_a_w @ T_w_c."""
    positions_a = scale * poses.positions_xyz @ R_a_w.T + t_a_w
    rot_a_c = Rotation.from_matrix(R_a_w) * Rotation.from_quat(poses.quats_xyzw)
    return StampedPoses(poses.stamps_s.copy(), positions_a, rot_a_c.as_quat())


def test_sim3_transformed_estimate_has_zero_error() -> None:
    gt = make_gt()
    R_a_w = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    est = transform_sim3(gt, 0.37, R_a_w, np.array([5.0, -2.0, 0.5]))

    m = evaluate_trajectory(est, gt)

    assert isinstance(m, TrajectoryMetrics)
    assert m.matched_poses == 80
    assert m.ate_rmse < 1e-6
    assert m.ate_percent_of_path < 1e-6
    # evo aligns the estimate onto the ground truth, p_gt ~= s R p_est + t: s undoes the 0.37 shrink.
    assert m.sim3_scale == pytest.approx(1.0 / 0.37, rel=1e-9)
    assert m.rpe_rot_deg_per_frame < 1e-6
    assert m.rpe_trans_rmse < 1e-6
    assert m.trans_direction_err_deg < 1e-5
    assert m.trans_direction_pairs == 79


def test_metrics_are_frozen() -> None:
    gt = make_gt(n=10)
    m = evaluate_trajectory(gt, gt)
    assert m.sim3_scale == pytest.approx(1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.ate_rmse = 1.0  # type: ignore[misc]


def test_plain_tuples_are_accepted() -> None:
    gt = make_gt(n=10)
    m = evaluate_trajectory(tuple(gt), tuple(gt))
    assert m.matched_poses == 10


def test_rotation_drift_gives_known_rpe() -> None:
    # World-frame drift of 1 deg per frame about z: R_est_i = Rz(i deg) R_gt_i. The relative error
    # (Q_rel^-1 P_rel) is then R_gt_{i+1}^T Rz(1 deg) R_gt_{i+1}: exactly 1 deg for every pair.
    gt = make_gt()
    drift = Rotation.from_euler("z", np.arange(len(gt.stamps_s))[:, None], degrees=True)
    est = StampedPoses(
        gt.stamps_s,
        gt.positions_xyz,
        (drift * Rotation.from_quat(gt.quats_xyzw)).as_quat(),
    )

    m = evaluate_trajectory(est, gt)

    assert m.rpe_rot_deg_per_frame == pytest.approx(1.0, abs=1e-9)
    assert m.ate_rmse < 1e-9  # positions are untouched
    assert (
        m.trans_direction_err_deg > 1.0
    )  # orientation drift turns the steps seen in the camera


def test_direction_error_known_answer() -> None:
    # Planar path (z constant) and orientations rotated by a fixed 5 deg about world z: every step is
    # perpendicular to z, so the step seen in each camera turns by exactly 5 deg. Relative rotations
    # are unchanged (a constant world rotation cancels), so RPE rotation stays 0.
    gt = make_gt(planar=True)
    yaw = Rotation.from_euler("z", 5.0, degrees=True)
    est = StampedPoses(
        gt.stamps_s,
        gt.positions_xyz,
        (yaw * Rotation.from_quat(gt.quats_xyzw)).as_quat(),
    )

    m = evaluate_trajectory(est, gt)

    assert m.trans_direction_err_deg == pytest.approx(5.0, abs=1e-9)
    assert m.trans_direction_pairs == 79
    assert m.rpe_rot_deg_per_frame < 1e-6


def test_translation_direction_error_reversed_steps() -> None:
    T_w_c_gt = np.tile(np.eye(4), (4, 1, 1))
    T_w_c_gt[:, :3, 3] = np.arange(4)[:, None] * [1.0, 0.0, 0.0]
    T_w_c_est = T_w_c_gt.copy()
    T_w_c_est[:, :3, 3] *= -0.01  # scale is irrelevant, the sign is not

    err_deg, pairs = translation_direction_error(T_w_c_est, T_w_c_gt)

    assert pairs == 3
    assert err_deg == pytest.approx(180.0)


def test_translation_direction_error_shape_mismatch() -> None:
    with pytest.raises(EvaluationError, match=r"\(M, 4, 4\)"):
        translation_direction_error(np.zeros((3, 4, 4)), np.zeros((4, 4, 4)))


def test_constant_estimate_positions() -> None:
    # An estimate that never moved: no step has a direction, and Sim(3) alignment is degenerate,
    # so the alignment-based metrics are NaN while the rotation RPE is still defined.
    gt = make_gt()
    positions_xyz = np.tile([1.0, 2.0, 3.0], (len(gt.stamps_s), 1))
    est = StampedPoses(gt.stamps_s, positions_xyz, gt.quats_xyzw)

    m = evaluate_trajectory(est, gt)

    assert m.trans_direction_pairs == 0
    assert np.isnan(m.trans_direction_err_deg)
    assert np.isnan(m.ate_rmse)
    assert np.isnan(m.ate_percent_of_path)
    assert np.isnan(m.sim3_scale)
    assert np.isnan(m.rpe_trans_rmse)
    assert m.rpe_rot_deg_per_frame < 1e-6


def test_association_with_jittered_stamps() -> None:
    gt = make_gt(n=60, rate_hz=20.0)
    rng = np.random.default_rng(3)
    keep = np.arange(0, 60, 2)
    stamps_s = gt.stamps_s[keep] + rng.uniform(-0.003, 0.003, size=keep.size)
    # One extra estimated pose far after the ground truth ends: never matched.
    stamps_s = np.append(stamps_s, gt.stamps_s[-1] + 1.0)
    positions_xyz = np.vstack([0.5 * gt.positions_xyz[keep], [[9.0, 9.0, 9.0]]])
    quats_xyzw = np.vstack([gt.quats_xyzw[keep], [[0.0, 0.0, 0.0, 1.0]]])
    est = StampedPoses(stamps_s, positions_xyz, quats_xyzw)

    m = evaluate_trajectory(est, gt, max_time_diff=0.01)

    assert m.matched_poses == 30
    assert m.ate_rmse < 1e-9
    assert m.sim3_scale == pytest.approx(2.0)
    # The same jitter with a tighter window drops the pairs that are more than 1 ms apart.
    n_close = int(np.count_nonzero(np.abs(stamps_s[:-1] - gt.stamps_s[keep]) <= 0.001))
    assert evaluate_trajectory(est, gt, max_time_diff=0.001).matched_poses == n_close


def test_fewer_than_three_poses() -> None:
    gt = make_gt(n=10)
    two = StampedPoses(gt.stamps_s[:2], gt.positions_xyz[:2], gt.quats_xyzw[:2])
    with pytest.raises(EvaluationError, match="need at least 3"):
        evaluate_trajectory(two, gt)


def test_fewer_than_three_matched_poses() -> None:
    gt = make_gt(n=10)
    est = StampedPoses(
        gt.stamps_s[[0, 1, 2]] + [0.0, 0.0, 50.0],
        gt.positions_xyz[:3],
        gt.quats_xyzw[:3],
    )
    with pytest.raises(EvaluationError, match="only 2 poses matched"):
        evaluate_trajectory(est, gt)


def test_no_matched_stamps() -> None:
    gt = make_gt(n=10)
    est = StampedPoses(gt.stamps_s + 1000.0, gt.positions_xyz, gt.quats_xyzw)
    with pytest.raises(EvaluationError, match="no poses matched"):
        evaluate_trajectory(est, gt)


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (
            lambda p: StampedPoses(p.stamps_s, p.positions_xyz[:, :2], p.quats_xyzw),
            r"positions_xyz must have shape",
        ),
        (
            lambda p: StampedPoses(p.stamps_s, p.positions_xyz, p.quats_xyzw[:-1]),
            r"quats_xyzw must have shape",
        ),
        (
            lambda p: StampedPoses(p.stamps_s[:, None], p.positions_xyz, p.quats_xyzw),
            r"stamps_s must have shape",
        ),
        (
            lambda p: StampedPoses(
                p.stamps_s,
                np.where(p.positions_xyz > 1, np.nan, p.positions_xyz),
                p.quats_xyzw,
            ),
            "non-finite",
        ),
        (
            lambda p: StampedPoses(
                p.stamps_s[::-1].copy(), p.positions_xyz, p.quats_xyzw
            ),
            "strictly increasing",
        ),
        (
            lambda p: StampedPoses(
                p.stamps_s, p.positions_xyz, np.zeros_like(p.quats_xyzw)
            ),
            "zero-norm",
        ),
        (
            lambda p: (p.stamps_s, p.positions_xyz),
            "expected \\(stamps_s, positions_xyz, quats_xyzw\\)",
        ),
    ],
)
def test_bad_input(mutate: Callable[[StampedPoses], tuple], match: str) -> None:
    gt = make_gt(n=10)
    with pytest.raises(EvaluationError, match=match):
        evaluate_trajectory(mutate(gt), gt)


def test_bad_max_time_diff() -> None:
    gt = make_gt(n=10)
    with pytest.raises(EvaluationError, match="max_time_diff"):
        evaluate_trajectory(gt, gt, max_time_diff=-1.0)


def test_metric_runs_are_judged_on_their_metric_poses() -> None:
    """Poses held (at the map's origin, VO units) before a scale source established metres are no
    positions: the metrics leave them out and count them; a run in VO units keeps every pose."""
    gt = make_gt(n=40)
    est = StampedPoses(gt.stamps_s.copy(), gt.positions_xyz.copy(), gt.quats_xyzw.copy())
    est.positions_xyz[:5] = est.positions_xyz[0]  # held where the map started
    stamps_ns = [round(float(t) * 1e9) for t in gt.stamps_s]
    records = [{"stamp_ns": ns, "metric_scale": i >= 5} for i, ns in enumerate(stamps_ns)]
    kept, held = metric_poses(est, records)
    assert held == 5 and kept.stamps_s.size == 35
    np.testing.assert_array_equal(kept.positions_xyz, gt.positions_xyz[5:])
    m = evaluate_trajectory(kept, gt)
    assert m.matched_poses == 35 and m.ate_se3_percent_of_path < 1e-6 and m.ate_rmse < 1e-6
    assert evaluate_trajectory(est, gt).ate_se3_percent_of_path > 1.0  # the held poses, judged as metres
    # VO units (no record claims metres): every pose is judged.
    kept, held = metric_poses(est, [dict(r, metric_scale=False) for r in records])
    assert held == 0 and kept.stamps_s.size == 40
