"""The front doors' workers: the step's computations ahead of and beside the frame loop (``epi_vo.runner``)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import features as fe
from epi_vo.core.config import BaSolver, VoConfig
from epi_vo.core.selection import ModelSelection, homography_scored, select_model
from epi_vo.core.workers import Ahead, InlineSolver, WindowSolver
from epi_vo.runner.bundle_worker import ProcessSolver
from epi_vo.runner.klt_ahead import KltAhead

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]


class Threaded:
    """One worker thread beside the frame loop: H while E runs in the loop, then tracking into the next
    image (queued behind H, so the two never share the second core and H is back when E is done); the
    windowed adjustment in a worker process with ``ba_solver: process``."""

    def __init__(self, cfg: VoConfig) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="epi_vo_worker")
        self._ahead = KltAhead(self._pool)
        self._next: U8 | None = None  # the image the next frame brings (``announce_next``)
        # Started now when the adjustment is on: its imports (about a second) overlap the first keyframes.
        process = cfg.ba_window_keyframes > 0 and cfg.ba_solver is BaSolver.PROCESS
        self._solver: WindowSolver = ProcessSolver() if process else InlineSolver()

    @property
    def solver(self) -> WindowSolver:
        return self._solver

    def announce_next(self, gray: U8) -> None:
        self._next = gray

    def track_klt(self, gray_prev: U8, gray_cur: U8, pts_prev: F32, cfg: VoConfig) -> tuple[fe.KltTracks, float]:
        got = self._ahead.take(gray_prev, gray_cur, pts_prev, cfg)
        return got if got is not None else (fe.track_klt(gray_prev, gray_cur, pts_prev, cfg), 0.0)

    def select_model(self, uv_kf: F64, uv_cur: F64, K: F64, cfg: VoConfig, ahead: Ahead | None) -> ModelSelection:
        h = self._pool.submit(homography_scored, uv_kf, uv_cur, cfg)
        if ahead is not None:
            self.track_ahead(ahead, cfg)
        return select_model(uv_kf, uv_cur, K, cfg, h.result)

    def track_ahead(self, ahead: Ahead, cfg: VoConfig) -> None:
        nxt, self._next = self._next, None
        if nxt is not None and nxt.shape == ahead.gray.shape:
            self._ahead.start(ahead.gray, nxt, ahead.pts, cfg)

    def close(self) -> None:
        """End the worker process (if any); the pipeline cannot adjust its window afterwards."""
        self._solver.close()
