"""A picture of one frame's two-view geometry (for ``vo/debug_image`` and inspection).

Tracks are drawn from their keyframe position to the current one: green for inliers of the chosen
model, red for outliers (magenta, with a box around them, for what moved in front of a static camera);
for a few inliers the epipolar line of F (E chosen) is drawn in cyan. Lines are computed in
undistorted pixels and drawn on the raw image: exact for undistorted cameras, a close approximation
otherwise.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.frame import FrameResult, Model
from epi_vo.core.geometry import homogeneous

_GREEN, _RED, _CYAN, _WHITE = (0, 200, 0), (0, 0, 230), (230, 200, 0), (255, 255, 255)
_MAGENTA = (230, 0, 230)


def draw_matches(result: FrameResult, gray: NDArray[np.uint8], n_epilines: int = 8) -> NDArray[np.uint8]:
    """BGR image of ``gray`` with the frame's tracks, inlier/outlier colouring and a few epipolar lines."""
    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    m = result.matches
    outlier = _MAGENTA if result.model is Model.STATIC else _RED
    for (x0, y0), (x1, y1), ok in zip(m.pts_kf, m.pts_cur, m.inliers, strict=True):
        color = _GREEN if ok else outlier
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
    return img
