"""The camera extrinsic of ``vo_node``: TF when it has it, the parameters otherwise; and its TF output.

The extrinsic ``T_base_cam`` maps points of the camera's optical frame (the image's ``header.frame_id``,
x right, y down, z forward, REP-103) into the robot base frame (``child_frame_id``). The first image
waits for it:

* TF (``tf2_ros`` importable, ``tf_timeout_s`` > 0, the image has a frame_id): the node looks up
  ``base <- frame_id`` and waits for it at most ``tf_timeout_s`` (steady clock), saying so in its
  diagnostics while it waits;
* otherwise, or when the wait runs out: ``camera_xyz`` / ``camera_rpy`` (the optical rotation appended),
  with one warning naming why.

Then it follows TF (:meth:`ExtrinsicResolver.follow`, once per frame; a lookup in a tf2 buffer is a map
search, cheap beside a frame): when the wait ran out, a TF that arrives later (a robot_state_publisher
started after the camera) replaces the parameters; a TF that moves (a camera on a pan-tilt head) is
followed when it changes by more than ``MOUNTING_TOLERANCE_M`` / ``MOUNTING_TOLERANCE_RAD``. Each switch
is a new :class:`Extrinsic` that the node applies between two frames and says. TF is never looked up when
``tf_timeout_s`` is 0, tf2_ros is missing or the image has no frame_id.

The lookup is a small object (:class:`BufferLookup`) around anything with tf2_ros.Buffer's
``lookup_transform(target, source, time)``, so tests drive the same code with a fake buffer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.transforms import invert_T, make_T, rotation_angle_deg, rotation_from_quat_xyzw

F64 = NDArray[np.float64]

# A mounting that moved less than this is the same mounting: a re-broadcast static transform differs by float
# rounding only, and a joint's encoder noise by far less than what one frame's VO resolves of the camera's
# pose (millimetres, milliradians at best); following it would re-anchor the odometry at every frame for
# nothing.
MOUNTING_TOLERANCE_M = 1.0e-3
MOUNTING_TOLERANCE_RAD = 1.0e-3


class TransformLookup(Protocol):
    """``T_target_source`` (4x4, maps source points into target) now, or None while TF does not have it."""

    def lookup(self, target_frame: str, source_frame: str) -> F64 | None: ...


def T_from_transform(transform: Any) -> F64:
    """A geometry_msgs/Transform (translation, rotation as x y z w) as a 4x4 matrix."""
    t, q = transform.translation, transform.rotation
    R = rotation_from_quat_xyzw([q.x, q.y, q.z, q.w])
    return make_T(R, [t.x, t.y, t.z])


class BufferLookup:
    """:class:`TransformLookup` over a tf2_ros.Buffer (or any object with its ``lookup_transform``).

    ``not_yet`` are the exceptions that mean "not available (yet)" (tf2_ros.TransformException); ``latest``
    makes the time argument (``rclpy.time.Time()``: the latest transform, as for a static mounting).
    """

    def __init__(self, buffer: Any, not_yet: tuple[type[BaseException], ...], latest: Callable[[], Any]) -> None:
        self._buffer = buffer
        self._not_yet = not_yet
        self._latest = latest
        self.keep: Any = None  # what must live as long as the buffer (the TransformListener)

    def lookup(self, target_frame: str, source_frame: str) -> F64 | None:
        try:
            stamped = self._buffer.lookup_transform(target_frame, source_frame, self._latest())
        except self._not_yet:
            return None
        T = T_from_transform(stamped.transform)
        return T if np.all(np.isfinite(T)) else None


def make_tf2_lookup(node: Any) -> BufferLookup | None:
    """A lookup over a tf2_ros Buffer and TransformListener of ``node``; None when tf2_ros is not importable."""
    try:
        from tf2_ros import Buffer, TransformException, TransformListener
    except ImportError:
        return None
    from rclpy.time import Time

    buffer = Buffer()
    lookup = BufferLookup(buffer, (TransformException,), Time)
    lookup.keep = TransformListener(buffer, node)
    return lookup


@dataclass(frozen=True)
class Extrinsic:
    """The decided extrinsic: ``T_base_cam``, ``source`` ('tf' or 'parameters'), and the sentence to log
    (``warn``: at WARN, since it is a fallback the user did not ask for)."""

    T_base_cam: F64
    source: str
    text: str
    warn: bool

    def record(self) -> dict[str, object]:
        """The frame record's ``extrinsic`` entry of a frame that switched to it."""
        return {"source": self.source, "xyz": [round(float(v), 6) for v in self.T_base_cam[:3, 3]],
                "detail": self.text}


def mounting_change(T_a: F64, T_b: F64) -> tuple[float, float]:
    """How far two mountings are apart: (translation in m, rotation in rad)."""
    D = invert_T(T_a) @ T_b
    return float(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3])), float(np.radians(rotation_angle_deg(D[:3, :3])))


class ExtrinsicResolver:
    """Decides ``T_base_cam`` at the first image, then follows TF (see the module doc). Not thread-safe: one
    caller (the node's worker), which calls :meth:`poll` until it returns an :class:`Extrinsic`, then
    :meth:`follow` once per frame."""

    def __init__(self, lookup: TransformLookup | None, base_frame: str, timeout_s: float, T_params: F64,
                 params_text: str, why_no_lookup: str = "tf2_ros is not importable") -> None:
        self._lookup = lookup
        self._base = base_frame
        self._timeout_s = timeout_s
        self._T_params = T_params
        self._params_text = params_text
        self._why_no_lookup = why_no_lookup
        self._started_s: float | None = None
        self.frame_id = ""  # the camera frame waited for ('' before the first image)
        self._current: Extrinsic | None = None  # the one in use, once decided
        self._follows = False  # whether TF is looked up again at every frame

    def _fallback(self, why: str, warn: bool = True) -> Extrinsic:
        return Extrinsic(self._T_params, "parameters", f"camera extrinsic from {self._params_text} ({why})", warn)

    def _from_tf(self, T: F64, why: str = "") -> Extrinsic:
        xyz = " ".join(f"{v:.3f}" for v in T[:3, 3])
        return Extrinsic(T, "tf", f"camera extrinsic from TF {self._base} <- {self.frame_id} (xyz {xyz} m){why}",
                         False)

    def _decided(self, extrinsic: Extrinsic, follows: bool) -> Extrinsic:
        self._current, self._follows = extrinsic, follows
        return extrinsic

    def poll(self, frame_id: str, now_s: float) -> Extrinsic | None:
        """The extrinsic for images of ``frame_id`` at steady time ``now_s``; None: keep waiting for TF."""
        self.frame_id = frame_id
        if self._timeout_s <= 0:
            return self._decided(self._fallback("tf_timeout_s is 0: TF not looked up", warn=False), False)
        if self._lookup is None:
            return self._decided(self._fallback(self._why_no_lookup), False)
        if not frame_id:
            return self._decided(self._fallback("the image header.frame_id is empty: no TF frame to look up"),
                                 False)
        if self._started_s is None:
            self._started_s = now_s
        T = self._lookup.lookup(self._base, frame_id)
        if T is not None:
            return self._decided(self._from_tf(T), True)
        if now_s - self._started_s >= self._timeout_s:
            why = (f"no TF {self._base} <- {frame_id} within tf_timeout_s={self._timeout_s:g} s; TF is still "
                   "looked up at every frame")
            return self._decided(self._fallback(why), True)
        return None

    def follow(self) -> Extrinsic | None:
        """One more lookup, once the extrinsic is decided: a new :class:`Extrinsic` when TF arrived after the
        fallback to the parameters, or moved by more than the tolerance (module doc); None: keep the one in
        use (also while TF has nothing: the last one known stands)."""
        if not self._follows or self._current is None or self._lookup is None:
            return None
        T = self._lookup.lookup(self._base, self.frame_id)
        if T is None:
            return None
        was = self._current
        if was.source != "tf":
            return self._decided(self._from_tf(T, f"; it arrived after the wait, replacing the {self._params_text}"),
                                 True)
        moved_m, turned_rad = mounting_change(was.T_base_cam, T)
        if moved_m <= MOUNTING_TOLERANCE_M and turned_rad <= MOUNTING_TOLERANCE_RAD:
            return None
        why = f"; the camera moved on base by {moved_m * 1e3:.1f} mm, {np.degrees(turned_rad):.2f} deg"
        return self._decided(self._from_tf(T, why), True)

    def waiting_text(self, now_s: float) -> str:
        """What the node is waiting for, for its diagnostics ('' when it is not waiting)."""
        if self._started_s is None:
            return ""
        return (f"waiting for TF {self._base} <- {self.frame_id} ({now_s - self._started_s:.1f} s of "
                f"tf_timeout_s={self._timeout_s:g} s)")


def make_tf_broadcaster(node: Any) -> tuple[Any, str]:
    """(a tf2_ros TransformBroadcaster of ``node``, '') or (None, why there is none)."""
    try:
        from tf2_ros import TransformBroadcaster
    except ImportError:
        return None, "tf2_ros is not importable"
    return TransformBroadcaster(node), ""
