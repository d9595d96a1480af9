"""Diagnostic records shared by the ROS node and the offline bag writer (no numpy, no ROS).

A ``DiagnosticStatusRecord`` carries the fields of one ``diagnostic_msgs/msg/DiagnosticStatus``; the
node and ``outbag.OutputBag`` turn it into their own message type by field name.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from epi_vo.core.errors import EpiVoError


class DiagnosticLevel(IntEnum):
    """``diagnostic_msgs/msg/DiagnosticStatus`` level constants."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True)
class DiagnosticStatusRecord:
    """One diagnostic status; ``level`` accepts a DiagnosticLevel or its int value (0..3)."""

    level: DiagnosticLevel
    name: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        try:
            level = DiagnosticLevel(self.level)
        except ValueError:
            msg = (
                f"diagnostic level {self.level!r} is not one of {[int(x) for x in DiagnosticLevel]}"
            )
            raise EpiVoError(msg) from None
        object.__setattr__(self, "level", level)
        for field_name in ("name", "message", "hardware_id"):
            if not isinstance(getattr(self, field_name), str):
                msg = f"diagnostic {field_name} must be str, got {getattr(self, field_name)!r}"
                raise EpiVoError(msg)
        values = tuple(self.values)
        for pair in values:
            if not (
                isinstance(pair, tuple)
                and len(pair) == 2
                and isinstance(pair[0], str)
                and isinstance(pair[1], str)
            ):
                msg = f"diagnostic values must be (key, value) pairs of str, got {pair!r}"
                raise EpiVoError(msg)
        object.__setattr__(self, "values", values)
