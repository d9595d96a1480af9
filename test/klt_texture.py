"""A synthetic texture moved by a known sub-pixel shift, for the KLT tests (test/core/test_features.py,
test/runner/)."""

from __future__ import annotations

import cv2
import numpy as np

SHIFT = np.array([2.3, -1.7], np.float32)


def texture() -> np.ndarray:
    """640x480 blurred random texture with grey levels 40-200 (room to brighten and darken)."""
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (0, 0), 2.0).astype(np.float64)
    img = 40.0 + 160.0 * (img - img.min()) / (img.max() - img.min())
    return np.round(img).astype(np.uint8)


def points() -> np.ndarray:
    """A 14 x 10 grid of points 40 px apart, a quarter pixel off the pixel centres."""
    u, v = np.meshgrid(np.arange(40.0, 600.0, 40.0), np.arange(40.0, 440.0, 40.0))
    return np.column_stack([u.ravel(), v.ravel()]).astype(np.float32) + 0.25


def moved(texture: np.ndarray, gain: float) -> np.ndarray:
    """``texture`` shifted by ``SHIFT`` and its exposure scaled by ``gain``."""
    M = np.array([[1.0, 0.0, SHIFT[0]], [0.0, 1.0, SHIFT[1]]])
    warped = cv2.warpAffine(texture.astype(np.float32), M, (640, 480), flags=cv2.INTER_CUBIC,
                            borderMode=cv2.BORDER_REFLECT)
    return np.clip(np.round(warped * gain), 0, 255).astype(np.uint8)
