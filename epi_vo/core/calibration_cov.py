"""The calibration's error in the pose covariance (numpy only).

A CameraInfo is a measurement too: its focal length, principal point and lens model are off by some
amount on a real camera (a factory calibration, a hand calibration, a lens that the model does not fit).
That error is the same in every frame, so it does not average out like image noise: every pose fitted
through it moves the same way, and the error it makes grows coherently along the path. The per-frame
noise the covariance is otherwise built from (KLT forward-backward errors, E's residuals) cannot see it:
the fitted pose absorbs most of a calibration error and leaves small residuals.

Carried as an EKF augmented with the calibration would: the sensitivity ``G`` (6 x 4) of the published
pose (position, rotation, odometry frame) to the four calibration errors of
``geometry.CALIBRATION_TERMS``, chained from keyframe to keyframe as the covariance is (``compose``: the
keyframe's rotation error moves the position through the lever arm), each step's own part from its
two-view geometry (``geometry.calibration_sensitivity``). The published covariance takes
``G diag(sigma^2) G^T``, ``sigma`` the declared calibration uncertainties (``VoConfig``
``focal_length_rel_sigma``, ``principal_point_sigma_px``, ``radial_distortion_k1_sigma``; all 0: the
calibration taken as exact, nothing added).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.geometry import calibration_sensitivity, skew

F64 = NDArray[np.float64]


def _zeros64() -> F64:
    return np.zeros((6, 4))


@dataclass(frozen=True)
class CalibrationError:
    """Sensitivity of the keyframe's and of the current pose to the calibration's errors, and their declared
    standard deviations (``sigmas``, in the units of ``geometry.CALIBRATION_TERMS``). Frozen: each frame
    returns the error after it."""

    sigmas: tuple[float, float, float, float]
    G_kf: F64 = field(default_factory=_zeros64)  # the reference keyframe's pose (odometry frame)
    G_cur: F64 = field(default_factory=_zeros64)  # the last pose's
    kf_index: int = -1  # the keyframe ``G_kf`` belongs to

    @property
    def declared(self) -> bool:
        return any(s > 0.0 for s in self.sigmas)

    def tracked(self, kf_index: int, T_w_kf: F64, R_cur_kf: F64, t_cur_kf: F64, xn_kf: F64 | None,
                xn_cur: F64 | None, fx: float) -> CalibrationError:
        """After a pose ``(R_cur_kf, t_cur_kf)`` relative to keyframe ``kf_index`` (at ``T_w_kf``), fitted to
        the inlier rays ``xn_kf`` / ``xn_cur`` (None: a held position, no two-view geometry of its own).
        A new keyframe is the last pose (it was set at that frame's pose)."""
        if not self.declared:
            return self
        G_kf = self.G_kf if kf_index == self.kf_index else self.G_cur
        R_w_kf = T_w_kf[:3, :3]
        c_kf = -R_cur_kf.T @ t_cur_kf
        J = np.eye(6)
        J[:3, 3:] = -skew(R_w_kf @ c_kf)
        G = J @ G_kf
        scale = float(np.linalg.norm(t_cur_kf))
        if xn_kf is not None and xn_cur is not None and scale > 0.0:
            S = calibration_sensitivity(R_cur_kf, t_cur_kf / scale, xn_kf, xn_cur, scale, fx)
            if S is not None:
                G = G + np.vstack([R_w_kf @ S[:3], R_w_kf @ S[3:]])
        if not np.all(np.isfinite(G)):
            return dataclasses.replace(self, G_kf=G_kf, kf_index=kf_index)
        return dataclasses.replace(self, G_kf=G_kf, G_cur=G, kf_index=kf_index)

    def rescaled(self, factor: float) -> CalibrationError:
        """The path was scaled by ``factor`` (metric scale established): the position rows with it."""
        scale = np.array([factor] * 3 + [1.0] * 3)[:, None]
        return dataclasses.replace(self, G_kf=self.G_kf * scale, G_cur=self.G_cur * scale)

    def cov(self) -> F64:
        """6x6 covariance of the last pose from the calibration's errors."""
        if not self.declared:
            return np.zeros((6, 6))
        G = self.G_cur * np.asarray(self.sigmas, dtype=np.float64)
        return np.asarray(G @ G.T, dtype=np.float64)
