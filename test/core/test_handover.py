"""The hand-over to a new map after a loss (epi_vo.core.handover): the covariance a new map starts from covers
the motion the platform could make while nothing measured it (test_pipeline_gap.py: a blackout end to end)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from epi_vo.core.config import VoConfig
from epi_vo.core.handover import Handover, bounded_motion_var
from epi_vo.core.transforms import make_T


def test_a_bounded_motion_is_spread_over_its_bound() -> None:
    # 1 s from rest, 2 m/s^2 and at most 5 m/s: at most 1 m, variance 1/3.
    assert bounded_motion_var(0.0, 5.0, 2.0, 1.0, 1e9) == pytest.approx(1.0 / 3.0)
    # From 1 m/s: 1 + 1 = 2 m; over 10 s the top speed bounds it (50 m, not 10 + 100).
    assert bounded_motion_var(1.0, 5.0, 2.0, 1.0, 1e9) == pytest.approx(4.0 / 3.0)
    assert bounded_motion_var(1.0, 5.0, 2.0, 10.0, 1e9) == pytest.approx(2500.0 / 3.0)
    assert bounded_motion_var(1.0, 5.0, 2.0, 10.0, math.pi) == pytest.approx(math.pi**2 / 3.0)  # a half turn
    assert bounded_motion_var(1.0, 5.0, 2.0, -1.0, 1e9) == 0.0


def test_the_handover_grows_with_the_gap_and_the_platform() -> None:
    cfg = dataclasses.replace(VoConfig(), max_speed_mps=1.0, max_accel_mps2=0.5, max_turn_rate_deg_s=30.0,
                              max_turn_accel_deg_s2=20.0)
    h = Handover.from_config(cfg)
    assert h.covariance(10**9, metric=True) is None  # no pose with a map yet
    cov0 = np.diag([1e-4] * 3 + [1e-6] * 3)
    T1 = make_T(np.eye(3), np.array([0.0, 0.0, 0.04]))
    h = h.booked(0, np.eye(4), cov0).booked(100_000_000, T1, cov0)  # 0.4 m/s straight ahead
    metric = [h.covariance(100_000_000 + int(gap * 1e9), metric=True) for gap in (0.1, 1.0, 4.0)]
    assert all(c is not None for c in metric)
    pos = [float(c[0, 0] - 1e-4) for c in metric if c is not None]
    rot = [float(c[3, 3] - 1e-6) for c in metric if c is not None]
    # 0.4 m/s x t + 0.5 m/s^2 x t^2 / 2: 0.0425 m in 0.1 s, 0.65 m in 1 s; over 4 s the top speed (4 m).
    np.testing.assert_allclose(pos, [0.0425**2 / 3, 0.65**2 / 3, 16.0 / 3], rtol=1e-9)
    # From no turn, 20 deg/s^2 x t^2 / 2: 0.1 deg, 10 deg; over 4 s the top rate (120 deg, not 160).
    np.testing.assert_allclose(rot, np.radians([0.1, 10.0, 120.0]) ** 2 / 3, rtol=1e-9)
    # In VO units a speed in metres has no length: the last speed over the gap is one sigma.
    vo = h.covariance(100_000_000 + 10**9, metric=False)
    assert vo is not None and vo[0, 0] - 1e-4 == pytest.approx(0.4**2)
