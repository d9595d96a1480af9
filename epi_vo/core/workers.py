"""Where the per-frame step's heavy computations run: the port the step calls, and its in-line form.

The step computes pure functions of its inputs: KLT from the previous image into this one
(``features.track_klt``), the homography beside the essential matrix (``selection``), the windowed
bundle adjustment (``bundle.adjust``). *When* and *where* they run is not the core's business: the
front doors give the pipeline a :class:`Workers` that may have done the KLT ahead (the next image is
known in a replay), estimate H on another thread while E runs here, or solve the window in a worker
process (``epi_vo.runner``). :class:`InLine` runs everything in the calling thread, in order. Either
way the results are the same, bit for bit: every function is deterministic and gets the same inputs.

The window's adjustments keep their order: each ``WindowSolver.send`` gets its ``receive`` later, in the
order sent.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import features as fe
from epi_vo.core.config import VoConfig
from epi_vo.core.selection import ModelSelection, select_model

if TYPE_CHECKING:
    from epi_vo.core import bundle

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Ahead:
    """This frame's image and the points tracked into it: the next frame tracks from them (KLT), so a
    runner that knows the next image may start that tracking now."""

    gray: NDArray[np.uint8]
    pts: F32


class WindowSolver(Protocol):
    """Where the windowed bundle adjustment runs: each ``send`` gets its ``receive`` later, in order."""

    def send(self, window: bundle.Window) -> None:
        """Start ``bundle.adjust(window)``."""
        ...

    def ready(self) -> bool:
        """Whether ``receive`` would return without waiting."""
        ...

    def receive(self) -> bundle.Adjusted | None:
        """The result of the oldest window sent and not received (waiting for it)."""
        ...

    def in_flight(self) -> int:
        """Windows sent and not yet received."""
        ...

    def take_failure(self) -> str:
        """Why the solver's worker stopped being used, the first time it is asked after it did ("" else)."""
        ...

    def close(self) -> None:
        """Forget what was sent; end the worker (if any)."""
        ...


class InlineSolver:
    """The adjustment in the calling thread (``ba_solver: inline``): ``send`` computes, ``receive`` returns it."""

    def __init__(self) -> None:
        self._results: deque[bundle.Adjusted | None] = deque()

    def send(self, window: bundle.Window) -> None:
        from epi_vo.core import bundle  # GTSAM: only with the windowed adjustment on

        self._results.append(bundle.adjust(window))

    def ready(self) -> bool:
        return True

    def receive(self) -> bundle.Adjusted | None:
        return self._results.popleft()

    def in_flight(self) -> int:
        return len(self._results)

    def take_failure(self) -> str:
        return ""

    def close(self) -> None:
        self._results.clear()


class Workers(Protocol):
    """The step's computations, wherever they run (module doc)."""

    def track_klt(self, gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], pts_prev: F32, cfg: VoConfig
                  ) -> tuple[fe.KltTracks, float]:
        """``features.track_klt(gray_prev, gray_cur, pts_prev, cfg)`` and the milliseconds spent on it
        ahead of this call (0.0: computed now)."""
        ...

    def select_model(self, uv_kf: F64, uv_cur: F64, K: F64, cfg: VoConfig, ahead: Ahead | None
                     ) -> ModelSelection:
        """``selection.select_model(uv_kf, uv_cur, K, cfg)``; ``ahead``: tracking that may start meanwhile."""
        ...

    def track_ahead(self, ahead: Ahead, cfg: VoConfig) -> None:
        """No model selection this frame: tracking into the next image may start now."""
        ...

    def announce_next(self, gray: NDArray[np.uint8]) -> None:
        """The (downscaled) image the next frame will bring, when the caller knows it."""
        ...

    @property
    def solver(self) -> WindowSolver:
        """Where the windowed bundle adjustment runs."""
        ...


class InLine:
    """Every computation in the calling thread, when it is asked for (no look-ahead, no worker)."""

    def __init__(self) -> None:
        self._solver = InlineSolver()

    def track_klt(self, gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], pts_prev: F32, cfg: VoConfig
                  ) -> tuple[fe.KltTracks, float]:
        return fe.track_klt(gray_prev, gray_cur, pts_prev, cfg), 0.0

    def select_model(self, uv_kf: F64, uv_cur: F64, K: F64, cfg: VoConfig, ahead: Ahead | None
                     ) -> ModelSelection:
        return select_model(uv_kf, uv_cur, K, cfg)

    def track_ahead(self, ahead: Ahead, cfg: VoConfig) -> None:
        pass

    def announce_next(self, gray: NDArray[np.uint8]) -> None:
        pass

    @property
    def solver(self) -> WindowSolver:
        return self._solver
