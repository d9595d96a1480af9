"""The pose from E with a map: E's rotation and direction scaled by the map points, checked against the map;
or the map points' own pose (motion-only refinement) when E cannot give it."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import TrackingState
from epi_vo.core.motion.initialize import initialize
from epi_vo.core.motion.map_check import PNP_MIN_POINTS, map_disagrees
from epi_vo.core.motion.record import Motion, MotionContext, MotionEstimate, has_map, residual_sq, with_inliers
from epi_vo.core.rotation_bias_cov import map_rotation_excess

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]

# Map points' reprojections count as this much noisier than their own residuals show: their depths carry
# the previous pair's image noise too (two images' worth: sqrt(2)).
MAP_INFO_SIGMA_FACTOR = math.sqrt(2.0)


def from_essential(cfg: VoConfig, ctx: MotionContext, E: F64, in_e: Mask, est: MotionEstimate, rh: float,
                   plane: bool = False) -> MotionEstimate:
    """E's pose (``plane``: asked although H won RH, a plane dominates the view)."""
    kf = ctx.kf
    uv_kf, xn_kf, xn_cur = kf.uv[ctx.rows], kf.xn[ctx.rows], ctx.xn_cur
    K = kf.camera.K
    R, t_dir, inl = geo.recover_pose(E, uv_kf, ctx.uv_cur, K, in_e)
    est = with_inliers(est, inl, R, xn_kf, xn_cur)
    if est.n_inliers < cfg.min_inliers:
        return est.noted(note(Decision.TOO_FEW_E_INLIERS, n=est.n_inliers, need=cfg.min_inliers, rh=rh))
    rot_cov = covm.rotation_var(cfg.pixel_noise_px, K[0, 0], est.n_inliers)
    if not has_map(cfg, kf):
        return initialize(cfg, ctx, R, t_dir, inl, est, Decision.MAP_FROM_ESSENTIAL)
    return track_with_map(cfg, ctx, R, t_dir, inl, est, rot_cov, plane)


def track_with_map(cfg: VoConfig, ctx: MotionContext, R: F64, t_dir: F64 | None, inl: Mask, est: MotionEstimate,
                   rot_cov: float, plane: bool = False) -> MotionEstimate:
    """Pose with the map's scale.

    E chosen with enough parallax: E's rotation and direction, scaled by the map points (robust 1-D
    median). Otherwise (H chosen, low parallax, no usable scale): motion-only LM on the map points, started
    from the E estimate or from the previous frame's relative pose.
    """
    kf, xn_cur, uv_cur = ctx.kf, ctx.xn_cur, ctx.uv_cur
    K = kf.camera.K
    X = kf.X_kf[ctx.rows]
    has_depth = inl & np.isfinite(X[:, 0])
    R0, t0 = ctx.T_cur_kf_prev[:3, :3], ctx.T_cur_kf_prev[:3, 3]
    scale: geo.ScaleEstimate | None = None
    e_inliers: Mask | None = None  # set when the map overrules E
    if t_dir is not None:
        R0 = R
        scale = geo.scale_from_points(X[has_depth], R, t_dir, xn_cur[has_depth], cfg.min_scale_points)
        if scale is not None:
            est = est.but(relative_scale=scale.scale)
            t0 = t_dir * scale.scale
    if t_dir is not None and scale is not None and est.median_parallax_deg >= cfg.e_pose_min_parallax_deg:
        # With enough parallax the essential matrix fixes rotation and direction better than the map (whose
        # depths carry the previous pairs' noise): take them, with the map's scale.
        par_rad = math.radians(est.median_parallax_deg)
        n = max(est.n_inliers, 1)
        dir_var = (cfg.pixel_noise_px / (K[0, 0] * par_rad)) ** 2 / n
        scale_var = scale.rel_spread**2 / max(scale.n_used, 1)
        trans_var = scale.scale**2 * (dir_var + scale_var)
        disagree, why = map_disagrees(cfg, ctx, X, R, t0, plane)
        if disagree is None:
            cov = essential_cov(cfg, ctx, R, t_dir, inl, X, has_depth, scale, covm.block(trans_var, rot_cov))
            scale_part = covm.shared_scale_part(-R.T @ t0, scale_var)
            pose = covm.tracked_since_keyframe(cov, scale_part, ctx.noise_sq, one_image=ctx.tracked,
                                               residual_sq=residual_sq(cfg, ctx, R, t_dir, inl))
            excess = None
            if cfg.rotation_bias_from_map:  # what the map's points say of E's rotation, beyond the noise
                Xd, xd = X[has_depth], xn_cur[has_depth]
                excess = map_rotation_excess(R, t0, Xd, xd, map_sigma(cfg, ctx, R, t0, Xd, xd), pose[3:, 3:])
            if plane:  # fused with the map: no separable scale part
                cov, pose = with_map_information(cfg, ctx, R, t0, X[has_depth], xn_cur[has_depth], cov, pose)
                return est.gave(Motion(TrackingState.TRACKING, R, t0, cov, inl, cov_pose=pose, rotation_excess=excess))
            return est.gave(Motion(TrackingState.TRACKING, R, t0, cov, inl, shared_scale_var=scale_var,
                                   from_essential=True, cov_pose=pose, rotation_excess=excess))
        # E's consensus was taken by something moving: the map's points, from the previous pose, decide.
        assert why is not None
        est = est.noted(why)
        R0, t0 = ctx.T_cur_kf_prev[:3, :3], ctx.T_cur_kf_prev[:3, 3]
        has_depth = disagree
        e_inliers = inl
    elif t_dir is not None and np.count_nonzero(has_depth) < cfg.min_scale_points:
        # E's consensus holds almost none of the map's points: the map's points decide on their own.
        all_depth = np.isfinite(X[:, 0])
        if np.count_nonzero(all_depth) >= max(cfg.min_scale_points, PNP_MIN_POINTS):
            has_depth, e_inliers = all_depth, inl
            R0, t0 = ctx.T_cur_kf_prev[:3, :3], ctx.T_cur_kf_prev[:3, 3]
            est = est.noted(note(Decision.E_HOLDS_NO_MAP_POINTS))
    refined = geo.refine_pose_pnp(X[has_depth], uv_cur[has_depth], K, R0, t0, cfg.max_reprojection_error_px,
                                  robust_start=e_inliers is not None)  # a mover: not LM from the last pose
    if refined is None:
        return est.noted(note(Decision.TOO_FEW_MAP_POINTS, n=int(np.count_nonzero(has_depth))))
    R_r, t_r, keep, cov_pnp = refined
    if np.count_nonzero(keep) < cfg.min_scale_points:
        return est.noted(note(Decision.TOO_FEW_MAP_POINTS_AGREE, n=int(np.count_nonzero(keep)),
                              need=cfg.min_scale_points))
    if not math.isfinite(est.relative_scale):
        est = est.but(relative_scale=float(np.linalg.norm(t_r)))
    # Covariance of the camera position in the keyframe frame: c = -R^T t.
    cov_t = R_r.T @ cov_pnp[3:, 3:] @ R_r
    cov_r = R_r.T @ cov_pnp[:3, :3] @ R_r
    cov_rel = np.zeros((6, 6))
    cov_rel[:3, :3] = cov_t
    cov_rel[3:, 3:] = cov_r + np.eye(3) * rot_cov
    # The map's own residuals set the fit's part; the added rotation term is at pixel_noise_px.
    cov_pose = cov_rel.copy()
    cov_pose[3:, 3:] += np.eye(3) * rot_cov * (ctx.noise_sq - 1.0)
    moving = None
    if e_inliers is not None:
        # The pose is the map's: every correspondence that fits its epipolar geometry is an inlier (so the
        # static scene without depth yet is triangulated at the next keyframe); those that made E's
        # consensus and do not fit it move on their own.
        F = geo.fundamental_from_essential(geo.essential_from_pose(R_r, t_r), K)
        _, fits = geo.score_fundamental(F, kf.uv[ctx.rows], uv_cur, cfg.score_sigma_px)
        map_rejected = np.zeros_like(fits)
        map_rejected[np.flatnonzero(has_depth)[~keep]] = True
        inl = fits & ~map_rejected
        moving = e_inliers & ~fits
    return est.gave(Motion(TrackingState.TRACKING, R_r, t_r, cov_rel, inl, moving=moving, cov_pose=cov_pose))


def essential_cov(cfg: VoConfig, ctx: MotionContext, R: F64, t_dir: F64, inl: Mask, X: F64, has_depth: Mask,
                  scale: geo.ScaleEstimate, fallback: F64) -> F64:
    """Covariance of E's pose scaled by the map, from its own residuals (``geometry.uncertainty``): rotation
    and direction coupled, the scale's dependence on the direction included."""
    cov = geo.essential_pose_covariance(R, t_dir, ctx.kf.xn[ctx.rows][inl], ctx.xn_cur[inl],
                                        cfg.pixel_noise_px / ctx.kf.camera.K[0, 0], scale.scale,
                                        scale.rel_spread**2 / max(scale.n_used, 1),
                                        (X[has_depth], ctx.xn_cur[has_depth]))
    return fallback if cov is None or not np.all(np.isfinite(cov)) else cov


def with_map_information(cfg: VoConfig, ctx: MotionContext, R: F64, t: F64, X: F64, xn: F64, cov: F64, pose: F64
                         ) -> tuple[F64, F64]:
    """E's covariance on a plane-dominated view, fused with what the map points say about the same pose: on
    a plane E's five parameters are poorly conditioned (the two-fold ambiguity's direction), while the map
    points (off the degeneracy) fix it. Independent to first order. The map points' reprojections carry the
    noise their own residuals show, as on the map-PnP frames around this one (RMS per axis, at least
    PNP_MIN_SIGMA_PX), MAP_INFO_SIGMA_FACTOR more for their depths. Both E's covariances are fused: at
    ``pixel_noise_px`` (``cov``) and at the tracks' (``pose``). The pose stays E's (the fusion's is less
    accurate where E's ridge is long), so each fused one also takes the Gauss-Newton step d from E's pose
    to that fusion as d d^T: how far the published pose may be, not the fusion's precision at a pose that
    is not the fusion's."""
    normal = geo.map_normal_equations(R, t, X, xn, map_sigma(cfg, ctx, R, t, X, xn))
    if normal is None:
        return cov, pose
    info, grad = normal
    out = []
    for P in (cov, pose):
        fused = geo.fuse(P, info)
        out.append(P if fused is None else fused + np.outer(fused @ grad, fused @ grad))
    return out[0], out[1]


def map_sigma(cfg: VoConfig, ctx: MotionContext, R: F64, t: F64, X: F64, xn: F64) -> float:
    """The noise (normalised units) of the map points' reprojections at the pose: what their own residuals
    show (RMS per axis, at least PNP_MIN_SIGMA_PX), MAP_INFO_SIGMA_FACTOR more for their depths."""
    fx = float(ctx.kf.camera.K[0, 0])
    rms = geo.reprojection_rms(R, t, X, xn)
    return MAP_INFO_SIGMA_FACTOR * max(rms if rms is not None else cfg.pixel_noise_px / fx, geo.PNP_MIN_SIGMA_PX / fx)
