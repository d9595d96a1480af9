"""The per-frame step: ``process(state, frame, env) -> (state, FrameResult)``, a function of the tracking state.

One frame goes through the stages in order, each a function (or a small object without hidden state) that
returns a frozen result with its own statistics and decisions:

    features (``features.track``) -> model selection (``selection``) -> motion (``motion.estimate``) ->
    keyframe / map, metric scale, windowed adjustment (``keyframing``) -> the record (``publish``)

The tracking state (``state.TrackState``) is replaced once per frame; nothing else persists. Where the heavy
computations run (KLT ahead, H beside E, the adjustment's worker process) is the ``Workers``' business
(``env.workers``, ``epi_vo.core.workers``): the results are the same. ``reject``, ``skip`` and ``restart``
are the other ways a frame (or the caller) changes the state.

Frames and units: ``epi_vo.core.pipeline`` (the shell around this step that the front doors drive).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import features as fe
from epi_vo.core import geometry as geo
from epi_vo.core import motion as mo
from epi_vo.core import relocalise as rl
from epi_vo.core.calibration_cov import CalibrationError
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import Frontend, VoConfig
from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.frame import MAX_STAMP_NS, FrameResult, Matches, TrackingState, clamp_stamp_ns
from epi_vo.core.handover import HeldStart
from epi_vo.core.keyframe import Keyframe
from epi_vo.core.keyframing import (
    KeyframeOutcome,
    book_movers,
    maybe_keyframe,
    movers_among,
    new_reference,
    set_keyframe,
)
from epi_vo.core.odometry import rotate_covariance
from epi_vo.core.publish import Observed, publish
from epi_vo.core.state import LastRelative, TrackedNoise, Tracks, TrackState
from epi_vo.core.transforms import invert_T, make_T
from epi_vo.core.workers import Ahead, Workers

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class Frame:
    """One grayscale image (2-D uint8, its size checked against ``camera``) taken at ``stamp_ns``."""

    gray: NDArray[np.uint8]
    camera: CameraModel
    stamp_ns: int


@dataclass(frozen=True)
class StepEnv:
    """What the step reads besides the state and the frame: the config, the ORB detector (frontend
    ``orb``; its settings only) and where the computations run."""

    cfg: VoConfig
    workers: Workers
    orb: cv2.ORB | None = None

    @staticmethod
    def of(cfg: VoConfig, workers: Workers) -> StepEnv:
        return StepEnv(cfg, workers, fe.make_orb(cfg) if cfg.frontend is Frontend.ORB else None)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def restart(state: TrackState, why: Note) -> TrackState:
    """Tracking restarts from the held pose at the next processed frame, which says ``why``."""
    return dataclasses.replace(state, kf=None, pending=why, recent=(), last_seen=None)


def skip(state: TrackState, stamp_ns: int, why: Note, problem: str, cfg: VoConfig) -> tuple[TrackState, FrameResult]:
    """A frame that cannot be used at all and must not touch tracking: nothing is processed, the stamp is
    not booked and no failure is counted; the record is skipped, rejected with ``problem``."""
    return publish(state, cfg, stamp_ns, TrackingState.LOST, False, False, Observed(), (why,), {}, time.perf_counter(),
                   book=False, skipped=True, problem=problem)


def check_stamp(state: TrackState, stamp_ns: int, cfg: VoConfig) -> tuple[TrackState, FrameResult | None]:
    """A stamp that is no valid ROS time: the frame is skipped. Equal stamp: the frame is skipped (a record
    saying so). Backwards: tracking restarts from the held pose (odometry stays continuous) and the frame is
    processed. The stamp is booked when its frame's record is made (``publish``), so a frame that fails
    half-way is not mistaken for a duplicate when it is then rejected."""
    if not 0 <= stamp_ns <= MAX_STAMP_NS:
        problem = f"image stamp {stamp_ns} ns is not a valid ROS time (0 to {MAX_STAMP_NS} ns)"
        return skip(state, clamp_stamp_ns(stamp_ns), note(Decision.STAMP_INVALID, problem=problem, note=""), problem,
                    cfg)
    last = state.last_stamp_ns
    if last is not None and stamp_ns == last:
        return skip(state, stamp_ns, note(Decision.DUPLICATE_STAMP), "", cfg)
    if last is not None and stamp_ns < last:
        return restart(state, note(Decision.TIME_JUMPED_BACK, seconds=(last - stamp_ns) * 1e-9)), None
    return state, None


def _on_failure(state: TrackState, cfg: VoConfig, n_tracked: int) -> tuple[TrackState, bool, Note]:
    """Count a frame without a pose; True when tracking must restart from the held pose (the failure
    persisted for ``lost_after_frames`` frames, or nothing is left to track). A frame without a pose is
    'lost' for consumers either way."""
    failures = state.fail_count + 1
    restart_now = failures >= cfg.lost_after_frames or n_tracked < cfg.min_inliers
    why = note(Decision.TRACKING_LOST, failures=failures) if restart_now else \
        note(Decision.NO_POSE, failures=failures, limit=cfg.lost_after_frames)
    return dataclasses.replace(state, fail_count=failures), restart_now, why


def reject_checked(state: TrackState, stamp_ns: int, why: Note, t_start: float, cfg: VoConfig
                   ) -> tuple[TrackState, FrameResult]:
    """A frame that could not be used, its stamp checked: no pose (held), counted as a frame without one."""
    state, restart_now, failed = _on_failure(state, cfg, 0)
    if restart_now:
        state = dataclasses.replace(state, kf=None)
    return publish(state, cfg, stamp_ns, TrackingState.LOST, False, False, Observed(), (why, failed), {}, t_start,
                   problem=why["problem"])


def process(state: TrackState, frame: Frame, env: StepEnv) -> tuple[TrackState, FrameResult]:
    """One frame (image already validated against its camera): the state after it and its record.

    An image the frontend cannot use (too small, or one OpenCV refuses) gives a rejected frame with the
    reason; the held pose and covariance are then those before the frame, and the map is dropped."""
    stamp_ns = int(frame.stamp_ns)
    state, skipped = check_stamp(state, stamp_ns, env.cfg)
    if skipped is not None:
        return state, skipped
    t_start = time.perf_counter()
    try:
        gray, camera = downscale(frame.gray, frame.camera, env.cfg.max_image_width)
        problem = fe.image_problem(gray.shape[1], gray.shape[0], env.cfg)
        if problem is not None:
            return reject_checked(state, stamp_ns, note(Decision.IMAGE_TOO_SMALL, problem=problem), t_start, env.cfg)
        return _tracked(state, Frame(gray, camera, stamp_ns), env, t_start)
    except cv2.error as exc:
        # OpenCV refused this image or these points: nothing of the frame is taken (the state before it),
        # the map is dropped and the record says what happened.
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        _log.warning("frame at %d ns: OpenCV failed: %s", stamp_ns, detail)
        problem = f"OpenCV could not process this frame ({detail}); tracking restarts from the last pose"
        state = dataclasses.replace(state, kf=None, window=state.window.cleared())
        return reject_checked(state, stamp_ns, note(Decision.OPENCV_FAILED, problem=problem, detail=detail), t_start,
                              env.cfg)


def _tracked(state: TrackState, frame: Frame, env: StepEnv, t_start: float) -> tuple[TrackState, FrameResult]:
    """One frame, downscaled and usable: a new reference when there is no keyframe, else tracked."""
    notes: tuple[Note, ...] = ()
    if state.pending is not None:
        notes, state = (state.pending,), dataclasses.replace(state, pending=None)
    if state.kf is not None and not state.kf.camera.same_as(frame.camera):
        notes, state = (*notes, note(Decision.CAMERA_CHANGED)), dataclasses.replace(state, kf=None)
    if state.kf is None:
        first = state.index == 0
        t0 = time.perf_counter()
        state = _held_from(new_reference(state, env.cfg, env.orb, frame.gray, frame.camera, frame.stamp_ns),
                           frame.stamp_ns)
        notes = (*notes, note(Decision.FIRST_FRAME if first else Decision.NEW_REFERENCE))
        return publish(state, env.cfg, frame.stamp_ns, TrackingState.INITIALIZING, True, True, Observed(), notes,
                       {"frontend": _ms(t0)}, t_start, unknown=not first)
    return _track(state, state.kf, frame, env, t_start, notes)


def _booked_noise(state: TrackState, kf: Keyframe, ratio: float) -> TrackedNoise:
    """What the tracks gathered since ``kf`` with this frame's image noise squared, ``ratio`` of
    ``pixel_noise_px`` (``covariance.twist_noise_ratio``; 1 for a frame that measured none); 1 per frame
    skipped."""
    noise = state.tracked_noise if state.tracked_noise.kf_index == kf.index else TrackedNoise(kf.index, 0.0, kf.index)
    noise_sq = noise.noise_sq + ratio**2 + float(max(state.index - noise.last_index - 1, 0))
    return TrackedNoise(kf.index, noise_sq, state.index)


def _track(state: TrackState, kf: Keyframe, frame: Frame, env: StepEnv, t_start: float, notes: tuple[Note, ...]
           ) -> tuple[TrackState, FrameResult]:
    """Features -> model selection -> motion -> keyframe / map -> record, against the keyframe ``kf``."""
    cfg, gray, camera, stamp_ns = env.cfg, frame.gray, frame.camera, frame.stamp_ns
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    tracked = fe.track(gray, cfg, env.orb, state.tracks.gray, state.tracks.pts, state.tracks.rows, kf.descriptors,
                       env.workers.track_klt)
    pts_cur, rows, orb_cur, track_noise = tracked.pts, tracked.rows, tracked.orb, tracked.noise_px
    born_uv, born_pts, born_stamp_ns = _newborn_tracked(state.tracks, gray, cfg, tracked.gain)
    born_uv_cur = camera.to_pixels(camera.normalize(born_pts))
    born_uv_kf = _at_keyframe(born_uv, born_uv_cur, born_stamp_ns, kf.stamp_ns, stamp_ns)
    n_refined = None
    if state.patches is not None and kf.ids is not None:
        patches, pts_cur, n_refined = state.patches.refined(gray, pts_cur, kf.ids[rows])
        state = dataclasses.replace(state, patches=patches)
    tracks_now = Tracks(rows, pts_cur, state.tracks.gray, born_uv, born_pts, born_stamp_ns, state.tracks.still_cells)
    # This frame's image noise as a share of pixel_noise_px: its twist's, and one step of its pose's.
    noise_ratio = covm.twist_noise_ratio(track_noise, cfg.twist_noise_fb_factor, cfg.twist_noise_floor_px,
                                         cfg.pixel_noise_px)
    state = dataclasses.replace(state, tracked_noise=_booked_noise(state, kf, noise_ratio))
    notes = notes + tracked.notes
    ahead = Ahead(gray, pts_cur) if env.orb is None else None  # KLT from this image into the next may start now
    xn_cur = camera.normalize(pts_cur)
    uv_cur = camera.to_pixels(xn_cur)
    timings["frontend"] = _ms(t0)
    if tracked.ahead_ms:  # KLT done ahead of this frame, during the previous one (not in "total")
        timings["klt_ahead"] = tracked.ahead_ms
    n_tracked = int(rows.shape[0])

    motion: mo.Motion | None = None
    est = mo.MotionEstimate(state.motion)
    rh, F, H = float("nan"), np.zeros((3, 3)), np.zeros((3, 3))
    # Tracks judged to move on their own stay out of model selection, pose and map while tracked.
    excluded = movers_among(state, kf, rows)
    use = ~excluded
    n_use = int(np.count_nonzero(use))
    if n_use < cfg.min_inliers:
        if ahead is not None:
            env.workers.track_ahead(ahead, cfg)
        notes = (*notes, note(Decision.TOO_FEW_TRACKED, n=n_use, need=cfg.min_inliers, movers=n_tracked - n_use))
    else:
        t0 = time.perf_counter()
        rows_u, xn_u, uv_u = (rows, xn_cur, uv_cur) if n_use == n_tracked else (rows[use], xn_cur[use], uv_cur[use])
        sel = env.workers.select_model(kf.uv[rows_u], uv_u, kf.camera.K, cfg, ahead)
        rh = sel.rh
        F = sel.F if sel.F is not None else F
        H = sel.H if sel.H is not None else H
        timings["models"] = _ms(t0)
        ctx = mo.MotionContext(kf, rows_u, xn_u, uv_u, state.T_cur_kf_prev, state.scale.initial_baseline,
                               _noise_since(state, kf, cfg), cfg.frontend is Frontend.KLT, stamp_ns,
                               born_uv=born_uv_kf, born_uv_cur=born_uv_cur, n_booked=n_tracked - n_use)
        est = mo.estimate(cfg, ctx, sel, state.motion)
        state = dataclasses.replace(state, motion=est.memory)
        notes = notes + est.notes
        timings["pose"] = est.ms
        motion = est.motion
        if motion is not None and not mo.is_finite(motion):
            notes = (*notes, note(Decision.MOTION_NOT_FINITE))
            motion = None
        if motion is not None and n_use < n_tracked:
            motion = mo.expanded(motion, use)
    state, movers = book_movers(state, kf, rows, uv_cur, excluded, motion, est.n_moving, est.moving_region)
    notes = notes + movers.notes
    if motion is not None and motion.state is TrackingState.TRACKING:
        spread = mo.grid_spread(uv_cur, motion.inliers, camera.width, camera.height)
        if spread < cfg.static_min_spread:
            notes = (*notes, note(Decision.INLIERS_CLUSTERED, spread=spread))
    inl = motion.inliers if motion is not None else np.zeros(n_tracked, bool)
    observed = Observed(est.model, rh, n_tracked, est.n_inliers, est.median_parallax_deg, est.n_triangulated,
                        est.positive_depth_ratio, est.median_reproj_err_px, est.relative_scale, est.static_score,
                        est.focal_ratio, track_noise, n_refined, movers.n_moving, movers.region,
                        matches=Matches(kf.pts[rows].astype(np.float64), pts_cur.astype(np.float64), kf.uv[rows],
                                        uv_cur, inl, F, H, movers.moving))

    views = state.recent if state.last_seen is None else (*state.recent, state.last_seen)
    if views and env.orb is None and (motion is None or state.held is not None):
        # Lost against the reference (or a new map not yet made after a loss): the map points of the last
        # tracked frame and of the recent keyframes may find this frame again, and the same map, trajectory
        # and scale continue.
        t0 = time.perf_counter()
        found = rl.relocalise(views, gray, camera, cfg)
        timings["relocalise"] = _ms(t0)
        if found is not None:
            return _relocalised(state, env, frame, found, observed, notes, timings, t_start)
    t0 = time.perf_counter()
    if motion is None:
        state, restart_now, failed = _on_failure(dataclasses.replace(state, last_relative=None), cfg, n_tracked)
        notes = (*notes, failed)
        if restart_now:
            state = dataclasses.replace(_held_from(new_reference(state, cfg, env.orb, gray, camera, stamp_ns, orb_cur),
                                                   stamp_ns), fail_count=0)
        else:
            state = dataclasses.replace(state, tracks=tracks_now)
        timings["mapping"] = _ms(t0)
        state = dataclasses.replace(state, tracks=dataclasses.replace(state.tracks, gray=gray))
        return publish(state, cfg, stamp_ns, TrackingState.LOST, False, restart_now, observed, notes, timings, t_start)

    # A pose: this frame's relative to the keyframe, composed onto the keyframe's.
    T_cur_kf = make_T(motion.R_cur_kf, motion.t_cur_kf)
    T_w_c = kf.T_w_kf @ invert_T(T_cur_kf)
    cov_w_c = covm.compose(kf.cov_w_kf, kf.T_w_kf, motion.cov_rel if motion.cov_pose is None else motion.cov_pose,
                           motion.t_cur_kf, motion.R_cur_kf)
    if motion.new_map is not None and state.held is not None:
        # The map starts at its reference keyframe's position, held since ``state.held.since_ns``: the
        # camera's motion over that time is what the frames tracked meanwhile saw (``handover.HeldStart``).
        cov_w_c[:3, :3] += np.eye(3) * state.held.motion_var(float(np.linalg.norm(motion.t_cur_kf)),
                                                             (stamp_ns - kf.stamp_ns) * 1e-9,
                                                             est.median_parallax_deg)
    state, step_cov = _step_covariance(state, cfg, kf, motion, T_w_c[:3, 3] - state.last_pos_w, noise_ratio)
    moved = motion.state is TrackingState.TRACKING
    state = dataclasses.replace(state, calib=_calibration(state, kf, motion, rows, xn_cur, camera),
                                rotation_bias=state.rotation_bias.tracked(
                                    kf.index, kf.T_w_kf, motion.R_cur_kf, motion.t_cur_kf,
                                    motion.rotation_excess if moved else None))
    state = dataclasses.replace(state, fail_count=0, T_w_c=T_w_c, cov_w_c=cov_w_c, last_pos_w=T_w_c[:3, 3].copy(),
                                T_cur_kf_prev=T_cur_kf, tracks=tracks_now)
    if motion.state is TrackingState.TRACKING:
        state = dataclasses.replace(state, handover=state.handover.booked(stamp_ns, state.T_w_c, state.cov_w_c),
                                    held=None)
    state, kfo = maybe_keyframe(state, cfg, env.orb, env.workers.solver, motion, kf, rows, pts_cur, xn_cur, gray,
                                camera, stamp_ns, orb_cur, est.n_inliers, est.median_parallax_deg, est.n_triangulated)
    if state.held is not None:
        # Still held: this frame measured the motion against the reference; a new reference books it.
        held = state.held.seen(stamp_ns, est.median_parallax_deg)
        state = dataclasses.replace(state, held=held.reanchored(stamp_ns) if kfo.is_keyframe else held)
    if motion.state is TrackingState.STATIC and not kfo.is_keyframe and env.orb is None:
        born_still = geo.score_static(born_uv_kf, born_uv_cur, cfg.score_sigma_px)[1]
        state = _replenished(state, cfg, gray, camera, stamp_ns,
                             np.vstack([pts_cur[motion.inliers], born_pts[born_still]]).astype(np.float32))
    state = _remembered(state, cfg, motion, kf, kfo, gray, rows, pts_cur)
    timings.update(kfo.timings)
    timings["mapping"] = _ms(t0)
    notes = notes + kfo.notes
    if kfo.triangulated:
        observed = dataclasses.replace(observed, n_triangulated=kfo.n_triangulated,
                                       positive_depth_ratio=kfo.positive_depth_ratio,
                                       median_reproj_err_px=kfo.median_reproj_err_px)
    if kfo.points_w is not None:
        observed = dataclasses.replace(observed, points_w=kfo.points_w)
    observed = dataclasses.replace(observed, correction=kfo.correction)
    state = dataclasses.replace(state, tracks=dataclasses.replace(state.tracks, gray=gray))
    step_cov = _unmeasured_step(state, cfg, step_cov, motion.state, kfo.jumped)
    # Initialising, the position is held (unknown scale): what is published says so, while the state's
    # covariance, which a re-anchored reference keyframe and the map after it take, stays the estimate's.
    return publish(state, cfg, stamp_ns, motion.state, True, kfo.is_keyframe, observed, notes, timings, t_start,
                   step_covariance=step_cov, unknown=motion.state is TrackingState.INITIALIZING)


def _remembered(state: TrackState, cfg: VoConfig, motion: mo.Motion, kf: Keyframe, kfo: KeyframeOutcome,
                gray: NDArray[np.uint8], rows: I64, pts_cur: NDArray[np.float32]) -> TrackState:
    """The views a lost frame may be found again from after this frame with a pose: a tracking keyframe
    joins the recent ones, a tracking frame that is none is the last one seen (its inliers). A new map or
    one now in metres has another unit: the old views go."""
    recent, last_seen = state.recent, state.last_seen
    if motion.new_map is not None or kfo.jumped:
        recent, last_seen = (), None
    if motion.state is TrackingState.TRACKING:
        if kfo.is_keyframe and state.kf is not None:
            recent, last_seen = rl.remembered(recent, state.kf, gray, cfg), None
        elif not kfo.is_keyframe:
            last_seen = rl.view(kf, gray, rows[motion.inliers], pts_cur[motion.inliers], cfg)
    return dataclasses.replace(state, recent=recent, last_seen=last_seen)


def _relocalised(state: TrackState, env: StepEnv, frame: Frame, found: rl.Relocalised, observed: Observed,
                 notes: tuple[Note, ...], timings: dict[str, float], t_start: float) -> tuple[TrackState, FrameResult]:
    """This frame found again against a recent keyframe: it becomes a keyframe at that pose, holding the
    map points that found it (in its own camera frame), so the map, its scale and the trajectory go on. Its
    covariance is the keyframe's and the fit's; the step from the last pose (across the loss) is not
    measured."""
    cfg, kf = env.cfg, found.kf
    T_w_c, cov = found.T_w_c, covm.floored(found.cov_w_c)
    state = dataclasses.replace(state, T_w_c=T_w_c, cov_w_c=cov, last_pos_w=T_w_c[:3, 3].copy(), fail_count=0,
                                held=None, last_relative=None,
                                handover=state.handover.booked(frame.stamp_ns, T_w_c, cov))
    ids = kf.ids[found.rows] if kf.ids is not None else None
    state = set_keyframe(state, cfg, env.orb, frame.gray, frame.camera, frame.stamp_ns, cov, found.pts, found.X_cur,
                         None, ids)
    assert state.kf is not None
    state = dataclasses.replace(state, recent=rl.remembered(state.recent, state.kf, frame.gray, cfg), last_seen=None)
    notes = (*notes, note(Decision.RELOCALISED, kf=kf.index, n=found.n))
    observed = dataclasses.replace(observed, n_inliers=found.n)
    return publish(state, cfg, frame.stamp_ns, TrackingState.TRACKING, True, True, observed, notes, timings, t_start,
                   step_covariance=covm.block(cfg.lost_position_variance, cfg.lost_rotation_variance))


def _calibration(state: TrackState, kf: Keyframe, motion: mo.Motion, rows: I64, xn_cur: F64,
                 camera: CameraModel) -> CalibrationError:
    """The calibration error's sensitivity after this pose: its own two-view part from the inliers when it
    moved relative to the keyframe (``calibration_cov``)."""
    if not state.calib.declared:
        return state.calib
    moved = motion.state is TrackingState.TRACKING
    inl = motion.inliers
    return state.calib.tracked(kf.index, kf.T_w_kf, motion.R_cur_kf, motion.t_cur_kf,
                               kf.xn[rows[inl]] if moved else None, xn_cur[inl] if moved else None,
                               float(camera.K[0, 0]))


def _held_from(state: TrackState, stamp_ns: int) -> TrackState:
    """A new reference keyframe without a map: the position is held from here, unless it already was (then
    the old reference's parallax and the time since it was last measured are booked)."""
    held = HeldStart.at(stamp_ns) if state.held is None else state.held.reanchored(stamp_ns)
    return dataclasses.replace(state, held=held)


def _newborn_tracked(tracks: Tracks, gray: NDArray[np.uint8], cfg: VoConfig, gain: float
                     ) -> tuple[F64, NDArray[np.float32], NDArray[np.int64]]:
    """The tracks born since the keyframe followed into ``gray`` (at the exposure ``gain`` the keyframe's
    tracks were followed with): where each kept one was found (undistorted pixels), where it is now (raw
    pixels) and when it was found."""
    if tracks.born_pts.shape[0] == 0 or tracks.gray is None:
        return tracks.born_uv, tracks.born_pts, tracks.born_stamp_ns
    kept = fe.track_klt(tracks.gray, gray, tracks.born_pts, cfg, gain=gain)
    return tracks.born_uv[kept.ok], kept.pts[kept.ok], tracks.born_stamp_ns[kept.ok]


def _at_keyframe(born_uv: F64, born_uv_cur: F64, born_stamp_ns: NDArray[np.int64], kf_stamp_ns: int,
                 stamp_ns: int) -> F64:
    """Where each newborn would have been at the keyframe had it moved at the image velocity it shows since
    it was found (``MotionContext.born_uv``): still ones stay where they were found."""
    since_found = np.maximum(stamp_ns - born_stamp_ns, 1).astype(np.float64)
    stretch = np.maximum(stamp_ns - kf_stamp_ns, 1) / since_found
    return np.asarray(born_uv_cur + (born_uv - born_uv_cur) * stretch[:, None], dtype=np.float64)


def _replenished(state: TrackState, cfg: VoConfig, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int,
                 still_pts: NDArray[np.float32]) -> TrackState:
    """A still camera's background found again where its tracks died (a mover crossing the view occludes
    them one after the other): new corners in the grid cells that held a still track (``still_pts`` now,
    ``Tracks.still_cells`` at the frames before) and hold no track now, tracked from here on as newborns.
    Without a keyframe row they take no part in E, H or a map; they show where the still background is in
    the "no camera motion" hypothesis (``motion.static``), so that the still features keep their spread
    instead of the mover taking the view. Cells whose tracks moved and left the view (a camera starting to
    move) are not refilled. The next keyframe drops them (it tops its grid up itself)."""
    tracks = state.tracks
    existing = np.vstack([tracks.pts, tracks.born_pts]).astype(np.float32)
    h, w = gray.shape[:2]
    still_cells = _cells(still_pts, cfg, w, h)
    if tracks.still_cells.size:
        still_cells |= tracks.still_cells
    refill = still_cells & ~_cells(existing, cfg, w, h)
    new = fe.detect_corners(gray, existing, cfg) if refill.any() else np.zeros((0, 2), np.float32)
    new = new[refill[fe.cell_index(new, w, h, cfg.grid_rows, cfg.grid_cols)]]
    born_uv = np.vstack([tracks.born_uv, camera.to_pixels(camera.normalize(new))])
    born_pts = np.vstack([tracks.born_pts, new]).astype(np.float32)
    born_stamp_ns = np.concatenate([tracks.born_stamp_ns, np.full(new.shape[0], stamp_ns, np.int64)])
    return dataclasses.replace(state, tracks=dataclasses.replace(tracks, born_uv=born_uv, born_pts=born_pts,
                                                                 born_stamp_ns=born_stamp_ns, still_cells=still_cells))


def _cells(pts: NDArray[np.float32], cfg: VoConfig, width: int, height: int) -> NDArray[np.bool_]:
    """The bucketing grid's cells holding any of ``pts``."""
    held = np.zeros(cfg.grid_rows * cfg.grid_cols, bool)
    held[fe.cell_index(pts, width, height, cfg.grid_rows, cfg.grid_cols)] = True
    return held


def _noise_since(state: TrackState, kf: Keyframe, cfg: VoConfig) -> float:
    """The image noise the tracks gathered since ``kf`` for the pose's covariance (``MotionContext.noise_sq``);
    ORB matches the keyframe directly: 1 (``pixel_noise_px``)."""
    if cfg.frontend is not Frontend.KLT or state.tracked_noise.kf_index != kf.index:
        return 1.0
    return state.tracked_noise.noise_sq


def _step_covariance(state: TrackState, cfg: VoConfig, kf: Keyframe, motion: mo.Motion, step_w: F64, ratio: float
                     ) -> tuple[TrackState, F64]:
    """Covariance of the motion since the previous frame (odometry frame) from both frames' poses relative
    to the keyframe (``covariance.step``); against a new keyframe (the previous frame) only this frame's
    counts. The image noise is the frame's tracks' (``ratio`` of ``pixel_noise_px``,
    ``covariance.twist_noise_ratio``): for the rotation always, for the position when this pose is E's
    against the previous frame's keyframe (``covariance.track_step``). The map's scale error is the same for
    both frames: it moves the step by its own fraction (``covariance.shared_scale_part``), not by the sum of
    both offsets from the keyframe."""
    c_kf = -motion.R_cur_kf.T @ motion.t_cur_kf
    own = motion.cov_rel - covm.shared_scale_part(c_kf, motion.shared_scale_var)
    cov = rotate_covariance(own, kf.T_w_kf[:3, :3])
    prev = state.last_relative
    same = prev if prev is not None and prev.kf_stamp_ns == kf.stamp_ns else None
    cov_step = covm.track_step(cov, None if same is None else same.cov, ratio,
                               motion.from_essential and same is not None)
    # The step's length carries the map's scale error (``MapScaleCovariance.step_rel_std``) and the keyframe
    # map's own (shared by both frames).
    rel2 = state.map_scale.step_rel_std(state.scale) ** 2 + motion.shared_scale_var
    return (dataclasses.replace(state, last_relative=LastRelative(kf.stamp_ns, cov)),
            cov_step + np.pad(np.outer(step_w, step_w) * rel2, (0, 3)))


def _unmeasured_step(state: TrackState, cfg: VoConfig, step_cov: F64, tracking: TrackingState, jumped: bool) -> F64:
    """The step covariance, or what nothing measured of it."""
    had = state.measured  # still the previous frame's: this one is booked by ``publish``
    if not had.pose or (state.scale.metric_source and (not state.scale.established or jumped)):
        # Nothing measured the step: the previous frame had no pose (a loss, a restart), or metres were asked
        # for while the position is held (scale unknown) or at the frame where the map first becomes metric
        # (the position jumps to metres).
        return covm.block(cfg.lost_position_variance, cfg.lost_rotation_variance)
    if not (had.position and tracking is not TrackingState.INITIALIZING):
        # A position held (initialising: the camera moves on while its keyframe's position is published) on
        # either side: the step's translation spans the frames it was held for.
        return covm.translation_unknown(step_cov, cfg.lost_position_variance)
    return step_cov


def downscale(gray: NDArray[np.uint8], camera: CameraModel, max_width: int) -> tuple[NDArray[np.uint8], CameraModel]:
    """The image and camera the pipeline works on: wider images shrunk to ``max_width`` (0: never)."""
    if max_width <= 0 or gray.shape[1] <= max_width:
        return gray, camera
    factor = max_width / gray.shape[1]
    small = cast(NDArray[np.uint8], cv2.resize(gray, (max_width, round(gray.shape[0] * factor)),
                                               interpolation=cv2.INTER_AREA))
    return small, camera.scaled(factor)
