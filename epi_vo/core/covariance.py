"""Pose covariance algebra: 6x6 over (x, y, z, rot_x, rot_y, rot_z), position first.

Every function returns finite values for finite inputs; ``is_finite`` is the guard the pipeline
applies before it takes an estimate into its held state.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.geometry import skew

F64 = NDArray[np.float64]


def rotation_var(sigma_px: float, fx: float, n: int) -> float:
    """Per-axis rotation variance (rad^2) of a rotation fitted to n rays with sigma_px pixel noise."""
    return 2.0 * (sigma_px / fx) ** 2 / max(n, 1)


def block(pos_var: float, rot_var: float) -> F64:
    """Diagonal covariance with one variance for the position and one for the rotation axes."""
    return np.diag([pos_var] * 3 + [rot_var] * 3)


def compose(cov_w_kf: F64, T_w_kf: F64, cov_rel: F64, t_cur_kf: F64, R_cur_kf: F64) -> F64:
    """First-order covariance of T_w_c = T_w_kf T_kf_cur (relative covariance given in the keyframe frame).

    Perturbations are left ones in their frame: the keyframe's (dp, dtheta) in ``w``, the relative
    (dc, dphi) in the keyframe frame. The keyframe's rotation error also moves the current position by
    ``dtheta x c_w`` (``c_w`` the camera's offset from the keyframe in ``w``): the Jacobian of the
    keyframe part is ``[[I, -[c_w]x], [0, I]]``, so the position block gains the lever-arm term and the
    position-rotation block the matching cross term; the relative part is rotated into ``w``.
    """
    R_w_kf = T_w_kf[:3, :3]
    A = np.zeros((6, 6))
    A[:3, :3] = R_w_kf
    A[3:, 3:] = R_w_kf
    c_w = R_w_kf @ (-R_cur_kf.T @ t_cur_kf)
    J = np.eye(6)
    J[:3, 3:] = -skew(c_w)
    return J @ cov_w_kf @ J.T + A @ cov_rel @ A.T


def chain_world(cov_w_a: F64, p_w_a: F64, p_w_b: F64, cov_w_b_given_a: F64) -> F64:
    """First-order covariance of pose b from pose a's covariance and b's covariance relative to a, both
    in ``w`` (left perturbations): a's rotation error moves b by ``dtheta x (p_b - p_a)`` (lever arm,
    as in ``compose``). For a marginal of b computed with a held fixed (a bundle adjustment's gauge)."""
    J = np.eye(6)
    J[:3, 3:] = -skew(np.asarray(p_w_b, dtype=np.float64) - np.asarray(p_w_a, dtype=np.float64))
    return J @ cov_w_a @ J.T + cov_w_b_given_a


def given(cov_w_b: F64, cov_w_a: F64, p_w_a: F64, p_w_b: F64) -> F64:
    """The inverse of ``chain_world``: pose b's covariance given pose a's (the motion from a to b's),
    ``cov_w_b - J cov_w_a J^T`` with the lever-arm J, made positive semi-definite as ``floored`` does
    (a covariance that is not a pure chain, e.g. a window's marginal, can leave a negative direction)."""
    J = np.eye(6)
    J[:3, 3:] = -skew(np.asarray(p_w_b, dtype=np.float64) - np.asarray(p_w_a, dtype=np.float64))
    return floored(cov_w_b - J @ cov_w_a @ J.T)


def step(cov_rel: F64, prev_rel: F64 | None) -> F64:
    """Covariance of the motion between two consecutive frames from their covariances relative to the
    same keyframe (one frame), ``prev_rel`` None when the previous frame is the keyframe itself.

    The keyframe's own pose error cancels and the two relative ones add. They are not the one new
    tracking step's noise only, although KLT follows each point from the previous frame: each frame's
    pose is its own robust fit (its own inliers, its own RANSAC), so its error is nearly independent of
    the previous frame's (Monte Carlo in test/core/test_uncertainty.py: the sum predicts the spread of
    the rotation between frames within 0.7-1.3x; one tracking step's share is 1.4-2.2x too narrow).
    """
    return cov_rel.copy() if prev_rel is None else cov_rel + prev_rel


def translation_unknown(cov: F64, pos_var: float) -> F64:
    """``cov`` with its translation not measured: ``pos_var`` on the position diagonal, no correlation of
    the position with the rotation, which keeps its own block."""
    out = np.array(cov, dtype=np.float64)
    out[:3, :] = 0.0
    out[:, :3] = 0.0
    out[:3, :3] = np.eye(3) * pos_var
    return out


def shared_scale_part(c: F64, scale_rel_var: float) -> F64:
    """The part of a pose's covariance relative to a keyframe that its map's scale error makes: the
    centre ``c`` (offset from the keyframe) moves along itself by the relative scale error,
    ``scale_rel_var c c^T`` (6x6, position block). Consecutive frames against the same keyframe share it
    (the same map points' depths), so their step carries it as ``scale_rel_var step step^T``, not as the
    sum of both frames' parts (``step``)."""
    out = np.zeros((6, 6))
    out[:3, :3] = np.outer(c, c) * scale_rel_var
    return out


def twist_noise_ratio(track_noise_px: float, fb_factor: float, floor_px: float, pixel_noise_px: float) -> float:
    """How much of ``pixel_noise_px`` the image noise behind a twist's rotation is: ``fb_factor`` x the
    frame's measured tracking noise (``features.fb_noise_px``), at least ``floor_px``, never more than
    ``pixel_noise_px`` (1.0 when not measured or ``fb_factor`` is 0).

    The twist is the motion between two consecutive frames: its error is the tracking noise between
    them, which the frame measures. The pose relative to its keyframe takes the sum over the frames
    since the keyframe (``tracked_since_keyframe``). Forward-backward KLT is blind to LK's error
    from a patch deformed by perspective (it comes back the same way), so the factor is large: the
    angular twist errors of the bundled renders and KITTI are 4.8-15 x their forward-backward RMS.
    """
    if not (fb_factor > 0.0 and math.isfinite(track_noise_px) and pixel_noise_px > 0.0):
        return 1.0
    return min(max(fb_factor * track_noise_px, floor_px), pixel_noise_px) / pixel_noise_px


def track_step(cov_rel: F64, prev_rel: F64 | None, ratio: float, essential: bool) -> F64:
    """A twist's step covariance (``step``) at the image noise the frame's tracks show, ``ratio`` of the
    configured one (``twist_noise_ratio``).

    The rotation always takes it. The position too when this frame's pose is E's and the previous frame
    was against the same keyframe (``essential``): E is fitted to where the tracks are now, and the tracks
    carry their accumulated error from one frame to the next, so what is new between the two frames is
    one tracking step's noise. The covariance of an E pose at a few frames from its keyframe is mostly
    that accumulated part (E's direction at low parallax), counted whole in both frames: general_motion's
    linear twist NEES was 0.3 on such frames, 2.7 on the frames fitted to the map's points (PnP, right
    after a keyframe), whose covariance takes the map's points as exact and is about this frame's
    observations only: it keeps it."""
    cov = step(cov_rel, prev_rel)
    if essential:
        return cov * ratio**2
    return with_rotation_scaled(cov, ratio)


# E's covariance (``geometry.essential_pose_covariance``) takes ``sigma`` in both images. Tracks followed
# from the keyframe start where the keyframe's features are: their error is in the current image only,
# which gives the epipolar residuals half the variance (``tracked_since_keyframe``, ``one_image``).
ONE_IMAGE_SHARE = 0.5


def tracked_since_keyframe(cov_rel: F64, scale_part: F64, noise_sq: float, *, one_image: bool = False,
                           residual_sq: float = 0.0) -> F64:
    """The covariance of a pose relative to its keyframe (``cov_rel``, at ``pixel_noise_px``) for tracks
    that were followed from the keyframe frame by frame: ``noise_sq`` is the sum over those frames of
    each one's squared image noise as a share of ``pixel_noise_px`` (``twist_noise_ratio`` squared). The
    map's scale part (``shared_scale_part``: the spread of the map points' scales, not image noise) is
    kept as it is.

    KLT tracks carry their error from frame to frame, a random walk: what a keyframe step adds to the
    chain is the noise of its own frames, not a whole ``pixel_noise_px`` whatever their number. With one
    ``pixel_noise_px`` per step, a floor-facing camera with a keyframe every 2.3 frames claims 3.5x its
    rotation error in variance (NEES 0.29) while sequences with a keyframe every 6-10 frames are
    consistent.

    ``one_image``: ``cov_rel`` is E's, computed for ``pixel_noise_px`` in both images, while the tracks'
    error is in the current image only (they start at the keyframe's features): ``ONE_IMAGE_SHARE`` of
    it (Monte Carlo in test/core/test_uncertainty.py). Without it the frames posed by E claim 4-10x their
    rotation error relative to the keyframe in variance (NEES 0.23 on the ground-robot render, 0.10 on the
    held-out loop).
    ``residual_sq``: the noise E's own residuals show (``geometry.sampson_rms``, as a share of
    ``pixel_noise_px``, squared); the image noise part is at least that. The tracks' noise predicted
    frame by frame misses a frame whose tracks are worse than their forward-backward check says (the
    held-out loop: rotation NEES 4.9, 86 % inside 3 sigma, without it; 3.7 and 93 % with it).
    A PnP pose's covariance comes from its own residuals and does not take either."""
    share = ONE_IMAGE_SHARE if one_image else 1.0
    return (cov_rel - scale_part) * max(noise_sq * share, residual_sq) + scale_part


def with_rotation_scaled(cov: F64, ratio: float) -> F64:
    """``cov`` with its rotation's standard deviations scaled by ``ratio`` (correlations kept)."""
    if ratio == 1.0:
        return cov
    d = np.array([1.0, 1.0, 1.0, ratio, ratio, ratio])
    return cov * np.outer(d, d)


def floored(cov: F64) -> F64:
    """Symmetrize, make positive semi-definite and keep every variance strictly positive (a zero
    covariance claims certainty), as a consumer that inverts it (an EKF) needs.

    A matrix with a negative eigenvalue gets that eigenvalue's magnitude instead: the inconsistency
    that made it negative is as large as that, so the direction is not known better. (The windowed
    adjustment's marginal, put in place of the keyframe chain while the map's scale keeps its
    correlation with the old chain, gave -2e-4 beside 1.6 on moving_mover: position NEES -3600.) A
    positive semi-definite matrix is only symmetrized and floored, to the bit."""
    cov = 0.5 * (cov + cov.T)
    w, V = np.linalg.eigh(cov)
    if w[0] < 0.0:
        cov = (V * np.abs(w)) @ V.T
        cov = 0.5 * (cov + cov.T)
    d = np.arange(6)
    cov[d, d] = np.maximum(cov[d, d], 1e-9)
    return cov


def cover(a: F64, b: F64) -> F64:
    """A covariance at least as wide as ``a`` and as ``b`` in every direction (``x^T C x >= max(x^T a x,
    x^T b x)``): ``b`` whitened by ``a``'s Cholesky factor, its eigenvalues raised to at least 1, and
    coloured back. For two estimates of one uncertainty of which neither is known to be the right one.
    ``a`` must be positive definite (``floored``)."""
    L = np.linalg.cholesky(0.5 * (a + a.T))
    Li = np.linalg.inv(L)
    w, V = np.linalg.eigh(Li @ (0.5 * (b + b.T)) @ Li.T)
    out = L @ (V * np.maximum(w, 1.0)) @ V.T @ L.T
    covered: F64 = 0.5 * (out + out.T)
    return covered


def is_finite(*arrays: F64) -> bool:
    return all(bool(np.all(np.isfinite(a))) for a in arrays)
