"""The KLT pyramid's reach (epi_vo.core.features): an image that moves further than the pyramid follows is
tracked from where the whole image's motion puts each point, and a part of the image that does not share
that motion is tracked from where it was."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from klt_texture import texture as _texture

from epi_vo.core import features as fe
from epi_vo.core.config import VoConfig

CFG = VoConfig()
FAR = np.array([131.3, -47.6], np.float32)  # |FAR| 140 px: two and a half times the pyramid's reach


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return _texture()


def _shifted(img: np.ndarray, shift: np.ndarray) -> np.ndarray:
    M = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]])
    h, w = img.shape
    return np.round(cv2.warpAffine(img.astype(np.float32), M, (w, h), flags=cv2.INTER_CUBIC,
                                   borderMode=cv2.BORDER_REFLECT)).astype(np.uint8)


def _grid(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    u, v = np.meshgrid(np.arange(x0, x1, 20.0), np.arange(y0, y1, 20.0))
    return np.column_stack([u.ravel(), v.ravel()]).astype(np.float32) + 0.25


def test_the_image_shift_is_the_whole_images_motion(texture: np.ndarray) -> None:
    """Measured at the pyramid's coarsest level (an eighth of the image): a few pixels off, well inside the
    reach the pyramid then follows from there."""
    assert float(np.hypot(*FAR)) > 2 * fe.pyramid_reach_px(CFG.klt_levels, CFG)
    assert np.allclose(fe.image_shift(texture, _shifted(texture, FAR), CFG.klt_levels), FAR, atol=4.0)
    assert np.allclose(fe.image_shift(texture, texture, CFG.klt_levels), 0.0, atol=0.05)
    flat = np.full_like(texture, 128)
    assert np.all(np.isfinite(fe.image_shift(flat, flat, CFG.klt_levels)))


def test_an_image_moved_beyond_the_pyramids_reach_is_tracked(texture: np.ndarray) -> None:
    """140 px between two frames (a 960 px camera taking off moves its image 100-150 px): every point whose
    texture is still in view lands where the texture went. From the points' own positions the pyramid
    (56 px of reach) follows none of them."""
    pts = _grid(40.0, 480.0, 80.0, 420.0)  # their texture stays in view (and away from the reflected border)
    tracks = fe.track_klt(texture, _shifted(texture, FAR), pts, CFG)
    err = np.linalg.norm(tracks.pts - (pts + FAR), axis=1)
    assert np.count_nonzero(tracks.ok) >= 0.95 * len(pts)
    assert float(np.max(err[tracks.ok])) < 0.1


def test_a_part_that_does_not_share_the_images_motion_is_tracked_from_where_it_was(texture: np.ndarray) -> None:
    """Three quarters of the image move 140 px, a quarter (a near object, a mover) stays: the image's motion
    is the larger part's, and the still part's tracks, lost from there, are found again from where they were.
    (A few started 140 px away converge on another patch that the forward-backward check, seeded at the
    start point, lets through: 2 of 100 here; the model's robust fit has them as outliers.)"""
    moved = _shifted(texture, FAR)
    cur = moved.copy()
    cur[:, 480:] = texture[:, 480:]  # the right quarter does not move
    pts_moving = _grid(40.0, 300.0, 80.0, 420.0)
    pts_still = _grid(520.0, 620.0, 40.0, 440.0)
    assert np.allclose(fe.image_shift(texture, cur, CFG.klt_levels), FAR, atol=4.0)
    tracks = fe.track_klt(texture, cur, np.vstack([pts_moving, pts_still]), CFG)
    n = len(pts_moving)
    for ok, pts, want in ((tracks.ok[:n], tracks.pts[:n], pts_moving + FAR),
                          (tracks.ok[n:], tracks.pts[n:], pts_still)):
        assert np.count_nonzero(ok & (np.linalg.norm(pts - want, axis=1) < 0.1)) >= 0.95 * len(ok)


def test_motion_within_reach_is_tracked_from_where_each_point_was(texture: np.ndarray,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Below the pyramid's reach nothing changes: each search starts at its point, as the pyramid alone
    would (one pass; the same tracks bit for bit)."""
    pts = _grid(40.0, 560.0, 80.0, 420.0)  # their texture stays in view
    small = np.array([17.4, -12.2], np.float32)  # 21 px < 56
    cur = _shifted(texture, small)
    starts = []
    real = fe._klt_from
    monkeypatch.setattr(fe, "_klt_from", lambda g0, g1, p, s, c: starts.append(s - p) or real(g0, g1, p, s, c))
    tracks = fe.track_klt(texture, cur, pts, CFG)
    assert len(starts) == 1 and not np.any(starts[0])
    p_alone, _, _ = cv2.calcOpticalFlowPyrLK(texture, cur, pts.reshape(-1, 1, 2), None,
                                              winSize=(CFG.klt_window_px, CFG.klt_window_px),
                                              maxLevel=CFG.klt_levels, criteria=fe._LK_CRITERIA)
    assert np.array_equal(tracks.pts[tracks.ok], p_alone.reshape(-1, 2)[tracks.ok])
    assert np.count_nonzero(tracks.ok) >= 0.9 * len(pts)


@pytest.mark.parametrize(("size", "levels"), [((480, 640), 3), ((240, 320), 3), ((121, 121), 3), ((120, 120), 2),
                                              ((31, 200), 1), ((30, 200), 0)])
def test_the_reach_is_the_pyramid_opencv_builds(size: tuple[int, int], levels: int) -> None:
    """A level no larger than the window is not built (OpenCV's rule): a small image's pyramid reaches less."""
    assert fe.pyramid_levels(*size, CFG) == levels
    built, _ = cv2.buildOpticalFlowPyramid(np.zeros(size, np.uint8), (CFG.klt_window_px, CFG.klt_window_px),
                                           CFG.klt_levels, withDerivatives=False)
    assert built == levels
    assert fe.pyramid_reach_px(levels, CFG) == 7.0 * 2**levels
