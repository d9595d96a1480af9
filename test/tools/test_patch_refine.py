"""klt_patch_refine_px end to end: the ground-robot bag (a floor whose patches scale and shear as the robot
drives over it) replayed with each track refined against its first image, against its ground truth."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from epi_vo.core.config import VoConfig
from epi_vo.tools.replay import ReplaySummary, run_replay

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "ground_robot" / "bag"


@pytest.fixture(scope="module")
def refined(tmp_path_factory: pytest.TempPathFactory) -> tuple[ReplaySummary, Path]:
    out = tmp_path_factory.mktemp("refined")
    return run_replay(BAG, out, dataclasses.replace(VoConfig(), klt_patch_refine_px=15)), out


def test_refined_tracks_follow_the_floor_closer(refined: tuple[ReplaySummary, Path]) -> None:
    """Sim(3) ATE about 0.04 % of the path and 0.0074 deg/frame RPE rotation where chained KLT gives 0.204 %
    and 0.0093 (the bag's epi_vo row in docs/benchmarks; its own test bounds it by 1 %). The bounds leave
    room for other OpenCV builds, and fail on the default tracks."""
    s, out = refined
    assert s.tracked_percent == 100.0 and s.metrics is not None
    assert s.metrics["ate_percent_of_path"] < 0.08
    assert s.metrics["rpe_rot_deg_per_frame"] < 0.0085
    recs = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert sum(r["state"] == "tracking" for r in recs) >= 295
    # The record says how many tracks were refined: 94 % of the tracked ones (median; 137-177 per frame).
    refined = [r["n_refined"] / r["n_tracked"] for r in recs if r["state"] == "tracking"]
    assert recs[0]["n_refined"] is None and sorted(refined)[len(refined) // 2] > 0.8


def test_without_refinement_the_record_says_none() -> None:
    from epi_vo.core.camera import CameraModel
    from epi_vo.core.pipeline import VoPipeline
    from epi_vo.io.bagio import open_camera_bag
    from epi_vo.io.msgconv import decode_frame

    pipe = VoPipeline(VoConfig())
    records = []
    with open_camera_bag(BAG) as bag:
        for frame in bag.iter_frames():
            gray = decode_frame(frame.image_msg, bag.image_is_compressed)
            res = pipe.process(gray, CameraModel.from_camera_info(frame.camera_info_msg), frame.stamp_ns)
            records.append(res.to_record())
            if frame.index == 3:
                break
    assert [r["n_refined"] for r in records] == [None] * 4
    assert records[-1]["n_tracked"] > 100
