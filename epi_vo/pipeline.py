"""The per-frame monocular VO pipeline: the one stateful object of epi_vo.

Both front doors drive this same object: ``epi-vo replay`` (offline, bags) and ``vo_node`` (ROS 2).

Frames and poses
    ``w`` is the odometry frame: the optical frame of the first camera pose (x right, y down,
    z forward). ``T_w_c`` maps current-camera points into ``w``; ``T_w_kf`` the same for the reference
    keyframe. Relative motion ``T_cur_kf`` maps keyframe-camera points into the current camera
    (``X_cur = R_cur_kf X_kf + t_cur_kf``), which is what ``cv2.recoverPose(E, uv_kf, uv_cur)`` returns.

Monocular scale convention
    Translation is observable only up to one global scale. The first map is built with a keyframe
    baseline of length 1 (``|t| = 1`` between the first two keyframes), and every later frame carries
    that same scale: its translation is scaled so that the map points triangulated between the last
    pair of keyframes project consistently (robust median of per-point scale estimates, then a
    motion-only refinement on those points). After tracking is lost, the new map's baseline is set to
    the last keyframe baseline so the trajectory continues in (approximately) the same units. An
    external scale source (wheel odometry, known baseline) would replace the baseline length in
    :meth:`VoPipeline._initial_baseline`; that is the seam left for it. The trajectory is therefore
    correct up to one Sim(3) transform.

What is never invented
    No parallax: no depth and no keyframe. Pure rotation (the homography explains the motion and no
    parallax is left after removing the rotation): the rotation is published, the position holds.
    Before the map exists the scale is unknown: the position holds and its covariance says so.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo import frontend as fe
from epi_vo import geometry as geo
from epi_vo.camera import CameraModel
from epi_vo.config import VoConfig, validate
from epi_vo.transforms import invert_T, make_T, quat_xyzw_from_rotation, rotation_angle_deg

_log = logging.getLogger(__name__)

# The largest stamp a ROS time can hold (builtin_interfaces/Time: int32 sec, nanosec < 1e9). Stamps
# outside [0, MAX_STAMP_NS] cannot be published or written: such frames are rejected.
MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


class TrackingState(enum.Enum):
    INITIALIZING = "initializing"  # no map yet: waiting for parallax; rotation is estimated, position holds
    TRACKING = "tracking"  # pose with the map's scale
    ROTATION_ONLY = "rotation_only"  # pure rotation detected: rotation estimated, position holds
    LOST = "lost"  # no pose this frame (pose held, covariance large)


class Model(enum.Enum):
    ESSENTIAL = "E"
    HOMOGRAPHY = "H"
    NONE = "none"


def _frozen(a: F64) -> F64:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Matches:
    """The correspondences of one frame with its keyframe, for drawing and inspection.

    ``pts_kf``/``pts_cur`` raw pixels, ``uv_kf``/``uv_cur`` undistorted pixels (N, 2); ``inliers`` of
    the chosen model; ``F`` (from E) and ``H`` in undistorted pixels, zero matrices when not estimated.
    """

    pts_kf: F64
    pts_cur: F64
    uv_kf: F64
    uv_cur: F64
    inliers: NDArray[np.bool_]
    F: F64
    H: F64

    @staticmethod
    def empty() -> Matches:
        z2 = np.zeros((0, 2))
        return Matches(z2, z2, z2, z2, np.zeros(0, bool), np.zeros((3, 3)), np.zeros((3, 3)))


@dataclass(frozen=True)
class FrameResult:
    """Everything known about one input frame. Every field is always set.

    Counts refer to correspondences between the reference keyframe and this frame. Angles in degrees,
    errors in undistorted pixels, times in milliseconds. ``T_w_c`` is always a valid pose: the held
    pose when ``has_pose`` is False. ``covariance`` is 6x6 over (x, y, z, rot_x, rot_y, rot_z) in the
    odometry frame (position in map units, rotation in radians).

    Finite by construction (checked in ``__post_init__``): ``T_w_c`` (a rigid transform),
    ``covariance`` (symmetric, positive diagonal), ``points_w`` and ``timings_ms`` are always finite,
    ``stamp_ns`` is a valid ROS time. A statistic that was not measured this frame (``rh``,
    ``median_parallax_deg``, ...) is NaN, never infinite; ``to_record`` writes it as null.
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
    skipped: bool = False  # not processed (duplicate stamp): consumers publish no pose for it

    def __post_init__(self) -> None:
        problems = []
        if not 0 <= self.stamp_ns <= MAX_STAMP_NS:
            problems.append(f"stamp {self.stamp_ns}")
        for name in ("T_w_c", "covariance", "points_w"):
            if not np.all(np.isfinite(getattr(self, name))):
                problems.append(name)
        if not all(math.isfinite(v) for v in self.timings_ms.values()):
            problems.append("timings_ms")
        for name in _STAT_FIELDS:
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
            "stamp": self.stamp_ns * 1e-9,
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
        }


_STAT_FIELDS = ("rh", "inlier_ratio", "median_parallax_deg", "positive_depth_ratio", "median_reproj_err_px",
                "relative_scale")


@dataclass(frozen=True)
class Keyframe:
    """The reference view all correspondences of the following frames are measured from.

    Arrays are aligned by row: ``pts`` raw pixels, ``xn`` normalized and ``uv`` undistorted pixels of
    each feature, ``X_kf`` its map point in this keyframe's camera frame (NaN: no depth), and, for the
    ORB frontend, ``descriptors``.
    """

    index: int
    stamp_ns: int
    T_w_kf: F64
    cov_w_kf: F64
    pts: F32
    xn: F64
    uv: F64
    X_kf: F64
    descriptors: NDArray[np.uint8] | None
    camera: CameraModel

    @property
    def n_features(self) -> int:
        return int(self.pts.shape[0])

    @property
    def n_map_points(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.X_kf[:, 0])))


@dataclass
class _FrameStats:
    """Mutable scratch of one ``process`` call; frozen into a FrameResult at the end."""

    stamp_ns: int = 0
    model: Model = Model.NONE
    rh: float = math.nan
    n_tracked: int = 0
    n_inliers: int = 0
    median_parallax_deg: float = math.nan
    n_triangulated: int = 0
    positive_depth_ratio: float = math.nan
    median_reproj_err_px: float = math.nan
    relative_scale: float = math.nan
    points_w: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    matches: Matches = field(default_factory=Matches.empty)
    F: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    H: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    reasons: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class _Motion:
    """A pose estimate of the current frame relative to the keyframe, with what justified it."""

    state: TrackingState
    R_cur_kf: F64
    t_cur_kf: F64
    cov_rel: F64  # 6x6 over (position, rotation) of the current camera in the keyframe frame
    inliers: NDArray[np.bool_]
    new_map: geo.Triangulation | None = None  # set when this frame initialises the map
    make_keyframe: bool = False


class VoPipeline:
    """Monocular VO: feed it frames, get one immutable :class:`FrameResult` per frame."""

    def __init__(self, cfg: VoConfig | None = None) -> None:
        self.cfg = cfg or VoConfig()
        validate(self.cfg)
        self._orb = fe.make_orb(self.cfg) if self.cfg.frontend == "orb" else None
        self._T_w_c = np.eye(4)
        self._cov_w_c = np.zeros((6, 6))
        self._kf: Keyframe | None = None
        self._rows = np.zeros(0, np.int64)  # keyframe row of each live track
        self._pts_prev = np.zeros((0, 2), np.float32)
        self._gray_prev: NDArray[np.uint8] | None = None  # previous image, for KLT
        self._T_cur_kf_prev = np.eye(4)
        self._speed: float | None = None  # map units per second at the last keyframe
        self._fail_count = 0
        self._n_keyframes = 0
        self._index = 0
        self._pending_reason = ""
        self._last_stamp_ns: int | None = None

    # ---------------------------------------------------------------------------------------------
    @property
    def pose(self) -> F64:
        """T_w_c of the last frame (a copy)."""
        return self._T_w_c.copy()

    def reset(self, reason: str = "reset requested") -> None:
        """Restart tracking from the current pose: the next frame becomes a new keyframe, no map."""
        self._kf = None
        self._pending_reason = reason

    def _check_stamp(self, stamp_ns: int) -> FrameResult | None:
        """A stamp that is no valid ROS time: the frame is rejected and skipped. Equal stamp: the frame
        is skipped (a result saying so). Backwards: tracking restarts from the held pose (odometry stays
        continuous) and the frame is processed.

        The stamp is booked as the last one only when its frame result is made (``_result``), so a
        frame that fails half-way is not mistaken for a duplicate when it is then rejected.
        """
        stamp_ns = int(stamp_ns)
        if not 0 <= stamp_ns <= MAX_STAMP_NS:
            return self._skip(min(max(stamp_ns, 0), MAX_STAMP_NS),
                              f"frame rejected: image stamp {stamp_ns} ns is not a valid ROS time (0 to "
                              f"{MAX_STAMP_NS} ns): frame skipped")
        last = self._last_stamp_ns
        if last is not None and stamp_ns == last:
            return self._skip(stamp_ns, "duplicate image stamp: frame skipped")
        if last is not None and stamp_ns < last:
            self.reset(f"time jumped backwards by {(last - stamp_ns) * 1e-9:.3f} s: tracking restarted from the "
                       "last pose")
        return None

    def _skip(self, stamp_ns: int, reason: str) -> FrameResult:
        st = _FrameStats(stamp_ns=stamp_ns)
        st.reasons.append(reason)
        result = self._result(stamp_ns, TrackingState.LOST, False, False, st, time.perf_counter(), book=False)
        return dataclasses.replace(result, skipped=True)

    def reject(self, stamp_ns: int, reason: str) -> FrameResult:
        """Account for a frame that could not be used (corrupt image, unusable calibration, ...).

        The frame gets its record like any other: no pose (held), a large covariance, the reason.
        It counts as a frame without a pose, so persistent bad input ends in a restart from the held
        pose, exactly as lost tracking does.
        """
        skipped = self._check_stamp(stamp_ns)
        if skipped is not None:
            return skipped
        return self._reject_checked(int(stamp_ns), reason, time.perf_counter())

    def _reject_checked(self, stamp_ns: int, reason: str, t_start: float) -> FrameResult:
        st = _FrameStats(stamp_ns=stamp_ns)
        st.reasons.append(f"frame rejected: {reason}")
        if self._on_failure(st):
            self._kf = None
        return self._result(stamp_ns, TrackingState.LOST, False, False, st, t_start)

    def process(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int) -> FrameResult:
        """Process one grayscale frame taken with ``camera`` at ``stamp_ns``.

        An image the frontend cannot use (too small, or one OpenCV refuses) gives a rejected frame
        with the reason; the held pose and covariance are then those before the frame.

        Raises:
            CameraModelError: the image size does not match ``camera``.
            ValueError: ``gray`` is not a 2-D uint8 array.
        """
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"expected a 2-D uint8 grayscale image, got {gray.dtype} {gray.shape}")
        camera.check_image_size(gray.shape[1], gray.shape[0])
        skipped = self._check_stamp(stamp_ns)
        if skipped is not None:
            return skipped
        stamp_ns = int(stamp_ns)
        t_start = time.perf_counter()
        work_w = gray.shape[1] if self.cfg.max_image_width <= 0 else min(gray.shape[1], self.cfg.max_image_width)
        problem = fe.image_problem(work_w, round(gray.shape[0] * work_w / gray.shape[1]), self.cfg)
        if problem is not None:
            return self._reject_checked(stamp_ns, problem, t_start)
        held = (self._T_w_c.copy(), self._cov_w_c.copy())
        try:
            return self._process(gray, camera, stamp_ns, t_start)
        except cv2.error as exc:
            # OpenCV refused this image or these points: nothing of the frame is trusted. Restore the
            # held pose, drop the map (its state may be half-updated) and say what happened.
            self._T_w_c, self._cov_w_c = held
            self._kf = None
            detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
            _log.warning("frame at %d ns: OpenCV failed: %s", stamp_ns, detail)
            return self._reject_checked(stamp_ns, f"OpenCV could not process this frame ({detail}); tracking "
                                        "restarts from the last pose", t_start)

    def _process(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int, t_start: float
                 ) -> FrameResult:
        st = _FrameStats(stamp_ns=stamp_ns)
        if self._pending_reason:
            st.reasons.append(self._pending_reason)
            self._pending_reason = ""
        gray, camera = downscale(gray, camera, self.cfg.max_image_width)
        if self._kf is not None and not _same_camera(self._kf.camera, camera):
            st.reasons.append("camera_info changed: tracking restarted")
            self._kf = None

        t0 = time.perf_counter()
        if self._kf is None:
            result = self._start_keyframe(gray, camera, stamp_ns, st, t_start)
            return result

        pts_cur, rows, orb_cur = self._track(gray)
        kf = self._kf
        xn_cur = camera.normalize(pts_cur)
        uv_cur = camera.to_pixels(xn_cur)
        st.timings["frontend"] = _ms(t0)
        st.n_tracked = int(rows.shape[0])

        motion: _Motion | None = None
        if st.n_tracked < self.cfg.min_inliers:
            st.reasons.append(f"too few tracked features ({st.n_tracked} < {self.cfg.min_inliers})")
        else:
            motion = self._estimate_motion(kf, rows, xn_cur, uv_cur, st)
            if motion is not None and not _motion_is_finite(motion):
                st.reasons.append("the motion estimate is not finite (check the calibration): no pose this frame")
                motion = None

        inl = motion.inliers if motion is not None else np.zeros(rows.shape[0], bool)
        st.matches = Matches(kf.pts[rows].astype(np.float64), pts_cur.astype(np.float64), kf.uv[rows], uv_cur, inl,
                             st.F, st.H)
        t0 = time.perf_counter()
        is_kf = False
        if motion is None:
            state, has_pose = TrackingState.LOST, False
            if self._on_failure(st):
                self._restart_here(gray, camera, stamp_ns, orb_cur)
                is_kf = True
            else:
                self._rows, self._pts_prev = rows, pts_cur
        else:
            self._fail_count = 0
            has_pose = True
            state = motion.state
            T_cur_kf = make_T(motion.R_cur_kf, motion.t_cur_kf)
            T_w_c = kf.T_w_kf @ invert_T(T_cur_kf)
            self._T_w_c = T_w_c
            self._cov_w_c = _compose_cov(kf.cov_w_kf, kf.T_w_kf, motion.cov_rel, motion.t_cur_kf,
                                         motion.R_cur_kf)
            self._T_cur_kf_prev = T_cur_kf
            if state is TrackingState.INITIALIZING:
                # Unknown scale: the position is not justified by anything yet.
                self._cov_w_c = self._cov_w_c.copy()
                self._cov_w_c[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
            self._rows, self._pts_prev = rows, pts_cur
            is_kf = self._maybe_keyframe(motion, kf, rows, pts_cur, xn_cur, gray, camera, stamp_ns,
                                         orb_cur, st)
        st.timings["mapping"] = _ms(t0)
        self._gray_prev = gray
        return self._result(stamp_ns, state, has_pose, is_kf, st, t_start)

    # ---------------------------------------------------------------------------------------------
    def _track(self, gray: NDArray[np.uint8]) -> tuple[F32, NDArray[np.int64], fe.OrbFeatures | None]:
        """Correspondences keyframe -> current: (current raw pixels, keyframe rows, ORB features)."""
        kf = self._kf
        assert kf is not None
        if self._orb is None:
            assert self._gray_prev is not None
            pts, ok = fe.track_klt(self._gray_prev, gray, self._pts_prev, self.cfg)
            return pts[ok], self._rows[ok], None
        feats = fe.detect_orb(self._orb, gray, self.cfg)
        assert kf.descriptors is not None
        i_kf, i_cur = fe.match_orb(kf.descriptors, feats.descriptors, self.cfg.orb_ratio)
        return feats.pts[i_cur], i_kf, fe.OrbFeatures(feats.pts, feats.descriptors)

    def _estimate_motion(self, kf: Keyframe, rows: NDArray[np.int64], xn_cur: F64, uv_cur: F64,
                         st: _FrameStats) -> _Motion | None:
        """E and H compete on the same correspondences; the winner and the map decide the pose."""
        cfg = self.cfg
        K = kf.camera.K
        uv_kf, xn_kf = kf.uv[rows], kf.xn[rows]
        t0 = time.perf_counter()
        E, _ = geo.estimate_essential(uv_kf, uv_cur, K, cfg.essential_method, cfg.ransac_threshold_px,
                                      cfg.ransac_confidence, cfg.ransac_max_iters)
        H, _ = geo.estimate_homography(uv_kf, uv_cur, cfg.homography_method, cfg.ransac_threshold_px,
                                       cfg.ransac_confidence, cfg.ransac_max_iters)
        s_e, in_e = (geo.score_fundamental(geo.fundamental_from_essential(E, K), uv_kf, uv_cur,
                                           cfg.score_sigma_px) if E is not None else (0.0, None))
        s_h, in_h = (geo.score_homography(H, uv_kf, uv_cur, cfg.score_sigma_px)
                     if H is not None else (0.0, None))
        st.rh = geo.rh_ratio(s_h, s_e)
        if E is not None:
            st.F = geo.fundamental_from_essential(E, K)
        if H is not None:
            st.H = H
        st.timings["models"] = _ms(t0)
        t0 = time.perf_counter()
        try:
            if H is not None and in_h is not None and (st.rh > cfg.rh_threshold or E is None):
                st.model = Model.HOMOGRAPHY
                return self._motion_from_homography(kf, rows, H, in_h, xn_kf, xn_cur, uv_cur, st)
            if E is not None and in_e is not None:
                st.model = Model.ESSENTIAL
                return self._motion_from_essential(kf, rows, E, in_e, uv_kf, xn_kf, xn_cur, uv_cur, st)
            st.reasons.append("no two-view model could be estimated")
            return None
        finally:
            st.timings["pose"] = _ms(t0)

    def _motion_from_essential(self, kf: Keyframe, rows: NDArray[np.int64], E: F64, in_e: NDArray[np.bool_],
                               uv_kf: F64, xn_kf: F64, xn_cur: F64, uv_cur: F64, st: _FrameStats
                               ) -> _Motion | None:
        cfg = self.cfg
        K = kf.camera.K
        R, t_dir, inl = geo.recover_pose(E, uv_kf, uv_cur, K, in_e)
        self._inlier_stats(st, inl, R, xn_kf, xn_cur)
        if st.n_inliers < cfg.min_inliers:
            st.reasons.append(f"too few inliers after cheirality ({st.n_inliers} < {cfg.min_inliers}, RH "
                              f"{st.rh:.2f})")
            return None
        rot_cov = _rotation_cov(cfg.score_sigma_px, K[0, 0], st.n_inliers)
        if not self._has_map(kf):
            return self._initialize(R, t_dir, inl, xn_kf, xn_cur, K, st, "essential matrix")
        return self._track_with_map(kf, rows, R, t_dir, inl, xn_cur, uv_cur, st, rot_cov)

    def _motion_from_homography(self, kf: Keyframe, rows: NDArray[np.int64], H: F64, in_h: NDArray[np.bool_],
                                xn_kf: F64, xn_cur: F64, uv_cur: F64, st: _FrameStats) -> _Motion | None:
        cfg = self.cfg
        K = kf.camera.K
        R_h = geo.rotation_from_homography(H, K)
        self._inlier_stats(st, in_h, R_h, xn_kf, xn_cur)
        if st.n_inliers < cfg.min_inliers:
            st.reasons.append(f"too few homography inliers ({st.n_inliers} < {cfg.min_inliers})")
            return None
        rot_cov = _rotation_cov(cfg.score_sigma_px, K[0, 0], st.n_inliers)
        zero = np.zeros(3)
        if st.median_parallax_deg < cfg.rotation_only_parallax_deg:
            angle = rotation_angle_deg(R_h)
            if angle >= cfg.min_rotation_for_rotation_only_deg:
                st.reasons.append(f"pure rotation: homography explains the motion (RH {st.rh:.2f}, parallax "
                                  f"{st.median_parallax_deg:.2f} deg, rotation {angle:.1f} deg); "
                                  "translation not observable, position held")
                return _Motion(TrackingState.ROTATION_ONLY, R_h, zero, _block_cov(1e-6, rot_cov), in_h)
            if not self._has_map(kf):
                st.reasons.append(f"low parallax ({st.median_parallax_deg:.2f} deg): waiting for baseline, "
                                  "position held")
                return _Motion(TrackingState.INITIALIZING, R_h, zero, _block_cov(1e-6, rot_cov), in_h)
        if not self._has_map(kf):
            planar = geo.pose_from_homography(H, K, xn_kf, xn_cur, in_h, cfg.max_reprojection_error_px,
                                              cfg.min_triangulation_angle_deg)
            if planar is None:
                st.reasons.append("planar scene: homography decomposition ambiguous, waiting for parallax")
                return _Motion(TrackingState.INITIALIZING, R_h, zero, _block_cov(1e-6, rot_cov), in_h)
            R_p, t_p, _ = planar
            if st.median_parallax_deg < cfg.init_min_parallax_deg:
                st.reasons.append(f"planar scene, low parallax ({st.median_parallax_deg:.2f} deg < "
                                  f"{cfg.init_min_parallax_deg}): waiting for baseline, position held")
                return _Motion(TrackingState.INITIALIZING, R_p, zero, _block_cov(1e-6, rot_cov), in_h)
            norm = float(np.linalg.norm(t_p))
            return self._initialize(R_p, t_p / norm, in_h, xn_kf, xn_cur, K, st, "homography (planar scene)")
        st.reasons.append(f"planar or low-parallax view (RH {st.rh:.2f}): pose from map points")
        return self._track_with_map(kf, rows, R_h, None, in_h, xn_cur, uv_cur, st, rot_cov)

    def _inlier_stats(self, st: _FrameStats, inl: NDArray[np.bool_], R: F64, xn_kf: F64, xn_cur: F64) -> None:
        st.n_inliers = int(np.count_nonzero(inl))
        par = geo.parallax_deg(R, xn_kf[inl], xn_cur[inl])
        st.median_parallax_deg = float(np.median(par)) if par.size else math.nan

    def _has_map(self, kf: Keyframe) -> bool:
        return kf.n_map_points >= self.cfg.min_scale_points

    def _initial_baseline(self, dt_s: float) -> float:
        """Length given to the first keyframe baseline of a new map (the scale seam, see module doc).

        The very first map has baseline 1. A map rebuilt after tracking was lost continues the units of
        the old one by assuming the speed of the last keyframe step over the time since the keyframe.
        """
        if self._speed is None or dt_s <= 0.0:
            return 1.0
        return self._speed * dt_s

    def _initialize(self, R: F64, t_dir: F64, inl: NDArray[np.bool_], xn_kf: F64, xn_cur: F64, K: F64,
                    st: _FrameStats, how: str) -> _Motion:
        """Build the first map from the keyframe and this frame, or explain why not yet."""
        cfg = self.cfg
        zero = np.zeros(3)
        rot_cov = _rotation_cov(cfg.score_sigma_px, K[0, 0], max(st.n_inliers, 1))
        hold = _Motion(TrackingState.INITIALIZING, R, zero, _block_cov(1e-6, rot_cov), inl)
        if st.median_parallax_deg < cfg.init_min_parallax_deg:
            st.reasons.append(f"low parallax ({st.median_parallax_deg:.2f} deg < {cfg.init_min_parallax_deg}): "
                              "waiting for baseline, position held")
            return hold
        kf = self._kf
        assert kf is not None
        t = t_dir * self._initial_baseline((st.stamp_ns - kf.stamp_ns) * 1e-9)
        idx = np.flatnonzero(inl)
        tri = geo.triangulate(R, t, xn_kf[idx], xn_cur[idx], K, cfg.max_reprojection_error_px,
                              cfg.min_triangulation_angle_deg)
        n_good = int(np.count_nonzero(tri.good))
        st.n_triangulated = n_good
        st.positive_depth_ratio = tri.positive_depth_ratio
        st.median_reproj_err_px = tri.median_reproj_err_px
        if tri.positive_depth_ratio < cfg.min_positive_depth_ratio:
            st.reasons.append(f"initialization rejected: only {tri.positive_depth_ratio:.0%} of inliers in front "
                              f"of both cameras (< {cfg.min_positive_depth_ratio:.0%})")
            return hold
        if n_good < cfg.min_triangulated:
            st.reasons.append(f"initialization rejected: {n_good} points pass the triangulation gates "
                              f"(< {cfg.min_triangulated})")
            return hold
        full = tri.expanded(idx, xn_kf.shape[0])
        st.reasons.append(f"map initialized from {how}: {n_good} points")
        trans_var = (0.1 * float(np.linalg.norm(t))) ** 2
        return _Motion(TrackingState.TRACKING, R, t, _block_cov(trans_var, rot_cov), inl, new_map=full,
                       make_keyframe=True)

    def _track_with_map(self, kf: Keyframe, rows: NDArray[np.int64], R: F64, t_dir: F64 | None,
                        inl: NDArray[np.bool_], xn_cur: F64, uv_cur: F64, st: _FrameStats, rot_cov: float
                        ) -> _Motion | None:
        """Pose with the map's scale.

        E chosen with enough parallax: E's rotation and direction, scaled by the map points (robust 1-D
        median). Otherwise (H chosen, low parallax, no usable scale): motion-only LM on the map points,
        started from the E estimate or from the previous frame's relative pose.
        """
        cfg = self.cfg
        K = kf.camera.K
        X = kf.X_kf[rows]
        has_depth = inl & np.isfinite(X[:, 0])
        R0, t0 = self._T_cur_kf_prev[:3, :3], self._T_cur_kf_prev[:3, 3]
        est: geo.ScaleEstimate | None = None
        if t_dir is not None:
            R0 = R
            est = geo.scale_from_points(X[has_depth], R, t_dir, xn_cur[has_depth], cfg.min_scale_points)
            if est is not None:
                st.relative_scale = est.scale
                t0 = t_dir * est.scale
        if t_dir is not None and est is not None and st.median_parallax_deg >= cfg.e_pose_min_parallax_deg:
            # With enough parallax the essential matrix fixes rotation and direction better than the
            # map (whose depths carry the previous pairs' noise): take them, with the map's scale.
            par_rad = math.radians(st.median_parallax_deg)
            n = max(st.n_inliers, 1)
            dir_var = (cfg.score_sigma_px / (K[0, 0] * par_rad)) ** 2 / n
            scale_var = est.rel_spread**2 / max(est.n_used, 1)
            trans_var = est.scale**2 * (dir_var + scale_var)
            return _Motion(TrackingState.TRACKING, R, t0, _block_cov(trans_var, rot_cov), inl)
        refined = geo.refine_pose_pnp(X[has_depth], uv_cur[has_depth], K, R0, t0, cfg.max_reprojection_error_px)
        if refined is None:
            st.reasons.append(f"too few map points to carry the scale ({int(np.count_nonzero(has_depth))})")
            return None
        R_r, t_r, keep, cov_pnp = refined
        if np.count_nonzero(keep) < cfg.min_scale_points:
            st.reasons.append(f"too few map points agree with the pose ({int(np.count_nonzero(keep))} < "
                              f"{cfg.min_scale_points})")
            return None
        if not math.isfinite(st.relative_scale):
            st.relative_scale = float(np.linalg.norm(t_r))
        # Covariance of the camera position in the keyframe frame: c = -R^T t.
        cov_t = R_r.T @ cov_pnp[3:, 3:] @ R_r
        cov_r = R_r.T @ cov_pnp[:3, :3] @ R_r
        cov_rel = np.zeros((6, 6))
        cov_rel[:3, :3] = cov_t
        cov_rel[3:, 3:] = cov_r + np.eye(3) * rot_cov
        return _Motion(TrackingState.TRACKING, R_r, t_r, cov_rel, inl)

    # ---------------------------------------------------------------------------------------------
    def _maybe_keyframe(self, motion: _Motion, kf: Keyframe, rows: NDArray[np.int64], pts_cur: F32,
                        xn_cur: F64, gray: NDArray[np.uint8],
                        camera: CameraModel, stamp_ns: int, orb_cur: fe.OrbFeatures | None,
                        st: _FrameStats) -> bool:
        """Decide on a new keyframe; triangulate the keyframe pair into the map when there is parallax."""
        cfg = self.cfg
        tracked_ratio = rows.shape[0] / max(kf.n_features, 1)
        too_old = (stamp_ns - kf.stamp_ns) * 1e-9 > cfg.kf_max_interval_s
        weak = tracked_ratio < cfg.kf_min_tracked_ratio or st.n_inliers < cfg.kf_min_inliers
        parallax = st.median_parallax_deg >= cfg.kf_min_parallax_deg
        R, t = motion.R_cur_kf, motion.t_cur_kf
        X_cur: F64 | None = None
        if motion.new_map is not None:
            X_cur = motion.new_map.X_ref @ R.T + t
            X_cur[~motion.new_map.good] = np.nan
        elif motion.state is TrackingState.TRACKING and (parallax or weak or too_old):
            idx = np.flatnonzero(motion.inliers)
            tri = geo.triangulate(R, t, kf.xn[rows[idx]], xn_cur[idx], kf.camera.K,
                                  cfg.max_reprojection_error_px, cfg.min_triangulation_angle_deg)
            st.n_triangulated = int(np.count_nonzero(tri.good))
            st.positive_depth_ratio = tri.positive_depth_ratio
            st.median_reproj_err_px = tri.median_reproj_err_px
            # Old map points still tracked carry over (moved into the new keyframe); fresh triangulations
            # from this pair replace them where they pass the gates.
            X_cur = kf.X_kf[rows] @ R.T + t
            X_cur[~motion.inliers] = np.nan
            new = np.full((rows.shape[0], 3), np.nan)
            new[idx] = tri.X_ref @ R.T + t
            good = np.zeros(rows.shape[0], bool)
            good[idx] = tri.good
            X_cur[good] = new[good]
            if not parallax and st.n_triangulated == 0:
                st.reasons.append("keyframe without parallax: no new depth")
        elif (motion.state is TrackingState.ROTATION_ONLY and (weak or too_old)) or (
                motion.state is TrackingState.INITIALIZING and (too_old or st.n_tracked < 2 * cfg.min_inliers)):
            # While initialising the keyframe is kept as long as enough features survive: re-anchoring
            # on the tracked ratio alone (ORB matches ~half the keyframe) would reset the parallax.
            # Re-anchor without triangulating: under rotation the existing depths stay valid (t = 0).
            X_cur = kf.X_kf[rows] @ R.T
        if X_cur is None:
            return False
        if motion.state is TrackingState.TRACKING:
            dt_s = (stamp_ns - kf.stamp_ns) * 1e-9
            if dt_s > 0:
                self._speed = float(np.linalg.norm(t)) / dt_s
        if motion.state is TrackingState.TRACKING and st.n_triangulated > 0:
            # The keyframe's point cloud: every map point it holds, in the odometry frame.
            st.points_w = _transform(self._T_w_c, X_cur[np.isfinite(X_cur[:, 0])])
        cov = self._cov_w_c.copy()
        if motion.state is TrackingState.TRACKING:
            cov[:3, :3] += np.eye(3) * (cfg.scale_drift_per_keyframe * float(np.linalg.norm(t))) ** 2
        self._set_keyframe(gray, camera, stamp_ns, cov, pts_cur, X_cur, orb_cur)
        return True

    def _set_keyframe(self, gray: NDArray[np.uint8], camera: CameraModel,
                      stamp_ns: int, cov_w: F64, pts_tracked: F32, X_tracked: F64,
                      orb_cur: fe.OrbFeatures | None) -> None:
        """Make the current frame the reference: keep tracked features (with depth), top up the grid."""
        cfg = self.cfg
        if self._orb is None:
            new = fe.detect_corners(gray, pts_tracked, cfg)
            pts = np.vstack([pts_tracked, new]).astype(np.float32)
            X = np.vstack([X_tracked, np.full((new.shape[0], 3), np.nan)])
            desc = None
        else:
            feats = orb_cur if orb_cur is not None else fe.detect_orb(self._orb, gray, cfg)
            pts, desc = feats.pts, feats.descriptors
            X = np.full((pts.shape[0], 3), np.nan)
            if X_tracked.shape[0]:
                # For ORB the tracked points are a subset of this frame's detections: match by position.
                for p, x in zip(pts_tracked, X_tracked, strict=False):
                    j = int(np.argmin(np.sum((pts - p) ** 2, axis=1)))
                    X[j] = x
        xn = camera.normalize(pts)
        self._kf = Keyframe(self._index, stamp_ns, self._T_w_c.copy(), cov_w, pts, xn, camera.to_pixels(xn), X,
                            desc, camera)
        self._rows = np.arange(pts.shape[0], dtype=np.int64)
        self._pts_prev = pts
        self._gray_prev = gray
        self._T_cur_kf_prev = np.eye(4)
        self._n_keyframes += 1

    def _start_keyframe(self, gray: NDArray[np.uint8], camera: CameraModel,
                        stamp_ns: int, st: _FrameStats, t_start: float) -> FrameResult:
        """First frame, or the first frame after a restart: it becomes the keyframe, pose held."""
        first = self._index == 0
        t0 = time.perf_counter()
        cov = self._cov_w_c.copy()
        if not first:
            cov[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
        self._set_keyframe(gray, camera, stamp_ns, cov, np.zeros((0, 2), np.float32), np.zeros((0, 3)),
                           None)
        st.timings["frontend"] = _ms(t0)
        self._cov_w_c = cov
        st.reasons.append("first frame: reference keyframe set" if first else "new reference keyframe, no map yet")
        return self._result(stamp_ns, TrackingState.INITIALIZING, True, True, st, t_start)

    def _restart_here(self, gray: NDArray[np.uint8], camera: CameraModel,
                      stamp_ns: int, orb_cur: fe.OrbFeatures | None) -> None:
        """Tracking lost: this frame becomes a keyframe at the held pose, the map is dropped."""
        cov = self._cov_w_c.copy()
        cov[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
        cov[3:, 3:] += np.eye(3) * self.cfg.lost_rotation_variance
        self._cov_w_c = cov
        self._set_keyframe(gray, camera, stamp_ns, cov, np.zeros((0, 2), np.float32), np.zeros((0, 3)),
                           orb_cur)
        self._fail_count = 0

    def _on_failure(self, st: _FrameStats) -> bool:
        """Count a frame without a pose; True when tracking must restart from the held pose.

        A frame without a pose is 'lost' for consumers either way; the map is dropped only once the
        failure persists for ``lost_after_frames`` frames, or nothing is left to track.
        """
        self._fail_count += 1
        restart = self._fail_count >= self.cfg.lost_after_frames or st.n_tracked < self.cfg.min_inliers
        if restart:
            st.reasons.append(f"tracking lost after {self._fail_count} frame(s) without a pose: re-initializing "
                              "from the last pose")
        else:
            st.reasons.append(f"no pose this frame ({self._fail_count}/{self.cfg.lost_after_frames}); pose held")
        return restart

    def _result(self, stamp_ns: int, state: TrackingState, has_pose: bool, is_kf: bool, st: _FrameStats,
                t_start: float, *, book: bool = True) -> FrameResult:
        if book:
            self._last_stamp_ns = stamp_ns
        self._keep_state_finite(st)
        cov = self._cov_w_c.copy()
        if not has_pose:
            cov[:3, :3] += np.eye(3) * self.cfg.lost_position_variance
            cov[3:, 3:] += np.eye(3) * self.cfg.lost_rotation_variance
        cov = _floor_cov(cov)
        st.timings["total"] = _ms(t_start)
        kf = self._kf
        n_features = kf.n_features if kf is not None else 0
        for name in _STAT_FIELDS[:1] + _STAT_FIELDS[2:]:  # not measured is NaN, never infinite
            if math.isinf(getattr(st, name)):
                setattr(st, name, math.nan)
        res = FrameResult(
            index=self._index, stamp_ns=int(stamp_ns), state=state, has_pose=has_pose, is_keyframe=is_kf,
            model=st.model, rh=st.rh, n_features=n_features, n_tracked=st.n_tracked, n_inliers=st.n_inliers,
            inlier_ratio=st.n_inliers / st.n_tracked if st.n_tracked else 0.0,
            median_parallax_deg=st.median_parallax_deg, n_triangulated=st.n_triangulated,
            positive_depth_ratio=st.positive_depth_ratio, median_reproj_err_px=st.median_reproj_err_px,
            relative_scale=st.relative_scale, n_keyframes=self._n_keyframes, T_w_c=_frozen(self._T_w_c),
            covariance=_frozen(cov), points_w=_frozen(st.points_w[np.all(np.isfinite(st.points_w), axis=1)]),
            timings_ms=dict(st.timings),
            reason="; ".join(st.reasons), matches=st.matches)
        self._index += 1
        return res


    def _keep_state_finite(self, st: _FrameStats) -> None:
        """The held pose and covariance are finite whatever the input did (a guard: every estimate is
        checked before it is taken, so this only fires on a defect; it says so in the record)."""
        if not np.all(np.isfinite(self._T_w_c)):
            _log.error("non-finite pose held: reset to the origin")
            st.reasons.append("internal: the held pose was not finite; reset to the origin")
            self._T_w_c = np.eye(4)
            self._kf = None
        if not np.all(np.isfinite(self._cov_w_c)):
            _log.error("non-finite covariance held: reset to the 'unknown' covariance")
            st.reasons.append("internal: the held covariance was not finite; reset to the 'unknown' covariance")
            self._cov_w_c = _block_cov(self.cfg.lost_position_variance, self.cfg.lost_rotation_variance)
            self._kf = None


# -------------------------------------------------------------------------------------------------
def _motion_is_finite(m: _Motion) -> bool:
    return bool(np.all(np.isfinite(m.R_cur_kf)) and np.all(np.isfinite(m.t_cur_kf))
                and np.all(np.isfinite(m.cov_rel)))


def downscale(gray: NDArray[np.uint8], camera: CameraModel, max_width: int
              ) -> tuple[NDArray[np.uint8], CameraModel]:
    """The image and camera the pipeline works on: wider images shrunk to ``max_width`` (0: never)."""
    if max_width <= 0 or gray.shape[1] <= max_width:
        return gray, camera
    factor = max_width / gray.shape[1]
    small = cv2.resize(gray, (max_width, round(gray.shape[0] * factor)), interpolation=cv2.INTER_AREA)
    return small, camera.scaled(factor)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _same_camera(a: CameraModel, b: CameraModel) -> bool:
    return (a.width, a.height, a.model) == (b.width, b.height, b.model) and np.array_equal(a.K, b.K) \
        and np.array_equal(a.D, b.D)


def _transform(T_a_b: F64, X_b: F64) -> F64:
    return X_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def _rotation_cov(sigma_px: float, fx: float, n: int) -> float:
    """Per-axis rotation variance (rad^2) of a rotation fitted to n rays with sigma_px pixel noise."""
    return 2.0 * (sigma_px / fx) ** 2 / max(n, 1)


def _block_cov(pos_var: float, rot_var: float) -> F64:
    return np.diag([pos_var] * 3 + [rot_var] * 3)


def _compose_cov(cov_w_kf: F64, T_w_kf: F64, cov_rel: F64, t_cur_kf: F64, R_cur_kf: F64) -> F64:
    """First-order covariance of T_w_c = T_w_kf T_kf_cur (relative covariance given in the keyframe frame).

    The keyframe's rotation uncertainty also moves the current position by ``delta_theta x c`` with
    ``c`` the camera position in the keyframe frame; that lever-arm term is included.
    """
    R_w_kf = T_w_kf[:3, :3]
    A = np.zeros((6, 6))
    A[:3, :3] = R_w_kf
    A[3:, 3:] = R_w_kf
    cov = cov_w_kf + A @ cov_rel @ A.T
    c_w = R_w_kf @ (-R_cur_kf.T @ t_cur_kf)
    lever = geo.skew(c_w)
    cov[:3, :3] = cov[:3, :3] + lever @ cov_w_kf[3:, 3:] @ lever.T
    return cov


def _floor_cov(cov: F64) -> F64:
    """Symmetrize and keep every variance strictly positive (a zero covariance claims certainty)."""
    cov = 0.5 * (cov + cov.T)
    d = np.arange(6)
    cov[d, d] = np.maximum(cov[d, d], 1e-9)
    return cov
