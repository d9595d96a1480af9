"""Tests for epi_vo.io.frame_queue: the node's frames from arrival to processing, within their bounds."""

from __future__ import annotations

from epi_vo.io.frame_queue import FrameQueue

MS = 1_000_000
PERIOD = 33 * MS


def _queue(max_frames: int | None, max_bytes: int) -> FrameQueue:
    return FrameQueue(max_frames=max_frames, max_bytes=max_bytes, camera_info_wait_s=0.2, no_info_wait_s=2.0)


def _feed(q: FrameQueue, n: int, nbytes: int = 1000, t0: float = 0.0) -> None:
    for i in range(n):
        stamp = 10**9 + i * PERIOD
        q.add_info(stamp, f"info{i}")
        q.add_image(stamp, f"img{i}", nbytes, t0 + 0.033 * i)


def test_every_frame_kept_within_the_memory_bound() -> None:
    q = _queue(None, 100_000)
    _feed(q, 50)
    assert len(q) == 50 and q.bytes == 50_000 and q.dropped == q.overflow == 0 and q.received == 50
    popped = [q.pop() for _ in range(50)]
    assert [r.image for r in popped if r is not None] == [f"img{i}" for i in range(50)]
    assert q.pop() is None and q.bytes == 0


def test_the_memory_bound_drops_the_oldest_counts_them_as_overflow_and_keeps_the_newest() -> None:
    q = _queue(None, 10_000)  # 10 frames of 1000 bytes
    _feed(q, 40)
    assert len(q) == 10 and q.bytes == 10_000 <= q.max_bytes
    assert q.dropped == q.overflow == 30 and q.received == 40
    assert [q.pop().image for _ in range(10)] == [f"img{i}" for i in range(30, 40)]  # type: ignore[union-attr]
    # One frame larger than the bound on its own still goes through (nothing would ever be processed).
    q.add_image(10**10, "huge", 50_000, 5.0)
    q.add_info(10**10, "info")
    assert len(q) == 1 and q.peek().image == "huge"  # type: ignore[union-attr]


def test_live_mode_keeps_the_newest_frames_and_those_drops_are_no_overflow() -> None:
    q = _queue(2, 10**9)
    _feed(q, 20)
    assert len(q) == 2 and q.dropped == 18 and q.overflow == 0
    q.set_limits(None, 1500)  # process_every_frame switched on at runtime, a small memory bound
    _feed(q, 5, t0=10.0)
    assert len(q) == 1 and q.overflow == 5 + 1


def test_clear_forgets_ready_and_waiting_frames() -> None:
    q = _queue(None, 10**9)
    _feed(q, 3)
    q.add_image(10**10, "waiting", 10, 1.0)  # no camera_info with its stamp yet
    assert len(q) == 3 and q.pending == 1 and q.held_bytes == 3010
    assert q.clear() == 4 and len(q) == 0 and q.pending == 0 and q.held_bytes == 0


def test_images_waiting_for_camera_info_leave_on_the_clock() -> None:
    q = _queue(None, 10**9)
    q.add_image(10**9, "no_info_yet", 10, 0.0)
    assert not q.expire(1.9) and q.pending == 1
    assert q.expire(2.0) and q.pop().info is None  # type: ignore[union-attr]
    assert q.input_rate_hz(2.0) == 0.0 and q.last_arrival_s == 0.0


def test_input_rate_decays_when_the_camera_stalls() -> None:
    q = _queue(None, 10**9)
    _feed(q, 31)
    assert abs(q.input_rate_hz(0.033 * 30) - 1 / 0.033) < 0.5
    assert q.input_rate_hz(0.033 * 30 + 10.0) < 0.11
