"""The calibration's error in the pose covariance (``core.calibration_cov``, ``geometry.calibration_sensitivity``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from epi_vo.core.calibration_cov import CalibrationError
from epi_vo.core.geometry import calibration_sensitivity, refine_relative_pose

FX = 300.0


def _scene(seed: int, plane: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A keyframe and a camera 0.3 to its right and a little forward, turned 2 deg, viewing points 3-6 m away
    (on a tilted wall when ``plane``): the pose (R_cur_kf, t_cur_kf) and the exact normalised rays of both."""
    rng = np.random.default_rng(seed)
    n = 150
    xy = rng.uniform(-0.5, 0.5, (n, 2))
    depth = 4.0 + 0.5 * xy[:, 0] if plane else rng.uniform(3.0, 6.0, n)
    X = np.column_stack([xy * depth[:, None], depth])
    R = Rotation.from_rotvec(np.radians([0.5, -2.0, 0.3])).as_matrix()
    c = np.array([0.3, 0.02, 0.1])
    t = -R @ c
    Xc = X @ R.T + t
    return R, t, X[:, :2] / X[:, 2:3], Xc[:, :2] / Xc[:, 2:3]


def _through(x: np.ndarray, dc: np.ndarray) -> np.ndarray:
    """The normalised points a pipeline computes from exact rays ``x`` through a calibration off by ``dc``
    (focal relative, principal point x and y px, undeclared k1): the inverse of the first-order model of
    ``calibration_sensitivity`` (the pixels of the true camera, normalised with the declared one)."""
    e, dx, dy, k1 = dc
    xd = x * (1.0 + k1 * np.sum(x * x, axis=1, keepdims=True))  # the lens distorts the true ray
    return xd * (1.0 + e) + np.array([dx, dy]) / FX


@pytest.mark.parametrize("plane", [False, True])
@pytest.mark.parametrize("term", range(4))
def test_the_sensitivity_predicts_how_far_a_calibration_error_moves_the_fitted_pose(plane: bool, term: int) -> None:
    """Exact rays seen through a calibration off by one term (1 % focal, 2 px principal point, k1 0.03):
    the pose refitted to them (Sampson, from the true pose) moves as the sensitivity times the error says,
    in rotation and in the direction of travel, within 25 % of the shift (first order), while the shift
    itself is well above the refit's own precision."""
    R, t, x_kf, x_cur = _scene(4 + term, plane)
    dc = np.zeros(4)
    dc[term] = (0.01, 2.0, 2.0, 0.03)[term]
    o_kf, o_cur = _through(x_kf, dc), _through(x_cur, dc)
    scale = float(np.linalg.norm(t))
    S = calibration_sensitivity(R, t / scale, o_kf, o_cur, scale, FX)
    assert S is not None
    fit = refine_relative_pose(R, t / scale, o_kf, o_cur, iterations=50)
    assert fit is not None
    R_fit, t_fit = fit[0], fit[1]
    phi = Rotation.from_matrix(R_fit.T @ R).as_rotvec()  # R_kf_cur perturbed on the left, keyframe frame
    c_true, c_fit = -R.T @ t, -R_fit.T @ t_fit * scale
    shift = np.concatenate([c_fit - c_true, phi])
    predicted = -S @ dc  # S: the true pose less the one fitted through the error, per unit error
    assert np.linalg.norm(shift[3:]) > 1e-5 or np.linalg.norm(shift[:3]) > 1e-4 * scale
    np.testing.assert_allclose(predicted[3:], shift[3:], atol=0.25 * np.linalg.norm(shift[3:]) + 2e-6)
    across = c_fit - c_true - np.dot(c_fit - c_true, c_true) * c_true / scale**2
    pred_across = predicted[:3] - np.dot(predicted[:3], c_true) * c_true / scale**2
    np.testing.assert_allclose(pred_across, across, atol=0.25 * np.linalg.norm(across) + 1e-6 * scale)


def test_an_exact_calibration_adds_nothing_and_a_declared_one_grows_coherently_along_the_path() -> None:
    """With every sigma 0 the term is off (the bundled renders' exact CameraInfo). Declared, the same
    calibration error moves two identical keyframe steps alike: the second pose's position variance is
    more than the sum of two independent steps' (twice the first's), and it scales with the path when
    metres are established."""
    R, t, x_kf, x_cur = _scene(1, False)
    T0 = np.eye(4)
    exact = CalibrationError((0.0, 0.0, 0.0, 0.0)).tracked(0, T0, R, t, x_kf, x_cur, FX)
    assert not exact.cov().any()
    one = CalibrationError((0.01, 2.0, 2.0, 0.03)).tracked(0, T0, R, t, x_kf, x_cur, FX)
    T1 = np.eye(4)
    T1[:3, :3], T1[:3, 3] = R.T, -R.T @ t  # the first step's pose becomes the keyframe
    two = one.tracked(1, T1, R, t, x_kf, x_cur, FX)
    v1, v2 = np.trace(one.cov()[:3, :3]), np.trace(two.cov()[:3, :3])
    assert v1 > 0.0
    assert v2 > 3.0 * v1
    metric = two.rescaled(10.0)
    assert np.trace(metric.cov()[:3, :3]) == pytest.approx(100.0 * v2, rel=1e-9)
    assert np.trace(metric.cov()[3:, 3:]) == pytest.approx(np.trace(two.cov()[3:, 3:]), rel=1e-12)
