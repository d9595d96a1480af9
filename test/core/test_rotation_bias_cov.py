"""The rotation error the keyframe steps share, as the map measures it (``core.rotation_bias_cov``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from epi_vo.core.rotation_bias_cov import RotationBias, map_rotation_excess
from epi_vo.core.transforms import make_T

SIGMA = 1e-3  # normalised image noise of the map points' reprojections


def rotation_from_vec(v: np.ndarray) -> np.ndarray:
    return np.asarray(cv2.Rodrigues(np.asarray(v, dtype=np.float64))[0], dtype=np.float64)


def _scene(rng: np.random.Generator, n: int = 120) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Map points in the keyframe's frame and where a camera 0.2 units to the side sees them, with noise."""
    X = rng.uniform([-3.0, -2.0, 4.0], [3.0, 2.0, 12.0], (n, 3))
    R, t = np.eye(3), np.array([-0.2, 0.0, 0.0])
    Xc = X @ R.T + t
    xn = Xc[:, :2] / Xc[:, 2:] + rng.normal(0.0, SIGMA, (n, 2))
    return X, xn, R, t


def test_a_rotation_off_beyond_the_noise_is_measured_with_its_sign() -> None:
    """E's rotation 0.5 deg off about y, far beyond both estimates' noise: the excess points back to where the
    map's points put it, about as large."""
    X, xn, R, t = _scene(np.random.default_rng(1))
    off = np.radians(0.5)
    R_e = rotation_from_vec(np.array([0.0, off, 0.0])) @ R
    excess = map_rotation_excess(R_e, t, X, xn, SIGMA, np.eye(3) * np.radians(0.01) ** 2)
    assert excess is not None
    # phi perturbs R_kf_cur (the camera's orientation in the keyframe): E's R_cur_kf turned by +off about y
    # is the camera turned by -off, so the step back is +off about y.
    assert excess[1] == pytest.approx(off, rel=0.15)
    assert abs(excess[0]) < 0.1 * off and abs(excess[2]) < 0.1 * off


def test_a_disagreement_within_the_noise_is_none() -> None:
    """E at the true pose with a covariance wider than the map's noise: nothing systematic to take, on every
    draw."""
    rng = np.random.default_rng(2)
    for _ in range(20):
        X, xn, R, t = _scene(rng)
        excess = map_rotation_excess(R, t, X, xn, SIGMA, np.eye(3) * np.radians(0.2) ** 2)
        assert excess is not None and np.all(excess == 0.0)


def test_the_excess_is_shrunk_by_the_noise_it_could_be() -> None:
    """Off by 2 sigma of the two estimates' noise (squared length 4 on 3 dof): a quarter of its squared length
    is systematic."""
    X, xn, R, t = _scene(np.random.default_rng(3), n=400)
    xn = (X @ R.T + t)[:, :2] / (X @ R.T + t)[:, 2:]  # exact: the disagreement is E's offset alone
    s = np.radians(0.05)
    R_e = rotation_from_vec(np.array([0.0, 2.0 * s, 0.0])) @ R
    excess = map_rotation_excess(R_e, t, X, xn, 1e-9, np.eye(3) * s**2)
    assert excess is not None
    assert np.linalg.norm(excess) == pytest.approx(2.0 * s * np.sqrt(1.0 - 3.0 / 4.0), rel=0.05)


def test_no_map_pose_no_measurement() -> None:
    X, xn, R, t = _scene(np.random.default_rng(4), n=5)
    assert map_rotation_excess(R, t, X, xn, SIGMA, np.eye(3) * 1e-8) is None


def _walk(excesses: list[np.ndarray]) -> RotationBias:
    """Keyframe after keyframe straight ahead along z, each step 1 unit, each with its measured excess."""
    bias = RotationBias(True)
    T_w_kf = np.eye(4)
    step = np.array([0.0, 0.0, -1.0])  # t_cur_kf of a camera 1 unit ahead
    for i, e in enumerate(excesses):
        bias = bias.tracked(i, T_w_kf, np.eye(3), step, e)
        T_w_kf = T_w_kf @ make_T(np.eye(3), -step)
    return bias


def test_excesses_that_point_the_same_way_add_up_linearly_and_alternating_ones_cancel() -> None:
    b = np.array([0.0, 1e-3, 0.0])
    coherent = _walk([b] * 10).cov()
    assert coherent[4, 4] == pytest.approx((10 * 1e-3) ** 2)
    # the keyframes' shared rotation error moves the later positions through the lever arm (x, by yaw)
    assert coherent[0, 0] > 0.0 and coherent[1, 1] == pytest.approx(0.0) and coherent[2, 2] == pytest.approx(0.0)
    alternating = _walk([b, -b] * 5).cov()
    assert alternating[4, 4] == pytest.approx(0.0, abs=1e-18)
    assert alternating[0, 0] < 0.1 * coherent[0, 0]


def test_unmeasured_steps_carry_the_keyframe_and_off_adds_nothing() -> None:
    b = np.array([1e-3, 0.0, 0.0])
    carried = _walk([b, None, None]).cov()
    assert carried[3, 3] == pytest.approx(1e-6)
    off = RotationBias(False).tracked(0, np.eye(4), np.eye(3), np.array([0.0, 0.0, -1.0]), b)
    assert np.all(off.cov() == 0.0)
    metric = _walk([b] * 3).rescaled(2.0)
    assert metric.cov()[1, 1] == pytest.approx(4.0 * _walk([b] * 3).cov()[1, 1])
    assert metric.cov()[3, 3] == pytest.approx(_walk([b] * 3).cov()[3, 3])
