"""Property-based fuzzing (hypothesis) of ``epi-vo summarize`` and ``epi-vo report`` on damaged result files.

A real replay output directory (14 frames of bags/planar, with ground truth) is copied and damaged: a field of
``stats.json``, of a ``frames.jsonl`` record or of ``status.json`` replaced by any JSON value (nested lists
and objects, NaN and infinities, huge numbers, long strings) or removed, a whole file or line replaced by other
JSON or by bytes that are not JSON. Both commands run in-process and must:

1. let no exception escape and print no traceback;
2. exit 0, 2, 3 or 4; exit 2 with exactly one stderr line ``epi-vo: error: ...`` naming the damaged file;
3. exit 0 (report): report.html written; exit 0, 3 or 4 (summarize): summary.csv with the directory's one row.

8 derandomized examples by default; ``--fuzz-examples N`` runs more.
"""

from __future__ import annotations

import csv
import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

import pytest
from bag_copies import BAGS, copy_frames
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from epi_vo.cli import main

DEFAULT_EXAMPLES = 8
FILES = ("stats.json", "frames.jsonl", "status.json")

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20) | st.sampled_from(["x" * 5000, "tracking", "m", "ok", "failed"]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=8)


@st.composite
def damages(draw: st.DrawFn) -> tuple[str, str, Any]:
    """(file, what, value): ``what`` is a field name to replace or remove, '<line>' / '<file>' to replace
    a record or the whole file by ``value`` (JSON, or bytes that are no JSON)."""
    file = draw(st.sampled_from(FILES))
    how = draw(st.sampled_from(["field", "remove", "line", "file"]))
    if how in ("field", "remove"):
        field = draw(st.sampled_from(["frames", "states", "metrics", "notes", "parameters", "units", "stamp",
                                      "index", "state", "timings_ms", "position", "reason", "has_pose",
                                      "status", "bag", "run", "scale_source", "metric_from_frame"]))
        return file, ("-" if how == "remove" else "") + field, draw(json_values)
    value = draw(json_values | st.binary(max_size=40))
    return file, f"<{how}>", value


def _dump(value: Any) -> bytes:
    return value if isinstance(value, bytes) else json.dumps(value).encode()


def damage(d: Path, file: str, what: str, value: Any) -> None:
    path = d / file
    if what == "<file>":
        path.write_bytes(_dump(value))
        return
    if file == "frames.jsonl":
        records = [json.loads(line) for line in path.read_text().splitlines()]
        i = 5
        if what == "<line>":
            lines = [json.dumps(r).encode() for r in records]
            lines[i] = _dump(value)
            path.write_bytes(b"\n".join(lines) + b"\n")
            return
        target = records[i]
    else:
        target = json.loads(path.read_text()) if path.exists() else {}
        records = None
        if what == "<line>":
            path.write_bytes(_dump(value))
            return
    if what.startswith("-"):
        target.pop(what[1:], None)
    else:
        target[what] = value
    text = "".join(json.dumps(r) + "\n" for r in records) if records is not None else json.dumps(target)
    path.write_text(text)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("results")
    bag = copy_frames(BAGS / "planar" / "bag", base / "bag", 14)
    main(["replay", str(bag), str(base / "missing"), "-o", str(base / "fleet"), "--no-progress", "-j", "1"])
    out = base / "fleet" / "bag"  # a fleet's directory: stats.json and status.json
    assert (out / "stats.json").is_file() and (out / "status.json").is_file()
    return out


def check_damage(source: Path, file: str, what: str, value: Any, capsys: pytest.CaptureFixture[str]) -> None:
    with tempfile.TemporaryDirectory(prefix="epi_vo_fuzz_results_") as tmp:
        d = shutil.copytree(source, Path(tmp) / "bag")
        damage(d, file, what, value)
        for command in ("summarize", "report"):
            rc = main([command, str(d)])
            captured = capsys.readouterr()
            note(f"{command}: exit {rc}; {captured.err[-500:]}")
            assert "Traceback" not in captured.out + captured.err
            assert rc in (0, 2, 3, 4), rc
            if rc == 2:
                lines = captured.err.strip().splitlines()
                assert len(lines) == 1 and lines[0].startswith("epi-vo: error: "), captured.err
                assert any(f in lines[0] for f in FILES) or str(d) in lines[0], lines[0]
            elif command == "report":
                assert rc == 0 and (d / "report.html").is_file()
            else:
                with (d / "summary.csv").open(newline="") as f:
                    assert len(list(csv.DictReader(f))) == 1


def test_damaged_result_files_keep_the_invariants(replayed: Path, pytestconfig: pytest.Config,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    requested = pytestconfig.getoption("--fuzz-examples", default=None)
    n = int(requested) if requested else DEFAULT_EXAMPLES

    @settings(max_examples=n, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(damages())
    def probe(case: tuple[str, str, Any]) -> None:
        check_damage(replayed, *case, capsys)

    probe()
