"""Two-view geometry, split by concept.

* ``models``: E and H estimation and their chi-square scoring (model selection's inputs), and the refit of
  a model an OpenCV release left unpolished;
* ``epipolar_refine``: a relative pose refined on its Sampson distances;
* ``pose``: pose recovery with cheirality, homography rotation / planar pose, parallax, refinement
  of a pose on map points;
* ``camera_error``: a rotation fitted with the focal length and radial distortion a calibration may have
  wrong;
* ``plane_normal``: how well a homography's decompositions fix the plane's normal;
* ``gric``: Torr's model selection between a model and its special case (a homography and a rotation);
* ``triangulation``: triangulation through its gates, scale of a direction from map points;
* ``common``: homogeneous coordinates, cross-product matrix, ray depths, nearest rotation, reprojection
  errors.

Everything is re-exported here: ``from epi_vo.core import geometry as geo`` then ``geo.recover_pose``.
"""

from epi_vo.core.geometry.camera_error import CameraErrorRotation, ray_angles, rotation_under_camera_error
from epi_vo.core.geometry.common import (
    F64,
    Mask,
    as_float64,
    homogeneous,
    nearest_rotation,
    ray_depths,
    reprojection_errors,
    skew,
)
from epi_vo.core.geometry.epipolar_refine import refine_relative_pose
from epi_vo.core.geometry.gric import gric, simpler_explains
from epi_vo.core.geometry.models import (
    CHI2_1DOF,
    CHI2_2DOF,
    ROBUST_METHOD_FLAGS,
    USAC_POLISHES,
    epipolar_distances_sq,
    essential_from_pose,
    estimate_essential,
    estimate_homography,
    fundamental_from_essential,
    polish_essential,
    polish_homography,
    polished_by_opencv,
    rh_ratio,
    sampson_distance_sq,
    score_fundamental,
    score_homography,
    score_static,
    transfer_errors_sq,
)
from epi_vo.core.geometry.plane_normal import homography_covariance, normal_covariance, normal_sigma_deg
from epi_vo.core.geometry.pose import (
    PNP_MIN_SIGMA_PX,
    PlanarSolution,
    agrees_with_plane,
    focal_for_rotation,
    homography_solutions,
    nearest_plane_motion,
    parallax_deg,
    pose_from_homography,
    recover_pose,
    refine_planar_pose,
    refine_pose_pnp,
    rotation_from_homography,
    solution_off_plane,
)
from epi_vo.core.geometry.triangulation import ScaleEstimate, Triangulation, scale_from_points, triangulate
from epi_vo.core.geometry.uncertainty import (
    CALIBRATION_TERMS,
    calibration_sensitivity,
    essential_pose_covariance,
    fuse,
    map_information,
    map_normal_equations,
    map_step,
    reprojection_rms,
    sampson_rms,
)

__all__ = [
    "CALIBRATION_TERMS",
    "CHI2_1DOF",
    "CHI2_2DOF",
    "F64",
    "PNP_MIN_SIGMA_PX",
    "ROBUST_METHOD_FLAGS",
    "USAC_POLISHES",
    "CameraErrorRotation",
    "Mask",
    "PlanarSolution",
    "ScaleEstimate",
    "Triangulation",
    "agrees_with_plane",
    "as_float64",
    "calibration_sensitivity",
    "epipolar_distances_sq",
    "essential_from_pose",
    "essential_pose_covariance",
    "estimate_essential",
    "estimate_homography",
    "focal_for_rotation",
    "fundamental_from_essential",
    "fuse",
    "gric",
    "homogeneous",
    "homography_covariance",
    "homography_solutions",
    "map_information",
    "map_normal_equations",
    "map_step",
    "nearest_plane_motion",
    "nearest_rotation",
    "normal_covariance",
    "normal_sigma_deg",
    "parallax_deg",
    "polish_essential",
    "polish_homography",
    "polished_by_opencv",
    "pose_from_homography",
    "ray_angles",
    "ray_depths",
    "recover_pose",
    "refine_planar_pose",
    "refine_pose_pnp",
    "refine_relative_pose",
    "reprojection_errors",
    "reprojection_rms",
    "rh_ratio",
    "rotation_from_homography",
    "rotation_under_camera_error",
    "sampson_distance_sq",
    "sampson_rms",
    "scale_from_points",
    "score_fundamental",
    "score_homography",
    "score_static",
    "simpler_explains",
    "skew",
    "solution_off_plane",
    "transfer_errors_sq",
    "triangulate",
]
