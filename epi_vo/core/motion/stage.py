"""The motion stage's entry: which hypothesis explains the frame, and the pose it gives."""

from __future__ import annotations

import time

import numpy as np

from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import Model
from epi_vo.core.motion.essential import from_essential
from epi_vo.core.motion.homography import e_moves_off_plane, from_homography
from epi_vo.core.motion.record import MotionContext, MotionEstimate, MotionMemory, has_map
from epi_vo.core.motion.static import static_camera
from epi_vo.core.selection import ModelSelection

# E won RH within this of rh_threshold: a plane nearly won, and before a map E is checked against it (far
# points at low parallax fit an H whose decompositions mean nothing: RH well below the threshold then)
E_PLANE_RH_MARGIN = 0.05


def estimate(cfg: VoConfig, ctx: MotionContext, sel: ModelSelection, memory: MotionMemory) -> MotionEstimate:
    """The pose of this frame relative to its keyframe from the winning model (``MotionEstimate.motion``;
    None: no pose), which model gave it, what was measured and decided, and the memory for the next frame."""
    t0 = time.perf_counter()
    est = _estimate(cfg, ctx, sel, MotionEstimate(memory))
    return est.but(ms=(time.perf_counter() - t0) * 1e3)


def _estimate(cfg: VoConfig, ctx: MotionContext, sel: ModelSelection, est: MotionEstimate) -> MotionEstimate:
    est = static_camera(cfg, ctx, sel, est)
    if est.motion is not None:
        return est
    if sel.model is Model.HOMOGRAPHY:
        assert sel.H is not None and sel.inliers_h is not None
        return from_homography(cfg, ctx, sel, est.but(model=Model.HOMOGRAPHY))
    if sel.model is Model.ESSENTIAL:
        assert sel.E is not None and sel.inliers_e is not None
        if (not has_map(cfg, ctx.kf) and sel.inliers_h is not None
                and sel.rh >= cfg.rh_threshold - E_PLANE_RH_MARGIN
                and np.count_nonzero(sel.inliers_h) >= 0.5 * np.count_nonzero(sel.inliers_e)):
            est, moves = e_moves_off_plane(cfg, ctx, sel, est)
            if moves:
                return from_homography(cfg, ctx, sel, est.but(model=Model.HOMOGRAPHY), e_moves=True)
        return from_essential(cfg, ctx, sel.E, sel.inliers_e, est.but(model=Model.ESSENTIAL), sel.rh)
    return est.noted(note(Decision.NO_MODEL))
