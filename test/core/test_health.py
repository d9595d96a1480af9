"""core/health.py: the node's /diagnostics statuses, one per concern, stable messages, numbers as key/values."""

from __future__ import annotations

import dataclasses

import pytest

from epi_vo.core import health
from epi_vo.core.diagnostics import DiagnosticLevel
from epi_vo.core.frame import FrameResult, TrackingState
from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.scale import ScaleStatus
from epi_vo.core.wheel_odometry import WheelInputCounts

NODE = "/robot1/vo_node"


def _frame(state: TrackingState, index: int = 0, **over: object) -> FrameResult:
    r = VoPipeline().reject(1_700_000_000_000_000_000 + index, "camera_info missing")
    return dataclasses.replace(r, state=state, index=index, problem="", reason=f"reason {index} (RH 0.{index})",
                               **over)


def test_each_state_has_one_level_and_a_message_without_numbers() -> None:
    verdicts = {s: health.frame_verdict(_frame(s)) for s in TrackingState}
    assert {s: v.level for s, v in verdicts.items()} == {
        TrackingState.TRACKING: DiagnosticLevel.OK, TrackingState.STATIC: DiagnosticLevel.OK,
        TrackingState.INITIALIZING: DiagnosticLevel.WARN, TrackingState.ROTATION_ONLY: DiagnosticLevel.WARN,
        TrackingState.LOST: DiagnosticLevel.ERROR}
    assert verdicts[TrackingState.TRACKING].message == "tracking"
    rejected = VoPipeline().reject(1_000, "camera_info missing")
    assert health.frame_verdict(rejected) == health.REJECTED
    assert health.frame_verdict(dataclasses.replace(_frame(TrackingState.LOST), skipped=True)) == health.SKIPPED
    texts = [v.message for v in verdicts.values()] + [health.REJECTED.message, health.SKIPPED.message,
                                                      health.NO_FRAME.message]
    assert not any(ch.isdigit() for t in texts for ch in t)


def test_the_period_says_its_worst_frame_and_the_latest_numbers() -> None:
    t = health.TrackingHealth()
    assert t.verdict() == health.NO_FRAME
    for i, state in enumerate((TrackingState.TRACKING, TrackingState.LOST, TrackingState.TRACKING,
                               TrackingState.INITIALIZING)):
        t = t.add(_frame(state, i, n_inliers=100 + i))
    status = t.status(NODE, "cam", (("parameter_changes", "none"),))
    values = dict(status.values)
    # A frame lost inside the second is not hidden by the once-a-second sampling ...
    assert (status.name, status.level, status.message) == (f"{NODE}: tracking", DiagnosticLevel.ERROR,
                                                           "lost: no pose")
    # ... and the numbers are the latest frame's, the counts the period's.
    assert values["frame_index"] == "3" and values["n_inliers"] == "103" and values["state"] == "initializing"
    assert values["reason"] == "reason 3 (RH 0.3)"
    assert values["states_this_period"] == "initializing=1 lost=1 tracking=2"
    assert (values["frames_processed"], values["frames_this_period"]) == ("4", "4")
    assert values["parameter_changes"] == "none"
    # A period without frames repeats the verdict; the next frame's period starts afresh.
    t = t.next_period()
    empty = t.status(NODE, "cam")
    assert (empty.level, empty.message) == (DiagnosticLevel.ERROR, "lost: no pose")
    assert dict(empty.values)["frames_this_period"] == "0" and dict(empty.values)["states_this_period"] == "none"
    t = t.add(_frame(TrackingState.TRACKING, 4)).next_period().add(_frame(TrackingState.TRACKING, 5))
    assert (t.verdict().level, t.verdict().message) == (DiagnosticLevel.OK, "tracking")
    assert dict(t.status(NODE, "cam").values)["frames_processed"] == "6"


def test_of_equal_levels_the_latest_frame_speaks() -> None:
    t = health.TrackingHealth().add(_frame(TrackingState.INITIALIZING, 0)).add(_frame(TrackingState.ROTATION_ONLY, 1))
    assert t.verdict().message == "rotation only: position held"


@pytest.mark.parametrize(("source", "scale", "level", "message"), [
    ("none", ScaleStatus(), DiagnosticLevel.OK, "VO units: no metric scale source"),
    ("none", None, DiagnosticLevel.OK, "VO units: no metric scale source"),
    ("ground_plane", None, DiagnosticLevel.WARN, "not established: no frame processed yet"),
    ("ground_plane", ScaleStatus(source="ground_plane", reason="no floor seen"), DiagnosticLevel.WARN,
     "not established: VO units, position held"),
    ("wheel_odometry", ScaleStatus(source="wheel_odometry", metric=True, scale=0.41, rel_std=0.03,
                                   wheel=WheelInputCounts(received=12, used=11, out_of_order=1)),
     DiagnosticLevel.OK, "metres"),
])
def test_scale_says_the_configured_source_and_whether_it_is_metres(source: str, scale: ScaleStatus | None,
                                                                   level: DiagnosticLevel, message: str) -> None:
    status = health.scale_status(NODE, "cam", source, scale, (("wheel_messages_lost", "0"),))
    values = dict(status.values)
    assert (status.name, status.level, status.message) == (f"{NODE}: scale", level, message)
    assert values["scale_source"] == source  # before any frame too: never 'none' for a configured source
    assert values["units"] == ("m" if scale is not None and scale.metric else "vo")
    assert values["wheel_messages_lost"] == "0"
    if scale is not None and scale.wheel is not None:
        assert values["scale"] == "0.41" and values["scale_rel_std"] == "0.03"
        assert values["wheel_messages"] == ("received=12 used=11 out_of_order=1 duplicate_stamp=0 non_finite=0 "
                                            "invalid_stamp=0")


@pytest.mark.parametrize(("state", "level", "message"), [
    (health.InputState(received_any=True), DiagnosticLevel.OK, "receiving images"),
    (health.InputState(stall=DiagnosticLevel.STALE), DiagnosticLevel.STALE, "no image received yet"),
    (health.InputState(stall=DiagnosticLevel.WARN, received_any=True), DiagnosticLevel.WARN,
     "stalled: no recent image"),
    (health.InputState(received_any=True, dropping=True), DiagnosticLevel.WARN,
     "dropping frames: queue_max_mb reached"),
    (health.InputState(active=False, stall=DiagnosticLevel.STALE), DiagnosticLevel.OK, "inactive: images ignored"),
])
def test_input(state: health.InputState, level: DiagnosticLevel, message: str) -> None:
    status = health.input_status(NODE, "cam", state, (("frames_received", "7"),))
    assert (status.name, status.level, status.message, status.values) == (
        f"{NODE}: input", level, message, (("frames_received", "7"),))


@pytest.mark.parametrize(("source", "waiting", "fallback", "level", "message"), [
    ("pending", False, False, DiagnosticLevel.OK, "pending: no image yet"),
    ("pending", True, False, DiagnosticLevel.WARN, "waiting for TF"),
    ("tf", False, False, DiagnosticLevel.OK, "from TF"),
    ("parameters", False, False, DiagnosticLevel.OK, "from parameters"),
    ("parameters", False, True, DiagnosticLevel.WARN, "from parameters: TF not available"),
])
def test_extrinsic(source: str, waiting: bool, fallback: bool, level: DiagnosticLevel, message: str) -> None:
    status = health.extrinsic_status(NODE, "cam", source, waiting, fallback, (("camera_xyz", "0.2 0 0.5"),))
    assert (status.name, status.level, status.message) == (f"{NODE}: extrinsic", level, message)
    assert status.values == (("extrinsic_source", source), ("camera_xyz", "0.2 0 0.5"))


def test_lifecycle() -> None:
    failed = health.lifecycle_status(NODE, "cam", "unconfigured", "frontend='sift' (choose one of klt, orb)")
    assert (failed.name, failed.level, failed.message) == (f"{NODE}: lifecycle", DiagnosticLevel.ERROR,
                                                           "unconfigured: configure failed")
    assert dict(failed.values)["configure_error"] == "frontend='sift' (choose one of klt, orb)"
    for state, message in (("unconfigured", "unconfigured: configure and activate to track"),
                           ("inactive", "inactive: activate to track"), ("active", "active"),
                           ("finalized", "finalized: shut down, no odometry")):
        status = health.lifecycle_status(NODE, "cam", state, "")
        assert (status.level, status.message, dict(status.values)["configure_error"]) == (DiagnosticLevel.OK,
                                                                                          message, "none")
