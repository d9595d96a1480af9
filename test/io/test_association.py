"""Tests for epi_vo.io.association: image / camera_info pairing by header stamp."""

from __future__ import annotations

import pytest

from epi_vo.core.errors import ConfigError
from epi_vo.io.association import CameraInfoAssociator, Ready

MS = 1_000_000
PERIOD = 66 * MS  # ~15 Hz camera


def _stamps(released: list[Ready]) -> list[int]:
    return [r.stamp_ns for r in released]


def test_info_before_image_is_released_at_once() -> None:
    assoc = CameraInfoAssociator()
    assert assoc.add_info(100, "info100") == []
    released = assoc.add_image(100, "img100")
    assert released == [Ready(100, "img100", "info100", exact=True, first_mismatch=False)]
    assert assoc.pending == 0


def test_info_after_image_releases_it() -> None:
    assoc = CameraInfoAssociator()
    assert assoc.add_image(100, "img100") == []
    assert assoc.pending == 1
    released = assoc.add_info(100, "info100")
    assert released == [Ready(100, "img100", "info100", exact=True, first_mismatch=False)]
    assert assoc.pending == 0


def test_interleaved_both_orders_all_exact_in_arrival_order() -> None:
    assoc = CameraInfoAssociator(max_pending=3)
    out: list[Ready] = []
    for i in range(20):
        stamp = 10**9 + i * PERIOD
        if i % 2:
            out += assoc.add_info(stamp, f"info{i}")
            out += assoc.add_image(stamp, f"img{i}")
        else:
            out += assoc.add_image(stamp, f"img{i}")
            out += assoc.add_info(stamp, f"info{i}")
    assert [r.image for r in out] == [f"img{i}" for i in range(20)]
    assert [r.info for r in out] == [f"info{i}" for i in range(20)]
    assert all(r.exact and not r.first_mismatch for r in out)


def test_ready_image_waits_behind_an_older_pending_one() -> None:
    assoc = CameraInfoAssociator(max_pending=3)
    assert assoc.add_image(100, "a") == []
    assert assoc.add_info(200, "info200") == []
    # b has its info, but a (older) is still waiting: arrival order holds b back.
    assert assoc.add_image(200, "b") == []
    released = assoc.add_info(100, "info100")
    assert [(r.image, r.info, r.exact) for r in released] == [("a", "info100", True), ("b", "info200", True)]


def test_never_matching_info_released_after_wait_with_latest_earlier_info() -> None:
    # camera_info stamped 1 ms before each image: never equal.
    assoc = CameraInfoAssociator(max_pending=10, max_wait_ns=200 * MS)
    out: list[Ready] = []
    for i in range(10):
        stamp = 10**9 + i * PERIOD
        out += assoc.add_info(stamp - MS, f"info{i}")
        out += assoc.add_image(stamp, f"img{i}")
    # 200 ms at 66 ms per frame: an image is given up on when the 4th newer one arrives.
    assert _stamps(out) == [10**9 + i * PERIOD for i in range(6)]
    assert assoc.pending == 4
    out += assoc.flush()
    assert [r.image for r in out] == [f"img{i}" for i in range(10)]
    assert [r.info for r in out] == [f"info{i}" for i in range(10)]  # latest info stamped <= image
    assert not any(r.exact for r in out)
    assert [r.first_mismatch for r in out] == [True] + [False] * 9


def test_never_matching_info_pushed_out_by_max_pending() -> None:
    assoc = CameraInfoAssociator(max_pending=2, max_wait_ns=10**12)
    out: list[Ready] = []
    for i in range(6):
        stamp = 10**9 + i * PERIOD
        out += assoc.add_info(stamp + MS, f"info{i}")  # 1 ms after its image
        got = assoc.add_image(stamp, f"img{i}")
        assert assoc.pending <= 2
        out += got
    assert [r.image for r in out] == [f"img{i}" for i in range(4)]
    # Stamped after the image: the latest info stamped <= the image is the previous frame's one;
    # img0 has none stamped <= it, so it gets the newest received when it is pushed out (info2).
    assert [r.info for r in out] == ["info2", "info0", "info1", "info2"]
    assert [r.first_mismatch for r in out] == [True, False, False, False]


def test_no_info_at_all_releases_with_none_and_no_mismatch_flag() -> None:
    assoc = CameraInfoAssociator(max_pending=2, max_wait_ns=200 * MS)
    out: list[Ready] = []
    for i in range(8):
        out += assoc.add_image(10**9 + i * PERIOD, f"img{i}")
    out += assoc.flush()
    assert [r.image for r in out] == [f"img{i}" for i in range(8)]
    assert all(r.info is None and not r.exact and not r.first_mismatch for r in out)


def test_rare_camera_info_is_used_for_all_later_images_warned_once() -> None:
    assoc = CameraInfoAssociator()
    out = assoc.add_info(10**9 - 5 * MS, "the_info")
    for i in range(30):
        out += assoc.add_image(10**9 + i * PERIOD, f"img{i}")
    out += assoc.flush()
    assert [r.image for r in out] == [f"img{i}" for i in range(30)]
    assert all(r.info == "the_info" and not r.exact for r in out)
    assert sum(r.first_mismatch for r in out) == 1
    assert out[0].first_mismatch


def test_info_stamped_after_every_image_falls_back_to_newest_received() -> None:
    assoc = CameraInfoAssociator(max_pending=0)
    assoc.add_info(5 * 10**9, "late_a")
    assoc.add_info(6 * 10**9, "late_b")
    (ready,) = assoc.add_image(10**9, "img")
    assert (ready.info, ready.exact, ready.first_mismatch) == ("late_b", False, True)


def test_exact_match_after_a_mismatch_is_exact_and_not_flagged() -> None:
    assoc = CameraInfoAssociator(max_pending=0)
    assoc.add_info(50, "old")
    (first,) = assoc.add_image(100, "a")
    assoc.add_info(200, "info200")
    (second,) = assoc.add_image(200, "b")
    assert (first.info, first.exact, first.first_mismatch) == ("old", False, True)
    assert (second.info, second.exact, second.first_mismatch) == ("info200", True, False)


def test_flush_releases_everything_in_arrival_order_and_empties() -> None:
    assoc = CameraInfoAssociator(max_pending=5, max_wait_ns=10**12)
    assoc.add_info(300, "info300")
    for stamp in (100, 200, 300):
        assert assoc.add_image(stamp, stamp) == []  # 300 is ready but waits behind 100 and 200
    out = assoc.flush()
    assert [(r.image, r.info, r.exact) for r in out] == [(100, "info300", False), (200, "info300", False),
                                                         (300, "info300", True)]
    assert assoc.pending == 0
    assert assoc.flush() == []


def test_bounded_memory_without_info() -> None:
    assoc = CameraInfoAssociator(max_pending=3, max_wait_ns=10**15, cache_size=5)
    released = 0
    for i in range(1000):
        released += len(assoc.add_image(i * PERIOD, i))
        assert assoc.pending <= 3
    released += len(assoc.flush())
    assert released == 1000


def test_info_cache_is_bounded() -> None:
    assoc = CameraInfoAssociator(cache_size=5)
    for i in range(100):
        assoc.add_info(i, f"info{i}")
    # Only the 5 newest remain: an image stamped like an evicted info is not exact.
    assert assoc.add_image(94, "img") == []
    (ready,) = assoc.add_info(94, "info94-again")
    assert ready.exact
    (old,) = assoc.add_image(3, "old") + assoc.flush()
    assert not old.exact and old.info == "info94-again"  # nothing cached <= 3: newest received


def test_duplicate_image_stamps_both_released() -> None:
    assoc = CameraInfoAssociator()
    assert assoc.add_image(100, "a") == []
    assert assoc.add_image(100, "b") == []
    assert [r.image for r in assoc.add_info(100, "info")] == ["a", "b"]


def test_max_pending_zero_never_holds() -> None:
    assoc = CameraInfoAssociator(max_pending=0)
    (ready,) = assoc.add_image(100, "a")
    assert ready.info is None and assoc.pending == 0


def test_bad_settings_are_reported_together() -> None:
    with pytest.raises(ConfigError, match=r"max_pending must be >= 0.*max_wait_ns.*cache_size must be >= 1"):
        CameraInfoAssociator(max_pending=-1, max_wait_ns=-1, cache_size=0)


def test_images_before_any_camera_info_wait_for_the_first_one() -> None:
    """A subscriber matched with the camera_info publisher a little after the image one loses the first
    camera_info messages: the first images wait (up to startup_pending, whatever their stamps) and take
    the first camera_info received; then the usual waiting applies."""
    assoc = CameraInfoAssociator(max_pending=2, max_wait_ns=200 * MS, startup_pending=10)
    out: list[Ready] = []
    for i in range(6):  # their camera_info messages were lost
        out += assoc.add_image(10**9 + i * PERIOD, f"img{i}")
    assert out == [] and assoc.pending == 6
    out += assoc.add_info(10**9 + 6 * PERIOD, "info6")
    out += assoc.add_image(10**9 + 6 * PERIOD, "img6")
    # Now the usual rules: img5 (66 ms before the newest) may still get its own; img6 waits behind it.
    assert [r.image for r in out] == [f"img{i}" for i in range(5)] and assoc.pending == 2
    assert all(r.info == "info6" and not r.exact for r in out)
    assert sum(r.first_mismatch for r in out) == 1
    out = assoc.add_image(10**9 + 7 * PERIOD, "img7")  # img5 waited long enough
    assert [(r.image, r.info, r.exact) for r in out] == [("img5", "info6", False), ("img6", "info6", True)]


def test_startup_holding_is_bounded() -> None:
    assoc = CameraInfoAssociator(max_pending=2, max_wait_ns=200 * MS, startup_pending=4)
    out: list[Ready] = []
    for i in range(10):
        out += assoc.add_image(10**9 + i * PERIOD, f"img{i}")
        assert assoc.pending <= 4
    assert [r.image for r in out] == [f"img{i}" for i in range(6)] and all(r.info is None for r in out)


def test_expire_releases_what_stamps_alone_would_hold_for_ever() -> None:
    # camera_info 0.5 ms off the image stamps: stamps release an image only once a newer one is 200 ms later,
    # so the last images of a stream would wait for ever. On the receiver's clock they go after max_wait_s.
    assoc = CameraInfoAssociator(max_pending=5, max_wait_ns=200 * MS, max_wait_s=0.2, no_info_wait_s=2.0)
    out: list[Ready] = []
    for i in range(10):
        stamp = 10**9 + i * PERIOD
        out += assoc.add_info(stamp + MS // 2, f"info{i}")
        out += assoc.add_image(stamp, f"img{i}", now_s=10.0 + 0.066 * i, nbytes=100)
    held = assoc.pending
    assert held == 4 and assoc.pending_bytes == 400
    # 0.1 s after the last arrival: the two that waited 0.2 s or more go, the two newer ones wait on.
    first = assoc.expire(10.0 + 0.066 * 9 + 0.1)
    assert [r.image for r in first] == ["img6", "img7"] and assoc.pending == 2
    released = first + assoc.expire(10.0 + 0.066 * 9 + 0.21)
    assert [r.image for r in out + released] == [f"img{i}" for i in range(10)] and assoc.pending == 0
    assert all(not r.exact and r.info is not None for r in released)
    assert released[0].arrived_s == pytest.approx(10.0 + 0.066 * 6) and released[0].nbytes == 100


def test_expire_without_any_camera_info_waits_no_info_wait_s_then_releases_without_one() -> None:
    assoc = CameraInfoAssociator(max_pending=5, startup_pending=30, max_wait_s=0.2, no_info_wait_s=2.0)
    for i in range(3):
        assert assoc.add_image(10**9 + i * PERIOD, f"img{i}", now_s=float(i)) == []
    assert assoc.expire(2.5) == [Ready(10**9, "img0", None, False, False, 0.0, 0)]
    assert [r.image for r in assoc.expire(4.0)] == ["img1", "img2"]
    assert assoc.pending == 0


def test_expire_without_a_clock_bound_or_arrival_time_changes_nothing() -> None:
    assoc = CameraInfoAssociator(max_pending=5, startup_pending=30)
    assoc.add_image(10**9, "a", now_s=0.0)
    assert assoc.expire(1e9) == [] and assoc.pending == 1
    timed = CameraInfoAssociator(max_pending=5, max_wait_s=0.1, no_info_wait_s=0.1)
    timed.add_image(10**9, "b")  # no arrival time: only stamps release it
    assert timed.expire(1e9) == [] and timed.pending == 1
    with pytest.raises(ConfigError, match="max_wait_s must be >= 0, got nan"):
        CameraInfoAssociator(max_wait_s=float("nan"))
