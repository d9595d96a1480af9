"""scripts/robot_drives.py, held-out ground-robot drives: valid drives, one per seed, the bundled one untouched."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import numpy as np
from script_module import load_script

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bags"))
import make_bags as mb

robot_drives = load_script("robot_drives")


def test_each_seed_gives_its_own_drive_clear_of_the_yard_and_leaves_the_bundled_one_alone() -> None:
    bundled = mb.ROBOT_TURNS
    specs = {}
    for seed in (1, 2):
        spec, turns, _ = robot_drives.drive_spec(seed)
        specs[seed] = (spec, turns)
        assert mb.ROBOT_TURNS == bundled
        assert spec.name == f"robot_drive_{seed}" and spec.T_w_c.shape == (mb.ROBOT_FRAMES, 4, 4)
        assert spec.wheel_odom is not None
        # four turns, left first and then alternating, none overlapping, all within the 20 s drive
        assert len(turns) == 4 and [np.sign(p) for _, _, p in turns] == [1.0, -1.0, 1.0, -1.0]
        ends = [(c - 0.5 * d, c + 0.5 * d) for c, d, _ in turns]
        assert all(a[1] <= b[0] for a, b in itertools.pairwise(ends))
        assert ends[-1][0] < mb.ROBOT_FRAMES / 15.0
        assert all(12.0 <= abs(p) <= 22.0 for _, _, p in turns)
        # the camera stays 0.45 m above the floor and 2 m from every structure
        np.testing.assert_allclose(spec.T_w_c[:, 1, 3], 0.0, atol=1e-9)
        assert mb.min_clearance_m(spec.quads, spec.T_w_c) >= mb.ROBOT_MIN_CLEARANCE_M
        assert robot_drives._structures_clear(spec.quads, spec.T_w_c)
        assert mb.max_floor_flow_px(spec.camera, spec.T_w_c, mb.ROBOT_FLOOR_Y_M) <= mb.MAX_FLOOR_FLOW_PX
    assert specs[1][1] != specs[2][1] and specs[1][0].noise_seed != specs[2][0].noise_seed
    again, turns, _ = robot_drives.drive_spec(1)
    assert turns == specs[1][1]
    np.testing.assert_array_equal(again.T_w_c, specs[1][0].T_w_c)
    # the bundled drive differs from the held-out ones
    times = np.array([(mb.stamp_ns(i) - mb.START_NS) / mb.NS_PER_S for i in range(mb.ROBOT_FRAMES)])
    T_bundled = mb.robot_camera_poses(mb.robot_base_poses(times))
    assert np.abs(T_bundled[:, :3, 3] - specs[1][0].T_w_c[:, :3, 3]).max() > 0.3
