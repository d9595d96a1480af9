"""The keyframe / map stage: when a frame becomes the new keyframe, and what depth it carries.

A new keyframe is made on parallax (``kf_min_parallax_deg``), weak tracking (tracked ratio or
inliers below their limits) or age (``kf_max_interval_s``). A tracking keyframe triangulates each tracked
point through the gates (positive depth, reprojection error, triangulation angle) from the widest baseline
it has: its track's first view (``Keyframe.first_rays``) or the last keyframe, whichever sees it under the
larger ray angle. Depth noise is the image noise over the ray angle, so a point seen first a few
keyframes back gets its depth from all of that baseline instead of from the last keyframe pair's (one
degree of parallax at ``kf_min_parallax_deg``); its depth improves as the baseline grows. Old map points
still tracked that no triangulation passes carry over. Low parallax makes no keyframe by itself and no
depth update; under rotation or while initialising the reference is re-anchored without triangulating.
The windowed bundle adjustment (``window``, off by default) refines points seen by several keyframes.
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
from epi_vo.core.keyframe import Keyframe, own_rays
from epi_vo.core.motion import Motion

F64 = NDArray[np.float64]
THIN_MAP_FACTOR = 2  # a keyframe when fewer map points than this many times min_scale_points are tracked


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
    first_rays: F64 | None = None  # (N, 6) their first views in the current camera frame (None: first seen here)


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
    if motion.state is TrackingState.TRACKING and motion.new_map is None and kf.n_map_points >= cfg.min_scale_points:
        # The map thinning out while tracking: a new keyframe before too few of its points are left to
        # carry the scale (at low parallax no keyframe would come until tracking was lost).
        held = np.isfinite(kf.X_kf[rows][:, 0]) & motion.inliers
        weak = weak or int(np.count_nonzero(held)) < THIN_MAP_FACTOR * cfg.min_scale_points
    parallax = median_parallax_deg >= cfg.kf_min_parallax_deg
    R, t = motion.R_cur_kf, motion.t_cur_kf
    if motion.new_map is not None:
        X_cur = motion.new_map.X_ref @ R.T + t
        X_cur[~motion.new_map.good] = np.nan
        # The first map's points were first seen at its reference keyframe.
        return KeyframeMap(X_cur, first_rays=carried_rays(own_rays(kf.xn[rows]), R, t))
    if motion.state is TrackingState.TRACKING and (parallax or weak or too_old):
        idx = np.flatnonzero(motion.inliers)
        K, max_err, min_angle = kf.camera.K, cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg
        tri = geo.triangulate(R, t, kf.xn[rows[idx]], xn_cur[idx], K, max_err, min_angle)
        rays = carried_rays(kf.first_rays[rows] if kf.first_rays is not None else own_rays(kf.xn[rows]), R, t)
        wide = geo.triangulate_rays(rays[idx, :3], rays[idx, 3:], xn_cur[idx], K, max_err, min_angle)
        # Each point from the wider of its two baselines (its first view, the last keyframe) that passes.
        use_wide = wide.good & (~tri.good | (wide.angle_deg > tri.angle_deg))
        # Old map points still tracked carry over (moved into the new keyframe); fresh triangulations
        # replace them where they pass the gates.
        X_cur = kf.X_kf[rows] @ R.T + t
        X_cur[~motion.inliers] = np.nan
        new = np.full((n_tracked, 3), np.nan)
        new[idx] = np.where(use_wide[:, None], wide.X_ref, tri.X_ref @ R.T + t)
        good = np.zeros(n_tracked, bool)
        good[idx] = tri.good | wide.good
        X_cur[good] = new[good]
        n_triangulated = int(np.count_nonzero(good))
        notes = (note(Decision.KEYFRAME_WITHOUT_DEPTH),) if not parallax and n_triangulated == 0 else ()
        return KeyframeMap(X_cur, True, n_triangulated, tri.positive_depth_ratio, tri.median_reproj_err_px, notes,
                           rays)
    if motion.state is TrackingState.ROTATION_ONLY and (weak or too_old):
        # Re-anchor without triangulating: under rotation the existing depths and first views stay valid (t = 0).
        first = kf.first_rays[rows] if kf.first_rays is not None else own_rays(kf.xn[rows])
        return KeyframeMap(kf.X_kf[rows] @ R.T, first_rays=carried_rays(first, R, np.zeros(3)))
    if motion.state in (TrackingState.INITIALIZING, TrackingState.STATIC) and (
            too_old or n_tracked < 2 * cfg.min_inliers):
        # While initialising the keyframe is kept as long as enough features survive: re-anchoring
        # on the tracked ratio alone (ORB matches ~half the keyframe) would reset the parallax.
        # Before a map the motion has no scale: the tracks count as first seen at the new keyframe.
        return KeyframeMap(kf.X_kf[rows] @ R.T)
    return KeyframeMap()


def carried_rays(first_rays: F64, R_cur_kf: F64, t_cur_kf: F64) -> F64:
    """First views (N, 6: camera centre, unit ray) in a keyframe's camera frame moved into the current one."""
    return np.hstack([first_rays[:, :3] @ R_cur_kf.T + t_cur_kf, first_rays[:, 3:] @ R_cur_kf.T])
