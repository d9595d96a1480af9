"""The keyframe (epi_vo.core.keyframe): what make_keyframe keeps, what it adds, and its coordinates."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from epi_vo.core import features as fe
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.keyframe import Keyframe, make_keyframe

CFG = VoConfig()
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
CAMERA = CameraModel.create(640, 480, K, [])
NO_PTS = np.zeros((0, 2), np.float32)
NO_X = np.zeros((0, 3))


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """A 640x480 random texture, blurred so that corners are well defined: corners everywhere."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)


@pytest.fixture(scope="module")
def tracked() -> tuple[np.ndarray, np.ndarray]:
    pts = np.array([[100.5, 100.25], [320.0, 240.0], [600.0, 50.0], [40.0, 440.0], [500.25, 300.75]], np.float32)
    X = np.array([[1.0, 2.0, 10.0], [0.0, 0.0, 5.0], [np.nan] * 3, [3.0, -2.0, 8.0], [0.5, 0.5, 20.0]])
    return pts, X


def _klt_keyframe(gray: np.ndarray, pts: np.ndarray, X: np.ndarray, cfg: VoConfig = CFG,
                  camera: CameraModel = CAMERA) -> Keyframe:
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    return make_keyframe(9, 123_000, T, np.eye(6) * 0.01, gray, camera, pts, X, cfg, None, None)


def test_tracked_points_come_first_with_their_depth(texture, tracked) -> None:
    pts, X = tracked
    kf = _klt_keyframe(texture, pts, X)
    n = pts.shape[0]
    assert kf.index == 9 and kf.stamp_ns == 123_000 and kf.descriptors is None and kf.camera is CAMERA
    np.testing.assert_array_equal(kf.pts[:n], pts)
    np.testing.assert_array_equal(kf.X_kf[:n], X)
    assert np.all(np.isnan(kf.X_kf[n:]))  # new corners have no depth yet
    assert kf.n_map_points == 4  # the tracked points with depth


def test_new_corners_top_up_to_max_features(texture, tracked) -> None:
    pts, X = tracked
    kf = _klt_keyframe(texture, pts, X)
    assert kf.n_features == CFG.max_features
    assert kf.pts.dtype == np.float32 and kf.X_kf.shape == (CFG.max_features, 3)
    new = kf.pts[pts.shape[0]:]
    assert np.all((new >= 0) & (new <= [639, 479]))
    # New corners keep their distance from the tracked points and from each other (sub-pixel refinement
    # may move a corner by a pixel or two).
    d_tracked = np.linalg.norm(new[:, None] - pts[None], axis=2)
    assert d_tracked.min() >= CFG.min_feature_distance_px - 2.0
    d_new = np.linalg.norm(new[:, None] - new[None], axis=2) + np.eye(new.shape[0]) * 1e9
    assert d_new.min() >= CFG.min_feature_distance_px - 2.0
    # ... and are spread over the bucketing grid.
    cell = (np.floor(new[:, 0] * CFG.grid_cols / 640) + CFG.grid_cols * np.floor(new[:, 1] * CFG.grid_rows / 480))
    assert np.unique(cell).size >= 0.9 * CFG.grid_rows * CFG.grid_cols


@pytest.mark.parametrize("max_features", [50, 120])
def test_top_up_follows_the_configured_maximum(texture, tracked, max_features: int) -> None:
    pts, X = tracked
    kf = _klt_keyframe(texture, pts, X, dataclasses.replace(CFG, max_features=max_features))
    assert kf.n_features == max_features


def test_no_top_up_when_the_grid_is_full(texture) -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform([0, 0], [639, 479], (CFG.max_features + 10, 2)).astype(np.float32)
    X = rng.uniform(1.0, 10.0, (pts.shape[0], 3))
    kf = _klt_keyframe(texture, pts, X)
    np.testing.assert_array_equal(kf.pts, pts)  # tracked points are all kept, none added
    np.testing.assert_array_equal(kf.X_kf, X)


def test_a_textureless_image_adds_no_corners(tracked) -> None:
    pts, X = tracked
    kf = _klt_keyframe(np.full((480, 640), 128, np.uint8), pts, X)
    np.testing.assert_array_equal(kf.pts, pts)
    assert kf.n_features == pts.shape[0]


def test_first_keyframe_has_no_map(texture) -> None:
    kf = _klt_keyframe(texture, NO_PTS, NO_X)
    assert kf.n_features == CFG.max_features and kf.n_map_points == 0


def test_xn_and_uv_are_consistent_with_the_camera(texture, tracked) -> None:
    pts, X = tracked
    kf = _klt_keyframe(texture, pts, X)
    np.testing.assert_allclose(kf.xn, (kf.pts.astype(np.float64) - K[:2, 2]) / [K[0, 0], K[1, 1]], atol=1e-12)
    np.testing.assert_allclose(kf.uv, kf.pts, atol=1e-9)  # no distortion: undistorted pixels = raw pixels


def test_xn_and_uv_undistort_a_distorted_camera(texture, tracked) -> None:
    cam = CameraModel.create(640, 480, K, [-0.25, 0.07, 0.001, -0.0005, 0.0])
    pts, X = tracked
    kf = _klt_keyframe(texture, pts, X, camera=cam)
    # Projecting the normalized rays through the lens model gives the raw pixels back.
    rays = np.column_stack([kf.xn, np.ones(kf.n_features)])
    np.testing.assert_allclose(cam.project(rays), kf.pts, atol=1e-3)
    np.testing.assert_allclose(kf.uv, kf.xn * [K[0, 0], K[1, 1]] + K[:2, 2], atol=1e-9)
    assert np.max(np.linalg.norm(kf.uv - kf.pts, axis=1)) > 5.0  # the corners are really distorted


def test_the_pose_is_copied(texture) -> None:
    T = np.eye(4)
    kf = make_keyframe(0, 0, T, np.eye(6), texture, CAMERA, NO_PTS, NO_X, CFG, None, None)
    T[0, 3] = 5.0
    np.testing.assert_array_equal(kf.T_w_kf, np.eye(4))


def test_orb_keyframe_places_tracked_depth_on_the_matching_detection(texture) -> None:
    cfg = dataclasses.replace(CFG, frontend="orb")
    orb = fe.make_orb(cfg)
    feats = fe.detect_orb(orb, texture, cfg)
    assert feats.pts.shape[0] > 50
    idx = np.array([3, 17, 42])
    # The tracked positions are those of detections (to within a fraction of a pixel).
    pts_tracked = (feats.pts[idx] + np.float32(0.2)).astype(np.float32)
    X_tracked = np.array([[1.0, 0.0, 4.0], [0.0, 1.0, 6.0], [-1.0, 0.5, 9.0]])
    kf = make_keyframe(2, 5, np.eye(4), np.eye(6), texture, CAMERA, pts_tracked, X_tracked, cfg, orb, feats)
    np.testing.assert_array_equal(kf.pts, feats.pts)
    assert kf.descriptors is feats.descriptors
    np.testing.assert_array_equal(kf.X_kf[idx], X_tracked)
    others = np.setdiff1d(np.arange(kf.n_features), idx)
    assert np.all(np.isnan(kf.X_kf[others]))
    np.testing.assert_allclose(kf.uv, kf.pts, atol=1e-9)
    # Without the current frame's detections, make_keyframe detects them itself (deterministically).
    again = make_keyframe(2, 5, np.eye(4), np.eye(6), texture, CAMERA, NO_PTS, NO_X, cfg, orb, None)
    np.testing.assert_array_equal(again.pts, feats.pts)
    assert again.n_map_points == 0
