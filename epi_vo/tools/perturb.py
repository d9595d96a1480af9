"""A calibration nobody could tell apart from the recorded one: the benchmark's run-to-run spread.

A camera's focal length is known to a few tenths of a percent at best (a good checkerboard calibration);
scaling CameraInfo's ``fx`` and ``fy`` by ``1 + rel`` with ``|rel|`` ~ 1e-3 moves a pixel at the image's
edge by a tenth of a pixel, below the tracks' noise. A pipeline whose result on a sequence changes much
under it decides something on a cliff; the distribution benchmark runs every sequence again under such
twins (``--perturb``) and prints how far each family's figures move (docs/distribution.md).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Any

import numpy as np


def scaled_focal(rel: float) -> Callable[[Any], Any]:
    """A CameraInfo edit: the same message with ``fx`` and ``fy`` times ``1 + rel`` (K's other entries, the
    size, the lens model and the region of interest unchanged).

    Raises:
        ValueError: ``rel`` not finite or not above -1 (the CLI refuses such a value first).
    """
    if not math.isfinite(rel) or rel <= -1.0:
        raise ValueError(f"focal perturbation {rel!r}: must be finite and above -1")
    factor = 1.0 + rel

    def edit(msg: Any) -> Any:
        k = np.asarray(msg.k, dtype=np.float64).reshape(9).copy()
        k[0] *= factor
        k[4] *= factor
        edited = copy.copy(msg)  # every other field as recorded (rclpy's and rosbags' messages alike)
        edited.k = k
        return edited

    return edit
