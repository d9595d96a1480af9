"""scripts/window_budget.py: the windowed adjustment's figures against a live node's frame budget."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from script_module import load_script

window_budget = load_script("window_budget")


def _records() -> list[dict]:
    """15 Hz; keyframes at frames 0, 1, 3, 4; adjustments collected at frames 3 (submitted at 1: 133 ms
    between them, solved in 100 ms: in time) and 4 (submitted at 3: 67 ms, solved in 90 ms: late)."""
    out = []
    for i in range(8):
        t = {"total": 5.0 + i}
        if i == 3:
            t.update(window_wait=45.0, window_solve=100.0, total=50.0)
        if i == 4:
            t.update(window_wait=25.0, window_solve=90.0, total=30.0)
        out.append({"stamp": 100.0 + i / 15.0, "is_keyframe": i in (0, 1, 3, 4), "timings_ms": t})
    return out


def test_budget_takes_the_waits_out_and_counts_the_late_adjustments() -> None:
    b = window_budget.budget(_records())
    assert b.frames == 8 and b.adjustments == 2 and b.late == 1
    assert b.flat_median_ms == pytest.approx(10.5)  # 5 6 7 10 11 12 30 50
    assert b.live_median_ms == pytest.approx(6.5)  # 5 5 5 6 7 10 11 12: the waits taken out
    assert b.solve_median_ms == pytest.approx(95.0) and b.solve_max_ms == 100.0


def test_the_script_prints_a_row_per_replay_and_refuses_a_directory_without_frames(tmp_path: Path, capsys) -> None:
    run = tmp_path / "gr"
    run.mkdir()
    (run / "frames.jsonl").write_text("\n".join(json.dumps(r) for r in _records()) + "\n")
    assert window_budget.main([str(run)]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("gr "))
    assert row.split() == ["gr", "8", "10.50", "43.00", "6.50", "11.65", "2", "95.0", "99.5", "100.0", "1"]
    assert window_budget.main([str(tmp_path / "nothing")]) == 2
    assert "no frames.jsonl" in capsys.readouterr().err
