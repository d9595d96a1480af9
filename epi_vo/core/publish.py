"""The frame record: what the step publishes for a frame, built from the stages' results at the end.

``Observed`` gathers what the stages measured this frame (each value from the stage that measured it);
``publish`` books the frame in the tracking state, guards the held pose, composes the published pose and
covariance (the held position's 'unknown' variance, the scale source's systematic error, the calibration's
error, the rotation error the keyframe steps share) and renders the notes to the ``reason``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.frame import FrameResult, Matches, Model, TrackingState, frozen
from epi_vo.core.reasons import render
from epi_vo.core.state import Measured, TrackState

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def _no_points() -> F64:
    return np.zeros((0, 3))


@dataclass(frozen=True)
class Observed:
    """What the stages measured this frame, for its record (not measured: NaN, counts 0)."""

    model: Model = Model.NONE
    rh: float = math.nan
    n_tracked: int = 0
    n_inliers: int = 0
    median_parallax_deg: float = math.nan
    n_triangulated: int = 0
    positive_depth_ratio: float = math.nan
    median_reproj_err_px: float = math.nan
    relative_scale: float = math.nan
    static_score: float = math.nan
    focal_ratio: float = math.nan
    track_noise_px: float = math.nan
    n_refined: int | None = None
    n_moving: int = 0
    moving_region: tuple[int, int, int, int] | None = None
    points_w: F64 = field(default_factory=_no_points)
    correction: F64 | None = None
    matches: Matches = field(default_factory=Matches.empty)


def _finite_or_nan(x: float) -> float:
    return math.nan if math.isinf(x) else x  # not measured is NaN, never infinite


def keep_finite(state: TrackState, cfg: VoConfig) -> tuple[TrackState, tuple[Note, ...]]:
    """The held pose and covariance are finite whatever the input did (a guard: every estimate is checked
    before it is taken, so this only fires on a defect; the record says so)."""
    notes: list[Note] = []
    if not np.all(np.isfinite(state.T_w_c)):
        _log.error("non-finite pose held: reset to the origin")
        notes.append(note(Decision.POSE_NOT_FINITE))
        state = dataclasses.replace(state, T_w_c=np.eye(4), kf=None)
    if not np.all(np.isfinite(state.cov_w_c)):
        _log.error("non-finite covariance held: reset to the 'unknown' covariance")
        notes.append(note(Decision.COVARIANCE_NOT_FINITE))
        state = dataclasses.replace(state, cov_w_c=covm.block(cfg.lost_position_variance, cfg.lost_rotation_variance),
                                    kf=None)
    return state, tuple(notes)


def publish(state: TrackState, cfg: VoConfig, stamp_ns: int, tracking: TrackingState, has_pose: bool, is_kf: bool,
            observed: Observed, notes: tuple[Note, ...], timings: dict[str, float], t_start: float, *,
            book: bool = True, unknown: bool = False, skipped: bool = False, problem: str = "",
            step_covariance: F64 | None = None) -> tuple[TrackState, FrameResult]:
    """The frame's record, and the state with the frame booked (its index and, with ``book``, its stamp and
    whether its pose and position were measured). ``unknown``: a new reference keyframe after a restart,
    where the camera is is not known yet."""
    if book:
        # A held position is not measured; the first frame's is the origin by definition.
        state = dataclasses.replace(state, last_stamp_ns=stamp_ns, measured=Measured(
            has_pose, has_pose and not unknown and (tracking is not TrackingState.INITIALIZING or state.index == 0)))
    state, guard = keep_finite(state, cfg)
    notes = notes + guard
    cov = state.cov_w_c.copy()
    if unknown:
        cov[:3, :3] += np.eye(3) * cfg.lost_position_variance
    if not has_pose:
        cov[:3, :3] += np.eye(3) * cfg.lost_position_variance
        cov[3:, 3:] += np.eye(3) * cfg.lost_rotation_variance
    T_out = state.T_w_c
    if has_pose and state.scale.metric_source and not state.scale.established:
        # Metres were asked for and the scale is not known yet: the pose is the map's, in VO units, and the
        # record says so (``scale.units``). What a robot may fuse is the front doors' decision
        # (``epi_vo.runner.outputs``: the position held with the "unknown" variance, nothing in VO units as
        # metres).
        notes = (*notes, note(Decision.METRIC_SCALE_PENDING))
    elif state.scale.established:
        cov[:3, :3] += state.map_scale.systematic(state.scale, T_out[:3, 3])
    kf = state.kf
    if has_pose and tracking is TrackingState.TRACKING and kf is not None and not state.scale.established:
        cov[:3, :3] += state.map_scale.since_keyframe(T_out[:3, 3] - kf.T_w_kf[:3, 3])
    cov += state.calib.cov() + state.rotation_bias.cov()
    cov = covm.floored(cov)
    timings = {**timings, "total": (time.perf_counter() - t_start) * 1e3}
    o = observed
    n_tracked = o.n_tracked
    points = o.points_w
    result = FrameResult(
        index=state.index, stamp_ns=int(stamp_ns), state=tracking, has_pose=has_pose, is_keyframe=is_kf,
        model=o.model, rh=_finite_or_nan(o.rh), n_features=kf.n_features if kf is not None else 0, n_tracked=n_tracked,
        n_inliers=o.n_inliers, inlier_ratio=o.n_inliers / n_tracked if n_tracked else 0.0,
        median_parallax_deg=_finite_or_nan(o.median_parallax_deg), n_triangulated=o.n_triangulated,
        positive_depth_ratio=_finite_or_nan(o.positive_depth_ratio),
        median_reproj_err_px=_finite_or_nan(o.median_reproj_err_px), relative_scale=_finite_or_nan(o.relative_scale),
        n_keyframes=state.n_keyframes, T_w_c=frozen(T_out), covariance=frozen(cov),
        points_w=frozen(points[np.all(np.isfinite(points), axis=1)]), timings_ms=timings, reason=render(notes),
        notes=notes, matches=o.matches, scale=state.scale.status(state.wheel), n_moving=o.n_moving,
        moving_fraction=o.n_moving / n_tracked if n_tracked else 0.0, moving_region=o.moving_region,
        static_score=o.static_score, focal_ratio=_finite_or_nan(o.focal_ratio),
        track_noise_px=_finite_or_nan(o.track_noise_px), n_refined=o.n_refined,
        correction=None if o.correction is None else frozen(o.correction),
        skipped=skipped, problem=problem,
        step_covariance=None if step_covariance is None else frozen(covm.floored(step_covariance)))
    return dataclasses.replace(state, index=state.index + 1), result
