"""The per-frame monocular VO pipeline: the one stateful object of epi_vo.

Both front doors drive this same object: ``epi-vo replay`` (offline, bags) and ``vo_node`` (ROS 2).

Frames and poses
    ``w`` is the odometry frame: the optical frame of the first camera pose (x right, y down,
    z forward). ``T_w_c`` maps current-camera points into ``w``; ``T_w_kf`` the same for the reference
    keyframe. Relative motion ``T_cur_kf`` maps keyframe-camera points into the current camera
    (``X_cur = R_cur_kf X_kf + t_cur_kf``), which is what ``cv2.recoverPose(E, uv_kf, uv_cur)`` returns.

Monocular scale convention
    Translation is observable only up to one global scale. The first map is built with a keyframe
    baseline of length 1 (VO units), and every later frame carries that scale through the map points
    triangulated between the last pair of keyframes; after a loss the new map's baseline continues from
    the last keyframe speed. A metric scale source (``scale``: the floor, wheel odometry) corrects each
    keyframe step and its map into metres once established.

Stages (each a module of ``epi_vo.core`` with its own tests; this object keeps the state and the order)
    features (``frontend``) -> two-view model selection (``selection``) -> motion: pose and scale
    (``motion``, ``scale``) -> keyframes / map (``mapping``, ``keyframe``, the optional windowed
    adjustment ``window``) -> frame record (``frame``); the covariance's map-scale and calibration terms
    are in ``map_scale``.

What is never invented
    No parallax: no depth and no keyframe. Pure rotation (the homography explains the motion and no
    parallax is left after removing the rotation): the rotation is published, the position holds.
    Before the map exists the scale is unknown: the position holds and its covariance says so.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import features as fe
from epi_vo.core import motion as mo
from epi_vo.core import scale as sc
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig, validate
from epi_vo.core.frame import (
    MAX_STAMP_NS,
    STAT_FIELDS,
    FrameResult,
    FrameStats,
    Matches,
    TrackingState,
    clamp_stamp_ns,
    frozen,
)
from epi_vo.core.handover import Handover
from epi_vo.core.keyframe import Keyframe, make_keyframe
from epi_vo.core.map_scale import DirectionOffset, MapScaleCovariance
from epi_vo.core.mapping import keyframe_map
from epi_vo.core.odometry import rotate_covariance
from epi_vo.core.patches import patch_templates
from epi_vo.core.selection import ModelSelector
from epi_vo.core.transforms import invert_T, make_T
from epi_vo.core.window import WindowedMap

_log = logging.getLogger(__name__)

MIN_MOVERS = 8  # features moving together before a group counts as an object moving on its own

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


class VoPipeline:
    """Monocular VO: feed it frames, get one immutable :class:`FrameResult` per frame."""

    def __init__(self, cfg: VoConfig | None = None) -> None:
        self.cfg = cfg or VoConfig()
        validate(self.cfg)
        self._orb = fe.make_orb(self.cfg) if self.cfg.frontend == "orb" else None
        self._patches = patch_templates(self.cfg)  # KLT tracks refined against their first image (None: off)
        self._motion = mo.MotionStage(self.cfg)
        self._wheel = sc.WheelOdometry()
        self._scale = sc.source_from_config(self.cfg, self._wheel)
        self._map_scale = MapScaleCovariance(self.cfg.scale_drift_per_keyframe)
        self._offset, self._fx = DirectionOffset(self.cfg.principal_point_sigma_px), 1.0  # fx: CameraInfo's
        self._window = WindowedMap(self.cfg.ba_window_keyframes, self.cfg.ba_every_keyframes, self.cfg.pixel_noise_px,
                                   self.cfg.ba_solver)
        self._next_id = 0  # the next feature track id
        self._mover_ids = np.zeros(0, np.int64)  # sorted ids of tracks judged to move on their own
        self._anchor: sc.WindowAnchor | None = None  # the scale source's anchor of the newest keyframe step
        self._factor = 1.0  # and its correction of that step (``_metric_step``)
        # keyframe stamp and relative covariance of the last pose (without its map's scale part)
        self._rel_prev: tuple[int, F64] | None = None
        self._last_pos_w = np.zeros(3)  # position of the last frame with a pose (for the step's scale error)
        self._jumped = False  # this frame's position jumped to metres (metric scale just established)
        self._T_w_c = np.eye(4)
        self._cov_w_c = np.zeros((6, 6))
        self._handover = Handover(self.cfg)  # the last pose with a map behind it; a restart starts from it
        # The last frame's (pose, position) were measured, not held: its step to the next is then measured.
        self._measured = (False, False)
        self._kf: Keyframe | None = None
        self._rows = np.zeros(0, np.int64)  # keyframe row of each live track
        self._pts_prev = np.zeros((0, 2), np.float32)
        self._gray_prev: NDArray[np.uint8] | None = None  # previous image, for KLT
        # One worker thread beside this one: H while E runs here, then tracking into the next image
        # (queued behind H, so the two never share the second core and H is back when E is done).
        worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="epi_vo_worker")
        self._ahead = fe.KltAhead(worker)
        self._select = ModelSelector(worker)
        self._key: object = None  # the image ``process`` was given (before downscaling)
        self._next: tuple[object, NDArray[np.uint8]] | None = None  # see ``announce_next``
        self._T_cur_kf_prev = np.eye(4)
        self._fail_count = 0
        self._n_keyframes = 0
        self._index = 0
        # (keyframe index, sum of the squared image-noise shares of the frames tracked since it, last frame)
        self._tracked_noise: tuple[int, float, int] = (-1, 0.0, -1)
        self._pending_reason = ""
        self._last_stamp_ns: int | None = None

    # ---------------------------------------------------------------------------------------------
    @property
    def pose(self) -> F64:
        """T_w_c of the last frame (a copy)."""
        return self._T_w_c.copy()

    @property
    def scale_status(self) -> sc.ScaleStatus:
        """The scale source's state now: source, metric or VO units, scale and its uncertainty."""
        return self._scale.status()

    def set_mounting(self, T_base_cam: F64) -> None:
        """The declared camera mounting, camera optical frame -> robot base (REP-103: base z up), from TF or
        the node's camera_xyz / camera_rpy: the floor (``ground_plane``) is sought along the up it implies
        (a level camera's -y without one). Raises ValueError when it is not finite."""
        up_cam = np.asarray(T_base_cam, dtype=np.float64)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        self._scale.set_mounting_up(up_cam)

    def add_wheel_odometry(self, stamp_ns: int | None, position_xyz: F64) -> sc.WheelSample:
        """One wheel odometry message (position in any fixed odom frame, metres; ``stamp_ns`` None: no ROS
        time) for the ``wheel_odometry`` scale source, in the order messages arrived: which are used is
        ``WheelOdometry.add``'s rule, the same for the node and the replay; the rest are counted."""
        return self._wheel.add(None if stamp_ns is None else int(stamp_ns), position_xyz)

    def reset(self, reason: str = "reset requested") -> None:
        """Restart tracking from the current pose: the next frame becomes a new keyframe, no map."""
        self._kf = None
        self._pending_reason = reason

    def _check_stamp(self, stamp_ns: int) -> FrameResult | None:
        """A stamp that is no valid ROS time: the frame is rejected and skipped. Equal stamp: the frame
        is skipped (a result saying so). Backwards: tracking restarts from the held pose (odometry stays
        continuous) and the frame is processed.

        The stamp is booked as the last one only when its frame result is made (``_result``), so a
        frame that fails half-way is not mistaken for a duplicate when it is then rejected.
        """
        stamp_ns = int(stamp_ns)
        if not 0 <= stamp_ns <= MAX_STAMP_NS:
            return self.skip(stamp_ns, f"image stamp {stamp_ns} ns is not a valid ROS time (0 to {MAX_STAMP_NS} ns)")
        last = self._last_stamp_ns
        if last is not None and stamp_ns == last:
            return self._skip(stamp_ns, "duplicate image stamp: frame skipped", "")
        if last is not None and stamp_ns < last:
            self.reset(f"time jumped backwards by {(last - stamp_ns) * 1e-9:.3f} s: tracking restarted from the "
                       "last pose")
        return None

    def skip(self, stamp_ns: int, problem: str, note: str = "") -> FrameResult:
        """Record a frame that cannot be used at all and must not touch tracking: its message could not be
        decoded, or its stamp is no valid ROS time. Nothing is processed, the stamp is not booked (the
        next frame is judged against the last good one) and no failure is counted; the record (skipped,
        rejected, with ``problem``; ``note`` is added to the reason) carries ``stamp_ns`` clamped into the
        valid range."""
        reason = f"frame rejected: {problem}; frame skipped" + (f" ({note})" if note else "")
        return self._skip(clamp_stamp_ns(stamp_ns), reason, problem)

    def _skip(self, stamp_ns: int, reason: str, problem: str) -> FrameResult:
        st = FrameStats(stamp_ns=stamp_ns)
        st.reasons.append(reason)
        result = self._result(stamp_ns, TrackingState.LOST, False, False, st, time.perf_counter(), book=False)
        return dataclasses.replace(result, skipped=True, problem=problem)

    def reject(self, stamp_ns: int, reason: str) -> FrameResult:
        """Account for a frame that could not be used (corrupt image, unusable calibration, ...).

        The frame gets its record like any other: no pose (held), a large covariance, the reason.
        It counts as a frame without a pose, so persistent bad input ends in a restart from the held
        pose, exactly as lost tracking does.
        """
        skipped = self._check_stamp(stamp_ns)
        if skipped is not None:
            return skipped
        return self._reject_checked(int(stamp_ns), reason, time.perf_counter())

    def _reject_checked(self, stamp_ns: int, reason: str, t_start: float) -> FrameResult:
        st = FrameStats(stamp_ns=stamp_ns)
        st.reasons.append(f"frame rejected: {reason}")
        if self._on_failure(st):
            self._kf = None
        return dataclasses.replace(self._result(stamp_ns, TrackingState.LOST, False, False, st, t_start),
                                   problem=reason)

    def announce_next(self, gray: NDArray[np.uint8], camera: CameraModel) -> None:
        """The image the next ``process`` call will get (the same object): tracking into it starts on a
        worker thread during this frame (``fe.KltAhead``; results identical). Replay knows it; live nodes do not."""
        if gray.ndim == 2 and gray.dtype == np.uint8:
            self._next = (gray, downscale(gray, camera, self.cfg.max_image_width)[0])

    def process(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int) -> FrameResult:
        """Process one grayscale frame taken with ``camera`` at ``stamp_ns``.

        An image the frontend cannot use (too small, or one OpenCV refuses) gives a rejected frame
        with the reason; the held pose and covariance are then those before the frame.

        Raises:
            CameraModelError: the image size does not match ``camera``.
            ValueError: ``gray`` is not a 2-D uint8 array.
        """
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"expected a 2-D uint8 grayscale image, got {gray.dtype} {gray.shape}")
        camera.check_image_size(gray.shape[1], gray.shape[0])
        skipped = self._check_stamp(stamp_ns)
        if skipped is not None:
            return skipped
        stamp_ns, self._key, self._fx = int(stamp_ns), gray, float(camera.K[0, 0])
        t_start = time.perf_counter()
        held = (self._T_w_c.copy(), self._cov_w_c.copy())
        try:
            gray, camera = downscale(gray, camera, self.cfg.max_image_width)
            problem = fe.image_problem(gray.shape[1], gray.shape[0], self.cfg)
            if problem is not None:
                return self._reject_checked(stamp_ns, problem, t_start)
            return self._process(gray, camera, stamp_ns, t_start)
        except cv2.error as exc:
            # OpenCV refused this image or these points: nothing of the frame is trusted. Restore the
            # held pose, drop the map (its state may be half-updated) and say what happened.
            self._T_w_c, self._cov_w_c = held
            self._kf = None
            detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
            _log.warning("frame at %d ns: OpenCV failed: %s", stamp_ns, detail)
            return self._reject_checked(stamp_ns, f"OpenCV could not process this frame ({detail}); tracking "
                                        "restarts from the last pose", t_start)

    def _process(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int, t_start: float
                 ) -> FrameResult:
        """One frame, already downscaled and checked usable: features -> model selection -> motion ->
        keyframes / map -> frame record."""
        st = FrameStats(stamp_ns=stamp_ns)
        if self._pending_reason:
            st.reasons.append(self._pending_reason)
            self._pending_reason = ""
        if self._kf is not None and not self._kf.camera.same_as(camera):
            st.reasons.append("camera_info changed: tracking restarted")
            self._kf = None

        t0 = time.perf_counter()
        if self._kf is None:
            result = self._start_keyframe(gray, camera, stamp_ns, st, t_start)
            return result

        kf = self._kf
        # features
        pts_cur, rows, orb_cur, ahead_ms, gain, st.track_noise_px = fe.track(
            gray, self.cfg, self._orb, self._gray_prev, self._pts_prev, self._rows, kf.descriptors,
            (self._ahead, self._key))
        if self._patches is not None and kf.ids is not None:
            pts_cur, st.n_refined = self._patches.refine(gray, pts_cur, kf.ids[rows])
        # This frame's image noise as a share of pixel_noise_px: its twist's, and one step of its pose's.
        noise_ratio = covm.twist_noise_ratio(st.track_noise_px, self.cfg.twist_noise_fb_factor,
                                             self.cfg.twist_noise_floor_px, self.cfg.pixel_noise_px)
        self._book_track_noise(kf, noise_ratio)
        if gain != 1.0:
            st.reasons.append(f"exposure changed: the image was scaled by {gain:.2f} to track it")
        nxt, self._next = self._next, None
        ahead = nxt is not None and self._orb is None and nxt[1].shape == gray.shape  # track into the next image
        xn_cur = camera.normalize(pts_cur)
        uv_cur = camera.to_pixels(xn_cur)
        st.timings["frontend"] = _ms(t0)
        if ahead_ms:  # KLT done on the worker thread during the previous frame (not in "total")
            st.timings["klt_ahead"] = ahead_ms
        st.n_tracked = int(rows.shape[0])

        motion: mo.Motion | None = None
        # Tracks judged to move on their own stay out of model selection, pose and map while tracked.
        excluded = self._movers_among(kf, rows)
        use = ~excluded
        n_use = int(np.count_nonzero(use))
        if n_use < self.cfg.min_inliers:
            if ahead:
                self._ahead.start(nxt[0], gray, nxt[1], pts_cur, self.cfg)
            st.reasons.append(f"too few tracked features ({n_use} < {self.cfg.min_inliers}"
                              + (f", {st.n_tracked - n_use} on moving objects)" if n_use < st.n_tracked else ")"))
        else:
            # two-view model selection, then motion (pose and scale)
            t0 = time.perf_counter()
            rows_u, xn_u, uv_u = (rows, xn_cur, uv_cur) if n_use == rows.shape[0] else \
                (rows[use], xn_cur[use], uv_cur[use])
            start_ahead = (lambda: self._ahead.start(nxt[0], gray, nxt[1], pts_cur, self.cfg)) if ahead else None
            sel = self._select(kf.uv[rows_u], uv_u, kf.camera.K, self.cfg, start_ahead)
            st.rh = sel.rh
            if sel.F is not None:
                st.F = sel.F
            if sel.H is not None:
                st.H = sel.H
            st.timings["models"] = _ms(t0)
            ctx = mo.MotionContext(kf, rows_u, xn_u, uv_u, self._T_cur_kf_prev, self._scale.initial_baseline,
                                   self._noise_since(kf), self.cfg.frontend == "klt")
            motion = self._motion.estimate(ctx, sel, st)
            if motion is not None and not mo.is_finite(motion):
                st.reasons.append("the motion estimate is not finite (check the calibration): no pose this frame")
                motion = None
            if motion is not None and n_use < rows.shape[0]:
                motion = _expanded(motion, use)
        moving = self._book_movers(kf, rows, uv_cur, excluded, motion, st)
        if motion is not None and motion.state is TrackingState.TRACKING:
            spread = mo.grid_spread(uv_cur, motion.inliers, camera.width, camera.height)
            if spread < self.cfg.static_min_spread:
                st.reasons.append(f"the pose's inliers are clustered: they cover {spread:.0%} of the image cells "
                                  "holding features (a moving object may dominate)")

        inl = motion.inliers if motion is not None else np.zeros(rows.shape[0], bool)
        st.matches = Matches(kf.pts[rows].astype(np.float64), pts_cur.astype(np.float64), kf.uv[rows], uv_cur, inl,
                             st.F, st.H, moving)
        t0 = time.perf_counter()
        is_kf = False
        step_cov: F64 | None = None
        if motion is None:
            state, has_pose = TrackingState.LOST, False
            self._rel_prev = None
            if self._on_failure(st):
                self._restart_here(gray, camera, stamp_ns, orb_cur)
                is_kf = True
            else:
                self._rows, self._pts_prev = rows, pts_cur
        else:
            self._fail_count = 0
            has_pose = True
            state = motion.state
            T_cur_kf = make_T(motion.R_cur_kf, motion.t_cur_kf)
            T_w_c = kf.T_w_kf @ invert_T(T_cur_kf)
            self._T_w_c = T_w_c
            self._cov_w_c = covm.compose(kf.cov_w_kf, kf.T_w_kf,
                                         motion.cov_rel if motion.cov_pose is None else motion.cov_pose,
                                         motion.t_cur_kf, motion.R_cur_kf)
            step_cov = self._step_covariance(kf, motion, T_w_c[:3, 3] - self._last_pos_w, noise_ratio)
            self._last_pos_w = T_w_c[:3, 3].copy()
            self._T_cur_kf_prev = T_cur_kf
            if state is TrackingState.TRACKING:
                self._handover.book(stamp_ns, self._T_w_c, self._cov_w_c)
            if state is TrackingState.INITIALIZING:
                # Unknown scale: the position is not justified by anything yet.
                self._cov_w_c = self._cov_w_c.copy()
                self._cov_w_c[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
            self._rows, self._pts_prev = rows, pts_cur
            # keyframes / map
            is_kf = self._maybe_keyframe(motion, kf, rows, pts_cur, xn_cur, gray, camera, stamp_ns, orb_cur, st)
        st.timings["mapping"] = _ms(t0)
        self._gray_prev = gray
        had_pose, had_position = self._measured
        if step_cov is not None and (not had_pose or (self._scale.metric_source and (
                not self._scale.established or self._jumped))):
            # Nothing measured the step: the previous frame had no pose (a loss, a restart), or metres
            # were asked for while the position is held (scale unknown) or at the frame where the map
            # first becomes metric (the position jumps to metres).
            step_cov = covm.block(self.cfg.lost_position_variance, self.cfg.lost_rotation_variance)
        elif step_cov is not None and not (had_position and state is not TrackingState.INITIALIZING):
            # A position held (initialising: the camera moves on while its keyframe's position is
            # published) on either side: the step's translation spans the frames it was held for.
            step_cov = covm.translation_unknown(step_cov, self.cfg.lost_position_variance)
        self._jumped = False
        return dataclasses.replace(self._result(stamp_ns, state, has_pose, is_kf, st, t_start),
                                   step_covariance=None if step_cov is None else frozen(covm.floored(step_cov)))

    def _book_track_noise(self, kf: Keyframe, ratio: float) -> None:
        """Add this frame's image noise squared, ``ratio`` of ``pixel_noise_px`` (``covariance.twist_noise_ratio``;
        1 for a frame that measured none), to what the tracks gathered since ``kf``; 1 per frame skipped."""
        if self._tracked_noise[0] != kf.index:
            self._tracked_noise = (kf.index, 0.0, kf.index)
        _, noise_sq, last = self._tracked_noise
        noise_sq += ratio**2 + float(max(self._index - last - 1, 0))
        self._tracked_noise = (kf.index, noise_sq, self._index)

    def _noise_since(self, kf: Keyframe) -> float:
        """The image noise the tracks gathered since ``kf`` (``_book_track_noise``) for the pose's covariance
        (``MotionContext.noise_sq``); ORB matches the keyframe directly: 1 (``pixel_noise_px``)."""
        if self.cfg.frontend != "klt" or self._tracked_noise[0] != kf.index:
            return 1.0
        return self._tracked_noise[1]

    def _step_covariance(self, kf: Keyframe, motion: mo.Motion, step_w: F64, ratio: float) -> F64:
        """Covariance of the motion since the previous frame (odometry frame) from both frames' poses
        relative to the keyframe (``covariance.step``); against a new keyframe (the previous frame) only
        this frame's counts. The image noise is the frame's tracks' (``ratio`` of ``pixel_noise_px``,
        ``covariance.twist_noise_ratio``): for the rotation always, for the position when this pose is E's
        against the previous frame's keyframe (``covariance.track_step``). The map's scale error is the
        same for both frames: it moves the step by its own fraction (``covariance.shared_scale_part``),
        not by the sum of both offsets from the keyframe."""
        c_kf = -motion.R_cur_kf.T @ motion.t_cur_kf
        own = motion.cov_rel - covm.shared_scale_part(c_kf, motion.shared_scale_var)
        cov = rotate_covariance(own, kf.T_w_kf[:3, :3])
        prev = self._rel_prev
        self._rel_prev = (kf.stamp_ns, cov)
        same = prev if prev is not None and prev[0] == kf.stamp_ns else None
        cov = covm.track_step(cov, None if same is None else same[1], ratio, motion.from_essential and same is not None)
        # The step's length carries the map's scale error (``MapScaleCovariance.step_rel_std``) and the
        # keyframe map's own (shared by both frames).
        rel2 = self._map_scale.step_rel_std(self._scale) ** 2 + motion.shared_scale_var
        return cov + np.pad(np.outer(step_w, step_w) * rel2, (0, 3))

    # ---------------------------------------------------------------------------------------------
    def _maybe_keyframe(self, motion: mo.Motion, kf: Keyframe, rows: NDArray[np.int64], pts_cur: F32,
                        xn_cur: F64, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int,
                        orb_cur: fe.OrbFeatures | None, st: FrameStats) -> bool:
        """The mapping stage decides; a new keyframe takes this frame's pose, covariance and map points."""
        X_cur = keyframe_map(self.cfg, motion, kf, rows, xn_cur, stamp_ns, st)
        if X_cur is None:
            return False
        self._anchor, self._factor = None, 1.0
        t = motion.t_cur_kf
        if motion.state is TrackingState.TRACKING:
            X_cur, t = self._metric_step(motion, kf, X_cur, stamp_ns)
            self._scale.on_keyframe(float(np.linalg.norm(t)), (stamp_ns - kf.stamp_ns) * 1e-9)
        if motion.state is TrackingState.TRACKING and st.n_triangulated > 0:
            # The keyframe's point cloud: every map point it holds, in the odometry frame.
            st.points_w = _transform(self._T_w_c, X_cur[np.isfinite(X_cur[:, 0])])
        cov = self._cov_w_c.copy()
        if motion.state is TrackingState.TRACKING:
            d = self._T_w_c[:3, 3] - kf.T_w_kf[:3, 3]
            cov[:3, :3] += self._map_scale.keyframe_cov(self._scale, motion.new_map is not None, d)
            self._offset.add_step(d, kf.T_w_kf[:3, :3], self._fx)
        ids_tracked = kf.ids[rows] if kf.ids is not None else None
        self._set_keyframe(gray, camera, stamp_ns, cov, pts_cur, X_cur, orb_cur, ids_tracked)
        if motion.state is TrackingState.TRACKING:
            self._adjust_window(st)
        else:
            self._window.clear()
        return True

    def _adjust_window(self, st: FrameStats) -> None:
        """Windowed bundle adjustment (``epi_vo.core.window``): the last keyframe's adjustment comes back and
        this keyframe (and the current pose) moves with the keyframe it adjusted; this one joins the window
        with its scale anchor and the scale stage's correction of its step, and the next adjustment starts
        when due (beside the frame loop with ``ba_solver: process``; either solver: same poses)."""
        kf = self._kf
        assert kf is not None
        t0 = time.perf_counter()
        update = self._window.collect(self.cfg.ba_wait)  # ba_wait: wait for the worker if it is not done
        if update is not None:
            st.timings["window_wait"], st.timings["window_solve"] = _ms(t0), update.ms  # solve: in the worker
            # The window's uncertainty (when it has one; covering the chain's) replaces the keyframe's.
            T, X, cov = self._window.correct(update, kf.T_w_kf, kf.ids, kf.X_kf, kf.cov_w_kf, self._factor)
            st.correction = update.correction  # the poses before move with it (the twist's reference)
            kf = self._kf = dataclasses.replace(kf, T_w_kf=T, X_kf=X, cov_w_kf=cov)
            self._T_w_c = T.copy()
            if update.cov_w_kf is not None:
                self._cov_w_c = cov.copy()
        self._window.add(kf.T_w_kf, kf.ids, kf.xn, kf.X_kf, self._anchor, kf.cov_w_kf, self._factor)
        submitted = self._window.due() and self._window.submit(float(kf.camera.K[0, 0]), self._mover_ids)
        if update is not None or submitted:
            st.timings["window"] = _ms(t0)
        if why := self._window.take_failure():
            st.reasons.append(why)

    def _metric_step(self, motion: mo.Motion, kf: Keyframe, X_cur: F64, stamp_ns: int) -> tuple[F64, F64]:
        """The scale source's correction of this keyframe step: the step from the last keyframe and the
        new keyframe's map points are scaled by it (and, when it establishes metric scale, the whole path
        of the current map about the point where the map was initialised). Returns the map points and
        the step translation ``t_cur_kf`` as corrected."""
        t = motion.t_cur_kf
        if motion.new_map is not None:
            self._map_scale.set_origin(kf.T_w_kf[:3, 3], kf.cov_w_kf)
            self._scale.on_new_map()
        was_metric = self._scale.established
        step = sc.KeyframeStep(X_cur, float(np.linalg.norm(t)), kf.stamp_ns, stamp_ns)
        factor = self._factor = self._scale.correction(step)
        self._anchor = self._scale.anchor(step)
        if factor == 1.0:
            return X_cur, t
        t = t * factor
        if was_metric:
            self._T_w_c = kf.T_w_kf @ invert_T(make_T(motion.R_cur_kf, t))
        else:  # metric from now on: the whole map so far was in VO units
            self._jumped = True
            self._window.clear()
            self._T_w_c = self._T_w_c.copy()
            origin = self._map_scale.origin_w
            d = factor * (self._T_w_c[:3, 3] - origin)
            self._T_w_c[:3, 3] = origin + d
            self._cov_w_c = self._map_scale.metric_covariance(self._scale, self._cov_w_c, factor, d)
            self._offset.rescale(factor)
        return X_cur * factor, t

    def _set_keyframe(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int, cov_w: F64,
                      pts_tracked: F32, X_tracked: F64, orb_cur: fe.OrbFeatures | None,
                      ids_tracked: NDArray[np.int64] | None = None) -> None:
        """Make the current frame the reference: keep tracked features (with depth and track id), top up
        the grid. Without ``ids_tracked`` (a new map) the window of adjusted keyframes is dropped."""
        if ids_tracked is None:
            self._window.clear()
        self._kf = make_keyframe(self._index, stamp_ns, self._T_w_c, cov_w, gray, camera, pts_tracked, X_tracked,
                                 self.cfg, self._orb, orb_cur, ids_tracked, self._next_id)
        if self._kf.ids is not None and self._kf.ids.size:
            self._next_id = max(self._next_id, int(self._kf.ids.max()) + 1)
            if self._patches is not None:
                self._patches.anchor(gray, self._kf.pts, self._kf.ids)
        # Movers stay flagged while they are tracked; tracks that ended are forgotten. Fewer than
        # MIN_MOVERS left is no group any more (the object left the view; a straggler may as well be a
        # static track caught at the group's edge): those are forgotten too.
        self._mover_ids = (np.intersect1d(self._mover_ids, self._kf.ids) if self._kf.ids is not None
                           else np.zeros(0, np.int64))
        if self._mover_ids.size < MIN_MOVERS:
            self._mover_ids = np.zeros(0, np.int64)
        self._rows = np.arange(self._kf.n_features, dtype=np.int64)
        self._pts_prev = self._kf.pts
        self._gray_prev = gray
        self._T_cur_kf_prev = np.eye(4)
        self._n_keyframes += 1

    def _start_keyframe(self, gray: NDArray[np.uint8], camera: CameraModel,
                        stamp_ns: int, st: FrameStats, t_start: float) -> FrameResult:
        """First frame, or the first frame after a restart: it becomes the keyframe, pose held."""
        first = self._index == 0
        t0 = time.perf_counter()
        cov = self._handover_cov(stamp_ns)
        self._set_keyframe(gray, camera, stamp_ns, cov, np.zeros((0, 2), np.float32), np.zeros((0, 3)),
                           None)
        self._map_scale.set_origin(self._T_w_c[:3, 3], cov)
        self._last_pos_w = self._T_w_c[:3, 3].copy()
        st.timings["frontend"] = _ms(t0)
        self._cov_w_c = cov
        st.reasons.append("first frame: reference keyframe set" if first else "new reference keyframe, no map yet")
        return self._result(stamp_ns, TrackingState.INITIALIZING, True, True, st, t_start, unknown=not first)

    def _restart_here(self, gray: NDArray[np.uint8], camera: CameraModel,
                      stamp_ns: int, orb_cur: fe.OrbFeatures | None) -> None:
        """Tracking lost: this frame becomes a keyframe at the held pose, the map is dropped."""
        cov = self._handover_cov(stamp_ns)
        self._cov_w_c = cov
        self._set_keyframe(gray, camera, stamp_ns, cov, np.zeros((0, 2), np.float32), np.zeros((0, 3)),
                           orb_cur)
        self._map_scale.set_origin(self._T_w_c[:3, 3], cov)
        self._last_pos_w = self._T_w_c[:3, 3].copy()
        self._fail_count = 0

    def _movers_among(self, kf: Keyframe, rows: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which of the tracked rows belong to tracks judged to move on their own."""
        if kf.ids is None or self._mover_ids.size == 0:
            return np.zeros(rows.shape[0], bool)
        return np.isin(kf.ids[rows], self._mover_ids)

    def _book_movers(self, kf: Keyframe, rows: NDArray[np.int64], uv_cur: F64, excluded: NDArray[np.bool_],
                     motion: mo.Motion | None, st: FrameStats) -> NDArray[np.bool_]:
        """Remember the tracks that moved on their own this frame (a coherent group of at least
        MIN_MOVERS: E's consensus against the map's pose), and say how many movers are in view and where.
        Returns which tracked rows are movers."""
        moving = excluded.copy()
        if motion is not None and motion.moving is not None and np.count_nonzero(motion.moving) >= MIN_MOVERS:
            moving |= motion.moving
            if kf.ids is not None:
                self._mover_ids = np.union1d(self._mover_ids, kf.ids[rows[motion.moving]])
        n = int(np.count_nonzero(moving))
        if n == 0:
            return moving
        if st.n_moving == 0:
            lo, hi = uv_cur[moving].min(axis=0), uv_cur[moving].max(axis=0)
            st.moving_region = (int(lo[0]), int(lo[1]), int(np.ceil(hi[0])), int(np.ceil(hi[1])))
            x0, y0, x1, y1 = st.moving_region
            st.reasons.append(f"{n} tracked features move on their own (x {x0}-{x1}, y {y0}-{y1} px): left out of "
                              "pose and map")
        st.n_moving += n
        return moving

    def _handover_cov(self, stamp_ns: int) -> F64:
        """Covariance of the held pose a new map starts from (a restart, a reset, a jump back in time): the
        last good pose's and the motion possible since (``handover``), not the 'unknown' variance: that one
        is added to what is published while the new map has no scale (``_result``), so it is never summed
        over restarts. Before any map: the current covariance."""
        good, metric = self._handover.good, self._scale.established
        scale_cov = self._map_scale.systematic(self._scale, good.T_w_c[:3, 3]) if good and metric else None
        cov = self._handover.covariance(stamp_ns, metric, scale_cov)
        return self._cov_w_c.copy() if cov is None else covm.floored(cov)

    def _on_failure(self, st: FrameStats) -> bool:
        """Count a frame without a pose; True when tracking must restart from the held pose.

        A frame without a pose is 'lost' for consumers either way; the map is dropped only once the
        failure persists for ``lost_after_frames`` frames, or nothing is left to track.
        """
        self._fail_count += 1
        restart = self._fail_count >= self.cfg.lost_after_frames or st.n_tracked < self.cfg.min_inliers
        if restart:
            st.reasons.append(f"tracking lost after {self._fail_count} frame(s) without a pose: re-initializing "
                              "from the last pose")
        else:
            st.reasons.append(f"no pose this frame ({self._fail_count}/{self.cfg.lost_after_frames}); pose held")
        return restart

    def _result(self, stamp_ns: int, state: TrackingState, has_pose: bool, is_kf: bool, st: FrameStats,
                t_start: float, *, book: bool = True, unknown: bool = False) -> FrameResult:
        if book:
            self._last_stamp_ns = stamp_ns
            # A held position is not measured; the first frame's is the origin by definition.
            self._measured = (has_pose, has_pose and not unknown and (
                state is not TrackingState.INITIALIZING or self._index == 0))
        self._keep_state_finite(st)
        cov = self._cov_w_c.copy()
        if unknown:  # a new reference keyframe after a restart: where the camera is, is not known yet
            cov[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
        if not has_pose:
            cov[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
            cov[3:, 3:] += np.eye(3) * self.cfg.lost_rotation_variance
        T_out = self._T_w_c
        if has_pose and self._scale.metric_source and not self._scale.established:
            # Metres were asked for and the scale is not known yet: the position holds where the map
            # started (nothing in VO units is published as metres) and its covariance says so.
            T_out = T_out.copy()
            T_out[:3, 3] = self._map_scale.origin_w
            cov[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
            st.reasons.append("metric scale not established yet: position held")
        elif self._scale.established:
            cov[:3, :3] += self._map_scale.systematic(self._scale, T_out[:3, 3])
        if (kf := self._kf) is not None:
            cov[:3, :3] += self._offset.cov(T_out[:3, 3] - kf.T_w_kf[:3, 3], kf.T_w_kf[:3, :3], self._fx)
        cov = covm.floored(cov)
        st.timings["total"] = _ms(t_start)
        n_features = kf.n_features if kf is not None else 0
        for name in STAT_FIELDS[:1] + STAT_FIELDS[2:]:  # not measured is NaN, never infinite
            if math.isinf(getattr(st, name)):
                setattr(st, name, math.nan)
        res = FrameResult(
            index=self._index, stamp_ns=int(stamp_ns), state=state, has_pose=has_pose, is_keyframe=is_kf,
            model=st.model, rh=st.rh, n_features=n_features, n_tracked=st.n_tracked, n_inliers=st.n_inliers,
            inlier_ratio=st.n_inliers / st.n_tracked if st.n_tracked else 0.0,
            median_parallax_deg=st.median_parallax_deg, n_triangulated=st.n_triangulated,
            positive_depth_ratio=st.positive_depth_ratio, median_reproj_err_px=st.median_reproj_err_px,
            relative_scale=st.relative_scale, n_keyframes=self._n_keyframes, T_w_c=frozen(T_out),
            covariance=frozen(cov), points_w=frozen(st.points_w[np.all(np.isfinite(st.points_w), axis=1)]),
            timings_ms=dict(st.timings),
            reason="; ".join(st.reasons), matches=st.matches, scale=self._scale.status(), n_moving=st.n_moving,
            moving_fraction=st.n_moving / st.n_tracked if st.n_tracked else 0.0, moving_region=st.moving_region,
            static_score=st.static_score, focal_ratio=st.focal_ratio, track_noise_px=st.track_noise_px,
            n_refined=st.n_refined,
            correction=None if st.correction is None or T_out is not self._T_w_c else frozen(st.correction))
        self._index += 1
        return res

    def _keep_state_finite(self, st: FrameStats) -> None:
        """The held pose and covariance are finite whatever the input did (a guard: every estimate is
        checked before it is taken, so this only fires on a defect; it says so in the record)."""
        if not np.all(np.isfinite(self._T_w_c)):
            _log.error("non-finite pose held: reset to the origin")
            st.reasons.append("internal: the held pose was not finite; reset to the origin")
            self._T_w_c = np.eye(4)
            self._kf = None
        if not np.all(np.isfinite(self._cov_w_c)):
            _log.error("non-finite covariance held: reset to the 'unknown' covariance")
            st.reasons.append("internal: the held covariance was not finite; reset to the 'unknown' covariance")
            self._cov_w_c = covm.block(self.cfg.lost_position_variance, self.cfg.lost_rotation_variance)
            self._kf = None


# -------------------------------------------------------------------------------------------------
def downscale(gray: NDArray[np.uint8], camera: CameraModel, max_width: int
              ) -> tuple[NDArray[np.uint8], CameraModel]:
    """The image and camera the pipeline works on: wider images shrunk to ``max_width`` (0: never)."""
    if max_width <= 0 or gray.shape[1] <= max_width:
        return gray, camera
    factor = max_width / gray.shape[1]
    small = cv2.resize(gray, (max_width, round(gray.shape[0] * factor)), interpolation=cv2.INTER_AREA)
    return small, camera.scaled(factor)


def _expanded(motion: mo.Motion, use: NDArray[np.bool_]) -> mo.Motion:
    """A motion estimated on the rows ``use`` spread back over all tracked rows (the others: no
    inlier, no point, not newly moving)."""
    n = use.shape[0]
    inl = np.zeros(n, bool)
    inl[use] = motion.inliers
    moving = None
    if motion.moving is not None:
        moving = np.zeros(n, bool)
        moving[use] = motion.moving
    new_map = motion.new_map.expanded(np.flatnonzero(use), n) if motion.new_map is not None else None
    return dataclasses.replace(motion, inliers=inl, moving=moving, new_map=new_map)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _transform(T_a_b: F64, X_b: F64) -> F64:
    return X_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
