"""How well a homography's decompositions fix the plane's normal: H's covariance from its inlier
correspondences at the image noise they show (H&Z 5.2.3, first-order propagation of the transfer error with
both images' noise), and each decomposition's normal propagated from it (numeric Jacobian of the
decomposition, Faugeras / Malis).

The normal of a plane seen over a short baseline is poorly fixed: it is the part of H that the translation
over the plane's distance makes, a few thousandths of H at the start of a floor drive. Whether a later view's
normal is the same plane's is a question of this uncertainty, not of a fixed angle.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.geometry.common import F64
from epi_vo.core.geometry.uncertainty import tangent_basis

# Relative step of the numeric Jacobian of the decomposition in H's entries (H[2, 2] = 1): well above the
# float noise of the SVD inside the decomposition, well below the entries' precision at any image noise.
NORMAL_JACOBIAN_STEP = 1e-7


def homography_covariance(H_n: F64, xn_ref: F64, xn_cur: F64) -> tuple[F64, float] | None:
    """Covariance (8, 8) of the entries of ``H_n`` (normalised coordinates, ``H_n[2, 2] = 1``; row-major, the
    last entry held) fitted to the correspondences ``xn_ref`` -> ``xn_cur`` (N, 2, normalised), at the image
    noise their transfer residuals show (a posteriori, both images' noise alike), and that noise (normalised
    units, per axis). None for fewer than five correspondences or a singular information matrix (the points
    on a line)."""
    n = xn_ref.shape[0]
    if n < 5:
        return None
    H = H_n / H_n[2, 2]
    x = np.column_stack([xn_ref, np.ones(n)])
    p = x @ H.T
    c = p[:, 2]
    if np.any(np.abs(c) < 1e-12):
        return None
    u, v = p[:, 0] / c, p[:, 1] / c
    r = xn_cur - np.column_stack([u, v])
    # d(u, v)/d(entries): rows of H act on x; the last entry is held (H's scale).
    J = np.zeros((n, 2, 9))
    J[:, 0, 0:3] = x / c[:, None]
    J[:, 0, 6:9] = -(u / c)[:, None] * x
    J[:, 1, 3:6] = x / c[:, None]
    J[:, 1, 6:9] = -(v / c)[:, None] * x
    J = J[:, :, :8]
    # The transfer's residual carries the reference image's noise through H's local Jacobian too.
    A = np.empty((n, 2, 2))
    A[:, 0, :] = (H[0, :2][None, :] - u[:, None] * H[2, :2][None, :]) / c[:, None]
    A[:, 1, :] = (H[1, :2][None, :] - v[:, None] * H[2, :2][None, :]) / c[:, None]
    S = np.eye(2)[None] + A @ np.transpose(A, (0, 2, 1))
    W = np.linalg.inv(S)
    chi2 = float(np.einsum("ni,nij,nj->", r, W, r))
    dof = 2 * n - 8
    if dof <= 0:
        return None
    sigma_sq = chi2 / dof
    info = np.einsum("nki,nkl,nlj->ij", J, W, J)
    try:
        cov = np.linalg.inv(info) * sigma_sq
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return cov, float(np.sqrt(sigma_sq))


def _normal_near(H_n: F64, normal: F64) -> F64 | None:
    """The unit normal of the decomposition of ``H_n`` (normalised coordinates) nearest ``normal``, its sign
    aligned with it."""
    _, _, _, ns = cv2.decomposeHomographyMat(H_n, np.eye(3))
    best, best_dot = None, -1.0
    for n_any in ns:
        n = np.asarray(n_any, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm == 0.0:
            continue
        n = n / norm
        d = float(n @ normal)
        if abs(d) > best_dot:
            best, best_dot = (n if d >= 0 else -n), abs(d)
    return best


def normal_covariance(H_n: F64, cov_h: F64, normal: F64) -> F64 | None:
    """Covariance (3, 3, rank 2: in the plane perpendicular to ``normal``) of the decomposition of ``H_n``
    whose unit normal is ``normal`` (the reference camera's frame), propagated from H's entries' covariance
    ``cov_h`` (``homography_covariance``). None when the decomposition does not follow H smoothly there."""
    H = H_n / H_n[2, 2]
    B = tangent_basis(normal)
    J = np.empty((2, 8))
    flat = H.reshape(9)
    for k in range(8):
        step = NORMAL_JACOBIAN_STEP * max(1.0, abs(float(flat[k])))
        hp, hm = flat.copy(), flat.copy()
        hp[k] += step
        hm[k] -= step
        n_p, n_m = _normal_near(hp.reshape(3, 3), normal), _normal_near(hm.reshape(3, 3), normal)
        if n_p is None or n_m is None:
            return None
        J[:, k] = B.T @ (n_p - n_m) / (2.0 * step)
    C2 = J @ cov_h @ J.T
    if not np.all(np.isfinite(C2)):
        return None
    out: NDArray[np.float64] = B @ C2 @ B.T
    return out


def normal_sigma_deg(H_n: F64, xn_ref: F64, xn_cur: F64, normals: list[F64]) -> float | None:
    """The largest standard deviation (deg, along its worst axis) of any of the decompositions' unit
    ``normals`` of ``H_n`` fitted to ``xn_ref`` -> ``xn_cur`` (normalised), at the noise their residuals show.
    None when H's covariance or a normal's cannot be had."""
    fit = homography_covariance(H_n, xn_ref, xn_cur)
    if fit is None:
        return None
    worst = 0.0
    for n in normals:
        C = normal_covariance(H_n, fit[0], n)
        if C is None:
            return None
        worst = max(worst, float(np.linalg.eigvalsh(C)[-1]))
    return float(np.degrees(np.sqrt(worst)))
