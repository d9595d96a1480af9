"""A trajectory: camera poses with their stamps (:class:`StampedPoses`), the one type the TUM files, the replay,
the benchmark and the evaluation pass around.

It is evo's ``PoseTrajectory3D`` (timestamps, positions, orientations) as plain arrays, so that reading a file
needs no evo: the evaluation turns it into evo's type in one place
(``epi_vo.tools.evaluation.to_evo_trajectory``, where the quaternion order changes from x y z w to evo's
w x y z). A NamedTuple, so ``stamps_s, positions_xyz, quats_xyzw = poses`` unpacks it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray


class StampedPoses(NamedTuple):
    """Camera poses ``T_w_c`` (the camera optical frame in a world frame) with their stamps."""

    stamps_s: NDArray[np.float64]  # (N,) seconds, strictly increasing
    positions_xyz: NDArray[np.float64]  # (N, 3) camera centre in world (translation of T_w_c)
    quats_xyzw: NDArray[np.float64]  # (N, 4) R_w_c as a quaternion, x, y, z, w order
