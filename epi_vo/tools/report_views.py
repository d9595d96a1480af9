"""The trajectory as the report draws it: a top and a side view of the estimate, its keyframes and the aligned
ground truth, in the robot's frame when the run knows the camera extrinsic.

Frames. The replay's trajectory is camera poses T_w_c, w the first camera's optical frame (x right, y down,
z forward); a camera pitched down makes a flat drive a ramp there. With the extrinsic ``T_base_cam`` the
replay used (``stats.json`` ``extrinsic``, source ``parameters``: ``camera_xyz`` / ``camera_rpy`` declared)
the views are base_link in odom, REP-103, as ``/vo/odometry`` carries it: ``T_odom_base = T_base_cam T_w_c
T_base_cam^-1`` (odom is base_link at the first image), the top view x (forward) - y (left), the side view
x (forward) - z (up), the heading base_link's x axis. Without one (the default extrinsic, an older
``stats.json``) the views stay in the optical frame: top x (right) - z (forward), side z (forward) - -y
(up), the heading the optical axis.

The ground truth (camera poses) is aligned onto the estimate (:func:`~epi_vo.tools.report_data.gt_alignment`)
and then taken through the same extrinsic, so both are drawn the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.errors import ReportError
from epi_vo.core.transforms import rotation_from_quat_xyzw
from epi_vo.tools.replay_outputs import recorded_extrinsic
from epi_vo.tools.report_data import AlignmentKind, GtAlignment, Run, gt_alignment, run_scale, units_name

F64 = NDArray[np.float64]

OPTICAL_FRAME = "camera optical frame of the first image"
ODOM_FRAME = "odom: base_link at the first image (x forward, y left, z up)"


class View(NamedTuple):
    """One 2-D projection of the trajectories (all arrays in the same plot coordinates)."""

    title: str
    xlabel: str
    ylabel: str
    est: F64  # (N, 2) estimated positions (camera centres, or base_link in odom)
    gt: F64  # (M, 2) ground truth in the same frame (empty without a usable ground truth)
    keyframes: F64  # (K, 2) estimated positions of the keyframes
    heading: F64  # (N, 2) projection of each estimated pose's forward axis, a unit 3-D vector


@dataclass(frozen=True)
class TrajectoryViews:
    top: View
    side: View
    est_frame_index: NDArray[np.int64]  # (N,) record index of each estimated pose
    keyframe_index: NDArray[np.int64]  # (K,) record index of each keyframe with a pose
    alignment: GtAlignment | None  # None: no ground truth
    frame: str  # what the views are in (OPTICAL_FRAME or ODOM_FRAME)
    heading_label: str  # what the heading arrows are


def run_extrinsic(run: Run) -> F64 | None:
    """``T_base_cam`` (4x4) of a run whose parameters declared the camera extrinsic; None when the replay used
    the default or the output predates the record. ReportError for a record that is no rigid transform."""
    try:
        return recorded_extrinsic(run.stats)
    except ValueError as exc:
        raise ReportError(f"{run.directory / 'stats.json'}: {exc}") from None


def base_in_odom(p_w_c: F64, R_w_c: F64, T_base_cam: F64) -> tuple[F64, F64]:
    """Camera poses in w ((N, 3) centres, (N, 3, 3) rotations) -> base_link in odom: positions (N, 3) and
    rotations (N, 3, 3) of ``T_odom_base = T_base_cam T_w_c T_cam_base``."""
    R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
    t_cb = -R_bc.T @ t_bc  # base origin in the camera frame
    p = (R_w_c @ t_cb + p_w_c) @ R_bc.T + t_bc
    R = R_bc @ R_w_c @ R_bc.T
    return p, R


def _rotations(quats_xyzw: F64) -> F64:
    return np.array([rotation_from_quat_xyzw(q) for q in quats_xyzw]).reshape(-1, 3, 3)


def _gt_poses(run: Run, alignment: GtAlignment | None) -> tuple[F64, F64]:
    """The ground-truth camera poses in the estimate's frame w: (M, 3) centres and (M, 3, 3) rotations; empty
    without a usable alignment. The Sim(3) T_gt_est = (s R, t) is inverted: p = R^T (p_gt - t) / s, R_w_c =
    R^T R_gt_c."""
    if run.gt is None or alignment is None or alignment.kind is AlignmentKind.NONE:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    T_est_gt = np.linalg.inv(alignment.T_gt_est)
    A = T_est_gt[:3, :3]
    R_est_gt = A / np.cbrt(np.linalg.det(A))
    p = run.gt.positions_xyz @ A.T + T_est_gt[:3, 3]
    return p, R_est_gt @ _rotations(run.gt.quats_xyzw)


def trajectory_views(run: Run) -> TrajectoryViews:
    """The estimate, its keyframes and the aligned ground truth in a top and a side view (module doc)."""
    kf_records = {int(r["index"]) for r in run.records if r["is_keyframe"]}
    kf_mask = np.array([i in kf_records for i in run.est_frame_index], dtype=bool)
    alignment = gt_alignment(run)
    p, R = run.est.positions_xyz, _rotations(run.est.quats_xyzw)
    gt_p, gt_R = _gt_poses(run, alignment)
    u = f"[{units_name(run_scale(run).units)}]"
    T_base_cam = run_extrinsic(run)
    if T_base_cam is None:
        forward = R[:, :, 2] if len(R) else np.zeros((0, 3))  # the optical axis

        def top(q: F64) -> F64:
            return q[:, [0, 2]] if q.size else np.zeros((0, 2))

        def side(q: F64) -> F64:
            return np.column_stack([q[:, 2], -q[:, 1]]) if q.size else np.zeros((0, 2))

        views = (View("top view (x-z)", f"x (right) {u}", f"z (forward) {u}", top(p), top(gt_p),
                      top(p[kf_mask]), top(forward)),
                 View("side view (z-y)", f"z (forward) {u}", f"-y (up) {u}", side(p), side(gt_p),
                      side(p[kf_mask]), side(forward)))
        frame, heading = OPTICAL_FRAME, "heading (optical axis)"
    else:
        p, R = base_in_odom(p, R, T_base_cam)
        gt_p = base_in_odom(gt_p, gt_R, T_base_cam)[0] if len(gt_p) else gt_p
        forward = R[:, :, 0] if len(R) else np.zeros((0, 3))  # base_link's x

        def top(q: F64) -> F64:
            return q[:, [0, 1]] if q.size else np.zeros((0, 2))

        def side(q: F64) -> F64:
            return q[:, [0, 2]] if q.size else np.zeros((0, 2))

        views = (View("top view (x-y)", f"x (forward) {u}", f"y (left) {u}", top(p), top(gt_p),
                      top(p[kf_mask]), top(forward)),
                 View("side view (x-z)", f"x (forward) {u}", f"z (up) {u}", side(p), side(gt_p),
                      side(p[kf_mask]), side(forward)))
        frame, heading = ODOM_FRAME, "heading (base_link x, forward)"
    return TrajectoryViews(*views, run.est_frame_index, run.est_frame_index[kf_mask], alignment, frame, heading)
