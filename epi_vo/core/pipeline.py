"""The per-frame monocular VO pipeline: a thin shell holding the tracking state between calls of the step.

Both front doors drive this same object: ``epi-vo replay`` (offline, bags) and ``vo_node`` (ROS 2), with
the workers of ``epi_vo.runner``.

Frames and poses
    ``w`` is the odometry frame: the optical frame of the first camera pose (x right, y down,
    z forward). ``T_w_c`` maps current-camera points into ``w``; ``T_w_kf`` the same for the reference
    keyframe. Relative motion ``T_cur_kf`` maps keyframe-camera points into the current camera
    (``X_cur = R_cur_kf X_kf + t_cur_kf``), which is what ``cv2.recoverPose(E, uv_kf, uv_cur)`` returns.

Monocular scale convention
    Translation is observable only up to one global scale. The first map is built with a keyframe
    baseline of length 1 (VO units), and every later frame carries that scale through the map points
    triangulated between the last pair of keyframes; after a loss the new map's baseline continues from
    the last keyframe speed. A metric scale source (``scale``: the floor, wheel odometry) corrects each
    keyframe step and its map into metres once established.

The step and its state
    ``epi_vo.core.step.process(state, frame, env) -> (state, FrameResult)`` is the whole per-frame path; the
    tracking state (``epi_vo.core.state.TrackState``) is one frozen value that each call replaces. This
    object keeps the current one, the config and the workers, and offers the calls the front doors make.

What is never invented
    No parallax: no depth and no keyframe. Pure rotation (the homography explains the motion and no
    parallax is left after removing the rotation): the rotation is published, the position holds.
    Before the map exists the scale is unknown: the position holds and its covariance says so.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import scale as sc
from epi_vo.core import step as sp
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig, validate
from epi_vo.core.decisions import Decision, Note, note
from epi_vo.core.frame import FrameResult, clamp_stamp_ns
from epi_vo.core.state import TrackState, initial_state
from epi_vo.core.step import downscale
from epi_vo.core.workers import InLine, Workers

F64 = NDArray[np.float64]

__all__ = ["VoPipeline", "downscale"]


class VoPipeline:
    """Monocular VO: feed it frames, get one immutable :class:`FrameResult` per frame."""

    def __init__(self, cfg: VoConfig | None = None, workers: Workers | None = None) -> None:
        """``workers``: where the heavy computations run (``epi_vo.core.workers``; the front doors give
        ``epi_vo.runner``'s); by default all in line. The results are the same either way."""
        self.cfg = cfg or VoConfig()
        validate(self.cfg)
        self._workers = workers if workers is not None else InLine()
        self._env = sp.StepEnv.of(self.cfg, self._workers)
        self._state = initial_state(self.cfg)

    @property
    def state(self) -> TrackState:
        """The tracking state after the last frame (frozen)."""
        return self._state

    @property
    def pose(self) -> F64:
        """T_w_c of the last frame (a copy)."""
        return self._state.T_w_c.copy()

    @property
    def scale_status(self) -> sc.ScaleStatus:
        """The scale source's state now: source, metric or VO units, scale and its uncertainty."""
        return self._state.scale.status(self._state.wheel)

    def set_mounting(self, T_base_cam: F64) -> None:
        """The declared camera mounting, camera optical frame -> robot base (REP-103: base z up), from TF or
        the node's camera_xyz / camera_rpy: the floor (``ground_plane``) is sought along the up it implies
        (a level camera's -y without one). Raises ValueError when it is not finite."""
        up_cam = np.asarray(T_base_cam, dtype=np.float64)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        self._state = dataclasses.replace(self._state, scale=self._state.scale.with_mounting_up(up_cam))

    def add_wheel_odometry(self, stamp_ns: int | None, position_xyz: F64) -> sc.WheelSample:
        """One wheel odometry message (position in any fixed odom frame, metres; ``stamp_ns`` None: no ROS
        time) for the ``wheel_odometry`` scale source, in the order messages arrived: which are used is
        ``WheelOdometry.add``'s rule, the same for the node and the replay; the rest are counted."""
        wheel, verdict = self._state.wheel.add(None if stamp_ns is None else int(stamp_ns), position_xyz)
        self._state = dataclasses.replace(self._state, wheel=wheel)
        return verdict

    def reset(self, reason: str = "reset requested") -> None:
        """Restart tracking from the current pose: the next frame becomes a new keyframe, no map; its record
        says ``reason`` (``Decision.RESET``)."""
        self._state = sp.restart(self._state, note(Decision.RESET, text=reason))

    def skip(self, stamp_ns: int, problem: str, note: str = "") -> FrameResult:
        """Record a frame that cannot be used at all and must not touch tracking: its message could not be
        decoded, or its stamp is no valid ROS time. Nothing is processed, the stamp is not booked (the
        next frame is judged against the last good one) and no failure is counted; the record (skipped,
        rejected, with ``problem``; ``note`` is added to the reason) carries ``stamp_ns`` clamped into the
        valid range."""
        why = Note(Decision.FRAME_SKIPPED, (("problem", problem), ("note", note)))
        self._state, result = sp.skip(self._state, clamp_stamp_ns(stamp_ns), why, problem, self.cfg)
        return result

    def reject(self, stamp_ns: int, reason: str) -> FrameResult:
        """Account for a frame that could not be used (corrupt image, unusable calibration, ...).

        The frame gets its record like any other: no pose (held), a large covariance, the reason.
        It counts as a frame without a pose, so persistent bad input ends in a restart from the held
        pose, exactly as lost tracking does.
        """
        state, skipped = sp.check_stamp(self._state, int(stamp_ns), self.cfg)
        if skipped is not None:
            self._state = state
            return skipped
        self._state, result = sp.reject_checked(state, int(stamp_ns), note(Decision.FRAME_REJECTED, problem=reason),
                                                time.perf_counter(), self.cfg)
        return result

    def announce_next(self, gray: NDArray[np.uint8], camera: CameraModel) -> None:
        """The image the next ``process`` call will get: the workers may start tracking into it during
        this frame (``epi_vo.runner``; results identical). Replay knows it; live nodes do not."""
        if gray.ndim == 2 and gray.dtype == np.uint8:
            self._workers.announce_next(downscale(gray, camera, self.cfg.max_image_width)[0])

    def process(self, gray: NDArray[np.uint8], camera: CameraModel, stamp_ns: int) -> FrameResult:
        """Process one grayscale frame taken with ``camera`` at ``stamp_ns`` (``step.process``).

        An image the frontend cannot use (too small, or one OpenCV refuses) gives a rejected frame
        with the reason; the held pose and covariance are then those before the frame.

        Raises:
            CameraModelError: the image size does not match ``camera``.
            ValueError: ``gray`` is not a 2-D uint8 array.
        """
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"expected a 2-D uint8 grayscale image, got {gray.dtype} {gray.shape}")
        camera.check_image_size(gray.shape[1], gray.shape[0])
        self._state, result = sp.process(self._state, sp.Frame(gray, camera, int(stamp_ns)), self._env)
        return result
