"""Twist covariance consistency: the published velocity against the ground truth's, per frame.

robot_localization fuses a visual odometry's twist (differential mode); its covariance must say how far
the velocity can be off. For each pair of consecutive odometry messages of tracking frames, the true
body velocity is the ground truth's motion between the two stamps, expressed in the child (base)
frame of the later one, over the time between them; the error against the published twist is
normalised by the published twist covariance (NEES, 3 dof each for linear and angular velocity).

Linear velocity in VO units is compared after the one global scale that fits best (least squares),
metres as they are. The twist of a frame whose covariance says "unknown" (lost, the frame the scale
jumped to metres, ...) is not evaluated.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.odometry import default_T_base_cam
from epi_vo.core.transforms import invert_T
from epi_vo.io.odometry_bag import OdometryTrack
from epi_vo.io.trajectory import StampedPoses
from epi_vo.tools.evaluation import CHI2_3DOF_99, nearest_rows, poses_from_xyz_quat, rotation_vectors

UNKNOWN_VARIANCE = 1.0e6  # a twist variance at or above this says "unknown": not evaluated


@dataclass(frozen=True)
class TwistNees:
    """Per evaluated frame the linear and angular twist NEES (3 dof each), and the fitted scale."""

    nees_linear: NDArray[np.float64]
    nees_angular: NDArray[np.float64]
    scale: float
    bound: float = CHI2_3DOF_99
    # (M,) per judged twist the odometry message it is (the later of the pair), and that frame's record
    # index (``replay_twist_nees``; empty without the records)
    rows: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_index: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    # A NaN NEES: not judged (no scale to fit: the ground truth did not move). Means and shares are over
    # the judged ones; NaN when there is none.
    @property
    def mean_linear(self) -> float:
        return _mean(self.nees_linear)

    @property
    def mean_angular(self) -> float:
        return _mean(self.nees_angular)

    @property
    def inside_linear_percent(self) -> float:
        return _inside(self.nees_linear, self.bound)

    @property
    def inside_angular_percent(self) -> float:
        return _inside(self.nees_angular, self.bound)


def _mean(nees: NDArray[np.float64]) -> float:
    judged = nees[np.isfinite(nees)]
    return float(np.mean(judged)) if judged.size else float("nan")


def _inside(nees: NDArray[np.float64], bound: float) -> float:
    judged = nees[np.isfinite(nees)]
    return 100.0 * float(np.mean(judged <= bound)) if judged.size else float("nan")


def twist_consistency(odometry: OdometryTrack, T_g_base_gt: NDArray[np.float64], evaluate: NDArray[np.bool_],
                      *, metric: bool) -> TwistNees:
    """Twist NEES of ``odometry`` against ground-truth base poses ``T_g_base_gt`` (N, 4, 4), one per
    odometry message (same order); ``evaluate`` (N,) the messages to judge (tracking, with ground
    truth). A message is judged with the one before it; ``metric``: no scale is fitted."""
    n = odometry.stamps_ns.shape[0]
    rows = [k for k in range(1, n) if evaluate[k] and evaluate[k - 1]
            and odometry.twist_covariance[k][0, 0] < UNKNOWN_VARIANCE
            and odometry.twist_covariance[k][3, 3] < UNKNOWN_VARIANCE
            and odometry.stamps_ns[k] > odometry.stamps_ns[k - 1]]
    if not rows:
        return TwistNees(np.zeros(0), np.zeros(0), 1.0)
    idx = np.asarray(rows)
    dt = (odometry.stamps_ns[idx] - odometry.stamps_ns[idx - 1]) * 1e-9
    T_rel = np.einsum("kij,kjl->kil", np.stack([invert_T(T) for T in T_g_base_gt[idx - 1]]), T_g_base_gt[idx])
    R_t = np.transpose(T_rel[:, :3, :3], (0, 2, 1))
    v_gt = np.einsum("kij,kj->ki", R_t, T_rel[:, :3, 3]) / dt[:, None]
    w_gt = np.einsum("kij,kj->ki", R_t, rotation_vectors(T_rel[:, :3, :3])) / dt[:, None]
    v, w = odometry.linear_velocity[idx], odometry.angular_velocity[idx]
    C = odometry.twist_covariance[idx]
    s = 1.0
    if not metric:
        den = float(np.sum(v * v))
        s = float(np.sum(v * v_gt)) / den if den > 0 else 1.0
    e_v = s * v - v_gt
    e_w = w - w_gt
    if s > 0.0:
        nees_v = np.einsum("ki,ki->k", e_v, np.linalg.solve(C[:, :3, :3] * s * s, e_v[..., None])[..., 0])
    else:  # the ground truth did not move along the estimate: no scale, the linear twist is not judged
        nees_v = np.full(idx.size, np.nan)
    nees_w = np.einsum("ki,ki->k", e_w, np.linalg.solve(C[:, 3:, 3:], e_w[..., None])[..., 0])
    return TwistNees(nees_v, nees_w, s, rows=idx.astype(np.int64))


def poses_at(gt_stamps_s: NDArray[np.float64], gt_pos: NDArray[np.float64], gt_quat: NDArray[np.float64],
             stamps_ns: NDArray[np.int64], T_cam_base: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ground-truth base poses (N, 4, 4) at the nearest ground-truth stamp of each of ``stamps_ns``."""
    j = nearest_rows(gt_stamps_s, stamps_ns.astype(np.float64) * 1e-9)
    return poses_from_xyz_quat(gt_pos[j], gt_quat[j]) @ T_cam_base


def replay_twist_nees(records: list[dict], odometry: OdometryTrack,
                      gt: StampedPoses,
                      T_base_cam: NDArray[np.float64] | None = None) -> TwistNees:
    """:func:`twist_consistency` of a replay: its frame records, its /vo/odometry and the ground-truth
    camera poses (TUM), turned into base poses with the extrinsic the odometry was made with
    (``T_base_cam``; default: the optical rotation). Tracking frames are judged; metres when the run
    established them."""
    by_stamp = {int(r.get("stamp_ns", -1)): r for r in records}
    evaluate = np.array([by_stamp.get(int(t), {}).get("state") == "tracking" for t in odometry.stamps_ns], bool)
    metric = any(bool(r.get("metric_scale")) for r in records if r.get("state") == "tracking")
    if metric:  # frames before metric scale was established are in VO units
        evaluate &= np.array([bool(by_stamp.get(int(t), {}).get("metric_scale")) for t in odometry.stamps_ns], bool)
    gt_s, gt_p, gt_q = (np.asarray(a, dtype=np.float64) for a in gt)
    T_bc = default_T_base_cam() if T_base_cam is None else np.asarray(T_base_cam, dtype=np.float64)
    T_gt = poses_at(gt_s, gt_p, gt_q, odometry.stamps_ns, invert_T(T_bc))
    r = twist_consistency(odometry, T_gt, evaluate, metric=metric)
    index = np.array([int(by_stamp.get(int(odometry.stamps_ns[k]), {}).get("index", -1)) for k in r.rows],
                     np.int64)
    return dataclasses.replace(r, frame_index=index)
