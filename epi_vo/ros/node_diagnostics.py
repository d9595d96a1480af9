"""What ``vo_node`` says about itself on ``/diagnostics`` besides each frame's status: the input figures
every status carries (rate, latency, frames received and dropped, the queue), the watchdog's stall
status, and the summary once a second (the worst of waiting / stalled / dropping / the last frame, with
the transport, extrinsic, parameter changes, wheel messages, map -> odom).

:class:`NodeDiagnostics` is part of :class:`~epi_vo.ros.node.VoNodeBase` (it reads the session's state);
every DiagnosticArray is stamped with the node's clock, every age is measured on the steady clock.
"""

from __future__ import annotations

import math
import time

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.status import summary_status
from epi_vo.core.transforms import rotation_angle_deg


class NodeDiagnostics:
    """The diagnostics of a VO session (mixed into ``VoNodeBase``: it uses the session's attributes)."""

    def _input_values(self) -> tuple[tuple[str, str], ...]:
        now = time.monotonic()
        with self._lock:
            q = self._frames
            rate, last = q.input_rate_hz(now), q.last_arrival_s
            received, dropped, overflow, queued, held = q.received, q.dropped, q.overflow, len(q), q.held_bytes
            waiting = q.pending
        since = now - last if last is not None else math.inf
        return (("input_rate_hz", f"{rate:.2f}"), ("latency_ms", f"{self._last_latency_ms:.2f}"),
                ("frames_received", str(received)), ("dropped_frames", str(dropped)),
                ("dropped_frames_over_limit", str(overflow)), ("queue_depth", str(queued)),
                ("waiting_for_camera_info", str(waiting)), ("queue_mb", f"{held * 1e-6:.3f}"),
                ("time_since_last_image_s", f"{since:.3f}" if math.isfinite(since) else "never"))

    def _diagnostics_stamp(self) -> Time:
        """The node's clock now: the one time base of all of vo_node's diagnostics (a frame's image stamp
        is in its values), as diagnostic_updater stamps them."""
        return self.get_clock().now().to_msg()

    def _publish_status(self, status: DiagnosticStatusRecord, stamp_msg: Time) -> None:
        """One status with the input figures, in a DiagnosticArray stamped ``stamp_msg``."""
        arr = DiagnosticArray()
        arr.header.stamp = stamp_msg
        msg = DiagnosticStatus(level=bytes([int(status.level)]), name=status.name, message=status.message,
                               hardware_id=status.hardware_id)
        msg.values = [KeyValue(key=k, value=v) for k, v in status.values + self._input_values()]
        arr.status = [msg]
        self._pub_diag.publish(arr)

    def _waiting_for_images(self) -> str:
        """'camera/image_raw or .../compressed': the image topics still subscribed, for the stall message."""
        return " or ".join(self._image_topics[k] for k in ("raw", "compressed") if k in self._image_subs)

    def _stall(self) -> tuple[DiagnosticLevel, str] | None:
        """The watchdog's verdict on the steady clock: None while images come in time."""
        with self._lock:
            last = self._frames.last_arrival_s
        silent = math.inf if last is None else time.monotonic() - last
        timeout = self.opts.watchdog_timeout_s
        if silent < timeout:
            return None
        level = DiagnosticLevel.STALE if silent >= 3 * timeout else DiagnosticLevel.WARN
        what = f"no image received yet on {self._waiting_for_images()}" if last is None \
            else f"no image for {silent:.1f} s on {self._waiting_for_images()}"
        return level, f"stalled: {what}"

    def _watchdog(self) -> None:
        if not self._active:  # not taking images on purpose: the summary says so
            return
        with self._cv:  # images that waited their camera_info long enough go on without it (status guarantee)
            if self._frames.expire(time.monotonic()):
                self._cv.notify()
        stall = self._stall()
        if stall is not None:
            self._publish_status(DiagnosticStatusRecord(stall[0], f"{self._status_name}: tracking", stall[1],
                                                        self._hardware_id()), self._diagnostics_stamp())

    def _publish_summary(self) -> None:
        """Once a second, as diagnostic_updater would: the worst of waiting / stalled / the last frame."""
        stall, frame = self._stall(), self._last_frame_status
        waiting = self._waiting
        if not self._active:
            level, message = DiagnosticLevel.OK, f"inactive: {self._n_ignored} images ignored (activate to track)"
        elif waiting:
            level, message = DiagnosticLevel.WARN, waiting
        elif stall is not None:
            level, message = stall
        elif frame is not None:
            level, message = frame.level, frame.message
        else:
            level, message = DiagnosticLevel.WARN, "starting"
        if dropping := self._dropping():
            level, message = max(level, DiagnosticLevel.WARN), f"{dropping}; {message}"
        extrinsic = self._extrinsic
        T = self._converter.T_base_cam
        values = (
            ("image_transport", self._transport or "auto (none received yet)"),
            ("image_topic", self._waiting_for_images()),
            ("camera_frame", self._camera_frame),
            ("extrinsic_source", extrinsic.source if extrinsic is not None else "pending"),
            ("camera_xyz", " ".join(f"{v:.4g}" for v in T[:3, 3])),
            ("frames_processed", str(self._n_processed)),
            ("parameter_changes", "; ".join(self._changes[-3:]) or "none"),  # the latest applied
            *self._wheel_values(),
            *self._map_odom_values(),
            *self._summary_extra_values(),
        )
        self._publish_status(summary_status(self._status_name, self._hardware_id(), level, message, values),
                             self._diagnostics_stamp())

    def _dropping(self) -> str:
        """Since the last summary: frames dropped by the queue's memory bound (which a configuration that keeps
        every frame, process_every_frame, does not ask for), said as a WARN while it lasts; '' when none."""
        with self._lock:
            q = self._frames
            new, self._overflow_reported = q.overflow - self._overflow_reported, q.overflow
            queued, held_mb = len(q), q.held_bytes * 1e-6
        if not new:
            return ""
        return (f"dropping frames: {new} since the last summary, the frames waiting reached queue_max_mb="
                f"{self.opts.queue_max_mb:g} ({queued} waiting, {held_mb:.1f} MB)")

    def _map_odom_values(self) -> tuple[tuple[str, str], ...]:
        """With map_frame_id: how far the corrections have taken map from odom (in the
        frame status's ``units``: metres, or VO units while no map -> odom is broadcast)."""
        if not self.opts.map_frame_id:
            return ()
        M = self._converter.T_map_odom
        return ((f"{self.opts.map_frame_id}_to_{self.opts.frame_id}",
                 f"{float(np.linalg.norm(M[:3, 3])):.4g} (the status's units), "
                 f"{rotation_angle_deg(M[:3, :3]):.3g} deg"),)

    def _wheel_values(self) -> tuple[tuple[str, str], ...]:
        """With wheel odometry: the messages received (what became of them: each frame's wheel_messages)."""
        if self.cfg.scale_source != "wheel_odometry":
            return ()
        return (("wheel_messages_received", str(self._wheel_received)),
                ("wheel_messages_lost", str(self._wheel_lost)))

    def _summary_extra_values(self) -> tuple[tuple[str, str], ...]:
        """Further key/values of the summary (the managed node's state)."""
        return ()
