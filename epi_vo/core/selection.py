"""Two-view model selection: an essential matrix and a homography compete on the same correspondences.

E comes from the 5-point solver inside a robust estimator, H from ``findHomography``; both are scored
ORB-SLAM style with chi-square gates at ``score_sigma_px`` and H wins when
``RH = S_H / (S_H + S_E) > rh_threshold`` (or when E could not be estimated). A third hypothesis,
"the camera did not move" (H = identity), is scored under the same gate: the motion stage uses it
before a map exists (a static camera must not build a map from something moving in front of it).
"""

from __future__ import annotations

from collections.abc import Callable
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


HomographyScored = tuple[F64 | None, tuple[float, Mask | None]]  # H and its (score, inliers)


def select_model(uv_kf: F64, uv_cur: F64, K: F64, cfg: VoConfig,
                 homography: Callable[[], HomographyScored] | None = None) -> ModelSelection:
    """Estimate and score E and H on (N, 2) undistorted pixel correspondences keyframe -> current.

    ``homography``: H and its score for these correspondences (``homography_scored``) when it is being
    computed elsewhere (a runner estimates it on another thread while E is estimated here: both OpenCV
    estimators are seeded the same on any thread, so the result is identical); asked for once E is done.
    """
    E, _ = geo.estimate_essential(uv_kf, uv_cur, K, cfg.essential_method, cfg.ransac_threshold_px,
                                  cfg.ransac_confidence, cfg.ransac_max_iters)
    H, (s_h, in_h) = homography() if homography is not None else homography_scored(uv_kf, uv_cur, cfg)
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


def homography_scored(uv_kf: F64, uv_cur: F64, cfg: VoConfig) -> HomographyScored:
    """H from ``findHomography`` and its (score, inliers) under the chi-square gate."""
    H, _ = geo.estimate_homography(uv_kf, uv_cur, cfg.homography_method, cfg.ransac_threshold_px,
                                   cfg.ransac_confidence, cfg.ransac_max_iters)
    return H, (geo.score_homography(H, uv_kf, uv_cur, cfg.score_sigma_px) if H is not None else (0.0, None))
