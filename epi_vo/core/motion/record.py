"""What the motion stage reads (``MotionContext``), remembers between frames (``MotionMemory``) and returns
(``MotionEstimate``: the ``Motion``, the statistics it measured and its decisions), all frozen."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core import geometry as geo
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Note
from epi_vo.core.frame import Model, TrackingState
from epi_vo.core.keyframe import Keyframe

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]


@dataclass(frozen=True)
class Motion:
    """A pose estimate of the current frame relative to the keyframe, with what justified it."""

    state: TrackingState
    R_cur_kf: F64
    t_cur_kf: F64
    cov_rel: F64  # 6x6 over (position, rotation) of the current camera in the keyframe frame
    inliers: Mask
    new_map: geo.Triangulation | None = None  # set when this frame initialises the map
    # Correspondences judged to move on their own this frame: they made E's consensus but do not fit
    # the epipolar geometry of the pose the map's points gave (None: no such check was made).
    moving: Mask | None = None
    # Relative variance of the map's scale in ``cov_rel`` (along the camera's offset from the keyframe):
    # the map points' depth errors behind it are the same for every frame against this keyframe, so it
    # moves consecutive frames alike (``covariance.shared_scale_part``; 0: none is in ``cov_rel``).
    shared_scale_var: float = 0.0
    # The pose is E's (rotation and direction) fitted to the tracks' positions since the keyframe: the
    # next frame's E is fitted to the same tracks one step on (``covariance.track_step``).
    from_essential: bool = False
    # The pose's covariance at the image noise its tracks gathered since the keyframe (``MotionContext``:
    # ``noise_sq``); ``cov_rel`` is at ``pixel_noise_px``, as the twist takes it. None: ``cov_rel``.
    cov_pose: F64 | None = None
    # E's rotation off the one the map's points give, beyond both estimates' noise (keyframe frame;
    # ``rotation_bias_cov``); None: not measured.
    rotation_excess: F64 | None = None


def is_finite(m: Motion) -> bool:
    return covm.is_finite(m.R_cur_kf, m.t_cur_kf, m.cov_rel, m.cov_rel if m.cov_pose is None else m.cov_pose)


@dataclass(frozen=True)
class MotionContext:
    """What the motion stage reads of the tracking state for one frame."""

    kf: Keyframe
    rows: NDArray[np.int64]  # keyframe row of each correspondence
    xn_cur: F64  # (N, 2) normalized coordinates in the current frame
    uv_cur: F64  # (N, 2) undistorted pixels in the current frame
    T_cur_kf_prev: F64  # the previous frame's pose relative to the keyframe (start of the refinement)
    initial_baseline: Callable[[float], float]  # the scale stage: a new map's baseline after dt seconds
    # The image noise the tracks gathered frame by frame since the keyframe, as a share of pixel_noise_px,
    # squared (``covariance.tracked_since_keyframe``); 1: pixel_noise_px (ORB matches the keyframe directly).
    noise_sq: float = 1.0
    # The tracks were followed from the keyframe's features (KLT): their error is in this image only
    # (``covariance.tracked_since_keyframe``'s ``one_image``); False: matched to the keyframe (ORB).
    tracked: bool = False
    stamp_ns: int = 0  # this frame's stamp (a new map's baseline grows with the time since the keyframe)
    # Tracks born since the keyframe (no keyframe row): (M, 2) undistorted pixels where each would have been
    # at the keyframe had it moved since at the image velocity it showed since it was found, and where it is
    # now. Only the "no camera motion" hypothesis reads them (``static_camera``).
    born_uv: F64 | None = None
    born_uv_cur: F64 | None = None
    # Tracks booked as movers and left out of ``rows``: tracked features no hypothesis of the camera's own
    # motion explains (the "no camera motion" share is of every tracked feature).
    n_booked: int = 0


@dataclass(frozen=True)
class PlaneViews:
    """An ambiguous planar initialisation: the keyframe, its valid solutions' plane normals at the first
    view, the frames waited since and the orientation held at the last of them (``plane_views``); the first
    view's normals' largest standard deviation (deg, nan when unknown), and whether a later view found them
    determined (until then the first view is replaced by each later one)."""

    kf_stamp_ns: int
    normals: tuple[F64, ...]
    waited: int
    held: F64
    sigma_deg: float = math.nan
    anchored: bool = True


@dataclass(frozen=True)
class MotionMemory:
    """What the motion stage carries from one frame to the next."""

    static: bool = False  # the last frame was judged static (hysteresis: staying static is easier)
    plane_views: PlaneViews | None = None
    focal_hint: float | None = None  # the last focal ratio a rotation was taken under (``focal``)


@dataclass(frozen=True)
class MotionEstimate:
    """The motion stage's result for one frame: the motion (None: no pose), which model gave it, what was
    measured on the way, the decisions (``notes``), and the memory for the next frame.

    The stage's paths pass it along, each returning it with what it measured and decided added; a
    statistic not measured is NaN (counts 0)."""

    memory: MotionMemory
    motion: Motion | None = None
    model: Model = Model.NONE
    n_inliers: int = 0
    median_parallax_deg: float = math.nan
    relative_scale: float = math.nan
    static_score: float = math.nan
    focal_ratio: float = math.nan
    n_moving: int = 0
    moving_region: tuple[int, int, int, int] | None = None  # x0, y0, x1, y1 (px) of what moved
    n_triangulated: int = 0
    positive_depth_ratio: float = math.nan
    median_reproj_err_px: float = math.nan
    notes: tuple[Note, ...] = ()
    ms: float = 0.0  # the stage's time

    def but(self, **changes: object) -> MotionEstimate:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]

    def noted(self, n: Note, motion: Motion | None = None) -> MotionEstimate:
        """With ``n`` said (and ``motion`` as the result)."""
        return dataclasses.replace(self, notes=(*self.notes, n), motion=motion)

    def gave(self, motion: Motion | None) -> MotionEstimate:
        return dataclasses.replace(self, motion=motion)


def has_map(cfg: VoConfig, kf: Keyframe) -> bool:
    """The keyframe holds enough map points to carry the scale to a new frame."""
    return kf.n_map_points >= cfg.min_scale_points


def with_inliers(est: MotionEstimate, inl: Mask, R: F64, xn_kf: F64, xn_cur: F64) -> MotionEstimate:
    """``est`` with the inlier count and the median parallax (deg) of the inliers under rotation ``R``."""
    par = geo.parallax_deg(R, xn_kf[inl], xn_cur[inl])
    return est.but(n_inliers=int(np.count_nonzero(inl)), median_parallax_deg=float(np.median(par)) if par.size
                   else math.nan)


def residual_sq(cfg: VoConfig, ctx: MotionContext, R: F64, t_dir: F64, inl: Mask) -> float:
    """The image noise E's inliers show about the pose (``geometry.sampson_rms``) as a share of
    ``pixel_noise_px``, squared, for ``covariance.tracked_since_keyframe``; 0 (not used) unless the tracks
    were followed from the keyframe."""
    if not ctx.tracked:
        return 0.0
    rms = geo.sampson_rms(R, t_dir, ctx.kf.xn[ctx.rows][inl], ctx.xn_cur[inl])
    return 0.0 if rms is None else (rms * ctx.kf.camera.K[0, 0] / cfg.pixel_noise_px) ** 2


def expanded(motion: Motion, use: Mask) -> Motion:
    """A motion estimated on the rows ``use`` spread back over all tracked rows (the others: no
    inlier, no point, not newly moving)."""
    n = use.shape[0]
    inl = np.zeros(n, bool)
    inl[use] = motion.inliers
    moving = None
    if motion.moving is not None:
        moving = np.zeros(n, bool)
        moving[use] = motion.moving
    new_map = motion.new_map.expanded(np.flatnonzero(use), n) if motion.new_map is not None else None
    return dataclasses.replace(motion, inliers=inl, moving=moving, new_map=new_map)
