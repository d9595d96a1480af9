"""The runner's workers (epi_vo.runner.workers): H beside E and KLT into the next image on a worker thread give
the records of the pipeline run in line, bit for bit; an OpenCV error in work done ahead rejects the frame it was
for."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from bag_frames import decoded_frames, run_frames

from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision
from epi_vo.core.frame import FrameResult, TrackingState
from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.selection import select_model
from epi_vo.runner import klt_ahead, make_pipeline
from epi_vo.runner.klt_ahead import KltAhead
from epi_vo.runner.workers import Threaded

CFG = VoConfig()
Frames = list[tuple[int, np.ndarray, CameraModel]]


@pytest.fixture(scope="module")
def frames() -> Frames:
    return decoded_frames()


@pytest.mark.parametrize("scene_name", ["general_scene_outliers", "planar_scene", "rotation_scene"])
def test_h_on_the_worker_thread_gives_the_same_selection(scene_name: str, request: pytest.FixtureRequest) -> None:
    """The runner estimates H on its worker thread while E is estimated: the selection is the one
    ``select_model`` makes in line, to the bit (the robust estimators' sampling does not depend on the
    thread), call after call."""
    s = request.getfixturevalue(scene_name)
    workers = Threaded(CFG)
    inline = select_model(s.uv_ref_obs, s.uv_cur_obs, s.K, CFG)
    for _ in range(3):
        par = workers.select_model(s.uv_ref_obs, s.uv_cur_obs, s.K, CFG, None)
        assert par.model is inline.model and par.rh == inline.rh
        for field in ("E", "H", "F", "inliers_e", "inliers_h", "inliers_static"):
            np.testing.assert_array_equal(getattr(par, field), getattr(inline, field))
        assert par.score_static == inline.score_static


def test_tracking_ahead_gives_the_records_of_tracking_in_line(frames: list[tuple[int, np.ndarray, CameraModel]],
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """``announce_next`` (replay's lookahead): KLT into the next image runs on the runner's worker thread
    while the current frame is processed. Every record is the one tracking in line gives, keyframes included (their
    new corners are tracked when the frame comes); the worker's time is recorded apart (``klt_ahead``)."""
    plain = run_frames(VoPipeline(), frames)
    used: list[bool] = []
    take = KltAhead.take

    def spy(self: KltAhead, *args: object) -> object:
        got = take(self, *args)  # type: ignore[arg-type]
        used.append(got is not None)
        return got

    monkeypatch.setattr(KltAhead, "take", spy)
    pipe = make_pipeline()
    ahead = []
    for i, (s, g, c) in enumerate(frames):
        if i + 1 < len(frames):
            pipe.announce_next(frames[i + 1][1], frames[i + 1][2])
        ahead.append(pipe.process(g, c, s))
    assert sum(used) >= len(frames) - 3  # every frame but the first two had its tracking done ahead
    assert sum(r.is_keyframe for r in plain) >= 5  # ... across keyframes too
    for a, b in zip(plain, ahead, strict=True):
        ra, rb = a.to_record(), b.to_record()
        ra.pop("timings_ms"), rb.pop("timings_ms")
        assert ra == rb
    assert [("klt_ahead" in r.timings_ms) for r in ahead[1:]] == used  # the worker's time, apart
    # Another image than the one announced: the work done ahead is dropped, the frame tracked in line. The
    # same pixels in another array are the same image: the work is used.
    for announced, used_it in ((frames[3][1], False), (frames[2][1].copy(), True)):
        pipe = make_pipeline()
        pipe.process(frames[0][1], frames[0][2], frames[0][0])
        pipe.announce_next(announced, frames[2][2])
        pipe.process(frames[1][1], frames[1][2], frames[1][0])
        used.clear()
        r = pipe.process(frames[2][1], frames[2][2], frames[2][0])
        assert used == [used_it]
        ra, rb = r.to_record(), plain[2].to_record()
        ra.pop("timings_ms"), rb.pop("timings_ms")
        assert ra == rb


def test_opencv_failure_in_tracking_done_ahead_rejects_the_frame_it_belongs_to(frames: Frames,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """KLT started ahead (replay's lookahead) that OpenCV refuses: the frame it was for is rejected with the
    reason, not the frame during which it ran; tracking comes back afterwards."""
    pipe = make_pipeline()
    cams = [c for _, _, c in frames]

    def run(k: int) -> FrameResult:
        if k + 1 < len(frames):
            pipe.announce_next(frames[k + 1][1], cams[k + 1])
        return pipe.process(frames[k][1], cams[k], frames[k][0])

    before = [run(k) for k in range(19)]

    def broken(*args: object, **kwargs: object) -> None:
        raise cv2.error("OpenCV(5.0.0) lkpyramid.cpp:1: error: (-215:Assertion failed) test in 'calcOpticalFlowPyrLK'")

    monkeypatch.setattr(klt_ahead, "timed_klt", broken)  # the job started during frame 19, for frame 20
    r19 = run(19)
    monkeypatch.undo()
    assert r19.has_pose and Decision.OPENCV_FAILED not in r19.decisions
    r20 = run(20)
    assert not r20.has_pose and "OpenCV could not process this frame" in r20.reason and "Assertion failed" in r20.reason
    np.testing.assert_array_equal(r20.T_w_c, r19.T_w_c)
    after = [run(k) for k in range(21, len(frames))]
    assert before[-1].state is TrackingState.TRACKING and any(x.state is TrackingState.TRACKING for x in after)
