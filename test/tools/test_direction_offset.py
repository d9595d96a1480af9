"""scripts/direction_offset.py: a constant offset of the directions of travel against the ground truth."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from script_module import load_script

from epi_vo.io import tum

direction_offset = load_script("direction_offset")


def _drive(n: int, offset_deg: tuple[float, float], noise_deg: float = 0.0, seed: int = 0
           ) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth: a camera (optical frame) driving forward 1 m per frame while it yaws 0.3 deg per frame.
    Estimate: the same steps, each turned in its own camera frame by ``offset_deg`` (horizontal about the
    camera's y axis, vertical about its x axis) plus white noise, chained from the true rotations."""
    rng = np.random.default_rng(seed)
    T_gt = np.tile(np.eye(4), (n, 1, 1))
    T_est = T_gt.copy()
    step_rot = Rotation.from_euler("y", 0.3, degrees=True).as_matrix()
    for i in range(1, n):
        T_gt[i, :3, :3] = T_gt[i - 1, :3, :3] @ step_rot
        T_gt[i, :3, 3] = T_gt[i - 1, :3, 3] + T_gt[i - 1, :3, :3] @ np.array([0.0, 0.0, 1.0])
        h, v = offset_deg[0] + rng.normal(0.0, noise_deg), offset_deg[1] + rng.normal(0.0, noise_deg)
        # a step (x, y, z) = (0, 0, 1) turned to horizontal angle h and vertical angle v
        d = np.array([math.tan(math.radians(h)), math.tan(math.radians(v)), 1.0])
        T_est[i, :3, :3] = T_gt[i, :3, :3]
        T_est[i, :3, 3] = T_est[i - 1, :3, 3] + T_gt[i - 1, :3, :3] @ (d / np.linalg.norm(d))
    return T_est, T_gt


def test_a_constant_offset_is_recovered_and_none_is_zero() -> None:
    T_est, T_gt = _drive(60, (-0.226, 0.162))
    o = direction_offset.direction_offset(T_est, T_gt, list(range(60)), stride=4)
    assert o.spans == 56
    assert o.horizontal_deg == pytest.approx(-0.226, abs=0.002)
    assert o.vertical_deg == pytest.approx(0.162, abs=0.002)
    assert o.horizontal_std_deg < 0.002 and o.vertical_std_deg < 0.002
    # KITTI 06's focal length: the offset is a principal point 2.8 px left and 2.0 px down of the truth
    dx, dy = o.principal_point_px(707.0912)
    assert dx == pytest.approx(-2.79, abs=0.03) and dy == pytest.approx(2.00, abs=0.03)
    T_est, T_gt = _drive(200, (0.0, 0.0), noise_deg=0.3, seed=1)
    o = direction_offset.direction_offset(T_est, T_gt, list(range(200)), stride=4)
    assert abs(o.horizontal_deg) < 0.05 and abs(o.vertical_deg) < 0.05
    assert 0.1 < o.horizontal_std_deg < 0.3  # four steps of 0.3 deg noise average to ~0.15


def test_backward_and_static_spans_are_left_out() -> None:
    T_est, T_gt = _drive(20, (0.1, 0.0))
    T_gt[10:, :3, 3] = T_gt[10, :3, 3]  # the camera stops at frame 10
    T_est[10:, :3, 3] = T_est[10, :3, 3]
    o = direction_offset.direction_offset(T_est, T_gt, list(range(20)), stride=4)
    assert o.spans == 10  # spans from frames 0-9 move 1-4 m; from 10-15 none (the median span: 2.5 m)
    assert o.horizontal_deg == pytest.approx(0.1, abs=1e-9)
    T_est, T_gt = _drive(20, (0.1, 0.0))
    T_est[:, :3, 3] *= -1.0  # a camera reversing along its optical axis: no span is compared
    T_gt[:, :3, 3] *= -1.0
    with pytest.raises(ValueError, match="no span"):
        direction_offset.direction_offset(T_est, T_gt, list(range(20)), stride=4)
    with pytest.raises(ValueError, match="no span"):
        direction_offset.direction_offset(T_est, T_gt, list(range(10, 20)), stride=4)


def _write_replay(d: Path, T_est: np.ndarray, T_gt: np.ndarray, states: list[str]) -> None:
    d.mkdir()
    stamps = 1.0 + 0.1 * np.arange(len(T_est))
    for name, T in (("trajectory.tum", T_est), ("groundtruth.tum", T_gt)):
        q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
        tum.write_tum(d / name, stamps, T[:, :3, 3], q)
    with (d / "frames.jsonl").open("w") as f:
        for i, (s, state) in enumerate(zip(stamps, states, strict=True)):
            f.write(json.dumps({"index": i, "stamp_ns": round(s * 1e9), "state": state}) + "\n")


def test_a_replay_directory_from_a_frame_on(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The first 12 frames carry another offset (as KITTI's contradicted ground truth does); from frame 12
    the constant one is found; frames that are not tracking start no span."""
    T_a, T_g = _drive(50, (0.5, -0.5))
    T_b, _ = _drive(50, (-0.2, 0.15))
    T_est = T_a.copy()
    for i in range(13, 50):  # from frame 12 on, the steps of the second drive
        T_est[i, :3, 3] = T_est[i - 1, :3, 3] + (T_b[i, :3, 3] - T_b[i - 1, :3, 3])
    states = ["tracking"] * 50
    states[20] = "lost"
    _write_replay(tmp_path / "r", T_est, T_g, states)
    o = direction_offset.replay_offset(tmp_path / "r", start=12, stride=4)
    assert o.spans == 50 - 12 - 4 - 1
    assert o.horizontal_deg == pytest.approx(-0.2, abs=0.003) and o.vertical_deg == pytest.approx(0.15, abs=0.003)
    assert direction_offset.main([str(tmp_path / "r"), "--from", "12", "--fx", "700"]) == 0
    out = capsys.readouterr().out
    assert "33 spans of 4 frames: horizontal -0.200 deg" in out and "move it by (-2.4, +1.8) px" in out
    assert direction_offset.main([str(tmp_path / "missing")]) == 1
