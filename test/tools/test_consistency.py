"""``epi-vo replay`` with ground truth judges its own covariance (issue 14): the NEES of the published pose
and twist, from the odometry samples kept in memory, equal to what the benchmark and the report compute
from output.mcap read back."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from epi_vo.io import tum
from epi_vo.io.odometry_bag import read_estimate_odometry
from epi_vo.tools.consistency import NEES_KEYS, format_consistency
from epi_vo.tools.evaluation import replay_dir_nees
from epi_vo.tools.replay import format_summary, run_replay
from epi_vo.tools.twist_consistency import replay_twist_nees

BAGS = Path(__file__).resolve().parents[2] / "bags"


def test_replay_reports_the_covariance_consistency_it_published(tmp_path: Path) -> None:
    s = run_replay(BAGS / "general_motion" / "bag", tmp_path)
    assert s.metrics is not None
    m = s.metrics
    assert set(NEES_KEYS) <= set(m)
    pose = replay_dir_nees(tmp_path)
    records = [json.loads(line) for line in (tmp_path / "frames.jsonl").read_text().splitlines()]
    twist = replay_twist_nees(records, read_estimate_odometry(tmp_path / "output.mcap"),
                              tum.read_tum(tmp_path / "groundtruth.tum"))
    assert pose is not None and m["nees_frames"] == pose.evaluated == 50
    assert m["nees_pos"] == pytest.approx(pose.mean_nees_pos, rel=1e-9)
    assert m["nees_rot"] == pytest.approx(pose.mean_nees_rot, rel=1e-9)
    assert m["nees_pos_inside_percent"] == pytest.approx(pose.inside_pos_percent)
    assert m["nees_twist_linear"] == pytest.approx(twist.mean_linear, rel=1e-9)
    assert m["nees_twist_angular"] == pytest.approx(twist.mean_angular, rel=1e-9)
    assert m["nees_twist_angular_inside_percent"] == pytest.approx(twist.inside_angular_percent)
    # consistent (3 in expectation), none off by an order of magnitude (the bag's row: docs/benchmarks)
    assert 0.5 < m["nees_pos"] < 6 and 0.5 < m["nees_rot"] < 6 and 1.0 < m["nees_twist_angular"] < 6
    stats = json.loads((tmp_path / "stats.json").read_text())["metrics"]
    assert stats["nees_pos"] == pytest.approx(m["nees_pos"])
    line = next(x for x in format_summary(s).splitlines() if x.strip().startswith("covariance"))
    assert f"NEES pos {m['nees_pos']:.2f} ({m['nees_pos_inside_percent']:.1f} % in 3σ)" in line
    assert f"w {m['nees_twist_angular']:.2f}" in line and "50 tracking frames" in line


def test_a_run_without_tracking_frames_says_its_covariance_was_not_judged(tmp_path: Path) -> None:
    s = run_replay(BAGS / "pure_rotation" / "bag", tmp_path)
    assert s.metrics is not None and s.metrics["nees_frames"] == 0 and math.isnan(s.metrics["nees_pos"])
    assert json.loads((tmp_path / "stats.json").read_text())["metrics"]["nees_pos"] is None  # strict JSON
    assert "covariance    not judged: no tracking frame with ground truth" in format_summary(s)
    assert format_consistency({"ate_rmse": 1.0}) is None  # a stats.json from before: no line
