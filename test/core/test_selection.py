"""Two-view model selection (epi_vo.core.selection) on synthetic scenes with exact ground truth."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.frame import Model
from epi_vo.core.selection import ModelSelection, select_model

CFG = VoConfig()


def _select(scene: Any, cfg: VoConfig = CFG) -> ModelSelection:
    return select_model(scene.uv_ref_obs, scene.uv_cur_obs, scene.K, cfg)


def _same_up_to_scale(A: np.ndarray, B: np.ndarray) -> float:
    a, b = A / np.linalg.norm(A), B / np.linalg.norm(B)
    return float(min(np.linalg.norm(a - b), np.linalg.norm(a + b)))


def _transfer(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = geo.homogeneous(uv) @ H.T
    return p[:, :2] / p[:, 2:3]


def test_general_scene_selects_the_essential_matrix(general_scene) -> None:
    s = general_scene
    sel = _select(s)
    assert sel.model is Model.ESSENTIAL
    assert 0.0 < sel.rh < CFG.rh_threshold
    assert sel.E is not None and sel.F is not None and sel.H is not None
    # E is the true [t]x R up to scale; F = K^-T E K^-1 puts the exact correspondences on their lines.
    assert _same_up_to_scale(sel.E, geo.essential_from_pose(s.R_cur_ref, s.t_cur_ref)) < 0.02
    np.testing.assert_allclose(sel.F, geo.fundamental_from_essential(sel.E, s.K))
    assert np.sqrt(np.max(geo.sampson_distance_sq(sel.F, s.uv_ref, s.uv_cur))) < 0.3
    # 0.3 px noise, no outliers: every correspondence is an E inlier, and H explains only a part.
    assert sel.inliers_e is not None and sel.inliers_h is not None
    assert np.all(sel.inliers_e)
    assert np.count_nonzero(sel.inliers_h) < 0.5 * s.n


def test_rh_is_the_ratio_of_the_two_scores(general_scene) -> None:
    s = general_scene
    sel = _select(s)
    s_e, in_e = geo.score_fundamental(sel.F, s.uv_ref_obs, s.uv_cur_obs, CFG.score_sigma_px)
    s_h, in_h = geo.score_homography(sel.H, s.uv_ref_obs, s.uv_cur_obs, CFG.score_sigma_px)
    assert sel.rh == pytest.approx(s_h / (s_h + s_e))
    np.testing.assert_array_equal(sel.inliers_e, in_e)
    np.testing.assert_array_equal(sel.inliers_h, in_h)


@pytest.mark.parametrize("scene_name", ["planar_scene", "rotation_scene"])
def test_planar_and_rotation_scenes_select_the_homography(scene_name: str, request: pytest.FixtureRequest) -> None:
    s = request.getfixturevalue(scene_name)
    sel = _select(s)
    assert sel.model is Model.HOMOGRAPHY
    assert CFG.rh_threshold < sel.rh < 1.0
    assert sel.H is not None and sel.inliers_h is not None
    # H is the scene's exact homography: the exact reference pixels transfer onto the exact current ones.
    assert np.max(np.linalg.norm(_transfer(sel.H, s.uv_ref) - s.uv_cur, axis=1)) < 0.6
    assert np.all(sel.inliers_h)


def test_the_threshold_decides_between_the_models(general_scene, planar_scene) -> None:
    assert _select(general_scene, dataclasses.replace(CFG, rh_threshold=0.0)).model is Model.HOMOGRAPHY
    never_h = dataclasses.replace(CFG, rh_threshold=1.0)
    assert _select(planar_scene, never_h).model is Model.ESSENTIAL  # E also fits a plane; RH only prefers H


def test_inlier_masks_flag_the_gross_outliers(general_scene_outliers, two_view_scene: Callable[..., Any]) -> None:
    s = general_scene_outliers
    sel = _select(s)
    assert sel.model is Model.ESSENTIAL and sel.rh < CFG.rh_threshold
    assert sel.inliers_e is not None
    # The epipolar gate is 1-D: an outlier may by chance land near its epipolar line (~1 % each).
    assert np.count_nonzero(sel.inliers_e & s.is_outlier) <= 1
    assert np.count_nonzero(sel.inliers_e & ~s.is_outlier) >= 0.97 * np.count_nonzero(~s.is_outlier)
    assert _same_up_to_scale(sel.E, geo.essential_from_pose(s.R_cur_ref, s.t_cur_ref)) < 0.02

    planar = two_view_scene("planar", seed=3, outlier_ratio=0.2)
    sel = _select(planar)
    assert sel.model is Model.HOMOGRAPHY and sel.rh > CFG.rh_threshold
    np.testing.assert_array_equal(sel.inliers_h, ~planar.is_outlier)  # the 2-D transfer gate is exact here


@pytest.mark.parametrize("n", [0, 1, 3])
def test_too_few_points_select_no_model(n: int, general_scene) -> None:
    s = general_scene
    sel = select_model(s.uv_ref_obs[:n], s.uv_cur_obs[:n], s.K, CFG)
    assert sel.model is Model.NONE
    assert sel.E is None and sel.H is None and sel.F is None
    assert sel.inliers_e is None and sel.inliers_h is None
    assert sel.rh == 0.5  # rh_ratio: neither model explains anything


def test_four_points_give_only_a_homography(general_scene) -> None:
    # The 5-point solver needs 5 correspondences; any 4 fit a homography exactly.
    s = general_scene
    sel = select_model(s.uv_ref_obs[:4], s.uv_cur_obs[:4], s.K, CFG)
    assert sel.E is None and sel.H is not None
    assert sel.model is Model.HOMOGRAPHY and sel.rh == 1.0


def test_selection_is_deterministic(general_scene_outliers) -> None:
    a, b = _select(general_scene_outliers), _select(general_scene_outliers)
    assert a.model is b.model and a.rh == b.rh
    np.testing.assert_array_equal(a.inliers_e, b.inliers_e)


def test_the_static_hypothesis_scores_as_the_identity_homography() -> None:
    """``score_static`` is ``score_homography`` of H = I without the general transfer: the same score and
    inliers to the bit, on still, slowly and quickly moving points."""
    rng = np.random.default_rng(3)
    for sigma in (0.0, 0.3, 1.0, 3.0, 20.0):
        a = rng.uniform(0.0, 640.0, size=(300, 2))
        b = a + rng.normal(0.0, sigma, size=(300, 2))
        s_h, in_h = geo.score_homography(np.eye(3), a, b, 1.0)
        s_0, in_0 = geo.score_static(a, b, 1.0)
        assert s_0 == s_h and np.array_equal(in_0, in_h)
        assert (sigma == 0.0) <= bool(in_0.all())
