"""E and H estimation and their ORB-SLAM style chi-square scoring (Mur-Artal et al. 2015, sec. IV).

E comes from the five-point solver (Nister 2004) inside a robust estimator, H from
``cv2.findHomography``; numerical failure (too few points, a degenerate sample) is a ``None`` model,
never an exception. Conventions: see ``epi_vo.core.geometry.common``.
"""

from __future__ import annotations

import math
from typing import cast

import cv2
import numpy as np

from epi_vo.core.geometry.common import F64, Mask, homogeneous, skew
from epi_vo.core.geometry.epipolar_refine import refine_relative_pose
from epi_vo.core.geometry.least_squares import Linearised, levenberg_marquardt

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
    d: F64 = num / np.maximum(den, 1e-300)
    return d


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
        H_inv = cast(F64, np.linalg.inv(H))
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


# Whether OpenCV's USAC estimators refit their winning model themselves: the final polisher
# (``UsacParams.final_polisher``, least squares on the inliers, 3 iterations) came with OpenCV 4.8. Without it
# (OpenCV 4.6, Ubuntu 24.04's, the one a ROS 2 Jazzy robot imports) the returned model is the best minimal
# or locally optimised one of the search, several times further from the truth: the package refits it
# (``polish_essential``, ``polish_homography``). docs/library_versions.md has the measurements.
USAC_POLISHES = hasattr(cv2, "UsacParams") and hasattr(cv2.UsacParams(), "final_polisher")
USAC_METHODS = frozenset({"magsac", "usac_default", "usac_accurate", "usac_fast"})

# Gate-and-refit rounds of ``polish_essential`` and ``polish_homography``: a refit that changes the inlier
# set is followed by one on the new set, up to three fits, as OpenCV's own final polisher iterates
# (``UsacParams.final_polisher_iterations``).
POLISH_ROUNDS = 3


def polished_by_opencv(method: str) -> bool:
    """Whether ``cv2.findEssentialMat`` / ``cv2.findHomography`` with ``method`` refit their model on its
    inliers themselves on this OpenCV: the USAC methods from OpenCV 4.8 on (``USAC_POLISHES``). The
    classic RANSAC and LMEDS return the best sample's model on every release, and are left as they are."""
    return method not in USAC_METHODS or USAC_POLISHES


def estimate_essential(uv_ref: F64, uv_cur: F64, K: F64, method: str = "magsac", threshold_px: float = 1.0,
                       confidence: float = 0.999, max_iters: int = 1000) -> tuple[F64 | None, Mask]:
    """Five-point E inside a robust estimator (USAC MAGSAC by default) on undistorted pixels.

    Returns ``(E, inlier_mask)``; ``E`` is None when fewer than 5 points or no model was found. When
    the estimator returns several stacked solutions (RANSAC/LMEDS may), the first is used. A USAC model
    that this OpenCV did not refit on its inliers (``polished_by_opencv``) is refitted here
    (``polish_essential``), and the mask is then the points within ``threshold_px`` of it.
    """
    n = uv_ref.shape[0]
    if n < 5:
        return None, np.zeros(n, dtype=bool)
    flag = ROBUST_METHOD_FLAGS[method]
    try:
        E_found, mask = cv2.findEssentialMat(uv_ref, uv_cur, K, method=flag, prob=confidence,
                                             threshold=threshold_px, maxIters=max_iters)
    except cv2.error:
        return None, np.zeros(n, dtype=bool)
    if E_found is None or E_found.shape[0] < 3 or E_found.shape[1] != 3 or mask is None:
        return None, np.zeros(n, dtype=bool)
    E: F64 = np.asarray(E_found[:3, :3], dtype=np.float64)
    if not np.all(np.isfinite(E)):
        return None, np.zeros(n, dtype=bool)
    if not polished_by_opencv(method):
        return polish_essential(E, uv_ref, uv_cur, K, threshold_px)
    return E, np.asarray(mask).reshape(-1).astype(np.bool_)


def polish_essential(E: F64, uv_ref: F64, uv_cur: F64, K: F64, threshold_px: float,
                     rounds: int = POLISH_ROUNDS) -> tuple[F64, Mask]:
    """E refitted on its consensus: the correspondences within ``threshold_px`` of it (Sampson distance,
    undistorted pixels) fitted by least squares on their Sampson distances (``refine_relative_pose``, five
    degrees of freedom, starting at E so that it stays in E's basin), gated again under the result and
    refitted while that set changes (at most ``rounds`` fits). Returns ``(E, mask of the correspondences
    within threshold_px of it)``; E unchanged when fewer than six correspondences support it.

    What OpenCV 4.8+ does after a USAC search (its final polisher), done in numpy so that an OpenCV without
    it (4.6) gives an E as good: on a synthetic scene at 0.1 px of noise, E's rotation error 6.7 mdeg
    unrefitted on 4.6, 2.2 refitted, 2.2 from OpenCV 5's own polisher. Any decomposition of E serves as
    the start: the four candidates of ``cv2.decomposeEssentialMat`` give the same E up to sign, and the
    Sampson distance does not see the sign.
    """
    gate_sq = threshold_px * threshold_px
    inliers = sampson_distance_sq(fundamental_from_essential(E, K), uv_ref, uv_cur) <= gate_sq
    R_any, _, t_any = cv2.decomposeEssentialMat(E)
    R: F64 = np.asarray(R_any, dtype=np.float64)
    t: F64 = np.asarray(t_any, dtype=np.float64).reshape(3)
    K_inv = np.linalg.inv(K)
    xn_ref = (homogeneous(uv_ref) @ K_inv.T)[:, :2]
    xn_cur = (homogeneous(uv_cur) @ K_inv.T)[:, :2]
    for _ in range(rounds):
        fitted = refine_relative_pose(R, t, xn_ref[inliers], xn_cur[inliers])
        if fitted is None:
            break
        R, t = fitted[0], fitted[1]
        E = essential_from_pose(R, t)
        again = sampson_distance_sq(fundamental_from_essential(E, K), uv_ref, uv_cur) <= gate_sq
        settled = np.array_equal(again, inliers)
        inliers = again
        if settled:
            break
    return E, inliers


def estimate_homography(uv_ref: F64, uv_cur: F64, method: str = "usac_fast", threshold_px: float = 1.0,
                        confidence: float = 0.999, max_iters: int = 1000) -> tuple[F64 | None, Mask]:
    """H (ref -> cur) by cv2.findHomography on undistorted pixels; None when it fails. A USAC model that
    this OpenCV did not refit (``polished_by_opencv``) is refitted here (``polish_homography``; the mask is
    then the points within ``threshold_px`` of it, transfer error into the current image).

    Plain RANSAC runs to its iteration cap on non-planar scenes (low inlier ratio), ~20 ms for 300
    points; the USAC variants stop early and are the default.
    """
    n = uv_ref.shape[0]
    if n < 4:
        return None, np.zeros(n, dtype=bool)
    try:
        H_found, mask = cv2.findHomography(uv_ref, uv_cur, ROBUST_METHOD_FLAGS[method], threshold_px,
                                           maxIters=max_iters, confidence=confidence)
    except cv2.error:
        return None, np.zeros(n, dtype=bool)
    if H_found is None or mask is None or not np.all(np.isfinite(H_found)) or abs(np.linalg.det(H_found)) < 1e-12:
        return None, np.zeros(n, dtype=bool)
    H: F64 = np.asarray(H_found, dtype=np.float64)
    if not polished_by_opencv(method):
        return polish_homography(H, uv_ref, uv_cur, threshold_px)
    return H, np.asarray(mask).reshape(-1).astype(np.bool_)


def polish_homography(H: F64, uv_ref: F64, uv_cur: F64, threshold_px: float,
                      rounds: int = POLISH_ROUNDS) -> tuple[F64, Mask]:
    """H refitted on its own consensus, as ``polish_essential`` refits E: least squares on the transfer
    errors into the current image (the error OpenCV's estimators gate and refine) of the correspondences
    within ``threshold_px`` of H, gated again under the result and refitted while that set changes (at
    most ``rounds`` fits). Returns ``(H normalised to H[2, 2] = 1, mask of the correspondences within
    threshold_px of it)``; H unchanged when fewer than eight correspondences support it or the fit fails.

    What OpenCV 4.8+ does after a USAC search, for an OpenCV without it: a pure rotation's attitude comes
    straight from H (bags/pure_rotation: 0.0089 deg per frame of rotation error on OpenCV 4.6 unrefitted,
    0.0064 on OpenCV 5).
    """
    gate_sq = threshold_px * threshold_px
    H = H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H
    inliers = _forward_errors_sq(H, uv_ref, uv_cur) <= gate_sq
    for _ in range(rounds):
        if np.count_nonzero(inliers) < 8:
            break
        fitted = _refine_homography(H, uv_ref[inliers], uv_cur[inliers])
        if fitted is None:
            break
        H = fitted
        again = _forward_errors_sq(H, uv_ref, uv_cur) <= gate_sq
        settled = np.array_equal(again, inliers)
        inliers = again
        if settled:
            break
    return H, inliers


def _forward_errors_sq(H: F64, uv_ref: F64, uv_cur: F64) -> F64:
    """Squared distances (px^2) of ``H uv_ref`` from ``uv_cur``; +inf where H maps to infinity."""
    return transfer_errors_sq(H, uv_ref, uv_cur)[0]


def _normalizer(uv: F64) -> F64:
    """Similarity moving the points' centroid to the origin and their mean distance to sqrt(2) (H&Z 4.4.4)."""
    c = uv.mean(axis=0)
    d = float(np.mean(np.linalg.norm(uv - c, axis=1)))
    s = math.sqrt(2.0) / d if d > 1e-12 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _refine_homography(H: F64, uv_ref: F64, uv_cur: F64, iterations: int = 15) -> F64 | None:
    """Levenberg-Marquardt on the transfer errors ``|H uv_ref - uv_cur|^2`` over the eight entries
    of H with ``H[2, 2]`` held, in normalized coordinates (``_normalizer``); None for a non-finite or
    degenerate result."""
    T_ref, T_cur = _normalizer(uv_ref), _normalizer(uv_cur)
    Hn = T_cur @ H @ np.linalg.inv(T_ref)
    if not abs(Hn[2, 2]) > 1e-12:
        return None
    Hn = Hn / Hn[2, 2]
    x = homogeneous(uv_ref) @ T_ref.T
    y = (homogeneous(uv_cur) @ T_cur.T)[:, :2]

    n = x.shape[0]

    def projected(M: F64) -> tuple[F64, F64]:
        p = x @ M.T
        return p[:, :2] / p[:, 2:3], p[:, 2]

    def residuals(M: F64) -> F64:
        r: F64 = (projected(M)[0] - y).ravel()
        return r

    def linearise(M: F64) -> Linearised[F64]:
        uv, w = projected(M)
        J = np.zeros((n, 2, 8))
        xs = x / w[:, None]
        J[:, 0, 0:3] = xs
        J[:, 1, 3:6] = xs
        J[:, 0, 6:8] = -uv[:, 0:1] * xs[:, :2]
        J[:, 1, 6:8] = -uv[:, 1:2] * xs[:, :2]
        return Linearised((uv - y).ravel(), J.reshape(2 * n, 8), lambda step: M + np.append(step, 0.0).reshape(3, 3))

    Hn = levenberg_marquardt(Hn, linearise, residuals, iterations)[0]
    H_out = np.linalg.inv(T_cur) @ Hn @ T_ref
    if not (np.all(np.isfinite(H_out)) and abs(np.linalg.det(H_out)) > 1e-12 and abs(H_out[2, 2]) > 1e-12):
        return None
    H_norm: F64 = H_out / H_out[2, 2]
    return H_norm


