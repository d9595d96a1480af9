"""The keyframe / map stage (epi_vo.core.mapping.keyframe_map) against the scenes' true points.

The motion is given (the scene's true motion, the translation in map units): these tests check the
keyframe decision and the map points of the new keyframe, not the motion estimate.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from epi_vo.core import geometry as geo
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.frame import TrackingState
from epi_vo.core.keyframe import Keyframe
from epi_vo.core.mapping import KeyframeMap, keyframe_map
from epi_vo.core.motion import Motion
from epi_vo.core.reasons import sentence

CFG = VoConfig()
KF_STAMP_NS = 5_000_000_000
STAMP_NS = KF_STAMP_NS + 100_000_000  # 0.1 s after the keyframe: not too old
MAP_SCALE = 2.5


def _keyframe(scene: Any, X_kf: np.ndarray | None = None) -> Keyframe:
    cam = CameraModel.create(640, 480, scene.K, [])
    pts = np.asarray(scene.uv_ref_obs, dtype=np.float32)
    xn = cam.normalize(pts)
    X = np.full((scene.n, 3), np.nan) if X_kf is None else X_kf
    return Keyframe(1, KF_STAMP_NS, np.eye(4), np.zeros((6, 6)), pts, xn, cam.to_pixels(xn), X, None, cam)


def _truth(scene: Any, state: TrackingState = TrackingState.TRACKING, inliers: np.ndarray | None = None,
           rows: np.ndarray | None = None, new_map: geo.Triangulation | None = None) -> Motion:
    rows = np.arange(scene.n) if rows is None else rows
    inl = ~np.asarray(scene.is_outlier)[rows] if inliers is None else inliers
    t = np.zeros(3) if state is not TrackingState.TRACKING else np.array(scene.t_cur_ref) * MAP_SCALE
    return Motion(state, np.array(scene.R_cur_ref), t, np.eye(6) * 1e-4, inl, new_map)


@dataclasses.dataclass(frozen=True)
class _Seen:
    """What the motion stage measured (inliers, their median parallax under the motion's rotation) and what
    the mapping stage returned."""

    n_inliers: int
    median_parallax_deg: float
    mapped: KeyframeMap

    @property
    def n_triangulated(self) -> int:
        return self.mapped.n_triangulated

    @property
    def positive_depth_ratio(self) -> float:
        return self.mapped.positive_depth_ratio

    @property
    def median_reproj_err_px(self) -> float:
        return self.mapped.median_reproj_err_px

    @property
    def reasons(self) -> list[str]:
        return [sentence(n) for n in self.mapped.notes]


def _run(scene: Any, motion: Motion, kf: Keyframe, rows: np.ndarray | None = None, cfg: VoConfig = CFG,
         stamp_ns: int = STAMP_NS) -> tuple[np.ndarray | None, _Seen]:
    rows = np.arange(scene.n, dtype=np.int64) if rows is None else rows
    xn_cur = kf.camera.normalize(np.asarray(scene.uv_cur_obs)[rows])
    n_inliers = int(np.count_nonzero(motion.inliers))
    par = geo.parallax_deg(motion.R_cur_kf, kf.xn[rows][motion.inliers], xn_cur[motion.inliers])
    mapped = keyframe_map(cfg, motion, kf, rows, xn_cur, stamp_ns, n_inliers, float(np.median(par)))
    return mapped.X_cur, _Seen(n_inliers, float(np.median(par)), mapped)


def _rel_err(X: np.ndarray, X_true: np.ndarray) -> np.ndarray:
    return np.linalg.norm(X - X_true, axis=1) / np.linalg.norm(X_true, axis=1)


# --- no keyframe ------------------------------------------------------------------------------------
def test_low_parallax_with_strong_tracking_makes_no_keyframe(general_scene) -> None:
    s = general_scene
    cfg = dataclasses.replace(CFG, kf_min_parallax_deg=5.0)  # the scene's ~3.3 deg are now "low"
    X, st = _run(s, _truth(s), _keyframe(s), cfg=cfg)
    assert st.median_parallax_deg < cfg.kf_min_parallax_deg and st.n_inliers >= cfg.kf_min_inliers
    assert X is None
    assert st.n_triangulated == 0 and st.reasons == []  # no depth update either


@pytest.mark.parametrize("state", [TrackingState.ROTATION_ONLY, TrackingState.INITIALIZING])
def test_rotation_or_initialising_with_strong_tracking_makes_no_keyframe(rotation_scene, state: TrackingState
                                                                         ) -> None:
    s = rotation_scene
    X, _ = _run(s, _truth(s, state), _keyframe(s, np.array(s.X_ref)))
    assert X is None


# --- a tracking keyframe triangulates its pair ---------------------------------------------------------
def test_tracking_keyframe_with_parallax_triangulates_the_true_points(general_scene_outliers) -> None:
    s = general_scene_outliers
    rng = np.random.default_rng(0)
    rows = np.sort(rng.choice(s.n, 170, replace=False)).astype(np.int64)  # 85 % tracked, in keyframe order
    rows = rows[rng.permutation(rows.size)]  # and any order: X_cur must follow rows
    motion = _truth(s, rows=rows)
    X, st = _run(s, motion, _keyframe(s), rows)
    assert X is not None and X.shape == (rows.size, 3)
    assert st.median_parallax_deg >= CFG.kf_min_parallax_deg
    finite = np.isfinite(X[:, 0])
    assert not np.any(finite & ~motion.inliers)  # outliers get no depth
    assert np.count_nonzero(finite) == st.n_triangulated >= 0.95 * np.count_nonzero(motion.inliers)
    X_true = np.array(s.X_cur)[rows] * MAP_SCALE  # in the current (new keyframe's) camera frame, map units
    err = _rel_err(X[finite], X_true[finite])
    assert np.median(err) < 0.03 and np.max(err) < 0.2
    assert st.positive_depth_ratio == 1.0 and st.median_reproj_err_px < 1.0


def test_old_map_points_carry_over_where_no_fresh_depth_passes_the_gates(general_scene_outliers) -> None:
    s = general_scene_outliers
    cfg = dataclasses.replace(CFG, kf_min_parallax_deg=5.0, min_triangulation_angle_deg=45.0)
    X_old = np.array(s.X_ref) * MAP_SCALE
    X_old[::3] = np.nan  # a third of the features have no depth yet
    kf = _keyframe(s, X_old)
    rows = np.arange(90, dtype=np.int64)  # 45 % tracked: weak tracking forces the keyframe
    motion = _truth(s, rows=rows)
    X, st = _run(s, motion, kf, rows, cfg)
    assert X is not None and st.n_triangulated == 0
    expected = X_old[rows] @ motion.R_cur_kf.T + motion.t_cur_kf
    expected[~motion.inliers] = np.nan
    np.testing.assert_array_equal(X, expected)
    np.testing.assert_allclose(X[np.isfinite(X[:, 0])], (np.array(s.X_cur)[rows] * MAP_SCALE)[np.isfinite(X[:, 0])],
                               rtol=1e-12)
    assert st.reasons == ["keyframe without parallax: no new depth"]


def test_fresh_triangulations_replace_old_points_and_the_rest_carries_over(general_scene) -> None:
    s = general_scene
    X_old = np.array(s.X_ref) * MAP_SCALE * 1.3  # stale depths, 30 % too far
    kf = _keyframe(s, X_old)
    motion = _truth(s)
    cfg = dataclasses.replace(CFG, min_triangulation_angle_deg=3.0)  # only part of the points pass
    X, st = _run(s, motion, kf, cfg=cfg)
    assert X is not None
    assert 0 < st.n_triangulated < s.n
    X_true = np.array(s.X_cur) * MAP_SCALE
    fresh = _rel_err(X, X_true) < 0.1
    assert np.count_nonzero(fresh) == st.n_triangulated
    carried = X_old @ motion.R_cur_kf.T + motion.t_cur_kf
    np.testing.assert_allclose(X[~fresh], carried[~fresh], rtol=1e-12)


@pytest.mark.parametrize("why", ["few_inliers", "too_old"])
def test_weak_tracking_or_age_makes_a_keyframe_without_parallax(general_scene, why: str) -> None:
    s = general_scene
    cfg = dataclasses.replace(CFG, kf_min_parallax_deg=5.0)
    stamp = STAMP_NS
    if why == "few_inliers":
        cfg = dataclasses.replace(cfg, kf_min_inliers=s.n + 1)
    else:
        stamp = KF_STAMP_NS + int(cfg.kf_max_interval_s * 1e9) + 1
    X, st = _run(s, _truth(s), _keyframe(s), cfg=cfg, stamp_ns=stamp)
    assert X is not None
    # The pair does have parallax (it is only below the keyframe limit): the new keyframe gets depth.
    assert st.n_triangulated >= 0.95 * s.n
    assert np.median(_rel_err(X[np.isfinite(X[:, 0])], (np.array(s.X_cur) * MAP_SCALE)[np.isfinite(X[:, 0])])) < 0.03


# --- the first map ----------------------------------------------------------------------------------------
def test_a_new_map_is_moved_into_the_new_keyframe(general_scene) -> None:
    s = general_scene
    motion0 = _truth(s)
    kf = _keyframe(s)
    xn_cur = kf.camera.normalize(s.uv_cur_obs)
    tri = geo.triangulate(motion0.R_cur_kf, motion0.t_cur_kf, kf.xn, xn_cur, s.K, CFG.max_reprojection_error_px,
                          3.0)  # a gate that only some points pass
    assert 0 < np.count_nonzero(tri.good) < s.n
    motion = dataclasses.replace(motion0, new_map=tri)
    cfg = dataclasses.replace(CFG, kf_min_parallax_deg=5.0)  # a new map makes a keyframe whatever the parallax
    X, st = _run(s, motion, kf, cfg=cfg)
    assert X is not None
    np.testing.assert_array_equal(np.isfinite(X[:, 0]), tri.good)
    np.testing.assert_allclose(X[tri.good], (tri.X_ref @ motion.R_cur_kf.T + motion.t_cur_kf)[tri.good])
    assert np.median(_rel_err(X[tri.good], (np.array(s.X_cur) * MAP_SCALE)[tri.good])) < 0.03
    assert st.n_triangulated == 0  # the motion stage already counted these


# --- re-anchoring without depth ----------------------------------------------------------------------------
@pytest.mark.parametrize("why", ["weak", "too_old"])
def test_rotation_re_anchors_keeping_the_depths_rotated(rotation_scene, why: str) -> None:
    s = rotation_scene
    X_old = np.array(s.X_ref) * MAP_SCALE
    X_old[1::4] = np.nan
    kf = _keyframe(s, X_old)
    if why == "weak":
        rows = np.arange(0, s.n, 3, dtype=np.int64)  # a third of the keyframe still tracked
        stamp = STAMP_NS
    else:
        rows = np.arange(s.n, dtype=np.int64)
        stamp = KF_STAMP_NS + int(CFG.kf_max_interval_s * 1e9) + 1
    motion = _truth(s, TrackingState.ROTATION_ONLY, rows=rows)
    X, st = _run(s, motion, kf, rows, stamp_ns=stamp)
    assert X is not None
    np.testing.assert_array_equal(X, X_old[rows] @ motion.R_cur_kf.T)  # t = 0: no triangulation, depths kept
    finite = np.isfinite(X[:, 0])
    np.testing.assert_allclose(X[finite], (np.array(s.X_cur) * MAP_SCALE)[rows][finite], rtol=1e-12)
    assert st.n_triangulated == 0 and np.isnan(st.positive_depth_ratio)


def test_initialising_re_anchors_when_too_few_features_survive(general_scene) -> None:
    s = general_scene
    rows = np.arange(2 * CFG.min_inliers - 1, dtype=np.int64)
    motion = _truth(s, TrackingState.INITIALIZING, rows=rows)
    X, st = _run(s, motion, _keyframe(s), rows)
    assert X is not None and X.shape == (rows.size, 3) and np.all(np.isnan(X))
    assert st.n_triangulated == 0
    rows = np.arange(2 * CFG.min_inliers, dtype=np.int64)  # enough survive (a low tracked ratio alone is not enough)
    X, _ = _run(s, _truth(s, TrackingState.INITIALIZING, rows=rows), _keyframe(s), rows)
    assert X is None
