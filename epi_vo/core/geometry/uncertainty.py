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

from collections.abc import Callable

import numpy as np

from epi_vo.core.geometry.common import F64, skew

FD_STEP = 1e-6  # rad: central differences of the Sampson distances (smooth: exact to ~1e-9)


def _exp(phi: F64) -> F64:
    angle = float(np.linalg.norm(phi))
    K = skew(phi)
    if angle < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(angle) / angle * K + (1.0 - np.cos(angle)) / angle**2 * (K @ K)


def tangent_basis(d: F64) -> F64:
    """(3, 2) orthonormal basis of the plane perpendicular to the unit vector ``d``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(d, a)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(d, b1)])


def _pose(R_kf_cur: F64, d: F64, B: F64, x: F64) -> tuple[F64, F64]:
    """(R_cur_kf, unit t_cur_kf) for the 5-vector perturbation x = (phi, beta)."""
    R = _exp(x[:3]) @ R_kf_cur
    c = d + B @ x[3:]
    c /= np.linalg.norm(c)
    R_cur_kf = R.T
    return R_cur_kf, -R_cur_kf @ c


def _sampson(R_cur_kf: F64, t: F64, xn_kf: F64, xn_cur: F64) -> F64:
    """Signed Sampson distances (normalised units) of the correspondences under E = [t]x R."""
    E = skew(t) @ R_cur_kf
    h_kf = np.column_stack([xn_kf, np.ones(xn_kf.shape[0])])
    h_cur = np.column_stack([xn_cur, np.ones(xn_cur.shape[0])])
    Ex = h_kf @ E.T
    Etx = h_cur @ E
    num = np.einsum("ij,ij->i", h_cur, Ex)
    den = np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2)
    return num / np.maximum(den, 1e-300)


def essential_pose_covariance(R_cur_kf: F64, t_dir: F64, xn_kf: F64, xn_cur: F64, sigma_n: float,
                              scale: float, scale_rel_var: float,
                              scale_of: Callable[[F64, F64], float | None] | None = None) -> F64 | None:
    """6x6 covariance over (camera centre, rotation) in the keyframe frame of the pose (R_cur_kf,
    scale * t_dir) estimated from the inlier correspondences ``xn_kf``/``xn_cur`` (N, 2) normalised.

    ``sigma_n`` is the image noise in normalised units (sigma_px / fx), ``scale_rel_var`` the relative
    variance of the scale given the direction, and ``scale_of(R_cur_kf, t_dir)`` (optional) the map's
    scale for another rotation and direction: its derivative carries the direction's error into the
    scale. None when the five parameters are not observable from these points (fewer than six, or a
    singular normal matrix: no parallax).
    """
    n = xn_kf.shape[0]
    if n < 6 or not scale > 0:
        return None
    R_kf_cur = R_cur_kf.T
    d = -R_kf_cur @ t_dir
    d /= np.linalg.norm(d)
    B = tangent_basis(d)
    J = np.zeros((n, 5))
    ds = np.zeros(5)
    for i in range(5):
        x = np.zeros(5)
        x[i] = FD_STEP
        Rp, tp = _pose(R_kf_cur, d, B, x)
        Rm, tm = _pose(R_kf_cur, d, B, -x)
        J[:, i] = (_sampson(Rp, tp, xn_kf, xn_cur) - _sampson(Rm, tm, xn_kf, xn_cur)) / (2 * FD_STEP)
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)) or np.linalg.cond(JtJ) > 1e12:
        return None
    cov5 = sigma_n**2 * np.linalg.inv(JtJ)
    if scale_of is not None:
        # The map's scale as the direction moves: one sigma of each parameter, both ways (the scale is a
        # median, piecewise constant: a slope over a sigma, not an infinitesimal one).
        step = np.sqrt(np.maximum(np.diag(cov5), 1e-18))
        for i in range(5):
            x = np.zeros(5)
            x[i] = step[i]
            sp = scale_of(*_pose(R_kf_cur, d, B, x))
            sm = scale_of(*_pose(R_kf_cur, d, B, -x))
            if sp is not None and sm is not None and np.isfinite(sp) and np.isfinite(sm):
                ds[i] = (sp - sm) / (2 * step[i])
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
