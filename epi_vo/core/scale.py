"""The scale stage: what length a monocular map's translation gets, and whether it is metres.

Translation is observable only up to one global scale (see ``epi_vo.core.pipeline``). ``scale_source``
chooses where the length comes from:

``none`` (:class:`VoUnitsScale`)
    VO units: the first map's keyframe baseline has length 1; a map rebuilt after tracking was lost
    continues the old units by assuming the last keyframe speed. Nothing is metric.
``ground_plane`` (:class:`GroundPlaneScale`)
    The floor among each keyframe's map points (robust plane fit restricted to plausible floor
    normals, ``epi_vo.core.floor``) gives the camera's height in map units; ``camera_height_m`` over
    it is a measurement of the map's scale error. The camera's pitch and roll to the floor come with it.
``wheel_odometry`` (:class:`WheelOdometryScale`)
    The distance the wheels travelled between two keyframes (positions interpolated at the image
    stamps) over the VO's own step length. Only distances are used: the VO keeps its rotation and never
    takes the wheels' heading (or its drift).

Both metric sources feed the same filter (:class:`ScaleFilter`): a 1-D Kalman filter on the log of
the map's scale error, with the VO's scale drift per keyframe as process noise; the window of recent
measurements judges outliers, says how noisy the measurements are, and bounds how sure the filter may be
(no surer than the mean of the window's measurements). At a keyframe the pipeline asks
:meth:`ScaleSource.correction` for the factor that takes the step from the last keyframe, and the new
keyframe's map, into metres; without a measurement the factor is 1 and the uncertainty grows.

A source and what it remembers (the filter, the last speed, the floor normals seen, the wheel steps) is
one frozen value: every call that learns something returns the source after it, which the pipeline's
state takes in place of the old one. Metric
scale is established once enough measurements agree: until then the pipeline publishes the position
held where the map started, with a covariance that says the scale is unknown.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field
from typing import ClassVar, Self

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.camera import CameraModel
from epi_vo.core.config import ScaleSourceKind, VoConfig
from epi_vo.core.floor import LEVEL_UP, GroundPlane, find_floor
from epi_vo.core.floor_view import FloorView, floor_between

# re-exported: callers name the wheel buffer through the scale stage
from epi_vo.core.wheel_odometry import WheelInputCounts as WheelInputCounts
from epi_vo.core.wheel_odometry import WheelOdometry as WheelOdometry
from epi_vo.core.wheel_odometry import WheelSample as WheelSample

F64 = NDArray[np.float64]

# Measurements the scale filter's window keeps. Consecutive keyframes measure the floor on many of the
# same map points, so their errors are shared: the window must span enough keyframes to hold several
# independent maps, or its spread understates the noise and its median carries their common error.
SCALE_WINDOW = 15
# Fewer measurements than this: their MAD is no estimate of their spread, their sample variance bounds the
# noise from below (``ScaleFilter.updated``).
SMALL_WINDOW = 7
# Earlier measurements of one kind of fit (the floor among the map points, its homography between the images)
# needed before the kind's own scatter in the window weighs its next one: fewer say nothing of it, and the
# window's overall spread stands for it.
KIND_MIN_FITS = 3
# A floor seen from one mounting keeps its normal between keyframes within this (deg), a wrong plane's does
# not: two fits establish metric scale only when their normals agree within it, and once FLOOR_STEADY_FITS
# fits are in, a new fit is sought within it of their median normal.
FLOOR_STEADY_DEG = 10.0
FLOOR_STEADY_FITS = 3
FLOOR_HISTORY = 7  # floor normals remembered (their median is the floor seen so far)
WHEEL_STEPS = 500  # keyframe steps remembered for the wheel measurement (it needs the last few)
# Measurements in a row beyond the window's 3-sigma gate on one side: the map's scale changed (a VO scale jump),
# no outlier. Three fall there by chance once in ~10^8 (0.00135^3); the map then takes their median at once.
SCALE_CHANGE_RUN = 3
# The last measurements whose mean shows a change of the map's scale the filter has not followed (``updated``):
# as many as make a jump, enough that their noise rarely mimics a change (the mean of three is known to
# 1/sqrt(3) of one), few enough that the map follows a drift within a few keyframes.
SCALE_TREND_RUN = SCALE_CHANGE_RUN
# A map rebuilt after a loss takes its baseline from the last keyframe speed over the time since its
# keyframe: its scale is that uncertain (relative, 1 sigma) until a scale source measures it.
NEW_MAP_REL_STD = 0.3


# The kinds of scale measurement, each with its own noise (``ScaleFilter.updated``): the floor among a keyframe's
# map points, the floor's homography between two keyframes' images, the wheels' distance.
FIT_POINTS = "points"
FIT_VIEW = "view"
FIT_WHEELS = "wheels"
Measured = tuple[float, float, str]  # log(true / map) scale, its variance, the kind of fit


class Units(enum.StrEnum):
    """What a length is measured in."""

    METRES = "m"  # a metric scale source is established
    VO = "vo"  # VO units: the first map's keyframe baseline is 1


@dataclass(frozen=True)
class ScaleStatus:
    """What a frame's record and diagnostics say about scale.

    ``scale`` is metres per VO unit of the first map (1.0 for ``none``: VO units); ``rel_std`` the
    relative standard deviation of the current map's scale (NaN for ``none``: unknown, not measured);
    ``metric`` whether positions are metres; pitch/roll of the camera to the floor in degrees (ground
    plane only, NaN otherwise); ``reason`` why the source gave no measurement at the last keyframe.
    """

    source: ScaleSourceKind = ScaleSourceKind.NONE
    metric: bool = False
    scale: float = 1.0
    rel_std: float = math.nan
    floor_pitch_deg: float = math.nan
    floor_roll_deg: float = math.nan
    reason: str = ""
    wheel: WheelInputCounts | None = None  # wheel_odometry: the messages received and what became of them

    @property
    def units(self) -> Units:
        """METRES ('m') when positions are metres, VO ('vo') for VO units."""
        return Units.METRES if self.metric else Units.VO


@dataclass(frozen=True)
class KeyframeStep:
    """A keyframe step as the scale stage sees it: map points of the new keyframe (its camera frame),
    the step's camera-centre chord in map units, and the two stamps; and the step's motion with the new
    keyframe's image, for the floor's homography between the two images (``floor_view``)."""

    X_cur: F64  # (N, 3) map points in the new keyframe's camera frame, NaN rows: no depth
    step_length: float  # |c_cur - c_kf| in the current map units
    kf_stamp_ns: int
    stamp_ns: int
    R_cur_kf: F64 | None = None  # X_cur = R_cur_kf X_kf + t_cur_kf (map units); None: not given
    t_cur_kf: F64 | None = None
    gray: NDArray[np.uint8] | None = None  # the new keyframe's image and its camera
    camera: CameraModel | None = None


@dataclass(frozen=True)
class WindowAnchor:
    """A keyframe's metric anchor for the windowed bundle adjustment: the wheel odometry position at its
    stamp with the relative sigma of wheel distances (``wheel_odometry``). The floor gives none: the scale
    filter owns ``ground_plane``'s scale and the window follows its corrections (``window``)."""

    wheel_xyz: F64 | None = None
    wheel_rel_sigma: float = math.nan


def _spread_var(zs: F64, med: float) -> float:
    """The variance of measurements ``zs`` (the newest last) about the window's median ``med``: their MAD's;
    for fewer than SMALL_WINDOW, at least the earlier ones' sample variance: a few measurements' MAD is no
    estimate of their spread (two may agree by chance where the fits scatter widely), and a wild newest one
    (a wall taken for the floor) must not widen its own gate."""
    var = (1.4826 * float(np.median(np.abs(zs - med)))) ** 2
    if zs.size < SMALL_WINDOW:
        var = max(var, float(np.var(zs[:-1] if zs.size > 2 else zs, ddof=1)))
    return var


@dataclass(frozen=True)
class ScaleFilter:
    """Robust filter of the current map's scale error, in log space (frozen: each call returns the filter after it).

    Each keyframe's measurement z = log(true / map) goes into a window of the last ``maxlen`` ones (kept
    relative to the map as it is now: a correction applied shifts them all). The window's median and
    MAD judge the newest (beyond 3 sigma: an outlier, not applied; ``SCALE_CHANGE_RUN`` of them in a row on
    one side: a jump of the map's scale) and give the measurement noise; a 1-D Kalman filter whose process
    noise is the VO's scale drift per keyframe takes each measurement once, its variance never below that
    of the mean of the window's measurements at that noise, nor below what the last ``SCALE_TREND_RUN``
    measurements' mean shows of a change it has not followed. Each measurement's noise is its own kind's
    scatter where the window holds fits of several kinds (``updated``). Metric scale is established once ``min_count``
    measurements are in the window: the first correction is their median.
    """

    drift_per_keyframe: float
    maxlen: int = SCALE_WINDOW
    min_count: int = 2
    window: tuple[tuple[float, float, str], ...] = ()  # (z, its variance, the kind of fit), oldest first
    var: float = math.inf
    total: float = 1.0  # product of every correction: metres per VO unit of the first map
    outlier: bool = False  # the last measurement was judged an outlier by the window
    run: int = 0  # outliers in a row on one side (signed: + the map too small, - too large)

    @property
    def q(self) -> float:
        return self.drift_per_keyframe**2

    @property
    def established(self) -> bool:
        return math.isfinite(self.var)

    @property
    def rel_std(self) -> float:
        return math.sqrt(self.var) if self.established else math.nan

    def predicted(self) -> ScaleFilter:
        """One keyframe later: the scale drifted by ``drift_per_keyframe`` more."""
        return dataclasses.replace(self, var=self.var + self.q) if self.established else self

    def inflated(self, rel_std: float) -> ScaleFilter:
        """The map's scale became uncertain by ``rel_std`` (1 sigma) more: a map rebuilt after a loss."""
        return dataclasses.replace(self, var=self.var + rel_std**2 if self.established else self.var, window=())

    def updated(self, z: float, r: float, kind: str = "") -> tuple[ScaleFilter, float]:
        """Fold in one measurement: the filter after it, and the correction factor to apply to the map
        (1.0 while not established). ``kind``: which fit measured it, when a source has fits of different
        noise (the floor among the map points, the floor's homography).

        The window's median and MAD judge the new measurement (an outlier is kept in the window but not
        applied) and say how noisy the measurements really are; the filter then takes this one measurement
        with that noise, so a measurement counts once however long it stays in the window. Where the
        window holds fits of several kinds, a measurement's noise is its own kind's scatter about the
        window's median: the quoted errors of one fit say little of another's, and a kind that scatters
        more must weigh less.
        """
        window = (*self.window, (z, r, kind))[-self.maxlen:]
        f = dataclasses.replace(self, window=window, outlier=False)
        if len(window) < self.min_count:
            return f, 1.0
        zs = np.array([w[0] for w in window])
        med = float(np.median(zs))
        n = zs.size
        r_eff = max(_spread_var(zs, med), r)
        # the same kind's earlier measurements (the newest must not widen its own gate)
        same = np.array([w[0] for w in window[:-1] if w[2] == kind])
        if 0 < same.size < n - 1 and same.size >= KIND_MIN_FITS:
            r_eff = max(_spread_var(np.append(same, z), med), r)
        if not self.established:
            var = 1.57 * r_eff / n  # the variance of a median of n
            log_c = med
            f = dataclasses.replace(f, run=0)
        else:
            if n >= 3 and (z - med) ** 2 > 9.0 * r_eff:
                side = 1 if z > med else -1
                run = self.run + side if self.run * side > 0 else side
                if abs(run) < SCALE_CHANGE_RUN:
                    # kept in the window (it may be the start of a change), not applied
                    return dataclasses.replace(f, outlier=True, run=run), 1.0
                # The start of a change: the map's scale jumped. The measurements since are the window now.
                recent = np.array([w[0] for w in window[-SCALE_CHANGE_RUN:]])
                r_new = max(float(np.var(recent, ddof=1)), max(w[1] for w in window[-SCALE_CHANGE_RUN:]))
                log_c = float(np.median(recent))
                f = dataclasses.replace(f, window=window[-SCALE_CHANGE_RUN:], run=0)
                var = 1.57 * r_new / SCALE_CHANGE_RUN
                factor = math.exp(log_c)
                return dataclasses.replace(f, window=tuple((x - log_c, v, k) for x, v, k in f.window), var=var,
                                           total=self.total * factor), factor
            # The filter knows the scale no better than the mean of the window's measurements at the noise the
            # window shows now: a first pair that agreed by chance leaves a variance too small for the later
            # measurements ever to move the map far, and the window's spread reveals it.
            # Nor surer than the last few measurements' agreement on a change it has not followed: their mean
            # (relative to the map as corrected) beyond what their noise explains is the map's scale drifting
            # faster than ``drift_per_keyframe`` (the VO's scale wanders by several per cent a keyframe on a
            # hard stretch), and the filter follows it within a few keyframes instead of a window's length.
            recent = zs[-SCALE_TREND_RUN:]
            trend = float(np.mean(recent)) ** 2 - r_eff / recent.size
            prior = max(self.var, r_eff / n, trend)
            gain = prior / (prior + r_eff)
            var = (1.0 - gain) * prior
            log_c = gain * z
            f = dataclasses.replace(f, run=0)
        factor = math.exp(log_c)
        return dataclasses.replace(f, window=tuple((x - log_c, v, k) for x, v, k in window), var=var,
                                   total=self.total * factor), factor


@dataclass(frozen=True, kw_only=True)
class ScaleSource:
    """A scale source and what it remembers between keyframes, frozen: every call that learns returns the
    source after it (``VoUnitsScale`` is the plain one)."""

    name: ClassVar[ScaleSourceKind] = ScaleSourceKind.NONE
    metric_source: ClassVar[bool] = False

    filter: ScaleFilter
    speed: float | None = None  # map units per second at the last keyframe
    reason: str = ""  # why the last keyframe gave no measurement ("" when it did)
    plane: GroundPlane | None = None  # the floor measured last (ground_plane)
    # The source's own error common to all its measurements (a calibration): it does not average out over
    # keyframes; an error of the scale it gives runs along the whole metric path.
    systematic_rel: float = 0.0
    up: F64 = field(default_factory=lambda: LEVEL_UP)  # the declared mounting's up, camera frame (``with_mounting_up``)

    def with_mounting_up(self, up: F64) -> Self:
        """The declared mounting's up direction in the camera optical frame (the floor's normal when the
        robot stands level); default a level camera's -y. Only the floor uses it. Raises ValueError when it
        is no direction."""
        up = np.asarray(up, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(up))
        if not (math.isfinite(norm) and norm > 0):
            raise ValueError(f"the mounting's up direction must be a finite non-zero vector, got {up}")
        return dataclasses.replace(self, up=up / norm)

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

    def status(self, wheel: WheelOdometry | None = None) -> ScaleStatus:
        """What the records say about scale; ``wheel``: the wheel odometry buffer (``wheel_odometry`` reports
        what became of its messages)."""
        plane = self.plane
        return ScaleStatus(self.name, self.established, self.filter.total, self.rel_std,
                           plane.pitch_deg if plane is not None else math.nan,
                           plane.roll_deg if plane is not None else math.nan, self.reason)

    def on_new_map(self) -> Self:
        """A map was (re)built: after a loss its baseline came from the last speed, so its scale is
        uncertain again (``NEW_MAP_REL_STD``)."""
        return dataclasses.replace(self, filter=self.filter.inflated(NEW_MAP_REL_STD))

    def viewing(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int) -> Self:
        """A keyframe was set on the image ``gray``: the source after it (``ground_plane`` keeps the image for
        the floor's homography to the next keyframe; the others need none)."""
        return self

    def on_keyframe(self, step_length: float, dt_s: float) -> Self:
        """A keyframe step of ``step_length`` map units over ``dt_s`` seconds was taken."""
        return dataclasses.replace(self, speed=step_length / dt_s) if dt_s > 0 else self

    def initial_baseline(self, dt_s: float) -> float:
        """Length given to the first keyframe baseline of a new map, ``dt_s`` after its keyframe."""
        if self.speed is None or dt_s <= 0.0:
            return 1.0
        return self.speed * dt_s

    def correction(self, step: KeyframeStep, wheel: WheelOdometry) -> tuple[Self, float]:
        """The source after this keyframe step, and the factor taking the step and its map into metres
        (1.0: no measurement)."""
        src = dataclasses.replace(self, filter=self.filter.predicted())
        src, measured = src.measure(step, wheel)
        if measured is None:
            return src, 1.0
        f, factor = src.filter.updated(*measured)
        src = dataclasses.replace(src, filter=f).on_corrected(factor)
        if not f.established:
            src = dataclasses.replace(src, reason=f"{len(f.window)} of {f.min_count} scale measurements needed to "
                                                  "establish metric scale: VO units")
        return src, factor

    def measure(self, step: KeyframeStep, wheel: WheelOdometry) -> tuple[Self, Measured | None]:
        """(log(true / map) scale, its variance, the kind of fit) at this keyframe, or None with ``reason``
        set."""
        return self, None

    def on_corrected(self, factor: float) -> Self:
        """The map was just scaled by ``factor`` (1.0: unchanged)."""
        return self

    def anchor(self, step: KeyframeStep, wheel: WheelOdometry) -> WindowAnchor | None:
        """What this source knows in metres about the keyframe of ``step`` (after its correction), for
        the windowed bundle adjustment's scale priors; None: nothing (or no metric scale yet)."""
        return None


@dataclass(frozen=True, kw_only=True)
class VoUnitsScale(ScaleSource):
    """Scale in VO units: baseline 1 for the first map, then the last keyframe speed carries it on."""


@dataclass(frozen=True, kw_only=True)
class GroundPlaneScale(ScaleSource):
    """Metric scale from the floor: ``camera_height_m`` over the floor's distance in map units."""

    name: ClassVar[ScaleSourceKind] = ScaleSourceKind.GROUND_PLANE
    metric_source: ClassVar[bool] = True

    camera_height_m: float
    max_tilt_deg: float
    inlier_ratio: float
    min_points: int
    # The least noise one floor measurement is given (relative, 1 sigma, ``ground_fit_min_rel_sigma``): the
    # window's spread of the fits says how noisy they are; below this it is not trusted.
    fit_min_rel_std: float = 0.005
    reason: str = "ground plane not seen yet: scale unknown (VO units)"
    normals: tuple[F64, ...] = ()  # the floor normals of the last FLOOR_HISTORY fits
    waiting: tuple[tuple[F64, float, float, str], ...] = ()  # fits before metric scale: (normal, z, r, kind)
    view: FloorView | None = None  # the last keyframe's image (``floor_view``)

    def viewing(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int) -> Self:
        return dataclasses.replace(self, view=FloorView(gray, camera, stamp_ns))

    def on_new_map(self) -> Self:
        return dataclasses.replace(super().on_new_map(), waiting=())

    def correction(self, step: KeyframeStep, wheel: WheelOdometry) -> tuple[Self, float]:
        """As ``ScaleSource.correction``, but before metric scale is established a fit waits until another
        fit's normal agrees with its own (``FLOOR_STEADY_DEG``); fits that agree with none are dropped then."""
        if self.filter.established:
            return super().correction(step, wheel)
        src, measured = self.measure(step, wheel)
        if measured is None:
            return src, 1.0
        normal = src.normals[-1]
        cos = math.cos(math.radians(FLOOR_STEADY_DEG))
        agree = [w for w in src.waiting if float(w[0] @ normal) >= cos]
        if not agree:
            waiting = (*src.waiting, (normal, *measured))
            return dataclasses.replace(src, waiting=waiting, reason=(
                f"{len(waiting)} floor fit(s), no two with normals within {FLOOR_STEADY_DEG:g} deg: metric scale "
                "waits for two that agree (VO units)")), 1.0
        f, factor = src.filter, 1.0
        for _, z, r, kind in [*agree, (normal, *measured)]:
            f, k = f.updated(z, r, kind)
            factor *= k
        src = dataclasses.replace(src, waiting=(), normals=(*(w[0] for w in agree), normal)[-FLOOR_HISTORY:],
                                  filter=f)
        return src.on_corrected(factor), factor

    def with_mounting_up(self, up: F64) -> Self:
        """The floor's normal the declared mounting implies (unit vector, camera optical frame): the camera's
        up when the robot stands level. The fits seen so far were judged against another: forgotten."""
        return dataclasses.replace(super().with_mounting_up(up), normals=(), waiting=())

    def _floor_between_views(self, step: KeyframeStep) -> GroundPlane | None:
        """The floor from its homography between the last keyframe's image and this one's (``floor_view``),
        when the step brings its motion and image; None otherwise. Its normal's prior is the declared
        mounting's up, not the floor seen so far: one step's homography trades the floor's tilt against its
        height, and a prior on the fits' own median feeds a first fit's tilt error into every later height
        (a road's camera a degree too level is a floor a few per cent too high, kept)."""
        view = self.view
        if (view is None or view.stamp_ns != step.kf_stamp_ns or step.gray is None or step.camera is None
                or step.R_cur_kf is None or step.t_cur_kf is None):
            return None
        # The height expected (map units): metres once the scale is established (the map is corrected into
        # them); before, every height is searched.
        h_guess = self.camera_height_m if self.filter.established else None
        fit = floor_between(view, step.gray, step.camera, step.R_cur_kf, step.t_cur_kf, self.up,
                            max_tilt_deg=self.max_tilt_deg, h_guess=h_guess)
        return fit.plane

    def _expected_up(self) -> tuple[F64, float]:
        """The floor normal seen over the last keyframes (the camera's mounting changes little), and how
        far a new fit may lie from it; before ``FLOOR_STEADY_FITS`` fits, the declared up and
        ``max_tilt_deg``."""
        if len(self.normals) < FLOOR_STEADY_FITS:
            return self.up, self.max_tilt_deg
        n = np.median(np.array(self.normals), axis=0)
        return n / np.linalg.norm(n), min(FLOOR_STEADY_DEG, self.max_tilt_deg)

    def measure(self, step: KeyframeStep, wheel: WheelOdometry) -> tuple[Self, Measured | None]:
        """The floor among the map points when they hold one; else the floor's homography between the two
        keyframes' images (``floor_view``): a sparsely textured floor (asphalt, concrete) gives the map few
        points, yet it fills the lower image. Where the points hold a floor they are the better measurement
        (on the distribution's floor-robot family the homography, whose tilt and height trade against each
        other within one step, scatters more), so they are tried first."""
        src, measured = self._measure_points(step)
        if measured is not None:
            return src, measured
        seen = self._floor_between_views(step)
        if seen is None:
            return src, None
        src = dataclasses.replace(src, normals=(*src.normals, seen.normal_up)[-FLOOR_HISTORY:])
        r = seen.rel_std**2 + self.fit_min_rel_std**2
        return dataclasses.replace(src, plane=seen, reason=""), (math.log(self.camera_height_m / seen.height), r,
                                                                 FIT_VIEW)

    def _measure_points(self, step: KeyframeStep) -> tuple[Self, Measured | None]:
        up, tilt = self._expected_up()
        search = find_floor(step.X_cur, max_tilt_deg=tilt, inlier_ratio=self.inlier_ratio,
                            min_points=self.min_points, up=up)
        plane = search.plane
        if plane is not None and float(plane.normal_up @ self.up) < math.cos(math.radians(self.max_tilt_deg)):
            return dataclasses.replace(self, reason=(
                f"the floor seen so far leans more than {self.max_tilt_deg:g} deg from the declared mounting's up: "
                f"no floor, {self.held}")), None
        if plane is None:
            where = "of the mounting's up" if len(self.normals) < FLOOR_STEADY_FITS else "of the floor seen so far"
            reason = f"no floor plane among {search.n_points} map points"
            on, beneath = search.best_unsupported
            if on >= self.min_points:
                reason += (f": the largest plane within {tilt:g} deg {where} and below the camera holds {on} and "
                           f"has {beneath} well beneath it; the floor carries the scene (is the camera mounted as "
                           "declared?)")
            else:
                reason += f" (need {self.min_points} within {tilt:g} deg {where})"
            return dataclasses.replace(self, reason=f"{reason}: {self.held}"), None
        from_history = len(self.normals) >= FLOOR_STEADY_FITS
        src = dataclasses.replace(self, normals=(*self.normals, plane.normal_up)[-FLOOR_HISTORY:])
        if from_history:
            # The floor's direction is known better from the last keyframes than from this one's few
            # points: measure the height of this fit's inliers along it.
            X = step.X_cur[np.all(np.isfinite(step.X_cur), axis=1)]
            on_plane = np.abs(X @ plane.normal_up + plane.height) < self.inlier_ratio * plane.height
            plane = GroundPlane(up, float(np.median(-(X[on_plane] @ up))), plane.n_inliers, plane.rel_std)
            if not plane.height > 0:
                return dataclasses.replace(src, reason="floor plane above the camera: ignored"), None
        # The fit's own standard error, at least fit_min_rel_std; the filter's window raises it to the fits'
        # spread.
        r = plane.rel_std**2 + self.fit_min_rel_std**2
        return dataclasses.replace(src, plane=plane, reason=""), (math.log(self.camera_height_m / plane.height), r,
                                                                  FIT_POINTS)


@dataclass(frozen=True, kw_only=True)
class WheelOdometryScale(ScaleSource):
    """Metric scale from the distance the wheels travelled over the last keyframe steps.

    Keyframes can be a few centimetres apart (a floor close to the camera makes parallax fast), where
    wheel noise and the camera's lever arm in turns dominate one step. So each measurement spans the
    most recent keyframe steps until the wheels covered ``window_m``: the sum of their wheel chords over
    the sum of their VO step lengths (kept in the current map's units as corrections are applied).
    """

    name: ClassVar[ScaleSourceKind] = ScaleSourceKind.WHEEL_ODOMETRY
    metric_source: ClassVar[bool] = True

    rel_sigma: float
    timeout_ns: int
    window_m: float = 0.5  # ``wheel_odometry_window_m``
    # The wheels' random error over one scale measurement (m, 1 sigma, ``wheel_odometry_noise_m``): the noise
    # that averages out over keyframes. Their calibration error (tyre radius), which does not, is
    # ``rel_sigma``, carried once as the source's systematic error (``ScaleSource.systematic_rel``).
    noise_m: float = 0.01
    reason: str = "no keyframe step measured by the wheels yet: scale unknown (VO units)"
    steps: tuple[tuple[int, int, float], ...] = ()  # the last WHEEL_STEPS: (kf stamp, stamp, VO step length)

    def on_corrected(self, factor: float) -> Self:
        return dataclasses.replace(self, steps=tuple((a, b, length * factor) for a, b, length in self.steps))

    def status(self, wheel: WheelOdometry | None = None) -> ScaleStatus:
        status = super().status(wheel)
        return status if wheel is None else dataclasses.replace(status, wheel=wheel.counts)

    def anchor(self, step: KeyframeStep, wheel: WheelOdometry) -> WindowAnchor | None:
        if not self.established:
            return None
        xyz, _ = wheel.position_at(step.stamp_ns, self.timeout_ns)
        return None if xyz is None else WindowAnchor(wheel_xyz=xyz, wheel_rel_sigma=self.rel_sigma)

    def measure(self, step: KeyframeStep, wheel: WheelOdometry) -> tuple[Self, Measured | None]:
        src = dataclasses.replace(self, steps=(*self.steps, (step.kf_stamp_ns, step.stamp_ns,
                                                             step.step_length))[-WHEEL_STEPS:])
        d_wheel = d_vo = 0.0
        n = 0
        for t0, t1, length in reversed(src.steps):
            p0, why0 = wheel.position_at(int(t0), self.timeout_ns)
            p1, why1 = wheel.position_at(int(t1), self.timeout_ns)
            if p0 is None or p1 is None:
                if n == 0:
                    return dataclasses.replace(src, reason=f"{why0 or why1}: {self.held}"), None
                break
            d_wheel += float(np.linalg.norm(p1 - p0))
            d_vo += length
            n += 1
            if d_wheel >= self.window_m:
                break
        if d_wheel < self.window_m or not d_vo > 0:
            return dataclasses.replace(src, reason=(
                f"wheels moved {d_wheel:.3f} m over the last {n} keyframe step(s) (< {self.window_m} m): "
                f"{self.held}")), None
        # Only the wheels' random part: their calibration error is common to every measurement, the
        # source's systematic error (``systematic_rel``).
        r = (self.noise_m / d_wheel) ** 2
        return dataclasses.replace(src, reason=""), (math.log(d_wheel / d_vo), r, FIT_WHEELS)


def source_from_config(cfg: VoConfig) -> ScaleSource:
    """The scale source ``cfg.scale_source`` names, before any keyframe."""
    f = ScaleFilter(cfg.scale_drift_per_keyframe)
    if cfg.scale_source is ScaleSourceKind.GROUND_PLANE:
        return GroundPlaneScale(filter=f, camera_height_m=cfg.camera_height_m, max_tilt_deg=cfg.ground_max_tilt_deg,
                                inlier_ratio=cfg.ground_inlier_ratio, min_points=cfg.ground_min_points,
                                systematic_rel=cfg.camera_height_rel_sigma,
                                fit_min_rel_std=cfg.ground_fit_min_rel_sigma)
    if cfg.scale_source is ScaleSourceKind.WHEEL_ODOMETRY:
        return WheelOdometryScale(filter=f, rel_sigma=cfg.wheel_odometry_rel_sigma,
                                  systematic_rel=cfg.wheel_odometry_rel_sigma,
                                  timeout_ns=int(cfg.wheel_odometry_timeout_s * 1e9),
                                  window_m=cfg.wheel_odometry_window_m, noise_m=cfg.wheel_odometry_noise_m)
    return VoUnitsScale(filter=f)
