"""The diagnostics status of one frame: what the node publishes and the replay records.

Level policy: a tracking frame is OK (its message is the reason when there is one, e.g. a planar view
tracked from the map); initializing and rotation-only frames are WARN (rotation only, no justified
translation), as is a frame skipped for a duplicate stamp; a frame without a pose is ERROR. The
key/values are the frame record's fields.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

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


@dataclass(frozen=True)
class StatusPose:
    """A frame's pose as the node publishes it: the position and orientation of ``child_frame`` in
    ``frame`` (odom -> base_link, as vo/odometry), with the diagonal of its covariance in that frame."""

    frame: str
    child_frame: str
    position: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    covariance_diagonal: tuple[float, ...]


# Without a StatusPose, the record's pose: the camera's optical frame at the first image (the pipeline's w).
CAMERA_POSITION_FRAME = "camera optical frame of the first image"


def frame_status(result: FrameResult, node_name: str, hardware_id: str,
                 pose: StatusPose | None = None, record: dict[str, Any] | None = None) -> DiagnosticStatusRecord:
    """Status named ``<node_name>: tracking`` with the level, the reason and the frame record.

    ``position``, ``quat_xyzw`` and ``covariance_diagonal`` are those of ``pose`` when given (the node
    gives the odometry's, odom -> base_link), else the record's (camera optical frame); the key
    ``position_frame`` names which ("odom -> base_link" for the former). ``record``: the frame's
    ``result.to_record()`` when the caller has it already (not changed).
    """
    level = DiagnosticLevel.WARN if result.skipped else _LEVELS[result.state]
    message = result.reason or result.state.value
    if not message.startswith(result.state.value):
        message = f"{result.state.value}: {message}"
    record = result.to_record() if record is None else dict(record)
    if pose is not None:
        record["position"] = list(pose.position)
        record["quat_xyzw"] = list(pose.quat_xyzw)
        record["covariance_diagonal"] = list(pose.covariance_diagonal)
    record["position_frame"] = f"{pose.frame} -> {pose.child_frame}" if pose is not None else CAMERA_POSITION_FRAME
    values = tuple((k, _fmt(v)) for k, v in record.items())
    return DiagnosticStatusRecord(level, f"{node_name}: tracking", message, hardware_id, values)
