"""The generated parameter reference (epi_vo.io.params_doc, `epi-vo params --markdown`) and docs/parameters.md."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from epi_vo import cli
from epi_vo.core.config import PIPELINE_NAMES, VoConfig, config_fields, field_doc
from epi_vo.io.node_options import NODE_DOCS, NODE_OPTION_NAMES, NodeOptions
from epi_vo.io.params_doc import REGENERATE, parameters_markdown, table_cell

REPO = Path(__file__).resolve().parents[2]
REFERENCE = REPO / "docs" / "parameters.md"


def _rows(text: str) -> dict[str, list[str]]:
    """{parameter: [default, allowed, at runtime, doc]} from the reference's table rows."""
    rows = {}
    for line in text.splitlines():
        m = re.match(r"^\| `(\w+)` \| (.*) \|$", line)
        if m:
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", m.group(2))]
            assert m.group(1) not in rows, f"{m.group(1)} listed twice"
            rows[m.group(1)] = cells
    return rows


def test_docs_parameters_md_is_the_generators_output() -> None:
    """docs/parameters.md cannot drift from VoConfig / NodeOptions: it must be exactly what the generator writes."""
    assert REFERENCE.read_text() == parameters_markdown(), f"docs/parameters.md is stale: run {REGENERATE}"


def test_every_parameter_has_one_row_with_its_default_range_and_doc() -> None:
    rows = _rows(parameters_markdown())
    assert list(rows) == [*NODE_OPTION_NAMES, *PIPELINE_NAMES]
    for f in config_fields():
        assert rows[f.name][3] == " ".join(field_doc(f).split()), f.name
    for name in NODE_OPTION_NAMES:
        assert rows[name][3] == " ".join(NODE_DOCS[name].split()), name
    assert rows["max_features"][:3] == ["`200`", "20 to 5000", "next frame"]
    assert rows["frontend"][:2] == ["`klt`", "`klt`, `orb`"]
    assert rows["lost_position_variance"][:2] == ["`10000.0`", "1 to 1e12"]
    assert rows["scale_source"][2] == "restart" and rows["wheel_odometry_topic"][2] == "restart"
    assert rows["camera_xyz"][:3] == ["`[0.0, 0.0, 0.0]`", "3 numbers", "restart"]
    assert rows["queue_size"][2] == "at once" and rows["hardware_id"][0] == "`''`"
    assert rows["qos_reliability"][1] == "`best_effort`, `reliable`"


def test_the_reference_follows_a_changed_default_and_escapes_table_pipes() -> None:
    cfg = dataclasses.replace(VoConfig(), max_features=321)
    rows = _rows(parameters_markdown(cfg, dataclasses.replace(NodeOptions(), frame_id="odom_vo")))
    assert rows["max_features"][0] == "`321`" and rows["frame_id"][0] == "`odom_vo`"
    assert table_cell("a | b\n   c") == "a \\| b c"


def test_cli_params_markdown_prints_the_reference(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["params", "--markdown"]) == 0
    assert capsys.readouterr().out == parameters_markdown()
