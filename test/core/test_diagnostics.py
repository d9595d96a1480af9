"""Tests for epi_vo.core.diagnostics: the DiagnosticStatusRecord checks and level coercion."""

from __future__ import annotations

import dataclasses

import pytest

from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.errors import EpiVoError


def test_int_level_becomes_enum() -> None:
    record = DiagnosticStatusRecord(2, "epi_vo: tracking", "lost", "camera", (("inliers", "3"),))
    assert record.level is DiagnosticLevel.ERROR
    assert int(record.level) == 2
    assert record.values == (("inliers", "3"),)


def test_values_default_empty_and_list_becomes_tuple() -> None:
    assert DiagnosticStatusRecord(0, "n", "m", "h").values == ()
    record = DiagnosticStatusRecord(0, "n", "m", "h", [("k", "v")])  # type: ignore[arg-type]
    assert record.values == (("k", "v"),)


def test_record_is_frozen() -> None:
    record = DiagnosticStatusRecord(DiagnosticLevel.OK, "n", "m", "h")
    with pytest.raises(dataclasses.FrozenInstanceError):
        record.level = DiagnosticLevel.WARN  # type: ignore[misc]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"level": 7}, r"diagnostic level 7 is not one of \[0, 1, 2, 3\]"),
        ({"name": None}, "diagnostic name must be str, got None"),
        ({"values": (("k", 1),)}, r"values must be \(key, value\) pairs of str, got \('k', 1\)"),
        ({"values": ("kv",)}, "values must be"),
    ],
)
def test_bad_fields_raise(kwargs: dict, match: str) -> None:
    fields = {"level": 0, "name": "n", "message": "m", "hardware_id": "h", "values": ()}
    fields.update(kwargs)
    with pytest.raises(EpiVoError, match=match):
        DiagnosticStatusRecord(**fields)
