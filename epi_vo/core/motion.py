"""The motion stage: the pose of the current frame relative to its keyframe, and what justifies it.

Given the winning two-view model (``epi_vo.core.selection``) and the keyframe's map:

* E with a map and enough parallax: E's rotation and translation direction (recoverPose with
  cheirality), scaled by the map points (robust 1-D median of per-point scales);
* otherwise with a map (H chosen, or low parallax): a motion-only refinement on the map points;
* H with no parallax left after removing the rotation: pure rotation, the position holds;
* no map yet: the first map is triangulated through the gates once there is enough parallax, its
  baseline length set by the scale stage (``MotionContext.initial_baseline``).

Every path appends the reason for what it did (or refused) to the frame's ``FrameStats``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import FrameStats, Model, TrackingState
from epi_vo.core.keyframe import Keyframe
from epi_vo.core.selection import ModelSelection
from epi_vo.core.transforms import rotation_angle_deg

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Motion:
    """A pose estimate of the current frame relative to the keyframe, with what justified it."""

    state: TrackingState
    R_cur_kf: F64
    t_cur_kf: F64
    cov_rel: F64  # 6x6 over (position, rotation) of the current camera in the keyframe frame
    inliers: NDArray[np.bool_]
    new_map: geo.Triangulation | None = None  # set when this frame initialises the map
    # Correspondences judged to move on their own this frame: they made E's consensus but do not fit
    # the epipolar geometry of the pose the map's points gave (None: no such check was made).
    moving: NDArray[np.bool_] | None = None
    # Relative variance of the map's scale in ``cov_rel`` (along the camera's offset from the keyframe):
    # the map points' depth errors behind it are the same for every frame against this keyframe, so it
    # moves consecutive frames alike (``covariance.shared_scale_part``; 0: none is in ``cov_rel``).
    shared_scale_var: float = 0.0
    # The pose is E's (rotation and direction) fitted to the tracks' positions since the keyframe: the
    # next frame's E is fitted to the same tracks one step on (``covariance.track_step``).
    from_essential: bool = False
    # The pose's covariance at the image noise its tracks gathered since the keyframe (``MotionContext``:
    # ``noise_sq``); ``cov_rel`` is at ``pixel_noise_px``, as the twist takes it. None: ``cov_rel``.
    cov_pose: F64 | None = None


def is_finite(m: Motion) -> bool:
    return covm.is_finite(m.R_cur_kf, m.t_cur_kf, m.cov_rel, m.cov_rel if m.cov_pose is None else m.cov_pose)


@dataclass(frozen=True)
class MotionContext:
    """What the motion stage reads of the pipeline's state for one frame."""

    kf: Keyframe
    rows: NDArray[np.int64]  # keyframe row of each correspondence
    xn_cur: F64  # (N, 2) normalized coordinates in the current frame
    uv_cur: F64  # (N, 2) undistorted pixels in the current frame
    T_cur_kf_prev: F64  # the previous frame's pose relative to the keyframe (start of the refinement)
    initial_baseline: Callable[[float], float]  # the scale stage: a new map's baseline after dt seconds
    # The image noise the tracks gathered frame by frame since the keyframe, as a share of pixel_noise_px,
    # squared (``covariance.tracked_since_keyframe``); 1: pixel_noise_px (ORB matches the keyframe directly).
    noise_sq: float = 1.0
    # The tracks were followed from the keyframe's features (KLT): their error is in this image only
    # (``covariance.tracked_since_keyframe``'s ``one_image``); False: matched to the keyframe (ORB).
    tracked: bool = False


E_MAP_MAX_DIRECTION_DIFF_DEG = 20.0  # E's direction of travel this far from the map's: a mover took E
E_MAP_AGREE_PX = 1.0  # map points this close to where E's pose puts them ...
E_MAP_AGREE_FRACTION = 0.8  # ... this share of them: E agrees with the map, no check of its own needed
E_MAP_HELD_SHARE = 0.7  # E's pose holding this share of the map points the map's own fit holds ...
E_MAP_RESIDUAL_RATIO = 2.0  # ... with a median reprojection error within this factor of the fit's: E stands
MIN_OFF_PLANE_FOR_E_HINT = 3  # E inliers off H's plane needed before they may pick among H's decompositions
NOT_A_PLANE_OFF = (10, 0.1)  # E inliers off H's plane, at least this many and this share: no plane, E initialises
E_PLANE_RH_MARGIN = 0.05  # E won RH within this of rh_threshold: a plane nearly won, E is checked against it
PLANE_NORMAL_AGREE_DEG = 1.5  # a decomposition's plane this close to one seen from an earlier view: the same plane
PLANE_MAX_WAIT = 10  # frames an initialisation on a plane with two valid decompositions waits for a view that
# tells them apart; then the one more points pass the gates is taken (as without the wait)
MAP_INFO_SIGMA_FACTOR = math.sqrt(2.0)  # map points' reprojections count as this much noisier (their depths
# carry the previous pair's image noise)
FOCAL_SUSPECT_RANGE = (0.8, 1.25)  # focal lengths (x the calibration's) a rotation-only view may suggest ...
FOCAL_SUSPECT_MIN_OFF = 0.03  # ... at least this far from it (closer: within the estimate's noise)
FOCAL_HINT_AGREE = 0.01  # a later frame's estimate this close to the last one taken: the same focal length
FOCAL_RATIO_SIGMA = 0.01  # of that focal length, relative (its estimates scatter 0.3-0.8 %, tests and bag)
STATIC_KEEP = 0.6  # a static camera stays static down to this share of static_min_fraction


class MotionStage:
    """Turns a model selection into a ``Motion`` (or None with the reason in ``FrameStats``)."""

    def __init__(self, cfg: VoConfig) -> None:
        self.cfg = cfg
        self.static = False  # the last frame was judged static (hysteresis: staying static is easier)
        # An ambiguous planar initialisation: (keyframe stamp, its valid solutions' normals at first, frames waited).
        self._plane_views: tuple[int, list[F64], int] | None = None
        self._focal_hint: float | None = None  # the last focal ratio a rotation was taken under (see below)

    def estimate(self, ctx: MotionContext, sel: ModelSelection, st: FrameStats) -> Motion | None:
        """The pose from the winning model; ``st.model`` says which one it was."""
        t0 = time.perf_counter()
        try:
            static = self._static(ctx, sel, st)
            if static is not None:
                return static
            if sel.model is Model.HOMOGRAPHY:
                assert sel.H is not None and sel.inliers_h is not None
                st.model = Model.HOMOGRAPHY
                return self._from_homography(ctx, sel, st)
            if sel.model is Model.ESSENTIAL:
                assert sel.E is not None and sel.inliers_e is not None
                if (not self.has_map(ctx.kf) and sel.inliers_h is not None
                        and sel.rh >= self.cfg.rh_threshold - E_PLANE_RH_MARGIN
                        and np.count_nonzero(sel.inliers_h) >= 0.5 * np.count_nonzero(sel.inliers_e)
                        and self._e_moves_off_plane(ctx, sel, st)):
                    st.model = Model.HOMOGRAPHY
                    return self._from_homography(ctx, sel, st, e_moves=True)
                st.model = Model.ESSENTIAL
                return self._from_essential(ctx, sel.E, sel.inliers_e, st)
            st.notes.append(note(Decision.NO_MODEL))
            return None
        finally:
            st.timings["pose"] = (time.perf_counter() - t0) * 1e3

    def _static(self, ctx: MotionContext, sel: ModelSelection, st: FrameStats) -> Motion | None:
        """The "no camera motion" hypothesis, before a map exists: when most tracked features did not
        move and those cover the image, the camera is static and whatever moved is another object. The
        pose holds (no map is built from the mover's motion); the frame says what moved and where.

        With a map, the pose comes from the map points, whose majority (the static background) decides
        it; E alone cannot tell: with no rotation every still point fits any translation's epipolar
        geometry, so RANSAC happily explains a mover's motion.
        """
        cfg = self.cfg
        was_static, self.static = self.static, False
        still = sel.inliers_static
        n = ctx.uv_cur.shape[0]
        if still is None or n == 0:
            return None
        fraction = float(np.count_nonzero(still)) / n
        st.static_score = fraction
        # Entering needs the majority; a static camera stays static while a growing mover covers more
        # of the background (and its occluded tracks), down to STATIC_KEEP of that.
        needed = cfg.static_min_fraction * (STATIC_KEEP if was_static else 1.0)
        if self.has_map(ctx.kf) or fraction < needed:
            return None
        K = ctx.kf.camera
        spread = grid_spread(ctx.uv_cur, still, K.width, K.height)
        if spread < cfg.static_min_spread:
            return None
        self.static = True
        moved = ~still
        st.n_moving = int(np.count_nonzero(moved))
        st.n_inliers = int(np.count_nonzero(still))
        st.median_parallax_deg = 0.0
        if st.n_moving:
            lo = np.percentile(ctx.uv_cur[moved], 5, axis=0)
            hi = np.percentile(ctx.uv_cur[moved], 95, axis=0)
            st.moving_region = (int(lo[0]), int(lo[1]), int(np.ceil(hi[0])), int(np.ceil(hi[1])))
        st.model = Model.STATIC
        st.notes.append(note(Decision.CAMERA_STATIC, fraction=fraction, spread=spread, n_moving=st.n_moving,
                             region=st.moving_region))
        rot_cov = covm.rotation_var(cfg.pixel_noise_px, K.K[0, 0], max(st.n_inliers, 1))
        return Motion(TrackingState.STATIC, np.eye(3), np.zeros(3), covm.block(1e-6, rot_cov), still)

    def _from_essential(self, ctx: MotionContext, E: F64, in_e: NDArray[np.bool_], st: FrameStats,
                        plane: bool = False) -> Motion | None:
        """E's pose (``plane``: asked although H won RH, a plane dominates the view)."""
        cfg = self.cfg
        kf = ctx.kf
        uv_kf, xn_kf, xn_cur = kf.uv[ctx.rows], kf.xn[ctx.rows], ctx.xn_cur
        K = kf.camera.K
        R, t_dir, inl = geo.recover_pose(E, uv_kf, ctx.uv_cur, K, in_e)
        self._inlier_stats(st, inl, R, xn_kf, xn_cur)
        if st.n_inliers < cfg.min_inliers:
            st.notes.append(note(Decision.TOO_FEW_E_INLIERS, n=st.n_inliers, need=cfg.min_inliers, rh=st.rh))
            return None
        rot_cov = covm.rotation_var(cfg.pixel_noise_px, K[0, 0], st.n_inliers)
        if not self.has_map(kf):
            return self._initialize(ctx, R, t_dir, inl, st, Decision.MAP_FROM_ESSENTIAL)
        return self._track_with_map(ctx, R, t_dir, inl, st, rot_cov, plane)

    def _e_moves_off_plane(self, ctx: MotionContext, sel: ModelSelection, st: FrameStats) -> bool:
        """Before a first map: E's motion is none H's plane allows (``geo.agrees_with_plane``): part of its consensus
        moves (moving_mover from frame 45: a cart's 60 points); the plane is taken as static. Where E won RH, only
        if a plane nearly did (RH within E_PLANE_RH_MARGIN of the threshold; 0.43-0.45 there): far points at low
        parallax fit an H whose decompositions mean nothing (RH 0.26-0.33). Only an E its points determine
        (``geo.pose_undetermined``) can disagree: a still camera's blurred frames (static_mover with motion
        blur) gave E 1.05 deg from the plane with 0.76 deg of its own sigma, and the plane started a map."""
        assert sel.E is not None and sel.inliers_e is not None and sel.H is not None and sel.inliers_h is not None
        kf, cfg = ctx.kf, self.cfg
        K = kf.camera.K
        R, t, inl = geo.recover_pose(sel.E, kf.uv[ctx.rows], ctx.uv_cur, K, sel.inliers_e)
        cov = geo.essential_pose_covariance(R, t, kf.xn[ctx.rows][inl], ctx.xn_cur[inl], cfg.pixel_noise_px / K[0, 0],
                                            1.0, cfg.scale_drift_per_keyframe**2)
        if geo.pose_undetermined(cov, t, cfg.init_max_rotation_sigma_deg, cfg.init_max_direction_sigma_deg) is not None:
            return False
        sols = geo.homography_solutions(sel.H, K, kf.xn[ctx.rows], ctx.xn_cur, sel.inliers_h,
                                        cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg)
        if not sols or geo.agrees_with_plane(R, t, sols):
            return False
        rot, dirn = geo.nearest_plane_motion(R, t, sols)
        st.notes.append(note(Decision.E_MOVES_OFF_PLANE, rotation=rot, direction=dirn))
        return True

    def _from_homography(self, ctx: MotionContext, sel: ModelSelection, st: FrameStats,
                         e_moves: bool = False) -> Motion | None:
        assert sel.H is not None and sel.inliers_h is not None
        H, in_h = sel.H, sel.inliers_h
        cfg = self.cfg
        kf = ctx.kf
        xn_kf, xn_cur = kf.xn[ctx.rows], ctx.xn_cur
        K = kf.camera.K
        R_h = geo.rotation_from_homography(H, K)
        self._inlier_stats(st, in_h, R_h, xn_kf, xn_cur)
        if st.n_inliers < cfg.min_inliers:
            st.notes.append(note(Decision.TOO_FEW_H_INLIERS, n=st.n_inliers, need=cfg.min_inliers))
            return None
        rot_cov = covm.rotation_var(cfg.pixel_noise_px, K[0, 0], st.n_inliers)
        zero = np.zeros(3)
        if st.median_parallax_deg < cfg.rotation_only_parallax_deg:
            angle = rotation_angle_deg(R_h)
            if angle >= cfg.min_rotation_for_rotation_only_deg:
                st.notes.append(note(Decision.PURE_ROTATION, rh=st.rh, parallax=st.median_parallax_deg, angle=angle))
                return Motion(TrackingState.ROTATION_ONLY, R_h, zero, covm.block(1e-6, rot_cov), in_h)
            if not self.has_map(kf):
                st.notes.append(note(Decision.LOW_PARALLAX, parallax=st.median_parallax_deg))
                return Motion(TrackingState.INITIALIZING, R_h, zero, covm.block(1e-6, rot_cov), in_h)
        else:
            rotation = self._rotation_under_other_focal(ctx, H, in_h, st, rot_cov)
            if rotation is not None:
                return rotation
        if not self.has_map(kf):
            R_off = None
            off_plane = 0 if sel.inliers_e is None else int(np.count_nonzero(sel.inliers_e & ~in_h))
            many_off = sel.E is not None and sel.inliers_e is not None and off_plane >= max(
                NOT_A_PLANE_OFF[0], NOT_A_PLANE_OFF[1] * np.count_nonzero(sel.inliers_e))
            e_moves = e_moves or (many_off and self._e_moves_off_plane(ctx, sel, st))
            if many_off and not e_moves and sel.E is not None and sel.inliers_e is not None:
                # RH favours H at low parallax whatever the scene; with this many of E's inliers off its
                # plane the scene is no plane, and H's decomposition would give the map a wrong pose
                # (moving_mover started at frame 20: 23 of 162, the map 1.6 deg off, 6.5 % ATE).
                st.model = Model.ESSENTIAL
                st.notes.append(note(Decision.NOT_A_PLANE, off=off_plane, n_e=int(np.count_nonzero(sel.inliers_e))))
                return self._from_essential(ctx, sel.E, sel.inliers_e, st)
            if not e_moves and sel.inliers_e is not None and off_plane >= MIN_OFF_PLANE_FOR_E_HINT:
                # The points off H's plane (E's inliers that H rejects) say which of H's decompositions is
                # the motion when they tell them apart (``geometry.solution_off_plane``). Not E's own
                # rotation: E fitted to a plane and a few points off it is near-degenerate and can take
                # the wrong solution (ground_robot with klt_window_px 31: 4.3 deg off, 21 % ATE).
                off = sel.inliers_e & ~in_h
                chosen = geo.solution_off_plane(
                    geo.homography_solutions(H, K, xn_kf, xn_cur, in_h, cfg.max_reprojection_error_px,
                                             cfg.min_triangulation_angle_deg),
                    K, kf.uv[ctx.rows][off], ctx.uv_cur[off], cfg.ransac_threshold_px)
                if chosen is not None:
                    R_off = chosen.R
                    st.notes.append(note(Decision.PLANE_PICKED_BY_OFF_POINTS, off=off_plane))
            planar = None
            if R_off is None and st.median_parallax_deg >= cfg.init_min_parallax_deg:
                verdict, planar, spread = self._plane_by_views(ctx, H, in_h, st)
                if verdict == "wait":
                    # Neither solution's rotation (nor R_h, which assumes no translation) can be published:
                    # the orientation is held too, its variance covering every valid solution's rotation.
                    return Motion(TrackingState.INITIALIZING, np.eye(3), zero,
                                  covm.block(1e-6, rot_cov + math.radians(spread) ** 2), in_h)
            if planar is None:
                planar = geo.pose_from_homography(H, K, xn_kf, xn_cur, in_h, cfg.max_reprojection_error_px,
                                                  cfg.min_triangulation_angle_deg, prefer_R=R_off)
            if planar is None:
                st.notes.append(note(Decision.PLANE_AMBIGUOUS))
                return Motion(TrackingState.INITIALIZING, R_h, zero, covm.block(1e-6, rot_cov), in_h)
            R_p, t_p, _ = planar
            if st.median_parallax_deg < cfg.init_min_parallax_deg:
                st.notes.append(note(Decision.PLANE_LOW_PARALLAX, parallax=st.median_parallax_deg,
                                     need=cfg.init_min_parallax_deg))
                return Motion(TrackingState.INITIALIZING, R_p, zero, covm.block(1e-6, rot_cov), in_h)
            on = in_h if sel.inliers_e is None or e_moves else in_h & sel.inliers_e  # E's, unless they move
            R_p, t_dir, what = geo.refine_planar_pose(R_p, t_p / float(np.linalg.norm(t_p)), xn_kf, xn_cur, on)
            st.notes.append(what)
            return self._initialize(ctx, R_p, t_dir, in_h, st, Decision.MAP_FROM_HOMOGRAPHY, planar=True)
        if sel.E is not None and sel.inliers_e is not None and st.median_parallax_deg >= cfg.plane_e_min_parallax_deg:
            # RH is ORB-SLAM's test for the uncalibrated 8-point F, which a plane makes degenerate. The
            # calibrated 5-point E is not degenerate on a plane (only two-fold ambiguous), and with a map
            # the ambiguity is settled: E's pose is checked against the map's points, which overrule it.
            # On a floor-dominated view, chained map-point poses drift in yaw (3.2 deg over the
            # ground-robot bag, against 1.0 from E).
            st.model = Model.ESSENTIAL
            st.notes.append(note(Decision.PLANE_E_WITH_PARALLAX, rh=st.rh))
            return self._from_essential(ctx, sel.E, sel.inliers_e, st, plane=True)
        st.notes.append(note(Decision.POSE_FROM_MAP_POINTS, rh=st.rh))
        return self._track_with_map(ctx, R_h, None, in_h, st, rot_cov)

    def _rotation_under_other_focal(self, ctx: MotionContext, H: F64, in_h: NDArray[np.bool_], st: FrameStats,
                                    rot_cov: float) -> Motion | None:
        """A pure rotation seen through a wrong focal length: rotation-only, and the reason says so.

        With the calibration's focal length off, a rotating camera's rays do not line up after the
        rotation is taken out: the leftover grows with the rotation (pure_rotation with fx x 0.9: 0.5 deg
        at 5 deg of rotation) and was taken for parallax, a plane and a translation. When H is a rotation
        under a focal length within ``FOCAL_SUSPECT_RANGE`` of the calibration's and at least
        ``FOCAL_SUSPECT_MIN_OFF`` away from it, and the parallax under that focal length is below
        ``rotation_only_parallax_deg``, the motion is that rotation (position held) before a map exists;
        with a map the map's points decide and the reason says what else the motion could be.

        The ambiguity is real for one kind of scene: a plane facing the camera seen while the camera turns
        about a point off its centre (a pan plus a sideways shift) is, to first order, a pure rotation
        under a focal length sqrt(1 + L / d) x the true one (lever arm L, distance d: 0.3 m before a wall 2
        m away, 1.07 x). Hence the map's say once there is one. Homographies of a camera translating over
        a floor or across a tilted plane are rotations under no plausible focal length (none, or 0.02-0.66
        x the calibration's: every H frame of the bundled bags and KITTI, a robot turning over a floor)."""
        cfg = self.cfg
        K = ctx.kf.camera.K
        f = geo.focal_for_rotation(H, K)
        lo, hi = FOCAL_SUSPECT_RANGE
        if f is None or not 0.85 * lo <= f / K[0, 0] <= 1.15 * hi:
            return None
        ratio = geo.refine_focal_for_rotation(H, K, f, ctx.kf.uv[ctx.rows][in_h], ctx.uv_cur[in_h]) / K[0, 0]
        if not lo <= ratio <= hi:
            return None
        K_f = K.copy()
        K_f[:2, :2] *= ratio  # normalised coordinates under K_f: xn / ratio
        R_f = geo.rotation_from_homography(H, K_f)
        par = geo.parallax_deg(R_f, ctx.kf.xn[ctx.rows][in_h] / ratio, ctx.xn_cur[in_h] / ratio)
        par_f = float(np.median(par)) if par.size else math.nan
        angle = rotation_angle_deg(R_f)
        if not (par_f < cfg.rotation_only_parallax_deg and angle >= cfg.min_rotation_for_rotation_only_deg):
            return None
        # The rotation also carries the focal length's error (a rotation under a focal length off by e is off
        # by about e x its angle): FOCAL_RATIO_SIGMA of it.
        rotation = Motion(TrackingState.ROTATION_ONLY, R_f, np.zeros(3),
                          covm.block(1e-6, rot_cov + (FOCAL_RATIO_SIGMA * math.radians(angle)) ** 2), in_h)
        # Once a rotation was taken under another focal length, later frames agreeing with it within
        # FOCAL_HINT_AGREE name it too, also a little closer to the calibration's than FOCAL_SUSPECT_MIN_OFF (a
        # focal length 3 % off is estimated at 2.9-3.4 % from frame to frame).
        hint = self._focal_hint
        agrees = hint is not None and abs(ratio - hint) <= FOCAL_HINT_AGREE
        if abs(ratio - 1.0) < FOCAL_SUSPECT_MIN_OFF * (0.5 if agrees else 1.0):
            # Within the calibration's tolerance: a rotation, without blaming the calibration (fx x 0.98 or
            # 0.97: frames at 0.15-0.5 deg of "parallax" otherwise waited as a plane, the orientation held).
            if self.has_map(ctx.kf):
                return None
            st.notes.append(note(Decision.ROTATION_UNDER_FOCAL_TOLERANCE, ratio=ratio, parallax_focal=par_f,
                                 parallax=st.median_parallax_deg, angle=angle))
            return rotation
        st.focal_ratio = self._focal_hint = ratio
        details = {"ratio": ratio, "parallax_focal": par_f, "parallax": st.median_parallax_deg, "angle": angle}
        if self.has_map(ctx.kf):
            # The map's points decide the pose, as without the check (a robot turning in place before a
            # wall 2 m away, the camera 0.3 m off the axis: 1.07 x); the frame says what else it could be.
            st.notes.append(note(Decision.FOCAL_SUSPECT_MAP_DECIDES, **details))
            return None
        st.notes.append(note(Decision.FOCAL_SUSPECT_ROTATION, **details))
        return rotation

    def _plane_by_views(self, ctx: MotionContext, H: F64, in_h: NDArray[np.bool_], st: FrameStats
                        ) -> tuple[str, tuple[F64, F64, geo.Triangulation] | None, float]:
        """A plane whose homography has two physically valid decompositions (both put the points in front
        of both cameras: a floor seen from a camera moving along it), with no point off the plane to
        tell them apart, is told apart by a later view against the same keyframe. The true plane keeps
        its normal in the keyframe's frame; the other solution's normal follows the direction of travel
        (ground_robot replayed from frame 31: 0.4 against 2.9 deg one frame later). The count of points
        through the triangulation gates does not decide: the wrong solution sees its points under larger
        angles (192 against 109 there; the map started 4.4 deg off, 1.2 % ATE).

        Returns ("unambiguous", None) when fewer than two solutions are valid, ("wait", None), ("picked",
        pose) when the view decides, ("fallback", None) after ``PLANE_MAX_WAIT`` frames without one; and
        the largest rotation angle (deg) among the valid solutions."""
        cfg = self.cfg
        kf = ctx.kf
        sols = geo.homography_solutions(H, kf.camera.K, kf.xn[ctx.rows], ctx.xn_cur, in_h,
                                        cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg)
        valid = [s for s in sols if s.tri.positive_depth_ratio >= cfg.min_positive_depth_ratio
                 and s.n_good >= cfg.min_triangulated]
        if len(valid) < 2:
            self._plane_views = None
            return "unambiguous", None, 0.0
        spread = max(rotation_angle_deg(s.R) for s in valid)
        pending = self._plane_views
        if pending is None or pending[0] != kf.stamp_ns:
            self._plane_views = (kf.stamp_ns, [s.normal for s in valid], 1)
            st.notes.append(note(Decision.PLANE_WAIT_FIRST, n=len(valid), max_wait=PLANE_MAX_WAIT))
            return "wait", None, spread
        _, normals, waited = pending
        with np.errstate(invalid="ignore"):
            dist = [min(math.degrees(math.acos(min(1.0, abs(float(s.normal @ n))))) for n in normals)
                    for s in valid]
        order = np.argsort(dist)
        best, runner = dist[order[0]], dist[order[1]]
        if best < PLANE_NORMAL_AGREE_DEG and runner >= max(3.0 * best, PLANE_NORMAL_AGREE_DEG):
            s = valid[int(order[0])]
            st.notes.append(note(Decision.PLANE_KEPT_NORMAL, views=waited + 1, best=best, runner=runner))
            return "picked", (s.R, s.t, s.tri.expanded(np.flatnonzero(in_h), ctx.xn_cur.shape[0])), spread
        if waited >= PLANE_MAX_WAIT:
            st.notes.append(note(Decision.PLANE_WAIT_GAVE_UP, max_wait=PLANE_MAX_WAIT))
            return "fallback", None, spread
        self._plane_views = (pending[0], normals, waited + 1)
        st.notes.append(note(Decision.PLANE_WAIT, n=len(valid), best=best, runner=runner, waited=waited + 1,
                             max_wait=PLANE_MAX_WAIT))
        return "wait", None, spread

    def _inlier_stats(self, st: FrameStats, inl: NDArray[np.bool_], R: F64, xn_kf: F64, xn_cur: F64) -> None:
        st.n_inliers = int(np.count_nonzero(inl))
        par = geo.parallax_deg(R, xn_kf[inl], xn_cur[inl])
        st.median_parallax_deg = float(np.median(par)) if par.size else math.nan

    def has_map(self, kf: Keyframe) -> bool:
        return kf.n_map_points >= self.cfg.min_scale_points

    def _initialize(self, ctx: MotionContext, R: F64, t_dir: F64, inl: NDArray[np.bool_], st: FrameStats,
                    how: Decision, *, planar: bool = False) -> Motion:
        """Build the first map from the keyframe and this frame, or explain why not yet."""
        cfg = self.cfg
        K = ctx.kf.camera.K
        xn_kf, xn_cur = ctx.kf.xn[ctx.rows], ctx.xn_cur
        zero = np.zeros(3)
        rot_cov = covm.rotation_var(cfg.pixel_noise_px, K[0, 0], max(st.n_inliers, 1))
        hold = Motion(TrackingState.INITIALIZING, R, zero, covm.block(1e-6, rot_cov), inl)
        if st.median_parallax_deg < cfg.init_min_parallax_deg:
            st.notes.append(note(Decision.INIT_LOW_PARALLAX, parallax=st.median_parallax_deg,
                                 need=cfg.init_min_parallax_deg))
            return hold
        kf = ctx.kf
        t = t_dir * ctx.initial_baseline((st.stamp_ns - kf.stamp_ns) * 1e-9)
        idx = np.flatnonzero(inl)
        tri = geo.triangulate(R, t, xn_kf[idx], xn_cur[idx], K, cfg.max_reprojection_error_px,
                              cfg.min_triangulation_angle_deg)
        n_good = int(np.count_nonzero(tri.good))
        st.n_triangulated = n_good
        st.positive_depth_ratio = tri.positive_depth_ratio
        st.median_reproj_err_px = tri.median_reproj_err_px
        if tri.positive_depth_ratio < cfg.min_positive_depth_ratio:
            st.notes.append(note(Decision.INIT_REJECTED_DEPTH, ratio=tri.positive_depth_ratio,
                                 need=cfg.min_positive_depth_ratio))
            return hold
        if n_good < cfg.min_triangulated:
            st.notes.append(note(Decision.INIT_REJECTED_GATES, n=n_good, need=cfg.min_triangulated))
            return hold
        full = tri.expanded(idx, xn_kf.shape[0])
        # The first baseline is the map's unit (VO units; a scale source rescales it and adds its own
        # uncertainty): its direction and the rotation have E's covariance; its length is as well known
        # as the scale carried from one keyframe to the next (scale_drift_per_keyframe).
        # On a plane (initialised from H) E's residuals do not constrain the pose (degenerate): the
        # isotropic form, with the rotation from the inliers' count.
        baseline = float(np.linalg.norm(t))
        cov = None if planar else geo.essential_pose_covariance(
            R, t_dir, xn_kf[inl], xn_cur[inl], cfg.pixel_noise_px / K[0, 0], baseline, cfg.scale_drift_per_keyframe**2)
        if not planar:
            undetermined = geo.pose_undetermined(cov, t, cfg.init_max_rotation_sigma_deg,
                                                 cfg.init_max_direction_sigma_deg)
            if undetermined is not None:
                st.notes.append(note(Decision.INIT_DEFERRED, rotation_sigma_deg=undetermined[0],
                                     direction_sigma_deg=undetermined[1]))
                if cov is not None and np.all(np.isfinite(cov)):
                    hold.cov_rel[3:, 3:] += cov[3:, 3:]  # the held orientation is E's, with E's uncertainty
                return hold
        st.notes.append(note(how, n=n_good))
        if cov is None or not np.all(np.isfinite(cov)):
            cov = covm.block((cfg.scale_drift_per_keyframe * baseline) ** 2, rot_cov)
            pose = covm.block((cfg.scale_drift_per_keyframe * baseline) ** 2, rot_cov * ctx.noise_sq)
        else:
            # Not one_image here: the first map's pose, halved too, took the held-out loop's rotation NEES
            # to 4.9 with 86 % inside 3 sigma (3.7 and 93 % without; 2026-11-27).
            pose = covm.tracked_since_keyframe(cov, covm.shared_scale_part(-R.T @ t, cfg.scale_drift_per_keyframe**2),
                                               ctx.noise_sq, one_image=False,
                                               residual_sq=self._residual_sq(ctx, R, t_dir, inl))
        return Motion(TrackingState.TRACKING, R, t, cov, inl, new_map=full, cov_pose=pose)

    def _track_with_map(self, ctx: MotionContext, R: F64, t_dir: F64 | None, inl: NDArray[np.bool_],
                        st: FrameStats, rot_cov: float, plane: bool = False) -> Motion | None:
        """Pose with the map's scale.

        E chosen with enough parallax: E's rotation and direction, scaled by the map points (robust 1-D
        median). Otherwise (H chosen, low parallax, no usable scale): motion-only LM on the map points,
        started from the E estimate or from the previous frame's relative pose.
        """
        cfg = self.cfg
        kf, xn_cur, uv_cur = ctx.kf, ctx.xn_cur, ctx.uv_cur
        K = kf.camera.K
        X = kf.X_kf[ctx.rows]
        has_depth = inl & np.isfinite(X[:, 0])
        R0, t0 = ctx.T_cur_kf_prev[:3, :3], ctx.T_cur_kf_prev[:3, 3]
        est: geo.ScaleEstimate | None = None
        e_inliers: NDArray[np.bool_] | None = None  # set when the map overrules E
        if t_dir is not None:
            R0 = R
            est = geo.scale_from_points(X[has_depth], R, t_dir, xn_cur[has_depth], cfg.min_scale_points)
            if est is not None:
                st.relative_scale = est.scale
                t0 = t_dir * est.scale
        if t_dir is not None and est is not None and st.median_parallax_deg >= cfg.e_pose_min_parallax_deg:
            # With enough parallax the essential matrix fixes rotation and direction better than the
            # map (whose depths carry the previous pairs' noise): take them, with the map's scale.
            par_rad = math.radians(st.median_parallax_deg)
            n = max(st.n_inliers, 1)
            dir_var = (cfg.pixel_noise_px / (K[0, 0] * par_rad)) ** 2 / n
            scale_var = est.rel_spread**2 / max(est.n_used, 1)
            trans_var = est.scale**2 * (dir_var + scale_var)
            disagree = self._map_disagrees(ctx, X, R, t0, st, plane)
            if disagree is None:
                cov = self._essential_cov(ctx, R, t_dir, inl, X, has_depth, est, covm.block(trans_var, rot_cov))
                scale_part = covm.shared_scale_part(-R.T @ t0, scale_var)
                pose = covm.tracked_since_keyframe(cov, scale_part, ctx.noise_sq, one_image=ctx.tracked,
                                                   residual_sq=self._residual_sq(ctx, R, t_dir, inl))
                if plane:  # fused with the map: no separable scale part
                    cov, pose = self._with_map_information(ctx, R, t0, X[has_depth], xn_cur[has_depth], cov, pose)
                    return Motion(TrackingState.TRACKING, R, t0, cov, inl, cov_pose=pose)
                return Motion(TrackingState.TRACKING, R, t0, cov, inl, shared_scale_var=scale_var, from_essential=True,
                              cov_pose=pose)
            # E's consensus was taken by something moving: the map's points, from the previous pose, decide.
            R0, t0 = ctx.T_cur_kf_prev[:3, :3], ctx.T_cur_kf_prev[:3, 3]
            has_depth = disagree
            e_inliers = inl
        elif t_dir is not None and np.count_nonzero(has_depth) < cfg.min_scale_points:
            # E's consensus holds almost none of the map's points: the map's points decide on their own.
            all_depth = np.isfinite(X[:, 0])
            if np.count_nonzero(all_depth) >= max(cfg.min_scale_points, 6):
                has_depth, e_inliers = all_depth, inl
                R0, t0 = ctx.T_cur_kf_prev[:3, :3], ctx.T_cur_kf_prev[:3, 3]
                st.notes.append(note(Decision.E_HOLDS_NO_MAP_POINTS))
        refined = geo.refine_pose_pnp(X[has_depth], uv_cur[has_depth], K, R0, t0, cfg.max_reprojection_error_px,
                                      robust_start=e_inliers is not None)  # a mover: not LM from the last pose
        if refined is None:
            st.notes.append(note(Decision.TOO_FEW_MAP_POINTS, n=int(np.count_nonzero(has_depth))))
            return None
        R_r, t_r, keep, cov_pnp = refined
        if np.count_nonzero(keep) < cfg.min_scale_points:
            st.notes.append(note(Decision.TOO_FEW_MAP_POINTS_AGREE, n=int(np.count_nonzero(keep)),
                                 need=cfg.min_scale_points))
            return None
        if not math.isfinite(st.relative_scale):
            st.relative_scale = float(np.linalg.norm(t_r))
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
            # The pose is the map's: every correspondence that fits its epipolar geometry is an inlier
            # (so the static scene without depth yet is triangulated at the next keyframe); those that
            # made E's consensus and do not fit it move on their own.
            F = geo.fundamental_from_essential(geo.essential_from_pose(R_r, t_r), K)
            _, fits = geo.score_fundamental(F, kf.uv[ctx.rows], uv_cur, cfg.score_sigma_px)
            map_rejected = np.zeros_like(fits)
            map_rejected[np.flatnonzero(has_depth)[~keep]] = True
            inl = fits & ~map_rejected
            moving = e_inliers & ~fits
        return Motion(TrackingState.TRACKING, R_r, t_r, cov_rel, inl, moving=moving, cov_pose=cov_pose)

    def _residual_sq(self, ctx: MotionContext, R: F64, t_dir: F64, inl: NDArray[np.bool_]) -> float:
        """The image noise E's inliers show about the pose (``geometry.sampson_rms``) as a share of
        ``pixel_noise_px``, squared, for ``covariance.tracked_since_keyframe``; 0 (not used) unless the
        tracks were followed from the keyframe."""
        if not ctx.tracked:
            return 0.0
        rms = geo.sampson_rms(R, t_dir, ctx.kf.xn[ctx.rows][inl], ctx.xn_cur[inl])
        return 0.0 if rms is None else (rms * ctx.kf.camera.K[0, 0] / self.cfg.pixel_noise_px) ** 2

    def _essential_cov(self, ctx: MotionContext, R: F64, t_dir: F64, inl: NDArray[np.bool_], X: F64,
                       has_depth: NDArray[np.bool_], est: geo.ScaleEstimate, fallback: F64) -> F64:
        """Covariance of E's pose scaled by the map, from its own residuals (``geometry.uncertainty``):
        rotation and direction coupled, the scale's dependence on the direction included."""
        cfg = self.cfg
        cov = geo.essential_pose_covariance(R, t_dir, ctx.kf.xn[ctx.rows][inl], ctx.xn_cur[inl],
                                            cfg.pixel_noise_px / ctx.kf.camera.K[0, 0], est.scale,
                                            est.rel_spread**2 / max(est.n_used, 1),
                                            (X[has_depth], ctx.xn_cur[has_depth]))
        return fallback if cov is None or not np.all(np.isfinite(cov)) else cov

    def _with_map_information(self, ctx: MotionContext, R: F64, t: F64, X: F64, xn: F64, cov: F64,
                              pose: F64) -> tuple[F64, F64]:
        """E's covariance on a plane-dominated view, fused with what the map points say about the same
        pose: on a plane E's five parameters are poorly conditioned (the two-fold ambiguity's direction),
        while the map points (off the degeneracy) fix it. Independent to first order. The map points'
        reprojections carry the noise their own residuals show, as on the map-PnP frames around this
        one (RMS per axis, at least PNP_MIN_SIGMA_PX), MAP_INFO_SIGMA_FACTOR more for their depths.
        Both E's covariances are fused: at ``pixel_noise_px`` (``cov``) and at the tracks' (``pose``).
        The pose stays E's (moving it to the fusion lost accuracy elsewhere: README), so each fused one also
        takes the Gauss-Newton step d from E's pose to that fusion as d d^T: how far the published pose
        may be, not the fusion's precision at a pose that is not the fusion's (README, "E's ridge")."""
        fx = ctx.kf.camera.K[0, 0]
        rms = geo.reprojection_rms(R, t, X, xn)
        sigma_n = MAP_INFO_SIGMA_FACTOR * max(rms if rms is not None else self.cfg.pixel_noise_px / fx,
                                              geo.PNP_MIN_SIGMA_PX / fx)
        normal = geo.map_normal_equations(R, t, X, xn, sigma_n)
        if normal is None:
            return cov, pose
        info, grad = normal
        out = []
        for P in (cov, pose):
            fused = geo.fuse(P, info)
            out.append(P if fused is None else fused + np.outer(fused @ grad, fused @ grad))
        return out[0], out[1]

    def _map_disagrees(self, ctx: MotionContext, X: F64, R_e: F64, t_e: F64, st: FrameStats,
                       plane: bool = False) -> NDArray[np.bool_] | None:
        """None when the map's points agree with E's rotation and direction of travel; else the map points
        that agree with the pose they give on their own (started from the previous frame's pose), and the
        reason is noted.

        E alone takes the largest consensus: a mover covering a third of the view can win it. The map's
        points were triangulated from the static scene before; their pose is the check.
        """
        cfg = self.cfg
        depth = np.isfinite(X[:, 0])
        if np.count_nonzero(depth) < max(cfg.min_scale_points, 6):
            return None
        K = ctx.kf.camera.K
        # Cheap first: E puts nearly all map points where seen; near a plane, where E slides along its ridge
        # and still does, one Gauss-Newton step towards the map's pose turns E by less than half the angle.
        err_e = geo.reprojection_errors(R_e, t_e, X[depth], ctx.uv_cur[depth], K)
        if (np.count_nonzero(err_e <= E_MAP_AGREE_PX) >= E_MAP_AGREE_FRACTION * err_e.shape[0]) if not plane else (
                (step := geo.map_step(R_e, t_e, X[depth], ctx.xn_cur[depth])) is not None
                and math.degrees(float(np.linalg.norm(step[3:]))) <= 0.5 * cfg.e_map_max_rotation_diff_deg):
            return None
        prev = ctx.T_cur_kf_prev
        refined = geo.refine_pose_pnp(X[depth], ctx.uv_cur[depth], K, prev[:3, :3], prev[:3, 3],
                                      cfg.max_reprojection_error_px)
        if refined is None or np.count_nonzero(refined[2]) < cfg.min_scale_points:
            return None
        held_by_e = np.count_nonzero(err_e <= cfg.max_reprojection_error_px)
        held_by_map = np.count_nonzero(refined[2])
        err_map = geo.reprojection_errors(refined[0], refined[1], X[depth], ctx.uv_cur[depth], K)
        ridge = plane and np.median(err_e) > E_MAP_RESIDUAL_RATIO * np.median(err_map)  # E explains them worse
        if held_by_map <= held_by_e and not ridge:
            # E's pose puts at least as many of the map's points where they are seen as the map's own
            # fit does: that fit, not E, went wrong (LM from the previous pose into a wrong minimum:
            # KITTI, 15 points against E's 100).
            return None
        if held_by_e >= E_MAP_HELD_SHARE * held_by_map \
                and np.median(err_e) <= E_MAP_RESIDUAL_RATIO * np.median(err_map):
            # The fit is made to hold its points, so it holds a few more than E's pose whenever the
            # tracks are degraded (motion blur: E 11-34 against 15-39, median errors alike). Unless it
            # holds clearly more, or explains them clearly better (a cart entering the view took E's
            # direction: 41 against 50, but median errors 0.76 against 0.08 px), E stands.
            return None
        angle = rotation_angle_deg(refined[0] @ R_e.T)
        c_map, c_e = -refined[0].T @ refined[1], -R_e.T @ t_e
        norms = float(np.linalg.norm(c_map) * np.linalg.norm(c_e))
        direction = math.degrees(math.acos(np.clip(float(c_map @ c_e) / norms, -1.0, 1.0))) if norms > 0 else 0.0
        if angle <= cfg.e_map_max_rotation_diff_deg and direction <= E_MAP_MAX_DIRECTION_DIFF_DEG:
            return None
        st.notes.append(note(Decision.E_DISAGREES_WITH_MAP, angle=angle, direction=direction, plane=plane))
        agree = np.zeros(depth.shape[0], bool)
        agree[np.flatnonzero(depth)[refined[2]]] = True
        return agree


def grid_spread(uv: F64, mask: NDArray[np.bool_], width: int, height: int, cells: int = 4) -> float:
    """Of the cells of a ``cells`` x ``cells`` grid holding any feature, the fraction holding a masked one."""
    col = np.clip((uv[:, 0] * cells / max(width, 1)).astype(np.int64), 0, cells - 1)
    row = np.clip((uv[:, 1] * cells / max(height, 1)).astype(np.int64), 0, cells - 1)
    cell = row * cells + col
    occupied = np.unique(cell)
    if occupied.size == 0:
        return 0.0
    return float(np.unique(cell[mask]).size) / occupied.size
