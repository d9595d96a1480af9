"""The replay's side of the one wheel odometry rule (``epi_vo.core.scale.WheelOdometry``): messages in the
bag's order, a message stamped before one received earlier dropped, every dropped message counted and said.

The bags are bags/ground_robot with its wheel stream modified (test/wheel_streams.py); the node's side, live
over DDS, is test/ros/test_node_scale.py.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from wheel_streams import every_third_early, write_wheel_variant

from epi_vo.cli import main
from epi_vo.core.config import VoConfig
from epi_vo.tools import evaluation
from epi_vo.tools.replay import run_replay

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "ground_robot" / "bag"
WHEELS = dataclasses.replace(VoConfig(), scale_source="wheel_odometry", wheel_odometry_topic="/wheel/odom")
N_WHEEL = 1027  # messages of the bag's wheel topic


def _records(out: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


def test_messages_stamped_early_are_dropped_and_said_not_sorted_into_the_stream(tmp_path: Path) -> None:
    # Every third message stamped 0.3 s early: sorted by stamp (as the replay did) they put positions 0.3 s
    # in the wrong place; the step scale came out 1.25, position NEES 23, with no note. Taken in arrival
    # order, as the node takes them, they are dropped and counted, and metres hold.
    bag = write_wheel_variant(BAG, tmp_path / "bag", every_third_early)
    s = run_replay(bag, tmp_path / "out", WHEELS)
    assert s.units == "m" and s.metrics is not None
    assert 0.97 <= s.metrics["step_scale_median"] <= 1.03
    nees = evaluation.replay_dir_nees(tmp_path / "out")
    assert nees is not None and nees.mean_nees_pos <= 6.0
    assert s.wheel_odometry == {"received": N_WHEEL, "used": N_WHEEL - N_WHEEL // 3, "out_of_order": N_WHEEL // 3,
                                "duplicate_stamp": 0, "non_finite": 0, "invalid_stamp": 0}
    assert (f"wheel odometry on /wheel/odom: {N_WHEEL} message(s) received, {N_WHEEL - N_WHEEL // 3} used: "
            f"{N_WHEEL // 3} out of order (stamped before a message received earlier)") in s.notes
    # Each frame's record says what arrived by then and what became of it.
    recs = _records(tmp_path / "out")
    counts = [r["wheel_messages"] for r in recs]
    assert all(c["received"] == c["used"] + c["out_of_order"] for c in counts)
    assert [c["received"] for c in counts] == sorted(c["received"] for c in counts)
    assert counts[-1]["out_of_order"] >= N_WHEEL // 3 - 20


def test_wheel_messages_that_cannot_be_used_are_counted_and_the_reason_says_why(tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture[str]
                                                                               ) -> None:
    def nan_position(k: int, msg: Any) -> None:
        msg.pose.pose.position.x = math.nan
        msg.pose.pose.position.y = math.nan
        msg.pose.pose.position.z = math.nan

    bag = write_wheel_variant(BAG, tmp_path / "bag", nan_position, n_images=60)
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    scale_source: wheel_odometry\n"
                      "    wheel_odometry_topic: /wheel/odom\n")
    assert main(["replay", str(bag), "--output", str(tmp_path / "out"), "--params", str(params),
                 "--no-progress"]) == 0
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    n = stats["wheel_odometry"]["received"]
    assert n > 150 and stats["wheel_odometry"] == {"received": n, "used": 0, "out_of_order": 0, "duplicate_stamp": 0,
                                                   "non_finite": n, "invalid_stamp": 0}
    note = f"wheel odometry on /wheel/odom: {n} message(s) received, 0 used: {n} with non-finite positions"
    assert note in stats["notes"] and note in capsys.readouterr().out
    assert stats["units"] == "vo"
    # The frames' scale reason: how many arrived and why none could be used, never "0 message(s) received".
    keyframes = [r for r in _records(tmp_path / "out") if r["is_keyframe"] and r["index"] > 0]
    assert keyframes
    for r in keyframes:
        received = r["wheel_messages"]["received"]
        assert received > 0 and r["wheel_messages"]["non_finite"] == received
        assert r["scale_reason"].startswith(f"wheel odometry: {received} message(s) received, 0 used: {received} "
                                            "with non-finite positions; need 2 usable")
    assert np.all([r["units"] == "vo" for r in _records(tmp_path / "out")])
