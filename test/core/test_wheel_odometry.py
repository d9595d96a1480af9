"""Wheel odometry as it arrives (epi_vo.core.wheel_odometry): one rule for which messages are used, every
dropped one counted, positions interpolated, extrapolated a little, stale."""

from __future__ import annotations

import math

import numpy as np
import pytest

from epi_vo.core import scale as sc
from epi_vo.core.wheel_odometry import HORIZON_S, WheelInputCounts, WheelOdometry, WheelSample


def _fed(arrivals: list[tuple[int | None, np.ndarray]]) -> tuple[WheelOdometry, list[WheelSample]]:
    w, verdicts = WheelOdometry(), []
    for stamp, xyz in arrivals:
        w, verdict = w.add(stamp, xyz)
        verdicts.append(verdict)
    return w, verdicts


def test_wheel_odometry_interpolates_and_says_when_it_is_stale() -> None:
    w, verdicts = _fed([(i * 100_000_000, np.array([i * 0.1, 0.0, 0.0])) for i in range(11)])  # 10 Hz, 1 m/s
    assert verdicts == [WheelSample.USED] * 11
    before = w
    w, verdict = w.add(500_000_000, np.zeros(3))
    assert verdict is WheelSample.OUT_OF_ORDER and len(w) == len(before) == 11  # not newer: ignored
    w, verdict = w.add(2_000_000_000, np.array([np.nan, 0, 0]))
    assert verdict is WheelSample.NON_FINITE
    assert w.ignored == 2 and before.ignored == 0  # the buffer before is as it was
    p, why = w.position_at(250_000_000, 500_000_000)
    assert why == "" and p is not None and p[0] == pytest.approx(0.25)
    p, why = w.position_at(1_200_000_000, 500_000_000)  # 0.2 s after the last: extrapolated
    assert p is not None and p[0] == pytest.approx(1.2)
    p, why = w.position_at(2_000_000_000, 500_000_000)
    assert p is None and "stale" in why and "1.00 s" in why


def test_wheel_messages_are_taken_in_arrival_order_and_every_dropped_one_is_counted() -> None:
    """The one rule of both doors: a message stamped before one received earlier is dropped, whatever
    its stamp would say if sorted; duplicates, non-finite positions and stamps that are no ROS time too."""
    arrivals = [(0, 0.0), (100, 0.1), (200, 0.2), (50, 9.9), (300, 0.3), (300, 7.7), (None, 0.4),
                (400, math.nan), (400, 0.4), (250, 9.9), (500, 0.5)]  # stamps in ms, x in m
    w, verdicts = _fed([(None if t is None else t * 1_000_000, np.array([x, 0.0, 0.0])) for t, x in arrivals])
    W = WheelSample
    assert verdicts == [W.USED, W.USED, W.USED, W.OUT_OF_ORDER, W.USED, W.DUPLICATE_STAMP, W.INVALID_STAMP,
                        W.NON_FINITE, W.USED, W.OUT_OF_ORDER, W.USED]
    assert w.counts == WheelInputCounts(received=11, used=6, out_of_order=2, duplicate_stamp=1, non_finite=1,
                                        invalid_stamp=1)
    # The positions are those of the messages used only: 0.25 s lies between 0.2 m and 0.3 m.
    p, why = w.position_at(250_000_000, 500_000_000)
    assert why == "" and p is not None and p[0] == pytest.approx(0.25)
    assert w.counts.text() == ("11 message(s) received, 6 used: 2 out of order (stamped before a message received "
                               "earlier), 1 with a duplicate stamp, 1 with non-finite positions, 1 with a stamp "
                               "that is no ROS time")


def test_unusable_wheel_messages_are_reported_as_received_and_why() -> None:
    w, _ = _fed([(i * 20_000_000, np.full(3, np.nan)) for i in range(1027)])
    p, why = w.position_at(1_000_000_000, 500_000_000)
    assert p is None
    assert why == "wheel odometry: 1027 message(s) received, 0 used: 1027 with non-finite positions; need 2 usable"
    src = sc.WheelOdometryScale(filter=sc.ScaleFilter(0.02), rel_sigma=0.03, systematic_rel=0.03,
                                timeout_ns=500_000_000)
    src, measured = src.measure(sc.KeyframeStep(np.zeros((0, 3)), 0.1, 0, 1_000_000_000), w)
    assert measured is None
    assert src.reason.startswith("wheel odometry: 1027 message(s) received, 0 used: 1027 with non-finite")
    assert src.status(w).wheel == WheelInputCounts(received=1027, non_finite=1027)


def test_samples_older_than_the_horizon_are_dropped_and_the_newest_stamp_is_kept() -> None:
    w, _ = _fed([(i * 1_000_000_000, np.array([float(i), 0.0, 0.0])) for i in range(70)])  # 1 Hz for 70 s
    assert len(w) == int(HORIZON_S) + 1 and int(w.stamps_ns[0]) == (69 - int(HORIZON_S)) * 1_000_000_000
    p, why = w.position_at(5_000_000_000, 500_000_000)
    assert p is None and "starts" in why
    w, verdict = w.add(3_000_000_000, np.zeros(3))  # pruned from the horizon, still older than the newest
    assert verdict is WheelSample.OUT_OF_ORDER
