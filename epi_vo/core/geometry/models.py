"""E and H estimation and their ORB-SLAM style chi-square scoring (Mur-Artal et al. 2015, sec. IV).

E comes from the five-point solver (Nister 2004) inside a robust estimator, H from
``cv2.findHomography``; numerical failure (too few points, a degenerate sample) is a ``None`` model,
never an exception. Conventions: see ``epi_vo.core.geometry.common``.
"""

from __future__ import annotations

import cv2
import numpy as np

from epi_vo.core.geometry.common import F64, Mask, homogeneous, skew

# Chi-square 95 % quantiles (ORB-SLAM): 1 DoF for a point-to-line distance, 2 DoF for a
# point-to-point distance. E is scored with the 2-DoF constant so that both models' scores share
# one scale, exactly as ORB-SLAM's CheckFundamental does.
CHI2_1DOF = 3.841
CHI2_2DOF = 5.991

ROBUST_METHOD_FLAGS = {
    "magsac": cv2.USAC_MAGSAC,
    "ransac": cv2.RANSAC,
    "lmeds": cv2.LMEDS,
    "usac_default": cv2.USAC_DEFAULT,
    "usac_accurate": cv2.USAC_ACCURATE,
    "usac_fast": cv2.USAC_FAST,
}


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


def score_static(uv_ref: F64, uv_cur: F64, sigma_px: float) -> tuple[float, Mask]:
    """``score_homography`` of H = identity ("the camera did not move"), without the general transfer: both
    directions' error is the displacement itself (the same numbers, ~0.2 ms less per frame)."""
    d2 = np.sum((uv_ref - uv_cur) ** 2, axis=1)
    return _chi2_score(d2, d2, sigma_px, CHI2_2DOF)


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


