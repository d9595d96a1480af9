"""The per-frame step (epi_vo.core.step) is a function of the tracking state: the state is one frozen value,
the step returns the next one and leaves the one it was given as it was."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from bag_frames import decoded_frames

from epi_vo.core import step as sp
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.frame import FrameResult, TrackingState
from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.state import TrackState, initial_state
from epi_vo.core.workers import InLine

Frames = list[tuple[int, np.ndarray, CameraModel]]


@pytest.fixture(scope="module")
def frames() -> Frames:
    return decoded_frames()


def _record(r: FrameResult) -> dict[str, object]:
    rec = r.to_record()
    rec.pop("timings_ms")
    return rec


def _run(state: TrackState, env: sp.StepEnv, frames: Frames) -> tuple[TrackState, list[FrameResult]]:
    results = []
    for s, g, c in frames:
        state, r = sp.process(state, sp.Frame(g, c, s), env)
        results.append(r)
    return state, results


def test_the_step_leaves_the_state_it_was_given(frames: Frames) -> None:
    """The same state and frame give the same record and the same next state, however often; the state
    given is not changed (a record can be replayed from any earlier state)."""
    cfg = VoConfig()
    env = sp.StepEnv.of(cfg, InLine())
    state, _ = _run(initial_state(cfg), env, frames[:20])
    T_before, kf_before, scale_before = state.T_w_c.copy(), state.kf, state.scale
    a_state, a = sp.process(state, sp.Frame(frames[20][1], frames[20][2], frames[20][0]), env)
    b_state, b = sp.process(state, sp.Frame(frames[20][1], frames[20][2], frames[20][0]), env)
    assert _record(a) == _record(b) and a.state is TrackingState.TRACKING
    np.testing.assert_array_equal(a_state.T_w_c, b_state.T_w_c)
    assert a_state.index == b_state.index == state.index + 1
    np.testing.assert_array_equal(state.T_w_c, T_before)  # unchanged
    assert state.kf is kf_before and state.scale is scale_before
    # Going on from either gives the records a single run gives.
    _, rest_a = _run(a_state, env, frames[21:30])
    _, rest_b = _run(b_state, env, frames[21:30])
    _, single = _run(initial_state(cfg), env, frames[:30])
    assert [_record(r) for r in rest_a] == [_record(r) for r in rest_b] == [_record(r) for r in single[21:30]]


def test_the_state_is_one_frozen_value(frames: Frames) -> None:
    pipe = VoPipeline()
    first = pipe.state
    pipe.process(frames[0][1], frames[0][2], frames[0][0])
    assert pipe.state is not first and first.index == 0 and pipe.state.index == 1
    with pytest.raises(dataclasses.FrozenInstanceError):
        pipe.state.fail_count = 3  # type: ignore[misc]
    frozen_fields = [f.name for f in dataclasses.fields(TrackState)]
    assert {"T_w_c", "cov_w_c", "kf", "scale", "window", "motion", "wheel", "handover"} <= set(frozen_fields)
    assert all(dataclasses.is_dataclass(getattr(pipe.state, name)) and
               type(getattr(pipe.state, name)).__dataclass_params__.frozen
               for name in ("scale", "window", "motion", "wheel", "handover", "map_scale", "calib", "tracks"))


def test_a_reject_and_a_restart_are_values_too(frames: Frames) -> None:
    cfg = VoConfig()
    env = sp.StepEnv.of(cfg, InLine())
    state, _ = _run(initial_state(cfg), env, frames[:10])
    restarted = sp.restart(state, note(Decision.RESET, text="operator"))
    assert state.kf is not None and restarted.kf is None and restarted.pending is not None
    after, r = sp.reject_checked(state, frames[10][0], note(Decision.FRAME_REJECTED, problem="bad"), 0.0, cfg)
    assert not r.has_pose and r.problem == "bad" and after.fail_count == state.fail_count + 1
    assert state.fail_count == 0 and after.index == state.index + 1


def _still_camera_with_a_mover_frames(n: int = 80) -> Frames:
    """A still camera (640x480) over a textured background; a textured block 350 px wide and as high as the
    image crosses it left to right at 6 px a frame, occluding the background's tracks one after the other;
    the exposure steps up 20 % half-way."""
    import cv2

    rng = np.random.default_rng(1)

    def texture(h: int, w: int, sigma: float) -> np.ndarray:
        img = cv2.GaussianBlur(rng.integers(0, 256, (h, w), dtype=np.uint8), (0, 0), sigma)
        return cv2.normalize(img, None, 30, 220, cv2.NORM_MINMAX).astype(np.float64)

    background, block = texture(480, 640, 2.0), texture(480, 350, 1.5)
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    camera = CameraModel.create(640, 480, K, [])
    frames = []
    for i in range(n):
        img = background.copy()
        x = -350 + 6 * i
        a, b = max(x, 0), min(x + 350, 640)
        if b > a:
            img[:, a:b] = block[:, a - x:b - x]
        gain = 1.0 if i < 40 else 1.2
        gray = np.clip(np.round(img * gain + rng.normal(0.0, 1.5, img.shape)), 0, 255).astype(np.uint8)
        frames.append((1_000_000_000 + i * 66_666_667, gray, camera))
    return frames


def _still_camera_with_a_mover() -> list[FrameResult]:
    vo = VoPipeline(VoConfig())
    return [vo.process(gray, camera, stamp) for stamp, gray, camera in _still_camera_with_a_mover_frames()]


def test_a_still_cameras_tracks_are_found_again_where_a_mover_ended_them() -> None:
    """The block occludes the keyframe's background tracks one cell after the other as it crosses. The cells
    that held a still track since the keyframe and hold none now are refilled with newborn tracks
    (``step._replenished``: the cells are remembered from frame to frame until the next keyframe); here they
    are found on the block that took those cells, and move with it."""
    cfg = VoConfig()
    env = sp.StepEnv.of(cfg, InLine())
    state = initial_state(cfg)
    born = []
    for i, (stamp, gray, camera) in enumerate(_still_camera_with_a_mover_frames(30)):
        state, r = sp.process(state, sp.Frame(gray, camera, stamp), env)
        assert i == 0 or (r.state is TrackingState.STATIC and not r.is_keyframe)
        born.append(state.tracks.born_pts.shape[0])
        edge = -350 + 6 * i  # the block spans x = edge .. edge + 350 px
        on_block = state.tracks.born_pts[:, 0] < edge + 350 + 10
        assert np.all(on_block)
        found_at = state.tracks.born_uv[:, 0]
        assert np.all(state.tracks.born_pts[:, 0] >= found_at)  # they moved right with it, never left
    assert max(born) >= 20


def test_a_still_camera_with_an_exposure_step_and_a_mover_does_not_move() -> None:
    """The block holds up to half of the tracks while it crosses, and the exposure steps meanwhile. The camera
    stays static at the origin on every frame (E alone would explain the block's motion: with no rotation
    every still point fits any translation)."""
    results = _still_camera_with_a_mover()
    assert all(r.state is TrackingState.STATIC for r in results[1:])
    assert all(np.all(r.T_w_c[:3, 3] == 0.0) for r in results)
