"""epi_vo.tools.bench_record: a benchmark's dated record says where its figures come from, in strict JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from epi_vo.core.errors import OutputError
from epi_vo.tools.bench_record import RecordHeader, write_record


def test_the_record_is_dated_and_names_commit_machine_command_and_libraries(tmp_path: Path) -> None:
    header = RecordHeader.now(["benchmark", "--suite", "subset"])
    assert len(header.commit) == 40 and header.cores >= 1
    assert header.libraries["numpy"] != "not installed" and header.libraries["opencv-python-headless"]
    md_text = header.markdown("a title", {"benchmark time": "12 s"})
    for part in ("# a title", f"`{header.commit}`", "`epi-vo benchmark --suite subset`", "- benchmark time: 12 s",
                 "numpy ", header.date):
        assert part in md_text
    md, js = write_record(tmp_path / "benchmarks", "subset", md_text + "\n\n| table |",
                          {"value": math.nan, "rows": [(1.0, math.inf)]}, header.date)
    assert md.name == f"{header.date}-subset.md" and md.read_text().endswith("| table |\n")
    assert json.loads(js.read_text()) == {"value": None, "rows": [[1.0, None]]}  # strict JSON: n/a is null


def test_an_unwritable_record_is_a_one_line_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="cannot write the benchmark record under"):
        write_record(blocker / "sub", "bundled", "x", {}, "2026-11-28")
