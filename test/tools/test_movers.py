"""Independent motion end to end: a static camera watching a large mover never moves, and says what moved
(bags/static_mover); a moving camera with a mover crossing its view (bags/moving_mover) is the open part."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from epi_vo.tools.replay import ReplaySummary, run_replay

BAGS = Path(__file__).resolve().parents[2] / "bags"
FPS = 15


def _records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def static_mover(tmp_path_factory: pytest.TempPathFactory) -> tuple[ReplaySummary, list[dict]]:
    out = tmp_path_factory.mktemp("static_mover")
    return run_replay(BAGS / "static_mover" / "bag", out), _records(out)


def test_static_camera_never_moves_with_a_mover_in_view(static_mover: tuple[ReplaySummary, list[dict]]) -> None:
    s, recs = static_mover
    assert s.frames == 120 and s.tracked_percent == 100.0
    assert s.path_length == 0.0
    assert all(r["position"] == [0.0, 0.0, 0.0] for r in recs)
    assert s.keyframes < 20  # no map is built from the panel's motion
    after_first_second = recs[FPS:]
    static = [r for r in after_first_second if r["state"] == "static"]
    assert len(static) >= 0.9 * len(after_first_second)
    assert all(r["model"] == "static" and r["n_triangulated"] == 0 for r in static)


def test_static_frames_say_what_moved_and_where(static_mover: tuple[ReplaySummary, list[dict]]) -> None:
    _, recs = static_mover
    cov = np.loadtxt(BAGS / "static_mover" / "mover_coverage.txt")
    by_frame = {int(row[0]): row for row in cov}
    overlaps = 0
    static = [r for r in recs if r["state"] == "static"]
    for r in static:
        assert r["n_moving"] > 0 and 0.1 < r["moving_fraction"] < 0.8
        assert r["static_score"] == pytest.approx(1.0 - r["moving_fraction"], abs=1e-6)
        assert "another object's motion, ignored" in r["reason"]
        x0, y0, x1, y1 = r["moving_region"]
        _, _, bx0, by0, bx1, by1 = by_frame[r["index"]]
        # The movers' box (5-95 percentiles of the moved features) lies on the panel's box.
        if x0 < bx1 and bx0 < x1 and y0 < by1 and by0 < y1:
            overlaps += 1
    assert overlaps >= 0.9 * len(static)


def test_a_mover_taking_es_consensus_is_caught_by_the_map(tmp_path: Path) -> None:
    """The cart crossing the view takes E's consensus on some frames; the map's points (the static scene)
    catch it: the pose then comes from the map, and the path error stays far below the 16 % it was."""
    s = run_replay(BAGS / "moving_mover" / "bag", tmp_path)
    recs = _records(tmp_path)
    caught = [r for r in recs if "E disagrees with the map's points" in r["reason"]]
    assert len(caught) >= 10
    cov = {int(row[0]): row[1] for row in np.loadtxt(BAGS / "moving_mover" / "mover_coverage.txt")}
    assert cov[caught[0]["index"]] > 0.25  # it starts with the cart filling a quarter of the view
    # Mostly while the cart is in view; after it left, a map it contaminated keeps disagreeing a while.
    assert sum(cov[r["index"]] > 0.1 for r in caught) >= 2 * len(caught) / 3
    assert s.metrics is not None and s.metrics["ate_percent_of_path"] < 8.0


@pytest.mark.xfail(strict=True, reason="OPEN (issue 11): mover rejection while the camera moves is not built; the "
                   "cart crossing the view still drags the pose (Sim(3) ATE ~5.6 % of path, RPE rot ~0.9 deg/frame)")
def test_moving_camera_with_a_mover_meets_the_target(tmp_path: Path) -> None:
    s = run_replay(BAGS / "moving_mover" / "bag", tmp_path)
    assert s.metrics is not None and s.tracked_percent == 100.0
    assert s.metrics["ate_percent_of_path"] <= 1.0
    assert s.metrics["rpe_rot_deg_per_frame"] <= 0.05
