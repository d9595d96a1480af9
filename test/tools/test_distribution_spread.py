"""The benchmark's run-to-run spread: camera_info's focal length perturbed by an amount nobody could tell
apart (epi_vo.tools.perturb), replayed (run_replay's camera_info_edit) and summarised per family
(epi_vo.tools.distribution_spread)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.io import tum
from epi_vo.tools import distribution_table as dt
from epi_vo.tools.bench_record import jsonable
from epi_vo.tools.benchmark import BenchRow
from epi_vo.tools.distribution import real_tasks
from epi_vo.tools.distribution_spread import (
    real_spread,
    real_spread_compare,
    real_spread_table,
    spread,
    spread_compare,
    spread_table,
)
from epi_vo.tools.perturb import scaled_focal
from epi_vo.tools.replay import run_replay

BAG = Path(__file__).resolve().parents[2] / "bags" / "general_motion" / "bag"


def _info(**over: object) -> SimpleNamespace:
    base: dict[str, object] = {"width": 640, "height": 480, "distortion_model": "plumb_bob",
                               "d": [0.01, -0.02, 0.0, 0.0, 0.0], "k": [500.0, 0.0, 320.0, 0.0, 505.0, 240.0,
                                                                        0.0, 0.0, 1.0],
                               "binning_x": 0, "binning_y": 0,
                               "roi": SimpleNamespace(x_offset=0, y_offset=0, width=0, height=0, do_rectify=False)}
    base.update(over)
    return SimpleNamespace(**base)


def test_the_focal_lengths_alone_are_scaled() -> None:
    msg = _info()
    edited = scaled_focal(1e-3)(msg)
    k = np.asarray(edited.k).reshape(3, 3)
    assert k[0, 0] == pytest.approx(500.5, abs=1e-12) and k[1, 1] == pytest.approx(505.505, abs=1e-12)
    assert (k[0, 2], k[1, 2], k[0, 1], k[2, 2]) == (320.0, 240.0, 0.0, 1.0)
    assert msg.k[0] == 500.0 and msg.k[4] == 505.0  # the recorded message is left as it was
    before, after = CameraModel.from_camera_info(msg), CameraModel.from_camera_info(edited)
    assert (after.width, after.height, after.model) == (before.width, before.height, before.model)
    np.testing.assert_array_equal(after.D, before.D)
    assert after.K[0, 0] / before.K[0, 0] == pytest.approx(1.001, rel=1e-12)


@pytest.mark.parametrize("rel", [-1.0, math.nan, math.inf])
def test_an_impossible_focal_change_is_refused(rel: float) -> None:
    with pytest.raises(ValueError, match="focal perturbation"):
        scaled_focal(rel)


def test_the_pipeline_sees_the_edited_camera_info(tmp_path: Path) -> None:
    uncalibrated = run_replay(BAG, tmp_path / "zero", camera_info_edit=scaled_focal(-0.9999))
    assert uncalibrated.frames_with_pose == 0 and uncalibrated.rejected_frames == uncalibrated.frames > 0
    plain = run_replay(BAG, tmp_path / "plain")
    twin = run_replay(BAG, tmp_path / "twin", camera_info_edit=scaled_focal(1e-3))
    assert twin.frames_with_pose == plain.frames_with_pose == plain.frames
    _, p_plain, _ = tum.read_tum(tmp_path / "plain" / "trajectory.tum")
    _, p_twin, _ = tum.read_tum(tmp_path / "twin" / "trajectory.tum")
    # a calibration 0.1 % apart: another run (not bit-identical) that goes the same way on this clean bag
    assert not np.array_equal(p_plain, p_twin)
    path = float(np.sum(np.linalg.norm(np.diff(p_plain, axis=0), axis=1)))
    assert float(np.max(np.linalg.norm(p_plain - p_twin, axis=1))) < 0.02 * path


def _result(family: str, seed: int, ate: float, static: bool = False) -> dt.SequenceResult:
    row = BenchRow("x", "epi_vo", 40, 100.0, ate, 0.1, 2.0, 5.0, 0, 3.0)
    return dt.SequenceResult(family, seed, 0.5, (320, 240), static, (row,))


def test_each_run_the_pooled_figures_and_the_seeds_that_flip() -> None:
    plain = [_result("fast", s, a) for s, a in enumerate([1.0, 2.0, 0.1, 4.0])] + [_result("still", 0, 0.0, True)]
    twin = [_result("fast", s, a) for s, a in enumerate([1.1, 3.5, 0.3, math.nan])] + [_result("still", 0, 0.0, True)]
    data = spread({0.0: plain, 1e-3: twin})
    assert set(data) == {"fast"}  # a still camera has no ATE to spread
    fast = data["fast"]
    assert [r["focal_rel"] for r in fast["runs"]] == [0.0, 1e-3]
    assert fast["runs"][0]["median"] == pytest.approx(1.5)
    assert math.isinf(fast["runs"][1]["p90"])  # seed 3 failed in the twin run: a failure, not a missing seed
    assert fast["pooled"]["n"] == 8 and fast["pooled"]["median"] == pytest.approx(1.55)
    # s1 2.0 / 3.5 flips; s0 1.0 / 1.1 is noise; s2 0.1 / 0.3 is three times but under half a percent
    assert [f["seed"] for f in fast["flipping"]] == [1, 3]
    assert fast["largest_spread"] == pytest.approx(1.5)  # s1's; a failed run is counted as flipping, not as a spread
    table = spread_table(data)
    assert "| fast | 1.50 / " in table and "s1 2.00/3.50" in table and "focal +0.10%" in table


def test_the_pooled_figures_are_compared_only_with_the_same_perturbations() -> None:
    runs = {0.0: [_result("orbit", 0, 1.0)], 1e-3: [_result("orbit", 0, 2.0)]}
    after = {"spread": spread(runs)}
    before = {"spread": spread({0.0: [_result("orbit", 0, 1.0)], 1e-3: [_result("orbit", 0, 1.2)]})}
    text = spread_compare(before, after)
    assert "| orbit | 1.10 -> 1.50 |" in text and "| 0 -> 1 |" in text
    failed = jsonable({"spread": spread({0.0: [_result("orbit", 0, math.nan)], 1e-3: [_result("orbit", 0, 1.0)]})})
    # a failed figure is null in a record
    assert "| orbit | 1.10 -> fail | 1.18 -> fail | 0 -> 1 |" in spread_compare(before, failed)
    other = {"spread": spread({0.0: [_result("orbit", 0, 1.0)], -1e-3: [_result("orbit", 0, 1.2)]})}
    assert "are not this run's" in spread_compare(other, after)
    assert "no run-to-run spread" in spread_compare({}, after)


def _real_row(clip: str, pipeline: str, ate: float, se3: float = math.nan) -> BenchRow:
    return dataclasses.replace(BenchRow(clip, pipeline, 51, 100.0, ate, 0.1, 2.0, 5.0, 0, 3.0), ate_se3_percent=se3)


def test_real_clips_are_run_again_under_every_perturbation_without_the_reference() -> None:
    clips = [("kitti", Path("k/bag"), Path("k/gt")), ("tello", Path("t/bag"), Path("t/gt"))]
    tasks = real_tasks(clips, VoConfig(), True, (1e-3, -1e-3))
    assert [(t.name, t.focal_rel, t.reference) for t in tasks] == [
        ("kitti", 0.0, True), ("tello", 0.0, True), ("kitti", 1e-3, False), ("tello", 1e-3, False),
        ("kitti", -1e-3, False), ("tello", -1e-3, False)]


def test_each_real_clip_gets_its_runs_their_median_and_spread() -> None:
    runs = {0.0: [_real_row("kitti", "epi_vo", 0.15), _real_row("kitti", "epi_vo[ground_plane]", 0.39, 0.61),
                  _real_row("kitti", "reference", 4.0)],
            1e-3: [_real_row("kitti", "epi_vo", 0.16), _real_row("kitti", "epi_vo[ground_plane]", 0.47, 0.70)],
            -1e-3: [_real_row("kitti", "epi_vo", 0.20), _real_row("kitti", "epi_vo[ground_plane]", math.nan)]}
    data = real_spread(runs)
    assert set(data) == {"kitti epi_vo", "kitti epi_vo[ground_plane]"}  # the reference runs once: no spread
    plain = data["kitti epi_vo"]
    assert [r["focal_rel"] for r in plain["runs"]] == [0.0, -1e-3, 1e-3]
    assert plain["median"] == pytest.approx(0.16) and plain["spread"] == pytest.approx(0.05)
    gp = data["kitti epi_vo[ground_plane]"]
    assert gp["median"] == pytest.approx(0.47)  # the failed run counts as the worst
    assert gp["spread"] == pytest.approx(0.08)  # of the runs with a figure
    table = real_spread_table(data)
    assert "| kitti epi_vo[ground_plane] | 0.39 (SE3 0.61) | fail | 0.47 (SE3 0.70) | 0.47 | 0.08 |" in table
    before = jsonable({"real_spread": real_spread({0.0: [_real_row("kitti", "epi_vo", 0.15)],
                                                   -1e-3: [_real_row("kitti", "epi_vo", 0.15)],
                                                   1e-3: [_real_row("kitti", "epi_vo", 0.30)]})})
    text = real_spread_compare(before, jsonable({"real_spread": data}))
    assert "| kitti epi_vo | 0.15 -> 0.16 | 0.15 -> 0.05 |" in text
    assert "no comparison" in real_spread_compare(
        jsonable({"real_spread": real_spread({0.0: [_real_row("kitti", "epi_vo", 0.15)]})}), {"real_spread": data})
    assert real_spread_compare({}, {"real_spread": data}) == "The baseline has no real clips' twins to compare with."
