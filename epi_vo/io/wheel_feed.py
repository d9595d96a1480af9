"""A bag's wheel odometry handed to the pipeline as a live node would have received it (``epi-vo replay``).

The messages go over in the bag's order, which is the order they arrived in when it was recorded: the
pipeline's rule of which are used (``epi_vo.core.scale.WheelOdometry``: arrival order, a message stamped
before one received earlier is dropped) is then the same offline as in ``vo_node``, which hands them over
in the order its subscription delivers them. Each image gets the messages stamped up to its own stamp plus
the stale timeout, as a live subscriber would have received them by the time they are needed.
"""

from __future__ import annotations

from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.scale import WheelInputCounts
from epi_vo.io.bagio import NO_STAMP, WheelOdometrySamples


class WheelFeed:
    """The messages of one bag's wheel topic (None: no wheel topic), fed to ``pipeline`` image by image."""

    def __init__(self, samples: WheelOdometrySamples | None, pipeline: VoPipeline, timeout_s: float) -> None:
        self._samples = samples
        self._pipeline = pipeline
        self._lookahead_ns = int(timeout_s * 1e9)
        self._next = 0

    def up_to(self, stamp_ns: int | None) -> None:
        """Hand over the messages up to the first one stamped after ``stamp_ns`` + the timeout (None: all)."""
        s = self._samples
        if s is None:
            return
        while self._next < len(s.stamps_ns):
            stamp = int(s.stamps_ns[self._next])
            if stamp_ns is not None and stamp > stamp_ns + self._lookahead_ns:
                break
            self._pipeline.add_wheel_odometry(None if stamp == NO_STAMP else stamp, s.positions[self._next])
            self._next += 1

    def counts(self) -> WheelInputCounts | None:
        """Every message of the topic handed over (the rest too) and what became of them; None: no topic."""
        if self._samples is None:
            return None
        self.up_to(None)
        return self._pipeline.scale_status.wheel
