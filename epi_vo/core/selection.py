"""Two-view model selection: an essential matrix and a homography compete on the same correspondences.

E comes from the 5-point solver inside a robust estimator, H from ``findHomography``; both are scored
ORB-SLAM style with chi-square gates at ``score_sigma_px`` and H wins when
``RH = S_H / (S_H + S_E) > rh_threshold`` (or when E could not be estimated). A third hypothesis,
"the camera did not move" (H = identity), is scored under the same gate: the motion stage uses it
before a map exists (a static camera must not build a map from something moving in front of it).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.frame import Model

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]


@dataclass(frozen=True)
class ModelSelection:
    """Both models with their chi-square inliers, RH, and the winner (``Model.NONE``: neither)."""

    model: Model
    rh: float
    E: F64 | None
    H: F64 | None
    F: F64 | None  # fundamental matrix of E in undistorted pixels
    inliers_e: Mask | None
    inliers_h: Mask | None
    score_static: float = 0.0  # the "no camera motion" hypothesis (H = identity) under the same gate
    inliers_static: Mask | None = None  # features that did not move


def select_model(uv_kf: F64, uv_cur: F64, K: F64, cfg: VoConfig, pool: ThreadPoolExecutor | None = None,
                 then: Callable[[], None] | None = None) -> ModelSelection:
    """Estimate and score E and H on (N, 2) undistorted pixel correspondences keyframe -> current.

    With ``pool``, H is estimated and scored on its worker while E is estimated here: both OpenCV
    estimators release the GIL and are seeded the same on any thread, so the result is identical.
    ``then`` is called once H is on its way (before E): work it queues on the same worker runs after H.
    """
    h_job: Future[tuple[F64 | None, tuple[float, Mask | None]]] | None = None
    if pool is not None:
        h_job = pool.submit(_homography, uv_kf, uv_cur, cfg)
    if then is not None:
        then()
    E, _ = geo.estimate_essential(uv_kf, uv_cur, K, cfg.essential_method, cfg.ransac_threshold_px,
                                  cfg.ransac_confidence, cfg.ransac_max_iters)
    H, (s_h, in_h) = h_job.result() if h_job is not None else _homography(uv_kf, uv_cur, cfg)
    F = geo.fundamental_from_essential(E, K) if E is not None else None
    s_e, in_e = geo.score_fundamental(F, uv_kf, uv_cur, cfg.score_sigma_px) if F is not None else (0.0, None)
    s_0, in_0 = geo.score_static(uv_kf, uv_cur, cfg.score_sigma_px)
    rh = geo.rh_ratio(s_h, s_e)
    if H is not None and in_h is not None and (rh > cfg.rh_threshold or E is None):
        model = Model.HOMOGRAPHY
    elif E is not None and in_e is not None:
        model = Model.ESSENTIAL
    else:
        model = Model.NONE
    return ModelSelection(model, rh, E, H, F, in_e, in_h, s_0, in_0)


def _homography(uv_kf: F64, uv_cur: F64, cfg: VoConfig) -> tuple[F64 | None, tuple[float, Mask | None]]:
    """H and its (score, inliers)."""
    H, _ = geo.estimate_homography(uv_kf, uv_cur, cfg.homography_method, cfg.ransac_threshold_px,
                                   cfg.ransac_confidence, cfg.ransac_max_iters)
    return H, (geo.score_homography(H, uv_kf, uv_cur, cfg.score_sigma_px) if H is not None else (0.0, None))


class ModelSelector:
    """``select_model`` with a worker thread for H (E and H overlap on two cores: ~0.6 ms a frame less at
    200 points on this project's machine): ``pool`` (one worker, shared with other jobs that should queue
    behind H), or its own, started with the first call."""

    def __init__(self, pool: ThreadPoolExecutor | None = None) -> None:
        self._pool = pool

    def __call__(self, uv_kf: F64, uv_cur: F64, K: F64, cfg: VoConfig, then: Callable[[], None] | None = None
                 ) -> ModelSelection:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="epi_vo_models")
        return select_model(uv_kf, uv_cur, K, cfg, self._pool, then)
