"""Tests for epi_vo.core.geometry on seeded synthetic two-view scenes (fixtures in conftest.py).

Ground truth follows the module's conventions: X_cur = R_cur_ref @ X_ref + t_cur_ref, E = [t]x R,
H maps reference pixels to current pixels. Errors are compared against known answers built with numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from epi_vo.core import geometry as geo

if TYPE_CHECKING:
    from conftest import TwoViewScene

SceneBuilder = Callable[..., "TwoViewScene"]


def _rotation(rvec: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))
    return R


def _rot_err_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    cos = (np.trace(R_a @ R_b.T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


def _xn_of(X: np.ndarray) -> np.ndarray:
    """(N, 3) camera points -> (N, 2) normalized coordinates."""
    return X[:, :2] / X[:, 2:3]


def _true_F(scene: TwoViewScene) -> np.ndarray:
    return geo.fundamental_from_essential(geo.essential_from_pose(scene.R_cur_ref, scene.t_cur_ref), scene.K)


# --- E, F, epipolar distances --------------------------------------------------------------------


def test_skew_is_the_cross_product_matrix() -> None:
    t = np.array([0.3, -1.2, 2.5])
    v = np.array([-0.7, 0.4, 1.1])
    np.testing.assert_allclose(geo.skew(t) @ v, np.cross(t, v), atol=1e-15)
    np.testing.assert_array_equal(geo.skew(t), -geo.skew(t).T)


def test_essential_from_pose_known_answer(general_scene: TwoViewScene) -> None:
    s = general_scene
    E = geo.essential_from_pose(s.R_cur_ref, s.t_cur_ref)
    np.testing.assert_allclose(E, geo.skew(s.t_cur_ref) @ s.R_cur_ref, atol=1e-15)
    # An essential matrix has two equal singular values |t| and a zero one (H&Z result 9.18).
    sv = np.linalg.svd(E, compute_uv=False)
    t_norm = np.linalg.norm(s.t_cur_ref)
    np.testing.assert_allclose(sv, [t_norm, t_norm, 0.0], atol=1e-12)
    # The epipolar constraint xn_cur^T E xn_ref = 0 on exact correspondences.
    x_ref = geo.homogeneous(_xn_of(s.X_ref))
    x_cur = geo.homogeneous(_xn_of(s.X_cur))
    assert np.max(np.abs(np.einsum("ij,jk,ik->i", x_cur, E, x_ref))) < 1e-12


def test_fundamental_from_essential_epipoles(general_scene: TwoViewScene) -> None:
    """F e_ref = 0 and F^T e_cur = 0, with e the image of the other camera's centre (H&Z 9.2.4)."""
    s = general_scene
    F = _true_F(s)
    C_cur_in_ref = -s.R_cur_ref.T @ s.t_cur_ref
    e_ref = s.K @ C_cur_in_ref
    e_cur = s.K @ s.t_cur_ref  # image of the reference centre: K (R 0 + t)
    assert np.linalg.norm(F @ e_ref) < 1e-12 * np.linalg.norm(F) * np.linalg.norm(e_ref)
    assert np.linalg.norm(F.T @ e_cur) < 1e-12 * np.linalg.norm(F) * np.linalg.norm(e_cur)
    assert np.linalg.matrix_rank(F, tol=1e-10 * np.linalg.norm(F)) == 2


def test_exact_correspondences_have_zero_epipolar_error(general_scene: TwoViewScene) -> None:
    s = general_scene
    F = _true_F(s)
    d_cur, d_ref = geo.epipolar_distances_sq(F, s.uv_ref, s.uv_cur)
    sampson = geo.sampson_distance_sq(F, s.uv_ref, s.uv_cur)
    assert d_cur.shape == d_ref.shape == sampson.shape == (s.n,)
    assert np.max(d_cur) < 1e-10
    assert np.max(d_ref) < 1e-10
    assert np.max(sampson) < 1e-10


def test_point_displaced_off_its_epipolar_line(general_scene: TwoViewScene) -> None:
    """Moving the current point by d px along the line normal puts it exactly d px from the line."""
    s = general_scene
    F = _true_F(s)
    d = 2.5
    l_cur = geo.homogeneous(s.uv_ref) @ F.T
    normal = l_cur[:, :2] / np.linalg.norm(l_cur[:, :2], axis=1, keepdims=True)
    uv_moved = s.uv_cur + d * normal
    d_cur, d_ref = geo.epipolar_distances_sq(F, s.uv_ref, uv_moved)
    np.testing.assert_allclose(np.sqrt(d_cur), d, atol=1e-6)
    # The reference point did not move, but the line of the moved point did: also ~d px.
    assert np.all((d_ref > 0.5 * d**2) & (d_ref < 2.0 * d**2))
    sampson = geo.sampson_distance_sq(F, s.uv_ref, uv_moved)
    # Sampson error splits the correction over both images: d_cur d_ref / (d_cur + d_ref), ~d^2/2.
    np.testing.assert_allclose(sampson, d_cur * d_ref / (d_cur + d_ref), rtol=1e-9)
    assert np.all((sampson > 0.3 * d**2) & (sampson < 0.7 * d**2))
    assert np.median(sampson) == pytest.approx(d**2 / 2.0, rel=0.1)


def test_epipolar_distances_point_at_epipole_is_finite() -> None:
    """Degenerate: the reference point is the epipole, F x_ref = 0 exactly (no epipolar line)."""
    F = geo.skew(np.array([0.0, 0.0, 1.0]))  # null vector (0, 0, 1): the pixel (0, 0)
    uv_ref = np.array([[0.0, 0.0], [10.0, 5.0]])
    uv_cur = np.array([[3.0, 4.0], [10.0, 5.0]])
    with np.errstate(all="raise"):
        d_cur, d_ref = geo.epipolar_distances_sq(F, uv_ref, uv_cur)
        sampson = geo.sampson_distance_sq(F, uv_ref, uv_cur)
    np.testing.assert_array_equal(d_cur, [0.0, 0.0])
    np.testing.assert_array_equal(d_ref, [0.0, 0.0])
    np.testing.assert_array_equal(sampson, [0.0, 0.0])


# --- homography transfer error ---------------------------------------------------------------------


@pytest.mark.parametrize("scene_name", ["planar_scene", "rotation_scene"])
def test_exact_homography_has_zero_transfer_error(scene_name: str, request: pytest.FixtureRequest) -> None:
    s: TwoViewScene = request.getfixturevalue(scene_name)
    assert s.H_true is not None
    e_cur, e_ref = geo.transfer_errors_sq(s.H_true, s.uv_ref, s.uv_cur)
    assert e_cur.shape == e_ref.shape == (s.n,)
    assert np.max(e_cur) < 1e-10
    assert np.max(e_ref) < 1e-10


def test_transfer_error_of_a_shifted_point(planar_scene: TwoViewScene) -> None:
    s = planar_scene
    assert s.H_true is not None
    uv_cur = s.uv_cur.copy()
    uv_cur[7] += [0.0, 3.0]
    e_cur, e_ref = geo.transfer_errors_sq(s.H_true, s.uv_ref, uv_cur)
    assert e_cur[7] == pytest.approx(9.0, abs=1e-9)
    assert 9.0 * 0.5 < e_ref[7] < 9.0 * 2.0  # H^-1 maps the 3 px back with its local scale
    assert np.max(np.delete(e_cur, 7)) < 1e-10


def test_transfer_error_known_answer_translation_homography() -> None:
    H = np.array([[1.0, 0.0, 5.0], [0.0, 1.0, -2.0], [0.0, 0.0, 1.0]])
    uv_ref = np.array([[100.0, 50.0], [300.0, 200.0]])
    uv_cur = uv_ref + np.array([5.0, -2.0])
    uv_cur[1] += [3.0, 0.0]
    e_cur, e_ref = geo.transfer_errors_sq(H, uv_ref, uv_cur)
    np.testing.assert_allclose(e_cur, [0.0, 9.0], atol=1e-12)
    np.testing.assert_allclose(e_ref, [0.0, 9.0], atol=1e-12)


def test_transfer_errors_degenerate_homographies() -> None:
    uv = np.array([[1.0, 5.0], [2.0, 3.0]])
    # The line u = 1 is sent to infinity by this (invertible) H.
    H_inf = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, -1.0]])
    e_cur, _ = geo.transfer_errors_sq(H_inf, uv, uv)
    assert e_cur[0] == np.inf
    assert np.isfinite(e_cur[1])
    # A singular H has no inverse: every error is infinite, no exception.
    H_sing = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    e_cur, e_ref = geo.transfer_errors_sq(H_sing, uv, uv)
    np.testing.assert_array_equal(e_cur, [np.inf, np.inf])
    np.testing.assert_array_equal(e_ref, [np.inf, np.inf])


# --- ORB-SLAM scoring and model selection ------------------------------------------------------------


def test_scores_of_exact_models_known_answer(planar_scene: TwoViewScene) -> None:
    """Noise-free planar points satisfy both exact models: every point scores CHI2_2DOF per image."""
    s = planar_scene
    assert s.H_true is not None
    full = 2.0 * geo.CHI2_2DOF * s.n
    score_f, mask_f = geo.score_fundamental(_true_F(s), s.uv_ref, s.uv_cur, sigma_px=1.0)
    score_h, mask_h = geo.score_homography(s.H_true, s.uv_ref, s.uv_cur, sigma_px=1.0)
    assert score_f == pytest.approx(full, abs=1e-6)
    assert score_h == pytest.approx(full, abs=1e-6)
    assert mask_f.all() and mask_h.all()
    assert geo.rh_ratio(score_h, score_f) == pytest.approx(0.5, abs=1e-12)


def test_score_homography_gate_known_answer() -> None:
    H = np.array([[1.0, 0.0, 5.0], [0.0, 1.0, -2.0], [0.0, 0.0, 1.0]])
    uv_ref = np.array([[100.0, 50.0], [300.0, 200.0], [50.0, 400.0]])
    uv_cur = uv_ref + np.array([5.0, -2.0])
    uv_cur[1] += [2.0, 0.0]  # chi2 = 4 < 5.991: inlier, scores 5.991 - 4 in each image
    uv_cur[2] += [0.0, 3.0]  # chi2 = 9 > 5.991: outlier, scores nothing
    score, mask = geo.score_homography(H, uv_ref, uv_cur, sigma_px=1.0)
    assert score == pytest.approx(2 * geo.CHI2_2DOF + 2 * (geo.CHI2_2DOF - 4.0), abs=1e-9)
    np.testing.assert_array_equal(mask, [True, True, False])
    # sigma scales the chi-square: with sigma 2 px the 3 px point passes (9 / 4 < 5.991).
    _, mask2 = geo.score_homography(H, uv_ref, uv_cur, sigma_px=2.0)
    np.testing.assert_array_equal(mask2, [True, True, True])


def test_score_fundamental_gate_known_answer(general_scene: TwoViewScene) -> None:
    s = general_scene
    F = _true_F(s)
    l_cur = geo.homogeneous(s.uv_ref[:1]) @ F.T
    uv_cur = s.uv_cur.copy()
    uv_cur[0] += 3.0 * l_cur[0, :2] / np.linalg.norm(l_cur[0, :2])  # chi2 = 9 > 3.841 in the current image
    score, mask = geo.score_fundamental(F, s.uv_ref, uv_cur, sigma_px=1.0)
    _, d_ref = geo.epipolar_distances_sq(F, s.uv_ref[:1], uv_cur[:1])
    ref_term = geo.CHI2_2DOF - d_ref[0] if d_ref[0] <= geo.CHI2_1DOF else 0.0
    assert score == pytest.approx(2 * geo.CHI2_2DOF * (s.n - 1) + ref_term, abs=1e-6)
    assert not mask[0]
    assert mask[1:].all()


def test_rh_ratio_known_values() -> None:
    assert geo.rh_ratio(3.0, 1.0) == 0.75
    assert geo.rh_ratio(0.0, 5.0) == 0.0
    assert geo.rh_ratio(0.0, 0.0) == 0.5  # neither model explains anything


def _rh_of_estimated_models(s: TwoViewScene) -> float:
    E, _ = geo.estimate_essential(s.uv_ref_obs, s.uv_cur_obs, s.K)
    H, _ = geo.estimate_homography(s.uv_ref_obs, s.uv_cur_obs)
    assert E is not None and H is not None
    score_e, _ = geo.score_fundamental(geo.fundamental_from_essential(E, s.K), s.uv_ref_obs, s.uv_cur_obs, 1.0)
    score_h, _ = geo.score_homography(H, s.uv_ref_obs, s.uv_cur_obs, 1.0)
    return geo.rh_ratio(score_h, score_e)


def test_model_selection_general_scene_prefers_essential(general_scene: TwoViewScene) -> None:
    assert _rh_of_estimated_models(general_scene) < 0.45


@pytest.mark.parametrize("scene_name", ["planar_scene", "rotation_scene"])
def test_model_selection_planar_or_rotation_prefers_homography(scene_name: str,
                                                                request: pytest.FixtureRequest) -> None:
    assert _rh_of_estimated_models(request.getfixturevalue(scene_name)) > 0.45


# --- essential matrix estimation and pose recovery ---------------------------------------------------


# Legacy RANSAC and LMedS return the best minimal-sample model without local optimisation: on this
# scene they are ~0.35 deg / ~2.5 deg off, the USAC estimators ~0.05 deg / ~0.3 deg.
@pytest.mark.parametrize(("method", "max_rot_deg", "max_dir_deg"), [
    ("magsac", 0.2, 2.0), ("usac_default", 0.2, 2.0), ("usac_accurate", 0.2, 2.0), ("usac_fast", 0.2, 2.0),
    ("ransac", 1.0, 5.0), ("lmeds", 1.0, 5.0),
])
def test_essential_and_pose_with_outliers(general_scene_outliers: TwoViewScene, method: str, max_rot_deg: float,
                                          max_dir_deg: float) -> None:
    s = general_scene_outliers
    E, inliers = geo.estimate_essential(s.uv_ref_obs, s.uv_cur_obs, s.K, method=method)
    assert E is not None
    assert E.shape == (3, 3) and inliers.shape == (s.n,) and inliers.dtype == bool
    R, t, mask = geo.recover_pose(E, s.uv_ref_obs, s.uv_cur_obs, s.K, inliers)
    assert _rot_err_deg(R, s.R_cur_ref) < max_rot_deg
    assert np.linalg.norm(t) == pytest.approx(1.0, abs=1e-9)
    assert _angle_deg(t, s.t_cur_ref) < max_dir_deg
    n_out = int(np.count_nonzero(s.is_outlier))
    assert np.count_nonzero(mask & s.is_outlier) <= 0.1 * n_out
    assert np.count_nonzero(mask & ~s.is_outlier) >= 0.9 * (s.n - n_out)
    assert not np.any(mask & ~inliers)  # cheirality only removes points from the given inliers


@pytest.mark.parametrize("kind", ["general", "planar"])
def test_recover_pose_picks_what_opencv_recover_pose_picks(two_view_scene: Callable[..., TwoViewScene],
                                                           kind: str) -> None:
    """The cheirality vote is done in numpy (0.35 instead of 0.87 ms a frame); it must choose exactly the
    candidate cv2.recoverPose chooses from the same (at most 100) inliers, with 20 % outliers."""
    for seed in range(12):
        s = two_view_scene(kind, seed=seed, n_points=180, outlier_ratio=0.2)
        E, mask = cv2.findEssentialMat(s.uv_ref_obs, s.uv_cur_obs, s.K, cv2.RANSAC, 0.999, 1.0)
        assert E is not None and E.shape == (3, 3)
        inliers = mask.ravel() > 0
        R, t, _ = geo.recover_pose(E, s.uv_ref_obs, s.uv_cur_obs, s.K, inliers)
        idx = np.flatnonzero(inliers)
        idx = idx[np.linspace(0, idx.size - 1, min(100, idx.size)).astype(np.int64)]
        out = cv2.recoverPose(E, s.uv_ref_obs[idx], s.uv_cur_obs[idx], cameraMatrix=s.K, distanceThresh=1.0e7,
                              mask=np.ones((idx.size, 1), np.uint8))
        np.testing.assert_array_equal(R, out[1])
        np.testing.assert_array_equal(t, out[2].ravel())


def test_recover_pose_keeps_the_given_mask(general_scene: TwoViewScene) -> None:
    s = general_scene
    E = geo.essential_from_pose(s.R_cur_ref, s.t_cur_ref)
    _, _, mask = geo.recover_pose(E, s.uv_ref, s.uv_cur, s.K, np.zeros(s.n, dtype=bool))
    assert not mask.any()
    R, t, mask = geo.recover_pose(E, s.uv_ref, s.uv_cur, s.K, np.ones(s.n, dtype=bool))
    assert mask.all()
    assert _rot_err_deg(R, s.R_cur_ref) < 1e-6
    assert _angle_deg(t, s.t_cur_ref) < 1e-6


def test_recover_pose_keeps_points_far_beyond_50_baselines(general_scene: TwoViewScene) -> None:
    """Short video baselines: depths of 80-300 baselines are still in front of both cameras."""
    s = general_scene
    t_short = s.t_cur_ref / np.linalg.norm(s.t_cur_ref) * 0.05
    X_cur = s.X_ref @ s.R_cur_ref.T + t_short
    assert np.min(s.X_ref[:, 2]) / 0.05 > 50.0
    uv_cur = X_cur @ s.K.T
    uv_cur = uv_cur[:, :2] / uv_cur[:, 2:3]
    E = geo.essential_from_pose(s.R_cur_ref, t_short)
    R, t, mask = geo.recover_pose(E, s.uv_ref, uv_cur, s.K, np.ones(s.n, dtype=bool))
    assert mask.all()
    assert _rot_err_deg(R, s.R_cur_ref) < 1e-6
    assert _angle_deg(t, t_short) < 1e-4


@pytest.mark.parametrize("n", [0, 1, 4])
def test_estimate_essential_too_few_points(general_scene: TwoViewScene, n: int) -> None:
    E, mask = geo.estimate_essential(general_scene.uv_ref_obs[:n], general_scene.uv_cur_obs[:n], general_scene.K)
    assert E is None
    assert mask.shape == (n,) and mask.dtype == bool and not mask.any()


def test_estimate_essential_identical_points_does_not_raise() -> None:
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    same = np.tile([[300.0, 200.0]], (30, 1))
    for uv_cur in (same, same + np.array([4.0, -1.0])):
        E, mask = geo.estimate_essential(same, uv_cur, K)
        assert mask.shape == (30,)
        if E is not None:
            assert E.shape == (3, 3) and np.all(np.isfinite(E))
        else:
            assert not mask.any()


def test_estimate_essential_unknown_method(general_scene: TwoViewScene) -> None:
    s = general_scene
    with pytest.raises(KeyError, match="bogus"):
        geo.estimate_essential(s.uv_ref_obs, s.uv_cur_obs, s.K, method="bogus")


# --- homography estimation and decomposition ---------------------------------------------------------


def test_rotation_from_estimated_homography(rotation_scene: TwoViewScene) -> None:
    s = rotation_scene
    H, mask = geo.estimate_homography(s.uv_ref_obs, s.uv_cur_obs)
    assert H is not None
    assert mask.sum() >= 0.85 * s.n  # 1 px gate on ~0.4 px per-axis transfer noise keeps ~94 %
    R = geo.rotation_from_homography(H, s.K)
    assert _rot_err_deg(R, s.R_cur_ref) < 0.1


def test_rotation_from_homography_known_answer_any_scale(rotation_scene: TwoViewScene) -> None:
    s = rotation_scene
    assert s.H_true is not None
    for scale in (1.0, 3.7, -2.5):  # H is defined up to scale, including its sign
        R = geo.rotation_from_homography(scale * s.H_true, s.K)
        np.testing.assert_allclose(R, s.R_cur_ref, atol=1e-12)


@pytest.mark.parametrize("focal_scale", [0.8, 0.9, 1.0, 1.1, 1.25])
def test_focal_for_rotation_finds_the_focal_length_under_which_h_is_a_rotation(
        rotation_scene: TwoViewScene, focal_scale: float) -> None:
    """A rotating camera's exact H against a calibration whose focal length is off: the algebraic fit
    gives the true focal length to 1e-9; from the noisy points' H (0.3 px) it is biased by ~2 %, and the
    fit of the rotation with the focal length on the inliers brings it within 1.5 % (what a 4.7 deg rotation
    seen at 0.3 px determines), where the rotation is the
    true one and the rays line up to the noise."""
    s = rotation_scene
    assert s.H_true is not None
    K = np.array(s.K, dtype=np.float64)
    K[:2, :2] *= focal_scale
    f_true = float(s.K[0, 0])
    f = geo.focal_for_rotation(-2.0 * s.H_true, K)  # any scale, any sign
    assert f == pytest.approx(f_true, rel=1e-9)
    H, mask = geo.estimate_homography(s.uv_ref_obs, s.uv_cur_obs)
    assert H is not None
    f0 = geo.focal_for_rotation(H, K)
    assert f0 is not None and f0 == pytest.approx(f_true, rel=0.05)
    K0 = K.copy()
    K0[:2, :2] *= f0 / K[0, 0]
    xn_ref, xn_cur = _normalized(s.uv_ref_obs[mask], K), _normalized(s.uv_cur_obs[mask], K)
    fit = geo.rotation_under_camera_error(geo.rotation_from_homography(H, K0), f0 / K[0, 0], xn_ref, xn_cur,
                                          0.3 / K[0, 0], radial=False)
    assert fit is not None and fit.k1 == 0.0
    assert abs(fit.ratio * K[0, 0] / f_true - 1.0) < 0.015
    assert _rot_err_deg(fit.R, s.R_cur_ref) < 0.08  # ~2 sigma of a rotation from 200 rays at 0.3 px
    assert fit.parallax_deg < 0.1


def _normalized(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (uv - K[:2, 2]) / K[0, 0]


def _rotation_through_a_lens(deg: float, k1: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                          np.ndarray]:
    """A camera (f 300 px, 320x240) panning by ``deg`` about a tilted axis, its lens bending the image by the
    radial distortion ``k1`` that the calibration (K, no distortion) does not declare, 0.3 px noise: the
    calibration's normalised coordinates of the two views, the rotation and K."""
    rng = np.random.default_rng(seed)
    K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
    rays = np.column_stack([rng.uniform(-0.55, 0.55, 200), rng.uniform(-0.42, 0.42, 200), np.ones(200)])
    X = rays * rng.uniform(4.0, 15.0, 200)[:, None]
    axis = np.array([0.1, 1.0, 0.05]) / np.linalg.norm([0.1, 1.0, 0.05])
    R = cv2.Rodrigues(axis * math.radians(deg))[0]

    def seen(Y: np.ndarray) -> np.ndarray:
        x = Y[:, :2] / Y[:, 2:]
        return x * (1.0 + k1 * np.sum(x * x, axis=1))[:, None] + rng.normal(0.0, 0.3 / 300.0, x.shape)

    return seen(X), seen(X @ R.T), R, K


def test_a_rotation_through_an_undeclared_lens_distortion_lines_up_once_the_lens_is_fitted() -> None:
    """A 12 deg pan through a lens with k1 0.05 that the calibration does not declare: under the calibration
    the rays leave 'parallax' well above the 0.15 deg a rotation may leave; fitted to the points with the
    focal length, and better with the radial distortion too, they line up to the noise (0.3 px: ~0.08 deg),
    and the rotation is the true one within a few tenths of a degree (a pan trades against the focal length
    and k1)."""
    xn_ref, xn_cur, R, K = _rotation_through_a_lens(12.0, 0.05)
    uv_ref, uv_cur = xn_ref * 300.0 + K[:2, 2], xn_cur * 300.0 + K[:2, 2]
    H, _ = geo.estimate_homography(uv_ref, uv_cur)
    assert H is not None
    assert float(np.median(geo.parallax_deg(geo.rotation_from_homography(H, K), xn_ref, xn_cur))) > 0.3
    f0 = geo.focal_for_rotation(H, K)
    assert f0 is not None
    K0 = K.copy()
    K0[:2, :2] *= f0 / K[0, 0]
    R0 = geo.rotation_from_homography(H, K0)
    focal_only = geo.rotation_under_camera_error(R0, f0 / K[0, 0], xn_ref, xn_cur, 0.3 / 300.0, radial=False)
    assert focal_only is not None and focal_only.parallax_deg < 0.15
    fit = geo.rotation_under_camera_error(R0, f0 / K[0, 0], xn_ref, xn_cur, 0.3 / 300.0)
    assert fit is not None and fit.parallax_deg < min(0.1, focal_only.parallax_deg)
    assert fit.k1 > 0.02  # the lens's distortion, traded against the focal length
    assert _rot_err_deg(fit.R, R) < min(0.6, _rot_err_deg(focal_only.R, R))
    # A still camera's rays line up under any camera; a translation's parallax is no camera's.
    assert geo.rotation_under_camera_error(np.eye(3), 1.0, xn_ref[:5], xn_ref[:5], 0.3 / 300.0) is None


def test_focal_for_rotation_needs_a_rotation_that_constrains_it(planar_scene: TwoViewScene) -> None:
    """No focal length from a roll about the optical axis, from an image shift (a translation across a
    plane facing the camera), nor a plausible one from a translating camera's plane homography."""
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    roll = K @ cv2.Rodrigues(np.array([0.0, 0.0, 0.1]))[0] @ np.linalg.inv(K)
    assert geo.focal_for_rotation(roll, K) is None
    assert geo.focal_for_rotation(np.array([[1.0, 0.0, 20.0], [0.0, 1.0, -5.0], [0.0, 0.0, 1.0]]), K) is None
    assert geo.focal_for_rotation(np.zeros((3, 3)), K) is None
    s = planar_scene
    assert s.H_true is not None
    f = geo.focal_for_rotation(s.H_true, s.K)
    assert f is None or not 0.5 < f / s.K[0, 0] < 2.0


def test_estimate_homography_rejects_outliers(two_view_scene: SceneBuilder) -> None:
    s = two_view_scene("planar", seed=11, outlier_ratio=0.2)
    H, mask = geo.estimate_homography(s.uv_ref_obs, s.uv_cur_obs)
    assert H is not None
    assert not np.any(mask & s.is_outlier)
    assert np.count_nonzero(mask & ~s.is_outlier) >= 0.9 * np.count_nonzero(~s.is_outlier)
    e_cur, _ = geo.transfer_errors_sq(H, s.uv_ref, s.uv_cur)
    assert np.median(np.sqrt(e_cur)) < 0.3  # exact points transfer to within noise


@pytest.mark.parametrize("n", [0, 3])
def test_estimate_homography_too_few_points(planar_scene: TwoViewScene, n: int) -> None:
    H, mask = geo.estimate_homography(planar_scene.uv_ref_obs[:n], planar_scene.uv_cur_obs[:n])
    assert H is None
    assert mask.shape == (n,) and not mask.any()


def test_estimate_homography_collinear_points_does_not_raise() -> None:
    """Degenerate: points on one line do not fix H; either no model or one that maps the points."""
    uv_ref = np.column_stack([np.linspace(10.0, 600.0, 30), np.linspace(10.0, 400.0, 30)])
    uv_cur = uv_ref * 1.01 + 2.0
    H, mask = geo.estimate_homography(uv_ref, uv_cur)
    assert mask.shape == (30,)
    if H is not None:
        assert np.all(np.isfinite(H))
        e_cur, _ = geo.transfer_errors_sq(H, uv_ref[mask], uv_cur[mask])
        assert np.all(e_cur <= 1.0 + 1e-9)


def test_pose_from_homography_planar_scene(planar_scene: TwoViewScene) -> None:
    s = planar_scene
    assert s.plane_n_ref is not None and s.plane_d is not None
    H, inliers = geo.estimate_homography(s.uv_ref_obs, s.uv_cur_obs)
    assert H is not None
    result = geo.pose_from_homography(H, s.K, s.xn(s.uv_ref_obs), s.xn(s.uv_cur_obs), inliers,
                                      max_reproj_err_px=2.0, min_angle_deg=0.5)
    assert result is not None
    R, t, tri = result
    assert _rot_err_deg(R, s.R_cur_ref) < 0.5
    assert _angle_deg(t, s.t_cur_ref) < 3.0
    # t is in units of the plane's distance from the reference camera.
    assert np.linalg.norm(t) == pytest.approx(np.linalg.norm(s.t_cur_ref) / s.plane_d, rel=0.1)
    assert tri.X_ref.shape == (s.n, 3)
    assert np.count_nonzero(tri.good) >= 0.9 * np.count_nonzero(inliers)
    assert not np.any(tri.good & ~inliers)
    # In the same units the triangulated points lie on the plane n . X = 1.
    on_plane = tri.X_ref[tri.good] @ s.plane_n_ref
    assert np.median(np.abs(on_plane - 1.0)) < 0.02


def test_pose_from_homography_pure_rotation_gives_none(rotation_scene: TwoViewScene) -> None:
    """Degenerate: without translation no decomposition triangulates a point above the angle gate."""
    s = rotation_scene
    assert s.H_true is not None
    inliers = np.ones(s.n, dtype=bool)
    assert geo.pose_from_homography(s.H_true, s.K, s.xn(s.uv_ref), s.xn(s.uv_cur), inliers, 2.0, 0.5) is None


# --- triangulation -------------------------------------------------------------------------------------


def test_triangulate_exact_correspondences(general_scene: TwoViewScene) -> None:
    s = general_scene
    tri = geo.triangulate(s.R_cur_ref, s.t_cur_ref, _xn_of(s.X_ref), _xn_of(s.X_cur), s.K,
                          max_reproj_err_px=1.0, min_angle_deg=0.5)
    np.testing.assert_allclose(tri.X_ref, s.X_ref, atol=1e-6)
    assert tri.good.all() and tri.positive_depth.all()
    assert tri.positive_depth_ratio == 1.0
    assert np.max(tri.reproj_err_px) < 1e-6
    assert tri.median_reproj_err_px < 1e-6


def test_triangulation_angle_known_answer() -> None:
    # Current camera centre at (1, 0, 0) in the reference frame: t = -R C with R = I.
    R = np.eye(3)
    t = np.array([-1.0, 0.0, 0.0])
    X_ref = np.array([[0.0, 0.0, 2.0]])
    tri = geo.triangulate(R, t, _xn_of(X_ref), _xn_of(X_ref + t), np.diag([500.0, 500.0, 1.0]), 1.0, 0.5)
    assert tri.angle_deg[0] == pytest.approx(math.degrees(math.atan(0.5)), abs=1e-9)
    np.testing.assert_allclose(tri.X_ref, X_ref, atol=1e-12)


def test_triangulate_points_behind_the_cameras(general_scene: TwoViewScene) -> None:
    s = general_scene
    X_behind = -s.X_ref[:10]  # mirrored through the reference centre: z < 0 in both cameras
    X_behind_cur = X_behind @ s.R_cur_ref.T + s.t_cur_ref
    assert np.all(X_behind_cur[:, 2] < 0.0)
    X_all = np.vstack([s.X_ref[:10], X_behind])
    X_all_cur = X_all @ s.R_cur_ref.T + s.t_cur_ref
    tri = geo.triangulate(s.R_cur_ref, s.t_cur_ref, _xn_of(X_all), _xn_of(X_all_cur), s.K, 1.0, 0.5)
    np.testing.assert_allclose(tri.X_ref, X_all, atol=1e-6)  # the linear solve finds them anyway
    np.testing.assert_array_equal(tri.positive_depth, [True] * 10 + [False] * 10)
    np.testing.assert_array_equal(tri.good, tri.positive_depth)
    assert tri.positive_depth_ratio == 0.5


def test_triangulate_low_parallax_fails_the_angle_gate(general_scene: TwoViewScene,
                                                        rotation_scene: TwoViewScene) -> None:
    s = general_scene
    X_far = np.array([[50.0, -20.0, 1.0e4]])  # 0.64 m baseline seen from 10 km: ~0.004 deg
    X_far_cur = X_far @ s.R_cur_ref.T + s.t_cur_ref
    tri = geo.triangulate(s.R_cur_ref, s.t_cur_ref, _xn_of(X_far), _xn_of(X_far_cur), s.K, 1.0, 0.5)
    assert tri.angle_deg[0] < 0.01
    assert tri.positive_depth[0]
    assert not tri.good[0]
    # Pure rotation: no baseline, every ray pair is parallel and nothing is triangulated.
    r = rotation_scene
    tri = geo.triangulate(r.R_cur_ref, r.t_cur_ref, r.xn(r.uv_ref), r.xn(r.uv_cur), r.K, 1.0, 0.5)
    assert not tri.good.any()
    assert np.all(tri.angle_deg < 0.5)


def test_triangulate_reprojection_gate(general_scene: TwoViewScene) -> None:
    s = general_scene
    xn_ref, xn_cur = _xn_of(s.X_ref), _xn_of(s.X_cur).copy()
    # 10 px perpendicular to the epipolar line: no 3D point explains the correspondence.
    E = geo.essential_from_pose(s.R_cur_ref, s.t_cur_ref)
    line = E @ np.array([*xn_ref[0], 1.0])
    xn_cur[0] += 10.0 / s.K[0, 0] * line[:2] / np.linalg.norm(line[:2])
    tri = geo.triangulate(s.R_cur_ref, s.t_cur_ref, xn_ref, xn_cur, s.K, max_reproj_err_px=2.0, min_angle_deg=0.5)
    assert tri.reproj_err_px[0] > 2.0
    assert not tri.good[0]
    assert tri.good[1:].all()


def test_triangulate_empty_input() -> None:
    empty = np.zeros((0, 2))
    tri = geo.triangulate(np.eye(3), np.array([1.0, 0.0, 0.0]), empty, empty, np.eye(3), 1.0, 0.5)
    assert tri.X_ref.shape == (0, 3)
    assert tri.good.shape == tri.positive_depth.shape == tri.reproj_err_px.shape == tri.angle_deg.shape == (0,)
    assert tri.positive_depth_ratio == 0.0
    assert math.isnan(tri.median_reproj_err_px)


def test_triangulation_expanded_places_rows(general_scene: TwoViewScene) -> None:
    s = general_scene
    tri = geo.triangulate(s.R_cur_ref, s.t_cur_ref, _xn_of(s.X_ref[:3]), _xn_of(s.X_cur[:3]), s.K, 1.0, 0.5)
    idx = np.array([4, 0, 2])
    full = tri.expanded(idx, 6)
    np.testing.assert_allclose(full.X_ref[idx], s.X_ref[:3], atol=1e-6)
    np.testing.assert_array_equal(full.good, [True, False, True, False, True, False])
    assert np.all(np.isnan(full.X_ref[[1, 3, 5]]))
    assert np.all(np.isinf(full.reproj_err_px[[1, 3, 5]]))
    np.testing.assert_array_equal(full.angle_deg[[1, 3, 5]], 0.0)
    assert full.positive_depth_ratio == 0.5


# --- parallax --------------------------------------------------------------------------------------------


def test_parallax_pure_rotation_is_zero(rotation_scene: TwoViewScene) -> None:
    s = rotation_scene
    par = geo.parallax_deg(s.R_cur_ref, s.xn(s.uv_ref), s.xn(s.uv_cur))
    assert par.shape == (s.n,)
    assert np.max(par) < 1e-5


def test_parallax_known_answer() -> None:
    R = _rotation((0.0, math.radians(10.0), 0.0))
    X_ref = np.array([[0.0, 0.0, 5.0]])
    # Translation perpendicular to the rotated ray: the two rays differ by exactly 7 degrees.
    t = R @ np.array([5.0 * math.tan(math.radians(7.0)), 0.0, 0.0])
    X_cur = X_ref @ R.T + t
    par = geo.parallax_deg(R, _xn_of(X_ref), _xn_of(X_cur))
    assert par[0] == pytest.approx(7.0, abs=1e-9)
    # Ignoring the rotation would report 17 degrees.
    assert geo.parallax_deg(np.eye(3), _xn_of(X_ref), _xn_of(X_cur))[0] == pytest.approx(17.0, abs=1e-9)


def test_parallax_empty() -> None:
    assert geo.parallax_deg(np.eye(3), np.zeros((0, 2)), np.zeros((0, 2))).shape == (0,)


# --- scale from map points ---------------------------------------------------------------------------------


def _scale_scene(s: TwoViewScene, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction of the scene's translation and exact current observations for |t| = scale."""
    t_dir = s.t_cur_ref / np.linalg.norm(s.t_cur_ref)
    X_cur = s.X_ref @ s.R_cur_ref.T + scale * t_dir
    return t_dir, _xn_of(X_cur)


def test_scale_from_points_known_answer(general_scene: TwoViewScene) -> None:
    s = general_scene
    t_dir, xn_cur = _scale_scene(s, 0.37)
    est = geo.scale_from_points(s.X_ref, s.R_cur_ref, t_dir, xn_cur, min_points=8)
    assert est is not None
    assert est.scale == pytest.approx(0.37, abs=1e-3)
    assert est.n_used == s.n
    assert est.rel_spread < 1e-6


def test_scale_from_points_with_noise(general_scene: TwoViewScene) -> None:
    s = general_scene
    t_dir = s.t_cur_ref / np.linalg.norm(s.t_cur_ref)
    est = geo.scale_from_points(s.X_ref, s.R_cur_ref, t_dir, s.xn(s.uv_cur_obs), min_points=8)
    assert est is not None
    assert est.scale == pytest.approx(np.linalg.norm(s.t_cur_ref), rel=0.02)


def test_scale_from_points_robust_to_wrong_depths(general_scene: TwoViewScene) -> None:
    s = general_scene
    t_dir, xn_cur = _scale_scene(s, 0.37)
    X_bad = s.X_ref.copy()
    wrong = np.random.default_rng(5).choice(s.n, int(0.3 * s.n), replace=False)
    X_bad[wrong] *= 2.0
    est = geo.scale_from_points(X_bad, s.R_cur_ref, t_dir, xn_cur, min_points=8)
    assert est is not None
    assert est.scale == pytest.approx(0.37, rel=0.02)
    assert est.n_used <= s.n - wrong.size + 5


def test_scale_from_points_too_few_points(general_scene: TwoViewScene) -> None:
    s = general_scene
    t_dir, xn_cur = _scale_scene(s, 0.37)
    assert geo.scale_from_points(s.X_ref[:7], s.R_cur_ref, t_dir, xn_cur[:7], min_points=8) is None
    assert geo.scale_from_points(s.X_ref[:8], s.R_cur_ref, t_dir, xn_cur[:8], min_points=8) is not None


def test_scale_from_points_rays_at_the_epipole() -> None:
    """Degenerate: forward motion and points within ~1.6 deg of the epipole carry no scale information."""
    rng = np.random.default_rng(6)
    t_dir = np.array([0.0, 0.0, 1.0])
    X_ref = np.column_stack([rng.uniform(-0.02, 0.02, (30, 2)), np.ones(30)]) * rng.uniform(4.0, 15.0, (30, 1))
    X_cur = X_ref + 0.37 * t_dir
    assert geo.scale_from_points(X_ref, np.eye(3), t_dir, _xn_of(X_cur), min_points=8) is None


def test_scale_from_points_wrong_direction_gives_none(general_scene: TwoViewScene) -> None:
    """A translation direction of the wrong sign would need a negative scale: no estimate."""
    s = general_scene
    t_dir, xn_cur = _scale_scene(s, 0.37)
    assert geo.scale_from_points(s.X_ref, s.R_cur_ref, -t_dir, xn_cur, min_points=8) is None


# --- motion-only PnP refinement ---------------------------------------------------------------------------


def _perturbed_pose(s: TwoViewScene, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The true pose rotated by 1 deg about a random axis, t moved by 10 % of |t| in a random direction."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    dirn = rng.normal(size=3)
    R0 = _rotation(axis / np.linalg.norm(axis) * math.radians(1.0)) @ s.R_cur_ref
    t0 = s.t_cur_ref + 0.1 * np.linalg.norm(s.t_cur_ref) * dirn / np.linalg.norm(dirn)
    return R0, t0


# With a 1 deg start error every point is ~9 px off; the first gate (4 x max_reproj_err_px) must
# contain that, so the tests use 3 px (the pipeline starts from the E rotation, much closer).
PNP_MAX_ERR_PX = 3.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_refine_pose_pnp_converges(general_scene: TwoViewScene, seed: int) -> None:
    s = general_scene
    R0, t0 = _perturbed_pose(s, seed)
    assert _rot_err_deg(R0, s.R_cur_ref) == pytest.approx(1.0, abs=1e-6)
    out = geo.refine_pose_pnp(s.X_ref, s.uv_cur_obs, s.K, R0, t0, PNP_MAX_ERR_PX)
    assert out is not None
    R, t, mask, _ = out
    assert _rot_err_deg(R, s.R_cur_ref) < 0.05
    assert np.linalg.norm(t - s.t_cur_ref) < 0.01 * np.linalg.norm(s.t_cur_ref)
    assert mask.all()


def test_refine_pose_pnp_excludes_outliers(general_scene: TwoViewScene) -> None:
    s = general_scene
    rng = np.random.default_rng(8)
    uv = s.uv_cur_obs.copy()
    bad = rng.choice(s.n, s.n // 4, replace=False)
    angle = rng.uniform(0.0, 2.0 * math.pi, bad.size)
    uv[bad] += rng.uniform(15.0, 40.0, (bad.size, 1)) * np.column_stack([np.cos(angle), np.sin(angle)])
    R0, t0 = _perturbed_pose(s, 3)
    out = geo.refine_pose_pnp(s.X_ref, uv, s.K, R0, t0, PNP_MAX_ERR_PX)
    assert out is not None
    R, t, mask, _ = out
    assert not mask[bad].any()
    assert np.count_nonzero(np.delete(mask, bad)) >= 0.98 * (s.n - bad.size)
    assert _rot_err_deg(R, s.R_cur_ref) < 0.05
    assert np.linalg.norm(t - s.t_cur_ref) < 0.01 * np.linalg.norm(s.t_cur_ref)


def test_refine_pose_pnp_covariance(general_scene: TwoViewScene) -> None:
    s = general_scene
    out = geo.refine_pose_pnp(s.X_ref, s.uv_cur_obs, s.K, s.R_cur_ref, s.t_cur_ref, PNP_MAX_ERR_PX)
    assert out is not None
    R, t, _, cov = out
    assert cov.shape == (6, 6)
    np.testing.assert_allclose(cov, cov.T, rtol=1e-9, atol=1e-18)
    assert np.min(np.linalg.eigvalsh(cov)) > 0.0
    # The covariance describes the actual error: the truth lies inside its 99.9 % ellipsoid.
    rvec, _ = cv2.Rodrigues(R)
    rvec_true, _ = cv2.Rodrigues(s.R_cur_ref)
    delta = np.concatenate([rvec.ravel() - rvec_true.ravel(), t - s.t_cur_ref])
    assert float(delta @ np.linalg.solve(cov, delta)) < 22.46  # chi-square 6 DoF, 99.9 %


def test_refine_pose_pnp_too_few_points(general_scene: TwoViewScene) -> None:
    s = general_scene
    assert geo.refine_pose_pnp(s.X_ref[:5], s.uv_cur_obs[:5], s.K, s.R_cur_ref, s.t_cur_ref, 2.0) is None


def test_refine_pose_pnp_far_off_start_never_returns_a_wrong_pose(general_scene: TwoViewScene) -> None:
    """From a start 20 deg away: either no pose, or (the median-scaled first gate) the true one."""
    s = general_scene
    R0 = _rotation((0.0, math.radians(20.0), 0.0)) @ s.R_cur_ref
    out = geo.refine_pose_pnp(s.X_ref, s.uv_cur_obs, s.K, R0, s.t_cur_ref, 2.0)
    if out is not None:
        assert _rot_err_deg(out[0], s.R_cur_ref) < 0.1


@pytest.mark.parametrize("off_deg", [10.0, 20.0])
def test_refine_pose_pnp_robust_start_keeps_the_static_consensus(general_scene: TwoViewScene, off_deg: float) -> None:
    """A third of the map's points on one rigid mover (25 px off where the static scene puts them), the
    start 10-20 deg away: LM from the start loses the static points at its gates (no pose), the
    consensus start (``robust_start``) keeps the static points and no mover."""
    s = general_scene
    n = s.X_ref.shape[0]
    mover = np.arange(n) >= 2 * n // 3
    uv = s.uv_cur_obs.copy()
    uv[mover] += np.array([25.0, 5.0])
    R0 = _rotation((0.0, math.radians(off_deg), 0.0)) @ s.R_cur_ref
    plain = geo.refine_pose_pnp(s.X_ref, uv, s.K, R0, 0.5 * s.t_cur_ref, 2.0)
    assert plain is None or np.count_nonzero(plain[2] & ~mover) < np.count_nonzero(~mover) // 2
    out = geo.refine_pose_pnp(s.X_ref, uv, s.K, R0, 0.5 * s.t_cur_ref, 2.0, robust_start=True)
    assert out is not None and _rot_err_deg(out[0], s.R_cur_ref) < 0.1
    assert np.count_nonzero(out[2] & mover) == 0 and np.count_nonzero(out[2] & ~mover) >= 0.9 * np.count_nonzero(~mover)
    clean = geo.refine_pose_pnp(s.X_ref, s.uv_cur_obs, s.K, s.R_cur_ref, s.t_cur_ref, 2.0, robust_start=True)
    ref = geo.refine_pose_pnp(s.X_ref, s.uv_cur_obs, s.K, s.R_cur_ref, s.t_cur_ref, 2.0)
    assert clean is not None and ref is not None and _rot_err_deg(clean[0], ref[0]) < 1e-3


# --- nearest rotation ------------------------------------------------------------------------------------


def _assert_proper_rotation(R: np.ndarray) -> None:
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


def test_nearest_rotation_of_noisy_rotation() -> None:
    rng = np.random.default_rng(9)
    R_true = _rotation((0.3, -0.5, 0.2))
    R = geo.nearest_rotation(R_true + rng.normal(0.0, 0.01, (3, 3)))
    _assert_proper_rotation(R)
    assert _rot_err_deg(R, R_true) < 1.0
    np.testing.assert_allclose(geo.nearest_rotation(2.0 * R_true), R_true, atol=1e-12)


def test_nearest_rotation_of_a_reflection_is_proper() -> None:
    _assert_proper_rotation(geo.nearest_rotation(np.diag([1.0, 1.0, -1.0]) @ _rotation((0.1, 0.2, 0.3))))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(arrays(np.float64, (3, 3), elements=st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)))
def test_nearest_rotation_property(M: np.ndarray) -> None:
    if np.linalg.svd(M, compute_uv=False)[-1] < 1e-3:
        return  # (near) singular: the nearest rotation is not unique
    R = geo.nearest_rotation(M)
    _assert_proper_rotation(R)
    # No rotation is closer: compare with a few random rotations near R.
    best = np.linalg.norm(M - R)
    for rvec in np.random.default_rng(0).normal(0.0, 0.05, (10, 3)):
        assert best <= np.linalg.norm(M - _rotation(rvec) @ R) + 1e-9
