"""scripts/keyframe_steps.py: keyframe steps of the rotation covariance against their errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
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


def test_a_replay_of_general_motion(tmp_path: Path) -> None:
    """The figures the README gives for general_motion (12 keyframe steps, step NEES 0.67)."""
    from epi_vo.core.config import VoConfig
    from epi_vo.tools.replay import run_replay

    run_replay(REPO / "bags" / "general_motion" / "bag", tmp_path, VoConfig())
    s = keyframe_steps.replay_steps(tmp_path)
    assert s.steps == 12
    assert 0.4 < s.nees_mean < 1.0
    assert np.all(s.rms_error_deg < s.rms_sigma_deg)
    assert keyframe_steps.main([str(tmp_path)]) == 0
