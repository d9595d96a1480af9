"""A rotation seen through a camera that is not the calibration's: with fx off, or a lens distortion the
calibration does not declare, a rotating camera's rays do not line up once the rotation is taken out, which
looks like parallax."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import TrackingState
from epi_vo.core.motion.record import Motion, MotionContext, MotionEstimate, has_map
from epi_vo.core.transforms import rotation_angle_deg

F64 = NDArray[np.float64]

FOCAL_SUSPECT_RANGE = (0.8, 1.25)  # focal lengths (x the calibration's) a rotation-only view may suggest ...
FOCAL_SUSPECT_MIN_OFF = 0.03  # ... at least this far from it (closer: within the estimate's noise)
# The closed-form focal length (from H's entries) is refined on the points, with the lens's radial distortion,
# only when it lies within this relative margin outside FOCAL_SUSPECT_RANGE: the refinement moves it by a few
# percent, not more.
FOCAL_PRECHECK_MARGIN = 0.15
FOCAL_HINT_AGREE = 0.01  # a later frame's estimate this close to the last one taken: the same focal length
FOCAL_RATIO_SIGMA = 0.01  # of that focal length, relative: its estimates scatter by 0.3-0.8 % frame to frame
# Below this displacement of the image's farthest corner (px) an undeclared radial distortion is within the
# calibration's tolerance (the tracks' own noise): the calibration is not blamed for it.
RADIAL_TOLERANCE_PX = 1.0
ROTATION_PARAMS = 3  # a rotation's degrees of freedom (GRIC's count; each camera term fitted adds one)
HOMOGRAPHY_PARAMS = 8
# A fitted focal length this many of its standard deviations outside FOCAL_SUSPECT_RANGE is implausible (two:
# a plausible camera is rejected by chance once in ~40 fits)
FOCAL_RANGE_SIGMAS = 2.0


def rotation_explains(cfg: VoConfig, ctx: MotionContext, H: F64, in_h: NDArray[np.bool_], angles: F64,
                      n_params: int) -> bool:
    """A rotation (``n_params``: 3, with each camera term fitted one more) explains H's inliers as well as H
    does, by GRIC (``geometry.gric``) at the model selection's noise (``score_sigma_px``, both images alike):
    the parallax ``angles`` (rad, per inlier) it leaves is no more than H's transfer errors by what its fewer
    parameters are worth. A translation's parallax grows with the baseline over the depth, a rotation's
    residual stays at the noise: in pixels, whatever the image's size."""
    K = ctx.kf.camera.K
    d_cur, d_ref = geo.transfer_errors_sq(H, ctx.kf.uv[ctx.rows][in_h], ctx.uv_cur[in_h])
    var = 2.0 * cfg.score_sigma_px**2  # a residual between two images carries both images' noise
    chi2_h = 0.5 * (d_cur + d_ref) / var
    chi2_r = (angles * K[0, 0]) ** 2 / var
    return geo.simpler_explains(chi2_r, n_params, chi2_h, HOMOGRAPHY_PARAMS)


def rotation_under_other_focal(cfg: VoConfig, ctx: MotionContext, H: F64, in_h: NDArray[np.bool_],
                               est: MotionEstimate, rot_cov: float) -> tuple[MotionEstimate, Motion | None]:
    """A pure rotation seen through a camera that is not the calibration's: rotation-only, and the reason says
    so (the motion; None: not such a rotation, or the map decides, and the caller goes on).

    With the calibration's focal length off, or a lens distortion it does not declare, a rotating camera's rays
    do not line up after the rotation is taken out: the leftover grows with the rotation (with fx x 0.9: 0.5
    deg at 5 deg of rotation; k1 0.05 undeclared: 0.5-0.9 deg at 10-15 deg) and would be taken for parallax,
    a plane and a translation. The rotation is fitted to the points with the focal length, and with the
    radial distortion when that is not enough (``geometry.rotation_under_camera_error``). When the rays then
    line up (``rotation_explains``) under a focal length within ``FOCAL_SUSPECT_RANGE``
    of the calibration's, with the distortion moving the image corner within that range too, the motion is
    that rotation (position held) before a map exists; with a map the map's points decide and the reason
    says what else the motion could be. A camera within the calibration's tolerance
    (``FOCAL_SUSPECT_MIN_OFF``, ``RADIAL_TOLERANCE_PX``) is not blamed.

    The ambiguity is real for one kind of scene: a plane facing the camera seen while the camera turns about
    a point off its centre (a pan plus a sideways shift) is, to first order, a pure rotation under a focal
    length sqrt(1 + L / d) x the true one (lever arm L, distance d: 0.3 m before a wall 2 m away, 1.07 x).
    Hence the map's say once there is one. Homographies of a camera translating over a floor or across a
    tilted plane are rotations under no plausible focal length (none, or 0.02-0.66 x the calibration's), and
    a translation's parallax, which depends on each point's depth, is no change of the camera."""
    cam = ctx.kf.camera
    K = cam.K
    f = geo.focal_for_rotation(H, K)
    lo, hi = FOCAL_SUSPECT_RANGE
    if f is None or not (1.0 - FOCAL_PRECHECK_MARGIN) * lo <= f / K[0, 0] <= (1.0 + FOCAL_PRECHECK_MARGIN) * hi:
        # H's entries fix the focal length only as well as the rotation shows it (poorly over a few degrees):
        # the fit starts from the calibration's instead, unless the parallax is more than a plausible camera
        # can leave (a focal length off by e leaves at most |e - 1| x the rotation's angle).
        if est.median_parallax_deg > max(hi - 1.0, 1.0 - lo) * rotation_angle_deg(geo.rotation_from_homography(H, K)):
            return est, None
        f = float(K[0, 0])
    K_f = K.copy()
    K_f[:2, :2] *= f / K[0, 0]
    R_f, xn_kf, xn_cur, noise = geo.rotation_from_homography(H, K_f), ctx.kf.xn[ctx.rows][in_h], ctx.xn_cur[in_h], \
        cfg.pixel_noise_px / K[0, 0]
    # The simplest camera that explains the rotation: the focal length alone, then with the lens's distortion
    # when the rays do not line up without it (k1 trades against the focal length and the pan's angle: on a
    # rotation of a few degrees it takes up the tracks' noise, 0.25 deg of rotation on a 4.7 deg one).
    fit = geo.rotation_under_camera_error(R_f, f / K[0, 0], xn_kf, xn_cur, noise, radial=False)
    if fit is None or not rotation_explains(cfg, ctx, H, in_h, fit.angles, ROTATION_PARAMS + 1):
        fit = geo.rotation_under_camera_error(R_f, f / K[0, 0], xn_kf, xn_cur, noise)
    # The focal length is judged within what the rays determine of it (FOCAL_RANGE_SIGMAS standard
    # deviations): over a pan of a few degrees they barely do, and a fit outside the range is no evidence.
    margin = math.exp(FOCAL_RANGE_SIGMAS * fit.log_ratio_sigma) if fit is not None else 1.0
    lo, hi = lo / margin, hi * margin
    if fit is None or not lo <= fit.ratio <= hi:
        return est, None
    ratio, par_f = fit.ratio, fit.parallax_deg
    # The focal length and k1 both scale the image radially, and a rotation of a few degrees tells them
    # apart only roughly (1.05 x and k1 0.10 fit a lens of 0.985 x and 0.05 as well): what must be plausible
    # is the camera they make together, judged where it differs most from the calibration, at the corner.
    corner = math.hypot(max(K[0, 2], cam.width - K[0, 2]), max(K[1, 2], cam.height - K[1, 2])) / K[0, 0]
    r_true = corner / ratio
    if not lo <= corner / r_true * (1.0 + fit.k1 * r_true**2) <= hi:
        return est, None
    angle = rotation_angle_deg(fit.R)
    if not (angle >= cfg.min_rotation_for_rotation_only_deg
            and rotation_explains(cfg, ctx, H, in_h, fit.angles, ROTATION_PARAMS + (2 if fit.k1 != 0.0 else 1))):
        return est, None
    # The rotation also carries the focal length's error (a rotation under a focal length off by e is off
    # by about e x its angle): FOCAL_RATIO_SIGMA of it.
    rotation = Motion(TrackingState.ROTATION_ONLY, fit.R, np.zeros(3),
                      covm.block(1e-6, rot_cov + (FOCAL_RATIO_SIGMA * math.radians(angle)) ** 2), in_h)
    # How far the undeclared distortion moves the image's farthest corner (px): what it costs the calibration.
    radial_px = abs(fit.k1) * r_true**3 * ratio * K[0, 0]
    # Once a rotation was taken under another focal length, later frames agreeing with it within
    # FOCAL_HINT_AGREE name it too, also a little closer to the calibration's than FOCAL_SUSPECT_MIN_OFF (a
    # focal length 3 % off is estimated at 2.9-3.4 % from frame to frame).
    hint = est.memory.focal_hint
    agrees = hint is not None and abs(ratio - hint) <= FOCAL_HINT_AGREE
    details = {"ratio": ratio, "k1": fit.k1, "radial_px": radial_px, "parallax_focal": par_f,
               "parallax": est.median_parallax_deg, "angle": angle}
    if abs(ratio - 1.0) < FOCAL_SUSPECT_MIN_OFF * (0.5 if agrees else 1.0) and radial_px < RADIAL_TOLERANCE_PX:
        # Within the calibration's tolerance: a rotation, without blaming the calibration (else such frames,
        # at a little "parallax", wait as a plane with the orientation held).
        if has_map(cfg, ctx.kf):
            return est, None
        return est.noted(note(Decision.ROTATION_UNDER_FOCAL_TOLERANCE, **details)), rotation
    est = est.but(focal_ratio=ratio, memory=dataclasses.replace(est.memory, focal_hint=ratio))
    if has_map(cfg, ctx.kf):
        # The map's points decide the pose, as without the check (a robot turning in place before a wall
        # 2 m away, the camera 0.3 m off the axis: 1.07 x); the frame says what else it could be.
        return est.noted(note(Decision.FOCAL_SUSPECT_MAP_DECIDES, **details)), None
    return est.noted(note(Decision.FOCAL_SUSPECT_ROTATION, **details)), rotation
