"""The scale stage (epi_vo.core.scale): VO units, baseline 1 first, then the last keyframe speed."""

from __future__ import annotations

import pytest

from epi_vo.core.scale import VoUnitsScale


def test_first_map_has_baseline_one_whatever_the_time() -> None:
    scale = VoUnitsScale()
    assert scale.metric_source is False and scale.established is False
    assert scale.status().units == "vo" and scale.status().source == "none"
    assert scale.speed is None
    for dt in (0.0, 0.05, 1.0, 100.0, -3.0):
        assert scale.initial_baseline(dt) == 1.0


def test_after_a_keyframe_the_baseline_is_speed_times_dt() -> None:
    scale = VoUnitsScale()
    scale.on_keyframe(0.5, 0.25)  # 2 map units per second
    assert scale.speed == pytest.approx(2.0)
    assert scale.initial_baseline(0.1) == pytest.approx(0.2)
    assert scale.initial_baseline(1.5) == pytest.approx(3.0)


def test_the_last_keyframe_speed_wins() -> None:
    scale = VoUnitsScale()
    scale.on_keyframe(0.5, 0.25)
    scale.on_keyframe(0.3, 1.0)
    assert scale.speed == pytest.approx(0.3)
    assert scale.initial_baseline(2.0) == pytest.approx(0.6)


@pytest.mark.parametrize("dt", [0.0, -0.1])
def test_a_keyframe_step_without_elapsed_time_is_ignored(dt: float) -> None:
    scale = VoUnitsScale()
    scale.on_keyframe(1.0, dt)
    assert scale.speed is None and scale.initial_baseline(0.5) == 1.0
    scale.on_keyframe(0.4, 0.2)
    scale.on_keyframe(5.0, dt)
    assert scale.speed == pytest.approx(2.0)


@pytest.mark.parametrize("dt", [0.0, -1.0])
def test_a_baseline_without_elapsed_time_falls_back_to_one(dt: float) -> None:
    scale = VoUnitsScale()
    scale.on_keyframe(0.4, 0.2)
    assert scale.initial_baseline(dt) == 1.0
