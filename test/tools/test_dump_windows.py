"""scripts/dump_windows.py: every window of a replay's windowed adjustment, pickled in order."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from script_module import load_script

from epi_vo.core import bundle

dump_windows = load_script("dump_windows")
BAG = Path(__file__).resolve().parents[2] / "bags" / "general_motion" / "bag"


def test_the_windows_of_a_replay_are_pickled_and_solve_as_in_the_replay(tmp_path: Path) -> None:
    params = tmp_path / "window.yaml"
    params.write_text("/**:\n  ros__parameters:\n    ba_window_keyframes: 4\n    ba_every_keyframes: 1\n"
                      "    ba_solver: process\n")
    out = tmp_path / "out"
    n = dump_windows.dump(BAG, out, params)
    records = [json.loads(line) for line in (out / "replay" / "frames.jsonl").read_text().splitlines()]
    adjusted = [r for r in records if "window_solve" in r["timings_ms"]]
    applied = [r for r in records if r["window_correction"] is not None]
    files = sorted(out.glob("window_*.pkl"))
    assert n == len(files) >= 3
    # one window per adjustment the replay made; the last one submitted is collected at the next
    # keyframe, which the bag may end before
    assert n - 1 <= len(adjusted) <= n
    assert len(applied) == len(adjusted)
    first = pickle.loads(files[0].read_bytes())
    assert isinstance(first, bundle.Window) and first.T_w_kf.shape[0] >= 2
    again = [bundle.adjust(pickle.loads(f.read_bytes())) for f in files]
    assert all(a is not None for a in again)
    # the same window solves the same way (the replay's adjustment is deterministic)
    twice = bundle.adjust(first)
    assert twice is not None and again[0] is not None
    assert np.array_equal(twice.T_w_kf, again[0].T_w_kf)
    assert (bundle.adjust.__module__, bundle.adjust.__name__) == ("epi_vo.core.bundle", "adjust")  # hook undone


def test_parameters_without_a_window_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = tmp_path / "none.yaml"
    params.write_text("/**:\n  ros__parameters:\n    ba_window_keyframes: 0\n")
    assert dump_windows.main([str(BAG), str(tmp_path / "out"), "--params", str(params)]) == 2
    assert "ba_window_keyframes: 0" in capsys.readouterr().err
    assert not list((tmp_path / "out").glob("window_*.pkl"))
