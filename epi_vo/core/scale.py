"""The scale stage: what length a monocular map's translation gets, and whether it is metres.

Translation is observable only up to one global scale (see ``epi_vo.core.pipeline``). ``scale_source``
chooses where the length comes from:

``none`` (:class:`VoUnitsScale`)
    VO units: the first map's keyframe baseline has length 1; a map rebuilt after tracking was lost
    continues the old units by assuming the last keyframe speed. Nothing is metric.
``ground_plane`` (:class:`GroundPlaneScale`)
    The floor among each keyframe's map points (robust plane fit restricted to plausible floor
    normals, :func:`fit_ground_plane`) gives the camera's height in map units; ``camera_height_m`` over
    it is a measurement of the map's scale error. The camera's pitch and roll to the floor come with it.
``wheel_odometry`` (:class:`WheelOdometryScale`)
    The distance the wheels travelled between two keyframes (positions interpolated at the image
    stamps) over the VO's own step length. Only distances are used: the VO keeps its rotation and never
    takes the wheels' heading (or its drift).

Both metric sources feed the same filter (:class:`ScaleFilter`): a 1-D Kalman filter on the log of
the map's scale error, with the VO's scale drift per keyframe as process noise; the window of recent
measurements judges outliers and says how noisy the measurements are. At a keyframe the pipeline asks
:meth:`ScaleSource.correction` for the factor that takes the step from the last keyframe, and the new
keyframe's map, into metres; without a measurement the factor is 1 and the uncertainty grows. Metric
scale is established once enough measurements agree: until then the pipeline publishes the position
held where the map started, with a covariance that says the scale is unknown.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.config import VoConfig

# re-exported: callers name the wheel buffer through the scale stage
from epi_vo.core.wheel_odometry import WheelInputCounts as WheelInputCounts
from epi_vo.core.wheel_odometry import WheelOdometry as WheelOdometry
from epi_vo.core.wheel_odometry import WheelSample as WheelSample

F64 = NDArray[np.float64]

SCALE_SOURCES = ("none", "ground_plane", "wheel_odometry")
# Measurements the scale filter's window keeps. Consecutive keyframes measure the floor on many of the
# same map points, so their errors are shared: a short window sees few independent maps, its spread
# understates the noise and its median carries their common error (KITTI 06 with ground_plane, window
# 7 -> 15: the early maps' 7 % too high scale is corrected sooner, Sim(3) ATE 0.60 -> 0.43 %; the
# ground-robot bag's figures are unchanged).
SCALE_WINDOW = 15
SMALL_WINDOW = 7  # fewer measurements than this: their sample variance bounds their noise from below
# The least noise one floor measurement is given (relative, 1 sigma): the window's spread of the fits says
# how noisy they are; below this it is not trusted. Until 2026-11-27 this was 2 %, which set the filter's
# noise on the renders, where the fits spread by 0.37 % (the window's MAD, median over ground_robot's 129
# measurements; the scale's error after a measurement 0.22 %): it claimed 1.25 % for the scale,
# `ground_plane` position NEES 0.27. KITTI's fits spread by 5-9 %, so the window sets its noise either way.
GROUND_FIT_MIN_REL_STD = 0.005
# Two floor fits establish metric scale only when their normals agree within this (deg): the camera's
# mounting does not change between keyframes, a wrong plane's normal does. KITTI 06 replayed from frame 5:
# the first fit leaned 24 deg (pitch 23.9 against 0.7-2.2 after it), the second established the scale with
# it at 0.41 of the truth, and the filter needed 25 frames to recover (step scale 0.58, SE(3)-only ATE 10 %).
FLOOR_AGREE_DEG = 10.0
# The wheels' random error over one scale measurement (m, 1 sigma): the noise that averages out over
# keyframes. Their calibration error (tyre radius), which does not, is ``wheel_odometry_rel_sigma`` and is
# carried once, as the source's systematic error (``ScaleSource.systematic_rel``).
WHEEL_NOISE_M = 0.01



@dataclass(frozen=True)
class ScaleStatus:
    """What a frame's record and diagnostics say about scale.

    ``scale`` is metres per VO unit of the first map (1.0 for ``none``: VO units); ``rel_std`` the
    relative standard deviation of the current map's scale (NaN for ``none``: unknown, not measured);
    ``metric`` whether positions are metres; pitch/roll of the camera to the floor in degrees (ground
    plane only, NaN otherwise); ``reason`` why the source gave no measurement at the last keyframe.
    """

    source: str = "none"
    metric: bool = False
    scale: float = 1.0
    rel_std: float = math.nan
    floor_pitch_deg: float = math.nan
    floor_roll_deg: float = math.nan
    reason: str = ""
    wheel: WheelInputCounts | None = None  # wheel_odometry: the messages received and what became of them

    @property
    def units(self) -> str:
        """'m' when positions are metres, 'vo' for VO units."""
        return "m" if self.metric else "vo"


@dataclass(frozen=True)
class KeyframeStep:
    """A keyframe step as the scale stage sees it: map points of the new keyframe (its camera frame),
    the step's camera-centre chord in map units, and the two stamps."""

    X_cur: F64  # (N, 3) map points in the new keyframe's camera frame, NaN rows: no depth
    step_length: float  # |c_cur - c_kf| in the current map units
    kf_stamp_ns: int
    stamp_ns: int


@dataclass(frozen=True)
class GroundPlane:
    """The floor in a camera frame: points X on it satisfy ``normal_up . X = -height``."""

    normal_up: F64  # unit normal pointing from the floor towards the camera (camera frame)
    height: float  # camera centre above the floor, map units
    n_inliers: int
    rel_std: float  # relative standard deviation of ``height``

    @property
    def pitch_deg(self) -> float:
        """Angle of the optical axis below the floor's horizon (positive: looking down)."""
        n = self.normal_up
        return math.degrees(math.atan2(-n[2], math.hypot(n[0], n[1])))

    @property
    def roll_deg(self) -> float:
        """Rotation about the optical axis relative to the floor, right-handed about z (x towards y):
        positive when the image's right side is lower than its left."""
        n = self.normal_up
        return math.degrees(math.atan2(-n[0], -n[1]))


@dataclass(frozen=True)
class FloorSearch:
    """What :func:`find_floor` found: the floor, or why there is none.

    ``n_candidates`` planes had a normal within the tilt of ``up`` with the camera on their upper side;
    ``n_unsupported`` of them had at least as many map points well beneath them as on them, and
    ``best_unsupported`` is the (on, beneath) count of the one with most points on it ((0, 0): none).
    """

    plane: GroundPlane | None
    n_points: int
    n_candidates: int = 0
    n_unsupported: int = 0
    best_unsupported: tuple[int, int] = (0, 0)


# A map point is beneath a floor candidate when it lies further than this fraction of the candidate's
# height through it: the floor's own points scatter within ``ground_inlier_ratio`` (a few %) of it.
BENEATH_FLOOR = 0.2
LEVEL_UP = np.array([0.0, -1.0, 0.0])  # a level camera's up axis in its optical frame (y down)
LEVEL_UP.setflags(write=False)


def find_floor(X: F64, *, max_tilt_deg: float, inlier_ratio: float, min_points: int,
               up: F64 | None = None, iterations: int = 200) -> FloorSearch:
    """The floor among map points ``X`` (camera frame, x right, y down, z forward), and why not.

    Deterministic RANSAC over 3-point planes whose upward normal is within ``max_tilt_deg`` of ``up``
    (a unit vector in the camera frame: the declared mounting's up, default a level camera's -y) and
    that lie below the camera; inliers are within ``inlier_ratio`` of the candidate's height.

    The floor carries the scene: every surface the camera sees stands on it, so map points beneath it
    are errors and few. A candidate with at least as many points well beneath it (``BENEATH_FLOOR``) as
    on it is no floor: a plane through objects (a table, a car's roof, a wall's foot), or, when the
    camera is not mounted as declared (upside down, the floor above), whatever surface lies on the
    declared floor's side. Among the others, points beneath count against a candidate twice. The best
    plane is refit by least squares on its inliers; its height is the median inlier height and its
    relative spread that of a median (1.25 MAD / sqrt(n)).
    """
    X = X[np.all(np.isfinite(X), axis=1)]
    n_pts = X.shape[0]
    if n_pts < max(min_points, 3):
        return FloorSearch(None, n_pts)
    up = LEVEL_UP if up is None else up
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    rng = np.random.default_rng(12345)  # fixed: replay stays deterministic
    idx = rng.integers(0, n_pts, size=(iterations, 3))
    A, B, C = X[idx[:, 0]], X[idx[:, 1]], X[idx[:, 2]]
    N = np.cross(B - A, C - A)
    norm = np.linalg.norm(N, axis=1)
    ok = norm > 1e-12
    N = N[ok] / norm[ok, None]
    A = A[ok]
    N *= np.where(N @ up < 0, -1.0, 1.0)[:, None]
    h = -np.einsum("ij,ij->i", N, A)
    ok = (N @ up >= cos_tilt) & (h > 0)
    if not np.any(ok):
        return FloorSearch(None, n_pts)
    N, h = N[ok], h[ok]
    # einsum, not BLAS: OpenBLAS's worker threads keep spinning after a call and slow the next
    # frame's OpenCV work on a small CPU (measured: KLT +2 ms per frame on 2 cores).
    D = np.einsum("ij,kj->ik", X, N) + h  # signed distances, positive towards the camera
    inliers = np.abs(D) < inlier_ratio * h
    n_on, n_beneath = inliers.sum(axis=0), (D < -BENEATH_FLOOR * h).sum(axis=0)
    carried = n_beneath < n_on
    search = FloorSearch(None, n_pts, int(N.shape[0]), int(np.count_nonzero(~carried)))
    if not np.all(carried):
        most = int(np.argmax(np.where(carried, -1, n_on)))
        search = dataclasses.replace(search, best_unsupported=(int(n_on[most]), int(n_beneath[most])))
    if not np.any(carried):
        return search
    score = np.where(carried, n_on - 2 * n_beneath, np.iinfo(np.int64).min)
    best = int(np.argmax(score))
    if int(n_on[best]) < min_points:
        return search
    P = X[inliers[:, best]]
    centroid = P.mean(axis=0)
    Q = P - centroid
    _, vecs = np.linalg.eigh(np.einsum("ij,ik->jk", Q, Q))  # 3x3 scatter: no BLAS threads
    n = vecs[:, 0]  # smallest eigenvalue: the plane's normal
    if n @ up < 0:
        n = -n
    if n @ up < cos_tilt:
        return search
    heights = -(P @ n)
    h_med = float(np.median(heights))
    if not h_med > 0:
        return search
    mad = float(np.median(np.abs(heights - h_med)))
    rel_std = 1.253 * 1.4826 * mad / h_med / math.sqrt(P.shape[0])
    return dataclasses.replace(search, plane=GroundPlane(n, h_med, int(P.shape[0]), rel_std))


def fit_ground_plane(X: F64, *, max_tilt_deg: float, inlier_ratio: float, min_points: int,
                     up: F64 | None = None, iterations: int = 200) -> GroundPlane | None:
    """The floor among map points ``X`` (:func:`find_floor`), or None."""
    return find_floor(X, max_tilt_deg=max_tilt_deg, inlier_ratio=inlier_ratio, min_points=min_points, up=up,
                      iterations=iterations).plane


@dataclass(frozen=True)
class WindowAnchor:
    """A keyframe's metric anchor for the windowed bundle adjustment: the wheel odometry position at its
    stamp with the relative sigma of wheel distances (``wheel_odometry``). The floor gives none: the scale
    filter owns ``ground_plane``'s scale and the window follows its corrections (``window``)."""

    wheel_xyz: F64 | None = None
    wheel_rel_sigma: float = math.nan


class ScaleFilter:
    """Robust filter of the current map's scale error, in log space.

    Each keyframe's measurement z = log(true / map) goes into a window of the last ``window`` ones (kept
    relative to the map as it is now: a correction applied shifts them all). The window's median and
    MAD judge the newest (beyond 3 sigma: an outlier, not applied) and give the measurement noise; a
    1-D Kalman filter whose process noise is the VO's scale drift per keyframe takes each measurement
    once. Metric scale is established once ``min_count`` measurements are in the window: the first
    correction is their median.
    """

    def __init__(self, drift_per_keyframe: float, window: int = SCALE_WINDOW, min_count: int = 2) -> None:
        self.q = drift_per_keyframe**2
        self.window: deque[tuple[float, float]] = deque(maxlen=window)  # (z, its variance)
        self.min_count = min_count
        self.var = math.inf
        self.total = 1.0  # product of every correction: metres per VO unit of the first map
        self.outlier = False  # the last measurement was judged an outlier by the window

    @property
    def established(self) -> bool:
        return math.isfinite(self.var)

    @property
    def rel_std(self) -> float:
        return math.sqrt(self.var) if self.established else math.nan

    def predict(self) -> None:
        if self.established:
            self.var += self.q

    def inflate(self, rel_std: float) -> None:
        """The map's scale became uncertain by ``rel_std`` (1 sigma) more: a map rebuilt after a loss."""
        if self.established:
            self.var += rel_std**2
        self.window.clear()

    def update(self, z: float, r: float) -> float:
        """Fold in one measurement; the correction factor to apply to the map (1.0 while not established).

        The window's median and MAD judge the new measurement (an outlier is dropped) and say how noisy
        the measurements really are; the filter then takes this one measurement with that noise, so a
        measurement counts once however long it stays in the window.
        """
        self.window.append((z, r))
        self.outlier = False
        if len(self.window) < self.min_count:
            return 1.0
        zs = np.array([w[0] for w in self.window])
        med = float(np.median(zs))
        n = zs.size
        mad_var = (1.4826 * float(np.median(np.abs(zs - med)))) ** 2
        r_eff = max(mad_var, r)
        if n < SMALL_WINDOW:
            # A few measurements' MAD is no estimate of their spread: with 3, two that agree by chance
            # gave KITTI's floor 4 % where its fits scatter by 10-20 %, and the map ran 7 % long for 20
            # frames (Sim(3) ATE 0.36 %, now 0.11 %). Their sample variance is the floor.
            # Without the newest: a wild one (a wall taken for the floor) must not widen its own gate.
            r_eff = max(r_eff, float(np.var(zs[:-1] if n > 2 else zs, ddof=1)))
        if not self.established:
            self.var = 1.57 * r_eff / n
            log_c = med
        else:
            if n >= 3 and (z - med) ** 2 > 9.0 * r_eff:
                self.outlier = True  # kept in the window (it may be the start of a change), not applied
                return 1.0
            gain = self.var / (self.var + r_eff)
            self.var = (1.0 - gain) * self.var
            log_c = gain * z
        self.window = deque(((x - log_c, v) for x, v in self.window), maxlen=self.window.maxlen)
        factor = math.exp(log_c)
        self.total *= factor
        return factor


class ScaleSource:
    """Common interface of the scale sources; ``VoUnitsScale`` is the plain one."""

    name = "none"
    metric_source = False

    def __init__(self, drift_per_keyframe: float = 0.02) -> None:
        self.speed: float | None = None  # map units per second at the last keyframe
        self.filter = ScaleFilter(drift_per_keyframe)
        self.reason = ""
        self.plane: GroundPlane | None = None
        # The source's own error common to all its measurements (a calibration): it does not average
        # out over keyframes; an error of the scale it gives runs along the whole metric path.
        self.systematic_rel = 0.0
        self.up = LEVEL_UP  # the declared mounting's up in the camera frame (``set_mounting_up``)

    def set_mounting_up(self, up: F64) -> None:
        """The declared mounting's up direction in the camera optical frame (the floor's normal when the
        robot stands level); default a level camera's -y. Only the floor uses it."""
        up = np.asarray(up, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(up))
        if not (math.isfinite(norm) and norm > 0):
            raise ValueError(f"the mounting's up direction must be a finite non-zero vector, got {up}")
        self.up = up / norm

    @property
    def rel_std(self) -> float:
        """Relative standard deviation of the current scale: the filter's, and the source's systematic
        part (NaN while not established)."""
        return math.hypot(self.filter.rel_std, self.systematic_rel)

    @property
    def established(self) -> bool:
        """Positions are metres (a metric measurement has been taken)."""
        return self.metric_source and self.filter.established

    @property
    def held(self) -> str:
        """What happens to the scale while the source gives no measurement (for the reason)."""
        return "last scale held" if self.filter.established else "scale unknown (VO units)"

    def status(self) -> ScaleStatus:
        plane = self.plane
        return ScaleStatus(self.name, self.established, self.filter.total, self.rel_std,
                           plane.pitch_deg if plane is not None else math.nan,
                           plane.roll_deg if plane is not None else math.nan, self.reason)

    def on_new_map(self) -> None:
        """A map was (re)built: after a loss its baseline came from the last speed, so its scale is
        uncertain again (30 %, 1 sigma)."""
        self.filter.inflate(0.3)

    def on_keyframe(self, step_length: float, dt_s: float) -> None:
        """A keyframe step of ``step_length`` map units over ``dt_s`` seconds was taken."""
        if dt_s > 0:
            self.speed = step_length / dt_s

    def initial_baseline(self, dt_s: float) -> float:
        """Length given to the first keyframe baseline of a new map, ``dt_s`` after its keyframe."""
        if self.speed is None or dt_s <= 0.0:
            return 1.0
        return self.speed * dt_s

    def correction(self, step: KeyframeStep) -> float:
        """The factor taking this keyframe step and its map into metres (1.0: no measurement)."""
        self.filter.predict()
        measured = self.measure(step)
        if measured is None:
            return 1.0
        z, r = measured
        factor = self.filter.update(z, r)
        self.on_corrected(factor)
        if not self.filter.established:
            self.reason = (f"{len(self.filter.window)} of {self.filter.min_count} scale measurements needed to "
                           "establish metric scale: VO units")
        return factor

    def measure(self, step: KeyframeStep) -> tuple[float, float] | None:
        """(log(true / map) scale, its variance) at this keyframe, or None with ``self.reason`` set."""
        return None

    def on_corrected(self, factor: float) -> None:
        """The map was just scaled by ``factor`` (1.0: unchanged)."""

    def anchor(self, step: KeyframeStep) -> WindowAnchor | None:
        """What this source knows in metres about the keyframe of ``step`` (after its correction), for
        the windowed bundle adjustment's scale priors; None: nothing (or no metric scale yet)."""
        return None


class VoUnitsScale(ScaleSource):
    """Scale in VO units: baseline 1 for the first map, then the last keyframe speed carries it on."""


class GroundPlaneScale(ScaleSource):
    """Metric scale from the floor: ``camera_height_m`` over the floor's distance in map units."""

    name = "ground_plane"
    metric_source = True

    def __init__(self, camera_height_m: float, drift_per_keyframe: float, *, max_tilt_deg: float,
                 inlier_ratio: float, min_points: int, height_rel_sigma: float = 0.0) -> None:
        super().__init__(drift_per_keyframe)
        self.camera_height_m = camera_height_m
        self.systematic_rel = height_rel_sigma
        self.max_tilt_deg = max_tilt_deg
        self.inlier_ratio = inlier_ratio
        self.min_points = min_points
        self.reason = "ground plane not seen yet: scale unknown (VO units)"
        self._normals: deque[F64] = deque(maxlen=7)
        self._waiting: list[tuple[F64, float, float]] = []  # fits before metric scale: (normal, z, r)

    def on_new_map(self) -> None:
        super().on_new_map()
        self._waiting.clear()

    def correction(self, step: KeyframeStep) -> float:
        """As ``ScaleSource.correction``, but before metric scale is established a fit waits until another
        fit's normal agrees with its own (``FLOOR_AGREE_DEG``); fits that agree with none are dropped then."""
        if self.filter.established:
            return super().correction(step)
        measured = self.measure(step)
        if measured is None:
            return 1.0
        normal = self._normals[-1]
        cos = math.cos(math.radians(FLOOR_AGREE_DEG))
        agree = [w for w in self._waiting if float(w[0] @ normal) >= cos]
        if not agree:
            self._waiting.append((normal, *measured))
            self.reason = (f"{len(self._waiting)} floor fit(s), no two with normals within {FLOOR_AGREE_DEG:g} deg: "
                           "metric scale waits for two that agree (VO units)")
            return 1.0
        self._waiting.clear()
        self._normals = deque([w[0] for w in agree] + [normal], maxlen=self._normals.maxlen)
        factor = 1.0
        for _, z, r in [*agree, (normal, *measured)]:
            factor *= self.filter.update(z, r)
        self.on_corrected(factor)
        return factor

    def set_mounting_up(self, up: F64) -> None:
        """The floor's normal the declared mounting implies (unit vector, camera optical frame): the camera's
        up when the robot stands level. The fits seen so far were judged against another: forgotten."""
        super().set_mounting_up(up)
        self._normals.clear()
        self._waiting.clear()

    def _expected_up(self) -> tuple[F64, float]:
        """The floor normal seen over the last keyframes (the camera's mounting changes little), and how
        far a new fit may lie from it; before three fits, the declared up and ``max_tilt_deg``."""
        if len(self._normals) < 3:
            return self.up, self.max_tilt_deg
        n = np.median(np.array(self._normals), axis=0)
        return n / np.linalg.norm(n), min(10.0, self.max_tilt_deg)

    def measure(self, step: KeyframeStep) -> tuple[float, float] | None:
        up, tilt = self._expected_up()
        search = find_floor(step.X_cur, max_tilt_deg=tilt, inlier_ratio=self.inlier_ratio,
                            min_points=self.min_points, up=up)
        plane = search.plane
        if plane is not None and float(plane.normal_up @ self.up) < math.cos(math.radians(self.max_tilt_deg)):
            self.reason = (f"the floor seen so far leans more than {self.max_tilt_deg:g} deg from the declared "
                           f"mounting's up: no floor, {self.held}")
            return None
        if plane is None:
            where = "of the mounting's up" if len(self._normals) < 3 else "of the floor seen so far"
            self.reason = f"no floor plane among {search.n_points} map points"
            on, beneath = search.best_unsupported
            if on >= self.min_points:
                self.reason += (f": the largest plane within {tilt:g} deg {where} and below the camera holds {on} "
                                f"and has {beneath} well beneath it; the floor carries the scene (is the camera "
                                "mounted as declared?)")
            else:
                self.reason += f" (need {self.min_points} within {tilt:g} deg {where})"
            self.reason += f": {self.held}"
            return None
        from_history = len(self._normals) >= 3
        self._normals.append(plane.normal_up)
        if from_history:
            # The floor's direction is known better from the last keyframes than from this one's few
            # points: measure the height of this fit's inliers along it.
            X = step.X_cur[np.all(np.isfinite(step.X_cur), axis=1)]
            on = np.abs(X @ plane.normal_up + plane.height) < self.inlier_ratio * plane.height
            plane = GroundPlane(up, float(np.median(-(X[on] @ up))), plane.n_inliers, plane.rel_std)
            if not plane.height > 0:
                self.reason = "floor plane above the camera: ignored"
                return None
        self.plane = plane
        self.reason = ""
        # The fit's own standard error, at least GROUND_FIT_MIN_REL_STD; the filter's window raises it to
        # the fits' spread.
        r = plane.rel_std**2 + GROUND_FIT_MIN_REL_STD**2
        return math.log(self.camera_height_m / plane.height), r


class WheelOdometryScale(ScaleSource):
    """Metric scale from the distance the wheels travelled over the last keyframe steps.

    Keyframes can be a few centimetres apart (a floor close to the camera makes parallax fast), where
    wheel noise and the camera's lever arm in turns dominate one step. So each measurement spans the
    most recent keyframe steps until the wheels covered ``window_m``: the sum of their wheel chords over
    the sum of their VO step lengths (kept in the current map's units as corrections are applied).
    """

    name = "wheel_odometry"
    metric_source = True

    def __init__(self, wheel: WheelOdometry, drift_per_keyframe: float, *, rel_sigma: float,
                 timeout_s: float, window_m: float = 0.5) -> None:
        super().__init__(drift_per_keyframe)
        self.wheel = wheel
        self.rel_sigma = rel_sigma
        self.systematic_rel = rel_sigma
        self.timeout_ns = int(timeout_s * 1e9)
        self.window_m = window_m
        self._steps: deque[list[float]] = deque(maxlen=500)  # [kf stamp, stamp, VO step length]
        self.reason = "no keyframe step measured by the wheels yet: scale unknown (VO units)"

    def on_corrected(self, factor: float) -> None:
        for step in self._steps:
            step[2] *= factor

    def status(self) -> ScaleStatus:
        return dataclasses.replace(super().status(), wheel=self.wheel.counts)

    def anchor(self, step: KeyframeStep) -> WindowAnchor | None:
        if not self.established:
            return None
        xyz, _ = self.wheel.position_at(step.stamp_ns, self.timeout_ns)
        return None if xyz is None else WindowAnchor(wheel_xyz=xyz, wheel_rel_sigma=self.rel_sigma)

    def measure(self, step: KeyframeStep) -> tuple[float, float] | None:
        self._steps.append([step.kf_stamp_ns, step.stamp_ns, step.step_length])
        d_wheel = d_vo = 0.0
        n = 0
        for t0, t1, length in reversed(self._steps):
            p0, why0 = self.wheel.position_at(int(t0), self.timeout_ns)
            p1, why1 = self.wheel.position_at(int(t1), self.timeout_ns)
            if p0 is None or p1 is None:
                if n == 0:
                    self.reason = f"{why0 or why1}: {self.held}"
                    return None
                break
            d_wheel += float(np.linalg.norm(p1 - p0))
            d_vo += length
            n += 1
            if d_wheel >= self.window_m:
                break
        if d_wheel < self.window_m or not d_vo > 0:
            self.reason = (f"wheels moved {d_wheel:.3f} m over the last {n} keyframe step(s) (< {self.window_m} m): "
                           f"{self.held}")
            return None
        self.reason = ""
        # Only the wheels' random part: their calibration error is common to every measurement, the
        # source's systematic error (counted in both until 2026-11-27: `wheel_odometry` position NEES
        # 0.55, now 0.77; Sim(3) ATE 0.031 -> 0.029 %).
        r = (WHEEL_NOISE_M / d_wheel) ** 2
        return math.log(d_wheel / d_vo), r


def source_from_config(cfg: VoConfig, wheel: WheelOdometry) -> ScaleSource:
    """The scale source ``cfg.scale_source`` names."""
    drift = cfg.scale_drift_per_keyframe
    if cfg.scale_source == "ground_plane":
        return GroundPlaneScale(cfg.camera_height_m, drift, max_tilt_deg=cfg.ground_max_tilt_deg,
                                inlier_ratio=cfg.ground_inlier_ratio, min_points=cfg.ground_min_points,
                                height_rel_sigma=cfg.camera_height_rel_sigma)
    if cfg.scale_source == "wheel_odometry":
        return WheelOdometryScale(wheel, drift, rel_sigma=cfg.wheel_odometry_rel_sigma,
                                  timeout_s=cfg.wheel_odometry_timeout_s)
    return VoUnitsScale(drift)
