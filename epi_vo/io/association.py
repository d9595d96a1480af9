"""Pair images with their camera_info by header stamp, for the live node (no rclpy).

image_transport publishes an image and its camera_info with the same header stamp on two topics, so
they arrive in either order. Some drivers publish camera_info rarely, or with stamps that never equal
an image stamp; the VO must still run on those images. :class:`CameraInfoAssociator` therefore

- releases an image at once when a camera_info with exactly its stamp is cached;
- otherwise holds it (at most ``max_pending`` images) until its camera_info arrives;
- gives up on an image once a newer image is stamped more than ``max_wait_ns`` after it, or when it
  is pushed out by ``max_pending``, and releases it with the best inexact camera_info: the latest
  cached one stamped at or before the image, else the most recently received one, else None;
- before any camera_info was received, holds up to ``startup_pending`` images whatever their stamps:
  a subscriber that matched the image publisher a few milliseconds before the camera_info one loses
  the first camera_info messages, not the calibration (a node started with a bag played as fast as
  possible lost four; those frames were rejected and the run differed from the offline replay);
- on the receiver's clock too (:meth:`CameraInfoAssociator.expire`, with the arrival time given to
  :meth:`add_image`): an image held ``max_wait_s`` (``no_info_wait_s`` while no camera_info has been
  received at all) is released as above. Stamps alone never release the last images of a stream, nor
  any image when camera_info never comes: those would wait for ever and never get a status.

Every image added comes out exactly once (nothing silently vanishes), always in arrival order: an
image whose camera_info is already there still waits behind older images that are waiting for theirs.
``Ready.first_mismatch`` is True on the first image ever released with an inexact camera_info, so
the node warns once; images released with ``info=None`` (no camera_info received at all) do not set
it, the node reports them on their own.

Stamps are integer nanoseconds (``sec * 10**9 + nanosec``); waiting is measured in image stamps,
not wall time, so the same inputs give the same outputs in a replay and live; the clock bound only
releases what stamps would hold for ever (or longer than the bound).
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Any

from epi_vo.core.errors import ConfigError


@dataclass(frozen=True)
class Ready:
    """An image leaving the associator with the camera_info to use for it.

    ``info`` is the camera_info stamped exactly ``stamp_ns`` when ``exact``; otherwise the best
    inexact one (see module doc), or None when no camera_info has been received. ``first_mismatch``
    is True only on the first image ever released with an inexact, non-None camera_info.
    """

    stamp_ns: int
    image: Any
    info: Any | None
    exact: bool
    first_mismatch: bool
    arrived_s: float | None = None  # the receiver's clock when the image arrived (``add_image``'s now_s)
    nbytes: int = 0  # the image's size as given to ``add_image``


@dataclass
class _Waiting:
    """An image in the arrival queue; ``resolved`` once its camera_info is decided."""

    stamp_ns: int
    image: Any
    arrived_s: float | None = None
    nbytes: int = 0
    resolved: bool = False
    info: Any | None = None
    exact: bool = False


class CameraInfoAssociator:
    """Exact-stamp image / camera_info pairing with bounded waiting (see module doc).

    ``max_pending``: images held waiting for their camera_info (0: never wait). ``max_wait_ns``: an
    image is given up on once a newer image is stamped more than this after it. ``cache_size``:
    camera_info messages kept, by arrival (the oldest received is dropped first). ``startup_pending``:
    images held, whatever their stamps, while no camera_info has been received at all. ``max_wait_s`` /
    ``no_info_wait_s``: how long :meth:`expire` lets an image wait on the receiver's clock once a
    camera_info has been received / before any (None: no bound).
    """

    def __init__(self, max_pending: int = 2, max_wait_ns: int = 200_000_000, cache_size: int = 50,
                 startup_pending: int = 0, max_wait_s: float | None = None,
                 no_info_wait_s: float | None = None) -> None:
        problems = []
        for name, wait in (("max_wait_s", max_wait_s), ("no_info_wait_s", no_info_wait_s)):
            if wait is not None and not wait >= 0:
                problems.append(f"{name} must be >= 0, got {wait}")
        if max_pending < 0:
            problems.append(f"max_pending must be >= 0, got {max_pending}")
        if startup_pending < 0:
            problems.append(f"startup_pending must be >= 0, got {startup_pending}")
        if max_wait_ns < 0:
            problems.append(f"max_wait_ns must be >= 0, got {max_wait_ns}")
        if cache_size < 1:
            problems.append(f"cache_size must be >= 1, got {cache_size}")
        if problems:
            raise ConfigError("invalid camera_info association settings: " + "; ".join(problems))
        self.max_pending = max_pending
        self.startup_pending = startup_pending
        self.max_wait_ns = max_wait_ns
        self.cache_size = cache_size
        self.max_wait_s = max_wait_s
        self.no_info_wait_s = no_info_wait_s
        self._infos: OrderedDict[int, Any] = OrderedDict()  # stamp -> info, oldest received first
        self._queue: deque[_Waiting] = deque()  # images in arrival order, not yet released
        self._newest_image_stamp_ns: int | None = None
        self._mismatch_reported = False

    @property
    def pending(self) -> int:
        """Images held right now (waiting for their camera_info or behind one that is)."""
        return len(self._queue)

    def add_info(self, stamp_ns: int, info: Any) -> list[Ready]:
        """Cache ``info`` (stamped ``stamp_ns``); return the images this releases, in arrival order."""
        stamp_ns = int(stamp_ns)
        self._infos[stamp_ns] = info
        self._infos.move_to_end(stamp_ns)  # a re-sent stamp counts as the newest received
        while len(self._infos) > self.cache_size:
            self._infos.popitem(last=False)
        for waiting in self._queue:
            if not waiting.resolved and waiting.stamp_ns == stamp_ns:
                self._resolve(waiting, info, exact=True)
        return self._give_up()  # images held before any camera_info now wait as usual

    def add_image(self, stamp_ns: int, image: Any, now_s: float | None = None, nbytes: int = 0) -> list[Ready]:
        """Queue ``image`` (arrived at ``now_s`` on the receiver's clock, ``nbytes`` large); return every
        image released now (this one included if it is), in arrival order."""
        stamp_ns = int(stamp_ns)
        waiting = _Waiting(stamp_ns, image, now_s, nbytes)
        if stamp_ns in self._infos:
            self._resolve(waiting, self._infos[stamp_ns], exact=True)
        self._queue.append(waiting)
        if self._newest_image_stamp_ns is None or stamp_ns > self._newest_image_stamp_ns:
            self._newest_image_stamp_ns = stamp_ns
        return self._give_up()

    def _give_up(self) -> list[Ready]:
        """Resolve the images waited for long enough (by stamps, or pushed out); release what can go."""
        if self._infos and self._newest_image_stamp_ns is not None:
            for older in self._queue:
                if not older.resolved and self._newest_image_stamp_ns - older.stamp_ns > self.max_wait_ns:
                    self._resolve_inexact(older)
        released = self._drain()
        bound = self.max_pending if self._infos else max(self.max_pending, self.startup_pending)
        while len(self._queue) > bound:
            # Pushed out: the head is necessarily unresolved (a resolved head would have drained).
            self._resolve_inexact(self._queue[0])
            released += self._drain()
        return released

    def expire(self, now_s: float) -> list[Ready]:
        """Release, in arrival order, what can go once every image that arrived ``max_wait_s`` (before any
        camera_info: ``no_info_wait_s``) or longer before ``now_s`` is given up on (best inexact info)."""
        wait = self.max_wait_s if self._infos else self.no_info_wait_s
        if wait is not None:
            for waiting in self._queue:
                if not waiting.resolved and waiting.arrived_s is not None and now_s - waiting.arrived_s >= wait:
                    self._resolve_inexact(waiting)
        return self._drain()

    @property
    def pending_bytes(self) -> int:
        """The sizes (``add_image``'s nbytes) of the images held."""
        return sum(w.nbytes for w in self._queue)

    def flush(self) -> list[Ready]:
        """Release every held image (end of stream, shutdown), inexact ones with the best camera_info."""
        for waiting in self._queue:
            if not waiting.resolved:
                self._resolve_inexact(waiting)
        return self._drain()

    @staticmethod
    def _resolve(waiting: _Waiting, info: Any | None, exact: bool) -> None:
        waiting.resolved, waiting.info, waiting.exact = True, info, exact

    def _resolve_inexact(self, waiting: _Waiting) -> None:
        self._resolve(waiting, self._best_inexact_info(waiting.stamp_ns), exact=False)

    def _best_inexact_info(self, stamp_ns: int) -> Any | None:
        """The cached info with the largest stamp <= ``stamp_ns``, else the newest received, else None."""
        if not self._infos:
            return None
        earlier = [s for s in self._infos if s <= stamp_ns]
        if earlier:
            return self._infos[max(earlier)]
        return next(reversed(self._infos.values()))

    def _drain(self) -> list[Ready]:
        released = []
        while self._queue and self._queue[0].resolved:
            w = self._queue.popleft()
            # Flagged on release, not on resolution, so that it is the first such image in arrival order.
            first_mismatch = not w.exact and w.info is not None and not self._mismatch_reported
            self._mismatch_reported |= first_mismatch
            released.append(Ready(w.stamp_ns, w.image, w.info, w.exact, first_mismatch, w.arrived_s, w.nbytes))
        return released
