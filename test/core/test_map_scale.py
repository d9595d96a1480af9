"""The map's scale in the pose covariance (``core.map_scale``)."""

from __future__ import annotations

import numpy as np
import pytest

from epi_vo.core import scale as sc
from epi_vo.core.map_scale import MapScaleCovariance, first_map_rel_var, length_rel_var


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


def test_a_rebuilt_maps_units_are_only_as_sure_as_the_speed_that_carried_them() -> None:
    """After a loss the new map's baseline comes from the last speed: its units against the first map's are
    known to ``NEW_MAP_REL_STD``. Its first baseline and every later step carry that one error coherently:
    after two steps d1, d2 the position's variance along the path is that of (d1 + d2) s, s ~ N(0, rel^2),
    not the drift per keyframe's. The first map's baseline is the unit itself (nothing added)."""
    rel2 = sc.NEW_MAP_REL_STD**2
    vo = sc.VoUnitsScale(filter=sc.ScaleFilter(0.0))
    d0, d1, d2 = np.array([1.0, 0.0, 0.0]), np.array([0.2, 0.0, 1.0]), np.array([0.0, 0.1, 0.8])
    first, cov0 = MapScaleCovariance(0.0).keyframe_cov(vo, True, d0)
    assert np.all(cov0 == 0.0) and first.var == 0.0
    rebuilt, cov1 = first.keyframe_cov(vo, True, d1)
    assert rebuilt.var == pytest.approx(rel2)
    _, cov2 = rebuilt.keyframe_cov(vo, False, d2)
    np.testing.assert_allclose(cov1 + cov2, rel2 * np.outer(d1 + d2, d1 + d2), rtol=1e-12)


def test_the_next_steps_are_measured_in_units_that_carry_the_keyframe_steps_length_error() -> None:
    """Monte Carlo: a keyframe step d1 whose length is off by e ~ N(0, r) (its own covariance holds that),
    then a step d2 measured against the points triangulated with it, so scaled by (1 + e) too: the position
    after both is off by e (d1 + d2). The step's own r d1 d1^T plus what the next keyframe step adds through
    the scale is that error's covariance (the drift per keyframe 0 here); without the term the next step
    would be as sure as if the units were exact."""
    r = 0.05**2
    vo = sc.VoUnitsScale(filter=sc.ScaleFilter(0.0))
    d0, d1, d2 = np.array([1.0, 0.0, 0.0]), np.array([0.3, 0.0, 1.0]), np.array([0.1, -0.2, 0.9])
    first, _ = MapScaleCovariance(0.0).keyframe_cov(vo, True, d0)
    after, cov1 = first.keyframe_cov(vo, False, d1, length_rel_var(d1, r * np.outer(d1, d1)))
    assert after.var == pytest.approx(r) and np.all(cov1 == 0.0)
    _, cov2 = after.keyframe_cov(vo, False, d2)
    e = np.random.default_rng(5).normal(0.0, np.sqrt(r), 20000)
    errors = e[:, None] * (d1 + d2)[None, :]
    total = r * np.outer(d1, d1) + cov2
    np.testing.assert_allclose(total, r * np.outer(d1 + d2, d1 + d2), rtol=1e-12)
    np.testing.assert_allclose(np.cov(errors.T), total, atol=0.03 * r * (d1 + d2) @ (d1 + d2))


def test_a_step_of_almost_no_length_gives_the_units_no_more_doubt_than_a_rebuilt_map() -> None:
    """A keyframe step whose length its own covariance hardly knows (a relative variance of 9: 300 %)
    carries at most a rebuilt map's ``NEW_MAP_REL_STD`` into the units: past that a first-order
    log-scale says nothing more, and it would blow the position covariance up by orders at once."""
    vo = sc.VoUnitsScale(filter=sc.ScaleFilter(0.0))
    first, _ = MapScaleCovariance(0.0).keyframe_cov(vo, True, np.array([1.0, 0.0, 0.0]))
    after, _ = first.keyframe_cov(vo, False, np.array([0.0, 0.0, 0.01]), 9.0)
    assert after.var == pytest.approx(sc.NEW_MAP_REL_STD**2)


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_a_first_maps_units_carry_the_rotation_error_across_its_baseline_over_the_parallax() -> None:
    """A sideways first baseline at low parallax: triangulated again with the rotation off by ``delta``
    about the axis across the baseline, every depth moves alike by about ``delta / alpha`` (a scale error
    of the whole map); the first map's log-scale variance says as much for a rotation that uncertain."""
    import cv2

    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-2.0, 2.0, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(9.0, 11.0, 200)])
    t = np.array([-0.5, 0.0, 0.0])  # camera moved 0.5 along +x: x_cur = X + t
    xn_ref = X[:, :2] / X[:, 2:]
    Xc = X + t
    xn_cur = Xc[:, :2] / Xc[:, 2:]
    alpha = np.median(np.arccos(np.sum(X * Xc, axis=1) / np.linalg.norm(X, axis=1) / np.linalg.norm(Xc, axis=1)))
    delta = np.radians(0.1)

    def depths(R: np.ndarray) -> np.ndarray:
        P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
        P2 = np.hstack([R, t.reshape(3, 1)])
        Xh = cv2.triangulatePoints(P1, P2, xn_ref.T, xn_cur.T)
        return Xh[2] / Xh[3]

    rel = np.median(depths(_rot_y(delta)) / depths(np.eye(3)) - 1.0)
    assert abs(rel) == pytest.approx(delta / alpha, rel=0.15)
    v = first_map_rel_var(np.array([1.0, 0.0, 0.0]), np.eye(3) * delta**2, float(np.degrees(alpha)))
    assert np.sqrt(v) == pytest.approx(abs(rel), rel=0.15)
    # and a first map built as before takes it: on its baseline and on every later step's units
    vo = sc.VoUnitsScale(filter=sc.ScaleFilter(0.01))
    d = np.array([1.0, 0.0, 0.0])
    m, cov = MapScaleCovariance(0.01).keyframe_cov(vo, True, d, 0.0, v)
    assert m.var == pytest.approx(0.01**2 + v)
    assert d @ cov @ d == pytest.approx(v)


def test_no_parallax_or_no_baseline_gives_the_first_maps_units_no_doubt_rather_than_any() -> None:
    assert first_map_rel_var(np.zeros(3), np.eye(3) * 1e-6, 5.0) == 0.0
    assert first_map_rel_var(np.array([1.0, 0.0, 0.0]), np.eye(3) * 1e-6, 0.0) == 0.0
    assert first_map_rel_var(np.array([1.0, 0.0, 0.0]), np.eye(3) * 1.0, 0.5) == pytest.approx(0.3**2)


def test_between_keyframes_the_path_since_the_keyframe_carries_the_maps_scale_as_the_next_keyframe_will() -> None:
    """The pose between keyframes takes, for its part of the path since the keyframe, the same scale term
    the keyframe step books when that frame becomes the next keyframe: the covariance does not jump there."""
    vo = sc.VoUnitsScale(filter=sc.ScaleFilter(0.01))
    m, _ = MapScaleCovariance(0.01).keyframe_cov(vo, True, np.array([0.0, 0.0, 1.0]), 0.0, 0.04)
    m, _ = m.keyframe_cov(vo, False, np.array([0.2, 0.0, 1.0]), 0.01)
    s = np.array([0.1, 0.3, 0.8])
    _, at_keyframe = m.keyframe_cov(vo, False, s, 0.02)
    np.testing.assert_allclose(m.since_keyframe(s), at_keyframe, rtol=1e-12, atol=1e-15)
    assert s @ m.since_keyframe(s) @ s > (s @ s) ** 2 * m.var  # the covariance with the position adds
