"""Bad input at the core, in general form: implausible calibration, binning and roi, images the frontend
cannot use, invalid stamps, OpenCV failures mid-frame, and a property test that every frame result is
finite whatever the input (nothing non-finite may reach the held state, a message or a file)."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from bag_frames import decoded_frames
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from epi_vo.core import features as fe
from epi_vo.core import step as step_module
from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision, note
from epi_vo.core.errors import CameraModelError
from epi_vo.core.frame import MAX_STAMP_NS, FrameResult, TrackingState
from epi_vo.core.odometry import OdometryConverter
from epi_vo.core.pipeline import VoPipeline
from epi_vo.core.status import frame_status

Frames = list[tuple[int, np.ndarray, Any]]


@pytest.fixture(scope="module")
def frames() -> Frames:
    """(stamp, gray image, camera_info message) of the bundled general-motion bag."""
    return decoded_frames(camera_info_messages=True)


def _info(width: int = 640, height: int = 480, k: list[float] | None = None, d: list[float] | None = None,
          model: str = "plumb_bob", binning: tuple[int, int] = (0, 0),
          roi: tuple[int, int, int, int] = (0, 0, 0, 0)) -> SimpleNamespace:
    k = k if k is not None else [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0]
    return SimpleNamespace(width=width, height=height, k=k, d=d if d is not None else [0.0] * 5,
                           distortion_model=model, binning_x=binning[0], binning_y=binning[1],
                           roi=SimpleNamespace(x_offset=roi[0], y_offset=roi[1], width=roi[2], height=roi[3]))


def _assert_finite_record(r: FrameResult) -> None:
    assert np.all(np.isfinite(r.T_w_c)) and np.all(np.isfinite(r.covariance)) and np.all(np.isfinite(r.points_w))
    np.testing.assert_allclose(r.T_w_c[:3, :3] @ r.T_w_c[:3, :3].T, np.eye(3), atol=1e-9)
    assert abs(np.linalg.norm(r.quat_xyzw) - 1.0) < 1e-9
    assert np.all(np.diag(r.covariance) > 0)
    assert 0 <= r.stamp_ns <= MAX_STAMP_NS
    json.dumps(r.to_record(), allow_nan=False)  # raises on NaN / inf
    for _, v in frame_status(r, "vo", "cam").values:
        try:
            assert math.isfinite(float(v))
        except ValueError:
            pass  # not a number: text


# -- implausible calibration ---------------------------------------------------------------------------
@pytest.mark.parametrize(("index", "value", "words"), [
    (0, 1e-300, "focal length fx = 1e-300 px is implausible"),
    (0, 1e300, "focal length fx = 1e+300 px is implausible"),
    (4, 1e-3, "focal length fy = 0.001 px is implausible"),
    (2, 1e6, "principal point cx = 1e+06 px is far outside"),
    (5, -5000.0, "principal point cy = -5000 px is far outside"),
])
def test_implausible_intrinsics_are_rejected_naming_the_value(index: int, value: float, words: str) -> None:
    info = _info()
    info.k[index] = value
    with pytest.raises(CameraModelError, match=words.replace("+", r"\+")):
        CameraModel.from_camera_info(info)


def test_implausible_distortion_is_rejected() -> None:
    with pytest.raises(CameraModelError, match="implausible coefficients"):
        CameraModel.from_camera_info(_info(d=[1e300, 0.0, 0.0, 0.0, 0.0]))


def test_plausible_extremes_are_accepted() -> None:
    """A 170 deg pinhole-ish wide angle (fx ~ 0.04 w) and a long telephoto (fx ~ 50 w) are real lenses."""
    for fx in (0.04 * 640, 50 * 640):
        cam = CameraModel.from_camera_info(_info(k=[fx, 0.0, 320.0, 0.0, fx, 240.0, 0.0, 0.0, 1.0]))
        assert cam.fx == fx


def test_bad_calibration_then_good_leaves_nothing_non_finite(frames: Frames) -> None:
    """The held covariance never picks up NaN from a bad camera_info, and tracking resumes after it."""
    pipe = VoPipeline()
    results = []
    for i, (stamp, gray, info) in enumerate(frames):
        if 15 <= i < 20:
            k = list(np.asarray(info.k, dtype=float))
            k[0] = 1e-300
            try:
                camera = CameraModel.from_camera_info(_info(info.width, info.height, k, list(info.d),
                                                            info.distortion_model))
                results.append(pipe.process(gray, camera, stamp))
            except CameraModelError as exc:
                assert "implausible" in str(exc)
                results.append(pipe.reject(stamp, str(exc)))
        else:
            results.append(pipe.process(gray, CameraModel.from_camera_info(info), stamp))
    for r in results:
        _assert_finite_record(r)
    assert all(not r.has_pose and "fx = 1e-300" in r.reason for r in results[15:20])
    assert sum(r.state is TrackingState.TRACKING for r in results[25:]) >= 0.8 * len(results[25:])


# -- binning and region of interest ----------------------------------------------------------------------
def test_binning_and_roi_follow_image_geometry() -> None:
    """The reduced image's pixel p is the sensor pixel p * binning + roi offset (image_geometry's
    toFullResolution): normalising either gives the same ray, distortion included."""
    full_info = _info(1280, 960, [1000.0, 0.0, 650.0, 0.0, 1002.0, 470.0, 0.0, 0.0, 1.0],
                      [-0.28, 0.09, 0.001, -0.0005, 0.0])
    full = CameraModel.from_camera_info(full_info)
    binned = CameraModel.from_camera_info(_info(1280, 960, full_info.k, full_info.d, binning=(2, 4),
                                                roi=(100, 60, 1000, 800)))
    assert (binned.width, binned.height) == (500, 200)
    np.testing.assert_allclose(binned.K, [[500.0, 0.0, 275.0], [0.0, 250.5, 102.5], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(3)
    p = rng.uniform([0, 0], [499, 199], size=(50, 2))
    p_full = p * [2, 4] + [100, 60]
    np.testing.assert_allclose(binned.normalize(p), full.normalize(p_full), atol=1e-9)


def test_binned_image_size_mismatch_names_the_binning() -> None:
    cam = CameraModel.from_camera_info(_info(binning=(2, 2)))
    assert (cam.width, cam.height) == (320, 240)
    cam.check_image_size(320, 240)
    with pytest.raises(CameraModelError, match=r"does not match camera_info size 320x240 \(after binning 2x2"):
        cam.check_image_size(640, 480)


@pytest.mark.parametrize(("binning", "roi", "words"), [
    ((0, 0), (600, 0, 100, 100), "roi .* is not inside the calibrated 640x480 image"),
    ((0, 0), (0, 0, 700, 480), "roi .* is not inside"),
    ((1000, 1), (0, 0, 0, 0), "binning 1000x1 leaves no pixel"),
])
def test_bad_roi_or_binning_is_rejected(binning: tuple[int, int], roi: tuple[int, int, int, int], words: str) -> None:
    with pytest.raises(CameraModelError, match=words):
        CameraModel.from_camera_info(_info(binning=binning, roi=roi))


def test_binned_camera_tracks_the_binned_images(frames: Frames) -> None:
    """Images binned 2x2 with the full-resolution camera_info (binning_x = binning_y = 2) track."""
    pipe = VoPipeline()
    results = []
    for stamp, gray, info in frames:
        small = cv2.resize(gray, (gray.shape[1] // 2, gray.shape[0] // 2), interpolation=cv2.INTER_AREA)
        cam = CameraModel.from_camera_info(_info(info.width, info.height, list(info.k), list(info.d),
                                                 info.distortion_model, binning=(2, 2)))
        results.append(pipe.process(small, cam, stamp))
    assert sum(r.state is TrackingState.TRACKING for r in results) >= 0.8 * len(results)


# -- images the frontend cannot use ----------------------------------------------------------------------
@pytest.mark.parametrize("frontend", ["klt", "orb"])
@pytest.mark.parametrize(("w", "h"), [(1, 1), (2, 7), (8, 8), (31, 200), (300, 20)])
def test_tiny_images_are_rejected_frames(frontend: str, w: int, h: int) -> None:
    cfg = VoConfig(frontend=frontend)
    pipe = VoPipeline(cfg)
    cam = CameraModel.create(w, h, [max(w, h), 0, w / 2, 0, max(w, h), h / 2, 0, 0, 1], [])
    img = np.random.default_rng(0).integers(0, 255, (h, w), dtype=np.uint8)
    results = [pipe.process(img, cam, 1_000 + i) for i in range(3)]
    for r in results:
        assert not r.has_pose and r.state is TrackingState.LOST
        assert f"image {w}x{h} is too small for the {frontend} frontend" in r.reason
        assert Decision.IMAGE_TOO_SMALL in r.decisions and r.problem == r.notes[0]["problem"]
        _assert_finite_record(r)


def test_min_image_side_is_usable(frames: Frames) -> None:
    """At the minimum size the frontends run without error (the limit is not set too low)."""
    for frontend in ("klt", "orb"):
        cfg = VoConfig(frontend=frontend)
        side = fe.min_image_side(cfg)
        pipe = VoPipeline(cfg)
        for stamp, gray, _ in frames[:5]:
            crop = np.ascontiguousarray(gray[200:200 + side, 300:300 + side])
            cam = CameraModel.create(side, side, [300.0, 0, side / 2, 0, 300.0, side / 2, 0, 0, 1], [])
            r = pipe.process(crop, cam, stamp)
            assert not {Decision.IMAGE_TOO_SMALL, Decision.OPENCV_FAILED} & set(r.decisions)
            _assert_finite_record(r)


def test_opencv_failure_mid_frame_is_a_rejected_frame(frames: Frames, monkeypatch: pytest.MonkeyPatch) -> None:
    """Whatever OpenCV refuses inside a frame gives a record with the reason; the pose held before the
    frame stays, and tracking comes back afterwards."""
    pipe = VoPipeline()
    before = [pipe.process(g, CameraModel.from_camera_info(i), s) for s, g, i in frames[:20]]
    held = before[-1].T_w_c.copy()

    def broken(*args: object, **kwargs: object) -> None:
        raise cv2.error("OpenCV(5.0.0) lkpyramid.cpp:1: error: (-215:Assertion failed) test in 'calcOpticalFlowPyrLK'")

    monkeypatch.setattr(fe, "track_klt", broken)
    s, g, i = frames[20]
    r = pipe.process(g, CameraModel.from_camera_info(i), s)
    assert not r.has_pose and "OpenCV could not process this frame" in r.reason and "Assertion failed" in r.reason
    assert r.decisions[0] is Decision.OPENCV_FAILED and "Assertion failed" in r.notes[0]["detail"]
    np.testing.assert_array_equal(r.T_w_c, held)
    monkeypatch.undo()
    after = [pipe.process(g, CameraModel.from_camera_info(i), s) for s, g, i in frames[21:]]
    assert Decision.DUPLICATE_STAMP not in after[0].decisions
    assert any(x.state is TrackingState.TRACKING for x in after)


# -- stamps -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad_stamp", [-1, -5_000_000_000, MAX_STAMP_NS + 1, 2**63 - 1])
def test_a_stamp_that_is_no_ros_time_is_a_skipped_frame(frames: Frames, bad_stamp: int) -> None:
    pipe = VoPipeline()
    results = [pipe.process(g, CameraModel.from_camera_info(i), s) for s, g, i in frames[:10]]
    _, g, i = frames[10]
    bad = pipe.process(g, CameraModel.from_camera_info(i), bad_stamp)
    assert bad.skipped and not bad.has_pose and bad.decisions == (Decision.STAMP_INVALID,)
    assert f"image stamp {bad_stamp} ns is not a valid ROS time" in bad.reason
    assert bad.stamp_ns == min(max(bad_stamp, 0), MAX_STAMP_NS)
    _assert_finite_record(bad)
    # The bad stamp was not booked: the next frames go on as if it had not come (no backwards jump).
    results += [pipe.process(g, CameraModel.from_camera_info(i), s) for s, g, i in frames[11:]]
    assert not any({Decision.TIME_JUMPED_BACK, Decision.DUPLICATE_STAMP} & set(r.decisions) for r in results)
    assert sum(r.state is TrackingState.TRACKING for r in results[11:]) >= 0.8 * len(results[11:])
    rejected = pipe.reject(bad_stamp, "corrupt")
    assert rejected.skipped and "not a valid ROS time" in rejected.reason


def test_failed_frame_then_reject_is_not_called_a_duplicate(frames: Frames, monkeypatch: pytest.MonkeyPatch) -> None:
    """A frame that raised inside the pipeline and is then rejected by its caller (what the node does
    for internal errors) gets the caller's reason, not 'duplicate image stamp'."""
    pipe = VoPipeline()
    for s, g, i in frames[:5]:
        pipe.process(g, CameraModel.from_camera_info(i), s)
    s, g, i = frames[5]
    monkeypatch.setattr(step_module, "_tracked", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.raises(RuntimeError):
        pipe.process(g, CameraModel.from_camera_info(i), s)
    r = pipe.reject(s, "internal error: RuntimeError('boom')")
    assert "internal error" in r.reason and Decision.DUPLICATE_STAMP not in r.decisions and not r.skipped
    assert r.notes[0] == note(Decision.FRAME_REJECTED, problem="internal error: RuntimeError('boom')")


def test_twist_is_finite_for_stamps_a_nanosecond_apart() -> None:
    conv = OdometryConverter()
    T = np.eye(4)
    conv.convert(1_000, T, np.eye(6) * 1e-4, True)
    T2 = np.eye(4)
    T2[:3, 3] = [1e300, 0.0, 0.0]
    s = conv.convert(1_001, T2, np.eye(6) * 1e300, True)
    for a in (s.linear_velocity, s.angular_velocity, s.twist_covariance):
        assert np.all(np.isfinite(a))


# -- property: every result finite, whatever the calibration and image ---------------------------------------
_finite_or_absurd = st.one_of(
    st.floats(min_value=-2000, max_value=2000, allow_nan=False),
    st.sampled_from([0.0, 1e-300, -1e-300, 1e300, -1e300, math.nan, math.inf, -math.inf, 5e-324]))


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(fx=_finite_or_absurd, fy=_finite_or_absurd, cx=_finite_or_absurd, cy=_finite_or_absurd,
       d=st.lists(_finite_or_absurd, min_size=0, max_size=8),
       size=st.sampled_from([(1, 1), (7, 3), (40, 30), (64, 48), (160, 120)]),
       binning=st.sampled_from([(0, 0), (1, 1), (2, 2), (3, 1)]),
       seed=st.integers(0, 2**16), n_frames=st.integers(2, 6), step=st.integers(-3, 3))
def test_every_frame_result_is_finite_whatever_the_input(
        fx: float, fy: float, cx: float, cy: float, d: list[float], size: tuple[int, int],
        binning: tuple[int, int], seed: int, n_frames: int, step: int) -> None:
    w, h = size
    info = _info(w, h, [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], d, binning=binning)
    good = CameraModel.create(w, h, [max(w, h), 0, w / 2, 0, max(w, h), h / 2, 0, 0, 1], [])
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 255, (h + 8, w + 8), dtype=np.uint8), (3, 3), 0)
    pipe = VoPipeline()
    stamp = 1_000_000_000
    for k in range(n_frames):
        # alternately the fuzzed calibration and a good one: bad input must not stick.
        try:
            camera = CameraModel.from_camera_info(info) if k % 2 == 0 else good
        except CameraModelError as exc:
            r = pipe.reject(stamp, str(exc))
        else:
            img = np.ascontiguousarray(base[k % 8:k % 8 + camera.height, k % 8:k % 8 + camera.width]) \
                if camera.height <= h and camera.width <= w else \
                np.zeros((camera.height, camera.width), np.uint8)
            r = pipe.process(img, camera, stamp)
        _assert_finite_record(r)
        stamp += step * 10_000_000
