"""The hand-over to a new map after a loss (epi_vo.core.handover): the covariance a new map starts from covers
the motion the platform could make while nothing measured it (test_pipeline_gap.py: a blackout end to end)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from epi_vo.core.config import VoConfig
from epi_vo.core.handover import Handover, HeldStart, bounded_motion_var
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


S = 1_000_000_000  # ns per second


def test_a_held_start_takes_the_motion_its_frames_measured_not_the_first_speed_over_the_time() -> None:
    # Held from 10 s; the reference's tracks showed 1 deg of parallax at 10.5 s, where the reference moved
    # on (that frame measured: nothing blind). The new map moves 1 unit in 0.25 s at 2 deg: 0.5 deg per unit,
    # so the held motion is 0.5 units, spread over the axes. Its first speed over the 0.5 s would say 2.
    held = HeldStart.at(10 * S).seen(10 * S + S // 2, 1.0).reanchored(10 * S + S // 2)
    assert held.motion_var(1.0, 0.25, 2.0) == pytest.approx(0.5**2 / 3.0)
    # Nothing held (the map from its first reference): nothing added.
    assert HeldStart.at(10 * S).motion_var(1.0, 0.25, 2.0) == 0.0
    # Without the new map's parallax the first speed over the held time stays the one standard deviation.
    assert held.motion_var(1.0, 0.25, math.nan) == pytest.approx(2.0**2)


def test_the_blind_time_of_a_held_start_moves_at_the_speeds_on_either_side() -> None:
    # 0.2 deg at 0.2 s (1 deg/s), then nothing tracked until a new reference at 0.4 s, and again until one
    # at 0.6 s. The new map: 1 unit in 0.1 s (10 units/s) at 2 deg (0.5 units per degree). Measured:
    # 0.5 * 0.2 = 0.1; blind 0.4 s from 0.5 units/s to 10: 0.4 * (0.5 + 10) / 2 = 2.1.
    held = HeldStart.at(0).seen(S // 5, 0.2).reanchored(2 * S // 5).reanchored(3 * S // 5)
    assert held.blind_s == pytest.approx(0.4)
    assert held.motion_var(1.0, 0.1, 2.0) == pytest.approx((0.1 + 2.1) ** 2 / 3.0)
    # A parallax not measured (NaN) leaves what was seen as it was.
    assert HeldStart.at(0).seen(S, math.nan) == HeldStart.at(0)
