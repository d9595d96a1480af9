"""A picture of one frame's two-view geometry (for ``vo/debug_image`` and inspection).

Tracks are drawn from their keyframe position to the current one: green for inliers of the chosen
model, red for outliers, magenta for movers (``mover_mask``: what moved on its own, with a box around
them); for a few inliers the epipolar line of F (E chosen) is drawn in cyan. Lines are computed in
undistorted pixels and drawn on the raw image: exact for undistorted cameras, a close approximation
otherwise.
"""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.frame import FrameResult, Model
from epi_vo.core.geometry import homogeneous

_GREEN, _RED, _CYAN, _WHITE = (0, 200, 0), (0, 0, 230), (230, 200, 0), (255, 255, 255)
_MAGENTA = (230, 0, 230)


def mover_mask(result: FrameResult) -> NDArray[np.bool_]:
    """(N,) which rows of ``result.matches`` are drawn as movers (features that moved on their own).

    In front of a static camera (model ``static``) the pipeline's inliers are the features that did not
    move, so every other one moved. While the camera moves, the movers were left out of the model
    (never inliers) and ``moving_region`` is their bounding box in undistorted pixels: the outliers inside
    it are drawn as movers. The pipeline's matches say exactly which rows are movers (``Matches.moving``);
    matches without that mask (older records) fall back to the box: an ordinary outlier inside it is then
    drawn as a mover too. All False without movers (``n_moving`` 0).
    """
    m = result.matches
    outliers = ~np.asarray(m.inliers, dtype=bool)
    if result.n_moving == 0 or m.uv_cur.shape[0] == 0:
        return np.zeros(outliers.shape, dtype=bool)
    if result.model is Model.STATIC:
        return outliers
    if m.moving is not None and m.moving.shape == outliers.shape:
        return np.asarray(m.moving, dtype=bool).copy()
    if result.moving_region is None:
        return np.zeros(outliers.shape, dtype=bool)
    x0, y0, x1, y1 = result.moving_region
    u, v = m.uv_cur[:, 0], m.uv_cur[:, 1]
    return outliers & (u >= x0) & (u <= x1) & (v >= y0) & (v <= y1)


def draw_matches(result: FrameResult, gray: NDArray[np.uint8], n_epilines: int = 8) -> NDArray[np.uint8]:
    """BGR image of ``gray`` with the frame's tracks, inlier/outlier/mover colouring and a few epipolar lines."""
    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    m = result.matches
    movers = mover_mask(result)
    for (x0, y0), (x1, y1), ok, moved in zip(m.pts_kf, m.pts_cur, m.inliers, movers, strict=True):
        color = _GREEN if ok else _MAGENTA if moved else _RED
        cv2.line(img, (int(x0), int(y0)), (int(x1), int(y1)), color, 1, cv2.LINE_AA)
        cv2.circle(img, (int(x1), int(y1)), 2, color, -1, cv2.LINE_AA)
    if result.model is Model.ESSENTIAL and np.any(m.F) and np.any(m.inliers):
        idx = np.flatnonzero(m.inliers)
        pick = idx[np.linspace(0, idx.size - 1, min(n_epilines, idx.size)).astype(np.int64)]
        w = img.shape[1]
        for a, b, c in homogeneous(m.uv_kf[pick]) @ m.F.T:  # l_cur = F x_kf
            if abs(b) < 1e-12:
                continue
            y0, y1 = np.rint([-c / b, -(c + a * (w - 1)) / b]).astype(np.int64)
            cv2.line(img, (0, int(y0)), (w - 1, int(y1)), _CYAN, 1, cv2.LINE_AA)
    if result.moving_region is not None:
        x0, y0, x1, y1 = result.moving_region
        cv2.rectangle(img, (x0, y0), (x1, y1), _MAGENTA, 2, cv2.LINE_AA)
        cv2.putText(img, f"moving {result.moving_fraction:.0%}", (x0, max(y0 - 4, 12)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.45, _MAGENTA, 1, cv2.LINE_AA)
    text = (f"{result.state.value} {result.model.value} RH {result.rh:.2f} inl {result.n_inliers}/"
            f"{result.n_tracked} par {result.median_parallax_deg:.2f}deg")
    cv2.putText(img, text, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, _WHITE, 1, cv2.LINE_AA)
    return cast(NDArray[np.uint8], img)
