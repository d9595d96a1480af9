"""Covariance of a two-view pose from its own residuals (first order, Hartley & Zisserman sec. 5.2).

An essential matrix fixes the rotation and the direction of travel, five degrees of freedom, and they
are coupled: with a narrow field of view a small rotation about an axis perpendicular to the motion
looks much like a small change of the direction of travel. An isotropic "pixel noise over the number
of points" rotation variance ignores that and is overconfident several times over. Here the five
parameters' covariance is ``sigma^2 (J^T J)^-1`` with ``J`` the Jacobian of the Sampson distances of the
inliers (normalised coordinates, ``sigma`` the pixel noise over fx), and the map's scale is propagated
with its own dependence on the direction (the scale fitted to the map points moves when the
direction does).

Conventions: the camera's pose in the keyframe frame, ``R_kf_cur`` perturbed on the left by ``phi``
(keyframe frame), and its centre ``c = s d`` with ``d`` the unit direction of travel perturbed in the
plane perpendicular to it. The returned 6x6 is over (c, phi), position first, as ``Motion.cov_rel``.
"""

from __future__ import annotations

import math
from typing import cast

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.geometry.common import F64, skew

FD_STEP = 1e-6  # rad: forward differences of the Sampson distances (smooth: exact to ~1e-6 relative)
MAX_POINTS = 80  # rows used for the Jacobians (evenly spread); the information is scaled to all of them


def tangent_basis(d: F64) -> F64:
    """(3, 2) orthonormal basis of the plane perpendicular to the unit vector ``d``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = _cross(d, a)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, _cross(d, b1)])


def _sampson(E: F64, h_kf: F64, h_cur: F64) -> F64:
    """Signed Sampson distances (normalised units) under each E of the stack ``E`` (K, 3, 3): (K, N)."""
    Ex = np.einsum("nj,kij->kni", h_kf, E)
    Etx = np.einsum("ni,kij->knj", h_cur, E)
    num = np.einsum("ni,kni->kn", h_cur, Ex)
    den = np.sqrt(Ex[..., 0] ** 2 + Ex[..., 1] ** 2 + Etx[..., 0] ** 2 + Etx[..., 1] ** 2)
    d: F64 = num / np.maximum(den, 1e-300)
    return d


def _rotation_steps(R: F64, k: int, first: int) -> F64:
    """``k`` copies of ``R`` (3, 3), those at ``first``..``first + 2`` perturbed on the left by FD_STEP
    about x, y and z (exp(phi) = I + [phi]x to ~1e-12 at that step): a stack for forward differences."""
    R_st = np.repeat(R[None], k, axis=0)
    for i in range(3):
        e = np.zeros(3)
        e[i] = FD_STEP
        R_st[first + i] = R + skew(e) @ R
    return R_st


def _subsample(n: int, m: int) -> NDArray[np.int64]:
    """At most ``m`` of ``n`` rows, evenly spread (deterministic)."""
    return np.arange(n) if n <= m else (np.arange(m) * (n - 1) // (m - 1)).astype(np.int64)


def _skew_stack(v: F64) -> F64:
    """[v]x of each row of ``v`` (K, 3): (K, 3, 3)."""
    S = np.zeros((v.shape[0], 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def _cross(u: F64, v: F64) -> F64:
    """Row-wise cross product with broadcasting over leading axes (no ``np.cross`` overhead)."""
    return np.stack([u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1], u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2],
                     u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]], axis=-1)


def _point_scales(R_cur_kf: F64, t: F64, X_kf: F64, b: F64) -> tuple[F64, F64]:
    """Per-point scale of the unit translation(s) ``t`` (3,) or (K, 3) with rotation(s) ``R_cur_kf``
    (3, 3) or (K, 3, 3), and the weights (see ``scale_from_points``): (..., N) each."""
    a = _cross(b, t[..., None, :])
    c = _cross(b, np.einsum("...ij,nj->...ni", R_cur_kf, X_kf))
    a2 = np.einsum("...ni,...ni->...n", a, a)
    return -np.einsum("...ni,...ni->...n", a, c) / np.maximum(a2, 1e-300), a2


def _pose_steps(R_cur_kf: F64, t_dir: F64) -> tuple[F64, F64, F64, F64]:
    """The two-view pose and each of its five parameters (rotation phi, 3; direction beta in the tangent
    basis ``B``, 2) one ``FD_STEP`` forward, as stacks for forward differences: the unit direction of the
    camera centre ``d``, ``B``, ``R_cur_kf`` (6, 3, 3) and ``t_cur_kf`` (6, 3). The step is so small that
    exp(phi) = I + [phi]x holds to ~1e-12."""
    R_kf_cur = R_cur_kf.T
    d = -R_kf_cur @ t_dir
    d /= np.linalg.norm(d)
    B = tangent_basis(d)
    R_kf_st = _rotation_steps(R_kf_cur, 6, 1)
    c_st = np.repeat(d[None], 6, axis=0)
    for j in range(2):
        c_st[4 + j] = d + FD_STEP * B[:, j]
    c_st /= np.linalg.norm(c_st, axis=1, keepdims=True)
    R_st = np.transpose(R_kf_st, (0, 2, 1))
    t_st = -np.einsum("kij,kj->ki", R_st, c_st)
    return d, B, R_st, t_st


def essential_pose_covariance(R_cur_kf: F64, t_dir: F64, xn_kf: F64, xn_cur: F64, sigma_n: float,
                              scale: float, scale_rel_var: float,
                              map_points: tuple[F64, F64] | None = None) -> F64 | None:
    """6x6 covariance over (camera centre, rotation) in the keyframe frame of the pose (R_cur_kf,
    scale * t_dir) estimated from the inlier correspondences ``xn_kf``/``xn_cur`` (N, 2) normalised.

    ``sigma_n`` is the image noise in normalised units (sigma_px / fx), ``scale_rel_var`` the relative
    variance of the scale given the direction. ``map_points`` (optional) are the map points
    ``(X_kf (M, 3), xn_cur (M, 2))`` the scale was fitted to (``scale_from_points``): the derivative of
    their weighted scale carries the direction's error into the scale. None when the five parameters
    are not observable from these points (fewer than six, or a singular normal matrix: no parallax).
    """
    n = xn_kf.shape[0]
    if n < 6 or not scale > 0:
        return None
    d, B, R_st, t_st = _pose_steps(R_cur_kf, t_dir)
    h = FD_STEP
    rows = _subsample(n, MAX_POINTS)
    h_kf = np.column_stack([xn_kf[rows], np.ones(rows.size)])
    h_cur = np.column_stack([xn_cur[rows], np.ones(rows.size)])
    r = _sampson(np.einsum("kij,kjl->kil", _skew_stack(t_st), R_st), h_kf, h_cur)
    J = ((r[1:] - r[0]) / h).T  # (m, 5)
    JtJ = np.einsum("ni,nj->ij", J, J) * (n / rows.size)  # the subsample stands for all n inliers (no BLAS)
    if not np.all(np.isfinite(JtJ)):
        return None
    eig, V = np.linalg.eigh(JtJ)
    if not eig[0] > 1e-12 * eig[-1]:  # a direction the residuals do not constrain: no parallax
        return None
    cov5 = sigma_n**2 * np.einsum("ik,k,jk->ij", V, 1.0 / eig, V)
    ds = np.zeros(5)
    if map_points is not None and map_points[0].shape[0] >= 3:
        # The scale is the weighted mean of the per-point scales near their median: its slope as the
        # rotation and direction move, over the points it kept.
        pick = _subsample(map_points[0].shape[0], MAX_POINTS)
        X_kf, xn_map = map_points[0][pick], map_points[1][pick]
        b = np.column_stack([xn_map, np.ones(xn_map.shape[0])])
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        s_i, w = _point_scales(R_cur_kf, t_dir, X_kf, b)
        med = float(np.median(s_i))
        mad = 1.4826 * float(np.median(np.abs(s_i - med)))
        keep = np.abs(s_i - med) <= max(3.0 * mad, 1e-9 * abs(med))
        if np.count_nonzero(keep) >= 3:
            s_k, _ = _point_scales(R_st, t_st, X_kf[keep], b[keep])
            s_mean = np.einsum("kn,n->k", s_k, w[keep]) / np.sum(w[keep])
            ds = (s_mean[1:] - s_mean[0]) / h
            if not np.all(np.isfinite(ds)):
                ds = np.zeros(5)
    # c = s(phi, beta) * d(beta): Jacobian over (phi, beta, scale noise)
    G = np.zeros((6, 6))
    G[:3, :3] = np.outer(d, ds[:3])
    G[:3, 3:5] = scale * B + np.outer(d, ds[3:])
    G[:3, 5] = d
    G[3:, :3] = np.eye(3)
    S = np.zeros((6, 6))
    S[:5, :5] = cov5
    S[5, 5] = scale_rel_var * scale**2
    cov = G @ S @ G.T
    return 0.5 * (cov + cov.T)


def map_information(R_cur_kf: F64, t_cur_kf: F64, X_kf: F64, xn_cur: F64, sigma_n: float) -> F64 | None:
    """6x6 information (inverse covariance) over (c, phi), as ``essential_pose_covariance``, of the
    pose (R_cur_kf, t_cur_kf) from the reprojections of map points ``X_kf`` (M, 3; keyframe frame) seen
    at ``xn_cur`` (M, 2; normalised) with noise ``sigma_n``; the points are taken as exact, so the
    caller discounts them (their depths carry the previous pair's noise). None with fewer than six
    points in front of the camera."""
    normal = map_normal_equations(R_cur_kf, t_cur_kf, X_kf, xn_cur, sigma_n)
    return None if normal is None else normal[0]


def map_normal_equations(R_cur_kf: F64, t_cur_kf: F64, X_kf: F64, xn_cur: F64, sigma_n: float
                         ) -> tuple[F64, F64] | None:
    """``map_information`` and the gradient ``g = J^T (xn_cur - proj) / sigma_n^2`` of the same
    reprojections at the pose, over (c, phi): ``info^-1 g`` is the Gauss-Newton step that moves the pose
    towards where the map points put it (``(P^-1 + info)^-1 g`` with a prior of covariance ``P``
    there). None as ``map_information``."""
    if X_kf.shape[0] < 6:
        return None
    rows = _subsample(X_kf.shape[0], MAX_POINTS)
    X = X_kf[rows]
    R_kf_cur = R_cur_kf.T
    c = -R_kf_cur @ t_cur_kf
    h = FD_STEP
    R_kf_st = _rotation_steps(R_kf_cur, 7, 4)
    c_st = np.repeat(c[None], 7, axis=0)
    c_st[1:4] += np.eye(3) * h
    Xc = np.einsum("kji,knj->kni", R_kf_st, X[None] - c_st[:, None, :])  # R_cur_kf (X - c) per pose
    seen = xn_cur[rows]
    if not np.all(Xc[0, :, 2] > 0):
        keep = Xc[0, :, 2] > 0
        if np.count_nonzero(keep) < 6:
            return None
        Xc, seen = Xc[:, keep], seen[keep]
    proj = Xc[..., :2] / Xc[..., 2:3]
    J = ((proj[1:] - proj[0]) / h).reshape(6, -1).T  # (2m, 6), rows (point, axis) as reshape(-1) orders them
    weight = (X_kf.shape[0] / rows.size) / sigma_n**2
    info = np.einsum("ni,nj->ij", J, J) * weight
    grad = J.T @ (seen - proj[0]).reshape(-1) * weight
    return (info, grad) if np.all(np.isfinite(info)) and np.all(np.isfinite(grad)) else None


def map_step(R_cur_kf: F64, t_cur_kf: F64, X_kf: F64, xn_cur: F64) -> F64 | None:
    """The Gauss-Newton step (c, phi) from the pose towards where the map points alone put it (``info^-1
    g`` of :func:`map_normal_equations`; independent of the noise's scale); None when there is none."""
    normal = map_normal_equations(R_cur_kf, t_cur_kf, X_kf, xn_cur, 1.0)
    if normal is None:
        return None
    try:
        step = cast(F64, np.linalg.solve(normal[0], normal[1]))
    except np.linalg.LinAlgError:
        return None
    return step if np.all(np.isfinite(step)) else None


def sampson_rms(R_cur_kf: F64, t_dir: F64, xn_kf: F64, xn_cur: F64) -> float | None:
    """RMS of the Sampson distances (normalised units) of the correspondences ``xn_kf``/``xn_cur`` (N, 2)
    under the pose (R_cur_kf, direction ``t_dir``), with E's five degrees of freedom taken out
    (``sum r^2 / (N - 5)``): the image noise the pose's own residuals show, as ``sigma_n`` of
    ``essential_pose_covariance`` means it. None for fewer than six or a non-finite result."""
    n = xn_kf.shape[0]
    if n < 6:
        return None
    E = skew(np.asarray(t_dir, dtype=np.float64)) @ R_cur_kf
    r = _sampson(E[None], np.column_stack([xn_kf, np.ones(n)]), np.column_stack([xn_cur, np.ones(n)]))[0]
    rms = math.sqrt(float(np.sum(r * r)) / (n - 5))
    return rms if math.isfinite(rms) else None


def reprojection_rms(R_cur_kf: F64, t_cur_kf: F64, X_kf: F64, xn_cur: F64) -> float | None:
    """RMS per axis of the reprojection residuals (normalised units) of the map points ``X_kf`` (M, 3;
    keyframe frame) in front of the camera at (R_cur_kf, t_cur_kf), seen at ``xn_cur`` (M, 2); None
    when no point is in front."""
    Xc = X_kf @ R_cur_kf.T + t_cur_kf
    front = Xc[:, 2] > 0
    if not np.any(front):
        return None
    res = Xc[front, :2] / Xc[front, 2:3] - xn_cur[front]
    rms = math.sqrt(float(np.mean(res**2)))
    return rms if math.isfinite(rms) else None


def fuse(cov: F64, info: F64) -> F64 | None:
    """Covariance of two independent estimates of the same quantity: ``(cov^-1 + info)^-1``; None when
    the sum is not invertible."""
    try:
        fused = np.linalg.inv(np.linalg.inv(cov) + info)
    except np.linalg.LinAlgError:
        return None
    fused = 0.5 * (fused + fused.T)
    return fused if np.all(np.isfinite(fused)) and np.all(np.diag(fused) > 0) else None


# Calibration errors a CameraInfo may carry, in the order of ``calibration_sensitivity``'s columns: the focal
# length (relative), the principal point's x and y (px) and an undeclared radial distortion k1 (normalised).
CALIBRATION_TERMS = ("focal_rel", "cx_px", "cy_px", "k1")


def calibration_sensitivity(R_cur_kf: F64, t_dir: F64, xn_kf: F64, xn_cur: F64, scale: float, fx: float
                            ) -> F64 | None:
    """(6, 4) first-order change of the two-view pose (camera centre, rotation; conventions as
    ``essential_pose_covariance``) per unit error of the calibration (``CALIBRATION_TERMS``).

    The rays the pose is fitted to are the pixels through the calibration: with the true focal length
    ``fx (1 + e)``, principal point off by ``(dx, dy)`` px and an undeclared radial ``k1``, the true
    normalised point of ``x`` is ``x (1 - e - k1 |x|^2) - (dx, dy) / fx`` to first order, the same error in
    both views. The pose minimising the Sampson distances moves by ``-(J^T J)^-1 J^T J_c`` (implicit
    function theorem; ``J`` over the pose's five parameters, ``J_c`` over the calibration's), which is
    large exactly where rotation and direction of travel are coupled (a narrow view, a plane). The
    scale is held (a calibration error does not change the map's units). None when the five parameters
    are not observable from these points (as ``essential_pose_covariance``)."""
    n = xn_kf.shape[0]
    if n < 6 or not scale > 0 or not fx > 0:
        return None
    _, B, R_st, t_st = _pose_steps(R_cur_kf, t_dir)
    h = FD_STEP
    E_st = np.einsum("kij,kjl->kil", _skew_stack(t_st), R_st)
    rows = _subsample(n, MAX_POINTS)
    x_kf, x_cur = xn_kf[rows], xn_cur[rows]
    one = np.ones(rows.size)
    r = _sampson(E_st, np.column_stack([x_kf, one]), np.column_stack([x_cur, one]))
    J = ((r[1:] - r[0]) / h).T  # (m, 5)
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)):
        return None
    eig, V = np.linalg.eigh(JtJ)
    if not eig[0] > 1e-12 * eig[-1]:
        return None

    # The rays moved by a small step of each calibration error (rows: error k's copy of the m points), both
    # views alike, and their Sampson distances under the estimate: the derivatives J_c in one evaluation.
    pp = np.zeros((4, 1, 2))
    pp[1, 0, 0] = pp[2, 0, 1] = -1.0 / fx

    def moved(x: F64) -> F64:
        dx = np.stack([-x, np.broadcast_to(pp[1], x.shape), np.broadcast_to(pp[2], x.shape),
                       -x * np.sum(x * x, axis=1, keepdims=True)])
        return np.column_stack([(x[None] + h * dx).reshape(-1, 2), np.ones(4 * x.shape[0])])

    rc = _sampson(E_st[:1], moved(x_kf), moved(x_cur))[0].reshape(4, -1)
    Jc = ((rc - r[0]) / h).T  # (m, 4)
    dtheta = -np.einsum("ik,k,jk->ij", V, 1.0 / eig, V) @ (J.T @ Jc)  # (5, 4): phi (3), beta (2)
    S = np.vstack([scale * B @ dtheta[3:5], dtheta[:3]])
    return S if np.all(np.isfinite(S)) else None
