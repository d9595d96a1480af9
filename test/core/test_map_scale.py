"""The map's scale and the calibration's direction offset in the pose covariance (``core.map_scale``)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from epi_vo.core import scale as sc
from epi_vo.core.map_scale import DirectionOffset, MapScaleCovariance


def _established_floor(rel_std: float) -> sc.GroundPlaneScale:
    src = sc.GroundPlaneScale(filter=sc.ScaleFilter(0.01, var=rel_std**2), camera_height_m=1.0, max_tilt_deg=35.0,
                              inlier_ratio=0.04, min_points=8)  # established: a finite variance
    assert src.established
    return src


def test_a_metric_scale_error_lengthens_the_step_and_does_not_turn_it() -> None:
    """Monte Carlo: steps scaled by (1 + s), s ~ N(0, rel_std): the sample covariance of the position error
    is the term's, along the step; nothing across it (an isotropic term would claim the same variance across
    the step as well)."""
    rel = 0.02
    d = np.array([0.3, -0.1, 1.2])
    _, cov = MapScaleCovariance(0.01).keyframe_cov(_established_floor(rel), False, d)
    s = np.random.default_rng(3).normal(0.0, rel, 20000)
    errors = s[:, None] * d[None, :]
    np.testing.assert_allclose(np.cov(errors.T), cov, atol=0.03 * rel**2 * d @ d)
    across = np.cross(d, [0.0, 1.0, 0.0])
    assert across @ cov @ across == pytest.approx(0.0, abs=1e-15)
    assert d @ cov @ d / (d @ d) ** 2 == pytest.approx(rel**2, rel=1e-12)


def _path(n: int = 40) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A turning, climbing camera path: each keyframe's orientation and its step in that camera's frame."""
    rng = np.random.default_rng(7)
    Rs, cs = [], []
    R = np.eye(3)
    for _ in range(n):
        Rs.append(R.copy())
        cs.append(np.array([0.05, -0.02, 1.0]) * 0.5 + rng.normal(0.0, 0.05, 3))
        R = R @ Rotation.from_rotvec(rng.normal(0.0, 0.08, 3)).as_matrix()
    return Rs, cs


def test_the_direction_offset_predicts_the_spread_of_a_constant_turn_of_every_step() -> None:
    """Monte Carlo: every step's direction turned by the same small angles (phi_x, phi_y) about the camera's
    x and y axes, phi ~ N(0, sigma_px / fx): the sample covariance of the end position's error is what
    ``DirectionOffset.cov`` predicts (within the sampling error), and a pose half-way into a step counts
    that part of it too."""
    sigma_px, fx = 2.0, 500.0
    Rs, cs = _path()
    off = DirectionOffset(sigma_px)
    for R, c in zip(Rs[:-1], cs[:-1], strict=True):
        off = off.with_step(R @ c, R, fx)
    half = 0.5 * Rs[-1] @ cs[-1]
    predicted = off.cov(half, Rs[-1], fx)
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(4000):
        phi = np.zeros(3)
        phi[:2] = rng.normal(0.0, sigma_px / fx, 2)
        Q = Rotation.from_rotvec(phi).as_matrix()
        steps = [R @ (Q @ c - c) for R, c in zip(Rs[:-1], cs[:-1], strict=True)]
        errors.append(np.sum(steps, axis=0) + 0.5 * Rs[-1] @ (Q @ cs[-1] - cs[-1]))
    sample = np.cov(np.array(errors).T)
    scale = np.trace(predicted)
    assert scale > 0.0
    np.testing.assert_allclose(sample, predicted, atol=0.06 * scale)
    assert np.trace(DirectionOffset(0.0).cov(half, Rs[-1], fx)) == 0.0  # an exact calibration: nothing


def test_the_direction_offset_follows_the_paths_rescaling_and_stays_finite() -> None:
    Rs, cs = _path(5)
    off = DirectionOffset(1.0)
    for R, c in zip(Rs, cs, strict=True):
        off = off.with_step(R @ c, R, 700.0)
    before = off.cov(np.zeros(3), Rs[-1], 700.0)
    off = off.rescaled(1.5)
    np.testing.assert_allclose(off.cov(np.zeros(3), Rs[-1], 700.0), 2.25 * before)
    off = off.with_step(np.array([np.nan, 0.0, 1.0]), Rs[-1], 700.0)  # a defect upstream: not taken
    np.testing.assert_allclose(off.cov(np.full(3, np.inf), Rs[-1], 700.0), 2.25 * before)


def test_a_principal_point_off_by_dx_turns_the_direction_of_travel_by_dx_over_fx() -> None:
    """The premise of ``DirectionOffset``: exact pixels of a forward motion, undistorted with cx off by
    3 px, give E a direction of travel 3 / fx rad off about the camera's y axis (the rotation stays)."""
    fx, cx, cy, dx = 500.0, 319.5, 239.5, 3.0
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-4, 4, 300), rng.uniform(-3, 3, 300), rng.uniform(5, 20, 300)])
    R = Rotation.from_rotvec([0.0, 0.02, 0.0]).as_matrix()
    t = np.array([0.0, 0.0, -1.0])  # X_cur = R X_kf + t: the camera moves forward by 1
    K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]])

    def pixels(P: np.ndarray) -> np.ndarray:
        uv = (K @ P.T).T
        return uv[:, :2] / uv[:, 2:]

    uv0, uv1 = pixels(X), pixels((R @ X.T).T + t)
    K_wrong = K.copy()
    K_wrong[0, 2] += dx
    E, _ = cv2.findEssentialMat(uv0, uv1, K_wrong, method=cv2.RANSAC, prob=0.999, threshold=0.1)
    _, R_est, t_est, _ = cv2.recoverPose(E, uv0, uv1, K_wrong)
    c_true = -R.T @ t  # the camera centre's direction in the first camera: +z
    c_est = (-R_est.T @ t_est).ravel()
    turn = math.atan2(c_est[0], c_est[2]) - math.atan2(c_true[0], c_true[2])
    assert abs(abs(turn) - dx / fx) < 0.1 * dx / fx
    assert abs(c_est[1] / c_est[2]) < 0.1 * dx / fx  # not about the x axis
    rot_err = np.linalg.norm(Rotation.from_matrix(R_est @ R.T).as_rotvec())
    assert rot_err < 0.2 * dx / fx


def test_a_keyframe_step_returns_the_map_scale_after_it_and_leaves_the_one_before() -> None:
    """Frozen: asking twice from the same value gives the same answer; the VO-units scale variance grows by
    the drift per keyframe and its covariance with the position by the step."""
    q = 0.01**2
    vo = sc.VoUnitsScale(filter=sc.ScaleFilter(0.01))
    d = np.array([0.0, 0.0, 1.0])
    m, first = MapScaleCovariance(0.01).keyframe_cov(vo, True, d)  # a new map: its baseline is the unit
    assert np.all(first == 0.0) and m.var == q
    after, cov = m.keyframe_cov(vo, False, d)
    again, cov_again = m.keyframe_cov(vo, False, d)
    assert m.var == q and np.array_equal(m.cov_ps, d * q)  # unchanged
    np.testing.assert_array_equal(cov, cov_again)
    assert after.var == again.var == 2 * q and np.array_equal(after.cov_ps, 2 * q * d)
    np.testing.assert_allclose(cov, 3 * q * np.outer(d, d))  # d d^T var_s + c d^T + d c^T
