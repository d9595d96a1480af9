"""Result files read back: ``summarize`` and ``report`` on a stats.json or frames.jsonl with a field of the
wrong type (one line naming file and field, exit 2, no traceback), and ``summarize`` writing where it is
pointed, never over a larger summary without --force."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from bag_copies import BAGS, copy_frames

from epi_vo.cli import main


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fleet of two small bags: OUT/planar, OUT/general_motion and OUT/summary.csv."""
    src = tmp_path_factory.mktemp("src")
    bags = [copy_frames(BAGS / name / "bag", src / name, 14) for name in ("planar", "general_motion")]
    out = tmp_path_factory.mktemp("fleet") / "out"
    assert main(["replay", *map(str, bags), "-o", str(out), "--no-progress", "-j", "1"]) == 0
    return out


def _one_error_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("epi-vo: error: "), captured.err
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


STATS_CASES: list[tuple[str, Any, str]] = [
    ("frames", "many", "frames is 'many', expected an integer"),
    ("states", 5, "states is 5, expected an object"),
    ("states", {"tracking": "x"}, "states.tracking is 'x', expected an integer"),
    ("tracked_percent", "x", "tracked_percent is 'x', expected a number or null"),
    ("notes", 3, "notes is 3, expected a list"),
    ("notes", [1], "notes[0] is 1, expected a string"),
    ("metrics", [1], "metrics is [1], expected an object or null"),
    ("metric_from_frame", 1.5, "metric_from_frame is 1.5, expected an integer or null"),
    ("units", ["m"], "units is ['m'], expected a string"),
    ("stage_ms", {"total": "x"}, "stage_ms.total is 'x'"),
    ("parameters", "x", "parameters is 'x', expected an object"),
    ("rejected_frames", True, "rejected_frames is True, expected an integer"),
]


@pytest.mark.parametrize(("field", "value", "said"), STATS_CASES, ids=[f"{c[0]}={c[1]!r}" for c in STATS_CASES])
def test_a_wrong_typed_stats_json_is_one_line(replayed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                             field: str, value: Any, said: str) -> None:
    d = shutil.copytree(replayed / "planar", tmp_path / "planar")
    stats = json.loads((d / "stats.json").read_text())
    stats[field] = value
    (d / "stats.json").write_text(json.dumps(stats))
    assert main(["summarize", str(d)]) == 2
    _one_error_line(capsys, str(d / "stats.json"), said)
    assert not (d / "summary.csv").exists()
    assert main(["report", str(d)]) == 2
    _one_error_line(capsys, "stats.json", said)


@pytest.mark.parametrize("text", ["[1, 2]", "{", '"ok"'])
def test_a_stats_json_that_is_no_object_is_one_line(replayed: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str], text: str) -> None:
    d = shutil.copytree(replayed / "planar", tmp_path / "planar")
    (d / "stats.json").write_text(text)
    for command in ("summarize", "report"):
        assert main([command, str(d)]) == 2
        _one_error_line(capsys, "stats.json")


RECORD_CASES: list[tuple[str, Any, str]] = [
    ("stamp", "abc", "stamp is 'abc', expected a number"),
    ("index", 1.5, "index is 1.5, expected an integer"),
    ("state", "bogus", "state is 'bogus', expected one of"),
    ("timings_ms", 5, "timings_ms is 5, expected an object"),
    ("has_pose", "yes", "has_pose is 'yes', expected true or false"),
    ("position", "x", "position is 'x', expected a list"),
    ("reason", 7, "reason is 7, expected a string"),
    ("rh", [1], "rh is [1], expected a number or null"),
    ("moving_region", "x", "moving_region is 'x', expected a list or null"),
]


@pytest.mark.parametrize(("field", "value", "said"), RECORD_CASES, ids=[f"{c[0]}={c[1]!r}" for c in RECORD_CASES])
def test_a_wrong_typed_frame_record_is_one_line(replayed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                               field: str, value: Any, said: str) -> None:
    d = shutil.copytree(replayed / "planar", tmp_path / "planar")
    records = [json.loads(line) for line in (d / "frames.jsonl").read_text().splitlines()]
    records[4][field] = value
    (d / "frames.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    assert main(["report", str(d)]) == 2
    _one_error_line(capsys, f"{d / 'frames.jsonl'}:5: {said}")
    assert main(["summarize", str(d)]) == 0  # the summary is made from stats.json alone


def test_the_record_types_cover_every_key_a_record_has(replayed: Path) -> None:
    from epi_vo.tools.json_check import fields_problem
    from epi_vo.tools.report_data import RECORD_TYPES

    for line in (replayed / "planar" / "frames.jsonl").read_text().splitlines():
        record = json.loads(line)
        assert set(record) == set(RECORD_TYPES)
        assert fields_problem(record, RECORD_TYPES, "frames.jsonl") is None


# --------------------------------------------------------------------------------------------------
# Where summarize writes


def _names(path: Path) -> list[str]:
    with path.open(newline="") as f:
        return [r["name"] for r in csv.DictReader(f)]


def test_summarize_writes_where_it_is_pointed(replayed: Path, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    out = shutil.copytree(replayed, tmp_path / "out")
    fleet_summary = (out / "summary.csv").read_bytes()
    assert _names(out / "summary.csv") == ["planar", "general_motion"]
    # One bag's directory: its summary goes there; the fleet's summary keeps every byte.
    assert main(["summarize", str(out / "planar")]) == 0
    assert _names(out / "planar" / "summary.csv") == ["planar"]
    assert (out / "summary.csv").read_bytes() == fleet_summary
    capsys.readouterr()
    # Pointed at the fleet's directory: it would drop a bag, so it is refused unless --force.
    assert main(["summarize", str(out / "planar"), "-o", str(out)]) == 2
    _one_error_line(capsys, str(out / "summary.csv"), "lists 2 bag(s), 1 of which this summary of 1 would drop",
                    "general_motion", "--force")
    assert (out / "summary.csv").read_bytes() == fleet_summary
    assert main(["summarize", str(out / "planar"), "-o", str(out), "--force"]) == 0
    assert _names(out / "summary.csv") == ["planar"]
    # The same bags (or more) replace it without --force.
    assert main(["summarize", str(out)]) == 0
    assert sorted(_names(out / "summary.csv")) == ["general_motion", "planar"]
    capsys.readouterr()
    # Several directories: the summary needs a place.
    assert main(["summarize", str(out / "planar"), str(out / "general_motion")]) == 2
    _one_error_line(capsys, "2 directories given", "--output")
    # A summary.csv that is not ours is no summary to replace.
    other = tmp_path / "other"
    other.mkdir()
    (other / "summary.csv").write_text("date,km\n2026-01-01,3\n")
    assert main(["summarize", str(out / "planar"), "-o", str(other)]) == 2
    _one_error_line(capsys, "is not an epi-vo summary")
    assert (other / "summary.csv").read_text() == "date,km\n2026-01-01,3\n"
