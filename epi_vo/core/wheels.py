"""Wheel odometry positions by stamp, interpolated at image stamps (for the ``wheel_odometry`` scale source).

A frozen buffer: ``add`` returns the buffer with the sample (the pipeline's state is replaced, never
changed in place).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

# Samples older than this behind the newest are dropped: a scale measurement spans the last keyframe steps
# until the wheels covered ``WheelOdometryScale.window_m``, seconds at any robot speed.
HORIZON_S = 60.0


def _empty_stamps() -> I64:
    return np.zeros(0, np.int64)


def _empty_xyz() -> F64:
    return np.zeros((0, 3))


@dataclass(frozen=True)
class WheelOdometry:
    """Wheel odometry positions (any fixed odom frame, metres) of the last ``HORIZON_S`` seconds, by stamp."""

    stamps_ns: I64 = field(default_factory=_empty_stamps)  # increasing
    xyz: F64 = field(default_factory=_empty_xyz)  # (N, 3)
    ignored: int = 0  # samples refused (not finite, or not newer than the newest)

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    def add(self, stamp_ns: int, xyz: F64) -> tuple[WheelOdometry, bool]:
        """The buffer with one more sample, and True; itself with the refusal counted and False when the
        sample is not finite or not newer than the newest."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(xyz)) or (len(self) and stamp_ns <= int(self.stamps_ns[-1])):
            return WheelOdometry(self.stamps_ns, self.xyz, self.ignored + 1), False
        stamps = np.append(self.stamps_ns, np.int64(stamp_ns))
        first = int(np.searchsorted(stamps, int(stamps[-1]) - int(HORIZON_S * 1e9), side="left"))
        return WheelOdometry(stamps[first:], np.vstack([self.xyz, xyz])[first:], self.ignored), True

    def position_at(self, stamp_ns: int, timeout_ns: int) -> tuple[F64 | None, str]:
        """The position at ``stamp_ns``: interpolated between the samples around it, extrapolated from the
        last two when the newest is at most ``timeout_ns`` older; (None, reason) otherwise."""
        stamps = self.stamps_ns
        n = len(self)
        if n < 2:
            return None, f"wheel odometry: {n} message(s) received, need 2"
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
