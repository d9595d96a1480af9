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

import collections
import copy
import enum
import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from evo.core import geometry, sync
from evo.core.metrics import APE, RPE, PoseRelation, StatisticsType, Unit
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from epi_vo.core.covariance import given
from epi_vo.core.errors import EpiVoError, EvaluationError
from epi_vo.core.odometry import default_T_base_cam
from epi_vo.core.transforms import invert_T
from epi_vo.io import tum
from epi_vo.io.odometry_bag import OdometryTrack, read_estimate_odometry
from epi_vo.io.trajectory import StampedPoses
from epi_vo.tools.replay_outputs import read_recorded_extrinsic

logger = logging.getLogger(__name__)

# Fewest matched poses that give two consecutive steps, hence a defined RPE and direction error
# and a non-trivial Sim(3) fit.
MIN_MATCHED_POSES = 3

# Numerical guards of the direction error, not tuning knobs: below these step lengths a
# translation direction is undefined (a stationary ground-truth step, in ground-truth units, or
# an estimate that held its pose, in estimate units).
_MIN_GT_STEP = 1e-6
_MIN_EST_STEP = 1e-9


def metric_poses(est: StampedPoses,
                 records: Sequence[dict[str, Any]]) -> tuple[StampedPoses, int]:
    """The poses of ``est`` that the trajectory metrics judge, and how many were left out.

    A run whose scale source established metres (a record with ``metric_scale``) had, before that,
    poses in VO units (vo/odometry held its position then, with a covariance that says it is unknown):
    no length in metres. Its metrics (Sim(3) and SE(3) ATE, step scale, RPE) are over the poses it
    published in metres, as the covariance consistency (``replay_nees``) is; the others are counted. A
    run in VO units keeps every pose.
    Poses are matched to ``records`` (frames.jsonl) by ``stamp_ns``.
    """
    stamps = np.asarray(est[0], dtype=np.float64)
    metric_ns = {int(r["stamp_ns"]) for r in records if r.get("metric_scale") and "stamp_ns" in r}
    if not metric_ns:
        return StampedPoses(stamps, np.asarray(est[1]), np.asarray(est[2])), 0
    metric_s = np.array(sorted(metric_ns), dtype=np.float64) * 1e-9
    # Within 1 us: a TUM stamp in float seconds is not exact to the nanosecond; frames are ms apart.
    keep = np.abs(metric_s[nearest_rows(metric_s, stamps)] - stamps) <= 1e-6
    return (StampedPoses(stamps[keep], np.asarray(est[1])[keep], np.asarray(est[2])[keep]),
            int(np.count_nonzero(~keep)))


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
    est: StampedPoses,
    gt: StampedPoses,
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
    poses: StampedPoses,
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


# ==================================================================================================
# Covariance consistency (NEES)
# ==================================================================================================

# Chi-square quantile, 3 degrees of freedom, 99 %: a consistent 3-dof error is within it 99 % of the time.
CHI2_3DOF_99 = 11.345
TRACKING_STATE = "tracking"


class AlignmentAnchor(enum.Enum):
    """How the estimate is put into the ground truth's frame before the errors are taken.

    ORIGIN: rotation and translation from the anchor pose (the odometry origin, where the published
    covariance is ~0); only the scale is fitted (least squares over the evaluated positions, relative to
    the anchor): the error accumulated since the origin, as the covariance describes it. UMEYAMA: the
    whole Sim(3) (or SE(3)) fitted to the evaluated positions (evo's), as for ATE; it absorbs 7 dof of
    error and puts an error on the early frames whose covariance is still small."""

    ORIGIN = "origin"
    UMEYAMA = "umeyama"


@dataclass(frozen=True)
class NeesResult:
    """Normalised estimation error squared of position and rotation, per evaluated frame and summed up.

    ``frame_index`` (M,) the evaluated frames (tracking, with ground truth); ``nees_pos`` / ``nees_rot``
    (M,) their NEES (3 dof each); NaN where undefined (no alignment: ``nees_pos`` all NaN).
    ``skipped`` counts the frames not evaluated, by reason (their state, "no ground truth", "no
    odometry message", "metric scale not established"). ``alignment`` is "sim3" or "se3" (metric scale
    established: no scale fitted); ``scale`` the fitted s of p_gt ~= s R p_est + t (1 for se3).
    """

    frame_index: NDArray[np.int64]
    nees_pos: NDArray[np.float64]
    nees_rot: NDArray[np.float64]
    skipped: dict[str, int]
    alignment: str
    anchor: AlignmentAnchor
    scale: float
    bound: float = CHI2_3DOF_99

    @property
    def evaluated(self) -> int:
        return int(self.frame_index.size)

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())

    @property
    def mean_nees_pos(self) -> float:
        return _nanmean(self.nees_pos)

    @property
    def mean_nees_rot(self) -> float:
        return _nanmean(self.nees_rot)

    @property
    def inside_pos_percent(self) -> float:
        return _inside_percent(self.nees_pos, self.bound)

    @property
    def inside_rot_percent(self) -> float:
        return _inside_percent(self.nees_rot, self.bound)


def _nanmean(a: NDArray[np.float64]) -> float:
    finite = a[np.isfinite(a)]
    return float(finite.mean()) if finite.size else float("nan")


def _inside_percent(a: NDArray[np.float64], bound: float) -> float:
    finite = a[np.isfinite(a)]
    return 100.0 * float(np.count_nonzero(finite <= bound)) / finite.size if finite.size else float("nan")


def rotation_vectors(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 3, 3) rotation matrices -> (M, 3) rotation vectors (axis * angle, rad), angle in [0, pi].

    Vectorised Shepperd (as ``transforms.quat_xyzw_from_rotation``, per matrix the same pivot: the
    largest of the trace and the diagonal), then the angle from atan2 of the vector and scalar parts."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    if not np.all(np.isfinite(R)):
        raise EpiVoError("rotation_vectors: non-finite rotation matrix")
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    trace = r00 + r11 + r22
    pivot = np.argmax(np.stack([trace, r00, r11, r22], axis=1), axis=1)
    q = np.empty((R.shape[0], 4))
    for p, (a, b, c) in enumerate(((1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0))):
        m = pivot == p
        if not np.any(m):
            continue
        Rm = R[m]
        s = 2.0 * np.sqrt(np.maximum(1.0 + a * Rm[:, 0, 0] + b * Rm[:, 1, 1] + c * Rm[:, 2, 2], 0.0))
        d21, d02, d10 = Rm[:, 2, 1] - Rm[:, 1, 2], Rm[:, 0, 2] - Rm[:, 2, 0], Rm[:, 1, 0] - Rm[:, 0, 1]
        s01, s02, s12 = Rm[:, 0, 1] + Rm[:, 1, 0], Rm[:, 0, 2] + Rm[:, 2, 0], Rm[:, 1, 2] + Rm[:, 2, 1]
        cols = ((d21 / s, d02 / s, d10 / s, 0.25 * s), (0.25 * s, s01 / s, s02 / s, d21 / s),
                (s01 / s, 0.25 * s, s12 / s, d02 / s), (s02 / s, s12 / s, 0.25 * s, d10 / s))[p]
        q[m] = np.stack(cols, axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0.0] *= -1.0  # w >= 0: the angle in [0, pi]
    v, w = q[:, :3], q[:, 3]
    n = np.linalg.norm(v, axis=1)
    small = n < 1e-12
    factor = np.where(small, 2.0, 2.0 * np.arctan2(n, w) / np.where(small, 1.0, n))
    return v * factor[:, None]


def _quadratic_forms(e: NDArray[np.float64], P: NDArray[np.float64]) -> NDArray[np.float64]:
    """e_i^T P_i^-1 e_i for (M, 3) errors and (M, 3, 3) covariances (pseudo-inverse where singular)."""
    out = np.full(e.shape[0], np.nan)
    for i in range(e.shape[0]):
        try:
            out[i] = float(e[i] @ np.linalg.solve(P[i], e[i]))
        except np.linalg.LinAlgError:
            out[i] = float(e[i] @ np.linalg.pinv(P[i]) @ e[i])
    return out


def covariance_consistency(
    T_o_b_est: NDArray[np.float64],
    cov_o: NDArray[np.float64],
    T_g_b_gt: NDArray[np.float64],
    evaluate: NDArray[np.bool_],
    *,
    metric: bool = False,
    anchor: AlignmentAnchor = AlignmentAnchor.ORIGIN,
    anchor_row: int = 0,
    frame_index: NDArray[np.int64] | None = None,
    skipped: dict[str, int] | None = None,
) -> NeesResult:
    """Position and rotation NEES of estimated poses against their published covariance.

    Args:
        T_o_b_est: (N, 4, 4) estimated poses, body into the odometry frame o (the pose of /vo/odometry).
        cov_o: (N, 6, 6) their published covariances over (x, y, z, rot_x, rot_y, rot_z) in o: the
            position error p_true - p_est and the rotation error delta with R_true = Exp(delta) R_est
            (a left perturbation in o, rad), in the estimate's units.
        T_g_b_gt: (N, 4, 4) ground-truth poses of the same body, row-matched, any world frame g, any
            units (metric when ``metric``).
        evaluate: (N,) which rows get a NEES (tracking frames); the others are ignored.
        metric: the estimate claims metres: SE(3) alignment, no scale fitted (s = 1).
        anchor: how the alignment is found (see ``AlignmentAnchor``).
        anchor_row: the row of the odometry origin for ``AlignmentAnchor.ORIGIN``.
        frame_index: (N,) frame numbers of the rows (default 0..N-1), reported for the evaluated ones.
        skipped: counts of frames left out before this call, by reason (copied into the result).

    The alignment S = (s, R, t) takes the estimate into g: p_g ~= s R p_o + t, R_g ~= R R_o. Errors are
    taken in g and expressed back in o, where the covariance lives: e_pos = R^T (p_gt - (s R p_est + t)) / s,
    e_rot = R^T Log(R_gt (R R_est)^T); equivalently the covariance is rotated by R (and the position block
    scaled by s^2) into g. NEES = e^T P^-1 e with the 3x3 position / rotation block P of ``cov_o``; for a
    consistent estimator it is chi-square with 3 dof (mean 3, 99 % below ``CHI2_3DOF_99``). Both NEES are
    invariant to a Sim(3) change of the estimate's frame (SE(3) when ``metric``) with the covariance
    transformed alike, and to one of the ground truth's.

    Returns:
        The per-frame NEES; ``nees_pos`` is NaN when no alignment exists (fewer than 2 evaluated frames,
        an estimate that never left the anchor, or a degenerate Umeyama fit).

    Raises:
        EvaluationError: shapes that do not match, non-finite poses or covariances, a bad anchor row.
    """
    T_est = np.asarray(T_o_b_est, dtype=np.float64)
    cov = np.asarray(cov_o, dtype=np.float64)
    T_gt = np.asarray(T_g_b_gt, dtype=np.float64)
    mask = np.asarray(evaluate, dtype=bool)
    n = T_est.shape[0] if T_est.ndim == 3 else -1
    if T_est.shape != (n, 4, 4) or T_gt.shape != (n, 4, 4) or cov.shape != (n, 6, 6) or mask.shape != (n,):
        msg = (f"expected (N, 4, 4) poses, (N, 6, 6) covariances, (N, 4, 4) ground truth and (N,) mask, got "
               f"{T_est.shape}, {cov.shape}, {T_gt.shape} and {mask.shape}")
        raise EvaluationError(msg)
    for name, a in (("estimated poses", T_est), ("covariances", cov), ("ground-truth poses", T_gt)):
        if not np.isfinite(a[mask]).all():
            msg = f"{name} of the evaluated frames have non-finite values"
            raise EvaluationError(msg)
    if anchor is AlignmentAnchor.ORIGIN and not 0 <= anchor_row < n:
        msg = f"anchor_row {anchor_row} is not a row of the {n} poses"
        raise EvaluationError(msg)
    idx = np.arange(n, dtype=np.int64) if frame_index is None else np.asarray(frame_index, dtype=np.int64)
    s, R, t = _nees_alignment(T_est, T_gt, mask, metric, anchor, anchor_row)
    T_e, P, T_g = T_est[mask], cov[mask], T_gt[mask]
    nees_pos = np.full(T_e.shape[0], np.nan)
    if math.isfinite(s):
        e_g = T_g[:, :3, 3] - (s * T_e[:, :3, 3] @ R.T + t)
        nees_pos = _quadratic_forms(e_g @ R / s, P[:, :3, :3])  # rows: R^T e_g / s, the error in o
    R_est_g = np.einsum("ij,njk->nik", R, T_e[:, :3, :3])
    e_rot_g = rotation_vectors(np.einsum("nij,nkj->nik", T_g[:, :3, :3], R_est_g))  # Log(R_gt R_est_g^T)
    nees_rot = _quadratic_forms(e_rot_g @ R, P[:, 3:, 3:])
    return NeesResult(idx[mask], nees_pos, nees_rot, dict(skipped or {}), "se3" if metric else "sim3", anchor,
                      s if math.isfinite(s) else float("nan"))


def _nees_alignment(T_est: NDArray[np.float64], T_gt: NDArray[np.float64], mask: NDArray[np.bool_], metric: bool,
                    anchor: AlignmentAnchor, anchor_row: int) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """(s, R, t) of p_g ~= s R p_o + t; s is NaN when no alignment exists (R then from the anchor or I)."""
    p_e, p_g = T_est[:, :3, 3], T_gt[:, :3, 3]
    if anchor is AlignmentAnchor.ORIGIN:
        a = anchor_row
        R = T_gt[a, :3, :3] @ T_est[a, :3, :3].T
        s = 1.0
        if not metric:
            d_e = (p_e[mask] - p_e[a]) @ R.T
            d_g = p_g[mask] - p_g[a]
            den = float(np.sum(d_e * d_e))
            s = float(np.sum(d_e * d_g)) / den if den > 1e-18 else float("nan")
            if not s > 0.0:
                s = float("nan")
        t = p_g[a] - (s if math.isfinite(s) else 1.0) * R @ p_e[a]
        return s, R, t
    if np.count_nonzero(mask) < 3:
        return float("nan"), np.eye(3), np.zeros(3)
    try:
        R, t, s = geometry.umeyama_alignment(p_e[mask].T, p_g[mask].T, with_scale=not metric)
    except geometry.GeometryException:
        return float("nan"), np.eye(3), np.zeros(3)
    return float(s), np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)


def nearest_rows(sorted_stamps: NDArray[np.float64], stamps: NDArray[np.float64]) -> NDArray[np.int64]:
    """For each of ``stamps`` the row of the nearest of ``sorted_stamps`` (ascending, not empty)."""
    last = sorted_stamps.size - 1
    j = np.clip(np.searchsorted(sorted_stamps, stamps), 1, max(last, 1))
    return np.where(np.abs(sorted_stamps[j - 1] - stamps) <= np.abs(sorted_stamps[np.minimum(j, last)] - stamps),
                    j - 1, np.minimum(j, last)).astype(np.int64)


def poses_from_xyz_quat(positions: NDArray[np.float64], quats_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 3) positions and (N, 4) x, y, z, w quaternions (normalised here) -> (N, 4, 4) homogeneous poses,
    as ``transforms.make_T(transforms.rotation_from_quat_xyzw(q), p)`` row by row. EpiVoError for a
    non-finite value or a (near) zero quaternion."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)
    if p.shape[0] != q.shape[0]:
        raise EpiVoError(f"poses_from_xyz_quat: {p.shape[0]} positions, {q.shape[0]} quaternions")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise EpiVoError("poses_from_xyz_quat: non-finite position or quaternion")
    norm = np.linalg.norm(q, axis=1)
    if np.any(norm < 1e-12):
        raise EpiVoError("poses_from_xyz_quat: a quaternion has (near) zero norm, cannot be normalised")
    x, y, z, w = (q / norm[:, None]).T
    T = np.tile(np.eye(4), (p.shape[0], 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = 2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = 2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)
    T[:, :3, 3] = p
    return T


def replay_nees(
    records: Sequence[dict[str, Any]],
    odometry: OdometryTrack,
    gt: StampedPoses,
    *,
    T_base_cam: NDArray[np.float64] | None = None,
    anchor: AlignmentAnchor = AlignmentAnchor.ORIGIN,
    max_time_diff: float = 0.01,
    from_ns: int | None = None,
) -> NeesResult:
    """Covariance consistency of a replay: its frame records, its /vo/odometry messages and ground truth.

    ``records`` are frames.jsonl (``stamp_ns``, ``index``, ``state``, ``metric_scale``); ``odometry`` the
    replay's /vo/odometry (base_link in odom, covariance as published, matched by header stamp); ``gt``
    ground-truth camera optical-frame poses (TUM), turned into base poses with ``T_base_cam`` (default:
    the optical rotation) and paired with the nearest stamp within ``max_time_diff`` s.

    Only frames in state ``tracking`` are evaluated; lost, initializing, rotation_only and static frames
    keep their meaning (a held pose with an "unknown" or "still" covariance) and are counted in
    ``skipped`` by state. Once the run established metres (a record with ``metric_scale``) the alignment
    is SE(3) over the metric frames (earlier ones skipped: "metric scale not established"), else Sim(3).
    The anchor is the first odometry message with ground truth (the odometry origin).

    ``from_ns``: judge only from this image stamp on (earlier ground truth contradicted by the images:
    ``tools.gt_check``), anchored at the first tracking frame there, each covariance given the anchor's
    (``conditioned_on``); earlier frames are skipped as "before the checked ground truth".

    Raises:
        EvaluationError: no odometry message, or none paired with ground truth.
    """
    T_bc = default_T_base_cam() if T_base_cam is None else np.asarray(T_base_cam, dtype=np.float64)
    T_cb = invert_T(T_bc)
    gt_stamps, gt_pos, gt_quat = (np.asarray(a, dtype=np.float64) for a in gt)
    if odometry.stamps_ns.size == 0:
        msg = "no odometry messages"
        raise EvaluationError(msg)
    if gt_stamps.size == 0:
        msg = "no ground-truth poses"
        raise EvaluationError(msg)
    row_of_stamp = {int(s): i for i, s in enumerate(odometry.stamps_ns)}
    odo_s = odometry.stamps_ns.astype(np.float64) * 1e-9
    j = nearest_rows(gt_stamps, odo_s)
    has_gt = np.abs(gt_stamps[j] - odo_s) <= max_time_diff
    if not has_gt.any():
        msg = f"no odometry message has a ground-truth pose within {max_time_diff} s"
        raise EvaluationError(msg)
    metric = any(bool(r.get("metric_scale")) for r in records if r.get("state") == TRACKING_STATE)
    skipped: collections.Counter[str] = collections.Counter()
    evaluate = np.zeros(odometry.stamps_ns.size, dtype=bool)
    frame_index = np.full(odometry.stamps_ns.size, -1, dtype=np.int64)
    for rec in records:
        state = str(rec.get("state"))
        row = row_of_stamp.get(int(rec.get("stamp_ns", -1)))
        if row is not None:
            frame_index[row] = int(rec["index"])
        if state != TRACKING_STATE:
            skipped[state] += 1
        elif row is None:
            skipped["no odometry message"] += 1
        elif not has_gt[row]:
            skipped["no ground truth"] += 1
        elif metric and not rec.get("metric_scale"):
            skipped["metric scale not established"] += 1
        elif from_ns is not None and int(rec["stamp_ns"]) < from_ns:
            skipped["before the checked ground truth"] += 1
        else:
            evaluate[row] = True
    T_est = poses_from_xyz_quat(odometry.positions, odometry.quats_xyzw)
    T_gt = poses_from_xyz_quat(gt_pos[j], gt_quat[j]) @ T_cb  # T_g_base = T_g_cam T_cam_base
    cov = odometry.pose_covariance
    anchor_row = int(np.argmax(has_gt))
    if from_ns is not None:
        if not evaluate.any():
            msg = f"no tracking frame with ground truth at or after {from_ns} ns"
            raise EvaluationError(msg)
        anchor_row = int(np.argmax(evaluate))
        evaluate[anchor_row] = False  # its error is zero by construction
        skipped["anchor"] = 1
        cov = conditioned_on(T_est, cov, anchor_row)
    return covariance_consistency(T_est, cov, T_gt, evaluate, metric=metric, anchor=anchor,
                                  anchor_row=anchor_row, frame_index=frame_index, skipped=dict(skipped))


def conditioned_on(T_o_b: NDArray[np.float64], cov_o: NDArray[np.float64], a: int) -> NDArray[np.float64]:
    """Each pose's covariance given pose ``a``'s (as published, in o), as the pipeline's chain composes
    them: ``core.covariance.given`` (P_i - J P_a J^T, J the lever arm from a to i)."""
    p = T_o_b[:, :3, 3]
    return np.array([given(cov_o[i], cov_o[a], p[a], p[i]) for i in range(cov_o.shape[0])]).reshape(cov_o.shape)


def replay_dir_nees(directory: str | Path, anchor: AlignmentAnchor = AlignmentAnchor.ORIGIN,
                    from_ns: int | None = None) -> NeesResult | None:
    """:func:`replay_nees` of an ``epi-vo replay`` output directory (frames.jsonl, output.mcap,
    groundtruth.tum, and the extrinsic stats.json records); None when it has no ground truth. Raises
    EvaluationError when the files cannot be read or evaluated (the message names the file)."""
    d = Path(directory)
    if not (d / "groundtruth.tum").is_file():
        return None
    try:
        records = [json.loads(line) for line in (d / "frames.jsonl").read_text(encoding="utf-8").splitlines()
                   if line.strip()]
        odometry = read_estimate_odometry(d / "output.mcap")  # the motion as estimated, in its units
        gt = tum.read_tum(d / "groundtruth.tum")
        T_base_cam = read_recorded_extrinsic(d)  # the odometry's (None: the default extrinsic)
    except (OSError, UnicodeDecodeError, ValueError, EpiVoError) as exc:  # ValueError: JSON, the extrinsic
        msg = f"{d}: cannot read the replay output for the covariance check: {exc}"
        raise EvaluationError(msg) from None
    return replay_nees(records, odometry, gt, T_base_cam=T_base_cam, anchor=anchor, from_ns=from_ns)
