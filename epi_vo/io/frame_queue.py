"""What the live node holds between an image's arrival and its processing, bounded (no rclpy).

:class:`FrameQueue` pairs each image with its camera_info (:class:`~epi_vo.io.association.CameraInfoAssociator`),
then keeps the frames ready for processing in arrival order, within two bounds:

- ``max_frames`` (vo_node's ``queue_size``) in live mode: the newest frames are the useful ones, the
  oldest waiting is dropped;
- ``max_bytes`` (``queue_max_mb``) in either mode, ``process_every_frame`` included: the images waiting
  may take at most this much memory (their encoded size, as received); beyond it the oldest waiting frame
  is dropped. The newest frame is always kept, so a single frame larger than the bound still goes through.

Dropping, not back-pressure: the node's subscription callbacks must return (they share the executor with
camera_info, the wheels, the watchdog and the diagnostics), and DDS gives a subscriber no way to slow a
publisher down. Every frame dropped is counted; :attr:`FrameQueue.overflow` counts those dropped by the
memory bound (with ``process_every_frame`` the only bound), which the node reports as a WARN while they
happen: unlike live mode's ``queue_size``, no configuration asks for them.

Every image added leaves exactly once: processed (:meth:`FrameQueue.pop`), dropped (counted), or cleared
(:meth:`FrameQueue.clear`, counted by the caller). Images waiting for their camera_info are held at most
``camera_info_wait_s`` on the node's clock (``no_info_wait_s`` while no camera_info has ever been received)
once :meth:`FrameQueue.expire` is called, so none waits for ever. Times are the caller's steady clock, in
seconds.
"""

from __future__ import annotations

import collections
from typing import Any

from epi_vo.io.association import CameraInfoAssociator, Ready

# Images held waiting for their camera_info once one has been received (a camera_info publisher a few
# frames behind its images), and before the first (the camera_info subscription matched after the
# image one loses the first camera_info messages: ``epi_vo.io.association``).
MAX_PENDING = 5
STARTUP_PENDING = 30
RATE_WINDOW = 30  # arrivals over which the input rate is measured
# Before any camera_info has been received, an image waits this long (steady clock, s) for one: the
# camera_info subscription can match seconds after the image one when discovery is slow (a loaded
# machine), and then its first messages are lost, not the calibration. Once one has been received, the
# node's camera_info_wait_s bounds the wait.
NO_CAMERA_INFO_WAIT_S = 2.0


class FrameQueue:
    """Frames from arrival to processing (module doc). Not thread-safe: the node calls it under its lock."""

    def __init__(self, *, max_frames: int | None, max_bytes: int, camera_info_wait_s: float,
                 no_info_wait_s: float) -> None:
        self._waits = (camera_info_wait_s, no_info_wait_s)
        self._assoc = self._new_associator()
        self._ready: collections.deque[Ready] = collections.deque()
        self.max_frames = max_frames
        self.max_bytes = max_bytes
        self.bytes = 0  # of the frames ready (not those still waiting for their camera_info)
        self.received = 0
        self.dropped = 0  # by either bound
        self.overflow = 0  # of those, dropped by the memory bound
        self.last_arrival_s: float | None = None
        self._arrivals: collections.deque[float] = collections.deque(maxlen=RATE_WINDOW)

    def __len__(self) -> int:
        return len(self._ready)

    def _new_associator(self) -> CameraInfoAssociator:
        wait_s, no_info_wait_s = self._waits
        return CameraInfoAssociator(max_pending=MAX_PENDING, max_wait_ns=int(wait_s * 1e9),
                                    startup_pending=STARTUP_PENDING, max_wait_s=wait_s, no_info_wait_s=no_info_wait_s)

    @property
    def pending(self) -> int:
        """Images still waiting for their camera_info."""
        return self._assoc.pending

    @property
    def held_bytes(self) -> int:
        """Everything held: the frames ready and the images waiting for their camera_info."""
        return self.bytes + self._assoc.pending_bytes

    def set_limits(self, max_frames: int | None, max_bytes: int) -> None:
        """New bounds (a runtime parameter change); applied at the next frame that arrives."""
        self.max_frames, self.max_bytes = max_frames, max_bytes

    def add_image(self, stamp_ns: int, image: Any, nbytes: int, now_s: float) -> bool:
        """One image arrived; True when frames became ready."""
        self.received += 1
        self.last_arrival_s = now_s
        self._arrivals.append(now_s)
        return self._take(self._assoc.add_image(stamp_ns, image, now_s, nbytes))

    def add_info(self, stamp_ns: int, info: Any) -> bool:
        """One camera_info arrived; True when frames became ready."""
        return self._take(self._assoc.add_info(stamp_ns, info))

    def expire(self, now_s: float) -> bool:
        """Give up on images that waited their camera_info long enough; True when frames became ready."""
        return self._take(self._assoc.expire(now_s))

    def peek(self) -> Ready | None:
        return self._ready[0] if self._ready else None

    def pop(self) -> Ready | None:
        if not self._ready:
            return None
        item = self._ready.popleft()
        self.bytes -= item.nbytes
        return item

    def clear(self) -> int:
        """Forget every frame held (ready or waiting for camera_info) and the camera_info seen: the next
        image starts afresh. How many frames there were."""
        n = len(self._ready) + self._assoc.pending
        self._ready.clear()
        self.bytes = 0
        self._assoc = self._new_associator()
        return n

    def input_rate_hz(self, now_s: float) -> float:
        """Images per second over the last arrivals; a stalled camera's rate decays instead of freezing."""
        a = self._arrivals
        rate = (len(a) - 1) / (a[-1] - a[0]) if len(a) > 1 and a[-1] > a[0] else 0.0
        if self.last_arrival_s is not None and now_s > self.last_arrival_s:
            rate = min(rate, 1.0 / (now_s - self.last_arrival_s))
        return rate

    def _take(self, ready: list[Ready]) -> bool:
        for r in ready:
            self._ready.append(r)
            self.bytes += r.nbytes
        while len(self._ready) > 1:
            over_count = self.max_frames is not None and len(self._ready) > self.max_frames
            over_bytes = self.bytes > self.max_bytes
            if not (over_count or over_bytes):
                break
            self.pop()
            self.dropped += 1
            self.overflow += int(over_bytes)
        return bool(ready)
