"""TUM trajectory files (``stamp tx ty tz qx qy qz qw`` per line): read and write (no rclpy)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from epi_vo.core.errors import BagError
from epi_vo.io.outbag import checked_array
from epi_vo.io.paths import refuse_special_file
from epi_vo.io.trajectory import StampedPoses

logger = logging.getLogger(__name__)

TUM_FILE = "TUM trajectory file"  # what a path read by read_tum is called in a refusal

# --------------------------------------------------------------------------------------------------
# TUM trajectories


def read_tum(path: str | Path) -> StampedPoses:
    """Read a TUM trajectory: lines ``timestamp tx ty tz qx qy qz qw``, whitespace separated.

    Returns the poses: ``stamps_s`` (N,), ``positions_xyz`` (N, 3), ``quats_xyzw`` (N, 4). Blank lines and lines
    starting with '#' are skipped. Raises BagError for a missing file or a malformed line (with its
    line number).
    """
    path = Path(path)
    refuse_special_file(path, TUM_FILE)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        msg = f"cannot read TUM file {path}: {err}"
        raise BagError(msg) from err
    rows: list[list[float]] = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        tokens = stripped.split()
        if len(tokens) != 8:
            msg = (
                f'{path}:{line_number}: expected 8 values "timestamp tx ty tz qx qy qz qw", '
                f"got {len(tokens)}"
            )
            raise BagError(msg)
        try:
            values = [float(token) for token in tokens]
        except ValueError:
            msg = f"{path}:{line_number}: not a number in {stripped!r}"
            raise BagError(msg) from None
        if not all(np.isfinite(values)):
            msg = f"{path}:{line_number}: non-finite value in {stripped!r}"
            raise BagError(msg)
        rows.append(values)
    table = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    return StampedPoses(table[:, 0].copy(), table[:, 1:4].copy(), table[:, 4:8].copy())


def write_tum(
    path: str | Path,
    stamps_s: ArrayLike,
    positions: ArrayLike,
    quats_xyzw: ArrayLike,
) -> None:
    """Write a TUM trajectory (``timestamp tx ty tz qx qy qz qw`` per line, '#' header line).

    ``stamps_s`` (N,) in seconds, ``positions`` (N, 3), ``quats_xyzw`` (N, 4). Stamps are written
    with 9 decimals, other values with the shortest text that reads back to the same float.
    """
    stamps = checked_array(stamps_s, (None,), "stamps_s")
    xyz = checked_array(positions, (stamps.shape[0], 3), "positions")
    quats = checked_array(quats_xyzw, (stamps.shape[0], 4), "quats_xyzw")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, position, quat in zip(stamps, xyz, quats, strict=True):
        values = " ".join(repr(float(v)) for v in (*position, *quat))
        lines.append(f"{float(stamp):.9f} {values}")
    try:
        Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as err:
        msg = f"cannot write TUM file {path}: {err}"
        raise BagError(msg) from err


