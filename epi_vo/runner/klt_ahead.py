"""KLT into the next image, started while the current one is still being processed.

Replay (and a node playing a bag) knows the next image before it processes the current one. Tracking the
current frame's points into it on a worker thread overlaps OpenCV's KLT (it releases the GIL) with the
current frame's model selection and pose. Pyramidal LK tracks each point on its own, and the exposure is
judged on the leading rows (``features.track_klt``), so the result is the one tracking at the next frame
would give: it is used only for the same two images (by content) and the points it tracked, which are the
first rows of the points to track then (a keyframe appends its new corners after the tracked ones; those
are tracked when the frame comes, with the job's exposure gain). When the job covered fewer rows than the
exposure is judged on, and rows were appended, it is dropped: the judgement could differ. Anything else
(a restart, another image) drops it too.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import features as fe
from epi_vo.core.config import VoConfig

F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]


def timed_klt(gray_from: U8, gray_to: U8, pts: F32, cfg: VoConfig) -> tuple[fe.KltTracks, float]:
    """``track_klt`` and the milliseconds it took (on the worker)."""
    t0 = time.perf_counter()
    tracks = fe.track_klt(gray_from, gray_to, pts, cfg)
    return tracks, (time.perf_counter() - t0) * 1e3


def same_image(a: U8, b: U8) -> bool:
    """The same pixels (the same array, or an equal one)."""
    return a is b or (a.shape == b.shape and bool(np.array_equal(a, b)))


@dataclass(frozen=True)
class _Job:
    gray_from: U8
    gray_to: U8
    pts: F32
    future: Future[tuple[fe.KltTracks, float]]


class KltAhead:
    """One KLT job into the next image at a time (module doc)."""

    def __init__(self, pool: ThreadPoolExecutor | None = None) -> None:
        self._pool = pool  # one worker (shared: a job queues behind what was submitted before), or its own
        self._job: _Job | None = None

    def start(self, gray_from: U8, gray_to: U8, pts: F32, cfg: VoConfig) -> None:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="epi_vo_klt_ahead")
        self._job = _Job(gray_from, gray_to, pts, self._pool.submit(timed_klt, gray_from, gray_to, pts, cfg))

    def take(self, gray_from: U8, gray_to: U8, pts_prev: F32, cfg: VoConfig) -> tuple[fe.KltTracks, float] | None:
        """``track_klt(gray_from, gray_to, pts_prev)`` and the milliseconds the worker spent on it, when the
        started job covers it (None: track now)."""
        job, self._job = self._job, None
        if job is None:
            return None
        n = job.pts.shape[0]
        if not (same_image(job.gray_from, gray_from) and same_image(job.gray_to, gray_to)) \
                or pts_prev.shape[0] < n or not np.array_equal(pts_prev[:n], job.pts) \
                or (n < fe.EXPOSURE_MAX_TRACKS and pts_prev.shape[0] > n):
            job.future.cancel()
            return None
        tracks, ms = job.future.result()  # an OpenCV error is raised here, at the frame it belongs to
        if pts_prev.shape[0] > n:
            t0 = time.perf_counter()
            more = fe.track_klt(gray_from, gray_to, pts_prev[n:], cfg, gain=tracks.gain)
            tracks = fe.KltTracks(np.vstack([tracks.pts, more.pts]), np.concatenate([tracks.ok, more.ok]),
                                  tracks.gain, np.concatenate([tracks.fb, more.fb]))
            ms += (time.perf_counter() - t0) * 1e3
        return tracks, ms
