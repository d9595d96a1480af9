"""The sentences a person reads: every :class:`~epi_vo.core.decisions.Note` rendered to text, in one place.

``render(notes)`` is a frame's ``reason`` (its sentences joined by "; "). Nothing in epi_vo reads these
sentences back: code asks the notes (``FrameResult.decisions``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

from epi_vo.core.decisions import Decision, Note

Details = dict[str, Any]


def _too_few_tracked(d: Details) -> str:
    movers = f", {d['movers']} on moving objects)" if d["movers"] else ")"
    return f"too few tracked features ({d['n']} < {d['need']}" + movers


def _region(d: Details) -> str:
    x0, y0, x1, y1 = d["region"]
    return f"x {x0}-{x1}, y {y0}-{y1} px"


def _static(d: Details) -> str:
    what = "nothing moved"
    if d["n_moving"]:
        where = f" in {_region(d)}" if d.get("region") is not None else ""
        what = f"{d['n_moving']} features ({1 - d['fraction']:.0%}) moved{where}: another object's motion, ignored"
    return (f"camera static: {d['fraction']:.0%} of tracked features did not move, spread over {d['spread']:.0%} "
            f"of the image; {what}; pose held")


def _lens(d: Details) -> str:
    """The undeclared radial distortion a rotation was fitted with, when it moves the image corner by a pixel."""
    if not d.get("radial_px", 0.0) >= 1.0:
        return ""
    return f" and the lens's radial distortion k1 {d['k1']:+.3f} (undeclared: {d['radial_px']:.1f} px at the corner)"


def _focal(d: Details) -> str:
    return (f"pure rotation if the focal length were {d['ratio']:.3f} x the calibration's{_lens(d)} (parallax "
            f"{d['parallax_focal']:.2f} deg instead of {d['parallax']:.2f}, rotation {d['angle']:.1f} deg; or a "
            "wall-like plane seen while turning about a point off the camera): check the camera calibration")


def _undetermined(d: Details) -> str:
    if not math.isfinite(d["rotation_sigma_deg"]):
        why = "no covariance"
    else:
        why = f"rotation sigma {d['rotation_sigma_deg']:.2f} deg, direction sigma {d['direction_sigma_deg']:.1f} deg"
    return (f"initialization deferred: E's pose is not determined by these points ({why}); waiting for baseline, "
            "position held")


def _skipped(d: Details) -> str:
    return f"frame rejected: {d['problem']}; frame skipped" + (f" ({d['note']})" if d["note"] else "")


def _suspect(d: Details) -> str:
    why = "E took the plane's other solution?" if d["plane"] else "a moving object took its consensus?"
    return (f"E disagrees with the map's points by {d['angle']:.2f} deg in rotation, {d['direction']:.0f} deg in "
            f"direction ({why}): pose from the map")


_TEXT: dict[Decision, str | Callable[[Details], str]] = {
    Decision.RESET: "{text}",
    Decision.TIME_JUMPED_BACK: "time jumped backwards by {seconds:.3f} s: tracking restarted from the last pose",
    Decision.STAMP_INVALID: _skipped,
    Decision.DUPLICATE_STAMP: "duplicate image stamp: frame skipped",
    Decision.FRAME_SKIPPED: _skipped,
    Decision.FRAME_REJECTED: "frame rejected: {problem}",
    Decision.IMAGE_TOO_SMALL: "frame rejected: {problem}",
    Decision.OPENCV_FAILED: "frame rejected: {problem}",
    Decision.CAMERA_CHANGED: "camera_info changed: tracking restarted",
    Decision.FIRST_FRAME: "first frame: reference keyframe set",
    Decision.NEW_REFERENCE: "new reference keyframe, no map yet",
    Decision.NO_POSE: "no pose this frame ({failures}/{limit}); pose held",
    Decision.TRACKING_LOST: "tracking lost after {failures} frame(s) without a pose: re-initializing from the last "
                            "pose",
    Decision.RELOCALISED: "re-localised against keyframe {kf}: {n} points; the same map and scale continue",
    Decision.POSE_NOT_FINITE: "internal: the held pose was not finite; reset to the origin",
    Decision.COVARIANCE_NOT_FINITE: "internal: the held covariance was not finite; reset to the 'unknown' covariance",
    Decision.EXPOSURE_CHANGED: "exposure changed: the image was scaled by {gain:.2f} to track it",
    Decision.TOO_FEW_TRACKED: _too_few_tracked,
    Decision.MOVERS_IN_VIEW: lambda d: f"{d['n']} tracked features move on their own ({_region(d)}): left out of "
                                       "pose and map",
    Decision.NO_MODEL: "no two-view model could be estimated",
    Decision.MOTION_NOT_FINITE: "the motion estimate is not finite (check the calibration): no pose this frame",
    Decision.INLIERS_CLUSTERED: "the pose's inliers are clustered: they cover {spread:.0%} of the image cells holding "
                                "features (a moving object may dominate)",
    Decision.CAMERA_STATIC: _static,
    Decision.TOO_FEW_E_INLIERS: "too few inliers after cheirality ({n} < {need}, RH {rh:.2f})",
    Decision.TOO_FEW_H_INLIERS: "too few homography inliers ({n} < {need})",
    Decision.PURE_ROTATION: "pure rotation: homography explains the motion (RH {rh:.2f}, parallax {parallax:.2f} deg, "
                            "rotation {angle:.1f} deg); translation not observable, position held",
    Decision.LOW_PARALLAX: "low parallax ({parallax:.2f} deg): waiting for baseline, position held",
    Decision.E_MOVES_OFF_PLANE: "E's motion is none of H's plane's ({rotation:.2f} deg, {direction:.0f} deg of "
                                "direction from the nearest): part of its consensus moves; the map starts from the "
                                "plane",
    Decision.NOT_A_PLANE: "not a plane: {off} of E's {n_e} inliers lie off H's plane; initialising from E",
    Decision.PLANE_PICKED_BY_OFF_POINTS: "planar scene: the {off} points off H's plane pick its decomposition",
    Decision.PLANE_AMBIGUOUS: "planar scene: homography decomposition ambiguous, waiting for parallax",
    Decision.PLANE_LOW_PARALLAX: "planar scene, low parallax ({parallax:.2f} deg < {need}): waiting for baseline, "
                                 "position held",
    Decision.PLANE_POSE_UNTESTED: "planar scene: pose from H (too few points to test it)",
    Decision.PLANE_POSE_FITS: "planar scene: H's pose fits its inliers' epipolar geometry (test {stat:.1f})",
    Decision.PLANE_POSE_OTHER_SOLUTION: "planar scene: pose from H: the epipolar fit moved {moved:.2f} deg / "
                                        "{turned:.1f} deg, to another solution",
    Decision.PLANE_POSE_REFINED: "planar scene: H's pose refined on its {n} epipolar inliers (test {stat:.0f}, "
                                 "rotation moved {moved:.3f} deg)",
    Decision.PLANE_E_WITH_PARALLAX: "plane-dominated view (RH {rh:.2f}) with parallax: E's pose, checked against the "
                                    "map",
    Decision.POSE_FROM_MAP_POINTS: "planar or low-parallax view (RH {rh:.2f}): pose from map points",
    Decision.ROTATION_UNDER_FOCAL_TOLERANCE: "pure rotation: homography explains the motion under a focal length "
                                             "{ratio:.3f} x the calibration's, within its tolerance (parallax "
                                             "{parallax_focal:.2f} deg instead of {parallax:.2f}, rotation {angle:.1f} "
                                             "deg); translation not observable, position held",
    Decision.FOCAL_SUSPECT_MAP_DECIDES: lambda d: f"{_focal(d)}; pose from the map",
    Decision.FOCAL_SUSPECT_ROTATION: lambda d: f"{_focal(d)}; no map from it: translation not observable, position "
                                               "held",
    Decision.PLANE_WAIT_FIRST: "planar scene: {n} decompositions of H fit; waiting for a view that tells the plane "
                               "apart (1/{max_wait}), pose held",
    Decision.PLANE_WAIT_UNDETERMINED: "planar scene: {n} decompositions of H fit; their normals were known to "
                                      "{first_sd:.1f} deg, now to {next_sd:.1f}: this view is taken as the first, "
                                      "pose held",
    Decision.PLANE_WAIT: "planar scene: {n} decompositions of H fit ({best:.1f} / {runner:.1f} deg from the first "
                         "view's planes); waiting for a view that tells the plane apart ({waited}/{max_wait}), pose "
                         "held",
    Decision.PLANE_KEPT_NORMAL: "planar scene: the plane kept its normal over {views} views ({best:.1f} deg; the other "
                                "solution moved {runner:.1f} deg)",
    Decision.PLANE_WAIT_GAVE_UP: "planar scene: no view told H's decompositions apart in {max_wait} frames; taking the "
                                 "one most points pass the gates",
    Decision.INIT_LOW_PARALLAX: "low parallax ({parallax:.2f} deg < {need}): waiting for baseline, position held",
    Decision.INIT_REJECTED_DEPTH: "initialization rejected: only {ratio:.0%} of inliers in front of both cameras "
                                  "(< {need:.0%})",
    Decision.INIT_REJECTED_GATES: "initialization rejected: {n} points pass the triangulation gates (< {need})",
    Decision.INIT_DEFERRED: _undetermined,
    Decision.MAP_FROM_ESSENTIAL: "map initialized from essential matrix: {n} points",
    Decision.MAP_FROM_HOMOGRAPHY: "map initialized from homography (planar scene): {n} points",
    Decision.E_HOLDS_NO_MAP_POINTS: "E's inliers hold almost none of the map's points (a moving object took its "
                                    "consensus?): pose from the map",
    Decision.TOO_FEW_MAP_POINTS: "too few map points to carry the scale ({n})",
    Decision.TOO_FEW_MAP_POINTS_AGREE: "too few map points agree with the pose ({n} < {need})",
    Decision.E_DISAGREES_WITH_MAP: _suspect,
    Decision.KEYFRAME_WITHOUT_DEPTH: "keyframe without parallax: no new depth",
    Decision.WINDOW_WORKER_FAILED: "{text}",
    Decision.METRIC_SCALE_PENDING: "metric scale not established yet: VO units",
}


def sentence(n: Note) -> str:
    """The sentence of one note."""
    text = _TEXT[n.decision]
    return text.format(**n.as_dict()) if isinstance(text, str) else text(n.as_dict())


def render(notes: Iterable[Note]) -> str:
    """A frame's ``reason``: the sentences of its notes, in order, joined by "; "."""
    return "; ".join(sentence(n) for n in notes)
