"""Windowed bundle adjustment over the last keyframes (GTSAM): a pure function over numpy arrays.

``adjust(Window)`` refines the keyframe poses ``T_w_kf`` (camera optical frame -> odometry frame ``w``)
and the map points seen by them from the observed normalized image coordinates ``xn`` (undistorted,
``x = (u - cx) / fx``). It holds no state: everything it needs is in the :class:`Window`, everything
it finds is in the :class:`Adjusted` it returns.

The model
    * one ``GenericProjectionFactorCal3_S2`` per observation, on normalized coordinates (a ``Cal3_S2``
      with fx = fy = 1, cx = cy = 0), isotropic noise ``sigma_px / fx`` made robust by a Huber loss
      (``huber_k`` in whitened units, on the norm of the 2-vector residual);
    * gauge: the ``n_fixed`` oldest keyframes are held by tight priors and are returned exactly as
      given. The priors' sigmas are ``GAUGE_FRACTION`` of one observation's noise: ``sigma_n`` rad in
      rotation, ``sigma_n`` times the median point depth in translation (tighter makes the linear
      systems ill-conditioned enough for GTSAM to call them indeterminant; this is far below any
      keyframe's real uncertainty, and independent of the map's units);
    * scale: with ``n_fixed >= 2`` the fixed keyframes fix it. Otherwise it comes from the
      ``distance_priors`` (``RangeFactorPose3``: a prior on the distance between two camera centres,
      e.g. from wheel odometry) and/or the :class:`PlanePrior`. With ``n_fixed == 1`` and neither,
      the scale of the initial window is kept: a tight prior on the distance between keyframe 0 and
      the keyframe farthest from it but the newest, at its initial value. The longest baseline is the one whose
      length the VO knows best in relative terms; fixing a short one (two fixed keyframes, or keyframe
      0 and 1) let the window's scale swing by the error of that one step (ground_robot with a window
      of 4: the newest keyframe's scale 0.42-10.9x before / after an adjustment, Sim(3) ATE 15 %);
    * floor plane: the window is solved in a floor frame ``F`` (z along the normal of the plane the
      floor points' initial positions fit, towards the cameras; ``plane_w`` maps its z = 0 back to
      ``w``). A floor point's height in ``F`` is 0 (sigma ``sigma_plane``, Huber: a
      ``PriorFactorPoint3`` free along the floor) and every keyframe's camera centre is at ``height``
      (sigma ``sigma_height``: a ``PoseTranslationPrior3D`` free along the floor). The plane is then
      where keyframe 0 is not held: the gauge holds keyframe 0 in x, y and yaw of ``F`` only (and the
      other fixed keyframes relative to it), so its height, roll and pitch above the floor are the
      plane's three unknowns, and the result is moved back so that keyframe 0 is where it was given.
      The same optimum as a plane variable with a factor per floor point (tested), in native GTSAM
      factors: an ``OrientedPlane3`` with Python ``CustomFactor`` objects takes 190 ms per floor window
      of the ground-robot render against 106 (same poses to 2e-6 of the window's extent).

The procedure
    1. Observations with non-finite coordinates, of a non-finite point, or of a point at or behind
       the observing camera at the initial estimate are not used; points seen by fewer than two
       keyframes, or whose rays span less than ``MIN_PARALLAX_DEG`` (depth unconstrained: in xyz such
       a point drifts towards infinity and makes the system singular), are excluded (NaN).
    2. Levenberg-Marquardt (deterministic parameters, COLAMD, multifrontal Cholesky, at most
       ``max_iterations`` per pass) on the robust problem; then the gate: a point behind any camera
       that observes it is dropped, an observation whose whitened squared residual exceeds
       ``CHI2_2DOF_99`` (2 dof, 99 %) is an outlier, a point left with fewer than two keyframes or
       too little parallax is dropped. If the gate changed anything, a second pass optimises the
       kept observations only and the gate is applied once more (without a third pass).
    3. ``cov_newest``: GTSAM ``Marginals`` of the newest keyframe pose on the *Gaussian* problem over
       the kept observations at the solution (the Huber weights are an outlier device; after the gate
       the kept residuals are modelled as Gaussian), converted from GTSAM's tangent space (rotation,
       translation; right perturbation ``T exp(xi)``, body frame) to the pipeline's convention: world
       frame, position first (see :func:`world_covariance` and ``epi_vo.core.covariance``).

Failure is a value: an unusable window (fewer than two keyframes, non-finite poses, too few points,
an adjusted keyframe with too few observations, no usable floor plane when a plane prior is given, an
optimiser or marginalisation error, a non-finite result) gives ``None``. Only programmer errors raise
(``ValueError``: wrong shapes or dtypes, indices out of range, non-positive sigmas, a pose that is not
a rigid transform). The result is deterministic: the same window gives bit-identical arrays (``ms``
aside).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any, NamedTuple, cast

import gtsam
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.covariance import floored
from epi_vo.core.geometry import nearest_rotation
from epi_vo.core.transforms import invert_T

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

CHI2_2DOF_99 = 9.21  # final inlier gate on an observation's whitened squared residual (2 dof, 99 %)
LM_RELATIVE_TOL = 1e-6  # Levenberg-Marquardt stops when the error drops by less than this fraction ...
LM_ABSOLUTE_TOL = 1e-3  # ... or by less than this (half a squared whitened residual: insignificant)
HUBER_K = 2.45  # whitened residual norm where Huber turns linear (95 % quantile of a 2-dof norm)
GAUGE_FRACTION = 1e-2  # sigma of the gauge / default scale priors in units of one observation's noise
MIN_DEPTH = 1e-6  # m: a point must be this far in front of every camera that observes it
MIN_PARALLAX_DEG = 0.5  # a point's rays must span this angle (else its depth is unconstrained: dropped)
MIN_POINTS = 8  # fewer adjusted points: the window is unusable
MIN_OBS_PER_KF = 6  # fewer observations on an adjusted (not fixed) keyframe: the window is unusable
MAX_PASSES = 2  # robust pass, then one pass on the gated observations
ROTATION_TOL = 1e-6  # max |R^T R - I| of an input pose
MIN_PLANE_POINTS = 3  # three points fix a plane: fewer floor points leave the plane prior unconstrained


class DistancePrior(NamedTuple):
    """A prior on the distance between the camera centres of keyframes ``i`` and ``j`` (m)."""

    i: int
    j: int
    distance: float
    sigma: float


@dataclass(frozen=True)
class PlanePrior:
    """Floor points and the camera height above the floor: fixes the scale of the window.

    ``points`` indexes ``Window.points_w`` (points believed to lie on the floor); ``height`` is the
    distance of every keyframe's camera centre to the floor plane, known to ``sigma_height``;
    ``sigma_plane`` how far a floor point may lie off the plane (floor roughness).
    """

    points: I64
    height: float
    sigma_height: float
    sigma_plane: float = 0.02


@dataclass(frozen=True)
class Window:
    """The last keyframes, their map points and the observations linking them (oldest keyframe first).

    ``obs_kf[m]``/``obs_pt[m]`` say which keyframe saw which point at normalized coordinates
    ``obs_xn[m]``; ``sigma_px`` is the pixel noise and ``fx`` the focal length in pixels (the noise in
    normalized units is ``sigma_px / fx``). ``n_fixed`` oldest keyframes are held fixed (gauge; with
    two or more they also fix the scale). ``distance_priors`` are :class:`DistancePrior` or plain
    ``(i, j, distance, sigma)`` tuples; ``plane_prior`` an optional :class:`PlanePrior`.
    """

    T_w_kf: F64
    points_w: F64
    obs_kf: I64
    obs_pt: I64
    obs_xn: F64
    sigma_px: float
    fx: float
    n_fixed: int = 1
    distance_priors: tuple[DistancePrior | tuple[int, int, float, float], ...] = ()
    plane_prior: PlanePrior | None = None


@dataclass(frozen=True)
class Adjusted:
    """The refined window.

    ``points_w`` is NaN for points not adjusted (seen by fewer than two keyframes, dropped behind a
    camera or left with fewer than two inlier keyframes); ``inlier_obs`` marks the observations the
    final estimate and its covariance use. ``cov_newest`` is the 6x6 marginal covariance of the newest
    keyframe pose over (x, y, z, rot_x, rot_y, rot_z) in ``w``, position first (symmetrised, variances
    floored as by ``epi_vo.core.covariance.floored``). ``initial_error`` and
    ``final_error`` are GTSAM's error (half the sum of squared whitened residuals) of the final
    Gaussian problem at the input and at the refined estimate; ``iterations`` counts the
    Levenberg-Marquardt iterations of every pass; ``plane_w`` is the refined floor plane (n, d) with
    ``n . X + d = 0`` (None without a plane prior); ``ms`` the wall time of the call.
    """

    T_w_kf: F64
    points_w: F64
    inlier_obs: BoolArray
    cov_newest: F64
    iterations: int
    initial_error: float
    final_error: float
    ms: float
    plane_w: F64 | None = None


@dataclass(frozen=True)
class _Problem:
    """The validated window, with the indices that do not change between passes."""

    T_w_kf: F64  # as given (the fixed keyframes are returned as such)
    T_rigid: F64  # with each rotation replaced by the nearest rotation matrix (what GTSAM gets)
    points_w: F64
    obs_kf: I64
    obs_pt: I64
    obs_xn: F64
    sigma_n: float
    n_fixed: int
    distances: tuple[DistancePrior, ...]
    plane: PlanePrior | None
    floor: BoolArray  # (P,) point is a floor point
    scale_pair: tuple[int, int] | None  # default scale prior (keyframes, initial distance kept)
    huber_k: float
    max_iterations: int

    @property
    def n_kf(self) -> int:
        return int(self.T_w_kf.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.points_w.shape[0])


def world_covariance(cov_tangent: F64, R_w_c: F64) -> F64:
    """GTSAM's Pose3 covariance (rotation, translation; ``T exp(xi)``, body frame) in the world frame,
    position first: (x, y, z, rot_x, rot_y, rot_z), rotations as ``exp(dtheta) R_w_c``.

    To first order ``T exp([w, v]) = (exp(R w) R, t + R v)``: the world position error is ``R v`` and
    the world rotation error ``R w``.
    """
    cov_tangent = np.asarray(cov_tangent, dtype=np.float64)
    R = np.asarray(R_w_c, dtype=np.float64)
    if cov_tangent.shape != (6, 6) or R.shape != (3, 3):
        msg = f"world_covariance: expected (6, 6) and (3, 3), got {cov_tangent.shape} and {R.shape}"
        raise ValueError(msg)
    A = np.zeros((6, 6))
    A[:3, 3:] = R  # position <- translation part (tangent 3:6)
    A[3:, :3] = R  # rotation <- rotation part (tangent 0:3)
    return A @ cov_tangent @ A.T


def adjust(window: Window, *, max_iterations: int = 10, huber_k: float = HUBER_K) -> Adjusted | None:
    """Bundle-adjust the window; None when it is unusable (see the module docstring).

    ``max_iterations`` bounds each Levenberg-Marquardt pass; ``huber_k`` is the Huber threshold in
    whitened units. Raises ValueError only for malformed input (shapes, dtypes, ranges).
    """
    t0 = time.perf_counter()
    problem = _validated(window, max_iterations, huber_k)
    if problem is None:
        return None
    try:
        result = _solve(problem)
    except RuntimeError:  # GTSAM: indeterminant system, cheirality, ... -- an unusable window
        return None
    if result is None:
        return None
    T_w_kf, points_w, inlier, cov, iterations, err0, err1, plane_w = result
    return Adjusted(T_w_kf=T_w_kf, points_w=points_w, inlier_obs=inlier, cov_newest=cov, iterations=iterations,
                    initial_error=err0, final_error=err1, ms=1e3 * (time.perf_counter() - t0), plane_w=plane_w)


# ----------------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------------


def _float_array(value: object, ndim_shape: tuple[int | None, ...], name: str) -> F64:
    array = np.asarray(value)
    if array.dtype.kind not in "fiu":
        msg = f"{name} must be a real array, got dtype {array.dtype}"
        raise ValueError(msg)
    if array.ndim != len(ndim_shape) or any(s is not None and s != a for s, a in zip(ndim_shape, array.shape,
                                                                                    strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in ndim_shape) + ")"
        msg = f"{name} has shape {array.shape}, expected {want}"
        raise ValueError(msg)
    return np.ascontiguousarray(array, dtype=np.float64)


def _index_array(value: object, length: int, upper: int, name: str) -> I64:
    array = np.asarray(value)
    if array.ndim != 1 or array.shape[0] != length:
        msg = f"{name} has shape {array.shape}, expected ({length},)"
        raise ValueError(msg)
    if array.size and array.dtype.kind not in "iu":
        msg = f"{name} must hold integers, got dtype {array.dtype}"
        raise ValueError(msg)
    array = array.astype(np.int64)
    if array.size and (array.min() < 0 or array.max() >= upper):
        msg = f"{name} has indices outside [0, {upper})"
        raise ValueError(msg)
    return array


def _positive(value: object, name: str) -> float:
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        msg = f"{name} must be a number, got {value!r}"
        raise ValueError(msg) from exc
    if not (math.isfinite(number) and number > 0.0):
        msg = f"{name} must be finite and > 0, got {value!r}"
        raise ValueError(msg)
    return number


def _validated(window: Window, max_iterations: int, huber_k: float) -> _Problem | None:
    """The checked, float64/int64 problem; ValueError for malformed input, None for unusable data."""
    T_w_kf = _float_array(window.T_w_kf, (None, 4, 4), "T_w_kf")
    points_w = _float_array(window.points_w, (None, 3), "points_w")
    obs_xn = _float_array(window.obs_xn, (None, 2), "obs_xn")
    n_kf, n_points, n_obs = T_w_kf.shape[0], points_w.shape[0], obs_xn.shape[0]
    obs_kf = _index_array(window.obs_kf, n_obs, n_kf, "obs_kf")
    obs_pt = _index_array(window.obs_pt, n_obs, n_points, "obs_pt")
    sigma_n = _positive(window.sigma_px, "sigma_px") / _positive(window.fx, "fx")
    huber_k = _positive(huber_k, "huber_k")
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int | np.integer) or max_iterations < 1:
        msg = f"max_iterations must be an int >= 1, got {max_iterations!r}"
        raise ValueError(msg)
    n_fixed = window.n_fixed
    if isinstance(n_fixed, bool) or not isinstance(n_fixed, int | np.integer) or n_fixed < 1:
        msg = f"n_fixed must be an int >= 1 (the gauge), got {n_fixed!r}"
        raise ValueError(msg)
    distances = tuple(_distance_prior(p, n_kf) for p in window.distance_priors)
    plane = window.plane_prior
    floor = np.zeros(n_points, dtype=bool)
    if plane is not None:
        if not isinstance(plane, PlanePrior):
            msg = f"plane_prior must be a PlanePrior or None, got {type(plane).__name__}"
            raise ValueError(msg)
        idx = np.asarray(plane.points)
        if idx.ndim != 1:
            msg = f"plane_prior.points has shape {idx.shape}, expected (N,)"
            raise ValueError(msg)
        floor[_index_array(idx, idx.shape[0], n_points, "plane_prior.points")] = True
        for name in ("height", "sigma_height", "sigma_plane"):
            _positive(getattr(plane, name), f"plane_prior.{name}")
    if n_kf < 2 or not np.all(np.isfinite(T_w_kf)):
        return None
    bottom = np.abs(T_w_kf[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max()
    R = T_w_kf[:, :3, :3]
    ortho = np.abs(np.einsum("kji,kjl->kil", R, R) - np.eye(3)).max()
    if bottom > 0.0 or ortho > ROTATION_TOL or np.any(np.linalg.det(R) <= 0.0):
        msg = f"T_w_kf must hold rigid transforms (|R^T R - I| = {ortho:.2g}, last row off by {bottom:.2g})"
        raise ValueError(msg)
    scale_pair = None
    if n_fixed == 1 and not distances and plane is None:
        scale_pair = _scale_pair(T_w_kf)
        if scale_pair is None:
            return None
    T_rigid = T_w_kf.copy()
    T_rigid[:, :3, :3] = [nearest_rotation(Rk) for Rk in R]
    return _Problem(T_w_kf=T_w_kf, T_rigid=T_rigid, points_w=points_w, obs_kf=obs_kf, obs_pt=obs_pt, obs_xn=obs_xn,
                    sigma_n=sigma_n, n_fixed=min(int(n_fixed), n_kf), distances=distances, plane=plane, floor=floor,
                    scale_pair=scale_pair, huber_k=huber_k, max_iterations=int(max_iterations))


def _distance_prior(prior: object, n_kf: int) -> DistancePrior:
    try:
        i, j, distance, sigma = cast(tuple[Any, Any, Any, Any], prior)
    except (TypeError, ValueError) as exc:
        msg = f"a distance prior must be (i, j, distance, sigma), got {prior!r}"
        raise ValueError(msg) from exc
    for k in (i, j):
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or not 0 <= k < n_kf:
            msg = f"distance prior {prior!r}: keyframe index {k!r} not an int in [0, {n_kf})"
            raise ValueError(msg)
    if i == j:
        msg = f"distance prior {prior!r}: i and j must differ"
        raise ValueError(msg)
    return DistancePrior(int(i), int(j), _positive(distance, "prior distance"), _positive(sigma, "prior sigma"))


def _scale_pair(T_w_kf: F64) -> tuple[int, int] | None:
    """Keyframe 0 and the keyframe farthest from it but the newest (the one an adjustment is for, least
    constrained yet) when there are three or more: their distance carries the window's scale (None:
    every keyframe is at keyframe 0's centre)."""
    dist = np.linalg.norm(T_w_kf[:, :3, 3] - T_w_kf[0, :3, 3], axis=1)
    far = int(np.argmax(dist[:-1] if dist.size >= 3 else dist))
    if not dist[far] > 0.0:
        return None
    return 0, far


# ----------------------------------------------------------------------------------------------
# Selection and gate
# ----------------------------------------------------------------------------------------------


def _depths_and_residuals(p: _Problem, T_w_kf: F64, points_w: F64, sel: BoolArray) -> tuple[F64, F64]:
    """Depth of each selected observation's point in its camera and its whitened residual (m, 2)."""
    kf, pt = p.obs_kf[sel], p.obs_pt[sel]
    R, t = T_w_kf[kf, :3, :3], T_w_kf[kf, :3, 3]
    X_c = np.einsum("mji,mj->mi", R, points_w[pt] - t)
    z = X_c[:, 2]
    safe = np.where(z > MIN_DEPTH, z, 1.0)
    return z, (X_c[:, :2] / safe[:, None] - p.obs_xn[sel]) / p.sigma_n


def _two_view_points(p: _Problem, active: BoolArray) -> BoolArray:
    """Points observed by at least two distinct keyframes through the active observations."""
    pairs = np.unique(p.obs_pt[active] * p.n_kf + p.obs_kf[active])
    return np.bincount(pairs // p.n_kf, minlength=p.n_points) >= 2


def _low_parallax(p: _Problem, T_w_kf: F64, points_w: F64, active: BoolArray) -> BoolArray:
    """Points whose rays span less than ``MIN_PARALLAX_DEG``: the largest angle between the ray from the
    camera of the point's first active observation and its rays from the other observing cameras."""
    idx = np.flatnonzero(active)
    pt = p.obs_pt[idx]
    rays = points_w[pt] - T_w_kf[p.obs_kf[idx], :3, 3]
    rays /= np.maximum(np.linalg.norm(rays, axis=1), 1e-300)[:, None]
    first_rays = np.zeros((p.n_points, 3))
    uniq, first = np.unique(pt, return_index=True)
    first_rays[uniq] = rays[first]
    cos = np.clip(np.sum(rays * first_rays[pt], axis=1), -1.0, 1.0)
    parallax = np.zeros(p.n_points)
    np.maximum.at(parallax, pt, np.degrees(np.arccos(cos)))
    return parallax < MIN_PARALLAX_DEG


def _initial_active(p: _Problem) -> BoolArray:
    """Usable observations: finite, of a finite point in front of the camera, of a point seen by two
    keyframes with enough parallax at the initial estimate."""
    usable = np.all(np.isfinite(p.obs_xn), axis=1) & np.all(np.isfinite(p.points_w[p.obs_pt]), axis=1)
    if np.any(usable):
        points_w = np.nan_to_num(p.points_w)
        z, _ = _depths_and_residuals(p, p.T_w_kf, points_w, usable)
        usable[np.flatnonzero(usable)[z <= MIN_DEPTH]] = False
        usable &= ~_low_parallax(p, p.T_w_kf, points_w, usable)[p.obs_pt]
    out: BoolArray = usable & _two_view_points(p, usable)[p.obs_pt]
    return out


def _gate(p: _Problem, T_w_kf: F64, points_w: F64, active: BoolArray) -> BoolArray:
    """Kept observations: point in front of all its cameras, chi2 within the gate, point in >= 2 keyframes
    with enough parallax."""
    idx = np.flatnonzero(active)
    z, r = _depths_and_residuals(p, T_w_kf, points_w, active)
    behind = np.zeros(p.n_points, dtype=bool)
    behind[p.obs_pt[idx[z <= MIN_DEPTH]]] = True
    keep = np.zeros_like(active)
    keep[idx] = (z > MIN_DEPTH) & (np.sum(r * r, axis=1) <= CHI2_2DOF_99)
    keep &= ~behind[p.obs_pt]
    keep &= _two_view_points(p, keep)[p.obs_pt]
    return keep & ~_low_parallax(p, T_w_kf, points_w, keep)[p.obs_pt]


def _usable(p: _Problem, active: BoolArray) -> bool:
    """Enough points, every adjusted keyframe observed enough, enough floor points for a plane prior."""
    used = _two_view_points(p, active)
    per_kf = np.bincount(p.obs_kf[active], minlength=p.n_kf)
    if int(used.sum()) < MIN_POINTS or np.any(per_kf[p.n_fixed:] < MIN_OBS_PER_KF):
        return False
    return p.plane is None or int((used & p.floor).sum()) >= MIN_PLANE_POINTS


# ----------------------------------------------------------------------------------------------
# Factor graph
# ----------------------------------------------------------------------------------------------

X = gtsam.symbol_shorthand.X  # keyframe poses
L = gtsam.symbol_shorthand.L  # map points


def _fit_plane(p: _Problem, points_w: F64, used: BoolArray) -> F64 | None:
    """Least-squares plane (n, d), ``n . X + d = 0``, through the used floor points, ``n`` towards the
    cameras; None if they do not span a plane."""
    floor = points_w[used & p.floor]
    centroid = floor.mean(axis=0)
    _, s, Vt = np.linalg.svd(floor - centroid)
    if s.shape[0] < 3 or s[1] <= 1e-6 * max(s[0], 1e-300):
        return None
    n = Vt[2]
    d = -float(n @ centroid)
    if float(np.mean(p.T_w_kf[:, :3, 3] @ n + d)) < 0.0:
        n, d = -n, -d
    return np.array([*n, d])


FREE_SIGMA_FACTOR = 1e4  # sigma of a prior's free components (along the floor), in median point depths
FREE_ROT_SIGMA = 10.0  # rad: sigma of keyframe 0's roll and pitch in the floor frame (free)


def _floor_frame(T_w_kf0: F64, plane_w: F64) -> F64:
    """T_F_w of the floor frame: z along the plane's unit normal (towards the cameras), origin at the foot
    of keyframe 0's centre, x along keyframe 0's optical axis (or its x axis) projected onto the plane."""
    norm = float(np.linalg.norm(plane_w[:3]))
    n, d = plane_w[:3] / norm, plane_w[3] / norm
    c0, R0 = T_w_kf0[:3, 3], T_w_kf0[:3, :3]
    ax = R0[:, 2] - (R0[:, 2] @ n) * n
    if np.linalg.norm(ax) < 1e-6:
        ax = R0[:, 0] - (R0[:, 0] @ n) * n
    ax /= np.linalg.norm(ax)
    T = np.eye(4)
    T[:3, :3] = np.stack([ax, np.cross(n, ax), n])  # rows: F's axes in w
    T[:3, 3] = -T[:3, :3] @ (c0 - (n @ c0 + d) * n)
    return T


def _gauge(p: _Problem, rot_sigma: float, trans_sigma: float, free: float) -> list[gtsam.NonlinearFactor]:
    """Keyframe 0 held in the floor frame's x, y (``trans_sigma``) and yaw (``rot_sigma``), free in
    height, roll and pitch; the other fixed keyframes held relative to it."""
    T0 = p.T_rigid[0]
    R0 = T0[:3, :3]
    # PoseRotationPrior3D's error w is in keyframe 0's own axes (R = R0 exp(w)); R0 w is in F's.
    sqrt_info = np.diag([1.0 / FREE_ROT_SIGMA, 1.0 / FREE_ROT_SIGMA, 1.0 / rot_sigma]) @ R0
    factors: list[gtsam.NonlinearFactor] = [
        gtsam.PoseTranslationPrior3D(X(0), T0[:3, 3], gtsam.noiseModel.Diagonal.Sigmas(
            np.array([trans_sigma, trans_sigma, free]))),
        gtsam.PoseRotationPrior3D(X(0), gtsam.Rot3(R0), gtsam.noiseModel.Gaussian.SqrtInformation(sqrt_info))]
    rigid = gtsam.noiseModel.Diagonal.Sigmas(np.array([rot_sigma] * 3 + [trans_sigma] * 3))
    for k in range(1, p.n_fixed):
        factors.append(gtsam.BetweenFactorPose3(X(0), X(k), gtsam.Pose3(invert_T(T0) @ p.T_rigid[k]), rigid))
    return factors


def _graph(p: _Problem, active: BoolArray, robust: bool,
           gauge_sigmas: tuple[float, float]) -> gtsam.NonlinearFactorGraph:
    """Gauge and scale priors, one projection factor per active observation, the plane factors.

    ``gauge_sigmas`` = (rad, m) of the priors holding the fixed keyframes (and the default scale).
    """
    graph = gtsam.NonlinearFactorGraph()
    rot_sigma, trans_sigma = gauge_sigmas
    free = FREE_SIGMA_FACTOR * trans_sigma / (GAUGE_FRACTION * p.sigma_n)  # FREE_SIGMA_FACTOR median depths
    if p.plane is not None:  # the problem is in the floor frame
        for factor in _gauge(p, rot_sigma, trans_sigma, free):
            graph.add(factor)
    else:
        gauge = gtsam.noiseModel.Diagonal.Sigmas(np.array([rot_sigma] * 3 + [trans_sigma] * 3))  # GTSAM: rot first
        for k in range(p.n_fixed):
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(p.T_rigid[k]), gauge))
    if p.scale_pair is not None:
        i, j = p.scale_pair
        d0 = float(np.linalg.norm(p.T_rigid[j, :3, 3] - p.T_rigid[i, :3, 3]))
        graph.add(gtsam.RangeFactorPose3(X(i), X(j), d0, gtsam.noiseModel.Isotropic.Sigma(1, trans_sigma)))
    for prior in p.distances:
        graph.add(gtsam.RangeFactorPose3(X(prior.i), X(prior.j), prior.distance,
                                         gtsam.noiseModel.Isotropic.Sigma(1, prior.sigma)))

    def maybe_robust(base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
        if not robust:
            return base
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(p.huber_k), base)

    pixel = maybe_robust(gtsam.noiseModel.Isotropic.Sigma(2, p.sigma_n))
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    for m in np.flatnonzero(active):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(p.obs_xn[m], pixel, X(int(p.obs_kf[m])),
                                                       L(int(p.obs_pt[m])), K))
    if p.plane is not None:
        on_floor = maybe_robust(gtsam.noiseModel.Diagonal.Sigmas(np.array([free, free, p.plane.sigma_plane])))
        for pt in np.flatnonzero(_two_view_points(p, active) & p.floor):
            x, y = p.points_w[pt, :2]  # the initial position along the floor (free)
            graph.add(gtsam.PriorFactorPoint3(L(int(pt)), np.array([x, y, 0.0]), on_floor))
        height = gtsam.noiseModel.Diagonal.Sigmas(np.array([free, free, p.plane.sigma_height]))
        for k in range(p.n_kf):
            x, y = p.T_rigid[k, :2, 3]
            graph.add(gtsam.PoseTranslationPrior3D(X(k), np.array([x, y, float(p.plane.height)]), height))
    return graph


def _values(T_w_kf: F64, points_w: F64, used: BoolArray) -> gtsam.Values:
    values = gtsam.Values()
    for k in range(T_w_kf.shape[0]):
        values.insert(X(k), gtsam.Pose3(T_w_kf[k]))
    for j in np.flatnonzero(used):
        values.insert(L(int(j)), np.ascontiguousarray(points_w[j]))
    return values


def _lm_params(max_iterations: int) -> gtsam.LevenbergMarquardtParams:
    """Every parameter the result depends on, set explicitly."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(LM_RELATIVE_TOL)
    params.setAbsoluteErrorTol(LM_ABSOLUTE_TOL)
    params.setErrorTol(0.0)
    params.setOrderingType("COLAMD")
    params.setLinearSolverType("MULTIFRONTAL_CHOLESKY")
    params.setlambdaInitial(1e-5)
    params.setlambdaFactor(10.0)
    params.setlambdaLowerBound(0.0)
    params.setlambdaUpperBound(1e5)
    params.setDiagonalDamping(False)
    params.setUseFixedLambdaFactor(True)
    params.setVerbosityLM("SILENT")
    params.setVerbosity("SILENT")
    return params


def _estimates(p: _Problem, values: gtsam.Values, used: BoolArray) -> tuple[F64, F64]:
    T_w_kf = np.stack([values.atPose3(X(k)).matrix() for k in range(p.n_kf)])
    points_w = np.full((p.n_points, 3), np.nan)
    for j in np.flatnonzero(used):
        points_w[j] = values.atPoint3(L(int(j)))
    return T_w_kf, points_w


def _solve(p: _Problem) -> tuple[F64, F64, BoolArray, F64, int, float, float, F64 | None] | None:
    """The window solved in ``w``, or with a plane prior in the floor frame and moved back (see the module
    docstring)."""
    if p.plane is None:
        solved = _solve_in(p)
        if solved is None:
            return None
        T_w_kf, points_w, active, cov, iterations, err0, err1 = solved
        return (T_w_kf, points_w, active, floored(world_covariance(cov, T_w_kf[-1, :3, :3])), iterations, err0, err1,
                None)
    active = _initial_active(p)
    if not _usable(p, active):
        return None
    plane0 = _fit_plane(p, np.where(np.isfinite(p.points_w), p.points_w, 0.0), _two_view_points(p, active))
    if plane0 is None:
        return None
    T_F_w = _floor_frame(p.T_rigid[0], plane0)
    T_F_kf = np.einsum("ij,kjl->kil", T_F_w, p.T_rigid)
    in_floor = replace(p, T_w_kf=T_F_kf, T_rigid=T_F_kf, points_w=p.points_w @ T_F_w[:3, :3].T + T_F_w[:3, 3])
    solved = _solve_in(in_floor)
    if solved is None:
        return None
    T_F_kf, points_F, active, cov, iterations, err0, err1 = solved
    G = p.T_rigid[0] @ invert_T(T_F_kf[0])  # F -> w with keyframe 0 where it was given
    T_w_kf = np.einsum("ij,kjl->kil", G, T_F_kf)
    T_w_kf[: p.n_fixed] = p.T_w_kf[: p.n_fixed]
    n_w = G[:3, 2]
    plane_w = np.array([*n_w, -float(n_w @ G[:3, 3])])
    return (T_w_kf, points_F @ G[:3, :3].T + G[:3, 3], active, floored(world_covariance(cov, T_w_kf[-1, :3, :3])),
            iterations, err0, err1, plane_w)


def _newest_covariance(p: _Problem, marginals: gtsam.Marginals, T_w_kf: F64) -> F64:
    """The newest keyframe's covariance relative to keyframe 0 in GTSAM's tangent space (its body frame).
    With keyframe 0 held by the gauge it is the newest one's marginal; in the floor frame, where keyframe
    0 is free in height, roll and pitch, xi_rel = xi_n - Ad(T_0n^-1) xi_0 of their joint marginal."""
    newest = p.n_kf - 1
    if p.plane is None:
        return np.asarray(marginals.marginalCovariance(X(newest)), dtype=np.float64)
    joint = marginals.jointMarginalCovariance(gtsam.KeyVector([X(0), X(newest)])).fullMatrix()
    T_0n = gtsam.Pose3(invert_T(T_w_kf[0]) @ T_w_kf[newest])
    J = np.hstack([-T_0n.inverse().AdjointMap(), np.eye(6)])
    return J @ joint @ J.T


def _solve_in(p: _Problem) -> tuple[F64, F64, BoolArray, F64, int, float, float] | None:
    active = _initial_active(p)
    if not _usable(p, active):
        return None
    T_w_kf = p.T_rigid
    points_w = np.where(np.isfinite(p.points_w), p.points_w, 0.0)
    z, _ = _depths_and_residuals(p, T_w_kf, points_w, active)
    gauge_sigmas = (GAUGE_FRACTION * p.sigma_n, GAUGE_FRACTION * p.sigma_n * float(np.median(z)))
    T_start, points_start = T_w_kf, points_w
    iterations = 0
    for _ in range(MAX_PASSES):
        used = _two_view_points(p, active)
        graph = _graph(p, active, robust=True, gauge_sigmas=gauge_sigmas)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, _values(T_w_kf, points_w, used),
                                                      _lm_params(p.max_iterations))
        result = optimizer.optimize()
        iterations += int(optimizer.iterations())
        T_w_kf, points_w = _estimates(p, result, used)
        points_w = np.where(used[:, None], points_w, 0.0)
        if not (np.all(np.isfinite(T_w_kf)) and np.all(np.isfinite(points_w))):
            return None
        kept = _gate(p, T_w_kf, points_w, active)
        changed = not np.array_equal(kept, active)
        active = kept
        if not _usable(p, active):
            return None
        if not changed:
            break
    used = _two_view_points(p, active)
    gaussian = _graph(p, active, robust=False, gauge_sigmas=gauge_sigmas)
    final = _values(T_w_kf, points_w, used)
    cov = _newest_covariance(p, gtsam.Marginals(gaussian, final), T_w_kf)  # tangent: ``_solve`` converts
    err0 = float(gaussian.error(_values(T_start, points_start, used)))
    err1 = float(gaussian.error(final))
    points_w = np.where(used[:, None], points_w, np.nan)
    if not (np.all(np.isfinite(cov)) and math.isfinite(err0) and math.isfinite(err1)):
        return None
    if p.plane is None:
        T_w_kf[: p.n_fixed] = p.T_w_kf[: p.n_fixed]  # held fixed (moved < the gauge sigmas): returned as given
    return T_w_kf, points_w, active, cov, iterations, err0, err1
