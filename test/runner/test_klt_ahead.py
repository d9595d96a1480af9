"""KLT into the next image on a worker thread (epi_vo.runner.klt_ahead): the in-line result, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from klt_texture import moved as _moved
from klt_texture import points as _points
from klt_texture import texture as _texture

from epi_vo.core import features as fe
from epi_vo.core.config import VoConfig
from epi_vo.runner.klt_ahead import KltAhead

CFG = VoConfig()


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return _texture()


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    return _points()


@pytest.mark.parametrize("n_ahead", [120, 60])
def test_klt_done_ahead_equals_klt_in_line_across_an_exposure_step(texture: np.ndarray, points: np.ndarray,
                                                                   n_ahead: int) -> None:
    """The worker tracks the frame's points into the next (darker) image; the next frame then tracks
    those rows plus corners a keyframe appended. The result must be the in-line one, bit for bit: with
    at least EXPOSURE_MAX_TRACKS rows ahead the exposure is judged the same way; with fewer, the job is
    dropped and the frame tracks in line."""
    cur = _moved(texture, 0.6)
    in_line = fe.track_klt(texture, cur, points, CFG)
    ahead = KltAhead()
    ahead.start(texture, cur, points[:n_ahead], CFG)
    got = ahead.take(texture, cur.copy(), points, CFG)  # the same image: its pixels, not the array object
    if n_ahead >= fe.EXPOSURE_MAX_TRACKS:
        assert got is not None
        tracks, _ = got
        for a, b in zip(tracks, in_line, strict=True):  # points, kept, gain and forward-backward errors
            np.testing.assert_array_equal(a, b)
    else:
        assert got is None


def test_a_job_for_other_images_or_points_is_dropped(texture: np.ndarray, points: np.ndarray) -> None:
    cur = _moved(texture, 1.0)
    for other in ((_moved(texture, 0.9), cur, points), (texture, _moved(texture, 0.9), points),
                  (texture, cur, points[::-1].copy())):
        ahead = KltAhead()
        ahead.start(texture, cur, points, CFG)
        assert ahead.take(*other, CFG) is None
        assert ahead.take(texture, cur, points, CFG) is None  # one job, taken or dropped once
