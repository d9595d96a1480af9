"""Wheel odometry positions by stamp (epi_vo.core.wheels): interpolated, extrapolated a little, stale."""

from __future__ import annotations

import numpy as np
import pytest

from epi_vo.core.wheels import HORIZON_S, WheelOdometry


def test_wheel_odometry_interpolates_and_says_when_it_is_stale() -> None:
    w = WheelOdometry()
    for i in range(11):  # 10 Hz, 1 m/s along x
        w, added = w.add(i * 100_000_000, np.array([i * 0.1, 0.0, 0.0]))
        assert added
    for stamp, xyz in ((500_000_000, np.zeros(3)), (2_000_000_000, np.array([np.nan, 0, 0]))):
        before = w
        w, added = w.add(stamp, xyz)  # not newer, not finite: ignored
        assert not added and len(w) == len(before) == 11
    assert w.ignored == 2
    p, why = w.position_at(250_000_000, 500_000_000)
    assert why == "" and p is not None and p[0] == pytest.approx(0.25)
    p, why = w.position_at(1_200_000_000, 500_000_000)  # 0.2 s after the last: extrapolated
    assert p is not None and p[0] == pytest.approx(1.2)
    p, why = w.position_at(2_000_000_000, 500_000_000)
    assert p is None and "stale" in why and "1.00 s" in why


def test_samples_older_than_the_horizon_are_dropped() -> None:
    w = WheelOdometry()
    for i in range(70):  # 1 Hz for 70 s
        w, _ = w.add(i * 1_000_000_000, np.array([float(i), 0.0, 0.0]))
    assert len(w) == int(HORIZON_S) + 1 and int(w.stamps_ns[0]) == (69 - int(HORIZON_S)) * 1_000_000_000
    p, why = w.position_at(5_000_000_000, 500_000_000)
    assert p is None and "starts" in why
