"""What ``vo_node`` says about itself: each frame's status on ``vo/frame_status``, and its health on
``/diagnostics`` once a second, the way diagnostic_updater publishes (``epi_vo.core.health``).

``vo/frame_status`` (diagnostic_msgs/DiagnosticArray, one per frame): the status ``<node>: tracking`` with the
frame's level and reason and the whole frame record, plus the input figures (rate, latency, frames received
and dropped, the queue). ``/diagnostics`` (one array a second, on the steady clock): ``<node>: tracking``
(the worst frame of the second), ``<node>: input`` (images coming, stalled by the watchdog, dropped for the
queue's memory bound), ``<node>: extrinsic`` and ``<node>: scale``, each with a stable message and its numbers
as key/values (and the managed node's ``<node>: lifecycle``).

:class:`NodeDiagnostics` is part of :class:`~epi_vo.ros.node.VoNodeBase` (it reads the session's state);
every DiagnosticArray is stamped with the node's clock, every age is measured on the steady clock.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from epi_vo.core import health
from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.frame import FrameResult
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

    def _array(self, statuses: Sequence[DiagnosticStatusRecord]) -> DiagnosticArray:
        arr = DiagnosticArray()
        arr.header.stamp = self._diagnostics_stamp()
        for status in statuses:
            msg = DiagnosticStatus(level=bytes([int(status.level)]), name=status.name, message=status.message,
                                   hardware_id=status.hardware_id)
            msg.values = [KeyValue(key=k, value=v) for k, v in status.values]
            arr.status.append(msg)
        return arr

    def _publish_frame(self, status: DiagnosticStatusRecord, r: FrameResult) -> None:
        """The frame's status (``epi_vo.runner.outputs``), with the input figures, on vo/frame_status; the
        frame is folded into the tracking health published on /diagnostics."""
        self._pub_frame_status.publish(self._array([DiagnosticStatusRecord(
            status.level, status.name, status.message, status.hardware_id, status.values + self._input_values())]))
        with self._lock:
            self._tracking = self._tracking.add(r)

    def _waiting_for_images(self) -> str:
        """'camera/image_raw or .../compressed': the image topics still subscribed."""
        return " or ".join(self._image_topics[k] for k in ("raw", "compressed") if k in self._image_subs)

    def _stall(self) -> DiagnosticLevel | None:
        """The watchdog's verdict on the steady clock: None while images come in time."""
        with self._lock:
            last = self._frames.last_arrival_s
        silent = math.inf if last is None else time.monotonic() - last
        timeout = self.opts.watchdog_timeout_s
        if silent < timeout:
            return None
        return DiagnosticLevel.STALE if silent >= 3 * timeout else DiagnosticLevel.WARN

    def _watchdog(self) -> None:
        """Images that waited their camera_info long enough go on without it (every image gets a status)."""
        if not self._active:
            return
        with self._cv:
            if self._frames.expire(time.monotonic()):
                self._cv.notify()

    def _health(self) -> list[DiagnosticStatusRecord]:
        """The statuses of /diagnostics now; the tracking period starts afresh."""
        name, hw = self._status_name, self._hardware_id()
        with self._lock:
            tracking, self._tracking = self._tracking, self._tracking.next_period()
            received_any = self._frames.last_arrival_s is not None
        dropping = self._dropping()
        state = health.InputState(active=self._active, stall=self._stall() if self._active else None,
                                  received_any=received_any, dropping=bool(dropping))
        input_values = (("image_transport", self._transport or "auto (none received yet)"),
                        ("image_topic", self._waiting_for_images()), ("camera_frame", self._camera_frame),
                        *self._input_values(), ("dropping", dropping or "none"))
        extrinsic = self._extrinsic
        T = self._converter.T_base_cam
        extrinsic_values = (("camera_frame", self._camera_frame), ("child_frame_id", self.opts.child_frame_id),
                            ("camera_xyz", " ".join(f"{v:.4g}" for v in T[:3, 3])),
                            ("detail", extrinsic.text if extrinsic is not None else self._waiting or "no image yet"))
        return [
            tracking.status(name, hw, (("parameter_changes", "; ".join(self._changes[-3:]) or "none"),
                                       *self._map_odom_values())),
            health.input_status(name, hw, state, input_values),
            health.extrinsic_status(name, hw, extrinsic.source if extrinsic is not None else "pending",
                                    bool(self._waiting), extrinsic is not None and extrinsic.warn, extrinsic_values),
            health.scale_status(name, hw, self.cfg.scale_source, tracking.scale, self._wheel_values()),
            *self._extra_statuses(),
        ]

    def _publish_diagnostics(self) -> None:
        """Once a second (steady clock), as diagnostic_updater would: one status per concern."""
        self._pub_diag.publish(self._array(self._health()))

    def _dropping(self) -> str:
        """Since the last publication: frames dropped by the queue's memory bound (which a configuration that
        keeps every frame, process_every_frame, does not ask for); '' when none."""
        with self._lock:
            q = self._frames
            new, self._overflow_reported = q.overflow - self._overflow_reported, q.overflow
            queued, held_mb = len(q), q.held_bytes * 1e-6
        if not new:
            return ""
        return (f"{new} frames since the last status, the frames waiting reached queue_max_mb="
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
        """With wheel odometry: the topic and the messages received (what became of them: wheel_messages)."""
        if self.cfg.scale_source != "wheel_odometry":
            return ()
        return (("wheel_odometry_topic", self._wheel_topic_name),
                ("wheel_messages_received", str(self._wheel_received)),
                ("wheel_messages_lost", str(self._wheel_lost)))

    def _extra_statuses(self) -> tuple[DiagnosticStatusRecord, ...]:
        """Further statuses of /diagnostics (the managed node's lifecycle)."""
        return ()
