"""The node's health on ``/diagnostics``, the way diagnostic_aggregator and rqt_robot_monitor read a node's.

About once a second, one status per concern, each with a stable name (``<node>: tracking``, ``<node>: input``,
``<node>: extrinsic``, ``<node>: scale``) and a stable message: the level and a short cause from a fixed set,
never a number (numbers are key/values). An aggregator groups and latches statuses by name and message; a
message that changes every frame ("RH 0.48") defeats both. The per-frame detail (the whole frame record,
each frame's own reason) is on a topic of its own (``vo/frame_status``, :func:`epi_vo.core.status.frame_status`).

``tracking`` summarises the frames since the last publication (:class:`TrackingHealth`): its level and message
are those of the worst frame of the period (a frame lost inside the second is not hidden by the sampling),
its key/values the latest frame's numbers and how many frames of each state the period had; a period
without frames repeats the last verdict (the input status says why no frames come). ``input``, ``extrinsic``
and ``scale`` say the state now, from plain values the node hands in. No ROS, no numpy.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from dataclasses import dataclass

from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.frame import FrameResult, TrackingState
from epi_vo.core.scale import ScaleStatus

TRACKING, INPUT, EXTRINSIC, SCALE, LIFECYCLE = "tracking", "input", "extrinsic", "scale", "lifecycle"
CONCERNS = (TRACKING, INPUT, EXTRINSIC, SCALE, LIFECYCLE)


def status_name(node_name: str, concern: str) -> str:
    """'/robot1/vo_node: tracking': the fully qualified node name and the concern."""
    return f"{node_name}: {concern}"


@dataclass(frozen=True)
class Verdict:
    """A level with its stable message."""

    level: DiagnosticLevel
    message: str


# One message per tracking state: what it means for a consumer of the odometry.
_STATE_VERDICTS = {
    TrackingState.TRACKING: Verdict(DiagnosticLevel.OK, "tracking"),
    TrackingState.STATIC: Verdict(DiagnosticLevel.OK, "static: the camera did not move"),
    TrackingState.INITIALIZING: Verdict(DiagnosticLevel.WARN, "initializing: waiting for parallax, position held"),
    TrackingState.ROTATION_ONLY: Verdict(DiagnosticLevel.WARN, "rotation only: position held"),
    TrackingState.LOST: Verdict(DiagnosticLevel.ERROR, "lost: no pose"),
}
REJECTED = Verdict(DiagnosticLevel.ERROR, "frames rejected: unusable input")
SKIPPED = Verdict(DiagnosticLevel.WARN, "frames skipped: duplicate stamp")
NO_FRAME = Verdict(DiagnosticLevel.WARN, "no frame processed yet")


def frame_verdict(r: FrameResult) -> Verdict:
    """The verdict of one frame (the per-frame status's level, with a stable message)."""
    if r.rejected:
        return REJECTED
    if r.skipped:
        return SKIPPED
    return _STATE_VERDICTS[r.state]


def _num(v: float, spec: str = ".4g") -> str:
    return f"{v:{spec}}" if math.isfinite(v) else "None"


@dataclass(frozen=True)
class TrackingHealth:
    """The frames since the last publication. Immutable: :meth:`add` and :meth:`next_period` return a new one."""

    frames: int = 0  # all frames so far
    period_frames: int = 0
    period_worst: Verdict | None = None  # the worst frame of the period (the latest of equal levels)
    period_states: tuple[tuple[str, int], ...] = ()
    last: Verdict | None = None  # the verdict published last, repeated by a period without frames
    latest: tuple[tuple[str, str], ...] = ()  # the latest frame's numbers
    scale: ScaleStatus | None = None  # the latest frame's

    def add(self, r: FrameResult) -> TrackingHealth:
        v = frame_verdict(r)
        worst = v if self.period_worst is None or v.level >= self.period_worst.level else self.period_worst
        states = Counter(dict(self.period_states))
        states["rejected" if r.rejected else "skipped" if r.skipped else r.state.value] += 1
        latest = (("state", r.state.value), ("frame_index", str(r.index)), ("stamp_ns", str(r.stamp_ns)),
                  ("reason", r.reason), ("model", r.model.value), ("n_inliers", str(r.n_inliers)),
                  ("inlier_ratio", _num(r.inlier_ratio)), ("rh", _num(r.rh)),
                  ("median_parallax_deg", _num(r.median_parallax_deg)), ("n_keyframes", str(r.n_keyframes)))
        return dataclasses.replace(self, frames=self.frames + 1, period_frames=self.period_frames + 1,
                                   period_worst=worst, period_states=tuple(sorted(states.items())), latest=latest,
                                   scale=r.scale)

    def verdict(self) -> Verdict:
        """The period's worst frame; without frames the last verdict; before any frame, NO_FRAME."""
        return self.period_worst or self.last or NO_FRAME

    def next_period(self) -> TrackingHealth:
        """After a publication: the period starts empty, its verdict remembered."""
        return dataclasses.replace(self, period_frames=0, period_worst=None, period_states=(), last=self.verdict())

    def status(self, node_name: str, hardware_id: str,
               values: tuple[tuple[str, str], ...] = ()) -> DiagnosticStatusRecord:
        v = self.verdict()
        states = " ".join(f"{k}={n}" for k, n in self.period_states) or "none"
        own = (("frames_processed", str(self.frames)), ("frames_this_period", str(self.period_frames)),
               ("states_this_period", states))
        return DiagnosticStatusRecord(v.level, status_name(node_name, TRACKING), v.message, hardware_id,
                                      own + self.latest + values)


def scale_status(node_name: str, hardware_id: str, source: str, scale: ScaleStatus | None,
                 values: tuple[tuple[str, str], ...] = ()) -> DiagnosticStatusRecord:
    """The metric scale: the configured ``source`` and, from the latest frame's ``scale`` (None before the
    first frame), whether positions are metres yet. With no metric source VO units are the configuration,
    not a fault (OK); a metric source not (yet) established is a WARN: positions are held until it is."""
    if source == "none":
        v = Verdict(DiagnosticLevel.OK, "VO units: no metric scale source")
    elif scale is None:
        v = Verdict(DiagnosticLevel.WARN, "not established: no frame processed yet")
    elif not scale.metric:
        v = Verdict(DiagnosticLevel.WARN, "not established: VO units, position held")
    else:
        v = Verdict(DiagnosticLevel.OK, "metres")
    own: tuple[tuple[str, str], ...] = (("scale_source", source), ("units", "vo" if scale is None else scale.units))
    if scale is not None:
        own += (("metric_scale", str(scale.metric)), ("scale", _num(scale.scale, ".6g")),
                ("scale_rel_std", _num(scale.rel_std)), ("floor_pitch_deg", _num(scale.floor_pitch_deg)),
                ("floor_roll_deg", _num(scale.floor_roll_deg)), ("scale_reason", scale.reason))
        if scale.wheel is not None:
            own += (("wheel_messages", " ".join(f"{k}={n}" for k, n in scale.wheel.record().items())),)
    return DiagnosticStatusRecord(v.level, status_name(node_name, SCALE), v.message, hardware_id, own + values)


@dataclass(frozen=True)
class InputState:
    """What the node knows of its images now (plain values)."""

    active: bool = True  # taking images (the managed node while inactive is not)
    stall: DiagnosticLevel | None = None  # the watchdog: WARN / STALE once images stop; None while they come
    received_any: bool = False
    dropping: bool = False  # frames dropped by queue_max_mb since the last publication


def input_status(node_name: str, hardware_id: str, state: InputState,
                 values: tuple[tuple[str, str], ...] = ()) -> DiagnosticStatusRecord:
    """The images: coming, stalled (the watchdog's level), or dropped for the queue's memory bound."""
    if not state.active:
        v = Verdict(DiagnosticLevel.OK, "inactive: images ignored")
    elif state.stall is not None:
        v = Verdict(state.stall, "stalled: no recent image" if state.received_any else "no image received yet")
    elif state.dropping:
        v = Verdict(DiagnosticLevel.WARN, "dropping frames: queue_max_mb reached")
    else:
        v = Verdict(DiagnosticLevel.OK, "receiving images")
    return DiagnosticStatusRecord(v.level, status_name(node_name, INPUT), v.message, hardware_id, values)


def extrinsic_status(node_name: str, hardware_id: str, source: str, waiting: bool, fallback: bool,
                     values: tuple[tuple[str, str], ...] = ()) -> DiagnosticStatusRecord:
    """The camera extrinsic: ``source`` 'tf', 'parameters' or 'pending'; ``waiting`` for TF while pending;
    ``fallback``: the parameters were taken because TF could not be used (not by choice)."""
    if source == "pending":
        v = Verdict(DiagnosticLevel.WARN, "waiting for TF") if waiting else \
            Verdict(DiagnosticLevel.OK, "pending: no image yet")
    elif source == "tf":
        v = Verdict(DiagnosticLevel.OK, "from TF")
    elif fallback:
        v = Verdict(DiagnosticLevel.WARN, "from parameters: TF not available")
    else:
        v = Verdict(DiagnosticLevel.OK, "from parameters")
    return DiagnosticStatusRecord(v.level, status_name(node_name, EXTRINSIC), v.message, hardware_id,
                                  (("extrinsic_source", source), *values))


def lifecycle_status(node_name: str, hardware_id: str, state: str, configure_error: str,
                     values: tuple[tuple[str, str], ...] = ()) -> DiagnosticStatusRecord:
    """The managed node's lifecycle ``state`` ('unconfigured', 'inactive', 'active', 'finalized'); a failed
    configure is an ERROR until one succeeds (``configure_error`` says why, as a key/value)."""
    if configure_error:
        v = Verdict(DiagnosticLevel.ERROR, "unconfigured: configure failed")
    else:
        v = Verdict(DiagnosticLevel.OK, {"unconfigured": "unconfigured: configure and activate to track",
                                         "inactive": "inactive: activate to track",
                                         "finalized": "finalized: shut down, no odometry"}.get(state, state))
    own = (("lifecycle_state", state), ("configure_error", configure_error or "none"))
    return DiagnosticStatusRecord(v.level, status_name(node_name, LIFECYCLE), v.message, hardware_id, own + values)
