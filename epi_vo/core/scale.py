"""The scale stage: what length a monocular map's translation gets.

Translation is observable only up to one global scale (see ``epi_vo.core.pipeline``). Today the only
source is the VO's own units: the first map's keyframe baseline has length 1 and a map rebuilt after
tracking was lost continues the old units by assuming the last keyframe speed. External sources
(ground plane with a known camera height, wheel odometry) plug in here: they decide the baseline of a
new map and, later, correct the scale of a running one.
"""

from __future__ import annotations


class VoUnitsScale:
    """Scale in VO units: baseline 1 for the first map, then the last keyframe speed carries it on."""

    metric = False

    def __init__(self) -> None:
        self.speed: float | None = None  # map units per second at the last keyframe

    def on_keyframe(self, step_length: float, dt_s: float) -> None:
        """A keyframe step of ``step_length`` map units over ``dt_s`` seconds was taken."""
        if dt_s > 0:
            self.speed = step_length / dt_s

    def initial_baseline(self, dt_s: float) -> float:
        """Length given to the first keyframe baseline of a new map, ``dt_s`` after its keyframe."""
        if self.speed is None or dt_s <= 0.0:
            return 1.0
        return self.speed * dt_s
