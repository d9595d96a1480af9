"""The frame record: what one input frame yields.

``FrameResult`` is the immutable record every front door (replay, node) turns into outputs; the step
(``epi_vo.core.step``) builds it once per frame from the stages' own frozen results (``publish``).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.decisions import Decision, Note
from epi_vo.core.scale import ScaleStatus
from epi_vo.core.transforms import quat_xyzw_from_rotation, rotation_angle_deg

F64 = NDArray[np.float64]

# The largest stamp a ROS time can hold (builtin_interfaces/Time: int32 sec, nanosec < 1e9). Stamps
# outside [0, MAX_STAMP_NS] cannot be published or written: such frames are rejected.
MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999


def clamp_stamp_ns(stamp_ns: int) -> int:
    """``stamp_ns`` clamped into the valid ROS time range [0, MAX_STAMP_NS]."""
    return min(max(int(stamp_ns), 0), MAX_STAMP_NS)


class TrackingState(enum.Enum):
    INITIALIZING = "initializing"  # no map yet: waiting for parallax; rotation is estimated, position holds
    TRACKING = "tracking"  # pose with the map's scale
    ROTATION_ONLY = "rotation_only"  # pure rotation detected: rotation estimated, position holds
    STATIC = "static"  # the camera did not move (what moved is another object): pose held, zero twist
    LOST = "lost"  # no pose this frame (pose held, covariance large)


class Model(enum.Enum):
    ESSENTIAL = "E"
    HOMOGRAPHY = "H"
    STATIC = "static"  # the "no camera motion" hypothesis explained the frame
    NONE = "none"


def stamp_seconds(stamp_ns: int) -> float:
    """``stamp_ns`` in seconds as the nearest double not above it: near 2**31 s a plain ``ns * 1e-9`` rounds
    2147483647.999999999 up to 2**31 s, which is no ROS time."""
    s = int(stamp_ns) / 1_000_000_000  # correctly rounded
    if Fraction(s) > Fraction(int(stamp_ns), 1_000_000_000):
        s = math.nextafter(s, -math.inf)
    return s


def frozen(a: F64) -> F64:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Matches:
    """The correspondences of one frame with its keyframe, for drawing and inspection.

    ``pts_kf``/``pts_cur`` raw pixels, ``uv_kf``/``uv_cur`` undistorted pixels (N, 2); ``inliers`` of
    the chosen model; ``F`` (from E) and ``H`` in undistorted pixels, zero matrices when not estimated;
    ``moving`` the features judged to move on their own while the camera moves (None: not judged).
    """

    pts_kf: F64
    pts_cur: F64
    uv_kf: F64
    uv_cur: F64
    inliers: NDArray[np.bool_]
    F: F64
    H: F64
    moving: NDArray[np.bool_] | None = None

    @staticmethod
    def empty() -> Matches:
        z2 = np.zeros((0, 2))
        return Matches(z2, z2, z2, z2, np.zeros(0, bool), np.zeros((3, 3)), np.zeros((3, 3)))


VO_UNITS = ScaleStatus()  # no scale source: VO units


@dataclass(frozen=True)
class FrameResult:
    """Everything known about one input frame. Every field is always set.

    Counts refer to correspondences between the reference keyframe and this frame. Angles in degrees,
    errors in undistorted pixels, times in milliseconds. ``T_w_c`` is always a valid pose: the held
    pose when ``has_pose`` is False. ``covariance`` is 6x6 over (x, y, z, rot_x, rot_y, rot_z) in the
    odometry frame (rotation in radians). Positions, point cloud and position covariance are in metres
    when ``scale.metric`` (a metric scale source is established), in VO units otherwise (``scale.units``
    says which).

    Finite by construction: ``__post_init__`` refuses a non-finite ``T_w_c``, ``covariance``,
    ``points_w`` or ``timings_ms`` and a ``stamp_ns`` that is no valid ROS time (the pipeline also
    keeps ``T_w_c`` rigid and the covariance symmetric with a positive diagonal). A statistic that was
    not measured this frame (``median_parallax_deg``, ...) is NaN, never infinite; ``to_record`` writes
    it as null.
    """

    index: int
    stamp_ns: int
    state: TrackingState
    has_pose: bool
    is_keyframe: bool
    model: Model
    rh: float
    n_features: int
    n_tracked: int
    n_inliers: int
    inlier_ratio: float
    median_parallax_deg: float
    n_triangulated: int
    positive_depth_ratio: float
    median_reproj_err_px: float
    relative_scale: float
    n_keyframes: int
    T_w_c: F64
    covariance: F64
    points_w: F64
    timings_ms: dict[str, float]
    reason: str
    matches: Matches
    skipped: bool = False  # not processed (duplicate or invalid stamp, undecodable): no pose is published for it
    problem: str = ""  # why the frame was rejected (bad input); "" when it was not
    scale: ScaleStatus = VO_UNITS  # scale source, metres or VO units, scale and its uncertainty
    n_moving: int = 0  # tracked features that moved while the camera was judged static
    moving_fraction: float = 0.0  # of the tracked features
    moving_region: tuple[int, int, int, int] | None = None  # x0, y0, x1, y1 (px) of the movers, None: none
    static_score: float = math.nan  # fraction of tracked features the "no camera motion" hypothesis explains
    # The focal length (x the calibration's) under which this frame's motion is a pure rotation, when the
    # calibration's made it look like parallax (the reason says "check the camera calibration"); else NaN
    focal_ratio: float = math.nan
    # The image noise the KLT tracks show this frame: per-axis RMS of their forward-backward errors (px;
    # NaN with ORB or without tracks). It sets the twist's uncertainty (``step._step_covariance``)
    track_noise_px: float = math.nan
    # KLT tracks moved onto their first image's patch this frame (``klt_patch_refine_px``); None: refinement off
    n_refined: int | None = None
    # 6x6 covariance (odometry frame, position first) of the motion since the previous frame, for the
    # twist; None when the frame has no pose or no previous frame with one
    step_covariance: F64 | None = None
    # The rigid transform (4x4, odometry frame) the windowed adjustment applied at this frame: the poses
    # before it move with it (T_new = correction @ T_old), so the motion since the previous frame, the
    # twist, is this frame's pose against correction @ the previous pose, not the jump; None: no correction
    correction: F64 | None = None
    # What the stages decided, in order, with their details: ``reason`` is their sentences
    # (``epi_vo.core.reasons.render``); code asks these, never the text
    notes: tuple[Note, ...] = ()

    @property
    def decisions(self) -> tuple[Decision, ...]:
        """The decisions of ``notes``, in order (``Decision.TIME_JUMPED_BACK in result.decisions``)."""
        return tuple(n.decision for n in self.notes)

    @property
    def rejected(self) -> bool:
        """The frame could not be used (its input was bad); ``problem`` says why."""
        return bool(self.problem)

    def __post_init__(self) -> None:
        problems = []
        if not 0 <= self.stamp_ns <= MAX_STAMP_NS:
            problems.append(f"stamp {self.stamp_ns}")
        for name in ("T_w_c", "covariance", "points_w", "correction"):
            if getattr(self, name) is not None and not np.all(np.isfinite(getattr(self, name))):
                problems.append(name)
        if not all(math.isfinite(v) for v in self.timings_ms.values()):
            problems.append("timings_ms")
        for name in STAT_FIELDS:
            if math.isinf(getattr(self, name)):
                problems.append(name)
        if problems:
            raise AssertionError(f"FrameResult {self.index} has non-finite or invalid values: {', '.join(problems)}")

    @property
    def position(self) -> F64:
        return self.T_w_c[:3, 3]

    @property
    def quat_xyzw(self) -> F64:
        return quat_xyzw_from_rotation(self.T_w_c[:3, :3])

    def to_record(self) -> dict[str, Any]:
        """JSON-ready dict of the record (non-finite floats become None)."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {
            "index": self.index,
            "stamp": stamp_seconds(self.stamp_ns),
            "stamp_ns": self.stamp_ns,
            "state": self.state.value,
            "has_pose": self.has_pose,
            "is_keyframe": self.is_keyframe,
            "model": self.model.value,
            "rh": num(self.rh),
            "n_features": self.n_features,
            "n_tracked": self.n_tracked,
            "n_inliers": self.n_inliers,
            "inlier_ratio": num(self.inlier_ratio),
            "median_parallax_deg": num(self.median_parallax_deg),
            "n_triangulated": self.n_triangulated,
            "positive_depth_ratio": num(self.positive_depth_ratio),
            "median_reproj_err_px": num(self.median_reproj_err_px),
            "relative_scale": num(self.relative_scale),
            "n_keyframes": self.n_keyframes,
            "position": [float(v) for v in self.position],
            "quat_xyzw": [float(v) for v in self.quat_xyzw],
            "covariance_diagonal": [float(v) for v in np.diag(self.covariance)],
            "n_points": int(self.points_w.shape[0]),
            "timings_ms": {k: round(v, 3) for k, v in self.timings_ms.items()},
            "reason": self.reason,
            "skipped": self.skipped,
            "rejected": self.rejected,
            "units": self.scale.units,
            "scale_source": self.scale.source,
            "metric_scale": self.scale.metric,
            "scale": num(self.scale.scale),
            "scale_rel_std": num(self.scale.rel_std),
            "floor_pitch_deg": num(self.scale.floor_pitch_deg),
            "floor_roll_deg": num(self.scale.floor_roll_deg),
            "scale_reason": self.scale.reason,
            # wheel_odometry: the messages received so far and why those not used were dropped
            "wheel_messages": None if self.scale.wheel is None else self.scale.wheel.record(),
            "static_score": num(self.static_score),
            "n_moving": self.n_moving,
            "moving_fraction": num(self.moving_fraction),
            "moving_region": list(self.moving_region) if self.moving_region is not None else None,
            "focal_ratio": num(self.focal_ratio),
            "track_noise_px": num(self.track_noise_px),
            "n_refined": self.n_refined,
            # how far the windowed adjustment moved the poses at this frame (position in ``units``)
            "window_correction": None if self.correction is None else float(np.linalg.norm(self.correction[:3, 3])),
            "window_correction_deg": None if self.correction is None else rotation_angle_deg(self.correction[:3, :3]),
        }


STAT_FIELDS = ("rh", "inlier_ratio", "median_parallax_deg", "positive_depth_ratio", "median_reproj_err_px",
                "relative_scale", "focal_ratio", "track_noise_px")
