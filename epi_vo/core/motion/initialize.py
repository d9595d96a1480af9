"""The first map: triangulated between the keyframe and this frame through the gates, once there is enough
parallax; its baseline's length is the scale stage's."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import TrackingState
from epi_vo.core.motion.record import Motion, MotionContext, MotionEstimate, residual_sq

F64 = NDArray[np.float64]


def initialize(cfg: VoConfig, ctx: MotionContext, R: F64, t_dir: F64, inl: NDArray[np.bool_], est: MotionEstimate,
               how: Decision, *, planar: bool = False) -> MotionEstimate:
    """Build the first map from the keyframe and this frame (``how``: from E or from H), or say why not
    yet; a frame that does not initialise holds the position (``TrackingState.INITIALIZING``)."""
    K = ctx.kf.camera.K
    xn_kf, xn_cur = ctx.kf.xn[ctx.rows], ctx.xn_cur
    zero = np.zeros(3)
    rot_cov = covm.rotation_var(cfg.pixel_noise_px, K[0, 0], max(est.n_inliers, 1))
    hold = Motion(TrackingState.INITIALIZING, R, zero, covm.block(1e-6, rot_cov), inl)
    if est.median_parallax_deg < cfg.init_min_parallax_deg:
        return est.noted(note(Decision.INIT_LOW_PARALLAX, parallax=est.median_parallax_deg,
                              need=cfg.init_min_parallax_deg), hold)
    kf = ctx.kf
    t = t_dir * ctx.initial_baseline((ctx.stamp_ns - kf.stamp_ns) * 1e-9)
    idx = np.flatnonzero(inl)
    tri = geo.triangulate(R, t, xn_kf[idx], xn_cur[idx], K, cfg.max_reprojection_error_px,
                          cfg.min_triangulation_angle_deg)
    n_good = int(np.count_nonzero(tri.good))
    est = est.but(n_triangulated=n_good, positive_depth_ratio=tri.positive_depth_ratio,
                  median_reproj_err_px=tri.median_reproj_err_px)
    if tri.positive_depth_ratio < cfg.min_positive_depth_ratio:
        return est.noted(note(Decision.INIT_REJECTED_DEPTH, ratio=tri.positive_depth_ratio,
                              need=cfg.min_positive_depth_ratio), hold)
    if n_good < cfg.min_triangulated:
        return est.noted(note(Decision.INIT_REJECTED_GATES, n=n_good, need=cfg.min_triangulated), hold)
    full = tri.expanded(idx, xn_kf.shape[0])
    # The first baseline is the map's unit (VO units; a scale source rescales it and adds its own
    # uncertainty): its direction and the rotation have E's covariance; its length is as well known as the
    # scale carried from one keyframe to the next (scale_drift_per_keyframe). On a plane (initialised from
    # H) E's residuals do not constrain the pose (degenerate): the isotropic form, with the rotation from
    # the inliers' count. The map is not refused for E's marginal rotation or direction sigma: a sideways
    # or orbiting camera trades the two along the bas-relief ambiguity at any parallax, and the depths the
    # pose puts into the map barely feel it; what a still camera's moving object would make a map of is
    # booked as a mover by the "no camera motion" hypothesis (``static.background_stood_still``).
    baseline = float(np.linalg.norm(t))
    cov = None if planar else geo.essential_pose_covariance(
        R, t_dir, xn_kf[inl], xn_cur[inl], cfg.pixel_noise_px / K[0, 0], baseline, cfg.scale_drift_per_keyframe**2)
    if not planar and (cov is None or not np.all(np.isfinite(cov))):
        # E's pose has no covariance (its points show no parallax to fit it on): nothing to start a map from.
        return est.noted(note(Decision.INIT_DEFERRED, rotation_sigma_deg=math.nan, direction_sigma_deg=math.nan),
                         hold)
    est = est.noted(note(how, n=n_good))
    if cov is None or not np.all(np.isfinite(cov)):
        cov = covm.block((cfg.scale_drift_per_keyframe * baseline) ** 2, rot_cov)
        pose = covm.block((cfg.scale_drift_per_keyframe * baseline) ** 2, rot_cov * ctx.noise_sq)
    else:
        # Not one_image: the first map's pose covariance, halved as the tracked frames' are, claims more
        # than its errors show (rotation NEES 4.9 on a held-out loop, 86 % inside 3 sigma; 3.7 and 93 %).
        pose = covm.tracked_since_keyframe(cov, covm.shared_scale_part(-R.T @ t, cfg.scale_drift_per_keyframe**2),
                                           ctx.noise_sq, one_image=False,
                                           residual_sq=residual_sq(cfg, ctx, R, t_dir, inl))
    return est.gave(Motion(TrackingState.TRACKING, R, t, cov, inl, new_map=full, cov_pose=pose))
