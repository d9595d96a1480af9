"""scripts/loop_bag.py, the held-out long loop: one full circle in general_motion's courtyard."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from epi_vo.io import bagio

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))
import loop_bag  # noqa: E402


def test_the_loop_is_one_circle_that_comes_back_to_its_start() -> None:
    spec = loop_bag.loop_spec(181)
    centres = spec.T_w_c[:, :3, 3]
    np.testing.assert_allclose(centres[-1], centres[0], atol=1e-9)  # closes
    xz = centres[:, [0, 2]] - np.asarray(loop_bag.CENTRE_XZ)
    np.testing.assert_allclose(np.linalg.norm(xz, axis=1), loop_bag.RADIUS_M, atol=1e-9)
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert abs(steps.sum() - 2 * math.pi * loop_bag.RADIUS_M) < 0.2
    # the camera looks 10 deg off the direction of travel, never backwards
    axis = spec.T_w_c[:-1, :3, 2]
    travel = np.diff(centres, axis=0) / steps[:, None]
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", axis, travel), -1, 1)))
    assert np.all((angle > 5.0) & (angle < 15.0)), (angle.min(), angle.max())


def test_a_short_loop_renders_a_bag_with_its_ground_truth(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "loop_bag.py"), str(tmp_path), "--frames", "8"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    assert "loop8: 8 frames" in done.stdout
    with bagio.open_camera_bag(tmp_path / "loop8" / "bag") as bag:
        frames = list(bag.iter_frames())
        gt = bag.read_ground_truth()
    assert len(frames) == 8 and gt is not None and gt.positions.shape == (8, 3)
    lines = (tmp_path / "loop8" / "groundtruth_tum.txt").read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 1 + 8
    bad = subprocess.run([sys.executable, str(REPO / "scripts" / "loop_bag.py"), str(tmp_path), "--frames", "2"],
                         capture_output=True, text=True, timeout=60, check=False)
    assert bad.returncode == 2 and "at least 3" in bad.stderr
