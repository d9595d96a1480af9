"""The tracking state: everything one frame leaves for the next, as one frozen value.

``epi_vo.core.step`` takes a ``TrackState`` and a frame and returns the state after the frame (and the
frame's record); nothing else persists between frames. Its parts are frozen values too: the keyframe and
its map (``Keyframe``), the scale source (``scale``), the windowed map (``window``), the motion stage's
memory (``motion``), the covariance's scale, calibration and shared rotation terms (``map_scale``, ``calib``,
``rotation_bias``), the
hand-over to a new map (``handover``), the recent keyframes and the last tracked frame a lost frame is
found again against (``recent``, ``last_seen``). Arrays held here are never changed in place: a new state holds
new arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import scale as sc
from epi_vo.core.calibration_cov import CalibrationError
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Note
from epi_vo.core.handover import Handover, HeldStart
from epi_vo.core.keyframe import Keyframe
from epi_vo.core.map_scale import MapScaleCovariance
from epi_vo.core.motion import MotionMemory
from epi_vo.core.patches import PatchTemplates, patch_templates
from epi_vo.core.relocalise import Recent
from epi_vo.core.rotation_bias_cov import RotationBias
from epi_vo.core.wheel_odometry import WheelOdometry
from epi_vo.core.window import WindowedMap

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]


def _no_rows() -> I64:
    return np.zeros(0, np.int64)


def _no_points() -> F32:
    return np.zeros((0, 2), np.float32)


def _no_uv() -> F64:
    return np.zeros((0, 2))


@dataclass(frozen=True)
class Tracks:
    """The live tracks: each one's keyframe row, its position in the previous image, and that image; and
    the tracks born since the keyframe (``step._replenished``), which have no keyframe row: where each was
    found (undistorted pixels) and its position in the previous image."""

    rows: I64 = field(default_factory=_no_rows)
    pts: F32 = field(default_factory=_no_points)
    gray: NDArray[np.uint8] | None = None  # the previous image, KLT's start
    born_uv: F64 = field(default_factory=_no_uv)  # (M, 2) undistorted pixels where each newborn was found
    born_pts: F32 = field(default_factory=_no_points)  # (M, 2) its raw pixels in the previous image
    born_stamp_ns: I64 = field(default_factory=_no_rows)  # (M,) the stamp of the image it was found in
    # The bucketing grid's cells (row-major) that held a still track on a frame of a still camera since the
    # keyframe (empty: none judged yet): where the background is, to be found again where its tracks die.
    still_cells: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))


@dataclass(frozen=True)
class TrackedNoise:
    """The image noise the tracks gathered since keyframe ``kf_index``: the sum of each frame's squared
    share of ``pixel_noise_px`` (``covariance.twist_noise_ratio``), up to frame ``last_index``."""

    kf_index: int = -1
    noise_sq: float = 0.0
    last_index: int = -1


@dataclass(frozen=True)
class LastRelative:
    """The last pose's covariance relative to its keyframe (odometry frame, without its map's scale part),
    for the next frame's step covariance (``covariance.track_step``)."""

    kf_stamp_ns: int
    cov: F64


@dataclass(frozen=True)
class Measured:
    """Whether the last frame's pose and position were measured (not held): its step to the next is then
    measured too."""

    pose: bool = False
    position: bool = False


def _eye4() -> F64:
    return np.eye(4)


def _zeros6() -> F64:
    return np.zeros((6, 6))


def _zeros3() -> F64:
    return np.zeros(3)


@dataclass(frozen=True)
class TrackState:
    """Everything the per-frame step carries from one frame to the next (module doc)."""

    scale: sc.ScaleSource
    handover: Handover
    map_scale: MapScaleCovariance
    calib: CalibrationError
    rotation_bias: RotationBias
    window: WindowedMap
    patches: PatchTemplates | None  # KLT tracks refined against their first image (None: off)
    index: int = 0  # the next frame's index (every frame gets one, skipped ones too)
    last_stamp_ns: int | None = None  # the stamp of the last frame booked (duplicates and jumps back)
    pending: Note | None = None  # a restart's note, said in the next processed frame
    T_w_c: F64 = field(default_factory=_eye4)  # the last pose (held when the last frame had none)
    cov_w_c: F64 = field(default_factory=_zeros6)  # and its covariance (odometry frame, position first)
    kf: Keyframe | None = None  # the reference keyframe and its map (None: the next frame starts one)
    tracks: Tracks = field(default_factory=Tracks)
    T_cur_kf_prev: F64 = field(default_factory=_eye4)  # the last pose relative to the keyframe
    fail_count: int = 0  # consecutive frames without a pose
    n_keyframes: int = 0
    next_id: int = 0  # the next feature track id
    mover_ids: I64 = field(default_factory=_no_rows)  # sorted ids of tracks judged to move on their own
    measured: Measured = field(default_factory=Measured)
    last_pos_w: F64 = field(default_factory=_zeros3)  # position of the last frame with a pose
    held: HeldStart | None = None  # the position held without a map, and what was seen meanwhile (None: a map)
    last_relative: LastRelative | None = None
    tracked_noise: TrackedNoise = field(default_factory=TrackedNoise)
    motion: MotionMemory = field(default_factory=MotionMemory)
    wheel: WheelOdometry = field(default_factory=WheelOdometry)
    recent: tuple[Recent, ...] = ()  # the current map's recent keyframes and images (re-localisation)
    last_seen: Recent | None = None  # the last frame tracked against the keyframe, as a view of its map points


def initial_state(cfg: VoConfig) -> TrackState:
    """The state before the first frame: no keyframe, the origin, the scale source's start."""
    return TrackState(scale=sc.source_from_config(cfg), handover=Handover.from_config(cfg),
                      map_scale=MapScaleCovariance(cfg.scale_drift_per_keyframe),
                      calib=CalibrationError((cfg.focal_length_rel_sigma, cfg.principal_point_sigma_px,
                                              cfg.principal_point_sigma_px, cfg.radial_distortion_k1_sigma)),
                      rotation_bias=RotationBias(cfg.rotation_bias_from_map),
                      window=WindowedMap.create(cfg.ba_window_keyframes, cfg.ba_every_keyframes, cfg.pixel_noise_px),
                      patches=patch_templates(cfg))
