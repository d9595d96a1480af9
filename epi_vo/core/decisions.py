"""What the stages decided about a frame, as values: a :class:`Decision` and the numbers behind it.

Every stage says what it did (or refused) with a :class:`Note`: one enum member and its details (counts,
angles, ratios, and for input problems the caller's own words). A frame's notes travel in its
``FrameResult`` (``notes``; ``decisions`` the members alone), so code asks ``Decision.TIME_JUMPED_BACK in
result.decisions``, never the text. The sentence a person reads (``FrameResult.reason``) is rendered from
the notes in one place, ``epi_vo.core.reasons``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any


class Decision(enum.Enum):
    """One decision of a stage about a frame (its sentence: ``epi_vo.core.reasons``)."""

    # --- the frame and its input (the pipeline) --------------------------------------------------
    RESET = "reset"  # tracking restarted on request (``text``: the caller's reason)
    TIME_JUMPED_BACK = "time_jumped_back"  # the stamp went back by ``seconds``: tracking restarted
    STAMP_INVALID = "stamp_invalid"  # the stamp is no ROS time: frame skipped
    DUPLICATE_STAMP = "duplicate_stamp"  # the same stamp again: frame skipped
    FRAME_SKIPPED = "frame_skipped"  # unusable message (``problem``, ``note``): frame skipped
    FRAME_REJECTED = "frame_rejected"  # unusable frame (``problem``): counted as a frame without a pose
    IMAGE_TOO_SMALL = "image_too_small"  # the frontend cannot use the image: rejected
    OPENCV_FAILED = "opencv_failed"  # OpenCV refused the frame (``detail``): rejected, map dropped
    CAMERA_CHANGED = "camera_changed"  # another camera_info: tracking restarted
    FIRST_FRAME = "first_frame"  # the first frame became the reference keyframe
    NEW_REFERENCE = "new_reference"  # a restart's frame became the reference keyframe, no map yet
    NO_POSE = "no_pose"  # no pose this frame (``failures`` of ``limit``), pose held
    TRACKING_LOST = "tracking_lost"  # ``failures`` frames without a pose: restart from the held pose
    RELOCALISED = "relocalised"  # found again against keyframe ``kf`` (``n`` map points): same map
    POSE_NOT_FINITE = "pose_not_finite"  # defect guard: the held pose was reset to the origin
    COVARIANCE_NOT_FINITE = "covariance_not_finite"  # defect guard: the held covariance was reset
    # --- features -----------------------------------------------------------------------------------
    EXPOSURE_CHANGED = "exposure_changed"  # the image was scaled by ``gain`` to track it
    TOO_FEW_TRACKED = "too_few_tracked"  # ``n`` usable tracks < ``need`` (``movers`` left out)
    MOVERS_IN_VIEW = "movers_in_view"  # ``n`` tracks move on their own, in ``region``: left out
    # --- model selection and motion ---------------------------------------------------------------
    NO_MODEL = "no_model"  # neither E nor H could be estimated
    MOTION_NOT_FINITE = "motion_not_finite"  # the motion estimate was not finite: no pose
    INLIERS_CLUSTERED = "inliers_clustered"  # the pose's inliers cover ``spread`` of the occupied cells
    CAMERA_STATIC = "camera_static"  # the "no motion" hypothesis explains the frame
    TOO_FEW_E_INLIERS = "too_few_e_inliers"  # after cheirality
    TOO_FEW_H_INLIERS = "too_few_h_inliers"
    PURE_ROTATION = "pure_rotation"  # H explains the motion with no parallax left: position held
    LOW_PARALLAX = "low_parallax"  # no map and too little parallax under H: waiting for baseline
    E_MOVES_OFF_PLANE = "e_moves_off_plane"  # E's motion is none H's plane allows: the plane is taken
    NOT_A_PLANE = "not_a_plane"  # many of E's inliers lie off H's plane: the map starts from E
    PLANE_PICKED_BY_OFF_POINTS = "plane_picked_by_off_points"  # points off the plane chose H's solution
    PLANE_AMBIGUOUS = "plane_ambiguous"  # H's decomposition ambiguous: waiting for parallax
    PLANE_LOW_PARALLAX = "plane_low_parallax"  # planar, below init_min_parallax_deg: waiting
    PLANE_POSE_UNTESTED = "plane_pose_untested"  # H's pose kept: too few points to test it
    PLANE_POSE_FITS = "plane_pose_fits"  # H's pose fits its inliers' epipolar geometry (``stat``)
    PLANE_POSE_OTHER_SOLUTION = "plane_pose_other_solution"  # the epipolar fit went to another solution
    PLANE_POSE_REFINED = "plane_pose_refined"  # H's pose refined on its epipolar inliers
    PLANE_E_WITH_PARALLAX = "plane_e_with_parallax"  # a plane with a map and parallax: E, checked
    POSE_FROM_MAP_POINTS = "pose_from_map_points"  # planar or low-parallax view with a map
    ROTATION_UNDER_FOCAL_TOLERANCE = "rotation_under_focal_tolerance"  # a rotation under a focal length near fx
    FOCAL_SUSPECT_MAP_DECIDES = "focal_suspect_map_decides"  # a rotation under another focal length; map decides
    FOCAL_SUSPECT_ROTATION = "focal_suspect_rotation"  # ... no map: taken as that rotation, position held
    PLANE_WAIT_FIRST = "plane_wait_first"  # two valid solutions of H: waiting for a second view
    PLANE_WAIT_UNDETERMINED = "plane_wait_undetermined"  # the next view fixes the normals far better: first now
    PLANE_WAIT = "plane_wait"  # still waiting (``waited`` of ``max_wait``)
    PLANE_KEPT_NORMAL = "plane_kept_normal"  # the view told the plane apart
    PLANE_WAIT_GAVE_UP = "plane_wait_gave_up"  # no view did: the one most points pass the gates
    INIT_LOW_PARALLAX = "init_low_parallax"  # below init_min_parallax_deg: waiting for baseline
    INIT_REJECTED_DEPTH = "init_rejected_depth"  # too few inliers in front of both cameras
    INIT_REJECTED_GATES = "init_rejected_gates"  # too few points through the triangulation gates
    INIT_DEFERRED = "init_deferred"  # E's pose not determined by its points (``rotation_sigma_deg``, ...)
    MAP_FROM_ESSENTIAL = "map_from_essential"  # the first map, from E (``n`` points)
    MAP_FROM_HOMOGRAPHY = "map_from_homography"  # the first map, from H (planar scene)
    E_HOLDS_NO_MAP_POINTS = "e_holds_no_map_points"  # E's inliers hold almost no map point: map decides
    TOO_FEW_MAP_POINTS = "too_few_map_points"  # to carry the scale
    TOO_FEW_MAP_POINTS_AGREE = "too_few_map_points_agree"  # with the map's pose
    E_DISAGREES_WITH_MAP = "e_disagrees_with_map"  # a mover (or the plane's other solution) took E
    # --- keyframes, map, window and scale -----------------------------------------------------------
    KEYFRAME_WITHOUT_DEPTH = "keyframe_without_depth"  # a keyframe at low parallax: no new depth
    WINDOW_WORKER_FAILED = "window_worker_failed"  # the adjustment's worker stopped (``text``)
    METRIC_SCALE_PENDING = "metric_scale_pending"  # metres asked for, not established: the pose in VO units


@dataclass(frozen=True)
class Note:
    """One decision about a frame with its details (numbers, or for input problems the caller's words)."""

    decision: Decision
    details: tuple[tuple[str, Any], ...] = ()

    def __getitem__(self, name: str) -> Any:
        for key, value in self.details:
            if key == name:
                return value
        raise KeyError(f"{self.decision.name} has no detail {name!r}")

    def as_dict(self) -> dict[str, Any]:
        return dict(self.details)


def note(decision: Decision, **details: Any) -> Note:
    """``Note(decision, details)`` with the details given by name."""
    return Note(decision, tuple(details.items()))
