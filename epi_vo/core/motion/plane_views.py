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

# A decomposition's plane this close (deg) to one seen from the first view is the same plane: the true
# plane's normal stays put in the keyframe's frame within the normals' noise (a few tenths of a degree).
PLANE_NORMAL_AGREE_DEG = 1.5
# The first view's normals are the ones every later view's are judged against. A first view whose normals'
# standard deviation exceeds a third of PLANE_NORMAL_AGREE_DEG may put the true plane outside that agreement
# for every later view (at a fraction of a degree of parallax its normals are a few degrees off the plane's);
# it is replaced by the next view when that one fixes them much better, its variance less than the first's
# by this ratio (the baseline still growing by half or more: a normal's variance falls with the square of the
# parallax). Once the next view is not much better, more baseline would not determine the first view's
# normals further (a scene not quite one plane, noise growing with the baseline): it is kept.
PLANE_ANCHOR_VAR_RATIO = 2.0
# Frames an initialisation on a plane with two valid decompositions waits for a view that tells them apart;
# then the one more points pass the gates is taken (as without the wait).
PLANE_MAX_WAIT = 10


class PlaneVerdict(enum.Enum):
    UNAMBIGUOUS = "unambiguous"  # fewer than two decompositions are valid
    WAIT = "wait"  # two are: waiting for a view that tells them apart, pose held
    PICKED = "picked"  # this view told them apart
    FALLBACK = "fallback"  # none did in PLANE_MAX_WAIT frames: the one most points pass the gates


def plane_by_views(cfg: VoConfig, ctx: MotionContext, H: F64, in_h: NDArray[np.bool_], est: MotionEstimate
                   ) -> tuple[MotionEstimate, PlaneVerdict, tuple[F64, F64, geo.Triangulation] | None,
                              tuple[F64, float]]:
    """A plane whose homography has two physically valid decompositions (both put the points in front of
    both cameras: a floor seen from a camera moving along it), with no point off the plane to tell them
    apart, is told apart by a later view against the same keyframe. The true plane keeps its normal in the
    keyframe's frame; the other solution's normal follows the direction of travel (0.4 against 2.9 deg one
    frame later on a floor). The count of points through the triangulation gates does not decide: the wrong
    solution sees its points under larger angles.

    Returns the estimate with the decision noted and the memory of the views, the verdict, the pose (R, t,
    triangulation) when ``PICKED``, and the orientation to hold while waiting with its uncertainty (deg): the
    valid solution nearest the orientation held at the last view (the keyframe's at the first), so that a turn
    while waiting is followed as the true solution's rotation changes smoothly from view to view, and the
    largest turn any solution makes (the truth is among them only if the scene is the plane)."""
    kf = ctx.kf
    sols = geo.homography_solutions(H, kf.camera.K, kf.xn[ctx.rows], ctx.xn_cur, in_h,
                                    cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg)
    # Valid: the decomposition puts the points in front of both cameras. Not how many of them pass the
    # triangulation gates: at low parallax the true solution passes few (its rays meet under small angles)
    # while the wrong one sees them under larger angles and passes them all, so a count gate would
    # leave the wrong solution alone to be taken without a second view.
    valid = [s for s in sols if s.tri.positive_depth_ratio >= cfg.min_positive_depth_ratio]

    def remembering(views: PlaneViews | None) -> MotionEstimate:
        return est.but(memory=dataclasses.replace(est.memory, plane_views=views))

    if len(valid) < 2:
        return remembering(None), PlaneVerdict.UNAMBIGUOUS, None, (np.eye(3), 0.0)
    pending = est.memory.plane_views
    first_view = pending is None or pending.kf_stamp_ns != kf.stamp_ns
    last = np.eye(3) if first_view or pending is None else pending.held
    held = min((s.R for s in valid), key=lambda R: rotation_angle_deg(last.T @ R))
    hold = (held, max(max(rotation_angle_deg(s.R), rotation_angle_deg(held.T @ s.R)) for s in valid))
    sigma_deg = math.nan
    if first_view or pending is None or not pending.anchored:
        H_n = np.asarray(np.linalg.solve(kf.camera.K, H @ kf.camera.K), dtype=np.float64)
        sigma = geo.normal_sigma_deg(H_n, kf.xn[ctx.rows][in_h], ctx.xn_cur[in_h], [s.normal for s in valid])
        sigma_deg = math.nan if sigma is None else sigma
    if first_view or pending is None:
        est = remembering(PlaneViews(kf.stamp_ns, tuple(s.normal for s in valid), 1, held, sigma_deg, False))
        return est.noted(note(Decision.PLANE_WAIT_FIRST, n=len(valid), max_wait=PLANE_MAX_WAIT)), PlaneVerdict.WAIT, \
            None, hold
    if (not pending.anchored and pending.sigma_deg > PLANE_NORMAL_AGREE_DEG / 3.0
            and pending.sigma_deg**2 > PLANE_ANCHOR_VAR_RATIO * sigma_deg**2):
        # (False when either is unknown: the first view is kept as it is.)
        est = remembering(PlaneViews(kf.stamp_ns, tuple(s.normal for s in valid), 1, held, sigma_deg, False))
        return est.noted(note(Decision.PLANE_WAIT_UNDETERMINED, n=len(valid), first_sd=pending.sigma_deg,
                              next_sd=sigma_deg)), PlaneVerdict.WAIT, None, hold
    normals, waited = pending.normals, pending.waited
    with np.errstate(invalid="ignore"):
        dist = [min(math.degrees(math.acos(min(1.0, abs(float(s.normal @ n))))) for n in normals) for s in valid]
    order = np.argsort(dist)
    best, runner = dist[order[0]], dist[order[1]]
    if best < PLANE_NORMAL_AGREE_DEG and runner >= max(3.0 * best, PLANE_NORMAL_AGREE_DEG):
        s = valid[int(order[0])]
        return est.noted(note(Decision.PLANE_KEPT_NORMAL, views=waited + 1, best=best, runner=runner)), \
            PlaneVerdict.PICKED, (s.R, s.t, s.tri.expanded(np.flatnonzero(in_h), ctx.xn_cur.shape[0])), hold
    if waited >= PLANE_MAX_WAIT:
        return est.noted(note(Decision.PLANE_WAIT_GAVE_UP, max_wait=PLANE_MAX_WAIT)), PlaneVerdict.FALLBACK, None, \
            hold
    est = remembering(PlaneViews(pending.kf_stamp_ns, normals, waited + 1, held, pending.sigma_deg, True))
    return est.noted(note(Decision.PLANE_WAIT, n=len(valid), best=best, runner=runner, waited=waited + 1,
                          max_wait=PLANE_MAX_WAIT)), PlaneVerdict.WAIT, None, hold
