"""The pose when H won model selection: pure rotation, a rotation under another focal length, a plane before
a map (which of H's decompositions), or with a map E's pose checked against it, or the map points' pose."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import Model, TrackingState
from epi_vo.core.motion.essential import from_essential, track_with_map
from epi_vo.core.motion.focal import ROTATION_PARAMS, rotation_explains, rotation_under_other_focal
from epi_vo.core.motion.initialize import initialize
from epi_vo.core.motion.plane_views import PlaneVerdict, plane_by_views
from epi_vo.core.motion.record import Motion, MotionContext, MotionEstimate, has_map, with_inliers
from epi_vo.core.selection import ModelSelection
from epi_vo.core.transforms import rotation_angle_deg

F64 = NDArray[np.float64]

# E's inliers off H's plane needed before they may pick among H's decompositions: fewer tell two
# decompositions apart no better than their noise
MIN_OFF_PLANE_FOR_E_HINT = 3
# E's inliers off H's plane, at least this many and this share of E's inliers: the scene is no plane (RH
# favours H at low parallax whatever the scene), and the first map starts from E
NOT_A_PLANE_OFF = (10, 0.1)


def e_moves_off_plane(cfg: VoConfig, ctx: MotionContext, sel: ModelSelection, est: MotionEstimate
                      ) -> tuple[MotionEstimate, bool]:
    """Before a first map: E's motion is none H's plane allows (``geo.agrees_with_plane``): part of its
    consensus moves (an object crossing a floor); the plane is taken as static. Only an E with a pose
    covariance (parallax its points show) can disagree."""
    assert sel.E is not None and sel.inliers_e is not None and sel.H is not None and sel.inliers_h is not None
    kf = ctx.kf
    K = kf.camera.K
    R, t, inl = geo.recover_pose(sel.E, kf.uv[ctx.rows], ctx.uv_cur, K, sel.inliers_e)
    cov = geo.essential_pose_covariance(R, t, kf.xn[ctx.rows][inl], ctx.xn_cur[inl], cfg.pixel_noise_px / K[0, 0],
                                        1.0, cfg.scale_drift_per_keyframe**2)
    if cov is None or not np.all(np.isfinite(cov)):
        return est, False
    sols = geo.homography_solutions(sel.H, K, kf.xn[ctx.rows], ctx.xn_cur, sel.inliers_h,
                                    cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg)
    if not sols or geo.agrees_with_plane(R, t, sols):
        return est, False
    rot, dirn = geo.nearest_plane_motion(R, t, sols)
    return est.noted(note(Decision.E_MOVES_OFF_PLANE, rotation=rot, direction=dirn)), True


def from_homography(cfg: VoConfig, ctx: MotionContext, sel: ModelSelection, est: MotionEstimate,
                    e_moves: bool = False) -> MotionEstimate:
    """The pose when H won (``e_moves``: E won but its motion is none of the plane's, so the plane is taken)."""
    assert sel.H is not None and sel.inliers_h is not None
    H, in_h = sel.H, sel.inliers_h
    kf = ctx.kf
    xn_kf, xn_cur = kf.xn[ctx.rows], ctx.xn_cur
    K = kf.camera.K
    R_h = geo.rotation_from_homography(H, K)
    est = with_inliers(est, in_h, R_h, xn_kf, xn_cur)
    if est.n_inliers < cfg.min_inliers:
        return est.noted(note(Decision.TOO_FEW_H_INLIERS, n=est.n_inliers, need=cfg.min_inliers))
    rot_cov = covm.rotation_var(cfg.pixel_noise_px, K[0, 0], est.n_inliers)
    zero = np.zeros(3)
    if rotation_explains(cfg, ctx, H, in_h, geo.ray_angles(R_h, 1.0, 0.0, xn_kf[in_h], xn_cur[in_h]),
                         ROTATION_PARAMS):
        angle = rotation_angle_deg(R_h)
        if angle >= cfg.min_rotation_for_rotation_only_deg:
            return est.noted(note(Decision.PURE_ROTATION, rh=sel.rh, parallax=est.median_parallax_deg, angle=angle),
                             Motion(TrackingState.ROTATION_ONLY, R_h, zero, covm.block(1e-6, rot_cov), in_h))
        if not has_map(cfg, kf):
            return est.noted(note(Decision.LOW_PARALLAX, parallax=est.median_parallax_deg),
                             Motion(TrackingState.INITIALIZING, R_h, zero, covm.block(1e-6, rot_cov), in_h))
    else:
        est, rotation = rotation_under_other_focal(cfg, ctx, H, in_h, est, rot_cov)
        if rotation is not None:
            return est.gave(rotation)
    if not has_map(cfg, kf):
        return _first_map_from_plane(cfg, ctx, sel, est, R_h, rot_cov, e_moves)
    if sel.E is not None and sel.inliers_e is not None and est.median_parallax_deg >= cfg.plane_e_min_parallax_deg:
        # RH is ORB-SLAM's test for the uncalibrated 8-point F, which a plane makes degenerate. The calibrated
        # 5-point E is not degenerate on a plane (only two-fold ambiguous), and with a map the ambiguity is
        # settled: E's pose is checked against the map's points, which overrule it. On a floor-dominated
        # view, chained map-point poses drift in yaw (three times E's on a floor).
        est = est.but(model=Model.ESSENTIAL).noted(note(Decision.PLANE_E_WITH_PARALLAX, rh=sel.rh))
        return from_essential(cfg, ctx, sel.E, sel.inliers_e, est, sel.rh, plane=True)
    est = est.noted(note(Decision.POSE_FROM_MAP_POINTS, rh=sel.rh))
    return track_with_map(cfg, ctx, R_h, None, in_h, est, rot_cov)


def _first_map_from_plane(cfg: VoConfig, ctx: MotionContext, sel: ModelSelection, est: MotionEstimate, R_h: F64,
                          rot_cov: float, e_moves: bool) -> MotionEstimate:
    """No map yet and H won: which of H's decompositions the motion is, or E's when the scene is no plane."""
    assert sel.H is not None and sel.inliers_h is not None
    H, in_h = sel.H, sel.inliers_h
    kf = ctx.kf
    xn_kf, xn_cur = kf.xn[ctx.rows], ctx.xn_cur
    K = kf.camera.K
    zero = np.zeros(3)
    R_off = None
    off_plane = 0 if sel.inliers_e is None else int(np.count_nonzero(sel.inliers_e & ~in_h))
    many_off = sel.E is not None and sel.inliers_e is not None and off_plane >= max(
        NOT_A_PLANE_OFF[0], NOT_A_PLANE_OFF[1] * np.count_nonzero(sel.inliers_e))
    if not e_moves and many_off:
        est, e_moves = e_moves_off_plane(cfg, ctx, sel, est)
    if many_off and not e_moves and sel.E is not None and sel.inliers_e is not None:
        # With this many of E's inliers off its plane the scene is no plane, and H's decomposition would
        # give the map a wrong pose.
        est = est.but(model=Model.ESSENTIAL).noted(note(Decision.NOT_A_PLANE, off=off_plane,
                                                        n_e=int(np.count_nonzero(sel.inliers_e))))
        return from_essential(cfg, ctx, sel.E, sel.inliers_e, est, sel.rh)
    if not e_moves and sel.inliers_e is not None and off_plane >= MIN_OFF_PLANE_FOR_E_HINT:
        # The points off H's plane (E's inliers that H rejects) say which of H's decompositions is the
        # motion when they tell them apart (``geometry.solution_off_plane``). Not E's own rotation: E fitted
        # to a plane and a few points off it is near-degenerate and can take the wrong solution.
        off = sel.inliers_e & ~in_h
        chosen = geo.solution_off_plane(
            geo.homography_solutions(H, K, xn_kf, xn_cur, in_h, cfg.max_reprojection_error_px,
                                     cfg.min_triangulation_angle_deg),
            K, kf.uv[ctx.rows][off], ctx.uv_cur[off], cfg.ransac_threshold_px)
        if chosen is not None:
            R_off = chosen.R
            est = est.noted(note(Decision.PLANE_PICKED_BY_OFF_POINTS, off=off_plane))
    planar = None
    if R_off is None and est.median_parallax_deg >= cfg.init_min_parallax_deg:
        est, verdict, planar, (R_held, spread) = plane_by_views(cfg, ctx, H, in_h, est)
        if verdict is PlaneVerdict.WAIT:
            # Not told apart, no solution is the pose (nor R_h, which assumes no translation): the one the
            # views follow is held, its variance covering every valid solution's rotation.
            return est.gave(Motion(TrackingState.INITIALIZING, R_held, zero,
                                   covm.block(1e-6, rot_cov + math.radians(spread) ** 2), in_h))
    if planar is None:
        planar = geo.pose_from_homography(H, K, xn_kf, xn_cur, in_h, cfg.max_reprojection_error_px,
                                          cfg.min_triangulation_angle_deg, prefer_R=R_off)
    if planar is None:
        return est.noted(note(Decision.PLANE_AMBIGUOUS),
                         Motion(TrackingState.INITIALIZING, R_h, zero, covm.block(1e-6, rot_cov), in_h))
    R_p, t_p, _ = planar
    if est.median_parallax_deg < cfg.init_min_parallax_deg:
        return est.noted(note(Decision.PLANE_LOW_PARALLAX, parallax=est.median_parallax_deg,
                              need=cfg.init_min_parallax_deg),
                         Motion(TrackingState.INITIALIZING, R_p, zero, covm.block(1e-6, rot_cov), in_h))
    on = in_h if sel.inliers_e is None or e_moves else in_h & sel.inliers_e  # E's, unless they move
    R_p, t_dir, what = geo.refine_planar_pose(R_p, t_p / float(np.linalg.norm(t_p)), xn_kf, xn_cur, on)
    return initialize(cfg, ctx, R_p, t_dir, in_h, est.noted(what), Decision.MAP_FROM_HOMOGRAPHY, planar=True)
