"""A rotation seen through a camera that is not the calibration's: the focal length and the radial distortion
the calibration may have wrong, fitted with the rotation (H&Z 19.6 for the focal length of a rotating camera;
Fitzgibbon, "Simultaneous linear estimation of multiple view geometry and lens distortion", CVPR 2001, for
radial distortion as part of the two-view model).

A rotating camera's rays line up exactly after the rotation is taken out, whatever the scene. Through a
calibration whose focal length is off, or whose lens distortion is not declared, they do not: the leftover
grows with the rotation (k1 0.05 undeclared: 0.5-0.9 deg at 10-15 deg of pan in a 0.9-width focal length)
and is taken for parallax, a plane and a translation. Fitting the rotation together with those two terms of
the camera tells a rotation seen through a wrong camera from a translation: a translation's parallax depends
on each point's depth, which no change of the camera explains.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from epi_vo.core.geometry.common import F64, homogeneous

# Gauss-Newton steps of the fit; it starts within a few percent of the answer (the closed-form focal length,
# no distortion, H's rotation) and converges in 3-5.
CAMERA_FIT_STEPS = 8
# Fixed-point steps undoing the lens's distortion: each shrinks the error by ~2 k1 r^2 (0.1 for k1 0.1 at the
# corner of a 65 deg view), to a millionth of the distortion in six.
UNDISTORT_STEPS = 6
# What a calibration is taken to get wrong (1 sigma), the prior of the fit: its focal length by 10 % (log of
# the ratio), the radial distortion it does not declare by k1 0.05 (a lens bending the corner of a 60 deg view
# by ~3 %, as cheap lenses do that nobody calibrated).
FOCAL_PRIOR_SIGMA = 0.1
RADIAL_PRIOR_SIGMA = 0.05
# Finite-difference step of the numeric Jacobian (rotation in rad, log focal ratio, distortion coefficient):
# well above the float noise of the residuals, well below the parameters' precision.
JACOBIAN_STEP = 1e-6


@dataclass(frozen=True)
class CameraErrorRotation:
    """A rotation ``R`` (reference -> current) under the focal length ``ratio`` x the calibration's and the
    radial distortion ``k1`` the calibration does not declare (``x_true = x_undistorted / ratio``, then
    distorted by ``1 + k1 r^2`` as the lens of Brown's model), with the median parallax (deg) its rays leave
    and each point's (rad, (N,)), and the standard deviation of the focal length's log ratio (what the rays
    and the prior determine of it: little over a rotation of a few degrees)."""

    R: F64
    ratio: float
    k1: float
    parallax_deg: float
    angles: F64
    log_ratio_sigma: float


def _true_rays(xn: F64, log_ratio: float, k1: float) -> F64:
    """Rays of the true camera from the calibration's normalised coordinates: the focal length's ratio, then
    the lens's radial distortion ``x_d = x (1 + k1 |x|^2)`` undone (fixed-point iterations, as
    ``cv2.undistortPoints`` does)."""
    x_d = xn * math.exp(-log_ratio)
    x = x_d
    if k1 == 0.0:  # no distortion to undo: each step would divide by exactly 1
        return homogeneous(x)
    for _ in range(UNDISTORT_STEPS):
        x = x_d / (1.0 + k1 * np.einsum("ij,ij->i", x, x))[:, None]
    return homogeneous(x)


def _camera_rays(p: F64, xn_both: F64) -> tuple[F64, F64]:
    """The true camera's rays under the camera terms ``(p[3], p[4])`` (k1 ``p[4]``, 0 without it) of
    ``xn_both`` (the reference's points, then as many of the current image's, undone in one pass): the
    reference's as they are, the current image's as unit vectors. They do not depend on the rotation
    ``p[:3]``, so the rotation's columns of the Jacobian share them."""
    k1 = float(p[4]) if p.size > 4 else 0.0
    rays = _true_rays(xn_both, p[3], k1)
    n = rays.shape[0] // 2
    b_cur = rays[n:]
    return rays[:n], b_cur / np.linalg.norm(b_cur, axis=1)[:, None]


def _residuals(p: F64, R0: F64, rays: tuple[F64, F64]) -> F64:
    """The difference of the unit rays (rad, to first order the parallax) of the current points and the
    reference points turned by the rotation ``exp(p[:3]) R0``, the ``rays`` those of the camera ``(p[3],
    p[4])`` (``_camera_rays``). Both images' noise enters alike: a transfer into one image would take the other's
    points as exact and bias the camera's terms (which scale both) towards explaining its noise."""
    R = np.asarray(cv2.Rodrigues(p[:3])[0], np.float64) @ R0
    b_ref = rays[0] @ R.T
    res: F64 = (b_ref / np.linalg.norm(b_ref, axis=1)[:, None] - rays[1])
    return res.reshape(-1)


def rotation_under_camera_error(R0: F64, ratio0: float, xn_ref: F64, xn_cur: F64, noise: float, *,
                                radial: bool = True) -> CameraErrorRotation | None:
    """The rotation, focal length ratio and undeclared radial distortion that best explain the correspondences
    ``xn_ref`` -> ``xn_cur`` (N, 2, normalised by the calibration, image noise ``noise`` in those units) as a
    pure rotation: Gauss-Newton on the rays' differences (``_residuals``) from the rotation ``R0`` under
    ``ratio0`` x the focal length without distortion, with the calibration as the prior of the camera terms
    (``FOCAL_PRIOR_SIGMA``, ``RADIAL_PRIOR_SIGMA``). A small rotation shows the camera terms little (their
    effect on the rays grows with the angle) and the focal length and k1 both scale the image radially: the
    prior keeps what the rays do not determine at the calibration's. None when the fit is singular (too few
    points) or does not converge to a plausible camera (a focal length off by a factor e). ``radial`` False:
    the focal length alone (k1 0)."""
    if xn_ref.shape[0] < 8:
        return None
    prior = np.array([0.0, 0.0, 0.0, 1.0 / FOCAL_PRIOR_SIGMA**2, 1.0 / RADIAL_PRIOR_SIGMA**2])
    w = 1.0 / noise**2
    n_par = 5 if radial else 4
    prior = prior[:n_par]
    p = np.zeros(n_par)
    p[3] = math.log(ratio0)
    xn_both = np.vstack((xn_ref, xn_cur))
    for _ in range(CAMERA_FIT_STEPS):
        rays = _camera_rays(p, xn_both)
        r = _residuals(p, R0, rays)
        J = np.empty((r.size, n_par))
        for j in range(n_par):
            dp = np.zeros(n_par)
            dp[j] = JACOBIAN_STEP
            p_j = p + dp
            J[:, j] = (_residuals(p_j, R0, rays if j < 3 else _camera_rays(p_j, xn_both)) - r) / JACOBIAN_STEP
        A = w * np.einsum("ki,kj->ij", J, J) + np.diag(prior)  # einsum, not BLAS: no worker threads left spinning
        g = w * np.einsum("ki,k->i", J, r) + prior * p
        if not np.all(np.isfinite(A)) or np.linalg.cond(A) > 1e12:
            return None
        step = -np.linalg.solve(A, g)
        p = p + step
        if not np.all(np.isfinite(p)) or abs(p[3]) > 1.0:
            return None
        if float(np.max(np.abs(step))) < 1e-9:
            break
    R = np.asarray(cv2.Rodrigues(p[:3])[0], np.float64) @ R0
    k1 = float(p[4]) if radial else 0.0
    angles = ray_angles(R, math.exp(p[3]), k1, xn_ref, xn_cur)
    log_ratio_sigma = math.sqrt(max(float(np.linalg.inv(A)[3, 3]), 0.0))
    return CameraErrorRotation(R, math.exp(p[3]), k1, float(np.degrees(np.median(angles))), angles,
                               log_ratio_sigma)


def ray_angles(R: F64, ratio: float, k1: float, xn_ref: F64, xn_cur: F64) -> F64:
    """The angle (rad, (N,)) between each current point's ray and its reference point's ray turned by ``R``,
    under the camera ``(ratio, k1)`` (``CameraErrorRotation``'s): the parallax a rotation leaves."""
    q, b_cur = _true_rays(xn_ref, math.log(ratio), k1) @ R.T, _true_rays(xn_cur, math.log(ratio), k1)
    cos_a = np.einsum("ij,ij->i", q, b_cur) / (np.linalg.norm(q, axis=1) * np.linalg.norm(b_cur, axis=1))
    out: F64 = np.arccos(np.clip(cos_a, -1.0, 1.0))
    return out
