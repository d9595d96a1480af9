"""The diagnostics status of one frame: what the node publishes and the replay records.

Level policy: a tracking frame is OK (its message is the reason when there is one, e.g. a planar view
tracked from the map); initializing and rotation-only frames are WARN (rotation only, no justified
translation), as is a frame skipped for a duplicate stamp; a frame without a pose is ERROR. The
key/values are the frame record's fields.
"""

from __future__ import annotations

import math

from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.frame import FrameResult, TrackingState

_LEVELS = {
    TrackingState.TRACKING: DiagnosticLevel.OK,
    TrackingState.INITIALIZING: DiagnosticLevel.WARN,
    TrackingState.ROTATION_ONLY: DiagnosticLevel.WARN,
    TrackingState.STATIC: DiagnosticLevel.OK,
    TrackingState.LOST: DiagnosticLevel.ERROR,
}


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return "None" if not math.isfinite(v) else f"{v:.6g}"  # as the record's null: not measured
    if isinstance(v, list):
        return " ".join(_fmt(x) for x in v)
    if isinstance(v, dict):
        return " ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    return str(v)


def frame_status(result: FrameResult, node_name: str, hardware_id: str) -> DiagnosticStatusRecord:
    """Status named ``<node_name>: tracking`` with the level, the reason and the frame record."""
    level = DiagnosticLevel.WARN if result.skipped else _LEVELS[result.state]
    message = result.reason or result.state.value
    if not message.startswith(result.state.value):
        message = f"{result.state.value}: {message}"
    record = result.to_record()
    values = tuple((k, _fmt(v)) for k, v in record.items())
    return DiagnosticStatusRecord(level, f"{node_name}: tracking", message, hardware_id, values)
