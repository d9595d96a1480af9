"""Re-localisation: a frame whose tracks against the reference are lost found again against the recent
keyframes' map points, so that a loss continues the same map, trajectory and scale instead of starting a
new map with a new unit.

Each recent keyframe is kept with its image, and so is the last frame tracked against the current keyframe
with where it saw the keyframe's map points (``Recent``: a view of a keyframe's points). A lost frame tracks
the map points from the nearest such view in time into its own (KLT started from the whole image's motion,
forward-backward checked: ``features.track_klt``), and the camera's pose is fitted to them
(``geometry.refine_pose_pnp``: a robust start from minimal poses, then Levenberg-Marquardt at the map's
reprojection gate). The pose is taken when at least ``min_inliers`` map points hold it: the number below
which no frame gives a pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import features as fe
from epi_vo.core import geometry as geo
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.keyframe import Keyframe
from epi_vo.core.transforms import invert_T, make_T

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class Recent:
    """A view of the map points of keyframe ``kf`` in an image ``gray`` (the keyframe's own, or a frame
    tracked against it): the keyframe's rows with depth and where they are in that image (raw pixels).
    Never changed in place."""

    kf: Keyframe
    gray: NDArray[np.uint8]
    rows: I64
    pts: F32


def view(kf: Keyframe, gray: NDArray[np.uint8], rows: I64, pts: F32, cfg: VoConfig) -> Recent | None:
    """The keyframe's map points among ``rows`` seen at ``pts`` in ``gray``; None with fewer than
    ``min_inliers`` of them (nothing a pose could be found from)."""
    depth = np.isfinite(kf.X_kf[rows, 0])
    if np.count_nonzero(depth) < cfg.min_inliers:
        return None
    return Recent(kf, gray, rows[depth], pts[depth])


@dataclass(frozen=True)
class Relocalised:
    """A pose found against the keyframe ``kf``: ``T_cur_kf``, its covariance relative to the keyframe
    (position of the camera then rotation, in the keyframe's frame), and the keyframe's map points that
    hold it: their rows, where they are in this image (raw pixels) and in this camera's frame."""

    kf: Keyframe
    T_cur_kf: F64
    cov_rel: F64
    rows: I64
    pts: F32
    X_cur: F64

    @property
    def n(self) -> int:
        return int(self.rows.shape[0])

    @property
    def T_w_c(self) -> F64:
        return np.asarray(self.kf.T_w_kf @ invert_T(self.T_cur_kf), dtype=np.float64)

    @property
    def cov_w_c(self) -> F64:
        """The pose's covariance in the odometry frame: the keyframe's and the fit's own."""
        return covm.compose(self.kf.cov_w_kf, self.kf.T_w_kf, self.cov_rel, self.T_cur_kf[:3, 3],
                            self.T_cur_kf[:3, :3])


def remembered(recent: tuple[Recent, ...], kf: Keyframe, gray: NDArray[np.uint8], cfg: VoConfig
               ) -> tuple[Recent, ...]:
    """The recent keyframes after ``kf`` (made from ``gray``) joined them: the last
    ``relocalise_keyframes``."""
    own = view(kf, gray, np.arange(kf.n_features, dtype=np.int64), kf.pts, cfg)
    if cfg.relocalise_keyframes <= 0 or own is None:
        return recent
    return (*recent, own)[-cfg.relocalise_keyframes:]


def relocalise(views: tuple[Recent, ...], gray: NDArray[np.uint8], camera: CameraModel, cfg: VoConfig
               ) -> Relocalised | None:
    """The pose of this image from the most recent of ``views`` whose map points find it (None: none)."""
    for r in reversed(views):
        if not r.kf.camera.same_as(camera) or r.gray.shape != gray.shape:
            continue
        found = _against(r, gray, camera, cfg)
        if found is not None:
            return found
    return None


def _against(r: Recent, gray: NDArray[np.uint8], camera: CameraModel, cfg: VoConfig) -> Relocalised | None:
    kf = r.kf
    klt = fe.track_klt(r.gray, gray, r.pts, cfg)
    rows, pts = r.rows[klt.ok], klt.pts[klt.ok]
    if rows.shape[0] < cfg.min_inliers:
        return None
    X = kf.X_kf[rows]
    uv = camera.to_pixels(camera.normalize(pts))
    fit = geo.refine_pose_pnp(X, uv, camera.K, np.eye(3), np.zeros(3), cfg.max_reprojection_error_px,
                              robust_start=True)
    if fit is None:
        return None
    R, t, keep, cov_pnp = fit
    X_cur = X[keep] @ R.T + t
    if np.count_nonzero(keep) < cfg.min_inliers or not np.all(X_cur[:, 2] > 0):
        return None
    T = make_T(R, t)
    # The fit's covariance is of (rotation vector, t); the camera's position in the keyframe is c = -R^T t.
    cov_rel = np.zeros((6, 6))
    cov_rel[:3, :3] = R.T @ cov_pnp[3:, 3:] @ R
    cov_rel[3:, 3:] = R.T @ cov_pnp[:3, :3] @ R
    return Relocalised(kf, T, cov_rel, rows[keep], pts[keep].astype(np.float32), X_cur)
