"""Render held-out ground-robot drives: ground_robot's yard and robot, other turns and other noise.

Not bundled bags (about 3 minutes and 14 MB each): drives the pipeline, its scale sources and its
covariance were never tuned on, to tell a property of the robot view from one of the one bundled drive.
Drive ``k`` keeps ground_robot's camera (0.45 m high, 15 deg down), speed law, 300 frames at 15 Hz and wheel
error model (bags/README.md), and draws from seed ``k``: four raised-cosine turns (each 2.5-4 s long,
12-22 deg/s at its peak, left first, then right and left in turn), the image noise and the wheel noise.
A drive that would come nearer than 2 m to a structure, or move a floor point faster than the renderer
allows, is re-drawn (the seed's next draw; the summary says how many were).

    .venv/bin/python scripts/robot_drives.py OUT_DIR --seeds 1 2 3
    .venv/bin/epi-vo replay OUT_DIR/robot_drive_1/bag --output DIR --params P.yaml   # as ground_robot
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bags"))
import make_bags as mb

TURNS = 4
DURATION_S = (2.5, 4.0)
PEAK_DEG_S = (12.0, 22.0)
FIRST_CENTRE_S = (2.5, 4.0)
GAP_S = (1.0, 2.5)  # straight driving between two turns
ATTEMPTS = 20


def draw_turns(rng: np.random.Generator) -> tuple[tuple[float, float, float], ...]:
    """Four non-overlapping turns (centre s, duration s, signed peak deg/s), 1-2.5 s of straight driving
    between two (the last one usually starts 14-19 s into the 20 s drive)."""
    turns: list[tuple[float, float, float]] = []
    sign = 1.0  # left first: the bundled drive's corridor leaves no room for a right turn first
    end = rng.uniform(*FIRST_CENTRE_S) - 0.5 * DURATION_S[0]
    for _ in range(TURNS):
        duration = rng.uniform(*DURATION_S)
        centre = end + (rng.uniform(*GAP_S) if turns else 0.0) + 0.5 * duration
        end = centre + 0.5 * duration
        turns.append((float(centre), float(duration), sign * float(rng.uniform(*PEAK_DEG_S))))
        sign = -sign  # left and right in turn: the yard is a corridor
    return tuple(turns)


def drive_spec(seed: int) -> tuple[mb.BagSpec, tuple[tuple[float, float, float], ...], int]:
    """The spec of drive ``seed``, its turns and how many draws were re-drawn for clearance."""
    rng = np.random.default_rng(seed)
    quads, camera = mb.ground_robot_scene(), mb.make_camera()
    times = np.array([(mb.stamp_ns(i) - mb.START_NS) / mb.NS_PER_S for i in range(mb.ROBOT_FRAMES)])
    bundled = mb.ROBOT_TURNS
    try:
        for attempt in range(ATTEMPTS):
            turns = mb.ROBOT_TURNS = draw_turns(rng)  # the speed, heading and wheel laws read it
            T_w_c = mb.robot_camera_poses(mb.robot_base_poses(times))
            if mb.min_clearance_m(quads, T_w_c) >= mb.ROBOT_MIN_CLEARANCE_M and _structures_clear(quads, T_w_c) \
                    and mb.max_floor_flow_px(camera, T_w_c, mb.ROBOT_FLOOR_Y_M) <= mb.MAX_FLOOR_FLOW_PX:
                wheel = mb.simulate_wheel_odometry(mb.wheel_stamps_ns(mb.ROBOT_FRAMES), seed=1000 + seed)
                spec = mb.BagSpec(f"robot_drive_{seed}", quads, camera, T_w_c, noise_seed=100 + seed,
                                  min_clearance_m=mb.ROBOT_MIN_CLEARANCE_M, jpeg_quality=mb.ROBOT_JPEG_QUALITY,
                                  wheel_odom=wheel, floor_y_m=mb.ROBOT_FLOOR_Y_M)
                return spec, turns, attempt
    finally:
        mb.ROBOT_TURNS = bundled  # the bundled bag's drive for anything else that renders in this process
    raise mb.SceneError(f"drive {seed}: no draw of {ATTEMPTS} keeps clear of the structures")


def _structures_clear(quads: tuple[mb.Quad, ...], T_w_c: np.ndarray, clearance_m: float = 2.0) -> bool:
    """Every camera centre at least ``clearance_m`` from every quad that is not the floor."""
    floor = [q for q in quads if abs(q.origin_w[1] - mb.ROBOT_FLOOR_Y_M) < 1e-9 and q.edge_u_w[1] == 0.0
             and q.edge_v_w[1] == 0.0]
    others = tuple(q for q in quads if not any(q is f for f in floor))
    return mb.min_clearance_m(others, T_w_c) >= clearance_m


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="output folder (robot_drive_<seed>/ each)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = parser.parse_args(argv)
    for seed in args.seeds:
        spec, turns, redrawn = drive_spec(seed)
        summary = mb.make_bag(spec, args.out)
        told = ", ".join(f"{p:+.0f} deg/s at {c:.1f} s" for c, _, p in turns)
        print(f"{summary.name}: {summary.frames} frames, path {summary.path_length_m:.2f} m, turns {told} "
              f"({redrawn} re-drawn), {summary.seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
