"""The bundled general-motion bag decoded for tests that drive the pipeline frame by frame
(test/core/test_step.py, test_pipeline.py, test_pipeline_faults.py, test/runner/test_workers.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from epi_vo.core.camera import CameraModel
from epi_vo.core.frame import FrameResult
from epi_vo.core.pipeline import VoPipeline
from epi_vo.io import bagio
from epi_vo.io.msgconv import decode_frame

GENERAL_MOTION = Path(__file__).resolve().parents[1] / "bags" / "general_motion" / "bag"
Frames = list[tuple[int, np.ndarray, CameraModel]]


def decoded_frames(bag: Path = GENERAL_MOTION, *,
                   camera_info_messages: bool = False) -> list[tuple[int, np.ndarray, Any]]:
    """(stamp ns, grey image, calibration) of every frame of ``bag``: the calibration as a CameraModel, or as the
    CameraInfo message itself with ``camera_info_messages``."""
    out: list[tuple[int, np.ndarray, Any]] = []
    with bagio.open_camera_bag(bag) as b:
        for f in b.iter_frames():
            cal = f.camera_info_msg if camera_info_messages else CameraModel.from_camera_info(f.camera_info_msg)
            out.append((f.stamp_ns, decode_frame(f.image_msg, b.image_is_compressed), cal))
    return out


def run_frames(pipe: VoPipeline, frames: Frames) -> list[FrameResult]:
    """Every frame through ``pipe`` in order."""
    return [pipe.process(g, c, s) for s, g, c in frames]
