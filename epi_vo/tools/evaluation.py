"""Trajectory metrics of an estimated monocular trajectory against ground truth, computed with evo.

Both trajectories hold camera optical-frame poses T_w_c (camera points into world): the position is
the camera centre in world, the quaternion is R_w_c in x, y, z, w order (ROS order). evo's
``PoseTrajectory3D`` takes quaternions in w, x, y, z order; the conversion happens in one place,
``to_evo_trajectory``.

Pipeline (the evaluation recommended by section 12 of the seed article: report relative rotation
error, translation-direction error and ATE/RPE separately, and say how scale was fixed):

1. association by stamp with ``evo.core.sync.associate_trajectories`` (nearest stamp within
   ``max_time_diff``);
2. Sim(3) Umeyama alignment of the estimate onto the ground truth (``PosePath3D.align`` with
   ``correct_scale=True``). evo solves p_gt ~= s * R @ p_est + t, so ``sim3_scale`` is the factor
   that takes estimate units to ground-truth units: an estimate that is the ground truth shrunk
   by 0.37 gives ``sim3_scale == 1 / 0.37``;
3. ATE: evo APE, translation part, RMSE, on the aligned estimate (ground-truth units);
4. RPE: evo RPE over consecutive matched poses (delta = 1 frame). The rotation angle is invariant
   to the alignment (a left-multiplied world transform cancels in T_i^-1 T_j), so it is computed
   on the unaligned estimate and stays defined when the alignment is not; the translation part
   uses the aligned estimate;
5. translation-direction error: evo has no such metric, so it is computed here with numpy. It is
   scale-free and, like the RPE rotation, unchanged by a Sim(3) world transform.

A degenerate alignment (the estimate never moves, or moves along one line, so Umeyama's
covariance has rank < 2) is an outcome of the estimator, not bad input: the metrics that need the
alignment are NaN, the others are still reported.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from evo.core import geometry, sync
from evo.core.metrics import APE, RPE, PoseRelation, StatisticsType, Unit
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from epi_vo.core.errors import EvaluationError

logger = logging.getLogger(__name__)

# Fewest matched poses that give two consecutive steps, hence a defined RPE and direction error
# and a non-trivial Sim(3) fit.
MIN_MATCHED_POSES = 3

# Numerical guards of the direction error, not tuning knobs: below these step lengths a
# translation direction is undefined (a stationary ground-truth step, in ground-truth units, or
# an estimate that held its pose, in estimate units).
_MIN_GT_STEP = 1e-6
_MIN_EST_STEP = 1e-9


class StampedPoses(NamedTuple):
    """Camera poses T_w_c with stamps; a plain ``(stamps_s, positions_xyz, quats_xyzw)`` tuple works too."""

    stamps_s: NDArray[np.float64]  # (N,) seconds, strictly increasing
    positions_xyz: NDArray[
        np.float64
    ]  # (N, 3) camera centre in world (translation of T_w_c)
    quats_xyzw: NDArray[np.float64]  # (N, 4) R_w_c as a quaternion, x, y, z, w order


@dataclass(frozen=True)
class TrajectoryMetrics:
    """Metrics of one estimated trajectory; NaN where a metric is undefined (see module docstring)."""

    matched_poses: int  # poses paired by stamp; every metric below uses only these
    ate_rmse: float  # APE translation RMSE after Sim(3) alignment, ground-truth units
    ate_percent_of_path: (
        float  # 100 * ate_rmse / ground-truth path length over the matched poses
    )
    sim3_scale: float  # Umeyama scale s of p_gt ~= s * R @ p_est + t (estimate -> ground-truth units)
    rpe_rot_deg_per_frame: (
        float  # RMSE of the relative rotation angle error, consecutive poses, deg
    )
    rpe_trans_rmse: (
        float  # RMSE of the relative translation error after Sim(3) alignment, GT units
    )
    trans_direction_err_deg: (
        float  # mean angle between estimated and GT step directions, deg
    )
    trans_direction_pairs: int  # consecutive pairs used for trans_direction_err_deg
    # Metric figures (meaningful when the estimate claims metres): ATE after an SE(3) alignment only (no
    # scale), % of the ground-truth path; median over consecutive pairs of |estimated step| / |GT step|.
    ate_se3_percent_of_path: float = float("nan")
    step_scale_median: float = float("nan")


def evaluate_trajectory(
    est: StampedPoses
    | tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    gt: StampedPoses
    | tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    max_time_diff: float = 0.01,
) -> TrajectoryMetrics:
    """Compare an estimated trajectory of camera poses T_w_c with ground truth.

    Args:
        est: estimated poses, ``(stamps_s (N,), positions_xyz (N, 3), quats_xyzw (N, 4))``, in any
            world frame and any scale.
        gt: ground-truth poses of the same camera optical frame, same layout, metric units.
        max_time_diff: largest stamp difference, in seconds, at which two poses are paired.

    Returns:
        The metrics over the stamp-matched poses (see ``TrajectoryMetrics``).

    Raises:
        EvaluationError: malformed or non-finite input, stamps not strictly increasing, or fewer
            than ``MIN_MATCHED_POSES`` poses matched by stamp.
    """
    if not np.isfinite(max_time_diff) or max_time_diff < 0.0:
        msg = f"max_time_diff must be a finite number >= 0 s, got {max_time_diff!r}"
        raise EvaluationError(msg)
    traj_est = to_evo_trajectory(est, "estimated trajectory")
    traj_gt = to_evo_trajectory(gt, "ground-truth trajectory")

    try:
        traj_gt, traj_est = sync.associate_trajectories(
            traj_gt, traj_est, max_diff=max_time_diff
        )
    except sync.SyncException as exc:
        msg = f"no poses matched by stamp within max_time_diff={max_time_diff} s: {exc}"
        raise EvaluationError(msg) from exc
    matched_poses = traj_est.num_poses
    if matched_poses < MIN_MATCHED_POSES:
        msg = (
            f"only {matched_poses} poses matched by stamp within max_time_diff={max_time_diff} s, "
            f"need at least {MIN_MATCHED_POSES}"
        )
        raise EvaluationError(msg)

    # Relative rotation needs no alignment: (S T_i)^-1 (S T_j) = T_i^-1 T_j for any world transform S.
    rpe_rot = RPE(
        PoseRelation.rotation_angle_deg,
        delta=1,
        delta_unit=Unit.frames,
        all_pairs=False,
    )
    rpe_rot.process_data((traj_gt, traj_est))
    rpe_rot_deg = rpe_rot.get_statistic(StatisticsType.rmse)

    direction_err_deg, direction_pairs = translation_direction_error(
        np.asarray(traj_est.poses_se3), np.asarray(traj_gt.poses_se3)
    )

    gt_path_length = float(traj_gt.path_length)
    _, ate_se3, _ = _aligned_ate(traj_est, traj_gt, correct_scale=False)
    ate_se3_percent = 100.0 * ate_se3 / gt_path_length if gt_path_length > 0.0 else float("nan")
    step_est = np.linalg.norm(np.diff(np.asarray(traj_est.positions_xyz), axis=0), axis=1)
    step_gt = np.linalg.norm(np.diff(np.asarray(traj_gt.positions_xyz), axis=0), axis=1)
    moving = step_gt > 1e-3 * max(float(np.median(step_gt)) if step_gt.size else 0.0, 1e-9)
    step_scale = float(np.median(step_est[moving] / step_gt[moving])) if np.any(moving) else float("nan")
    ate_percent = rpe_trans = float("nan")
    traj_est_aligned, ate_rmse, sim3_scale = _aligned_ate(traj_est, traj_gt, correct_scale=True)
    if traj_est_aligned is not None:
        if gt_path_length > 0.0:
            ate_percent = 100.0 * ate_rmse / gt_path_length
        rpe_t = RPE(
            PoseRelation.translation_part,
            delta=1,
            delta_unit=Unit.frames,
            all_pairs=False,
        )
        rpe_t.process_data((traj_gt, traj_est_aligned))
        rpe_trans = rpe_t.get_statistic(StatisticsType.rmse)

    return TrajectoryMetrics(
        matched_poses=matched_poses,
        ate_rmse=float(ate_rmse),
        ate_percent_of_path=float(ate_percent),
        sim3_scale=float(sim3_scale),
        rpe_rot_deg_per_frame=float(rpe_rot_deg),
        rpe_trans_rmse=float(rpe_trans),
        trans_direction_err_deg=direction_err_deg,
        trans_direction_pairs=direction_pairs,
        ate_se3_percent_of_path=float(ate_se3_percent),
        step_scale_median=step_scale,
    )


def _aligned_ate(traj_est: PoseTrajectory3D, traj_gt: PoseTrajectory3D, correct_scale: bool
                 ) -> tuple[PoseTrajectory3D | None, float, float]:
    """Umeyama-align a copy of the estimate onto the ground truth (p_gt ~= s * R @ p_est + t; s = 1 for
    SE(3)) and its APE translation RMSE: (aligned copy, ATE, s), or (None, NaN, NaN) when degenerate."""
    aligned = copy.deepcopy(traj_est)
    kind = "Sim(3)" if correct_scale else "SE(3)"
    try:
        _, _, scale = aligned.align(traj_gt, correct_scale=correct_scale)
    except geometry.GeometryException as exc:
        logger.warning("%s alignment is degenerate, its ATE (and RPE translation) is NaN: %s", kind, exc)
        return None, float("nan"), float("nan")
    ape = APE(PoseRelation.translation_part)
    ape.process_data((traj_gt, aligned))
    return aligned, float(ape.get_statistic(StatisticsType.rmse)), float(scale)


def translation_direction_error(
    T_w_c_est: NDArray[np.float64], T_w_c_gt: NDArray[np.float64]
) -> tuple[float, int]:
    """Mean angle between estimated and ground-truth step directions of consecutive poses.

    For each consecutive pair (i, i+1) the step is expressed in the earlier camera's frame,
    t_ci = R_w_ci^T (p_w_{i+1} - p_w_i), which is what two-view geometry recovers (up to scale) and
    is invariant to a Sim(3) change of world frame. The error is the unsigned angle between the
    estimated and ground-truth t_ci, computed as atan2(|a x b|, a . b) (accurate near 0 and 180 deg).
    Pairs where either step is too short to have a direction (the ground truth stood still, or the
    estimate held its pose) are skipped. evo has no such metric.

    Args:
        T_w_c_est: (M, 4, 4) estimated poses, camera into world, index-matched with ``T_w_c_gt``.
        T_w_c_gt: (M, 4, 4) ground-truth poses.

    Returns:
        (mean error in degrees, number of pairs used); the mean is NaN when no pair is usable.
    """
    if (
        T_w_c_est.shape != T_w_c_gt.shape
        or T_w_c_est.ndim != 3
        or T_w_c_est.shape[1:] != (4, 4)
    ):
        msg = (
            f"expected two (M, 4, 4) pose stacks of equal shape, got {T_w_c_est.shape} and "
            f"{T_w_c_gt.shape}"
        )
        raise EvaluationError(msg)
    t_prev_est = _steps_in_previous_camera(T_w_c_est)
    t_prev_gt = _steps_in_previous_camera(T_w_c_gt)
    usable = (np.linalg.norm(t_prev_gt, axis=1) >= _MIN_GT_STEP) & (
        np.linalg.norm(t_prev_est, axis=1) >= _MIN_EST_STEP
    )
    n_pairs = int(np.count_nonzero(usable))
    if n_pairs == 0:
        return float("nan"), 0
    a = t_prev_est[usable]
    b = t_prev_gt[usable]
    angles_rad = np.arctan2(
        np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ni,ni->n", a, b)
    )
    return float(np.degrees(angles_rad).mean()), n_pairs


def _steps_in_previous_camera(T_w_c: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 4, 4) poses T_w_c -> (M-1, 3) steps R_w_ci^T (p_w_{i+1} - p_w_i), in camera i's frame."""
    R_w_prev = T_w_c[:-1, :3, :3]
    step_w = T_w_c[1:, :3, 3] - T_w_c[:-1, :3, 3]
    return np.einsum("nji,nj->ni", R_w_prev, step_w)


def to_evo_trajectory(
    poses: StampedPoses
    | tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    name: str,
) -> PoseTrajectory3D:
    """Validate ``(stamps_s, positions_xyz, quats_xyzw)`` and build an evo trajectory (wxyz quaternions)."""
    if len(poses) != 3:
        msg = f"{name}: expected (stamps_s, positions_xyz, quats_xyzw), got {len(poses)} items"
        raise EvaluationError(msg)
    stamps_s, positions_xyz, quats_xyzw = (
        np.asarray(a, dtype=np.float64) for a in poses
    )
    n = stamps_s.shape[0] if stamps_s.ndim == 1 else -1
    problems = []
    if stamps_s.ndim != 1:
        problems.append(f"stamps_s must have shape (N,), got {stamps_s.shape}")
    if positions_xyz.shape != (n, 3):
        problems.append(
            f"positions_xyz must have shape (N, 3) = ({n}, 3), got {positions_xyz.shape}"
        )
    if quats_xyzw.shape != (n, 4):
        problems.append(
            f"quats_xyzw must have shape (N, 4) = ({n}, 4), got {quats_xyzw.shape}"
        )
    if problems:
        msg = f"{name}: " + "; ".join(problems)
        raise EvaluationError(msg)
    if n < MIN_MATCHED_POSES:
        msg = f"{name}: {n} poses, need at least {MIN_MATCHED_POSES}"
        raise EvaluationError(msg)
    for label, values in (
        ("stamps_s", stamps_s),
        ("positions_xyz", positions_xyz),
        ("quats_xyzw", quats_xyzw),
    ):
        if not np.isfinite(values).all():
            msg = f"{name}: {label} has non-finite values"
            raise EvaluationError(msg)
    # Consecutive-frame metrics assume temporal order; a repeated stamp would make pairing ambiguous.
    if not (np.diff(stamps_s) > 0.0).all():
        msg = f"{name}: stamps_s must be strictly increasing"
        raise EvaluationError(msg)
    # evo normalizes quaternions, but a (near-)zero one has no rotation to normalize to.
    if (np.linalg.norm(quats_xyzw, axis=1) < 1e-6).any():
        msg = f"{name}: quats_xyzw has zero-norm quaternions"
        raise EvaluationError(msg)
    quats_wxyz = quats_xyzw[:, [3, 0, 1, 2]]
    return PoseTrajectory3D(
        positions_xyz=positions_xyz,
        orientations_quat_wxyz=quats_wxyz,
        timestamps=stamps_s,
        name=name,
    )
