"""The published covariance at a keyframe frame (``keyframing.maybe_keyframe``, ``publish``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from epi_vo.core import covariance as covm
from epi_vo.core.camera import CameraModelCache
from epi_vo.core.config import VoConfig
from epi_vo.core.frame import TrackingState
from epi_vo.core.pipeline import VoPipeline
from epi_vo.io import bagio
from epi_vo.io.msgconv import decode_frame

BAG = Path(__file__).resolve().parents[2] / "bags" / "general_motion"


def test_a_keyframe_frame_publishes_the_covariance_its_keyframe_holds() -> None:
    """A keyframe takes the map's scale term for its step (``MapScaleCovariance.keyframe_cov``); the frame
    that becomes the keyframe publishes that covariance too, rather than one without it that the frames on
    either side both exceed along the path. Exact calibration declared and the map's measure of the steps'
    shared rotation error off, so nothing else is added."""
    cfg = VoConfig(focal_length_rel_sigma=0.0, principal_point_sigma_px=0.0, radial_distortion_k1_sigma=0.0,
                   rotation_bias_from_map=False)
    pipe, cameras = VoPipeline(cfg), CameraModelCache()
    checked = 0
    with bagio.open_camera_bag(BAG / "bag") as bag:
        for i, f in enumerate(bag.iter_frames()):
            if i >= 120:
                break
            r = pipe.process(decode_frame(f.image_msg, bag.image_is_compressed), cameras.get(f.camera_info_msg),
                             f.stamp_ns)
            if r.is_keyframe and r.state is TrackingState.TRACKING and r.has_pose and pipe.state.kf is not None:
                expected = covm.floored(pipe.state.kf.cov_w_kf)
                np.testing.assert_allclose(r.covariance[:3, :3], expected[:3, :3], rtol=1e-9, atol=1e-15)
                checked += 1
    assert checked >= 3
