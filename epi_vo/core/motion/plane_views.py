"""A plane whose homography has two physically valid decompositions, told apart by a later view."""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.motion.record import MotionContext, MotionEstimate, PlaneViews
from epi_vo.core.transforms import rotation_angle_deg

F64 = NDArray[np.float64]

# A decomposition's plane is the first view's when their normals' drift is within what the normals' own
# uncertainty explains, and not once it is beyond it: the squared Mahalanobis distance of the drift
# (chi-square, 2 degrees of freedom) at 0.1 %, so that over the PLANE_MAX_WAIT views the wrong solution's
# drift of noise alone passes for a move about one time in a hundred.
PLANE_DRIFT_CHI2 = 13.82
# A decomposition's plane this close (deg) to one seen from the first view is the same plane, and one that
# moved at least this far and PLANE_NORMAL_MOVED_RATIO times as far as the closest is not. The normals'
# uncertainty comes from H's residuals, which also carry what of the scene is not the plane (a wall and the
# floor it stands on): there it can exceed a degree while the other solution's plane plainly turned.
PLANE_NORMAL_AGREE_DEG = 1.5
PLANE_NORMAL_MOVED_RATIO = 3.0
# Frames an initialisation on a plane with two valid decompositions waits for a view that tells them apart;
# then the one more points pass the gates is taken (as without the wait).
PLANE_MAX_WAIT = 10
# Variance (rad^2) of a normal whose uncertainty cannot be propagated: a radian, i.e. no information.
UNKNOWN_NORMAL_VAR = 1.0


class PlaneVerdict(enum.Enum):
    UNAMBIGUOUS = "unambiguous"  # fewer than two decompositions are valid
    WAIT = "wait"  # two are: waiting for a view that tells them apart, pose held
    PICKED = "picked"  # this view told them apart
    FALLBACK = "fallback"  # none did in PLANE_MAX_WAIT frames: the one most points pass the gates


def plane_by_views(cfg: VoConfig, ctx: MotionContext, H: F64, in_h: NDArray[np.bool_], est: MotionEstimate
                   ) -> tuple[MotionEstimate, PlaneVerdict, tuple[F64, F64, geo.Triangulation] | None, float]:
    """A plane whose homography has two physically valid decompositions (both put the points in front of
    both cameras: a floor seen from a camera moving along it), with no point off the plane to tell them
    apart, is told apart by a later view against the same keyframe. The true plane keeps its normal in the
    keyframe's frame; the other solution's normal follows the direction of travel (0.4 against 2.9 deg one
    frame later on a floor). The count of points through the triangulation gates does not decide: the wrong
    solution sees its points under larger angles.

    Returns the estimate with the decision noted and the memory of the views, the verdict, the pose (R, t,
    triangulation) when ``PICKED``, and the largest rotation angle (deg) among the valid solutions."""
    kf = ctx.kf
    xn_kf, xn_cur = kf.xn[ctx.rows], ctx.xn_cur
    sols = geo.homography_solutions(H, kf.camera.K, xn_kf, xn_cur, in_h,
                                    cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg)
    valid = [s for s in sols if s.tri.positive_depth_ratio >= cfg.min_positive_depth_ratio
             and s.n_good >= cfg.min_triangulated]

    def remembering(views: PlaneViews | None) -> MotionEstimate:
        return est.but(memory=dataclasses.replace(est.memory, plane_views=views))

    if len(valid) < 2:
        return remembering(None), PlaneVerdict.UNAMBIGUOUS, None, 0.0
    spread = max(rotation_angle_deg(s.R) for s in valid)
    covs = _normal_covariances(kf.camera.K, H, xn_kf[in_h], xn_cur[in_h], valid)
    pending = est.memory.plane_views
    if pending is None or pending.kf_stamp_ns != kf.stamp_ns:
        est = remembering(PlaneViews(kf.stamp_ns, tuple(s.normal for s in valid), covs, 1))
        return est.noted(note(Decision.PLANE_WAIT_FIRST, n=len(valid), max_wait=PLANE_MAX_WAIT)), PlaneVerdict.WAIT, \
            None, spread
    normals, waited = pending.normals, pending.waited
    # Each solution against the first view's plane it is nearest to, in the normals' own uncertainty.
    drifts = [[geo.normal_drift_sq(s.normal, c, n, nc) for n, nc in zip(normals, pending.covs, strict=True)]
              for s, c in zip(valid, covs, strict=True)]
    near = [min(range(len(d)), key=d.__getitem__) for d in drifts]
    chi = [geo.normal_drift_sq(s.normal, c, normals[j], pending.covs[j])
           for s, c, j in zip(valid, covs, near, strict=True)]
    deg = [math.degrees(math.acos(min(1.0, abs(float(s.normal @ normals[j])))))
           for s, j in zip(valid, near, strict=True)]
    order = np.argsort(chi)
    best, runner = int(order[0]), int(order[1])
    by_noise = chi[best] <= PLANE_DRIFT_CHI2 < chi[runner]
    by_angle = deg[best] < PLANE_NORMAL_AGREE_DEG <= deg[runner] and deg[runner] >= PLANE_NORMAL_MOVED_RATIO * deg[best]
    if by_noise or by_angle:
        s = valid[best]
        return est.noted(note(Decision.PLANE_KEPT_NORMAL, views=waited + 1, best=deg[best], runner=deg[runner],
                              best_sigma=math.sqrt(chi[best]), runner_sigma=math.sqrt(chi[runner]))), \
            PlaneVerdict.PICKED, (s.R, s.t, s.tri.expanded(np.flatnonzero(in_h), ctx.xn_cur.shape[0])), spread
    if waited >= PLANE_MAX_WAIT:
        return est.noted(note(Decision.PLANE_WAIT_GAVE_UP, max_wait=PLANE_MAX_WAIT)), PlaneVerdict.FALLBACK, None, \
            spread
    est = remembering(PlaneViews(pending.kf_stamp_ns, normals, pending.covs, waited + 1))
    return est.noted(note(Decision.PLANE_WAIT, n=len(valid), best=deg[best], runner=deg[runner],
                          best_sigma=math.sqrt(chi[best]), runner_sigma=math.sqrt(chi[runner]), waited=waited + 1,
                          max_wait=PLANE_MAX_WAIT)), PlaneVerdict.WAIT, None, spread


def _normal_covariances(K: F64, H: F64, xn_kf: F64, xn_cur: F64, valid: list[geo.PlanarSolution]
                        ) -> tuple[F64, ...]:
    """Each valid solution's normal's covariance (3, 3) from H's fit to its inliers ``xn_kf`` -> ``xn_cur``
    at the noise their residuals show; a normal whose uncertainty cannot be had is taken as unknown (any
    drift is within it), so it never decides a pick."""
    H_n = np.asarray(np.linalg.solve(K, H @ K), np.float64)
    fit = geo.homography_covariance(H_n, xn_kf, xn_cur)
    out = []
    for s in valid:
        c = None if fit is None else geo.normal_covariance(H_n, fit[0], s.normal)
        out.append(np.eye(3) * UNKNOWN_NORMAL_VAR if c is None else c)
    return tuple(out)
