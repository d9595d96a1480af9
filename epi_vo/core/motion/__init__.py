"""The motion stage: the pose of the current frame relative to its keyframe, and what justifies it.

Given the winning two-view model (``epi_vo.core.selection``) and the keyframe's map:

* no motion at all, before a map (``static``): the camera is still, whatever moved is another object;
* E with a map and enough parallax (``essential``): E's rotation and translation direction (recoverPose
  with cheirality), scaled by the map points (robust 1-D median of per-point scales), checked against the
  map (``map_check``);
* otherwise with a map (H chosen, or low parallax): a motion-only refinement on the map points;
* H with no parallax left after removing the rotation (``homography``): pure rotation, the position holds;
  a rotation under another focal length (``focal``);
* no map yet: the first map (``initialize``), from E or from a plane's decomposition (``homography``,
  ``plane_views``), its baseline's length set by the scale stage (``MotionContext.initial_baseline``).

The stage is a function (``estimate``): it reads a ``MotionContext`` and the ``MotionMemory`` of the frames
before, and returns a frozen ``MotionEstimate`` with the motion, the statistics it measured, its decisions
(``Note``) and the memory for the next frame.
"""

from epi_vo.core.motion.plane_views import PLANE_MAX_WAIT
from epi_vo.core.motion.record import (
    Motion,
    MotionContext,
    MotionEstimate,
    MotionMemory,
    PlaneViews,
    expanded,
    has_map,
    is_finite,
)
from epi_vo.core.motion.stage import estimate
from epi_vo.core.motion.static import grid_spread, moving_region

__all__ = ["PLANE_MAX_WAIT", "Motion", "MotionContext", "MotionEstimate", "MotionMemory", "PlaneViews", "estimate",
           "expanded", "grid_spread", "has_map", "is_finite", "moving_region"]
