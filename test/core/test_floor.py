"""The floor among a keyframe's map points (epi_vo.core.floor): height, pitch and roll of a real floor, and no
floor where the scene has none or stands beneath the plane."""

from __future__ import annotations

import numpy as np
import pytest
from floor_scenes import scene as _scene
from floor_scenes import table_over_its_pedestal as _table_over_its_pedestal

from epi_vo.core.floor import find_floor, fit_ground_plane


@pytest.mark.parametrize(("height", "pitch", "roll"), [(0.45, 15.0, 0.0), (1.65, 0.5, -1.0), (0.3, 20.0, 3.0)])
def test_floor_fit_recovers_height_pitch_and_roll(height: float, pitch: float, roll: float) -> None:
    X = _scene(height, pitch, roll, n_floor=80, n_clutter=60, noise=0.003 * height)
    plane = fit_ground_plane(X, max_tilt_deg=35.0, inlier_ratio=0.04, min_points=10)
    assert plane is not None
    assert plane.height == pytest.approx(height, rel=0.01)
    assert plane.pitch_deg == pytest.approx(pitch, abs=0.5)
    assert plane.roll_deg == pytest.approx(roll, abs=0.5)
    assert plane.n_inliers >= 70 and 0 < plane.rel_std < 0.01


def test_floor_fit_refuses_a_scene_without_floor() -> None:
    X = _scene(1.0, 0.0, 0.0, n_floor=0, n_clutter=80, noise=0.001)
    X = X[X[:, 2] > 8.5]  # the wall only: vertical, no floor normal
    assert fit_ground_plane(X, max_tilt_deg=35.0, inlier_ratio=0.04, min_points=10) is None
    assert fit_ground_plane(np.full((30, 3), np.nan), max_tilt_deg=35.0, inlier_ratio=0.04, min_points=10) is None


def test_floor_fit_is_not_fooled_by_box_tops_above_the_floor() -> None:
    # A level table top with more points than the floor: the floor supports the scene from below.
    rng = np.random.default_rng(3)
    floor = np.column_stack([rng.uniform(-3, 3, 40), np.full(40, 1.0), rng.uniform(2, 8, 40)])
    table = np.column_stack([rng.uniform(-1, 1, 60), np.full(60, 0.4), rng.uniform(3, 5, 60)])
    plane = fit_ground_plane(np.vstack([floor, table]), max_tilt_deg=35.0, inlier_ratio=0.04, min_points=10)
    assert plane is not None and plane.height == pytest.approx(1.0, rel=0.01)


def test_a_plane_with_the_scene_beneath_it_is_no_floor() -> None:
    """The floor carries the scene: a plane with as many map points well beneath it as on it is none,
    however it scores, and the search says why."""
    X = _table_over_its_pedestal(0.3)
    assert fit_ground_plane(X, max_tilt_deg=35.0, inlier_ratio=0.04, min_points=8) is None
    search = find_floor(X, max_tilt_deg=35.0, inlier_ratio=0.04, min_points=8)
    assert search.plane is None and search.n_unsupported > 0
    assert search.best_unsupported == (12, 30)
    # The same plane with the pedestal standing on it is the floor.
    X_up = X.copy()
    X_up[12:, 1] = 0.3 - X_up[12:, 1] + 0.3
    plane = fit_ground_plane(X_up, max_tilt_deg=35.0, inlier_ratio=0.04, min_points=8)
    assert plane is not None and plane.height == pytest.approx(0.3, rel=1e-6) and plane.n_inliers == 12
