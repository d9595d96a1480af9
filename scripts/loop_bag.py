"""Render a held-out long loop: general_motion's courtyard walked once round a circle, 720 frames.

Not a bundled bag (4 minutes to render, 57 MB): a sequence the pipeline and its covariance were never
tuned on, to check them over a long run that comes back to its start. The camera (general_motion's
distorted model, 1.6 m above the ground) walks a 3.8 m-radius circle in the open part of the courtyard
at 0.5 m/s, looking 10 deg off the direction of travel, with small pitch, roll and height waves; 15 Hz,
compressed images, exact ground truth (``bags/make_bags.py`` renders it).

    .venv/bin/python scripts/loop_bag.py OUT_DIR [--frames 720]
    .venv/bin/epi-vo replay OUT_DIR/loop720/bag --output /tmp/loop     # ATE and NEES against its ground truth
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bags"))
import make_bags as mb

CENTRE_XZ = (0.0, -2.5)  # m, world x (right) and z (forward): the open part in front of the boxes
RADIUS_M = 3.8  # the nearest box and the front wall stay 1.5 m away (the renderer's minimum)
LOOK_OFF_DEG = -10.0  # the optical axis against the direction of travel (yaw)


def loop_spec(n_frames: int) -> mb.BagSpec:
    """One full circle over ``n_frames``: sample i at angle 2 pi i / (n - 1), so the last pose is the first."""
    deg = math.pi / 180.0

    def position(s: float) -> tuple[float, float, float]:
        a = 2.0 * math.pi * s
        return (CENTRE_XZ[0] + RADIUS_M * math.sin(a), -0.1 * math.sin(3.0 * a),
                CENTRE_XZ[1] - RADIUS_M * math.cos(a))

    def angles(s: float) -> tuple[float, float, float]:
        a = 2.0 * math.pi * s
        yaw = math.atan2(math.cos(a), math.sin(a)) + LOOK_OFF_DEG * deg  # travel is (cos a, sin a) in x, z
        return yaw, 2.0 * deg * math.sin(4.0 * a), 1.5 * deg * math.sin(3.0 * a + 0.3)

    return mb.BagSpec(f"loop{n_frames}", mb.courtyard_scene(), mb.make_camera(mb.DISTORTION_GENERAL),
                      mb.smooth_trajectory(n_frames, position, angles), noise_seed=11)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", type=int, default=720)
    args = ap.parse_args(argv)
    if args.frames < 3:
        print("loop_bag: --frames must be at least 3", file=sys.stderr)
        return 2
    s = mb.make_bag(loop_spec(args.frames), args.out)
    print(f"{s.name}: {s.frames} frames, path {s.path_length_m:.2f} m, clearance {s.min_clearance_m:.2f} m, "
          f"{s.bag_bytes / 1e6:.1f} MB, {s.seconds:.0f} s -> {args.out / s.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
