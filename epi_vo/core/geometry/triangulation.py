"""Triangulation through quality gates (positive depth in both views, reprojection error,
triangulation angle; H&Z ch. 12) and the scale of a translation direction from map points.
Conventions: see ``epi_vo.core.geometry.common``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.geometry.common import F64, Mask, homogeneous


@dataclass(frozen=True)
class Triangulation:
    """Points triangulated from two views and the outcome of the quality gates.

    ``X_ref`` (N, 3) are in the reference camera frame (NaN where the linear solve failed);
    ``good`` marks points passing every gate: finite, positive depth in both views, reprojection error
    below the limit in both views, triangulation angle above the limit.
    """

    X_ref: F64
    good: Mask
    positive_depth: Mask
    reproj_err_px: F64
    angle_deg: F64

    @property
    def positive_depth_ratio(self) -> float:
        n = self.X_ref.shape[0]
        return float(np.count_nonzero(self.positive_depth)) / n if n else 0.0

    def expanded(self, idx: NDArray[np.int64], n: int) -> Triangulation:
        """This triangulation of rows ``idx`` placed into arrays of n rows (others: no point)."""
        X = np.full((n, 3), np.nan)
        good = np.zeros(n, bool)
        pos = np.zeros(n, bool)
        err = np.full(n, np.inf)
        ang = np.zeros(n)
        X[idx], good[idx], pos[idx], err[idx], ang[idx] = (self.X_ref, self.good, self.positive_depth,
                                                            self.reproj_err_px, self.angle_deg)
        return Triangulation(X, good, pos, err, ang)

    @property
    def median_reproj_err_px(self) -> float:
        e = self.reproj_err_px[np.isfinite(self.reproj_err_px)]
        return float(np.median(e)) if e.size else math.nan


def triangulate(R_cur_ref: F64, t_cur_ref: F64, xn_ref: F64, xn_cur: F64, K: F64,
                max_reproj_err_px: float, min_angle_deg: float) -> Triangulation:
    """Linear (DLT) triangulation in normalized coordinates (H&Z 12.2) followed by the quality gates.

    Reprojection error is measured in pixels (normalized error scaled by fx, fy).
    """
    n = xn_ref.shape[0]
    if n == 0:
        empty = np.zeros((0,))
        return Triangulation(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, bool), empty, empty)
    P_ref = np.hstack([np.eye(3), np.zeros((3, 1))])
    P_cur = np.hstack([R_cur_ref, t_cur_ref.reshape(3, 1)])
    X_h = cv2.triangulatePoints(P_ref, P_cur, xn_ref.T.astype(np.float64), xn_cur.T.astype(np.float64))
    w = X_h[3]
    with np.errstate(divide="ignore", invalid="ignore"):
        X_ref = (X_h[:3] / w).T
    X_ref[np.abs(w) < 1e-12] = np.nan
    finite = np.all(np.isfinite(X_ref), axis=1)
    X_cur = X_ref @ R_cur_ref.T + t_cur_ref
    with np.errstate(invalid="ignore"):
        positive = finite & (X_ref[:, 2] > 0.0) & (X_cur[:, 2] > 0.0)
    fx, fy = K[0, 0], K[1, 1]
    scale = np.array([fx, fy])
    with np.errstate(divide="ignore", invalid="ignore"):
        e_ref = np.linalg.norm((X_ref[:, :2] / X_ref[:, 2:3] - xn_ref) * scale, axis=1)
        e_cur = np.linalg.norm((X_cur[:, :2] / X_cur[:, 2:3] - xn_cur) * scale, axis=1)
    err = np.maximum(e_ref, e_cur)
    # A point at a camera centre (depth 0, e.g. t = 0) reprojects to 0/0: no error defined, as a failed solve.
    err = np.where(finite & ~np.isnan(err), err, np.inf)
    # Triangulation angle: between the rays from both camera centres to the point.
    C_cur = -R_cur_ref.T @ t_cur_ref
    ray_ref = X_ref
    ray_cur = X_ref - C_cur
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_a = np.einsum("ij,ij->i", ray_ref, ray_cur) / (
            np.linalg.norm(ray_ref, axis=1) * np.linalg.norm(ray_cur, axis=1))
    angle = np.degrees(np.arccos(np.clip(np.nan_to_num(cos_a, nan=1.0), -1.0, 1.0)))
    good = positive & (err <= max_reproj_err_px) & (angle >= min_angle_deg)
    return Triangulation(X_ref, good, positive, err, angle)


@dataclass(frozen=True)
class ScaleEstimate:
    """Scale ``s`` such that ``s * t_dir`` is the translation in map units, from map points."""

    scale: float
    n_used: int
    rel_spread: float  # robust relative spread (1.4826 MAD / median) of the per-point estimates


def scale_from_points(X_ref: F64, R_cur_ref: F64, t_dir: F64, xn_cur: F64, min_points: int,
                      min_ray_angle_deg: float = 2.0) -> ScaleEstimate | None:
    """Robust 1-D scale of a unit translation from points with known depth in the reference frame.

    For a point ``X_ref`` seen along ``b = [xn_cur, 1]`` in the current view, ``b x (R X + s t) = 0``
    gives ``s = -((b x t) . (b x R X)) / |b x t|^2``. Rays closer than ``min_ray_angle_deg`` to the
    epipole (``b`` parallel to ``t``) carry no scale information and are skipped. The estimate is the
    median, refined by the weighted mean of the points within 3 robust sigmas of it.
    """
    if X_ref.shape[0] < min_points:
        return None
    b = homogeneous(xn_cur)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a = np.cross(b, t_dir)
    c = np.cross(b, X_ref @ R_cur_ref.T)
    a2 = np.einsum("ij,ij->i", a, a)
    usable = a2 > math.sin(math.radians(min_ray_angle_deg)) ** 2
    if np.count_nonzero(usable) < min_points:
        return None
    s_i = -np.einsum("ij,ij->i", a[usable], c[usable]) / a2[usable]
    w = a2[usable]
    med = float(np.median(s_i))
    if not math.isfinite(med) or med <= 0.0:
        return None
    mad = 1.4826 * float(np.median(np.abs(s_i - med)))
    keep = np.abs(s_i - med) <= max(3.0 * mad, 1e-9 * med)
    s = float(np.sum(w[keep] * s_i[keep]) / np.sum(w[keep]))
    if not math.isfinite(s) or s <= 0.0:
        # Per-point estimates so scattered that the weighted mean leaves the median's side: the
        # points disagree with the direction (as a non-positive median does), no scale.
        return None
    return ScaleEstimate(s, int(np.count_nonzero(keep)), mad / med)


