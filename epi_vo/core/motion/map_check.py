"""E checked against the map: a mover (or, on a plane, E's other solution) may take E's consensus; the map's
points, triangulated from the static scene before, give a pose of their own that overrules it."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.motion.record import MotionContext
from epi_vo.core.transforms import rotation_angle_deg

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]

PNP_MIN_POINTS = 6  # a pose has six unknowns: fewer map points leave the map's own fit unconstrained
E_MAP_MAX_DIRECTION_DIFF_DEG = 20.0  # E's direction of travel this far from the map's: a mover took E
# The map's own fit is made to hold its points, so it holds a few more than E's pose whenever the tracks are
# degraded (motion blur). E stands when it holds this share of the points the fit holds, with a median
# reprojection error within this factor of the fit's; a mover that took E's consensus leaves E holding
# clearly fewer, or explaining them clearly worse.
E_MAP_HELD_SHARE = 0.7
E_MAP_RESIDUAL_RATIO = 2.0


def map_disagrees(cfg: VoConfig, ctx: MotionContext, X: F64, R_e: F64, t_e: F64, plane: bool = False
                  ) -> tuple[Mask | None, Note | None]:
    """(None, None) when the map's points agree with E's rotation and direction of travel; else the map
    points that agree with the pose they give on their own (started from the previous frame's pose), and
    the decision.

    E alone takes the largest consensus: a mover covering a third of the view can win it. The map's
    points were triangulated from the static scene before; their pose is the check.
    """
    depth = np.isfinite(X[:, 0])
    if np.count_nonzero(depth) < max(cfg.min_scale_points, PNP_MIN_POINTS):
        return None, None
    K = ctx.kf.camera.K
    # Cheap first: one Gauss-Newton step towards the map's pose turns E by less than half the angle (E
    # may put nearly all map points within a pixel and still be off: near a plane it slides along its ridge).
    step = geo.map_step(R_e, t_e, X[depth], ctx.xn_cur[depth])
    if step is not None and math.degrees(float(np.linalg.norm(step[3:]))) <= 0.5 * cfg.e_map_max_rotation_diff_deg:
        return None, None
    err_e = geo.reprojection_errors(R_e, t_e, X[depth], ctx.uv_cur[depth], K)
    prev = ctx.T_cur_kf_prev
    refined = geo.refine_pose_pnp(X[depth], ctx.uv_cur[depth], K, prev[:3, :3], prev[:3, 3],
                                  cfg.max_reprojection_error_px)
    if refined is None or np.count_nonzero(refined[2]) < cfg.min_scale_points:
        return None, None
    held_by_e = np.count_nonzero(err_e <= cfg.max_reprojection_error_px)
    held_by_map = np.count_nonzero(refined[2])
    err_map = geo.reprojection_errors(refined[0], refined[1], X[depth], ctx.uv_cur[depth], K)
    ridge = plane and np.median(err_e) > E_MAP_RESIDUAL_RATIO * np.median(err_map)  # E explains them worse
    if held_by_map <= held_by_e and not ridge:
        # E's pose puts at least as many of the map's points where they are seen as the map's own fit
        # does: that fit, not E, went wrong (LM from the previous pose into a wrong minimum).
        return None, None
    if held_by_e >= E_MAP_HELD_SHARE * held_by_map \
            and np.median(err_e) <= E_MAP_RESIDUAL_RATIO * np.median(err_map):
        return None, None  # the fit holds only a few more, and explains them no better: E stands
    angle = rotation_angle_deg(refined[0] @ R_e.T)
    c_map, c_e = -refined[0].T @ refined[1], -R_e.T @ t_e
    norms = float(np.linalg.norm(c_map) * np.linalg.norm(c_e))
    direction = math.degrees(math.acos(np.clip(float(c_map @ c_e) / norms, -1.0, 1.0))) if norms > 0 else 0.0
    if angle <= cfg.e_map_max_rotation_diff_deg and direction <= E_MAP_MAX_DIRECTION_DIFF_DEG:
        return None, None
    agree = np.zeros(depth.shape[0], bool)
    agree[np.flatnonzero(depth)[refined[2]]] = True
    return agree, note(Decision.E_DISAGREES_WITH_MAP, angle=angle, direction=direction, plane=plane)
