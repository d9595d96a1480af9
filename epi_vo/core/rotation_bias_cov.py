"""The rotation error the keyframe steps share, as the map measures it, in the pose covariance (numpy only).

The keyframe chain composes each step's covariance as if every step's error were new (a random walk). On a
narrow or forward view the essential matrix's fit is biased along its rotation / direction-of-travel valley
(part of a turn read as a sideways direction of travel), the same way in every step of a steady motion: the
steps' rotation errors point the same way and their sum outgrows the random walk, while each step's own
residuals cannot see the bias (the fitted pose absorbs it).

The map measures it on every frame E's pose is taken with a map: the map's points, at depths triangulated
before, put the pose where their reprojections say (one Gauss-Newton step from E's pose, ``map_step``), and
with known depths a rotation and a sideways translation are no longer alike. Their rotation's disagreement
``d`` with E's has two parts: the two estimates' noise (covariance ``C``: E's own and the map fit's) and what
is systematic. Only the part beyond the noise is taken: ``d`` shrunk so that its squared Mahalanobis length is
``d^T C^-1 d - 3`` (the unbiased estimate of the systematic part's, a 3-dof noise adding 3 on average), none
when it is below.

Carried as ``calibration_cov`` carries the calibration's error (one shared unknown ``z`` of unit variance per
path): each step's rotation error has a part ``b z``, ``b`` the step's measured excess (signed, in the
odometry frame), chained from keyframe to keyframe with the lever arm (the keyframe's rotation error moves the
later positions); the published covariance takes ``g g^T``. Signed, so the measurement decides the
coherence too: excesses that point the same way step after step add up linearly, while steps whose excesses
change sign at random add up as a random walk of what is left above the noise.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.geometry import map_normal_equations, skew

F64 = NDArray[np.float64]

# A 3-dof noise adds this much to the squared Mahalanobis length of a disagreement on average: only what is
# beyond it is systematic.
NOISE_DOF = 3.0


def _zeros6() -> F64:
    return np.zeros(6)


def map_rotation_excess(R_cur_kf: F64, t_cur_kf: F64, X_kf: F64, xn_cur: F64, sigma_n: float,
                        cov_rot_e: F64) -> F64 | None:
    """The systematic part of the disagreement between E's rotation ``R_cur_kf`` (of the pose
    ``(R_cur_kf, t_cur_kf)``, its rotation covariance ``cov_rot_e`` in the keyframe frame) and the rotation the
    map points ``X_kf`` (keyframe frame) seen at ``xn_cur`` (normalised) put it at, their reprojections at noise
    ``sigma_n`` (normalised units): a 3-vector in the keyframe frame (zero when the disagreement is within the
    two estimates' noise); None when the map gives no pose."""
    normal = map_normal_equations(R_cur_kf, t_cur_kf, X_kf, xn_cur, sigma_n)
    if normal is None:
        return None
    info, grad = normal
    try:
        cov_map = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    d = cov_map[3:] @ grad  # the Gauss-Newton step's rotation: where the map's points put it
    C = cov_map[3:, 3:] + cov_rot_e
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(C))):
        return None
    try:
        m2 = float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        return None
    if not (math.isfinite(m2) and m2 > NOISE_DOF):
        return np.zeros(3)
    return np.asarray(d * math.sqrt(1.0 - NOISE_DOF / m2), dtype=np.float64)


@dataclass(frozen=True)
class RotationBias:
    """Sensitivity ``g`` (position, rotation; odometry frame) of the keyframe's and of the current pose to the
    rotation error the keyframe steps share, as the map measured it (``on``: False adds nothing). Frozen: each
    frame returns the one after it."""

    on: bool
    g_kf: F64 = field(default_factory=_zeros6)  # the reference keyframe's pose
    g_cur: F64 = field(default_factory=_zeros6)  # the last pose's
    kf_index: int = -1  # the keyframe ``g_kf`` belongs to

    def tracked(self, kf_index: int, T_w_kf: F64, R_cur_kf: F64, t_cur_kf: F64, excess: F64 | None) -> RotationBias:
        """After a pose ``(R_cur_kf, t_cur_kf)`` relative to keyframe ``kf_index`` (at ``T_w_kf``) whose rotation
        the map measured ``excess`` off (keyframe frame; None: not measured, nothing of its own). A new keyframe
        is the last pose (it was set at that frame's pose)."""
        if not self.on:
            return self
        g_kf = self.g_kf if kf_index == self.kf_index else self.g_cur
        R_w_kf = T_w_kf[:3, :3]
        J = np.eye(6)
        J[:3, 3:] = -skew(R_w_kf @ (-R_cur_kf.T @ t_cur_kf))
        g = J @ g_kf
        if excess is not None:
            g[3:] += R_w_kf @ excess
        if not np.all(np.isfinite(g)):
            return dataclasses.replace(self, g_kf=g_kf, kf_index=kf_index)
        return dataclasses.replace(self, g_kf=g_kf, g_cur=g, kf_index=kf_index)

    def rescaled(self, factor: float) -> RotationBias:
        """The path was scaled by ``factor`` (metric scale established): the position rows with it."""
        scale = np.array([factor] * 3 + [1.0] * 3)
        return dataclasses.replace(self, g_kf=self.g_kf * scale, g_cur=self.g_cur * scale)

    def cov(self) -> F64:
        """6x6 covariance of the last pose from the rotation error the steps share."""
        if not self.on:
            return np.zeros((6, 6))
        return np.asarray(np.outer(self.g_cur, self.g_cur), dtype=np.float64)
