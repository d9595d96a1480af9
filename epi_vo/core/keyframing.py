"""Keyframes in the step: a new reference (the first frame, a restart), a tracking frame made the keyframe
with its map points in metres when a scale source measures them, the windowed adjustment at a keyframe,
and the tracks judged to move on their own.

Each function takes the tracking state and returns the state after it (``epi_vo.core.state``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import features as fe
from epi_vo.core import motion as mo
from epi_vo.core import scale as sc
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.frame import TrackingState
from epi_vo.core.keyframe import Keyframe, make_keyframe
from epi_vo.core.map_scale import first_map_rel_var, length_rel_var
from epi_vo.core.mapping import keyframe_map
from epi_vo.core.state import Tracks, TrackState
from epi_vo.core.transforms import invert_T, make_T
from epi_vo.core.window import correct
from epi_vo.core.workers import WindowSolver

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]

# Tracks moving together before they count as an object moving on its own: eight correspondences determine
# a relative motion (the 8-point algorithm), the least that shows a rigid object's own motion; fewer may be
# static tracks caught at a mover's edge.
MIN_MOVERS = 8


@dataclass(frozen=True)
class KeyframeOutcome:
    """What making (or not making) this tracking frame a keyframe measured and decided."""

    is_keyframe: bool = False
    triangulated: bool = False  # a fresh triangulation of the keyframe pair (the statistics below are its)
    n_triangulated: int = 0
    positive_depth_ratio: float = float("nan")
    median_reproj_err_px: float = float("nan")
    points_w: F64 | None = None  # the keyframe's point cloud in the odometry frame (None: not sent)
    correction: F64 | None = None  # the windowed adjustment's correction of the poses (None: none)
    jumped: bool = False  # the position jumped to metres (metric scale established at this keyframe)
    timings: tuple[tuple[str, float], ...] = ()
    notes: tuple[Note, ...] = ()


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def set_keyframe(state: TrackState, cfg: VoConfig, orb: cv2.ORB | None, gray: NDArray[np.uint8],
                 camera: CameraModel, stamp_ns: int, cov_w: F64, pts_tracked: F32, X_tracked: F64,
                 orb_cur: fe.OrbFeatures | None, ids_tracked: I64 | None = None) -> TrackState:
    """The current frame as the reference: the tracked features kept (with depth and track id), the grid
    topped up. Without ``ids_tracked`` (a new map) the window of adjusted keyframes is dropped."""
    window = state.window.cleared() if ids_tracked is None else state.window
    kf = make_keyframe(state.index, stamp_ns, state.T_w_c, cov_w, gray, camera, pts_tracked, X_tracked, cfg, orb,
                       orb_cur, ids_tracked, state.next_id)
    next_id, patches = state.next_id, state.patches
    if kf.ids is not None and kf.ids.size:
        next_id = max(next_id, int(kf.ids.max()) + 1)
        if patches is not None:
            patches = patches.anchored(gray, kf.pts, kf.ids)
    # Movers stay flagged while they are tracked; tracks that ended are forgotten. Fewer than MIN_MOVERS
    # left is no group any more (the object left the view): those are forgotten too.
    movers = np.intersect1d(state.mover_ids, kf.ids) if kf.ids is not None else np.zeros(0, np.int64)
    if movers.size < MIN_MOVERS:
        movers = np.zeros(0, np.int64)
    return dataclasses.replace(state, window=window, kf=kf, next_id=next_id, patches=patches, mover_ids=movers,
                               scale=state.scale.viewing(gray, camera, stamp_ns),
                               tracks=Tracks(np.arange(kf.n_features, dtype=np.int64), kf.pts, gray),
                               T_cur_kf_prev=np.eye(4), n_keyframes=state.n_keyframes + 1)


def handover_cov(state: TrackState, stamp_ns: int) -> F64:
    """Covariance of the held pose a new map starts from (a restart, a reset, a jump back in time): the last
    good pose's and the motion possible since (``handover``), not the 'unknown' variance: that one is added
    to what is published while the new map has no scale (``publish``), so it is never summed over
    restarts. Before any map: the current covariance."""
    good, metric = state.handover.good, state.scale.established
    scale_cov = state.map_scale.systematic(state.scale, good.T_w_c[:3, 3]) if good and metric else None
    cov = state.handover.covariance(stamp_ns, metric, scale_cov)
    return state.cov_w_c.copy() if cov is None else covm.floored(cov)


def new_reference(state: TrackState, cfg: VoConfig, orb: cv2.ORB | None, gray: NDArray[np.uint8],
                  camera: CameraModel, stamp_ns: int, orb_cur: fe.OrbFeatures | None = None) -> TrackState:
    """This frame becomes a keyframe at the held pose, without a map (the first frame, a restart)."""
    cov = handover_cov(state, stamp_ns)
    state = set_keyframe(state, cfg, orb, gray, camera, stamp_ns, cov, np.zeros((0, 2), np.float32),
                         np.zeros((0, 3)), orb_cur)
    return dataclasses.replace(state, cov_w_c=cov, map_scale=state.map_scale.with_origin(state.T_w_c[:3, 3], cov),
                               last_pos_w=state.T_w_c[:3, 3].copy())


def movers_among(state: TrackState, kf: Keyframe, rows: I64) -> NDArray[np.bool_]:
    """Which of the tracked rows belong to tracks judged to move on their own."""
    if kf.ids is None or state.mover_ids.size == 0:
        return np.zeros(rows.shape[0], bool)
    return np.isin(kf.ids[rows], state.mover_ids)


@dataclass(frozen=True)
class Movers:
    """The tracked rows that move on their own this frame, how many, where, and what is said of them."""

    moving: NDArray[np.bool_]
    n_moving: int
    region: tuple[int, int, int, int] | None
    notes: tuple[Note, ...] = ()


def book_movers(state: TrackState, kf: Keyframe, rows: I64, uv_cur: F64, excluded: NDArray[np.bool_],
                motion: mo.Motion | None, n_moving: int, region: tuple[int, int, int, int] | None
                ) -> tuple[TrackState, Movers]:
    """Remember the tracks that moved on their own this frame (a coherent group of at least MIN_MOVERS: E's
    consensus against the map's pose), and say how many movers are in view and where (``n_moving`` and
    ``region``: what the motion stage already saw move, a static camera's)."""
    moving = excluded.copy()
    if motion is not None and motion.moving is not None and np.count_nonzero(motion.moving) >= MIN_MOVERS:
        moving |= motion.moving
        if kf.ids is not None:
            state = dataclasses.replace(state, mover_ids=np.union1d(state.mover_ids, kf.ids[rows[motion.moving]]))
    n = int(np.count_nonzero(moving))
    if n == 0:
        return state, Movers(moving, n_moving, region)
    notes: tuple[Note, ...] = ()
    if n_moving == 0:
        lo, hi = uv_cur[moving].min(axis=0), uv_cur[moving].max(axis=0)
        region = (int(lo[0]), int(lo[1]), int(np.ceil(hi[0])), int(np.ceil(hi[1])))
        notes = (note(Decision.MOVERS_IN_VIEW, n=n, region=region),)
    # A still camera's count (``n_moving``) holds the tracks it booked this frame: counted once; its region
    # (where what it saw move this frame is) is taken over the movers booked before too.
    total = n_moving + int(np.count_nonzero(excluded)) if n_moving else n
    if n_moving and np.any(excluded):
        region = mo.moving_region(uv_cur[moving])
    return state, Movers(moving, total, region, notes)


def maybe_keyframe(state: TrackState, cfg: VoConfig, orb: cv2.ORB | None, solver: WindowSolver, motion: mo.Motion,
                   kf: Keyframe, rows: I64, pts_cur: F32, xn_cur: F64, gray: NDArray[np.uint8], camera: CameraModel,
                   stamp_ns: int, orb_cur: fe.OrbFeatures | None, n_inliers: int, median_parallax_deg: float,
                   n_triangulated: int) -> tuple[TrackState, KeyframeOutcome]:
    """The mapping stage decides; a new keyframe takes this frame's pose, covariance and map points, in
    metres when the scale source measured the step. ``n_triangulated``: what the motion stage triangulated
    (a first map)."""
    mapped = keyframe_map(cfg, motion, kf, rows, xn_cur, stamp_ns, n_inliers, median_parallax_deg)
    out = KeyframeOutcome(False, mapped.triangulated, mapped.n_triangulated, mapped.positive_depth_ratio,
                          mapped.median_reproj_err_px, notes=mapped.notes)
    if mapped.X_cur is None:
        return state, out
    X_cur = mapped.X_cur
    if mapped.triangulated:
        n_triangulated = mapped.n_triangulated
    tracking = motion.state is TrackingState.TRACKING
    # the scale source's anchor of this keyframe step and its correction
    step_scale: tuple[sc.WindowAnchor | None, float] = (None, 1.0)
    t = motion.t_cur_kf
    jumped = False
    if tracking:
        state, X_cur, t, step_scale, jumped = metric_step(state, motion, kf, X_cur, stamp_ns, gray, camera)
        state = dataclasses.replace(state, scale=state.scale.on_keyframe(float(np.linalg.norm(t)),
                                                                         (stamp_ns - kf.stamp_ns) * 1e-9))
    points_w = None
    if tracking and n_triangulated > 0:
        # The keyframe's point cloud: every map point it holds, in the odometry frame.
        points_w = _transform(state.T_w_c, X_cur[np.isfinite(X_cur[:, 0])])
    cov = state.cov_w_c.copy()
    if tracking:
        d = state.T_w_c[:3, 3] - kf.T_w_kf[:3, 3]
        step_cov = motion.cov_rel if motion.cov_pose is None else motion.cov_pose
        first = 0.0
        if motion.new_map is not None:
            rot_cov = state.cov_w_c[3:, 3:] + state.calib.cov()[3:, 3:]
            first = first_map_rel_var(d, rot_cov, median_parallax_deg)
        map_scale, scale_cov = state.map_scale.keyframe_cov(
            state.scale, motion.new_map is not None, d, length_rel_var(-motion.R_cur_kf.T @ motion.t_cur_kf, step_cov),
            first)
        cov[:3, :3] += scale_cov
        # This frame is the keyframe: it publishes what the keyframe holds, the step's scale term included.
        state = dataclasses.replace(state, map_scale=map_scale, cov_w_c=cov.copy())
    ids_tracked = kf.ids[rows] if kf.ids is not None else None
    state = set_keyframe(state, cfg, orb, gray, camera, stamp_ns, cov, pts_cur, X_cur, orb_cur, ids_tracked)
    out = dataclasses.replace(out, is_keyframe=True, points_w=points_w, jumped=jumped)
    if not tracking:
        return dataclasses.replace(state, window=state.window.cleared()), out
    state, correction, timings, notes = adjust_window(state, cfg, solver, *step_scale)
    return state, dataclasses.replace(out, correction=correction, timings=timings, notes=out.notes + notes)


def metric_step(state: TrackState, motion: mo.Motion, kf: Keyframe, X_cur: F64, stamp_ns: int,
                gray: NDArray[np.uint8] | None = None, camera: CameraModel | None = None
                ) -> tuple[TrackState, F64, F64, tuple[sc.WindowAnchor | None, float], bool]:
    """The scale source's correction of this keyframe step: the step from the last keyframe and the new
    keyframe's map points are scaled by it (and, when it establishes metric scale, the whole path of the
    current map about the point where the map was initialised). Returns the state, the map points and the
    step translation ``t_cur_kf`` as corrected, the source's (anchor, correction) of the step, and whether
    the position jumped to metres."""
    t = motion.t_cur_kf
    if motion.new_map is not None:
        state = dataclasses.replace(state, map_scale=state.map_scale.with_origin(kf.T_w_kf[:3, 3], kf.cov_w_kf),
                                    scale=state.scale.on_new_map())
    was_metric = state.scale.established
    step = sc.KeyframeStep(X_cur, float(np.linalg.norm(t)), kf.stamp_ns, stamp_ns, motion.R_cur_kf, t, gray, camera)
    scale, factor = state.scale.correction(step, state.wheel)
    state = dataclasses.replace(state, scale=scale)
    step_scale = (scale.anchor(step, state.wheel), factor)
    if factor == 1.0:
        return state, X_cur, t, step_scale, False
    t = t * factor
    if was_metric:
        return (dataclasses.replace(state, T_w_c=kf.T_w_kf @ invert_T(make_T(motion.R_cur_kf, t))), X_cur * factor, t,
                step_scale, False)
    # Metric from now on: the whole map so far was in VO units.
    T_w_c = state.T_w_c.copy()
    origin = state.map_scale.origin_w
    d = factor * (T_w_c[:3, 3] - origin)
    T_w_c[:3, 3] = origin + d
    state = dataclasses.replace(state, window=state.window.cleared(), T_w_c=T_w_c,
                                cov_w_c=state.map_scale.metric_covariance(state.scale, state.cov_w_c, factor, d),
                                calib=state.calib.rescaled(factor), rotation_bias=state.rotation_bias.rescaled(factor))
    return state, X_cur * factor, t, step_scale, True


def adjust_window(state: TrackState, cfg: VoConfig, solver: WindowSolver, anchor: sc.WindowAnchor | None,
                  factor: float) -> tuple[TrackState, F64 | None, tuple[tuple[str, float], ...], tuple[Note, ...]]:
    """Windowed bundle adjustment (``epi_vo.core.window``): the last keyframe's adjustment comes back and this
    keyframe (and the current pose) moves with the keyframe it adjusted; this one joins the window with its
    scale ``anchor`` and the scale stage's correction ``factor`` of its step, and the next adjustment starts
    when due. Returns the state, the correction applied to the poses (None: none), the times and notes."""
    kf = state.kf
    assert kf is not None
    t0 = time.perf_counter()
    timings: list[tuple[str, float]] = []
    window, update = state.window.collected(solver, cfg.ba_wait)  # ba_wait: wait for a result not back yet
    correction = None
    if update is not None:
        timings += [("window_wait", _ms(t0)), ("window_solve", update.ms)]  # solve: in the worker
        # The window's uncertainty (when it has one; covering the chain's) replaces the keyframe's.
        T, X, cov = correct(update, kf.T_w_kf, kf.ids, kf.X_kf, kf.cov_w_kf, factor)
        correction = update.correction  # the poses before move with it (the twist's reference)
        kf = dataclasses.replace(kf, T_w_kf=T, X_kf=X, cov_w_kf=cov)
        state = dataclasses.replace(state, kf=kf, T_w_c=T.copy(),
                                    cov_w_c=cov.copy() if update.cov_w_kf is not None else state.cov_w_c)
    window = window.added(kf.T_w_kf, kf.ids, kf.xn, kf.X_kf, anchor, kf.cov_w_kf, factor)
    window, submitted = window.submitted(solver, float(kf.camera.K[0, 0]), state.mover_ids) if window.due() \
        else (window, False)
    if update is not None or submitted:
        timings.append(("window", _ms(t0)))
    why = solver.take_failure()
    notes = (note(Decision.WINDOW_WORKER_FAILED, text=why),) if why else ()
    return dataclasses.replace(state, window=window), correction, tuple(timings), notes


def _transform(T_a_b: F64, X_b: F64) -> F64:
    return X_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
