"""Wheel odometry as it arrives: one rule for which messages are used (the node and the replay share it),
the count of every message dropped and why, and positions interpolated at image stamps."""

from __future__ import annotations

import bisect
import dataclasses
import enum
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

class WheelSample(enum.Enum):
    """What became of one wheel odometry message handed to :meth:`WheelOdometry.add`."""

    USED = "used"
    OUT_OF_ORDER = "out_of_order"  # stamped before a message received earlier
    DUPLICATE_STAMP = "duplicate_stamp"  # stamped as the newest message received before it
    NON_FINITE = "non_finite"  # a position that is NaN or infinite
    INVALID_STAMP = "invalid_stamp"  # a header stamp that is no ROS time


@dataclass(frozen=True)
class WheelInputCounts:
    """How many wheel odometry messages arrived and what became of them (:class:`WheelSample`)."""

    received: int = 0
    used: int = 0
    out_of_order: int = 0
    duplicate_stamp: int = 0
    non_finite: int = 0
    invalid_stamp: int = 0

    @property
    def dropped(self) -> int:
        return self.received - self.used

    def dropped_text(self) -> str:
        """'12 out of order (stamped before a message received earlier), 3 with non-finite positions'; ''
        when none was dropped."""
        parts = [f"{n} {WHY_DROPPED[kind]}" for kind, n in self.record().items()
                 if kind in WHY_DROPPED and n]
        return ", ".join(parts)

    def text(self) -> str:
        """'1027 message(s) received, 0 used: 1027 with non-finite positions'."""
        why = self.dropped_text()
        return f"{self.received} message(s) received, {self.used} used" + (f": {why}" if why else "")

    def record(self) -> dict[str, int]:
        return dataclasses.asdict(self)


WHY_DROPPED = {
    WheelSample.OUT_OF_ORDER.value: "out of order (stamped before a message received earlier)",
    WheelSample.DUPLICATE_STAMP.value: "with a duplicate stamp",
    WheelSample.NON_FINITE.value: "with non-finite positions",
    WheelSample.INVALID_STAMP.value: "with a stamp that is no ROS time",
}


class WheelOdometry:
    """Wheel odometry positions by stamp (the last ``horizon_s`` seconds), interpolated at image stamps.

    One rule for the node and the replay: messages are taken in the order they arrived (a bag's
    order), and a message is used only when it is stamped after every message used before it. A
    message stamped earlier cannot be put back in its place: the driver stamped it wrong or it was
    delayed behind newer ones, and either way the positions around it would be interpolated from a
    stamp that does not say when the wheels were there. Every message dropped is counted by why
    (:attr:`counts`), and the frame records, diagnostics and replay summary say so.
    """

    def __init__(self, horizon_s: float = 60.0) -> None:
        self.horizon_ns = int(horizon_s * 1e9)
        self._stamps: deque[int] = deque()
        self._xyz: deque[F64] = deque()
        self._counts: dict[str, int] = dict.fromkeys(WheelInputCounts().record(), 0)
        self._newest_ns: int | None = None  # the newest stamp used (also once pruned from the horizon)

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def counts(self) -> WheelInputCounts:
        return WheelInputCounts(**self._counts)

    @property
    def ignored(self) -> int:
        """Messages not used (every reason)."""
        return self.counts.dropped

    def add(self, stamp_ns: int | None, xyz: F64) -> WheelSample:
        """Take one message, in arrival order: ``stamp_ns`` None when its header stamp is no ROS time.
        The sample is used (``WheelSample.USED``) or dropped and counted (the other values)."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(3)
        self._counts["received"] += 1
        if stamp_ns is None:
            verdict = WheelSample.INVALID_STAMP
        elif not np.all(np.isfinite(xyz)):
            verdict = WheelSample.NON_FINITE
        elif self._newest_ns is not None and stamp_ns < self._newest_ns:
            verdict = WheelSample.OUT_OF_ORDER
        elif stamp_ns == self._newest_ns:
            verdict = WheelSample.DUPLICATE_STAMP
        else:
            verdict = WheelSample.USED
        self._counts[verdict.value] += 1
        if verdict is not WheelSample.USED:
            return verdict
        self._newest_ns = int(stamp_ns)
        self._stamps.append(int(stamp_ns))
        self._xyz.append(xyz)
        while self._stamps and self._stamps[-1] - self._stamps[0] > self.horizon_ns:
            self._stamps.popleft()
            self._xyz.popleft()
        return verdict

    def position_at(self, stamp_ns: int, timeout_ns: int) -> tuple[F64 | None, str]:
        """The position at ``stamp_ns``: interpolated between the samples around it, extrapolated from the
        last two when the newest is at most ``timeout_ns`` older; (None, reason) otherwise."""
        stamps = self._stamps
        if len(stamps) < 2:
            counts = self.counts
            if counts.used >= 2:
                return None, f"wheel odometry: no two messages within {self.horizon_ns * 1e-9:g} s"
            return None, f"wheel odometry: {counts.text()}; need 2 usable"
        i = bisect.bisect_left(stamps, stamp_ns)
        if i == 0:
            if stamps[0] - stamp_ns > timeout_ns:
                return None, f"wheel odometry starts {(stamps[0] - stamp_ns) * 1e-9:.2f} s after the image"
            i = 1
        elif i == len(stamps):
            late = stamp_ns - stamps[-1]
            if late > timeout_ns:
                return None, f"wheel odometry stale: last message {late * 1e-9:.2f} s before the image"
            i = len(stamps) - 1
        elif stamps[i] - stamps[i - 1] > 2 * timeout_ns:
            return None, f"wheel odometry gap of {(stamps[i] - stamps[i - 1]) * 1e-9:.2f} s around the image"
        t0, t1 = stamps[i - 1], stamps[i]
        a = (stamp_ns - t0) / (t1 - t0)
        return self._xyz[i - 1] + a * (self._xyz[i] - self._xyz[i - 1]), ""
