"""Torr's GRIC (epi_vo.core.geometry.gric): known answers on residuals drawn at the noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from epi_vo.core import geometry as geo


def test_gric_known_answer() -> None:
    """Residuals below the cap count as they are, above it as the cap (2 x (4 - 2) = 4); ln 4 per structure
    dimension per point, ln(4 n) per parameter."""
    chi2 = np.array([0.5, 1.0, 10.0])
    expected = 0.5 + 1.0 + 4.0 + math.log(4.0) * 2 * 3 + math.log(12.0) * 8
    assert geo.gric(chi2, 8, 2) == pytest.approx(expected)


@pytest.mark.parametrize("seed", range(5))
def test_the_simpler_model_wins_when_both_leave_the_noise(seed: int) -> None:
    """Both models leave chi-square residuals of the noise (2 dof; the general one a little less, as a
    model with more parameters does): the simpler one's fewer parameters decide."""
    rng = np.random.default_rng(seed)
    chi2 = rng.chisquare(2, 200)
    assert geo.simpler_explains(chi2, 3, 0.95 * chi2, 8)


def test_the_general_model_wins_when_the_simpler_leaves_more_than_the_noise() -> None:
    """A rotation that leaves 2 sigma on every point where H leaves the noise is no rotation."""
    rng = np.random.default_rng(0)
    chi2_h = rng.chisquare(2, 200)
    assert not geo.simpler_explains(chi2_h + 4.0, 3, chi2_h, 8)


def test_points_sent_to_infinity_count_as_outliers() -> None:
    chi2 = np.full(50, 0.5)
    worse = chi2.copy()
    worse[:10] = np.inf
    assert geo.simpler_explains(chi2, 3, worse, 8)
    assert not geo.simpler_explains(worse, 3, chi2, 8)
