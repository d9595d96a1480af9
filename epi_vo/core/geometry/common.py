"""Shared two-view helpers: homogeneous coordinates, the cross-product matrix, depths along rays,
the nearest rotation, float64 coercion.

Conventions of every module of ``epi_vo.core.geometry``:
Conventions (used by every function here):
- ``uv_ref``, ``uv_cur``: (N, 2) undistorted pixel coordinates (ideal pinhole camera with intrinsics K)
  of the same N points in the reference (keyframe) and current images; ``xn_*`` the normalized ones.
- ``R_cur_ref``, ``t_cur_ref``: the rigid motion mapping reference-camera coordinates into the
  current camera, ``X_cur = R_cur_ref @ X_ref + t_cur_ref`` (what ``cv2.recoverPose(E, uv_ref, uv_cur)``
  returns). ``t`` from an essential matrix is a unit direction: monocular scale is not observable.
- ``E`` satisfies ``xn_cur^T E xn_ref = 0``; ``F = K^-T E K^-1``; ``H`` maps ``uv_ref`` to ``uv_cur``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]


def homogeneous(x: F64) -> F64:
    """(N, 2) -> (N, 3) by appending ones."""
    return np.hstack([x, np.ones((x.shape[0], 1))])


def skew(t: F64) -> F64:
    """[t]_x, the cross-product matrix of a 3-vector (H&Z A4.5)."""
    tx, ty, tz = np.asarray(t, dtype=np.float64).reshape(3)
    return np.array([[0.0, -tz, ty], [tz, 0.0, -tx], [-ty, tx, 0.0]])


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
    R: F64 = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R


def as_float64(x: Any) -> F64:
    return np.ascontiguousarray(x, dtype=np.float64)


def reprojection_errors(R_cur_kf: F64, t_cur_kf: F64, X_kf: F64, uv: F64, K: F64) -> F64:
    """Pixel distances of the map points ``X_kf`` under the pose from where they are seen (``uv``);
    infinite behind the camera (so no distance gate counts them)."""
    Xc = np.einsum("ij,nj->ni", R_cur_kf, X_kf) + t_cur_kf
    with np.errstate(divide="ignore", invalid="ignore"):
        uv_p = np.einsum("ij,nj->ni", K[:2, :2], Xc[:, :2] / Xc[:, 2:3]) + K[:2, 2]
    return np.where(Xc[:, 2] > 0, np.linalg.norm(uv_p - uv, axis=1), np.inf)
