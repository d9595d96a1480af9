"""Ground truth is a topic named as ground truth, or the one given with --gt / --gt-topic; never a robot's own
odometry found in the bag and never the scale source's topic; --no-gt takes none."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from bag_copies import BAGS, copy_frames

from epi_vo.cli import main

WHEEL = "/wheel/odom"


@pytest.fixture(scope="module")
def wheel_only(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """ground_robot's first 40 frames with its wheel odometry, without its ground truth."""
    return copy_frames(BAGS / "ground_robot" / "bag", tmp_path_factory.mktemp("gr") / "wheel_only", 40,
                       drop_topics={"/ground_truth/pose"})


def _stats(out: Path) -> dict:
    return json.loads((out / "stats.json").read_text())


def test_wheel_odometry_is_not_taken_for_ground_truth(wheel_only: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(wheel_only), "-o", str(tmp_path / "a"), "--no-progress"]) == 0
    stats = _stats(tmp_path / "a")
    assert stats["gt_source"] == "" and stats["metrics"] is None
    assert not (tmp_path / "a" / "groundtruth.tum").exists()
    assert "vs GT" not in capsys.readouterr().out


def test_a_chosen_topic_is_ground_truth_but_never_the_scale_source(wheel_only: Path, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(wheel_only), "-o", str(tmp_path / "b"), "--gt-topic", WHEEL, "--no-progress"]) == 0
    stats = _stats(tmp_path / "b")
    assert stats["gt_source"] == f"bag topic {WHEEL}" and stats["metrics"]["matched_poses"] > 20
    capsys.readouterr()
    params = tmp_path / "wheels.yaml"
    params.write_text("/**:\n  ros__parameters:\n    scale_source: wheel_odometry\n"
                      f"    wheel_odometry_topic: {WHEEL}\n")
    assert main(["replay", str(wheel_only), "-o", str(tmp_path / "c"), "--gt-topic", WHEEL, "--params", str(params),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == (f"epi-vo: error: --gt-topic '{WHEEL}' is the wheel odometry topic, the scale source: "
                           "ground truth must be independent of what it judges")


def test_no_gt_takes_none_and_a_named_topic_is_found(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = copy_frames(BAGS / "ground_robot" / "bag", tmp_path / "gr", 30)
    assert main(["replay", str(bag), "-o", str(tmp_path / "d"), "--no-progress"]) == 0
    assert _stats(tmp_path / "d")["gt_source"] == "bag topic /ground_truth/pose"  # beside /wheel/odom
    assert main(["replay", str(bag), "-o", str(tmp_path / "e"), "--no-gt", "--no-progress"]) == 0
    assert _stats(tmp_path / "e")["gt_source"] == "" and _stats(tmp_path / "e")["metrics"] is None
    capsys.readouterr()
    # --gt, --gt-topic and --no-gt exclude each other.
    with pytest.raises(SystemExit) as exc:
        main(["replay", str(bag), "-o", str(tmp_path / "f"), "--no-gt", "--gt-topic", WHEEL])
    assert exc.value.code == 2
    assert "--gt-topic: not allowed with argument --no-gt" in capsys.readouterr().err
    # A fleet takes --gt-topic / --no-gt for every bag; a fleet re-run with another choice is not "complete".
    fleet = tmp_path / "fleet"
    assert main(["replay", str(bag), str(tmp_path / "wheel_only_missing"), "-o", str(fleet), "--no-gt",
                 "--no-progress", "-j", "1"]) == 4
    assert _stats(fleet / "gr")["gt_source"] == ""
    assert main(["replay", str(bag), str(tmp_path / "wheel_only_missing"), "-o", str(fleet), "--no-progress",
                 "-j", "1"]) == 4
    assert _stats(fleet / "gr")["gt_source"] == "bag topic /ground_truth/pose"
