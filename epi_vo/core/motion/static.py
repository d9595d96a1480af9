"""The "no camera motion" hypothesis: a still camera must not build a map from something moving before it."""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import Model, TrackingState
from epi_vo.core.motion.record import Motion, MotionContext, MotionEstimate, has_map
from epi_vo.core.selection import ModelSelection

F64 = NDArray[np.float64]

# A static camera stays static down to this share of static_min_fraction: a mover growing in front of it
# covers more of the background (and occludes its tracks) without the camera having moved.
STATIC_KEEP = 0.6
GRID_CELLS = 4  # the spread of features is judged on a GRID_CELLS x GRID_CELLS grid of the image


def static_camera(cfg: VoConfig, ctx: MotionContext, sel: ModelSelection, est: MotionEstimate) -> MotionEstimate:
    """The "no camera motion" hypothesis, before a map exists: when most tracked features did not move and
    those cover the image, the camera is static and whatever moved is another object. The pose holds (no
    map is built from the mover's motion); the frame says what moved and where. ``est.motion`` is the held
    pose when the camera is static, None otherwise (the other hypotheses decide).

    With a map, the pose comes from the map points, whose majority (the static background) decides it; E
    alone cannot tell: with no rotation every still point fits any translation's epipolar geometry, so
    RANSAC happily explains a mover's motion.
    """
    was_static = est.memory.static
    est = est.but(memory=dataclasses.replace(est.memory, static=False))
    still = sel.inliers_static
    n = ctx.uv_cur.shape[0]
    if still is None or n == 0:
        return est
    fraction = float(np.count_nonzero(still)) / n
    # The record's share is of every tracked feature; the decision's of those not booked as movers (a mover
    # booked while the camera stood still must not talk it out of being still).
    share = float(np.count_nonzero(still)) / (n + ctx.n_booked)
    est = est.but(static_score=share)
    # Entering needs the majority; staying needs STATIC_KEEP of it.
    needed = cfg.static_min_fraction * (STATIC_KEEP if was_static else 1.0)
    if has_map(cfg, ctx.kf) or fraction < needed:
        return est
    K = ctx.kf.camera
    # Where the still background is, the tracks born since the keyframe where others died say too: a mover
    # crossing the view occludes the keyframe's tracks one cell after the other, and the background behind
    # it has not gone. Their motion since they were found is taken back to the keyframe at the image
    # velocity it shows (``MotionContext.born_uv``): a camera that started moving is not judged on a shorter
    # interval than its keyframe's tracks are. (They do not vote in the share above.) Those that moved were
    # found on whatever took the background's cells (a mover, or the view of a camera that started moving):
    # they say nothing of where the background is, and the keyframe's tracks already say whether it moved.
    uv_all, still_all = ctx.uv_cur, still
    if ctx.born_uv is not None and ctx.born_uv_cur is not None and ctx.born_uv.shape[0]:
        _, still_born = geo.score_static(ctx.born_uv, ctx.born_uv_cur, cfg.score_sigma_px)
        uv_all = np.vstack([ctx.uv_cur, ctx.born_uv_cur[still_born]])
        still_all = np.concatenate([still, np.ones(int(np.count_nonzero(still_born)), bool)])
    spread = grid_spread(uv_all, still_all, K.width, K.height)
    if spread < cfg.static_min_spread:
        return est
    moved = ~still
    n_moving = int(np.count_nonzero(moved))
    n_still = int(np.count_nonzero(still))
    region = moving_region(ctx.uv_cur[moved]) if n_moving else None
    rot_cov = covm.rotation_var(cfg.pixel_noise_px, K.K[0, 0], max(n_still, 1))
    motion = Motion(TrackingState.STATIC, np.eye(3), np.zeros(3), covm.block(1e-6, rot_cov), still,
                    moving=moved if n_moving and background_stood_still(cfg, ctx, still) else None)
    est = est.but(memory=dataclasses.replace(est.memory, static=True),
                  n_moving=n_moving, n_inliers=n_still, median_parallax_deg=0.0, moving_region=region,
                  model=Model.STATIC)
    return est.noted(note(Decision.CAMERA_STATIC, fraction=share, spread=spread, n_moving=n_moving + ctx.n_booked,
                          region=region), motion)


def moving_region(uv: F64) -> tuple[int, int, int, int]:
    """The box (x0, y0, x1, y1 px) of the 5-95 percentiles of the moved features ``uv`` (N >= 1, 2): where
    another object is, without a stray track stretching it over the image."""
    lo, hi = np.percentile(uv, 5, axis=0), np.percentile(uv, 95, axis=0)
    return int(lo[0]), int(lo[1]), int(np.ceil(hi[0])), int(np.ceil(hi[1]))


def background_stood_still(cfg: VoConfig, ctx: MotionContext, still: NDArray[np.bool_]) -> bool:
    """The tracks that did not move stayed where they were, within the least noise tracks have
    (``twist_noise_floor_px``, their median displacement since the keyframe): a still camera's background.
    What moved meanwhile moved on its own, and is booked as a mover (``Motion.moving``): it stays out of the
    "no camera motion" share, E, H and a map while it is tracked. An object crossing a still camera may hold
    most of the tracks and the cells (after a keyframe made while it was in view, or an exposure step that
    ended the background's tracks); E explains it, and the background with it as points at infinity (with no
    rotation a track that did not move fits any translation). A camera that starts to move is judged still
    for a frame or two while its slowest tracks creep (0.5-1.7 px on the distribution's starts, 0.05-0.2 on
    its still cameras): it books nothing."""
    d = np.linalg.norm(ctx.uv_cur[still] - ctx.kf.uv[ctx.rows][still], axis=1)
    return d.size > 0 and float(np.median(d)) <= cfg.twist_noise_floor_px


def grid_spread(uv: F64, mask: NDArray[np.bool_], width: int, height: int, cells: int = GRID_CELLS) -> float:
    """Of the cells of a ``cells`` x ``cells`` grid holding any feature, the fraction holding a masked one."""
    col = np.clip((uv[:, 0] * cells / max(width, 1)).astype(np.int64), 0, cells - 1)
    row = np.clip((uv[:, 1] * cells / max(height, 1)).astype(np.int64), 0, cells - 1)
    cell = row * cells + col
    occupied = np.unique(cell)
    if occupied.size == 0:
        return 0.0
    return float(np.unique(cell[mask]).size) / occupied.size
