"""epi_vo.tools.distribution_table: the per-family statistics (median / p90 / worst on the bad side of each
figure, a figure that could not be computed counted as a failure) and the issue's targets read from them."""

from __future__ import annotations

import math

import pytest

from epi_vo.tools import distribution_table as dt
from epi_vo.tools.benchmark import BenchRow


def row(pipeline: str = "epi_vo", **values: float) -> BenchRow:
    base = {"bag": "x", "pipeline": pipeline, "frames": 40, "tracked_percent": 100.0, "ate_percent": 1.0,
            "rpe_rot_deg": 0.1, "trans_dir_deg": 2.0, "ms_per_frame": 5.0, "moving_frames": 0,
            "gt_path_length": 3.0}
    base.update(values)
    return BenchRow(**base)


def test_high_low_scale_and_nees_statistics() -> None:
    high = dt.summarise([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0], "high")
    assert (high.median, high.p90, high.worst) == (4.5, pytest.approx(7.3), 8.0)
    low = dt.summarise([100.0, 90.0, 80.0, 95.0], "low")
    assert (low.median, low.p90, low.worst) == (92.5, pytest.approx(83.0), 80.0)
    scale = dt.summarise([-1.0, 0.5, 4.0, math.nan], "scale")
    assert (scale.median, scale.worst, scale.judged, scale.seeds) == (0.5, 4.0, 3, 4)
    assert scale.p90 == pytest.approx(3.4)  # of the magnitudes 0.5, 1, 4
    nees = dt.summarise([0.01, 3.0, 20.0], "nees")
    assert nees.median == 3.0 and nees.worst == 0.01  # 300 x too cautious is worse than 6.7 x over-confident
    assert dt.summarise([math.nan, math.nan], "nees") is None


def test_a_figure_that_could_not_be_computed_is_the_worst_case() -> None:
    metric = dt.METRIC_BY_KEY["ate_percent"]
    values = [dt.value_of(row(ate_percent=v), metric) for v in (0.5, 1.0, math.nan)]
    stat = dt.summarise(values, metric.kind)
    assert stat.median == 1.0 and math.isinf(stat.p90) and math.isinf(stat.worst)
    assert dt.cell(stat, metric) == "1.00 / fail / fail"
    never = dt.value_of(row(metric_after_s=math.inf), dt.METRIC_BY_KEY["metric_after_s"])
    assert dt.fmt(never, 2, "never") == "never"


def test_family_statistics_apply_each_figure_where_it_means_something() -> None:
    results = [
        dt.SequenceResult("pure_rotation", s, s / 8, (320, 240), True,
                          (row(ate_percent=math.nan, moved_depth_percent=0.1 * s, keyframes=2),
                           row("reference", ate_percent=math.nan, moving_frames=30)))
        for s in range(3)
    ] + [
        dt.SequenceResult("road", s, s / 8, (480, 360), False,
                          (row(ate_percent=0.5 + s), row("epi_vo[ground_plane]", step_scale=0.95, metric_after_s=2.0,
                                                         ate_se3_percent=3.0),
                           row("reference", ate_percent=4.0)))
        for s in range(3)
    ]
    stats = dt.family_stats(results)
    assert "ate_percent" not in stats["pure_rotation"]["epi_vo"]  # no path: ATE does not apply
    assert stats["pure_rotation"]["epi_vo"]["moved_depth_percent"].worst == pytest.approx(0.2)
    assert stats["pure_rotation"]["reference"]["moving_frames"].median == 30
    assert "moved_depth_percent" not in stats["pure_rotation"]["reference"]  # no map to measure it against
    assert stats["road"]["epi_vo"]["ate_percent"].median == 1.5
    assert stats["road"]["epi_vo[ground_plane]"]["step_scale"].median == pytest.approx(-5.0)
    assert "step_scale" not in stats["road"]["epi_vo"]
    goals = {t.what: t for t in dt.targets(stats, results, [])}
    ours = goals["road: p90 ATE <= half the reference's median"]
    assert ours.met is False and ours.measured == "2.30 vs 2.00"
    assert goals["pure_rotation: moves <= 1 % of the scene depth on every seed"].met is True
    assert goals["road ground_plane: metres within 1 s on the median seed"].met is False
    tables = dt.family_tables(stats, results)
    assert "| road | 480x360 | epi_vo | 1.50 / 2.30 / 2.50 |" in tables
    assert "| pure_rotation | reference | 30 / 30 / 30 | – |" in tables


def test_the_handheld_target_is_judged_at_every_handheld_resolution() -> None:
    """A phone's 1280x720 video is judged against the same target as the 320 px family: a pose on 97 % of the
    frames and at most a keyframe in four, each family on its own seeds."""
    def seqs(family: str, size: tuple[int, int], pose: float, keyframes: int) -> list[dt.SequenceResult]:
        return [dt.SequenceResult(family, s, s / 8, size, False,
                                  (row(tracked_percent=pose, keyframes=keyframes, frames=40),))
                for s in range(3)]

    results = seqs("handheld", (320, 240), 100.0, 8) + seqs("handheld_hd", (1280, 720), 80.0, 24)
    goals = {t.what.split(":")[0]: t for t in dt.targets(dt.family_stats(results), results, [])
             if "keyframe in 4" in t.what}
    assert set(goals) == {"handheld", "handheld_hd"}
    assert goals["handheld"].met is True and goals["handheld"].measured == "100.0 % (100.0), 0.20 (0.20)"
    assert goals["handheld_hd"].met is False and goals["handheld_hd"].measured == "80.0 % (80.0), 0.60 (0.60)"
