"""The windowed adjustment in a worker process (epi_vo.runner.bundle_worker): the in-line result, bit for bit,
beside the frame loop and below its priority; a dead worker hands its windows back to the frame loop."""

from __future__ import annotations

import os

import numpy as np
import pytest
from window_scenes import Win
from window_scenes import entry as _entry
from window_scenes import same_update as _same_update
from window_scenes import scene as _scene
from window_scenes import window_of as _window_of


def test_the_worker_process_gives_the_inline_result_bit_for_bit() -> None:
    inline, process = _window_of("inline"), _window_of("process")
    try:
        assert process.submit(500.0)  # returns at once; the worker adjusts beside this process
        assert inline.submit(500.0)
        a, b = inline.collect(), process.collect()
        assert a is not None and b is not None and a.n_points >= 80
        _same_update(a, b)
        assert process.take_failure() == ""
        assert process.collect() is None  # nothing pending any more
    finally:
        process.close()


def test_a_dead_worker_hands_its_window_to_the_frame_loop_and_says_so_once() -> None:
    inline, process = _window_of("inline"), _window_of("process")
    try:
        proc = process.solver._proc
        assert proc is not None
        proc.kill()
        proc.wait()
        assert process.submit(500.0) and inline.submit(500.0)
        _same_update(inline.collect(), process.collect())
        why = process.take_failure()
        assert "bundle adjustment worker" in why and "adjusting in the frame loop from now on" in why
        assert process.take_failure() == ""  # said once
        assert process.submit(500.0) and inline.submit(500.0)  # and the next windows are adjusted here
        _same_update(inline.collect(), process.collect())
    finally:
        process.close()


def test_a_cleared_window_drops_the_adjustment_under_way() -> None:
    win = _window_of("process")
    try:
        assert win.submit(500.0)
        win.clear()  # a restart: the result no longer fits the keyframes
        assert win.collect() is None
        fresh = Win(size=5, every=1, sigma_px=1.0)
        poses, pts = _scene(seed=1)
        rng = np.random.default_rng(7)
        ids = np.arange(pts.shape[0])
        for T in poses:
            entry = _entry(T, pts, ids, rng, noise=0.0)
            win.add(T, ids, *entry)
            fresh.add(T, ids, *entry)
        assert win.submit(500.0)
        update = win.collect()  # the new window's own result, not the dropped one's
        assert update is not None
        _same_update(update, fresh.adjust(500.0))
    finally:
        win.close()


def test_the_worker_says_when_its_result_is_back_without_waiting_for_it() -> None:
    import time

    inline, process = _window_of("inline"), _window_of("process")
    try:
        assert process.submit(500.0) and inline.submit(500.0)
        deadline = time.monotonic() + 120.0  # a condition with a generous bound, not a fixed sleep
        while not process.solver.ready():
            assert time.monotonic() < deadline, "the worker's result never came back"
            time.sleep(0.01)
        update = process.collect(wait=False)
        assert update is not None
        _same_update(update, inline.collect())
        proc = process.solver._proc
        proc.kill()  # a dead worker is 'ready' too: its window is solved here
        proc.wait()
        assert process.submit(500.0) and inline.submit(500.0)
        while not process.solver.ready():
            assert time.monotonic() < deadline, "the worker's end was never noticed"
            time.sleep(0.01)
        _same_update(inline.collect(), process.collect(wait=False))
        assert "bundle adjustment worker" in process.take_failure()
    finally:
        process.close()


@pytest.mark.skipif(not hasattr(os, "getpriority"), reason="POSIX scheduling priorities only")
def test_the_worker_runs_below_the_frame_loops_priority() -> None:
    import time

    from epi_vo.runner.bundle_worker import WORKER_NICENESS

    process = _window_of("process")
    try:
        assert process.submit(500.0)
        deadline = time.monotonic() + 120.0  # the worker lowers its priority before it serves a window
        while not process.solver.ready():
            assert time.monotonic() < deadline, "the worker's result never came back"
            time.sleep(0.01)
        assert process.collect(wait=False) is not None
        mine = os.getpriority(os.PRIO_PROCESS, 0)
        worker = os.getpriority(os.PRIO_PROCESS, process.solver._proc.pid)
        assert worker == min(mine + WORKER_NICENESS, 19)
    finally:
        process.close()
