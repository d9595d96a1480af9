"""The one frame handler of both front doors: decode, process, turn the result into outputs.

``vo_node`` (live) and ``epi-vo replay`` (offline) hand every image to a :class:`FrameHandler` as a
:class:`FrameInput` (the image and camera_info messages, by field name: rclpy's and rosbags' alike) and
get a :class:`HandledFrame` back: the frame's record and its outputs (:mod:`epi_vo.runner.outputs`). The
rule of what a frame yields lives here only, so live and offline cannot drift apart:

* a message that is unusable whatever its pixels (undecodable, a header stamp that is no ROS time) is
  skipped: recorded, tracking untouched (``VoPipeline.skip``);
* an image or calibration that cannot be used (no camera_info, a bad calibration, pixels that do not
  decode) is rejected: recorded as a frame without a pose (``VoPipeline.reject``);
* otherwise the pipeline processes it. When the caller knows the next frame (bag playback) its image is
  decoded first and announced (``VoPipeline.announce_next``): the workers track into it while this frame is
  processed, with the same results.

A runtime change of the pipeline's knobs (:meth:`FrameHandler.apply_config`) starts a new pipeline anchored
at the pose the old one reached: its results are composed onto that pose (and covariance), so the
odometry stays continuous.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core.camera import CameraModel, CameraModelCache
from epi_vo.core.config import VoConfig
from epi_vo.core.errors import CameraModelError, EpiVoError
from epi_vo.core.frame import FrameResult
from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.scale import WheelSample
from epi_vo.core.transforms import invert_T
from epi_vo.io.msgconv import decode_frame, stamp_problem
from epi_vo.runner import make_pipeline
from epi_vo.runner.outputs import FrameOutputs, OutputFrames, OutputMaker

F64 = NDArray[np.float64]
Gray = NDArray[np.uint8]


@dataclass(frozen=True)
class FrameInput:
    """One image as a front door received it.

    ``image``: a sensor_msgs/Image (or CompressedImage when ``compressed``) by field name, None when its
    bytes could not be decoded; ``camera_info`` the CameraInfo paired with it (None: none yet);
    ``stamp_ns`` its header stamp (or where the frame is filed when the stamp is unusable). ``problem``:
    why the message cannot be used whatever its pixels (the handler also checks the header stamp), with
    ``note`` added to the reason; ``no_camera_info``: what the rejection says when ``camera_info`` is None.
    """

    stamp_ns: int
    image: Any
    compressed: bool
    camera_info: Any | None
    problem: str | None = None
    note: str = ""
    no_camera_info: str = "no camera_info"


@dataclass(frozen=True)
class HandledFrame:
    """What one frame gave: its outputs (``outputs.result`` the record), why it was skipped or rejected
    (None when it was not), and the image and camera the pipeline saw (None when it saw none)."""

    outputs: FrameOutputs
    problem: str | None
    gray: Gray | None = None
    camera: CameraModel | None = None

    @property
    def result(self) -> FrameResult:
        return self.outputs.result


@dataclass(frozen=True)
class Anchor:
    """Where a new pipeline starts in the odometry's frame: the pose ``T_w_a`` and covariance ``cov_w_a`` the
    old one reached, and the frame index its first frame continues from."""

    T_w_a: F64
    cov_w_a: F64
    index_offset: int


@dataclass(frozen=True)
class LastPose:
    """The last pose handed out (odometry's frame): what a new pipeline is anchored at."""

    T_w_c: F64
    covariance: F64
    index: int


@dataclass(frozen=True)
class _Ahead:
    """The next frame's image and camera, decoded ahead of its turn (matched by its image message)."""

    image: Any
    gray: Gray
    camera: CameraModel


class FrameHandler:
    """Decode, process, outputs: the per-frame rule of every front door (module doc).

    ``frames``: the outputs' frame ids; ``T_base_cam``: the camera mounting (None: the default, a level
    camera at base; :meth:`set_mounting` when it is known later); ``status_name``: the statuses are named
    ``<status_name>: tracking``; ``announce``: said in the first frame's reason.
    """

    def __init__(self, cfg: VoConfig | None = None, frames: OutputFrames | None = None,
                 T_base_cam: F64 | None = None, *, path_max_length: int = 1000, status_name: str = "epi_vo",
                 announce: str = "") -> None:
        self.cfg = cfg or VoConfig()
        self.status_name = status_name
        self._pipeline = make_pipeline(self.cfg)
        self._outputs = OutputMaker(frames, T_base_cam, path_max_length=path_max_length,
                                    unknown_position_variance=self.cfg.lost_position_variance)
        if T_base_cam is not None:
            self._pipeline.set_mounting(self._outputs.T_base_cam)
        self._cameras = CameraModelCache()
        self._ahead: _Ahead | None = None
        self._anchor: Anchor | None = None
        self._last = LastPose(np.eye(4), np.zeros((6, 6)), -1)
        if announce:
            self._pipeline.reset(announce)

    @property
    def pipeline(self) -> VoPipeline:
        """The pipeline frames go through now (a runtime change replaces it)."""
        return self._pipeline

    @property
    def output(self) -> OutputMaker:
        return self._outputs

    @property
    def last_pose(self) -> LastPose:
        return self._last

    def set_mounting(self, T_base_cam: F64) -> None:
        """The camera mounting (camera optical frame -> base): the odometry is made with it and the floor is
        sought along the up it declares."""
        self._outputs.set_mounting(T_base_cam)
        self._pipeline.set_mounting(self._outputs.T_base_cam)

    def add_wheel_odometry(self, stamp_ns: int | None, position_xyz: F64) -> WheelSample:
        """One wheel odometry message, in arrival order (``VoPipeline.add_wheel_odometry``)."""
        return self._pipeline.add_wheel_odometry(stamp_ns, position_xyz)

    def reset(self, reason: str) -> None:
        """Tracking restarts from the last pose at the next frame, whose reason says ``reason``."""
        self._pipeline.reset(reason)

    def apply_config(self, cfg: VoConfig, announce: str) -> None:
        """A new pipeline with ``cfg``, anchored at the last pose (and covariance): the odometry stays
        continuous, the map starts afresh (a new unit in VO units). ``announce`` is said in the next
        frame's reason."""
        last = self._last
        self._pipeline = make_pipeline(cfg)
        self._pipeline.set_mounting(self._outputs.T_base_cam)
        self._pipeline.reset(announce)
        self._anchor = Anchor(last.T_w_c, last.covariance, last.index + 1)
        self._ahead = None
        self._outputs.unknown_position_variance = cfg.lost_position_variance
        self.cfg = cfg

    def handle(self, frame: FrameInput, next_frame: FrameInput | None = None, hardware_id: str = "") -> HandledFrame:
        """One frame through the pipeline and into its outputs (module doc). Bad input in the frame gives a
        skipped or rejected record with the reason, never an exception (EpiVoError is caught); anything
        else raised is a defect, left to the caller (:meth:`internal_error`)."""
        problem = frame.problem
        if problem is None and frame.image is not None:
            problem = stamp_problem(frame.image.header.stamp)
        if problem is not None:
            # Nothing of the frame is used: tracking is untouched, the next frame is judged against the last one.
            return self._out(self._pipeline.skip(frame.stamp_ns, problem, frame.note), problem, hardware_id)
        gray = camera = None
        try:
            gray, camera = self._decoded(frame)
            if next_frame is not None:
                self._look_ahead(next_frame)
            result = self._pipeline.process(gray, camera, frame.stamp_ns)
        except EpiVoError as exc:
            # Bad input in this frame: it is accounted for like any other (held pose, reason).
            return self._out(self._pipeline.reject(frame.stamp_ns, str(exc)), str(exc), hardware_id)
        return self._out(result, result.problem or None, hardware_id, gray, camera)

    def internal_error(self, frame: FrameInput, exc: Exception, hardware_id: str = "") -> HandledFrame:
        """The record of a frame whose processing raised a defect (not an input problem): the pipeline's state
        may be half-updated, so tracking restarts from the held pose, and the record says it was an internal
        error."""
        self._ahead = None
        self._pipeline.reset(f"internal error in the previous frame ({type(exc).__name__}): tracking restarted "
                             "from the last pose")
        problem = f"internal error: {exc!r}"
        return self._out(self._pipeline.reject(frame.stamp_ns, problem), problem, hardware_id)

    def outputs_of(self, result: FrameResult, hardware_id: str = "") -> FrameOutputs:
        """The outputs of a result made elsewhere (a pipeline driven directly, as the soak does)."""
        return self._outputs.outputs(result, self.status_name, hardware_id)

    # -- inside ---------------------------------------------------------------------------------------
    def _out(self, result: FrameResult, problem: str | None, hardware_id: str, gray: Gray | None = None,
             camera: CameraModel | None = None) -> HandledFrame:
        result = self._anchored(result)
        if not result.skipped:
            self._last = LastPose(result.T_w_c, result.covariance, result.index)
        return HandledFrame(self._outputs.outputs(result, self.status_name, hardware_id), problem, gray, camera)

    def _anchored(self, r: FrameResult) -> FrameResult:
        """A result of the current pipeline in the odometry's frame (after a runtime change)."""
        if self._anchor is None:
            return r
        a = self._anchor
        T_c_a = invert_T(r.T_w_c)  # the new pipeline's w is the anchor
        cov = covm.compose(a.cov_w_a, a.T_w_a, r.covariance, T_c_a[:3, 3], T_c_a[:3, :3])
        points = r.points_w @ a.T_w_a[:3, :3].T + a.T_w_a[:3, 3] if r.points_w.shape[0] else r.points_w
        return dataclasses.replace(r, index=r.index + a.index_offset, T_w_c=a.T_w_a @ r.T_w_c,
                                   covariance=covm.floored(cov), points_w=points)

    def _decode(self, frame: FrameInput) -> tuple[Gray, CameraModel]:
        """The frame's image and camera; EpiVoError naming what is wrong with them."""
        if frame.camera_info is None:
            raise CameraModelError(frame.no_camera_info)
        camera = self._cameras.get(frame.camera_info)  # first: a compressed image of another size is not decoded
        return decode_frame(frame.image, frame.compressed, (camera.width, camera.height)), camera

    def _decoded(self, frame: FrameInput) -> tuple[Gray, CameraModel]:
        """The frame's image, decoded ahead when it was the announced next frame."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None and frame.image is not None and ahead.image is frame.image:
            return ahead.gray, ahead.camera
        return self._decode(frame)

    def _look_ahead(self, frame: FrameInput) -> None:
        """Decode the next frame now and announce it (only when that works: a frame that cannot be decoded
        is decoded again in its turn and rejected there with the reason)."""
        if frame.problem is not None or frame.image is None or stamp_problem(frame.image.header.stamp) is not None:
            return
        try:
            gray, camera = self._decode(frame)
        except EpiVoError:
            return
        self._ahead = _Ahead(frame.image, gray, camera)
        self._pipeline.announce_next(gray, camera)
