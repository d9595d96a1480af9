"""Covariance consistency of a replay from what it published, for ``epi-vo replay`` with ground truth.

The replay keeps each /vo/odometry sample it writes (pose, twist and their covariances, as published)
and the frames' states in memory (:class:`OdometryLog`), so the NEES of the pose
(:func:`epi_vo.tools.evaluation.replay_nees`) and of the twist
(:func:`epi_vo.tools.twist_consistency.replay_twist_nees`) are computed without reading output.mcap
back: the same numbers as the benchmark's and the report's, which read it. (The evaluation modules,
which import evo, are imported only when ground truth is there to evaluate against.)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from epi_vo.core.odometry import OdometrySample
from epi_vo.io.odometry_bag import OdometryTrack
from epi_vo.io.trajectory import StampedPoses

# stats.json ``metrics`` keys this module adds (NaN, written as null, when there is nothing to judge)
NEES_KEYS = ("nees_frames", "nees_pos", "nees_pos_inside_percent", "nees_rot", "nees_rot_inside_percent",
             "nees_twist_linear", "nees_twist_linear_inside_percent", "nees_twist_angular",
             "nees_twist_angular_inside_percent")


class OdometryLog:
    """The odometry samples a replay published and the state of the frame each belongs to."""

    def __init__(self) -> None:
        self._samples: list[OdometrySample] = []
        self.records: list[dict[str, Any]] = []

    def add(self, sample: OdometrySample, record: dict[str, Any]) -> None:
        self._samples.append(sample)
        self.records.append({k: record.get(k) for k in ("stamp_ns", "index", "state", "metric_scale")})

    def track(self, frame_id: str, child_frame_id: str) -> OdometryTrack:
        s = self._samples

        def stack(values: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
            return np.array(values, dtype=np.float64).reshape((len(values), *shape))

        return OdometryTrack(np.array([x.stamp_ns for x in s], dtype=np.int64),
                             stack([x.position for x in s], (3,)), stack([x.quat_xyzw for x in s], (4,)),
                             stack([x.pose_covariance for x in s], (6, 6)),
                             stack([x.twist_covariance for x in s], (6, 6)), frame_id, child_frame_id,
                             stack([x.linear_velocity for x in s], (3,)), stack([x.angular_velocity for x in s], (3,)))


def consistency_metrics(log: OdometryLog, gt: StampedPoses, frame_id: str,
                        child_frame_id: str, T_base_cam: np.ndarray | None = None) -> dict[str, Any]:
    """Mean NEES (3 dof each; consistent: 3) of the tracking frames' position, rotation, linear and angular
    velocity against the published covariances, and the share inside the chi-square 99 % bound. The
    ground-truth camera poses become base poses with the odometry's extrinsic ``T_base_cam`` (default: the
    optical rotation).

    Raises:
        EvaluationError: no odometry sample, or none with ground truth.
    """
    from epi_vo.tools.evaluation import replay_nees  # evo: only with ground truth
    from epi_vo.tools.twist_consistency import replay_twist_nees

    track = log.track(frame_id, child_frame_id)
    pose = replay_nees(log.records, track, gt, T_base_cam=T_base_cam)
    twist = replay_twist_nees(log.records, track, gt, T_base_cam)
    values = (pose.evaluated, pose.mean_nees_pos, pose.inside_pos_percent, pose.mean_nees_rot,
              pose.inside_rot_percent, twist.mean_linear, twist.inside_linear_percent, twist.mean_angular,
              twist.inside_angular_percent)
    return {k: v if k == "nees_frames" else float(v) for k, v in zip(NEES_KEYS, values, strict=True)}


def format_consistency(m: dict[str, Any]) -> str | None:
    """The replay summary's covariance line, or None when the metrics have none."""
    if "nees_frames" not in m:
        return None
    if not m["nees_frames"]:
        return "  covariance    not judged: no tracking frame with ground truth"

    def f(key: str, nd: int) -> str:
        v = m.get(key)
        return "n/a" if v is None or not math.isfinite(v) else f"{v:.{nd}f}"

    return (f"  covariance    NEES pos {f('nees_pos', 2)} ({f('nees_pos_inside_percent', 1)} % in 3σ)  rot "
            f"{f('nees_rot', 2)} ({f('nees_rot_inside_percent', 1)} %)  twist v {f('nees_twist_linear', 2)} "
            f"({f('nees_twist_linear_inside_percent', 1)} %)  w {f('nees_twist_angular', 2)} "
            f"({f('nees_twist_angular_inside_percent', 1)} %)  (3 dof, consistent: 3; "
            f"{m['nees_frames']} tracking frames)")
