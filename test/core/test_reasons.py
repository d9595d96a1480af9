"""Decisions are values and their sentences are rendered in one place (``epi_vo.core.reasons``)."""

from __future__ import annotations

import math

import pytest

from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.reasons import render, sentence

# Details enough for every sentence (each template takes what it names).
DETAILS = dict(text="operator reset", seconds=4.9331, problem="bad image", note="", detail="x", failures=2, limit=3,
               gain=1.6, n=12, need=25, movers=3, region=(1, 2, 30, 40), spread=0.25, fraction=0.75, n_moving=5,
               rh=0.5, parallax=0.3, angle=2.0, rotation=1.0, direction=20.0, off=12, n_e=100, stat=30.0, moved=0.02,
               turned=1.0, ratio=0.95, parallax_focal=0.05, max_wait=10, best=0.4, runner=2.9, views=2, waited=2,
               rotation_sigma_deg=0.5, direction_sigma_deg=18.7, plane=False, kf=7,
               first_sd=0.8, next_sd=0.3)


@pytest.mark.parametrize("decision", list(Decision))
def test_every_decision_has_a_sentence(decision: Decision) -> None:
    text = sentence(note(decision, **DETAILS))
    assert text and "{" not in text and text == text.strip()


def test_known_sentences() -> None:
    assert sentence(note(Decision.TIME_JUMPED_BACK, seconds=4.9331)) == (
        "time jumped backwards by 4.933 s: tracking restarted from the last pose")
    assert sentence(note(Decision.TOO_FEW_TRACKED, n=12, need=25, movers=0)) == "too few tracked features (12 < 25)"
    assert sentence(note(Decision.RELOCALISED, kf=27, n=116)) == (
        "re-localised against keyframe 27: 116 points; the same map and scale continue")
    assert sentence(note(Decision.TOO_FEW_TRACKED, n=12, need=25, movers=3)) == (
        "too few tracked features (12 < 25, 3 on moving objects)")
    assert sentence(note(Decision.INIT_DEFERRED, rotation_sigma_deg=math.nan, direction_sigma_deg=math.nan)) == (
        "initialization deferred: E's pose is not determined by these points (no covariance); waiting for baseline, "
        "position held")
    assert sentence(Note(Decision.FRAME_SKIPPED, (("problem", "undecodable"), ("note", "recorded at 5 ns")))) == (
        "frame rejected: undecodable; frame skipped (recorded at 5 ns)")


def test_a_frames_reason_is_its_notes_in_order() -> None:
    notes = [note(Decision.RESET, text="operator reset"), note(Decision.NEW_REFERENCE)]
    assert render(notes) == "operator reset; new reference keyframe, no map yet"
    assert render([]) == ""


def test_a_note_names_a_missing_detail() -> None:
    with pytest.raises(KeyError, match="NO_MODEL has no detail 'n'"):
        _ = note(Decision.NO_MODEL)["n"]
