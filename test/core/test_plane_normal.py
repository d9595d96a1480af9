"""How well a homography's decompositions fix the plane's normal (core/geometry/plane_normal.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from epi_vo.core import geometry as geo

F = 500.0
NOISE_PX = 0.3


def _plane_pair(rng: np.random.Generator, step_m: float, noise_px: float = NOISE_PX, n: int = 120
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A wall 4 m ahead tilted 30 deg about y, the camera stepping ``step_m`` sideways and a little ahead:
    (xn_ref, xn_cur with noise, normalised; the true normal in the reference frame; R; t)."""
    th = math.radians(30.0)
    normal = np.array([math.sin(th), 0.0, -math.cos(th)])  # n . X = -d: the wall faces the camera
    d = 4.0 * math.cos(th)
    xn = rng.uniform(-0.5, 0.5, (n, 2))
    rays = np.column_stack([xn, np.ones(n)])
    X = rays * (-d / (rays @ normal))[:, None]
    R = cv2.Rodrigues(np.array([0.0, 0.01, 0.0]))[0]
    t = np.array([-step_m, 0.0, -0.2 * step_m])
    Xc = X @ R.T + t
    sigma = noise_px / F
    xn_ref = X[:, :2] / X[:, 2:3] + rng.normal(0.0, sigma, (n, 2))
    xn_cur = Xc[:, :2] / Xc[:, 2:3] + rng.normal(0.0, sigma, (n, 2))
    return xn_ref, xn_cur, normal, R, t


def _true_solution_normal(H_n: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The normal of the decomposition whose rotation is the true one (either sign)."""
    _, Rs, _, ns = cv2.decomposeHomographyMat(H_n, np.eye(3))
    k = int(np.argmin([np.linalg.norm(np.asarray(Ri) - R) for Ri in Rs]))
    n = np.asarray(ns[k], dtype=np.float64).reshape(3)
    return n / np.linalg.norm(n)


@pytest.mark.parametrize("step_m", [0.1, 0.4])
def test_the_normals_propagated_uncertainty_matches_its_scatter_over_noise_draws(step_m: float) -> None:
    """Over 60 noise draws the true decomposition's normal scatters as H's covariance at the residuals' noise
    says (per axis, within a quarter), and both shrink as the baseline grows."""
    rng = np.random.default_rng(7)
    normals, sigmas, noises = [], [], []
    for _ in range(60):
        xn_ref, xn_cur, _, R, _ = _plane_pair(rng, step_m)
        H_n, _ = cv2.findHomography(xn_ref, xn_cur, 0)
        fit = geo.homography_covariance(H_n, xn_ref, xn_cur)
        assert fit is not None
        n = _true_solution_normal(H_n, R)
        C = geo.normal_covariance(H_n, fit[0], n)
        assert C is not None
        assert abs(float(n @ C @ n)) < 1e-6 * float(np.trace(C))  # no variance along the normal itself
        normals.append(n)
        sigmas.append(math.sqrt(float(np.trace(C)) / 2.0))
        noises.append(fit[1] * F)
    N = np.array(normals)
    N *= np.sign(N @ N[0])[:, None]
    mean = N.mean(axis=0) / np.linalg.norm(N.mean(axis=0))
    scatter = math.sqrt(float(np.mean(1.0 - (N @ mean) ** 2)) / 2.0)  # rad per axis
    assert float(np.median(noises)) == pytest.approx(NOISE_PX, rel=0.1)
    assert float(np.median(sigmas)) == pytest.approx(scatter, rel=0.25)
    assert scatter < (math.radians(1.5) if step_m == 0.1 else math.radians(0.4))


def test_the_normals_worst_deviation_shrinks_as_the_baseline_grows() -> None:
    """``normal_sigma_deg``: the worst axis of the worst of the given normals, in degrees; four times the
    baseline fixes them about four times better; None when H's covariance cannot be had."""
    rng = np.random.default_rng(3)
    sig = []
    for step_m in (0.05, 0.2):
        xn_ref, xn_cur, _, _, _ = _plane_pair(rng, step_m)
        H_n, _ = cv2.findHomography(xn_ref, xn_cur, 0)
        _, _, _, ns = cv2.decomposeHomographyMat(H_n, np.eye(3))
        normals = [np.asarray(n, dtype=np.float64).reshape(3) / np.linalg.norm(n) for n in ns[::2]]
        s = geo.normal_sigma_deg(H_n, xn_ref, xn_cur, normals)
        assert s is not None
        fit = geo.homography_covariance(H_n, xn_ref, xn_cur)
        assert fit is not None
        each = [math.degrees(math.sqrt(float(np.linalg.eigvalsh(geo.normal_covariance(H_n, fit[0], n))[-1])))
                for n in normals]
        assert s == pytest.approx(max(each))
        sig.append(s)
    assert 2.5 < sig[0] / sig[1] < 6.0
    assert geo.normal_sigma_deg(H_n, xn_ref[:4], xn_cur[:4], normals) is None


def test_a_homography_the_points_do_not_fix_has_no_covariance() -> None:
    """Fewer than five correspondences, or all of them on one line, fix no homography: None, not a raise."""
    rng = np.random.default_rng(1)
    xn_ref, xn_cur, _, _, _ = _plane_pair(rng, 0.2)
    H_n, _ = cv2.findHomography(xn_ref, xn_cur, 0)
    assert geo.homography_covariance(H_n, xn_ref[:4], xn_cur[:4]) is None
    line = np.column_stack([np.linspace(-0.4, 0.4, 20), np.zeros(20)])
    assert geo.homography_covariance(H_n, line, line + 0.01) is None
