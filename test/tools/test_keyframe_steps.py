"""scripts/keyframe_steps.py: keyframe steps of the rotation covariance against their errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from exact_calibration import exact
from script_module import load_script

REPO = Path(__file__).resolve().parents[2]
keyframe_steps = load_script("keyframe_steps")


def _walk(rng: np.random.Generator, n: int, sigma: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """A rotation error that is a random walk of n steps with per-axis sigma, each step correlated with
    the previous one by rho (AR(1)), and the covariance a random walk model publishes for it."""
    steps = np.zeros((n, 3))
    for k in range(1, n):
        steps[k] = rho * steps[k - 1] + np.sqrt(1.0 - rho**2) * rng.normal(0.0, sigma)
    errors = np.cumsum(steps, axis=0)
    covs = np.array([np.diag(sigma**2) * k for k in range(n)])
    return errors, covs


def test_a_random_walk_is_consistent_step_by_step() -> None:
    errors, covs = _walk(np.random.default_rng(0), 2001, np.array([1e-4, 2e-4, 3e-4]), 0.0)
    s = keyframe_steps.step_statistics(errors, covs)
    assert s.steps == 2000
    assert s.nees_mean == pytest.approx(3.0, rel=0.1)
    np.testing.assert_allclose(s.rms_error_deg, s.rms_sigma_deg, rtol=0.1)
    assert np.all(np.abs(s.lag1) < 0.1)
    np.testing.assert_allclose(s.sum_ratio, 1.0, atol=0.3)


def test_correlated_steps_add_up_coherently() -> None:
    """Steps with lag-1 correlation 0.5: each step alone is as predicted, but 10 of them summed spread
    ~2.8x as much in variance as 10 independent ones ((1 + rho) / (1 - rho) - edge terms)."""
    errors, covs = _walk(np.random.default_rng(1), 4001, np.array([1e-4, 1e-4, 1e-4]), 0.5)
    s = keyframe_steps.step_statistics(errors, covs)
    assert s.nees_mean == pytest.approx(3.0, rel=0.1)
    np.testing.assert_allclose(s.lag1, 0.5, atol=0.06)
    assert np.all((s.sum_ratio > 2.2) & (s.sum_ratio < 3.3))


def _rot(v: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(v, dtype=np.float64).reshape(3, 1))[0]


def test_relative_to_the_keyframe_consistent_and_overgrown() -> None:
    """Frames 1-3 after a keyframe whose error relative to it is drawn from a covariance of sigma^2 per
    axis: NEES 3 at every count when the published covariance grows by sigma^2; 3 / n when it grows by
    n sigma^2 (the error does not grow with the frames, the covariance does)."""
    rng = np.random.default_rng(2)
    sigma = 1e-3
    R_gt, R_est, P, P_over, pairs = [], [], [], [], []
    for _ in range(1500):
        base = _rot(rng.normal(0.0, 0.3, 3))
        k = len(R_gt)
        R_gt.append(base)
        R_est.append(base)
        P.append(np.eye(3) * 1e-6)
        P_over.append(np.eye(3) * 1e-6)
        for n in (1, 2, 3):
            truth = base @ _rot(rng.normal(0.0, 0.05, 3))
            R_gt.append(truth)
            R_est.append(truth @ _rot(rng.normal(0.0, sigma, 3)))
            P.append(np.eye(3) * (1e-6 + sigma**2))
            P_over.append(np.eye(3) * (1e-6 + n * sigma**2))
            pairs.append((k, len(R_gt) - 1, n))
    R_gt, R_est = np.array(R_gt), np.array(R_est)
    ok = keyframe_steps.since_keyframe_nees(R_est, R_gt, np.array(P), pairs)
    over = keyframe_steps.since_keyframe_nees(R_est, R_gt, np.array(P_over), pairs)
    assert sorted(ok) == [1, 2, 3] and all(c == 1500 for c, _ in ok.values())
    for n in (1, 2, 3):
        assert ok[n][1] == pytest.approx(3.0, rel=0.1)
        assert over[n][1] == pytest.approx(3.0 / n, rel=0.1)


def test_a_replay_of_general_motion(tmp_path: Path) -> None:
    """general_motion: 12 keyframe steps, their NEES near 1.3 (consistent: E's poses take the tracks' noise in
    the current image only, ``covariance.ONE_IMAGE_SHARE``), each step's error inside its sigma."""
    from epi_vo.tools.replay import run_replay

    run_replay(REPO / "bags" / "general_motion" / "bag", tmp_path, exact())  # the bag's camera is exact
    s = keyframe_steps.replay_steps(tmp_path)
    assert s.steps == 12
    assert 0.9 < s.nees_mean < 2.0
    assert np.all(s.rms_error_deg < s.rms_sigma_deg)
    # relative to the keyframe: about 1.4, 1.2, 1.0 at 1, 2, 3 frames after it (12, 12, 11 frames)
    since = keyframe_steps.replay_since_keyframe(tmp_path)
    assert [since[n][0] for n in (1, 2, 3)] == [12, 12, 11]
    assert 0.9 < since[1][1] < 2.0 and since[3][1] < since[2][1] < since[1][1]
    assert keyframe_steps.main([str(tmp_path)]) == 0
