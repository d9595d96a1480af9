"""One frozen config object holding every tuning knob of the pipeline.

The defaults here are the values of ``config/epi_vo.yaml`` (a test keeps them equal). The node
declares one ROS parameter per field by iterating over :func:`config_fields`; the offline tools read
the same YAML (``/**: ros__parameters:`` block) through ``epi_vo.io.params``. :func:`validate`
reports every bad field at once. Thresholds are in pixels of the undistorted (ideal pinhole) image
unless the name says otherwise.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import math
from dataclasses import dataclass, field
from typing import Any

from epi_vo.core.errors import ConfigError


# The modes of the pipeline: each knob's text in a parameter file is its member's value. A string is converted
# once, where the config is made (``VoConfig.__post_init__``, so also ``from_dict`` and the node's parameters);
# code compares members, never text. ``StrEnum``: a member is its text wherever text is written (JSON, YAML,
# ROS parameters).
class Frontend(enum.StrEnum):
    """Where the correspondences come from."""

    KLT = "klt"  # tracked frame to frame (Lucas-Kanade), corners re-detected at keyframes
    ORB = "orb"  # ORB descriptors matched against the keyframe


class ScaleSourceKind(enum.StrEnum):
    """Where metric scale comes from (``epi_vo.core.scale``)."""

    NONE = "none"  # VO units
    GROUND_PLANE = "ground_plane"  # the floor and camera_height_m
    WHEEL_ODOMETRY = "wheel_odometry"  # wheel odometry's distances

    @property
    def metric(self) -> bool:
        """Whether the source can establish metres."""
        return self is not ScaleSourceKind.NONE


class RobustMethod(enum.StrEnum):
    """OpenCV's robust estimators for E and H (``epi_vo.core.geometry.models.ROBUST_METHOD_FLAGS``)."""

    MAGSAC = "magsac"
    RANSAC = "ransac"
    LMEDS = "lmeds"
    USAC_DEFAULT = "usac_default"
    USAC_ACCURATE = "usac_accurate"
    USAC_FAST = "usac_fast"


class BaSolver(enum.StrEnum):
    """Where the windowed bundle adjustment runs."""

    PROCESS = "process"  # a worker process beside the frame loop
    INLINE = "inline"  # in the frame loop


def choices_of(kind: type[enum.StrEnum]) -> tuple[str, ...]:
    """The texts a parameter of the mode ``kind`` may take, in declaration order."""
    return tuple(m.value for m in kind)


def shown(value: object) -> str:
    """``repr`` of a parameter value as a parameter file writes it: a mode by its text (``'orb'``)."""
    return repr(value.value) if isinstance(value, enum.Enum) else repr(value)


SCALE_SOURCES = choices_of(ScaleSourceKind)
ROBUST_METHODS = choices_of(RobustMethod)
FRONTENDS = choices_of(Frontend)
BA_SOLVERS = choices_of(BaSolver)

# The node's own parameters (``NodeOptions`` in epi_vo/node.py, which imports rclpy): valid names in a
# parameter file, which the offline tools (replay, inspect, benchmark, soak) accept and ignore. A test
# keeps this tuple equal to NodeOptions' fields.
NODE_PARAMETER_NAMES: tuple[str, ...] = (
    "frame_id", "child_frame_id", "map_frame_id", "camera_xyz", "camera_rpy", "image_transport", "qos_reliability",
    "qos_depth", "queue_size", "process_every_frame", "queue_max_mb", "publish_tf", "publish_debug_image",
    "path_max_length", "watchdog_timeout_s", "camera_info_wait_s", "hardware_id", "tf_timeout_s",
)
# Parameters every rclpy node declares or reads, also valid in a parameter file; ``qos_overrides`` (a
# mapping, or dotted ``qos_overrides./topic...`` names) configures a node's QoS.
ROS_PARAMETER_NAMES: tuple[str, ...] = ("use_sim_time", "start_type_description_service", "qos_overrides")


def _knob(default: Any, doc: str, lo: float | None = None, hi: float | None = None,
          mode: type[enum.StrEnum] | None = None, off: float | None = None) -> Any:
    """A config field with its doc line and allowed range, kept in the dataclass metadata.

    The range is physical (what a camera, an image, a robot can be), not a sign: every value in it must
    work (``test/core/test_config_ranges.py`` runs the pipeline at the ends of each). ``off``: the one
    value outside ``[lo, hi]`` that is also allowed, meaning "off" or "not set" (its doc line says which).
    ``mode``: the enum of a mode's values (``choices`` in the metadata: their texts).
    """
    return field(default=default, metadata={"doc": doc, "min": lo, "max": hi, "mode": mode,
                                             "choices": None if mode is None else choices_of(mode), "off": off})


@dataclass(frozen=True)
class VoConfig:
    """Every threshold of the pipeline, with its default and one line saying why it exists."""

    # --- frontend -------------------------------------------------------------------------
    frontend: Frontend = _knob(Frontend.KLT, "feature frontend: 'klt' (track + re-detect, fast) or 'orb' (descriptor "
                               "matching)", mode=Frontend)
    max_features: int = _knob(200, "features kept per keyframe, spread over the grid", 20, 5000)
    grid_rows: int = _knob(6, "rows of the bucketing grid that spreads features over the image", 1, 64)
    grid_cols: int = _knob(8, "columns of the bucketing grid", 1, 64)
    min_feature_distance_px: float = _knob(12.0, "minimum distance between detected corners (px)", 1.0, 200.0)
    corner_quality: float = _knob(0.005, "Shi-Tomasi quality level relative to the best corner", 1e-5, 1.0)
    klt_window_px: int = _knob(15, "KLT window size (px, odd)", 5, 101)
    klt_levels: int = _knob(3, "KLT pyramid levels above the base image", 0, 8)
    klt_max_fb_error_px: float = _knob(1.0, "forward-backward KLT consistency gate (px)", 0.01, 50.0)
    klt_patch_refine_px: int = _knob(0, "0: off; else the odd size (px) of the patch each KLT track is refined "
                                     "against in the image it was first seen in, by an affine fit (drift-free "
                                     "tracks, +3-6 ms/frame; core/patches.py)", 5, 101, off=0)
    orb_features: int = _knob(1500, "ORB features detected per frame (frontend 'orb')", 50, 20000)
    orb_ratio: float = _knob(0.8, "Lowe ratio test for ORB kNN matching (with mutual check)", 0.1, 1.0)
    max_image_width: int = _knob(0, "downscale wider images to this width before processing (0: never)", 160, 20000,
                                 off=0)

    # --- two-view models --------------------------------------------------------------------
    essential_method: RobustMethod = _knob(RobustMethod.MAGSAC, "robust estimator for the 5-point essential matrix",
                                           mode=RobustMethod)
    homography_method: RobustMethod = _knob(RobustMethod.USAC_FAST, "robust estimator for the homography "
                                            "(findHomography)", mode=RobustMethod)
    ransac_threshold_px: float = _knob(1.0, "inlier threshold of the E and H robust estimators (px)", 0.05, 50.0)
    ransac_confidence: float = _knob(0.999, "robust estimator confidence", 0.5, 0.999999)
    ransac_max_iters: int = _knob(1000, "robust estimator iteration cap", 10, 100000)
    score_sigma_px: float = _knob(1.0, "pixel noise sigma of the ORB-SLAM style chi-square scoring", 0.05, 50.0)
    pixel_noise_px: float = _knob(0.8, "image noise of the features (1 sigma, px) behind the published covariance, "
                                  "per frame at most; ORB's, and a frame's that measured none (the scoring gates use "
                                  "score_sigma_px)", 0.01, 50.0)
    twist_noise_fb_factor: float = _knob(
        5.5, "each frame's image noise is the one its KLT tracks show: this factor x the per-axis RMS of their "
        "forward-backward errors, between twist_noise_floor_px and pixel_noise_px; the twist takes it (its "
        "rotation; its position between E poses), the pose the sum over the frames since its keyframe "
        "(0: always pixel_noise_px)", 1.0, 100.0, off=0.0)
    twist_noise_floor_px: float = _knob(0.25, "the least image noise a frame's tracks are taken to have (px)",
                                        0.01, 50.0)
    rh_threshold: float = _knob(0.45, "choose H when RH = S_H / (S_H + S_E) exceeds this", 0.0, 1.0)
    min_inliers: int = _knob(25, "fewer model inliers than this: the frame gives no pose", 8, 10000)

    # --- static camera ------------------------------------------------------------------------
    static_min_fraction: float = _knob(
        0.5, "before a map exists: the camera is static when at least this fraction of the tracked features did "
        "not move (chi-square gate at score_sigma_px)", 0.0, 1.0)
    static_min_spread: float = _knob(
        0.5, "the still features must also cover at least this fraction of the occupied cells of a 4x4 image grid",
        0.0,
        1.0)

    # --- degeneracy, parallax and triangulation gates ----------------------------------------
    init_min_parallax_deg: float = _knob(0.5, "median parallax needed to initialise the map (deg)", 0.01, 45.0)
    kf_min_parallax_deg: float = _knob(1.0, "median parallax that makes a new keyframe (deg)", 0.01, 45.0)
    e_pose_min_parallax_deg: float = _knob(
        0.5, "above this median parallax the pose comes from E (scaled by the map), below from the map", 0.0, 45.0)
    plane_e_min_parallax_deg: float = _knob(
        1.0, "with a map and H chosen (a plane dominates), above this median parallax the pose still comes from E, "
        "checked against the map; below, from the map points (deg)", 0.0, 45.0)
    e_map_max_rotation_diff_deg: float = _knob(
        0.3, "E's rotation further than this from the map points' pose: a mover took E's consensus, the map decides "
        "(deg)", 0.01, 45.0)
    min_rotation_for_rotation_only_deg: float = _knob(
        0.5, "rotation needed before a no-parallax motion is called pure rotation (deg)", 0.0, 90.0)
    min_triangulation_angle_deg: float = _knob(0.5, "points seen under a smaller ray angle get no depth (deg)",
                                               0.0, 45.0)
    max_reprojection_error_px: float = _knob(2.0, "triangulated points above this error are rejected (px)",
                                             0.05, 100.0)
    min_positive_depth_ratio: float = _knob(0.8, "cheirality: fraction of inliers in front of both views", 0.0, 1.0)
    min_triangulated: int = _knob(20, "fewer points passing the gates: no map update", 3, 10000)
    min_scale_points: int = _knob(8, "map points needed to carry the scale to a new frame", 3, 10000)

    # --- keyframes ---------------------------------------------------------------------------
    kf_min_tracked_ratio: float = _knob(0.5, "new keyframe when fewer of the keyframe's features are tracked", 0.0, 1.0)
    kf_min_inliers: int = _knob(60, "new keyframe when model inliers fall below this", 8, 10000)
    kf_max_interval_s: float = _knob(2.0, "new keyframe at the latest after this time (s)", 0.01, 3600.0)

    # --- windowed bundle adjustment -------------------------------------------------------------
    ba_window_keyframes: int = _knob(0, "keyframes adjusted together by the windowed bundle adjustment (GTSAM; "
                                     "it needs three); 0: off", 3, 50, off=0)
    ba_every_keyframes: int = _knob(3, "run the windowed bundle adjustment every this many tracking keyframes",
                                    1, 1000)
    ba_solver: BaSolver = _knob(
        BaSolver.PROCESS, "where the windowed bundle adjustment runs: 'process' (a worker process beside the frame "
        "loop) or 'inline' (in it); its result is applied at the next keyframe either way, so both give the same "
        "poses", mode=BaSolver)
    ba_wait: bool = _knob(True, "at the keyframe after an adjustment started, wait for its result if the worker is "
                          "not done: a replay gives the same poses run to run; false: never wait, a late result is "
                          "applied at the first keyframe after it is back (a live node keeps its frame rate; the "
                          "poses then depend on the worker's speed)")

    # --- tracking lost -------------------------------------------------------------------------
    lost_after_frames: int = _knob(3, "consecutive frames without a pose before tracking is declared lost", 1, 1000)
    relocalise_keyframes: int = _knob(
        3, "recent keyframes (with their images) a lost frame is found again against before a new map is started "
        "(core/relocalise.py): the same map, trajectory and scale continue; 0: never", 1, 20, off=0)
    # What the platform can do bounds the motion a pose held through a loss may have missed (core/handover.py).
    max_speed_mps: float = _knob(
        20.0, "the platform's largest plausible speed (m/s): a map restarted after a loss covers in its position "
        "covariance what this allows over the time without a map (metric scale; generous: set your robot's)",
        0.01, 400.0)
    max_accel_mps2: float = _knob(
        10.0, "the platform's largest plausible acceleration (m/s^2): over a short loss the speed stays near the "
        "last one, within this", 0.01, 1000.0)
    max_turn_rate_deg_s: float = _knob(
        180.0, "the platform's largest plausible turn rate about any axis (deg/s), for the rotation covariance "
        "after a loss as max_speed_mps for the position (at most a half turn)", 0.1, 3600.0)
    max_turn_accel_deg_s2: float = _knob(
        360.0, "the platform's largest plausible angular acceleration (deg/s^2), as max_accel_mps2", 0.1, 100000.0)

    # --- metric scale ----------------------------------------------------------------------------
    scale_source: ScaleSourceKind = _knob(
        ScaleSourceKind.NONE, "where metric scale comes from: 'none' (VO units), 'ground_plane' (needs "
        "camera_height_m) or 'wheel_odometry' (reads wheel_odometry_topic)", mode=ScaleSourceKind)
    camera_height_m: float = _knob(0.0, "height of the camera's optical centre above the floor (m; ground_plane; "
                                   "0: not set)", 0.01, 100.0, off=0.0)
    camera_height_rel_sigma: float = _knob(
        0.02, "relative uncertainty (1 sigma) of camera_height_m: common to every floor measurement, so the metric "
        "scale is never known better (ground_plane)", 0.0, 1.0)
    wheel_odometry_topic: str = _knob(
        "odom", "nav_msgs/Odometry topic of the wheel odometry (wheel_odometry); relative names resolve in the "
        "node's namespace (epi-vo replay reads a bag's as the root namespace's: odom is /odom)")
    wheel_odometry_rel_sigma: float = _knob(
        0.03, "relative calibration error (1 sigma) of the wheel distances (tyre radius): common to every keyframe, "
        "so the metric scale is never known better; their random error is measured from their spread", 0.001, 1.0)
    wheel_odometry_timeout_s: float = _knob(
        0.5, "wheel messages further than this from an image stamp are stale: the last scale is held (s)", 0.01,
        60.0)
    wheel_odometry_noise_m: float = _knob(
        0.01, "the wheels' random distance error over one scale measurement (m, 1 sigma: encoder resolution, slip, "
        "stamp jitter); it averages out over keyframes, their calibration error (wheel_odometry_rel_sigma) does not",
        0.0001, 1.0)
    wheel_odometry_window_m: float = _knob(
        0.5, "each scale measurement spans the last keyframe steps until the wheels covered this distance (m): "
        "longer steps drown the wheel noise and the camera's lever arm in turns", 0.01, 100.0)
    ground_max_tilt_deg: float = _knob(35.0, "floor normals further than this from the camera's up axis are no "
                                       "floor (deg)", 1.0, 89.0)
    ground_inlier_ratio: float = _knob(0.04, "floor inliers lie within this fraction of the camera height", 0.001,
                                       0.5)
    ground_min_points: int = _knob(8, "map points on the floor needed to measure the scale", 3, 10000)
    ground_fit_min_rel_sigma: float = _knob(
        0.005, "the least relative uncertainty (1 sigma) one floor measurement of the camera height is given: the "
        "floor's unevenness under the fit (the fits' spread raises it)", 0.0001, 0.5)

    # --- covariance ----------------------------------------------------------------------------
    scale_drift_per_keyframe: float = _knob(
        0.01, "relative scale drift of the map per keyframe (1 sigma, a random walk): the scale filter's process "
        "noise, and in VO units the position covariance's scale term, grown coherently along the path", 0.0, 1.0)
    # The calibration's uncertainty (1 sigma): a CameraInfo is a measurement, off on a real camera by about
    # what the scenario distribution draws (docs/distribution.md: principal point up to 4 px, focal length up
    # to 1.5 %, an undeclared k1 up to 0.05; these defaults are about their RMS). 0 declares it exact.
    principal_point_sigma_px: float = _knob(
        2.0, "uncertainty of the calibration's principal point (1 sigma, px of CameraInfo, each axis): its effect "
        "on every pose, grown coherently along the path in the pose covariance (0: exact)", 0.0, 100.0)
    focal_length_rel_sigma: float = _knob(
        0.01, "uncertainty of the calibration's focal length (1 sigma, relative): its effect on every pose, grown "
        "coherently along the path in the pose covariance (0: exact)", 0.0, 0.5)
    radial_distortion_k1_sigma: float = _knob(
        0.025, "radial distortion the calibration may leave undeclared (1 sigma of k1, normalised image "
        "coordinates): its effect on every pose, grown coherently along the path in the pose covariance "
        "(0: the lens model taken as exact)", 0.0, 1.0)
    rotation_bias_from_map: bool = _knob(
        True, "take the keyframe steps' rotation error beyond their noise, as the map's points measure it against "
        "E's rotation on every frame, as an error the steps share, grown along the path in the pose covariance "
        "(off: the steps' errors independent)")
    lost_position_variance: float = _knob(1.0e4, "position variance reported when no pose can be justified",
                                          1.0, 1.0e12)
    lost_rotation_variance: float = _knob(1.0e2, "rotation variance (rad^2) reported when no pose can be justified "
                                          "(a turn known within a radian is no unknown one)", 1.0, 1.0e6)

    def __post_init__(self) -> None:
        """A mode given as its text becomes its member: the one conversion (a text no member has is left for
        :func:`validate` to name)."""
        for f in _MODE_FIELDS:
            value = getattr(self, f.name)
            mode = f.metadata["mode"]
            if isinstance(value, str) and not isinstance(value, mode) and value in choices_of(mode):
                object.__setattr__(self, f.name, mode(value))


def config_fields() -> tuple[dataclasses.Field[Any], ...]:
    """The config fields in declaration order (for declaring ROS parameters)."""
    return dataclasses.fields(VoConfig)


PIPELINE_NAMES: tuple[str, ...] = tuple(f.name for f in config_fields())
_MODE_FIELDS = tuple(f for f in config_fields() if f.metadata.get("mode") is not None)


def field_doc(f: dataclasses.Field[Any]) -> str:
    """The field's doc line and, for a number, its allowed range (``[lo to hi]``, ``[0, or lo to hi]``)."""
    doc = str(f.metadata.get("doc", ""))
    lo, hi, off = f.metadata.get("min"), f.metadata.get("max"), f.metadata.get("off")
    if lo is None or hi is None:
        return doc
    return f"{doc} [{'' if off is None else f'{off:g}, or '}{lo:g} to {hi:g}]"


def allowed_range(f: dataclasses.Field[Any]) -> tuple[float, float] | None:
    """The smallest and largest value ``f`` takes (its ``off`` value included), None for a non-number."""
    lo, hi, off = f.metadata.get("min"), f.metadata.get("max"), f.metadata.get("off")
    if lo is None or hi is None:
        return None
    return (lo if off is None else min(lo, off)), (hi if off is None else max(hi, off))


def validate(cfg: VoConfig) -> None:
    """Raise :class:`ConfigError` naming every bad field at once."""
    problems: list[str] = []
    for f in config_fields():
        value = getattr(cfg, f.name)
        kind = type(f.default)
        if (mode := f.metadata.get("mode")) is not None:
            if not isinstance(value, mode):
                problems.append(f"{f.name}={shown(value)} (choose one of {', '.join(choices_of(mode))})")
            continue
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) != isinstance(f.default, bool):
            problems.append(f"{f.name}={value!r} (expected {kind.__name__})")
            continue
        if isinstance(value, float) and not math.isfinite(value):
            problems.append(f"{f.name}={value!r} (not finite)")
            continue
        lo, hi = f.metadata.get("min"), f.metadata.get("max")
        off = f.metadata.get("off")
        if off is not None and value == off:
            continue
        if lo is not None and value < lo:
            problems.append(f"{f.name}={value!r} (minimum {lo}" + ("" if off is None else f", or {off:g}") + ")")
        if hi is not None and value > hi:
            problems.append(f"{f.name}={value!r} (maximum {hi})")
    if isinstance(cfg.klt_window_px, int) and cfg.klt_window_px % 2 == 0:
        problems.append(f"klt_window_px={cfg.klt_window_px} (must be odd)")
    if isinstance(cfg.klt_patch_refine_px, int) and cfg.klt_patch_refine_px and cfg.klt_patch_refine_px % 2 == 0:
        problems.append(f"klt_patch_refine_px={cfg.klt_patch_refine_px} (0, or odd)")
    if cfg.scale_source is ScaleSourceKind.GROUND_PLANE and isinstance(cfg.camera_height_m, float) \
            and not cfg.camera_height_m > 0:
        problems.append("scale_source='ground_plane' needs camera_height_m > 0 (height of the camera's optical "
                        "centre above the floor, m)")
    if cfg.scale_source is ScaleSourceKind.WHEEL_ODOMETRY and isinstance(cfg.wheel_odometry_topic, str) \
            and not cfg.wheel_odometry_topic.strip():
        problems.append("scale_source='wheel_odometry' needs wheel_odometry_topic (a nav_msgs/Odometry topic)")
    if problems:
        raise ConfigError("invalid epi_vo parameters: " + "; ".join(problems))


def live_advice(cfg: VoConfig) -> list[str]:
    """What a live node should be told about a valid configuration that serves replay better than live
    use (the node logs each as a warning when it starts a session)."""
    advice = []
    if cfg.ba_window_keyframes > 0 and cfg.ba_wait:
        advice.append("ba_window_keyframes > 0 with ba_wait true: at each keyframe after an adjustment started the "
                      "frame loop waits for its result (deterministic replay; live, a frame waits whenever an "
                      "adjustment takes longer than the keyframe interval: on a slow 2-core machine 3-7 of 42 "
                      "for ground_robot ground_plane at 15 Hz); set ba_wait: false for a live node")
    return advice


def is_parameter_name(name: object) -> bool:
    """True for a name a parameter file may hold: a pipeline knob, a node option or a ROS node parameter."""
    if not isinstance(name, str):
        return False
    if name in PIPELINE_NAMES or name in NODE_PARAMETER_NAMES or name in ROS_PARAMETER_NAMES:
        return True
    return name.startswith("qos_overrides.")


#: Parameters that existed and were removed, with what took their place: a parameter file written for an
#: older epi_vo that still sets one is refused with this reason rather than a bare "unknown".
REMOVED_PARAMETERS: dict[str, str] = {
    "rotation_only_parallax_deg": "removed: pure rotation is chosen by GRIC against the homography; "
                                  "delete the key",
    "init_max_rotation_sigma_deg": "removed: a first map is not refused for E's rotation sigma (a still "
                                   "camera's moving object is booked as a mover instead); delete the key",
    "init_max_direction_sigma_deg": "removed: a first map is not refused for E's direction sigma (a still "
                                    "camera's moving object is booked as a mover instead); delete the key",
}


def unknown_names_text(names: list[str], candidates: tuple[str, ...] | None = None) -> str:
    """'a (did you mean b?), c': each unknown name with its closest parameter name when one is close, or
    why it was removed (:data:`REMOVED_PARAMETERS`)."""
    pool = list(candidates) if candidates is not None else [*PIPELINE_NAMES, *NODE_PARAMETER_NAMES,
                                                            *ROS_PARAMETER_NAMES]
    parts = []
    for name in sorted(names, key=str):
        if str(name) in REMOVED_PARAMETERS:
            parts.append(f"{name} ({REMOVED_PARAMETERS[str(name)]})")
            continue
        close = difflib.get_close_matches(str(name), pool, n=1)
        parts.append(f"{name} (did you mean {close[0]}?)" if close else str(name))
    return ", ".join(parts)


def _as_float(value: Any) -> Any:
    """Widen ints, and read strings like '1e4' as ROS 2's YAML parser does (PyYAML leaves them str)."""
    if isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def from_dict(values: dict[str, Any], base: VoConfig | None = None) -> VoConfig:
    """Build a validated config from ``{name: value}``; unknown names are errors, ints widen to floats."""
    base = base or VoConfig()
    known = {f.name: f for f in config_fields()}
    unknown = sorted(set(values) - set(known))
    kwargs: dict[str, Any] = {}
    for name, value in values.items():
        if name in known and isinstance(known[name].default, float):
            value = _as_float(value)
        if name in known:
            kwargs[name] = value
    cfg = dataclasses.replace(base, **kwargs)
    try:
        validate(cfg)
    except ConfigError as exc:
        if unknown:
            raise ConfigError(f"{exc}; unknown parameters: {unknown_names_text(unknown, PIPELINE_NAMES)}") from None
        raise
    if unknown:
        raise ConfigError("invalid epi_vo parameters: unknown parameters: "
                          + unknown_names_text(unknown, PIPELINE_NAMES))
    return cfg
