"""Pose covariance algebra (epi_vo.core.covariance) against numerical and Monte-Carlo propagation.

Perturbation conventions (those of ``compose``'s docstring and of the pipeline's 6x6 over (x, y, z,
rot_x, rot_y, rot_z)): the keyframe pose in the odometry frame is perturbed as ``p_kf + dp`` and
``exp(dtheta) R_w_kf`` (rotation about the odometry axes); the relative pose as the current camera
position in the keyframe frame ``c + dc`` and ``exp(dphi) R_kf_cur`` (rotation about the keyframe axes).
The result is the current position and the rotation error ``log(R_w_cur' R_w_cur^T)`` in the odometry frame.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from epi_vo.core import covariance as covm
from epi_vo.core.geometry import skew
from epi_vo.core.transforms import make_T


def _exp(w: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(w, dtype=np.float64).reshape(3, 1))
    return np.asarray(R)


def _log(R: np.ndarray) -> np.ndarray:
    return _log_batch(R[None])[0]  # (cv2.Rodrigues returns 0 for angles below ~1e-5 rad)


def _exp_batch(W: np.ndarray) -> np.ndarray:
    """(M, 3) rotation vectors -> (M, 3, 3) rotations (Rodrigues' formula, vectorised)."""
    theta = np.linalg.norm(W, axis=1)
    k = W / np.where(theta > 0, theta, 1.0)[:, None]
    Kx = np.zeros((W.shape[0], 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * Kx + (1.0 - c) * (Kx @ Kx)


def _log_batch(R: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations (angles well below pi) -> (M, 3) rotation vectors."""
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    f = np.where(theta > 1e-12, theta / (2.0 * np.sin(np.maximum(theta, 1e-12))), 0.5)
    return v * f[:, None]


class _Setup:
    """A keyframe pose and a relative motion with covariances; ``T_w_c = T_w_kf @ T_kf_cur``."""

    def __init__(self, seed: int, correlated: bool) -> None:
        rng = np.random.default_rng(seed)
        self.R_w_kf = _exp(rng.normal(0.0, 0.6, 3))
        self.p_kf = rng.normal(0.0, 3.0, 3)
        self.R_kf_cur = _exp(rng.normal(0.0, 0.2, 3))
        self.c_kf = np.array([1.5, -0.4, 2.0])  # current camera position in the keyframe frame
        self.cov_w_kf = self._random_cov(rng, 0.05, 0.01, correlated)
        self.cov_rel = self._random_cov(rng, 0.03, 0.004, correlated)

    @staticmethod
    def _random_cov(rng: np.random.Generator, pos_sigma: float, rot_sigma: float, correlated: bool) -> np.ndarray:
        L = np.diag([pos_sigma] * 3 + [rot_sigma] * 3) @ (np.eye(6) + 0.3 * rng.normal(size=(6, 6)))
        cov = L @ L.T
        if not correlated:  # the pipeline's case: no position-rotation cross terms
            cov[:3, 3:] = 0.0
            cov[3:, :3] = 0.0
        return cov

    @property
    def T_w_kf(self) -> np.ndarray:
        return make_T(self.R_w_kf, self.p_kf)

    @property
    def R_cur_kf(self) -> np.ndarray:
        return self.R_kf_cur.T

    @property
    def t_cur_kf(self) -> np.ndarray:
        return -self.R_kf_cur.T @ self.c_kf

    def composed(self) -> np.ndarray:
        return covm.compose(self.cov_w_kf, self.T_w_kf, self.cov_rel, self.t_cur_kf, self.R_cur_kf)

    def pose_w_cur(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Current pose (R_w_cur, p_w_cur) for the 12-vector perturbation (dp, dtheta, dc, dphi)."""
        R_w_kf = _exp(d[3:6]) @ self.R_w_kf
        R_kf_cur = _exp(d[9:12]) @ self.R_kf_cur
        return R_w_kf @ R_kf_cur, self.p_kf + d[0:3] + R_w_kf @ (self.c_kf + d[6:9])

    def jacobian(self, h: float = 1e-6) -> np.ndarray:
        R0, _ = self.pose_w_cur(np.zeros(12))
        J = np.zeros((6, 12))
        for i in range(12):
            d = np.zeros(12)
            d[i] = h
            Rp, pp = self.pose_w_cur(d)
            Rm, pm = self.pose_w_cur(-d)
            J[:3, i] = (pp - pm) / (2 * h)
            J[3:, i] = (_log(Rp @ R0.T) - _log(Rm @ R0.T)) / (2 * h)
        return J

    def first_order(self) -> np.ndarray:
        S = np.zeros((12, 12))
        S[:6, :6] = self.cov_w_kf
        S[6:, 6:] = self.cov_rel
        J = self.jacobian()
        return J @ S @ J.T

    def monte_carlo(self, n: int, seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        dk = rng.multivariate_normal(np.zeros(6), self.cov_w_kf, n)
        dr = rng.multivariate_normal(np.zeros(6), self.cov_rel, n)
        R_w_kf = _exp_batch(dk[:, 3:]) @ self.R_w_kf
        R_kf_cur = _exp_batch(dr[:, 3:]) @ self.R_kf_cur
        p = self.p_kf + dk[:, :3] + np.einsum("nij,nj->ni", R_w_kf, self.c_kf + dr[:, :3])
        R0, _ = self.pose_w_cur(np.zeros(12))
        rot = _log_batch(R_w_kf @ R_kf_cur @ R0.T)
        return np.cov(np.hstack([p, rot]).T)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compose_matches_first_order_propagation_on_the_position_and_rotation_blocks(seed: int) -> None:
    s = _Setup(seed, correlated=False)
    got, ref = s.composed(), s.first_order()
    np.testing.assert_allclose(got[:3, :3], ref[:3, :3], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(got[3:, 3:], ref[3:, 3:], rtol=1e-6, atol=1e-12)


def test_compose_agrees_with_monte_carlo_for_small_perturbations() -> None:
    s = _Setup(5, correlated=False)
    got, mc = s.composed(), s.monte_carlo(40_000, seed=11)
    # Sampling error of a variance with 40k samples is ~0.7 %; second-order effects are smaller still.
    np.testing.assert_allclose(np.diag(got), np.diag(mc), rtol=0.04)
    np.testing.assert_allclose(got[:3, :3], mc[:3, :3], atol=0.04 * np.max(np.diag(mc)[:3]))
    np.testing.assert_allclose(got[3:, 3:], mc[3:, 3:], atol=0.04 * np.max(np.diag(mc)[3:]))


def test_lever_arm_of_the_keyframe_rotation_moves_the_position() -> None:
    # Keyframe certain in position, uncertain only in yaw (about z); the camera 2 m ahead along x.
    cov_w_kf = np.diag([0.0, 0.0, 0.0, 0.0, 0.0, 0.01])
    R_cur_kf = np.eye(3)
    t_cur_kf = np.array([-2.0, 0.0, 0.0])  # camera at x = +2 in the keyframe frame
    cov = covm.compose(cov_w_kf, np.eye(4), np.zeros((6, 6)), t_cur_kf, R_cur_kf)
    # A yaw error d moves the camera by d x c = (0, 2 d, 0): variance 4 * 0.01 along y only.
    np.testing.assert_allclose(np.diag(cov), [0.0, 0.04, 0.0, 0.0, 0.0, 0.01], atol=1e-15)


def test_compose_rotates_the_relative_covariance_into_the_odometry_frame() -> None:
    R_w_kf = _exp([0.0, 0.0, math.pi / 2])  # keyframe x axis is odometry y
    cov_rel = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) * 1e-4
    cov = covm.compose(np.zeros((6, 6)), make_T(R_w_kf, [1.0, 2.0, 3.0]), cov_rel, np.zeros(3), np.eye(3))
    np.testing.assert_allclose(np.diag(cov), np.array([2.0, 1.0, 3.0, 5.0, 4.0, 6.0]) * 1e-4, atol=1e-15)
    np.testing.assert_allclose(cov, cov.T, atol=1e-18)


@pytest.mark.parametrize("correlated", [False, True])
def test_compose_matches_the_full_first_order_covariance(correlated: bool) -> None:
    s = _Setup(0, correlated=correlated)
    got, ref = s.composed(), s.first_order()
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-9)


def test_the_lever_arm_cross_term_is_not_negligible() -> None:
    """The position-rotation cross term the keyframe's rotation error induces (``-[c_w]x cov_rot``) is
    carried: dropping it leaves a visible difference from the full first-order covariance."""
    s = _Setup(0, correlated=False)
    got, ref = s.composed(), s.first_order()
    c_w = s.R_w_kf @ s.c_kf
    cross = -skew(c_w) @ s.cov_w_kf[3:, 3:]
    np.testing.assert_allclose(got[:3, 3:], ref[:3, 3:], rtol=1e-6, atol=1e-12)
    assert np.max(np.abs(cross)) > 1e-3 * np.max(np.abs(ref))


def test_rotation_var_and_block() -> None:
    assert covm.rotation_var(1.0, 500.0, 100) == pytest.approx(2.0 * (1.0 / 500.0) ** 2 / 100)
    assert covm.rotation_var(1.0, 500.0, 0) == covm.rotation_var(1.0, 500.0, 1)  # n floored at 1
    assert covm.rotation_var(2.0, 500.0, 50) == pytest.approx(4 * covm.rotation_var(1.0, 500.0, 50))
    np.testing.assert_array_equal(covm.block(0.5, 0.25), np.diag([0.5, 0.5, 0.5, 0.25, 0.25, 0.25]))


def test_floored_is_symmetric_with_a_positive_diagonal() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T
    cov[2, :] = cov[:, 2] = 0.0  # positive semi-definite, a zero variance
    before = cov.copy()
    out = covm.floored(cov)
    np.testing.assert_array_equal(cov, before)  # the input is not modified
    np.testing.assert_array_equal(out, out.T)
    assert out[2, 2] == 1e-9 and np.all(np.diag(out) > 0.0)
    off = ~np.eye(6, dtype=bool)
    np.testing.assert_array_equal(out[off], before[off])  # positive semi-definite: only floored


def test_floored_makes_a_covariance_positive_semi_definite() -> None:
    """A negative eigenvalue (an inconsistent update) becomes its magnitude: an EKF inverts what it gets,
    and a direction claimed below zero is not known better than that."""
    rng = np.random.default_rng(4)
    V, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    w = np.array([-2e-4, 1e-6, 0.02, 0.5, 1.0, 1.6])
    cov = (V * w) @ V.T
    out = covm.floored(cov)
    np.testing.assert_array_equal(out, out.T)
    got = np.linalg.eigvalsh(out)
    assert got[0] > 0.0
    np.testing.assert_allclose(np.sort(got), np.sort(np.abs(w)), rtol=1e-6, atol=1e-12)
    err = rng.normal(size=(200, 6))
    assert np.all(np.einsum("ki,ij,kj->k", err, np.linalg.inv(out), err) > 0.0)  # NEES never negative


def test_floored_keeps_a_valid_covariance() -> None:
    cov = covm.block(0.01, 1e-4)
    np.testing.assert_array_equal(covm.floored(cov), cov)


def test_is_finite() -> None:
    ok = np.eye(3)
    assert covm.is_finite(ok, np.zeros(3), np.eye(6))
    assert covm.is_finite()
    for bad in (math.nan, math.inf, -math.inf):
        v = np.zeros(3)
        v[1] = bad
        assert not covm.is_finite(ok, v)


def test_the_twist_noise_ratio_follows_the_measured_tracking_noise_within_its_bounds() -> None:
    # 8 x 0.05 px = 0.4 px of the configured 0.8
    assert covm.twist_noise_ratio(0.05, 8.0, 0.3, 0.8) == pytest.approx(0.5)
    assert covm.twist_noise_ratio(0.01, 8.0, 0.3, 0.8) == pytest.approx(0.3 / 0.8)  # floor
    assert covm.twist_noise_ratio(0.5, 8.0, 0.3, 0.8) == 1.0  # never above pixel_noise_px
    assert covm.twist_noise_ratio(math.nan, 8.0, 0.3, 0.8) == 1.0  # not measured (ORB)
    assert covm.twist_noise_ratio(0.05, 0.0, 0.3, 0.8) == 1.0  # switched off


def test_with_rotation_scaled_scales_the_rotation_and_keeps_the_correlations() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T
    got = covm.with_rotation_scaled(cov, 0.5)
    np.testing.assert_allclose(got[:3, :3], cov[:3, :3])
    np.testing.assert_allclose(got[3:, 3:], 0.25 * cov[3:, 3:])
    np.testing.assert_allclose(got[:3, 3:], 0.5 * cov[:3, 3:])
    corr = lambda c: c / np.sqrt(np.outer(np.diag(c), np.diag(c)))  # noqa: E731
    np.testing.assert_allclose(corr(got), corr(cov))
    assert covm.with_rotation_scaled(cov, 1.0) is cov


def _spd(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return A @ A.T + 0.1 * np.eye(6)


def test_cover_is_at_least_as_wide_as_both_in_every_direction() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = _spd(rng), _spd(rng)
        c = covm.cover(a, b)
        np.testing.assert_allclose(c, c.T)
        for x in rng.normal(size=(200, 6)):
            assert x @ c @ x >= max(x @ a @ x, x @ b @ x) * (1 - 1e-9)
        # and no wider than needed along a's and b's own worst directions: the two together
        assert np.trace(c) <= np.trace(a) + np.trace(b) + 1e-9


def test_cover_of_nested_covariances_is_the_wider_one() -> None:
    rng = np.random.default_rng(4)
    a = _spd(rng)
    np.testing.assert_allclose(covm.cover(a, 0.5 * a), a, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(covm.cover(a, 2.0 * a), 2.0 * a, rtol=1e-10, atol=1e-12)
    # wider along one axis only: that axis takes b's variance, the others keep a's
    a = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    b = np.diag([0.5, 8.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(covm.cover(a, b), np.diag([1.0, 8.0, 3.0, 4.0, 5.0, 6.0]), atol=1e-12)


def test_a_step_whose_translation_nothing_measured_keeps_only_its_rotation() -> None:
    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T
    out = covm.translation_unknown(cov, 1e4)
    np.testing.assert_array_equal(out[:3, :3], np.eye(3) * 1e4)
    np.testing.assert_array_equal(out[:3, 3:], 0.0)
    np.testing.assert_array_equal(out[3:, :3], 0.0)
    np.testing.assert_array_equal(out[3:, 3:], cov[3:, 3:])
    assert np.all(np.linalg.eigvalsh(out) > 0) and cov[0, 0] != 1e4  # its input is left as it was
