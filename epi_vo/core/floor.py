"""The floor among a keyframe's map points: a robust plane fit restricted to plausible floor normals.

The ``ground_plane`` scale source (``epi_vo.core.scale``) measures the camera's height above it in map
units; ``camera_height_m`` over that height is a measurement of the map's scale error.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GroundPlane:
    """The floor in a camera frame: points X on it satisfy ``normal_up . X = -height``."""

    normal_up: F64  # unit normal pointing from the floor towards the camera (camera frame)
    height: float  # camera centre above the floor, map units
    n_inliers: int
    rel_std: float  # relative standard deviation of ``height``

    @property
    def pitch_deg(self) -> float:
        """Angle of the optical axis below the floor's horizon (positive: looking down)."""
        n = self.normal_up
        return math.degrees(math.atan2(-n[2], math.hypot(n[0], n[1])))

    @property
    def roll_deg(self) -> float:
        """Rotation about the optical axis relative to the floor, right-handed about z (x towards y):
        positive when the image's right side is lower than its left."""
        n = self.normal_up
        return math.degrees(math.atan2(-n[0], -n[1]))


@dataclass(frozen=True)
class FloorSearch:
    """What :func:`find_floor` found: the floor, or why there is none.

    ``n_candidates`` planes had a normal within the tilt of ``up`` with the camera on their upper side;
    ``n_unsupported`` of them had at least as many map points well beneath them as on them, and
    ``best_unsupported`` is the (on, beneath) count of the one with most points on it ((0, 0): none).
    """

    plane: GroundPlane | None
    n_points: int
    n_candidates: int = 0
    n_unsupported: int = 0
    best_unsupported: tuple[int, int] = (0, 0)


# A map point is beneath a floor candidate when it lies further than this fraction of the candidate's
# height through it: the floor's own points scatter within ``ground_inlier_ratio`` (a few %) of it.
BENEATH_FLOOR = 0.2
LEVEL_UP = np.array([0.0, -1.0, 0.0])  # a level camera's up axis in its optical frame (y down)
LEVEL_UP.setflags(write=False)


def find_floor(X: F64, *, max_tilt_deg: float, inlier_ratio: float, min_points: int,
               up: F64 | None = None, iterations: int = 200) -> FloorSearch:
    """The floor among map points ``X`` (camera frame, x right, y down, z forward), and why not.

    Deterministic RANSAC over 3-point planes whose upward normal is within ``max_tilt_deg`` of ``up``
    (a unit vector in the camera frame: the declared mounting's up, default a level camera's -y) and
    that lie below the camera; inliers are within ``inlier_ratio`` of the candidate's height.

    The floor carries the scene: every surface the camera sees stands on it, so map points beneath it
    are errors and few. A candidate with at least as many points well beneath it (``BENEATH_FLOOR``) as
    on it is no floor: a plane through objects (a table, a car's roof, a wall's foot), or, when the
    camera is not mounted as declared (upside down, the floor above), whatever surface lies on the
    declared floor's side. Among the others, points beneath count against a candidate twice. The best
    plane is refit by least squares on its inliers; its height is the median inlier height and its
    relative spread that of a median (1.25 MAD / sqrt(n)).
    """
    X = X[np.all(np.isfinite(X), axis=1)]
    n_pts = X.shape[0]
    if n_pts < max(min_points, 3):
        return FloorSearch(None, n_pts)
    up = LEVEL_UP if up is None else up
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    rng = np.random.default_rng(12345)  # fixed: replay stays deterministic
    idx = rng.integers(0, n_pts, size=(iterations, 3))
    A, B, C = X[idx[:, 0]], X[idx[:, 1]], X[idx[:, 2]]
    N = np.cross(B - A, C - A)
    norm = np.linalg.norm(N, axis=1)
    ok = norm > 1e-12
    N = N[ok] / norm[ok, None]
    A = A[ok]
    N *= np.where(N @ up < 0, -1.0, 1.0)[:, None]
    h = -np.einsum("ij,ij->i", N, A)
    ok = (N @ up >= cos_tilt) & (h > 0)
    if not np.any(ok):
        return FloorSearch(None, n_pts)
    N, h = N[ok], h[ok]
    # einsum, not BLAS: OpenBLAS's worker threads keep spinning after a call and slow the next
    # frame's OpenCV work on a small CPU (measured: KLT +2 ms per frame on 2 cores).
    D = np.einsum("ij,kj->ik", X, N) + h  # signed distances, positive towards the camera
    inliers = np.abs(D) < inlier_ratio * h
    n_on, n_beneath = inliers.sum(axis=0), (D < -BENEATH_FLOOR * h).sum(axis=0)
    carried = n_beneath < n_on
    search = FloorSearch(None, n_pts, int(N.shape[0]), int(np.count_nonzero(~carried)))
    if not np.all(carried):
        most = int(np.argmax(np.where(carried, -1, n_on)))
        search = dataclasses.replace(search, best_unsupported=(int(n_on[most]), int(n_beneath[most])))
    if not np.any(carried):
        return search
    score = np.where(carried, n_on - 2 * n_beneath, np.iinfo(np.int64).min)
    best = int(np.argmax(score))
    if int(n_on[best]) < min_points:
        return search
    P = X[inliers[:, best]]
    centroid = P.mean(axis=0)
    Q = P - centroid
    _, vecs = np.linalg.eigh(np.einsum("ij,ik->jk", Q, Q))  # 3x3 scatter: no BLAS threads
    n = vecs[:, 0]  # smallest eigenvalue: the plane's normal
    if n @ up < 0:
        n = -n
    if n @ up < cos_tilt:
        return search
    heights = -(P @ n)
    h_med = float(np.median(heights))
    if not h_med > 0:
        return search
    mad = float(np.median(np.abs(heights - h_med)))
    rel_std = 1.253 * 1.4826 * mad / h_med / math.sqrt(P.shape[0])
    return dataclasses.replace(search, plane=GroundPlane(n, h_med, int(P.shape[0]), rel_std))


def fit_ground_plane(X: F64, *, max_tilt_deg: float, inlier_ratio: float, min_points: int,
                     up: F64 | None = None, iterations: int = 200) -> GroundPlane | None:
    """The floor among map points ``X`` (:func:`find_floor`), or None."""
    return find_floor(X, max_tilt_deg=max_tilt_deg, inlier_ratio=inlier_ratio, min_points=min_points, up=up,
                      iterations=iterations).plane
