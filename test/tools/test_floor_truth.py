"""scripts/floor_truth.py, the diagnostic of the ground-plane scale (docs/tools.md): every floor
measurement of a ``ground_plane`` replay beside the ground truth. On the bundled ground-robot bag (a
flat, textured floor exactly 0.45 m below the camera) the floor's scale is the true one to a few per
mille, and the inliers' heights are the camera height."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_floor_measurements_of_the_ground_robot_bag_match_the_ground_truth(tmp_path: Path) -> None:
    params = tmp_path / "gp.yaml"
    params.write_text("/**:\n  ros__parameters:\n    scale_source: ground_plane\n    camera_height_m: 0.45\n")
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "floor_truth.py"),
                           str(REPO / "bags" / "ground_robot" / "bag"), "--params", str(params)],
                          capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    summary = re.search(r"(\d+) floor measurements: ratio geometric mean ([\d.]+), spread ([\d.]+) \(log\), "
                        r"range ([\d.]+)-([\d.]+)", done.stdout)
    assert summary is not None, done.stdout[-2000:]
    n, mean, spread, lo, hi = int(summary[1]), *(float(summary[k]) for k in range(2, 6))
    assert n >= 100  # a keyframe most frames on this view, nearly all with a floor
    assert abs(mean - 1.0) < 0.01 and spread < 0.02 and 0.95 < lo <= hi < 1.05
    rows = [line.split() for line in done.stdout.splitlines() if re.match(r"\s*\d+\s+[\d.]+\s+[\d.]+\s+[\d.]+", line)]
    assert len(rows) == n
    heights = [float(r[4]) for r in rows]  # h_vo: the floor inliers' height in metres
    assert all(abs(h - 0.45) < 0.02 for h in heights)
