"""The runner: what runs ahead of and beside the per-frame step, shared by the front doors.

The core's step computes pure functions in line (``epi_vo.core.workers.InLine``). The front doors
(``vo_node``, ``epi-vo replay`` and the other offline tools) give it :class:`~epi_vo.runner.workers.Threaded`
instead: KLT into the next image while the current one is processed (when the caller knows it), the
homography on a worker thread while the essential matrix is estimated, the windowed bundle adjustment in a
worker process (``ba_solver: process``). The results are the same bit for bit; only when they are ready
differs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from epi_vo.core.config import VoConfig
    from epi_vo.core.pipeline import VoPipeline


def make_pipeline(cfg: VoConfig | None = None) -> VoPipeline:
    """A :class:`~epi_vo.core.pipeline.VoPipeline` run as the front doors run it (module doc)."""
    from epi_vo.core.config import VoConfig
    from epi_vo.core.pipeline import VoPipeline
    from epi_vo.runner.workers import Threaded

    cfg = cfg or VoConfig()
    return VoPipeline(cfg, workers=Threaded(cfg))
