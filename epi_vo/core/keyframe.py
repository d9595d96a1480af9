"""The keyframe: the reference view every correspondence of the following frames is measured from.

A keyframe holds its features (raw pixels, normalized and undistorted coordinates), the map point of
each feature in its own camera frame (NaN: no depth yet), its pose and covariance in the odometry
frame, and for the ORB frontend the descriptors. ``make_keyframe`` builds one from an image: the
features still tracked (with their depth) are kept and the grid is topped up with new corners.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core import features as fe
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Keyframe:
    """The reference view all correspondences of the following frames are measured from.

    Arrays are aligned by row: ``pts`` raw pixels, ``xn`` normalized and ``uv`` undistorted pixels of
    each feature, ``X_kf`` its map point in this keyframe's camera frame (NaN: no depth), and, for the
    ORB frontend, ``descriptors``. ``ids`` names each feature's track: a feature tracked from the
    previous keyframe keeps its id, so a map point observed by several keyframes has one id (what the
    windowed bundle adjustment links).
    """

    index: int
    stamp_ns: int
    T_w_kf: F64
    cov_w_kf: F64
    pts: F32
    xn: F64
    uv: F64
    X_kf: F64
    descriptors: NDArray[np.uint8] | None
    camera: CameraModel
    ids: NDArray[np.int64] | None = None  # None: no track ids (every feature its own track)

    @property
    def n_features(self) -> int:
        return int(self.pts.shape[0])

    @property
    def n_map_points(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.X_kf[:, 0])))


def make_keyframe(index: int, stamp_ns: int, T_w_kf: F64, cov_w_kf: F64, gray: NDArray[np.uint8],
                  camera: CameraModel, pts_tracked: F32, X_tracked: F64, cfg: VoConfig, orb: cv2.ORB | None,
                  orb_cur: fe.OrbFeatures | None, ids_tracked: NDArray[np.int64] | None = None,
                  next_id: int = 0) -> Keyframe:
    """The current frame as the new reference: tracked features keep their depth and track id, the grid
    is topped up with new features numbered from ``next_id`` (``ids_tracked`` None: the tracked ones too)."""
    if ids_tracked is None:
        ids_tracked = next_id + np.arange(pts_tracked.shape[0], dtype=np.int64)
        next_id += pts_tracked.shape[0]
    if orb is None:
        new = fe.detect_corners(gray, pts_tracked, cfg)
        pts = np.vstack([pts_tracked, new]).astype(np.float32)
        X = np.vstack([X_tracked, np.full((new.shape[0], 3), np.nan)])
        ids = np.concatenate([ids_tracked, next_id + np.arange(new.shape[0])]).astype(np.int64)
        desc = None
    else:
        feats = orb_cur if orb_cur is not None else fe.detect_orb(orb, gray, cfg)
        pts, desc = feats.pts, feats.descriptors
        X = np.full((pts.shape[0], 3), np.nan)
        ids = next_id + np.arange(pts.shape[0], dtype=np.int64)
        if X_tracked.shape[0]:
            # For ORB the tracked points are a subset of this frame's detections: match by position.
            for p, x, i in zip(pts_tracked, X_tracked, ids_tracked, strict=False):
                j = int(np.argmin(np.sum((pts - p) ** 2, axis=1)))
                X[j] = x
                ids[j] = i
    xn = camera.normalize(pts)
    return Keyframe(index, stamp_ns, T_w_kf.copy(), cov_w_kf, pts, xn, camera.to_pixels(xn), X, desc, camera, ids)
