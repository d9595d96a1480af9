"""Wheel odometry as it arrives: one rule for which messages are used (the node and the replay share it),
the count of every message dropped and why, and positions interpolated at image stamps.

The buffer is a frozen value: ``add`` returns the buffer with the message taken (or counted), which the
tracking state holds in place of the one before.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

# Samples older than this behind the newest are dropped: a scale measurement spans the last keyframe steps
# until the wheels covered ``WheelOdometryScale.window_m``, seconds at any robot speed.
HORIZON_S = 60.0

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


def _empty_stamps() -> I64:
    return np.zeros(0, np.int64)


def _empty_xyz() -> F64:
    return np.zeros((0, 3))


@dataclass(frozen=True)
class WheelOdometry:
    """Wheel odometry positions by stamp (the last ``HORIZON_S`` seconds), interpolated at image stamps.

    One rule for the node and the replay: messages are taken in the order they arrived (a bag's
    order), and a message is used only when it is stamped after every message used before it. A
    message stamped earlier cannot be put back in its place: the driver stamped it wrong or it was
    delayed behind newer ones, and either way the positions around it would be interpolated from a
    stamp that does not say when the wheels were there. Every message dropped is counted by why
    (:attr:`counts`), and the frame records, diagnostics and replay summary say so.
    """

    stamps_ns: I64 = field(default_factory=_empty_stamps)  # increasing
    xyz: F64 = field(default_factory=_empty_xyz)  # (N, 3) positions (any fixed odom frame, metres)
    counts: WheelInputCounts = field(default_factory=WheelInputCounts)
    newest_ns: int | None = None  # the newest stamp used (also once pruned from the horizon)
    horizon_ns: int = int(HORIZON_S * 1e9)

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    @property
    def ignored(self) -> int:
        """Messages not used (every reason)."""
        return self.counts.dropped

    def add(self, stamp_ns: int | None, xyz: F64) -> tuple[WheelOdometry, WheelSample]:
        """Take one message, in arrival order (``stamp_ns`` None when its header stamp is no ROS time): the
        buffer after it, and whether the sample is used (``WheelSample.USED``) or dropped and counted."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(3)
        if stamp_ns is None:
            verdict = WheelSample.INVALID_STAMP
        elif not np.all(np.isfinite(xyz)):
            verdict = WheelSample.NON_FINITE
        elif self.newest_ns is not None and stamp_ns < self.newest_ns:
            verdict = WheelSample.OUT_OF_ORDER
        elif stamp_ns == self.newest_ns:
            verdict = WheelSample.DUPLICATE_STAMP
        else:
            verdict = WheelSample.USED
        c = self.counts
        counts = dataclasses.replace(c, received=c.received + 1, **{verdict.value: getattr(c, verdict.value) + 1})
        if verdict is not WheelSample.USED:
            return dataclasses.replace(self, counts=counts), verdict
        assert stamp_ns is not None
        stamps = np.append(self.stamps_ns, np.int64(stamp_ns))
        first = int(np.searchsorted(stamps, int(stamps[-1]) - self.horizon_ns, side="left"))
        return WheelOdometry(stamps[first:], np.vstack([self.xyz, xyz])[first:], counts, int(stamp_ns),
                             self.horizon_ns), verdict

    def position_at(self, stamp_ns: int, timeout_ns: int) -> tuple[F64 | None, str]:
        """The position at ``stamp_ns``: interpolated between the samples around it, extrapolated from the
        last two when the newest is at most ``timeout_ns`` older; (None, reason) otherwise."""
        stamps = self.stamps_ns
        n = len(self)
        if n < 2:
            if self.counts.used >= 2:
                return None, f"wheel odometry: no two messages within {self.horizon_ns * 1e-9:g} s"
            return None, f"wheel odometry: {self.counts.text()}; need 2 usable"
        i = int(np.searchsorted(stamps, stamp_ns, side="left"))
        if i == 0:
            if int(stamps[0]) - stamp_ns > timeout_ns:
                return None, f"wheel odometry starts {(int(stamps[0]) - stamp_ns) * 1e-9:.2f} s after the image"
            i = 1
        elif i == n:
            late = stamp_ns - int(stamps[-1])
            if late > timeout_ns:
                return None, f"wheel odometry stale: last message {late * 1e-9:.2f} s before the image"
            i = n - 1
        elif int(stamps[i]) - int(stamps[i - 1]) > 2 * timeout_ns:
            return None, (f"wheel odometry gap of {(int(stamps[i]) - int(stamps[i - 1])) * 1e-9:.2f} s around the "
                          "image")
        t0, t1 = int(stamps[i - 1]), int(stamps[i])
        a = (stamp_ns - t0) / (t1 - t0)
        return self.xyz[i - 1] + a * (self.xyz[i] - self.xyz[i - 1]), ""
