"""Tests for epi_vo.core.transforms: quaternion <-> rotation, rigid transforms, rotation angle."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from epi_vo.core.errors import EpiVoError
from epi_vo.core.transforms import (
    invert_T,
    make_T,
    quat_xyzw_from_rotation,
    rotation_angle_deg,
    rotation_from_quat_xyzw,
)


def _random_quats_xyzw(count: int, seed: int) -> np.ndarray:
    """Uniformly distributed unit quaternions (normalised 4-D Gaussians), w >= 0."""
    quats = np.random.default_rng(seed).normal(size=(count, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats[quats[:, 3] < 0] *= -1.0
    return quats


def _rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    rvec = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis) * angle_rad
    R, _ = cv2.Rodrigues(rvec)
    return R


def _same_rotation_quat(q_a: np.ndarray, q_b: np.ndarray) -> bool:
    """q and -q are the same rotation."""
    return bool(np.allclose(q_a, q_b, atol=1e-12) or np.allclose(q_a, -q_b, atol=1e-12))


# --- quaternion <-> rotation -------------------------------------------------------------------


def test_identity_known_answer() -> None:
    np.testing.assert_array_equal(quat_xyzw_from_rotation(np.eye(3)), [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(rotation_from_quat_xyzw([0.0, 0.0, 0.0, 1.0]), np.eye(3))


def test_quarter_turn_about_z_known_answer() -> None:
    R_a_b = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    half = np.sqrt(0.5)
    np.testing.assert_allclose(quat_xyzw_from_rotation(R_a_b), [0.0, 0.0, half, half], atol=1e-15)
    np.testing.assert_allclose(rotation_from_quat_xyzw([0.0, 0.0, half, half]), R_a_b, atol=1e-15)


def test_random_rotations_round_trip() -> None:
    for quat_xyzw in _random_quats_xyzw(500, seed=7):
        R_a_b = rotation_from_quat_xyzw(quat_xyzw)
        np.testing.assert_allclose(R_a_b @ R_a_b.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(R_a_b) == pytest.approx(1.0, abs=1e-14)
        back = quat_xyzw_from_rotation(R_a_b)
        np.testing.assert_allclose(back, quat_xyzw, atol=1e-12)
        assert back[3] >= 0.0


def test_matches_opencv_rodrigues() -> None:
    rng = np.random.default_rng(11)
    for rvec in rng.uniform(-np.pi, np.pi, size=(100, 3)):
        R_a_b, _ = cv2.Rodrigues(rvec)
        np.testing.assert_allclose(
            rotation_from_quat_xyzw(quat_xyzw_from_rotation(R_a_b)), R_a_b, atol=1e-12
        )


@pytest.mark.parametrize(
    "axis",
    [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 0.0), (0.3, -0.5, 0.8)],
)
def test_half_turns_are_exact(axis: tuple[float, float, float]) -> None:
    """180 degrees: trace -1, w = 0; the naive sqrt(1 + trace) formula fails here."""
    n = np.asarray(axis) / np.linalg.norm(axis)
    R_a_b = 2.0 * np.outer(n, n) - np.eye(3)
    quat_xyzw = quat_xyzw_from_rotation(R_a_b)
    assert _same_rotation_quat(quat_xyzw, np.array([*n, 0.0]))
    np.testing.assert_allclose(rotation_from_quat_xyzw(quat_xyzw), R_a_b, atol=1e-15)


def test_near_half_turns_round_trip() -> None:
    rng = np.random.default_rng(3)
    for axis in rng.normal(size=(50, 3)):
        for angle in (np.pi - 1e-9, np.pi - 1e-5, np.pi):
            R_a_b = _rotation_about(axis, angle)
            R_back = rotation_from_quat_xyzw(quat_xyzw_from_rotation(R_a_b))
            np.testing.assert_allclose(R_back, R_a_b, atol=1e-12)


def test_rotation_from_quat_normalises() -> None:
    quat_xyzw = _random_quats_xyzw(1, seed=1)[0]
    np.testing.assert_allclose(
        rotation_from_quat_xyzw(3.5 * quat_xyzw), rotation_from_quat_xyzw(quat_xyzw), atol=1e-15
    )
    # -q is the same rotation.
    np.testing.assert_allclose(
        rotation_from_quat_xyzw(-quat_xyzw), rotation_from_quat_xyzw(quat_xyzw), atol=1e-15
    )


def test_quat_from_slightly_non_orthonormal_rotation_is_unit() -> None:
    R_a_b = rotation_from_quat_xyzw(_random_quats_xyzw(1, seed=5)[0]) + 1e-9
    assert np.linalg.norm(quat_xyzw_from_rotation(R_a_b)) == pytest.approx(1.0, abs=1e-15)


def test_zero_quaternion_raises() -> None:
    with pytest.raises(EpiVoError, match="norm 0, cannot be normalised"):
        rotation_from_quat_xyzw([0.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: rotation_from_quat_xyzw([0.0, 0.0, 1.0]), r"quat_xyzw has shape \(3,\)"),
        (lambda: rotation_from_quat_xyzw([np.nan, 0, 0, 1]), "quat_xyzw contains non-finite"),
        (lambda: quat_xyzw_from_rotation(np.eye(4)), r"R_a_b has shape \(4, 4\)"),
        (lambda: quat_xyzw_from_rotation(np.full((3, 3), np.inf)), "R_a_b contains non-finite"),
        (lambda: make_T(np.eye(3), [1.0, 2.0]), r"t_a_b has shape \(2,\)"),
        (lambda: invert_T(np.eye(3)), r"T_a_b has shape \(3, 3\)"),
        (lambda: rotation_angle_deg(np.zeros(3)), r"R_a_b has shape \(3,\)"),
    ],
)
def test_bad_input_raises(call, match: str) -> None:
    with pytest.raises(EpiVoError, match=match):
        call()


# --- rigid transforms ----------------------------------------------------------------------------


def test_make_T_known_answer() -> None:
    R_a_b = _rotation_about([0.0, 0.0, 1.0], np.pi / 2)
    T_a_b = make_T(R_a_b, np.array([[1.0], [2.0], [3.0]]))
    X_b = np.array([1.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(T_a_b @ X_b, [1.0, 3.0, 3.0, 1.0], atol=1e-15)
    np.testing.assert_array_equal(T_a_b[3], [0.0, 0.0, 0.0, 1.0])


def test_invert_T_round_trip() -> None:
    rng = np.random.default_rng(2)
    for quat_xyzw in _random_quats_xyzw(50, seed=9):
        T_a_b = make_T(rotation_from_quat_xyzw(quat_xyzw), rng.normal(scale=10.0, size=3))
        T_b_a = invert_T(T_a_b)
        np.testing.assert_allclose(T_b_a @ T_a_b, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(T_b_a, np.linalg.inv(T_a_b), atol=1e-12)


# --- rotation angle ------------------------------------------------------------------------------


@pytest.mark.parametrize("angle_deg", [0.0, 1e-6, 0.5, 30.0, 90.0, 135.0, 179.9, 180.0])
def test_rotation_angle_known_answers(angle_deg: float) -> None:
    R_a_b = _rotation_about([0.2, -1.0, 0.4], np.radians(angle_deg))
    assert rotation_angle_deg(R_a_b) == pytest.approx(angle_deg, rel=1e-9, abs=1e-12)


def test_rotation_angle_is_symmetric_in_direction() -> None:
    R_a_b = _rotation_about([1.0, 2.0, 3.0], 0.7)
    assert rotation_angle_deg(R_a_b.T) == pytest.approx(rotation_angle_deg(R_a_b), abs=1e-12)
