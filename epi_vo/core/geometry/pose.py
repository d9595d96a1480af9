"""Pose recovery with cheirality: the pose of an essential matrix (recoverPose), rotation and planar
pose of a homography, parallax after removing a rotation, and the motion-only refinement of a pose on
map points (H&Z ch. 9, 18). Conventions: see ``epi_vo.core.geometry.common``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.geometry.common import F64, Mask, homogeneous, nearest_rotation, ray_depths
from epi_vo.core.geometry.epipolar_refine import refine_relative_pose
from epi_vo.core.geometry.models import essential_from_pose, fundamental_from_essential, sampson_distance_sq
from epi_vo.core.geometry.triangulation import Triangulation, triangulate
from epi_vo.core.transforms import rotation_angle_deg

# Distance (in baselines) beyond which a point votes for no decomposition of E: only points whose rays are
# parallel to numerical precision (at infinity) lie there. recoverPose's own cut (50 baselines) is lifted: at
# video rates the baseline is short and real points lie thousands of baselines away.
_CHEIRALITY_MAX_DISTANCE = 1.0e7


def recover_pose(E: F64, uv_ref: F64, uv_cur: F64, K: F64, inliers: Mask, max_points: int = 100
                 ) -> tuple[F64, F64, Mask]:
    """Decompose E and pick the candidate with most points in front of both cameras (cheirality).

    The motion ref -> cur, as ``cv2.recoverPose(E, uv_ref, uv_cur, K)`` returns it: the four candidates
    of ``cv2.decomposeEssentialMat`` (R1, t), (R2, t), (R1, -t), (R2, -t) vote on at most ``max_points``
    inliers spread evenly through the list (the vote is not close for a correct E), ties going to the
    earlier candidate as in OpenCV. The vote is done here, on the least-squares depths of both rays
    (``ray_depths``), in one vectorised pass: recoverPose triangulates every point four times, which
    cost 0.67 ms a frame. The cheirality of every inlier is then checked against the chosen motion.
    Returns ``(R_cur_ref, t_cur_ref (3,) unit, mask of inliers in front of both cameras)``.
    """
    idx = np.flatnonzero(inliers)
    if idx.size < 5:
        return np.eye(3), np.zeros(3), np.zeros(inliers.shape[0], dtype=bool)
    K_inv = np.linalg.inv(K)
    xn_ref = (homogeneous(uv_ref) @ K_inv.T)[:, :2]
    xn_cur = (homogeneous(uv_cur) @ K_inv.T)[:, :2]
    vote = idx if idx.size <= max_points else idx[np.linspace(0, idx.size - 1, max_points).astype(np.int64)]
    R1_any, R2_any, t_any = cv2.decomposeEssentialMat(np.asarray(E, dtype=np.float64))
    R1: F64 = np.asarray(R1_any, np.float64)
    R2: F64 = np.asarray(R2_any, np.float64)
    t: F64 = np.asarray(t_any, dtype=np.float64).reshape(3)
    # The depths are linear in t: those of (R, -t) are those of (R, t) negated.
    far = _CHEIRALITY_MAX_DISTANCE
    votes = []
    for R_c in (R1, R2):
        d_ref, d_cur = ray_depths(R_c, t, xn_ref[vote], xn_cur[vote])
        votes.append((int(np.count_nonzero((d_ref > 0.0) & (d_cur > 0.0) & (d_ref < far) & (d_cur < far))),
                      int(np.count_nonzero((d_ref < 0.0) & (d_cur < 0.0) & (d_ref > -far) & (d_cur > -far)))))
    counts = [votes[0][0], votes[1][0], votes[0][1], votes[1][1]]  # OpenCV's order: (R1,t) (R2,t) (R1,-t) (R2,-t)
    best = int(np.argmax(counts))  # the first of equal counts
    R, t = (R1, R2)[best % 2], (t if best < 2 else -t)
    d_ref, d_cur = ray_depths(R, t, xn_ref, xn_cur)
    return R, t, inliers & (d_ref > 0.0) & (d_cur > 0.0)


def rotation_from_homography(H: F64, K: F64) -> F64:
    """Under pure rotation ``H = K R K^-1`` (H&Z 8.4.2): R_cur_ref is the nearest rotation to K^-1 H K."""
    M = np.linalg.inv(K) @ H @ K
    M = M / np.cbrt(np.linalg.det(M))
    return nearest_rotation(M)


def focal_for_rotation(H: F64, K: F64) -> float | None:
    """The focal length (px) under which the homography ``H`` (reference -> current, undistorted pixels)
    is a pure rotation, with K's principal point and square pixels; None when no positive one is.

    Under pure rotation ``H = K R K^-1``, so ``H w H^T = w`` for ``w = K K^T`` (the dual image of the
    absolute conic, H&Z 19.6 / 8.5), with H scaled to unit determinant; with the principal point at the
    origin ``w = f^2 diag(1, 1, 0) + diag(0, 0, 1)`` and each entry of ``H w H^T - w = 0`` is linear in
    ``f^2``: solved in least squares. A rotation about the optical axis alone, or the homography of a
    translation across a plane facing the camera (a pure shift of the image), constrains no focal length.
    This algebraic fit is biased by a few per cent with noisy points (2 % at 0.3 px and 5 deg):
    ``rotation_under_camera_error`` takes it from there.
    """
    T = np.array([[1.0, 0.0, -K[0, 2]], [0.0, 1.0, -K[1, 2]], [0.0, 0.0, 1.0]])
    Hc = T @ H @ np.linalg.inv(T)
    det = float(np.linalg.det(Hc))
    if not abs(det) > 1e-12:
        return None
    Hc = Hc / np.cbrt(det)
    iu = np.triu_indices(3)
    a = (Hc[:, :2] @ Hc[:, :2].T - np.diag([1.0, 1.0, 0.0]))[iu]
    b = (np.diag([0.0, 0.0, 1.0]) - np.outer(Hc[:, 2], Hc[:, 2]))[iu]
    den = float(a @ a)
    if not den > 1e-18:
        return None
    f2 = float(a @ b) / den
    if not (math.isfinite(f2) and f2 > 0.0):
        return None
    return math.sqrt(f2)


PNP_MIN_SIGMA_PX = 0.05  # floor of the a posteriori image noise behind refine_pose_pnp's covariance (px per axis)


PLANE_MOTION_AGREE = (0.5, 30.0)  # deg: a motion this close in rotation and direction is the plane's


@dataclass(frozen=True)
class PlanarSolution:
    """One decomposition of a homography: ``X_cur = R X_ref + t`` with ``t`` in units of the plane's
    distance from the reference camera, the plane's unit ``normal`` in the reference frame, and the
    triangulation of H's inliers under this motion (``n_good`` points pass the gates)."""

    R: F64
    t: F64
    normal: F64
    tri: Triangulation
    n_good: int


def homography_solutions(H: F64, K: F64, xn_ref: F64, xn_cur: F64, inliers: Mask, max_reproj_err_px: float,
                         min_angle_deg: float) -> list[PlanarSolution]:
    """The decompositions of H (Faugeras / Malis, ``cv2.decomposeHomographyMat``) with at least one point
    through the triangulation gates, most such points first; each triangulates H's inliers only."""
    _, Rs, ts, ns = cv2.decomposeHomographyMat(H, K)
    idx = np.flatnonzero(inliers)
    out = []
    for R_any, t_any, n_any in zip(Rs, ts, ns, strict=False):
        R: F64 = np.asarray(R_any, dtype=np.float64)
        t: F64 = np.asarray(t_any, dtype=np.float64).reshape(3)
        n: F64 = np.asarray(n_any, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.all(np.isfinite(n))
                and np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.norm(n) > 0):
            # OpenCV returns non-rotations for an H that no plane can produce (e.g. wildly unequal
            # singular values of K^-1 H K); such a candidate is no pose at all.
            continue
        tri = triangulate(R, t, xn_ref[idx], xn_cur[idx], K, max_reproj_err_px, min_angle_deg)
        n_good = int(np.count_nonzero(tri.good))
        if n_good:
            out.append(PlanarSolution(R, t, n / np.linalg.norm(n), tri, n_good))
    out.sort(key=lambda r: -r.n_good)
    return out


def solution_off_plane(solutions: list[PlanarSolution], K: F64, uv_ref: F64, uv_cur: F64, max_px: float,
                       ratio: float = 4.0) -> PlanarSolution | None:
    """The decomposition of H whose motion explains the correspondences off H's plane (``uv_ref``,
    ``uv_cur``: pixels, E's inliers that H rejects), when they tell the decompositions apart: under it
    their median distance from their epipolar lines (Sampson) is within ``max_px``, under every other
    solution at least ``max_px`` and ``ratio`` times its own. None otherwise (points on the plane fit
    every decomposition alike; too little parallax leaves them all close).

    The points themselves decide, not the rotation of E fitted to them with the plane: E on a plane plus
    a few points is near-degenerate, and its decomposition can take the wrong solution. On a floor
    tracked with klt_window_px 31, E's rotation agreed with the 4.3 deg solution, whose motion
    leaves its 3 off-plane points 1.9-2.0 px from their epipolar lines; the true one (0.02 deg) leaves
    them at 0.13-0.24 px. Where E was right (max_features 80-140, a box in a floor pair), the right
    solution had 0.01-0.29 px and the other 2-16 px."""
    if uv_ref.shape[0] == 0 or not solutions:
        return None
    dist = [np.sqrt(sampson_distance_sq(fundamental_from_essential(essential_from_pose(s.R, s.t), K),
                                        uv_ref, uv_cur)) for s in solutions]
    med = [float(np.median(d)) for d in dist]
    best = int(np.argmin(med))
    if med[best] > max_px:
        return None
    if any(m < max(max_px, ratio * med[best]) for i, m in enumerate(med) if i != best):
        return None
    return solutions[best]


def nearest_plane_motion(R: F64, t: F64, solutions: list[PlanarSolution]) -> tuple[float, float]:
    """How far the motion (``R``, ``t`` of any length) is from the nearest of a plane's motions (H's
    decompositions), in units of ``PLANE_MOTION_AGREE``: (rotation deg, direction of travel deg) of the
    solution with the smallest max(rotation / 0.5 deg, direction / 30 deg); (inf, inf) without one.

    A static plane allows only its decompositions' motions, so an E fitted to the same matches is one
    of them unless part of its consensus moves. Measured on the bundled bags started from many of their
    frames and on KITTI: at most 0.34 deg / 18 deg from the nearest where E
    was right; 0.86-1.99 deg or 40-118 deg where a cart's points took E's consensus (the map then
    started 1-2 deg off: ATE 1-12 %, pose NEES 4000-13000)."""
    tn = np.asarray(t, dtype=np.float64) / max(float(np.linalg.norm(t)), 1e-300)
    best, best_d = (math.inf, math.inf), math.inf
    for s in solutions:
        ts = s.t / max(float(np.linalg.norm(s.t)), 1e-300)
        rot = rotation_angle_deg(s.R @ R.T)
        dirn = math.degrees(math.acos(min(1.0, max(-1.0, float(ts @ tn)))))
        d = max(rot / PLANE_MOTION_AGREE[0], dirn / PLANE_MOTION_AGREE[1])
        if d < best_d:
            best, best_d = (rot, dirn), d
    return best


def agrees_with_plane(R: F64, t: F64, solutions: list[PlanarSolution]) -> bool:
    """``nearest_plane_motion`` within ``PLANE_MOTION_AGREE`` in rotation and direction."""
    rot, dirn = nearest_plane_motion(R, t, solutions)
    return rot <= PLANE_MOTION_AGREE[0] and dirn <= PLANE_MOTION_AGREE[1]


def pose_from_homography(H: F64, K: F64, xn_ref: F64, xn_cur: F64, inliers: Mask,
                         max_reproj_err_px: float, min_angle_deg: float, prefer_R: F64 | None = None
                         ) -> tuple[F64, F64, Triangulation] | None:
    """Planar decomposition of H (``homography_solutions``) resolved by cheirality.

    Returns ``(R_cur_ref, t_cur_ref, triangulation)`` for the solution with the most points passing the
    gates, with ``t`` in units of the plane's distance from the reference camera; None when no solution
    is clearly best (ORB-SLAM: the runner-up must have < 75 % of the winner's good points).

    ``prefer_R`` (e.g. the essential matrix's rotation on the same correspondences) resolves the planar
    ambiguity: two decompositions can both put every point in front of both cameras (a floor seen from
    a camera moving forward), and only one has the rotation the other model agrees with. When the
    winner's rotation is more than 1 deg from it and a solution within 0.5 deg has at least a quarter
    of the winner's good points, that solution is taken (the wrong one of a forward-moving camera sees
    its points under larger angles, so more pass the triangulation gates). When no solution that close
    has that many, the pair is ambiguous (None): with little parallax the right solution passes few
    points through the gates, and the winner E disagrees with was 1.6-3.7 deg off on a floor with a cart
    crossing it and on synthetic floor pairs. Without ``prefer_R`` the rule above decides alone.
    """
    results = homography_solutions(H, K, xn_ref, xn_cur, inliers, max_reproj_err_px, min_angle_deg)
    if not results:
        return None
    if prefer_R is not None and rotation_angle_deg(results[0].R.T @ prefer_R) > 1.0:
        # The other model's rotation decides between physically valid solutions, or says wait.
        agree = [r for r in results if rotation_angle_deg(r.R.T @ prefer_R) < 0.5]
        if not agree or agree[0].n_good < 0.25 * results[0].n_good:
            return None
        results = [agree[0]]
    if len(results) > 1 and results[1].n_good >= 0.75 * results[0].n_good:
        return None
    best = results[0]
    # Outliers of H are not triangulated: expand back to all N correspondences.
    return best.R, best.t, best.tri.expanded(np.flatnonzero(inliers), xn_ref.shape[0])


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
    angles: F64 = np.degrees(np.arccos(np.clip(cos_a, -1.0, 1.0)))
    return angles


def refine_pose_pnp(X_ref: F64, uv_cur: F64, K: F64, R_cur_ref: F64, t_cur_ref: F64,
                    max_reproj_err_px: float, robust_start: bool = False) -> tuple[F64, F64, Mask, F64] | None:
    """Motion-only refinement of (R, t) on map points by Levenberg-Marquardt (``cv2.solvePnPRefineLM``).

    Rounds with a shrinking gate (4x, 2x, 1x ``max_reproj_err_px`` around the current estimate) so
    that map points with bad depth do not pull the least-squares solution before they are dropped. Returns
    ``(R_cur_ref, t_cur_ref, inlier mask, 6x6 covariance of (rvec, tvec))`` or None with < 6 inliers.
    The covariance is ``sigma^2 (J^T J)^-1`` with sigma the RMS reprojection error of the inliers.

    ``robust_start``: also start from the largest consensus of minimal (AP3P) poses within 2x the gate
    (``cv2.solvePnPRansac``, deterministic), and keep whichever result holds more points (the given
    start's on a tie). From a pose a frame or more away the first gate is wide, and a few points of a
    moving object in the map pull LM into their own minimum, after which the static points fail the
    narrower gates: with a cart in the map, the pose from the map came out 0.138 deg off, 3 of its 36
    points 5-19 px off under the true pose and 15 static ones rejected. (The
    consensus start alone, taken whenever it held 6 points, did worse on noisy images: moving_mover with
    3 grey levels of noise 0.25 -> 0.40 % ATE, with motion blur 0.70 -> 1.04 %.)
    """
    if X_ref.shape[0] < 6:
        return None
    obj = X_ref.reshape(-1, 1, 3).astype(np.float64)
    img = uv_cur.reshape(-1, 1, 2).astype(np.float64)
    rvec = cast(F64, cv2.Rodrigues(R_cur_ref)[0])
    best = _pnp_gated_lm(obj, img, uv_cur, K, rvec, t_cur_ref.reshape(3, 1).astype(np.float64), max_reproj_err_px)
    if robust_start:
        ok, rv, tv, inl = cv2.solvePnPRansac(obj, img, K, np.zeros(5), iterationsCount=200,
                                             reprojectionError=2.0 * max_reproj_err_px, confidence=0.999,
                                             flags=cv2.SOLVEPNP_AP3P)
        if ok and inl is not None and len(inl) >= 6 and np.all(np.isfinite(rv)) and np.all(np.isfinite(tv)):
            other = _pnp_gated_lm(obj, img, uv_cur, K, np.asarray(rv, np.float64),
                                  np.asarray(tv, np.float64).reshape(3, 1), max_reproj_err_px)
            if other is not None and (best is None or np.count_nonzero(other[2]) > np.count_nonzero(best[2])):
                best = other
    return best


def _pnp_gated_lm(obj: F64, img: F64, uv_cur: F64, K: F64, rvec: F64, tvec: F64, max_reproj_err_px: float
                  ) -> tuple[F64, F64, Mask, F64] | None:
    """``refine_pose_pnp``'s gated Levenberg-Marquardt rounds from (``rvec``, ``tvec``)."""
    zero_d = np.zeros(5)

    def errors() -> F64:
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, zero_d)
        e: F64 = np.linalg.norm(proj.reshape(-1, 2) - uv_cur, axis=1)
        return e

    for i, gate in enumerate((4.0, 2.0, 1.0)):
        err = errors()
        # The first gate also scales with the median error, so that a coarse start (a degree off)
        # keeps the consistent majority rather than nothing.
        limit = gate * max_reproj_err_px if i else max(gate * max_reproj_err_px, 2.0 * float(np.median(err)))
        keep = err <= limit
        if np.count_nonzero(keep) < 6:
            return None
        refined = cv2.solvePnPRefineLM(obj[keep], img[keep], K, zero_d, rvec, tvec)
        rvec, tvec = cast(F64, refined[0]), cast(F64, refined[1])
    keep = errors() <= max_reproj_err_px
    if np.count_nonzero(keep) < 6:
        return None
    proj, J = cv2.projectPoints(obj[keep], rvec, tvec, K, zero_d)
    J = J[:, :6]
    res = proj.reshape(-1, 2) - uv_cur[keep]
    sigma2 = max(float(np.mean(res**2)), PNP_MIN_SIGMA_PX**2)  # per axis
    try:
        cov = sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    R, _ = cv2.Rodrigues(rvec)
    return np.asarray(R, dtype=np.float64), tvec.reshape(3), keep, cov


# chi-square, 5 dof, 99.9 %: the drop in the epipolar residuals that says a homography's pose is not the
# pose its own inliers show (``refine_planar_pose``)
CHI2_5DOF_999 = 20.515


def refine_planar_pose(R_cur_ref: F64, t_dir: F64, xn_ref: F64, xn_cur: F64, inliers: Mask,
                       max_rotation_deg: float = 0.5, max_direction_deg: float = 10.0) -> tuple[F64, F64, Note]:
    """A homography decomposition's pose refined on the epipolar distances of ``inliers``
    (``refine_relative_pose``) when they reject it, else the decomposition's, unchanged. Returns
    ``(R, t_dir, what was done)`` for the frame's notes.

    The test: the refinement's drop in the squared residuals over their variance after it,
    ``n (rms_before^2 / rms_after^2 - 1)``, above the chi-square 5-dof 99.9 % bound. A floor with a
    few points off it (ground_robot, moving_mover, the robot drives) gives 179-455: H's fit leans to
    the points its threshold let in, and its pose was 0.02-0.03 deg off (the epipolar one 0.002-0.008).
    A true plane (bags/planar) gives 0.5-7: its points leave E's pose in a flat valley, where the
    refinement only wanders (with ``klt_window_px`` 21 / 31 it took planar's rotation NEES 2.8 / 5.9
    to 10 / 18). The result must also stay within ``max_rotation_deg`` and ``max_direction_deg``."""
    idx = np.flatnonzero(inliers)
    out = refine_relative_pose(R_cur_ref, t_dir, xn_ref[idx], xn_cur[idx])
    if out is None:
        return R_cur_ref, t_dir, note(Decision.PLANE_POSE_UNTESTED)
    R, t, before, after = out
    stat = idx.size * (before * before / max(after * after, 1e-300) - 1.0)
    if not stat > CHI2_5DOF_999:
        return R_cur_ref, t_dir, note(Decision.PLANE_POSE_FITS, stat=stat)
    moved = rotation_angle_deg(R @ R_cur_ref.T)
    turned = math.degrees(math.acos(min(1.0, float(t @ t_dir) / float(np.linalg.norm(t_dir)))))
    if moved > max_rotation_deg or turned > max_direction_deg:
        return R_cur_ref, t_dir, note(Decision.PLANE_POSE_OTHER_SOLUTION, moved=moved, turned=turned)
    return R, t, note(Decision.PLANE_POSE_REFINED, n=idx.size, stat=stat, moved=moved)
