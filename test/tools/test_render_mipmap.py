"""bags/make_bags.py's texture sampling: every mipmap level addresses the same point of the surface.

A level of detail that changes with the distance must blur a texture, not move it: were the levels
offset against each other, a floor approached by the camera would slide under it (half a texel between
levels 0 and 1, 1.5 between 0 and 2, turn a 300-frame floor drive's yaw by about a degree)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest


@pytest.mark.parametrize("centre", [(256.0, 250.0), (255.5, 251.25)])
def test_each_mipmap_level_samples_the_texture_where_level_0_does(make_bags, centre: tuple[float, float]) -> None:
    """A Gaussian blob (6 texels) sampled at every level of detail keeps its centroid to 0.01 texel; with
    each level addressed on its own grid it moved by (2^k - 1) / 2 texels: 0.5, 1.5, 3.5, 7.5."""
    n = 512
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    texture = (200.0 * np.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * 6.0**2))).astype(np.float32)
    pyramid = [texture]
    while min(pyramid[-1].shape) >= 16:
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    ij = np.arange(180, 330, dtype=np.float64)  # one sample per level-0 texel around the blob
    fu, fv = np.meshgrid((ij + 0.5) / n, (ij + 0.5) / n)
    inside = np.ones(fu.shape, bool)
    for level in (0.0, 1.0, 1.5, 2.0, 3.0, 4.0):
        s = make_bags._sample_trilinear(pyramid, fu, fv, np.full(fu.shape, level, np.float32), inside)
        s = s.astype(np.float64)
        cx, cy = (s * ij[None, :]).sum() / s.sum(), (s * ij[:, None]).sum() / s.sum()
        assert abs(cx - centre[0]) < 0.01 and abs(cy - centre[1]) < 0.01, (level, cx - centre[0], cy - centre[1])
        if level == 0.0:
            np.testing.assert_allclose(s, texture[180:330, 180:330], atol=1e-3)  # level 0 is the texture itself
