"""A constant offset between the estimated and the true directions of travel, from a replay with ground truth.

A principal point that is off by ``d`` px, or a ground truth whose camera frame is rotated against the
images, turns every step's direction of travel (in the camera frame) by the same small angle. Such an
offset adds up linearly along the path, where the published covariance grows each step's independent
error, so the position NEES grows with the distance (KITTI 06's clip: a VO-unit position NEES of 34.6
from frame 12 is an offset of -0.23 / +0.16 deg; README, "Is the ground truth right?").

For every tracking frame ``i`` from ``--from`` on, the step to frame ``i + stride`` is taken in camera
``i``'s frame (camera optical frame: x right, y down, z forward), in the estimate and in the ground
truth; its horizontal angle ``atan2(x, z)`` and vertical angle ``atan2(y, z)`` are compared. Printed:
the mean difference (estimate - ground truth) with its standard deviation, per axis in deg, and what a
principal-point shift of the same size is at the camera's focal length (``--fx``): moving the principal
point by ``+fx tan(offset)`` px turns the estimated directions by ``-offset``. Steps shorter than
``--min-step`` of the median step (a near-static camera) or not forward (``z <= 0``) are left out.

    .venv/bin/epi-vo replay ../shared/data/kitti06_0-50/bag --output /tmp/k
    .venv/bin/python scripts/direction_offset.py /tmp/k --from 12 --stride 4 --fx 707.0912
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Offset:
    spans: int
    horizontal_deg: float  # mean of estimate - ground truth
    vertical_deg: float
    horizontal_std_deg: float  # spread of the spans about the mean
    vertical_std_deg: float

    def principal_point_px(self, fx: float) -> tuple[float, float]:
        """The principal-point shift (px) that turns the estimated directions back by the offset."""
        return fx * math.tan(math.radians(self.horizontal_deg)), fx * math.tan(math.radians(self.vertical_deg))


def _steps(T: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """Each span's step from pose i to pose j in camera i's frame, (n, 3)."""
    i, j = spans[:, 0], spans[:, 1]
    return np.einsum("nji,nj->ni", T[i, :3, :3], T[j, :3, 3] - T[i, :3, 3])


def direction_offset(T_est: np.ndarray, T_gt: np.ndarray, rows: list[int], stride: int = 4,
                     min_step: float = 0.1) -> Offset:
    """The offset over the spans ``rows[k] -> rows[k] + stride`` (camera-into-world poses, optical frame,
    one row per frame in both arrays). Raises ValueError when no span is usable."""
    spans = np.array([(r, r + stride) for r in rows if r + stride < len(T_est)], dtype=np.int64).reshape(-1, 2)
    if spans.shape[0] == 0:
        msg = "no span of forward motion to compare"
        raise ValueError(msg)
    te, tg = _steps(T_est, spans), _steps(T_gt, spans)
    le, lg = np.linalg.norm(te, axis=1), np.linalg.norm(tg, axis=1)
    keep = (lg >= min_step * np.median(lg)) & (le >= min_step * np.median(le)) & (tg[:, 2] > 0.0)
    if not keep.any():
        msg = "no span of forward motion to compare"
        raise ValueError(msg)
    te, tg = te[keep], tg[keep]
    h = np.degrees(np.arctan2(te[:, 0], te[:, 2]) - np.arctan2(tg[:, 0], tg[:, 2]))
    v = np.degrees(np.arctan2(te[:, 1], te[:, 2]) - np.arctan2(tg[:, 1], tg[:, 2]))
    return Offset(int(keep.sum()), float(h.mean()), float(v.mean()), float(h.std()), float(v.std()))


def replay_offset(directory: Path, start: int = 0, stride: int = 4) -> Offset:
    """:func:`direction_offset` of an ``epi-vo replay`` output directory (trajectory.tum, groundtruth.tum,
    frames.jsonl), over its tracking frames from frame ``start`` on."""
    from epi_vo.io import tum
    from epi_vo.tools import evaluation as ev

    est = tum.read_tum(directory / "trajectory.tum")
    gt = tum.read_tum(directory / "groundtruth.tum")
    j = ev.nearest_rows(gt[0], est[0])
    T_est = ev.poses_from_xyz_quat(est[1], est[2])
    T_gt = ev.poses_from_xyz_quat(gt[1][j], gt[2][j])
    records = [json.loads(line) for line in (directory / "frames.jsonl").read_text().splitlines() if line.strip()]
    row_of = {round(s * 1e9): k for k, s in enumerate(est[0])}
    rows = sorted(row_of[r["stamp_ns"]] for r in records
                  if r["state"] == "tracking" and r["index"] >= start and r["stamp_ns"] in row_of)
    return direction_offset(T_est, T_gt, rows, stride)


def main(argv: list[str] | None = None) -> int:
    from epi_vo.core.errors import EpiVoError

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dirs", nargs="+", type=Path, help="epi-vo replay output directories with ground truth")
    p.add_argument("--from", dest="start", type=int, default=0, help="first frame index (default 0)")
    p.add_argument("--stride", type=int, default=4, help="frames per span (default 4)")
    p.add_argument("--fx", type=float, default=0.0, help="focal length (px) for the principal-point equivalent")
    a = p.parse_args(argv)
    for d in a.dirs:
        try:
            o = replay_offset(d, a.start, a.stride)
        except (OSError, ValueError, KeyError, EpiVoError) as exc:
            print(f"{d}: {exc}", file=sys.stderr)
            return 1
        line = (f"{d}: {o.spans} spans of {a.stride} frames: horizontal {o.horizontal_deg:+.3f} deg "
                f"(spread {o.horizontal_std_deg:.3f}), vertical {o.vertical_deg:+.3f} deg (spread "
                f"{o.vertical_std_deg:.3f})")
        if a.fx > 0:
            dx, dy = o.principal_point_px(a.fx)
            line += f"; as a principal point: move it by ({dx:+.1f}, {dy:+.1f}) px"
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
