"""Two-view geometry: model estimation, ORB-SLAM style scoring, pose recovery, triangulation, scale.

Conventions (used by every function here):
- ``uv_ref``, ``uv_cur``: (N, 2) undistorted pixel coordinates (ideal pinhole camera with intrinsics K)
  of the same N points in the reference (keyframe) and current images; ``xn_*`` the normalized ones.
- ``R_cur_ref``, ``t_cur_ref``: the rigid motion mapping reference-camera coordinates into the
  current camera, ``X_cur = R_cur_ref @ X_ref + t_cur_ref`` (what ``cv2.recoverPose(E, uv_ref, uv_cur)``
  returns). ``t`` from an essential matrix is a unit direction: monocular scale is not observable.
- ``E`` satisfies ``xn_cur^T E xn_ref = 0``; ``F = K^-T E K^-1``; ``H`` maps ``uv_ref`` to ``uv_cur``.

Numerical failure (too few points, a degenerate sample) is a returned value (``None`` model, zero
counts), never an exception. References: Hartley & Zisserman (H&Z) ch. 9-12, 18; Mur-Artal et al.,
ORB-SLAM (2015) sec. IV (model selection); Nister (2004) five-point algorithm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]

# Chi-square 95 % quantiles (ORB-SLAM): 1 DoF for a point-to-line distance, 2 DoF for a
# point-to-point distance. E is scored with the 2-DoF constant so that both models' scores share
# one scale, exactly as ORB-SLAM's CheckFundamental does.
CHI2_1DOF = 3.841
CHI2_2DOF = 5.991

# Distance (in baselines) beyond which recoverPose calls a point 'at infinity'.
_CHEIRALITY_MAX_DISTANCE = 1.0e7

ROBUST_METHOD_FLAGS = {
    "magsac": cv2.USAC_MAGSAC,
    "ransac": cv2.RANSAC,
    "lmeds": cv2.LMEDS,
    "usac_default": cv2.USAC_DEFAULT,
    "usac_accurate": cv2.USAC_ACCURATE,
    "usac_fast": cv2.USAC_FAST,
}


def homogeneous(x: F64) -> F64:
    """(N, 2) -> (N, 3) by appending ones."""
    return np.hstack([x, np.ones((x.shape[0], 1))])


def skew(t: F64) -> F64:
    """[t]_x, the cross-product matrix of a 3-vector (H&Z A4.5)."""
    tx, ty, tz = np.asarray(t, dtype=np.float64).reshape(3)
    return np.array([[0.0, -tz, ty], [tz, 0.0, -tx], [-ty, tx, 0.0]])


def essential_from_pose(R_cur_ref: F64, t_cur_ref: F64) -> F64:
    """E = [t]_x R (H&Z 9.12)."""
    return skew(t_cur_ref) @ R_cur_ref


def fundamental_from_essential(E: F64, K: F64) -> F64:
    """F = K^-T E K^-1 for two views sharing the intrinsics K (H&Z 9.6)."""
    K_inv = np.linalg.inv(K)
    return K_inv.T @ E @ K_inv


def epipolar_distances_sq(F: F64, uv_ref: F64, uv_cur: F64) -> tuple[F64, F64]:
    """Squared point-to-epipolar-line distances (px^2) in the current and in the reference image.

    ``l_cur = F x_ref`` and ``l_ref = F^T x_cur`` (H&Z 9.2).
    """
    x_ref, x_cur = homogeneous(uv_ref), homogeneous(uv_cur)
    l_cur = x_ref @ F.T
    l_ref = x_cur @ F
    num = np.einsum("ij,ij->i", x_cur, l_cur)  # x_cur^T F x_ref, same for both lines
    d_cur = num**2 / np.maximum(l_cur[:, 0] ** 2 + l_cur[:, 1] ** 2, 1e-300)
    d_ref = num**2 / np.maximum(l_ref[:, 0] ** 2 + l_ref[:, 1] ** 2, 1e-300)
    return d_cur, d_ref


def sampson_distance_sq(F: F64, uv_ref: F64, uv_cur: F64) -> F64:
    """First-order geometric error of the epipolar constraint (H&Z 11.9), px^2 for a pixel F."""
    x_ref, x_cur = homogeneous(uv_ref), homogeneous(uv_cur)
    Fx = x_ref @ F.T
    Ftx = x_cur @ F
    num = np.einsum("ij,ij->i", x_cur, Fx) ** 2
    den = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
    return num / np.maximum(den, 1e-300)


def transfer_errors_sq(H: F64, uv_ref: F64, uv_cur: F64) -> tuple[F64, F64]:
    """Squared transfer errors (px^2) of ``H`` (ref -> cur) in the current and in the reference image.

    Symmetric transfer error is their sum (H&Z 4.2.2). Points mapped to infinity get +inf.
    """
    def _transfer(M: F64, src: F64, dst: F64) -> F64:
        p = homogeneous(src) @ M.T
        w = p[:, 2]
        ok = np.abs(w) > 1e-12
        out = np.full(src.shape[0], np.inf)
        proj = p[ok, :2] / w[ok, None]
        out[ok] = np.sum((proj - dst[ok]) ** 2, axis=1)
        return out

    try:
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        inf = np.full(uv_ref.shape[0], np.inf)
        return inf, inf.copy()
    return _transfer(H, uv_ref, uv_cur), _transfer(H_inv, uv_cur, uv_ref)


def _chi2_score(err_sq_cur: F64, err_sq_ref: F64, sigma_px: float, gate: float) -> tuple[float, Mask]:
    """ORB-SLAM scoring of squared errors in both images: each error within the chi-square ``gate``
    adds ``CHI2_2DOF - e^2/sigma^2``; inliers pass the gate in both images."""
    inv_s2 = 1.0 / (sigma_px * sigma_px)
    chi_cur, chi_ref = err_sq_cur * inv_s2, err_sq_ref * inv_s2
    ok_cur, ok_ref = chi_cur <= gate, chi_ref <= gate
    score = float(np.sum(CHI2_2DOF - chi_cur[ok_cur]) + np.sum(CHI2_2DOF - chi_ref[ok_ref]))
    return score, ok_cur & ok_ref


def score_fundamental(F: F64, uv_ref: F64, uv_cur: F64, sigma_px: float) -> tuple[float, Mask]:
    """ORB-SLAM CheckFundamental: point-to-epipolar-line distances in both images, 1-DoF gate, scored
    with the 2-DoF constant; returns (score, inlier mask)."""
    return _chi2_score(*epipolar_distances_sq(F, uv_ref, uv_cur), sigma_px, CHI2_1DOF)


def score_homography(H: F64, uv_ref: F64, uv_cur: F64, sigma_px: float) -> tuple[float, Mask]:
    """ORB-SLAM CheckHomography: transfer errors in both directions, 2-DoF gate; returns (score, inlier
    mask: gate passed in both directions)."""
    return _chi2_score(*transfer_errors_sq(H, uv_ref, uv_cur), sigma_px, CHI2_2DOF)


def rh_ratio(score_h: float, score_e: float) -> float:
    """RH = S_H / (S_H + S_E) (ORB-SLAM eq. 4); 0.5 when neither model explains anything."""
    total = score_h + score_e
    return 0.5 if total <= 0.0 else score_h / total


def estimate_essential(uv_ref: F64, uv_cur: F64, K: F64, method: str = "magsac", threshold_px: float = 1.0,
                       confidence: float = 0.999, max_iters: int = 1000) -> tuple[F64 | None, Mask]:
    """Five-point E inside a robust estimator (USAC MAGSAC by default) on undistorted pixels.

    Returns ``(E, inlier_mask)``; ``E`` is None when fewer than 5 points or no model was found. When
    the estimator returns several stacked solutions (RANSAC/LMEDS may), the first is used.
    """
    n = uv_ref.shape[0]
    if n < 5:
        return None, np.zeros(n, dtype=bool)
    flag = ROBUST_METHOD_FLAGS[method]
    try:
        E, mask = cv2.findEssentialMat(uv_ref, uv_cur, K, method=flag, prob=confidence,
                                       threshold=threshold_px, maxIters=max_iters)
    except cv2.error:
        return None, np.zeros(n, dtype=bool)
    if E is None or E.shape[0] < 3 or E.shape[1] != 3 or mask is None:
        return None, np.zeros(n, dtype=bool)
    E = np.asarray(E[:3, :3], dtype=np.float64)
    if not np.all(np.isfinite(E)):
        return None, np.zeros(n, dtype=bool)
    return E, mask.reshape(-1).astype(bool)


def estimate_homography(uv_ref: F64, uv_cur: F64, method: str = "usac_fast", threshold_px: float = 1.0,
                        confidence: float = 0.999, max_iters: int = 1000) -> tuple[F64 | None, Mask]:
    """H (ref -> cur) by cv2.findHomography on undistorted pixels; None when it fails.

    Plain RANSAC runs to its iteration cap on non-planar scenes (low inlier ratio), ~20 ms for 300
    points; the USAC variants stop early and are the default.
    """
    n = uv_ref.shape[0]
    if n < 4:
        return None, np.zeros(n, dtype=bool)
    try:
        H, mask = cv2.findHomography(uv_ref, uv_cur, ROBUST_METHOD_FLAGS[method], threshold_px, maxIters=max_iters,
                                     confidence=confidence)
    except cv2.error:
        return None, np.zeros(n, dtype=bool)
    if H is None or mask is None or not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
        return None, np.zeros(n, dtype=bool)
    return np.asarray(H, dtype=np.float64), mask.reshape(-1).astype(bool)


def recover_pose(E: F64, uv_ref: F64, uv_cur: F64, K: F64, inliers: Mask, max_points: int = 100
                 ) -> tuple[F64, F64, Mask]:
    """Decompose E and pick the candidate with most points in front of both cameras (cheirality).

    ``cv2.recoverPose(E, uv_ref, uv_cur, K)`` returns the motion ref -> cur. It chooses among the four
    candidates on at most ``max_points`` inliers spread evenly through the list (the vote is not
    close for a correct E, and recoverPose triangulates every point four times); the cheirality of
    every inlier is then checked against the chosen motion. Returns
    ``(R_cur_ref, t_cur_ref (3,) unit, mask of inliers in front of both cameras)``.
    """
    idx = np.flatnonzero(inliers)
    if idx.size < 5:
        return np.eye(3), np.zeros(3), np.zeros(inliers.shape[0], dtype=bool)
    if idx.size > max_points:
        idx = idx[np.linspace(0, idx.size - 1, max_points).astype(np.int64)]
    # The plain overload drops points farther than 50 baselines as 'at infinity', which with video
    # frame rates (short baselines, depths of 100+ baselines) discards most good inliers; only the
    # sign of the depth matters here, so the distance limit is lifted.
    _, R, t, _, _ = cv2.recoverPose(E, uv_ref[idx], uv_cur[idx], cameraMatrix=K,
                                    distanceThresh=_CHEIRALITY_MAX_DISTANCE,
                                    mask=np.ones((idx.size, 1), np.uint8))
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    K_inv = np.linalg.inv(K)
    xn_ref = (homogeneous(uv_ref) @ K_inv.T)[:, :2]
    xn_cur = (homogeneous(uv_cur) @ K_inv.T)[:, :2]
    d_ref, d_cur = ray_depths(R, t, xn_ref, xn_cur)
    return R, t, inliers & (d_ref > 0.0) & (d_cur > 0.0)


def ray_depths(R_cur_ref: F64, t_cur_ref: F64, xn_ref: F64, xn_cur: F64) -> tuple[F64, F64]:
    """Depths (d_ref, d_cur) along both rays of each correspondence, in the least-squares sense.

    Solves ``d_cur b_cur = d_ref R b_ref + t`` per point (2x2 normal equations, vectorised), with
    ``b = [xn, 1]``; the signs are the cheirality test (H&Z 9.6.3). Parallel rays give depth 0.
    """
    a = homogeneous(xn_ref) @ R_cur_ref.T  # R b_ref
    b = homogeneous(xn_cur)
    aa = np.einsum("ij,ij->i", a, a)
    bb = np.einsum("ij,ij->i", b, b)
    ab = np.einsum("ij,ij->i", a, b)
    at = a @ t_cur_ref
    bt = b @ t_cur_ref
    det = ab * ab - aa * bb
    ok = np.abs(det) > 1e-15
    safe = np.where(ok, det, 1.0)
    # d_ref a - d_cur b = -t  ->  [aa -ab; ab -bb] [d_ref d_cur]^T = [-at; -bt]
    d_ref = np.where(ok, (at * bb - ab * bt) / safe, 0.0)
    d_cur = np.where(ok, (ab * at - aa * bt) / safe, 0.0)
    return d_ref, d_cur


def nearest_rotation(M: F64) -> F64:
    """Closest rotation matrix to M in Frobenius norm (polar decomposition via SVD)."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R


def rotation_from_homography(H: F64, K: F64) -> F64:
    """Under pure rotation ``H = K R K^-1`` (H&Z 8.4.2): R_cur_ref is the nearest rotation to K^-1 H K."""
    M = np.linalg.inv(K) @ H @ K
    M = M / np.cbrt(np.linalg.det(M))
    return nearest_rotation(M)


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


def pose_from_homography(H: F64, K: F64, xn_ref: F64, xn_cur: F64, inliers: Mask,
                         max_reproj_err_px: float, min_angle_deg: float
                         ) -> tuple[F64, F64, Triangulation] | None:
    """Planar decomposition of H (Faugeras / Malis, ``cv2.decomposeHomographyMat``) resolved by cheirality.

    Returns ``(R_cur_ref, t_cur_ref, triangulation)`` for the solution with the most points passing the
    gates, with ``t`` in units of the plane's distance from the reference camera; None when no solution
    is clearly best (ORB-SLAM: the runner-up must have < 75 % of the winner's good points).
    """
    _, Rs, ts, _ = cv2.decomposeHomographyMat(H, K)
    idx = np.flatnonzero(inliers)
    results = []
    for R, t in zip(Rs, ts, strict=False):
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.allclose(R @ R.T, np.eye(3), atol=1e-6)):
            # OpenCV returns non-rotations for an H that no plane can produce (e.g. wildly unequal
            # singular values of K^-1 H K); such a candidate is no pose at all.
            continue
        tri = triangulate(R, t, xn_ref[idx], xn_cur[idx], K, max_reproj_err_px, min_angle_deg)
        results.append((int(np.count_nonzero(tri.good)), R, t, tri))
    results.sort(key=lambda r: -r[0])
    if not results or results[0][0] == 0:
        return None
    if len(results) > 1 and results[1][0] >= 0.75 * results[0][0]:
        return None
    _, R, t, tri_in = results[0]
    # Outliers of H are not triangulated: expand back to all N correspondences.
    return R, t, tri_in.expanded(idx, xn_ref.shape[0])


def parallax_deg(R_cur_ref: F64, xn_ref: F64, xn_cur: F64) -> F64:
    """Per-point angle (deg) between the current ray and the rotated reference ray.

    Rotation moves every ray alike and carries no depth information; what is left after removing it is
    the parallax that translation produced, the quantity that makes triangulation possible.
    """
    if xn_ref.shape[0] == 0:
        return np.zeros(0)
    b_ref = homogeneous(xn_ref) @ R_cur_ref.T
    b_cur = homogeneous(xn_cur)
    cos_a = np.einsum("ij,ij->i", b_ref, b_cur) / (np.linalg.norm(b_ref, axis=1) * np.linalg.norm(b_cur, axis=1))
    return np.degrees(np.arccos(np.clip(cos_a, -1.0, 1.0)))


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


def refine_pose_pnp(X_ref: F64, uv_cur: F64, K: F64, R_cur_ref: F64, t_cur_ref: F64,
                    max_reproj_err_px: float) -> tuple[F64, F64, Mask, F64] | None:
    """Motion-only refinement of (R, t) on map points by Levenberg-Marquardt (``cv2.solvePnPRefineLM``).

    Rounds with a shrinking gate (4x, 2x, 1x ``max_reproj_err_px`` around the current estimate) so
    that map points with bad depth do not pull the least-squares solution before they are dropped. Returns
    ``(R_cur_ref, t_cur_ref, inlier mask, 6x6 covariance of (rvec, tvec))`` or None with < 6 inliers.
    The covariance is ``sigma^2 (J^T J)^-1`` with sigma the RMS reprojection error of the inliers.
    """
    if X_ref.shape[0] < 6:
        return None
    rvec, _ = cv2.Rodrigues(R_cur_ref)
    tvec = t_cur_ref.reshape(3, 1).astype(np.float64)
    obj = X_ref.reshape(-1, 1, 3).astype(np.float64)
    img = uv_cur.reshape(-1, 1, 2).astype(np.float64)
    zero_d = np.zeros(5)
    def errors() -> F64:
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, zero_d)
        return np.linalg.norm(proj.reshape(-1, 2) - uv_cur, axis=1)

    for i, gate in enumerate((4.0, 2.0, 1.0)):
        err = errors()
        # The first gate also scales with the median error, so that a coarse start (a degree off)
        # keeps the consistent majority rather than nothing.
        limit = gate * max_reproj_err_px if i else max(gate * max_reproj_err_px, 2.0 * float(np.median(err)))
        keep = err <= limit
        if np.count_nonzero(keep) < 6:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj[keep], img[keep], K, zero_d, rvec, tvec)
    keep = errors() <= max_reproj_err_px
    if np.count_nonzero(keep) < 6:
        return None
    proj, J = cv2.projectPoints(obj[keep], rvec, tvec, K, zero_d)
    J = J[:, :6]
    res = proj.reshape(-1, 2) - uv_cur[keep]
    sigma2 = max(float(np.mean(res**2)), 0.05**2)
    try:
        cov = sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    R, _ = cv2.Rodrigues(rvec)
    return np.asarray(R, dtype=np.float64), tvec.reshape(3), keep, cov


def as_float64(x: Any) -> F64:
    return np.ascontiguousarray(x, dtype=np.float64)
