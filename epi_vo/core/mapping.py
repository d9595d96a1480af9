"""The keyframe / map stage: when a frame becomes the new keyframe, and what depth it carries.

A new keyframe is made on parallax (``kf_min_parallax_deg``), weak tracking (tracked ratio or
inliers below their limits) or age (``kf_max_interval_s``). A tracking keyframe triangulates its pair
through the gates (positive depth, reprojection error, triangulation angle); old map points still
tracked carry over. Low parallax makes no keyframe by itself and no depth update; under rotation or
while initialising the reference is re-anchored without triangulating. This is the seam for a
windowed map (points observed over several keyframes) and its optimisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.frame import TrackingState
from epi_vo.core.keyframe import Keyframe
from epi_vo.core.motion import Motion

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class KeyframeMap:
    """The mapping stage's decision for a frame: no new keyframe (``X_cur`` None), or the map points of its
    tracked features; with what a fresh triangulation measured and the decision's notes."""

    X_cur: F64 | None = None  # (N, 3) map points in the current camera frame of the N tracked features, NaN: none
    triangulated: bool = False  # a fresh triangulation of the keyframe pair (the statistics below are its)
    n_triangulated: int = 0
    positive_depth_ratio: float = math.nan
    median_reproj_err_px: float = math.nan
    notes: tuple[Note, ...] = ()


def keyframe_map(cfg: VoConfig, motion: Motion, kf: Keyframe, rows: NDArray[np.int64], xn_cur: F64,
                 stamp_ns: int, n_inliers: int, median_parallax_deg: float) -> KeyframeMap:
    """Decide whether this frame becomes a keyframe; if so, the map points of its tracked features.

    ``X_cur`` None: no new keyframe. Otherwise the (N, 3) map points in the current camera frame of the N
    tracked features (NaN: no depth): fresh triangulations of the keyframe pair where they pass the gates,
    old map points carried over otherwise. ``n_inliers`` and ``median_parallax_deg`` are the motion's.
    """
    n_tracked = rows.shape[0]
    tracked_ratio = n_tracked / max(kf.n_features, 1)
    too_old = (stamp_ns - kf.stamp_ns) * 1e-9 > cfg.kf_max_interval_s
    weak = tracked_ratio < cfg.kf_min_tracked_ratio or n_inliers < cfg.kf_min_inliers
    parallax = median_parallax_deg >= cfg.kf_min_parallax_deg
    R, t = motion.R_cur_kf, motion.t_cur_kf
    if motion.new_map is not None:
        X_cur = motion.new_map.X_ref @ R.T + t
        X_cur[~motion.new_map.good] = np.nan
        return KeyframeMap(X_cur)
    if motion.state is TrackingState.TRACKING and (parallax or weak or too_old):
        idx = np.flatnonzero(motion.inliers)
        tri = geo.triangulate(R, t, kf.xn[rows[idx]], xn_cur[idx], kf.camera.K,
                              cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg)
        n_triangulated = int(np.count_nonzero(tri.good))
        # Old map points still tracked carry over (moved into the new keyframe); fresh triangulations
        # from this pair replace them where they pass the gates.
        X_cur = kf.X_kf[rows] @ R.T + t
        X_cur[~motion.inliers] = np.nan
        new = np.full((n_tracked, 3), np.nan)
        new[idx] = tri.X_ref @ R.T + t
        good = np.zeros(n_tracked, bool)
        good[idx] = tri.good
        X_cur[good] = new[good]
        notes = (note(Decision.KEYFRAME_WITHOUT_DEPTH),) if not parallax and n_triangulated == 0 else ()
        return KeyframeMap(X_cur, True, n_triangulated, tri.positive_depth_ratio, tri.median_reproj_err_px, notes)
    if (motion.state is TrackingState.ROTATION_ONLY and (weak or too_old)) or (
            motion.state in (TrackingState.INITIALIZING, TrackingState.STATIC)
            and (too_old or n_tracked < 2 * cfg.min_inliers)):
        # While initialising the keyframe is kept as long as enough features survive: re-anchoring
        # on the tracked ratio alone (ORB matches ~half the keyframe) would reset the parallax.
        # Re-anchor without triangulating: under rotation the existing depths stay valid (t = 0).
        return KeyframeMap(kf.X_kf[rows] @ R.T)
    return KeyframeMap()
