"""KLT done ahead (epi_vo.runner.klt_ahead) when the image moves beyond the pyramid's reach: the rows a
keyframe appends are tracked later, on their own, and must land where tracking all rows in line puts them.
The image's motion each search starts from is the two images' (``features.image_shift``), not the rows'."""

from __future__ import annotations

import cv2
import numpy as np
from klt_texture import texture as _texture

from epi_vo.core import features as fe
from epi_vo.core.config import VoConfig
from epi_vo.runner.klt_ahead import KltAhead

CFG = VoConfig()
FAR = np.array([131.3, -47.6], np.float32)  # beyond the pyramid's 56 px


def test_klt_done_ahead_equals_klt_in_line_beyond_the_reach() -> None:
    texture = _texture()
    M = np.array([[1.0, 0.0, FAR[0]], [0.0, 1.0, FAR[1]]])
    cur = np.round(cv2.warpAffine(texture.astype(np.float32), M, (640, 480), flags=cv2.INTER_CUBIC,
                                  borderMode=cv2.BORDER_REFLECT)).astype(np.uint8)
    u, v = np.meshgrid(np.arange(40.0, 620.0, 20.0), np.arange(40.0, 440.0, 20.0))
    pts = np.column_stack([u.ravel(), v.ravel()]).astype(np.float32) + 0.25
    in_line = fe.track_klt(texture, cur, pts, CFG)
    assert np.count_nonzero(in_line.ok) >= 0.5 * len(pts)  # the texture that stays in view is followed
    ahead = KltAhead()
    n = fe.EXPOSURE_MAX_TRACKS + 50
    ahead.start(texture, cur, pts[:n], CFG)
    got = ahead.take(texture, cur.copy(), pts, CFG)
    assert got is not None
    tracks, _ = got
    assert np.array_equal(tracks.ok, in_line.ok) and np.array_equal(tracks.pts, in_line.pts)
    assert np.array_equal(tracks.fb, in_line.fb) and tracks.gain == in_line.gain
