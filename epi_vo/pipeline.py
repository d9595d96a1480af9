"""Temporary: the pipeline moved to epi_vo.core (stages); this re-export goes with the layer move."""

from epi_vo.core.frame import MAX_STAMP_NS, FrameResult, Matches, Model, TrackingState
from epi_vo.core.keyframe import Keyframe
from epi_vo.core.pipeline import VoPipeline, downscale

__all__ = ["MAX_STAMP_NS", "FrameResult", "Keyframe", "Matches", "Model", "TrackingState", "VoPipeline",
           "downscale"]
