"""The frame record (epi_vo.core.frame): what FrameResult accepts, and what to_record writes."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest

from epi_vo.core.frame import (
    MAX_STAMP_NS,
    STAT_FIELDS,
    FrameResult,
    Matches,
    Model,
    TrackingState,
    frozen,
    stamp_seconds,
)
from epi_vo.core.transforms import make_T, rotation_from_quat_xyzw


def _pose() -> np.ndarray:
    c, s = math.cos(0.3), math.sin(0.3)
    return make_T(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [1.0, -2.0, 0.5])


def _result(**changes: Any) -> FrameResult:
    fields: dict[str, Any] = dict(
        index=7, stamp_ns=1_500_000_000, state=TrackingState.TRACKING, has_pose=True, is_keyframe=False,
        model=Model.ESSENTIAL, rh=0.2, n_features=200, n_tracked=180, n_inliers=150, inlier_ratio=150 / 180,
        median_parallax_deg=1.5, n_triangulated=0, positive_depth_ratio=math.nan, median_reproj_err_px=math.nan,
        relative_scale=0.8, n_keyframes=3, T_w_c=frozen(_pose()), covariance=frozen(np.diag([1e-3] * 3 + [1e-5] * 3)),
        points_w=frozen(np.array([[0.0, 1.0, 5.0], [1.0, 2.0, 7.0]])), timings_ms={"frontend": 1.25, "total": 3.5},
        reason="", matches=Matches.empty())
    fields.update(changes)
    return FrameResult(**fields)


def test_a_valid_record_is_accepted_and_keeps_its_values() -> None:
    r = _result()
    np.testing.assert_array_equal(r.position, [1.0, -2.0, 0.5])
    np.testing.assert_allclose(rotation_from_quat_xyzw(r.quat_xyzw), _pose()[:3, :3], atol=1e-12)
    assert not r.rejected and not r.skipped
    assert not r.T_w_c.flags.writeable


@pytest.mark.parametrize("stamp_ns", [0, 1, MAX_STAMP_NS])
def test_stamps_at_the_limits_of_a_ros_time_are_accepted(stamp_ns: int) -> None:
    assert _result(stamp_ns=stamp_ns).stamp_ns == stamp_ns


@pytest.mark.parametrize("stamp_ns", [-1, -10**18, MAX_STAMP_NS + 1, 2**63])
def test_stamps_outside_a_ros_time_are_refused(stamp_ns: int) -> None:
    with pytest.raises(AssertionError, match=f"stamp {stamp_ns}"):
        _result(stamp_ns=stamp_ns)


def _with_nan(a: np.ndarray, value: float = math.nan) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.flat[a.size // 2] = value
    return a


@pytest.mark.parametrize("name", ["T_w_c", "covariance", "points_w"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_pose_covariance_or_points_are_refused(name: str, value: float) -> None:
    good = _result()
    with pytest.raises(AssertionError, match=name):
        _result(**{name: _with_nan(getattr(good, name), value)})


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_timings_are_refused(value: float) -> None:
    with pytest.raises(AssertionError, match="timings_ms"):
        _result(timings_ms={"frontend": 1.0, "total": value})


@pytest.mark.parametrize("name", STAT_FIELDS)
@pytest.mark.parametrize("value", [math.inf, -math.inf])
def test_infinite_statistics_are_refused(name: str, value: float) -> None:
    with pytest.raises(AssertionError, match=name):
        _result(**{name: value})


def test_every_problem_is_named_at_once() -> None:
    with pytest.raises(AssertionError) as info:
        _result(stamp_ns=-5, T_w_c=_with_nan(_pose()), rh=math.inf, timings_ms={"total": math.nan})
    message = str(info.value)
    for part in ("FrameResult 7", "stamp -5", "T_w_c", "rh", "timings_ms"):
        assert part in message
    assert "covariance" not in message and "points_w" not in message


def test_nan_statistics_are_allowed_and_written_as_null() -> None:
    nan_stats = {name: math.nan for name in STAT_FIELDS}
    r = _result(**nan_stats)
    rec = r.to_record()
    for name in STAT_FIELDS:
        assert rec[name] is None, name
    text = json.dumps(rec, allow_nan=False)  # raises ValueError if anything non-finite is left
    assert json.loads(text)["rh"] is None


def test_to_record_writes_the_values_of_the_record() -> None:
    r = _result(points_w=np.zeros((5, 3)), state=TrackingState.ROTATION_ONLY, model=Model.HOMOGRAPHY,
                reason="pure rotation", timings_ms={"total": 3.14159})
    rec = json.loads(json.dumps(r.to_record(), allow_nan=False))
    assert rec["index"] == 7 and rec["stamp_ns"] == 1_500_000_000 and rec["stamp"] == 1.5
    assert rec["state"] == "rotation_only" and rec["model"] == "H"
    assert rec["rh"] == 0.2 and rec["relative_scale"] == 0.8 and rec["median_reproj_err_px"] is None
    assert rec["n_points"] == 5 and rec["n_inliers"] == 150 and rec["n_keyframes"] == 3
    assert rec["position"] == [1.0, -2.0, 0.5]
    np.testing.assert_allclose(rec["quat_xyzw"], [0.0, 0.0, math.sin(0.15), math.cos(0.15)], atol=1e-12)
    assert rec["covariance_diagonal"] == pytest.approx([1e-3] * 3 + [1e-5] * 3)
    assert rec["timings_ms"] == {"total": 3.142}
    assert rec["reason"] == "pure rotation" and rec["skipped"] is False and rec["rejected"] is False


def test_a_problem_makes_the_record_rejected() -> None:
    r = dataclasses.replace(_result(), skipped=True, problem="bad image")
    assert r.rejected and r.to_record()["rejected"] is True and r.to_record()["skipped"] is True


def test_stamp_seconds_never_rounds_above_the_stamp() -> None:
    s = stamp_seconds(MAX_STAMP_NS)
    assert s < 2**31  # ns * 1e-9 would round up to 2**31 s, which is no ROS time
    assert 2**31 - s < 1e-6
    assert stamp_seconds(0) == 0.0 and stamp_seconds(1_500_000_000) == 1.5
