"""`epi-vo replay` on a perturbed bag: the robustness figures of the README come from this.

The bag is not rewritten: the replay's frame iterator and image decoder are wrapped.

    .venv/bin/python scripts/perturbed_replay.py [--start N] [--every K] [--gain-step F@FRAME]
        [--flicker A/PERIOD] [--noise SIGMA] -- replay BAG --output DIR [replay options]

--start N        skip the bag's first N frames (a node started mid-run)
--every K        keep every K-th frame only (dropped frames)
--gain-step F@I  multiply the grey levels by F from the I-th replayed frame on (exposure step; 0.6: 40 %
                 darker)
--flicker A/P    multiply the grey levels by 1 + A sin(2 pi i / P) (auto-exposure flicker)
--noise SIGMA    add Gaussian noise of SIGMA grey levels (seeded)
--blur S/K       Gaussian blur of sigma S px on every K-th replayed frame (defocus)
--motion-blur L/K horizontal motion blur over L px on every K-th replayed frame
--focal-scale F  a wrong calibration: fx and fy of every camera_info multiplied by F
--cx-shift PX    a wrong calibration: cx of every camera_info shifted by PX pixels

Everything after ``--`` is the ``epi-vo`` command line. With --start or --every the replay reports the
frames left out as announced but not read (exit status 3); its outputs are complete for what it read.
"""

from __future__ import annotations

import argparse
import math
import sys

import cv2
import numpy as np


def main(argv: list[str]) -> int:
    if "--" not in argv:
        print(__doc__, file=sys.stderr)
        return 2
    cut = argv.index("--")
    ap = argparse.ArgumentParser(description="epi-vo replay on a perturbed bag")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--gain-step", default="")
    ap.add_argument("--flicker", default="")
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--blur", default="")
    ap.add_argument("--motion-blur", default="")
    ap.add_argument("--focal-scale", type=float, default=1.0)
    ap.add_argument("--cx-shift", type=float, default=0.0)
    args = ap.parse_args(argv[:cut])
    if args.start < 0 or args.every < 1 or args.noise < 0:
        ap.error("--start >= 0, --every >= 1, --noise >= 0")
    step, step_at = (float(args.gain_step.split("@")[0]), int(args.gain_step.split("@")[1])) if args.gain_step \
        else (1.0, 0)
    amp, period = (float(args.flicker.split("/")[0]), float(args.flicker.split("/")[1])) if args.flicker \
        else (0.0, 1.0)
    blur, blur_every = (float(args.blur.split("/")[0]), int(args.blur.split("/")[1])) if args.blur else (0.0, 1)
    streak, streak_every = (int(args.motion_blur.split("/")[0]), int(args.motion_blur.split("/")[1])) \
        if args.motion_blur else (0, 1)

    import epi_vo.io.bagio as bagio
    import epi_vo.runner.frames as frames_module
    from epi_vo.cli import main as cli_main
    from epi_vo.core.camera import CameraModel

    if args.focal_scale != 1.0 or args.cx_shift:
        create = CameraModel.create.__func__  # type: ignore[attr-defined]

        def miscalibrated(cls, width, height, K, D, *rest, **kw):  # type: ignore[no-untyped-def]
            K = np.asarray(K, np.float64).reshape(3, 3).copy()
            K[0, 0] *= args.focal_scale
            K[1, 1] *= args.focal_scale
            K[0, 2] += args.cx_shift
            return create(cls, width, height, K, D, *rest, **kw)

        CameraModel.create = classmethod(miscalibrated)  # type: ignore[method-assign,assignment]

    for name in dir(bagio):
        cls = getattr(bagio, name)
        if isinstance(cls, type) and hasattr(cls, "iter_frames"):
            def frames(self, _inner=cls.iter_frames):  # type: ignore[no-untyped-def]
                for i, f in enumerate(_inner(self)):
                    if i >= args.start and (i - args.start) % args.every == 0:
                        yield f
            cls.iter_frames = frames

    decode = frames_module.decode_frame  # the frame handler's decoder (replay and node)
    rng = np.random.default_rng(0)
    count = [0]

    def perturbed(msg, compressed, expected_size=None):  # type: ignore[no-untyped-def]
        gray = decode(msg, compressed, expected_size)
        i = count[0]
        count[0] += 1
        if blur and i % blur_every == 0:
            gray = cv2.GaussianBlur(gray, (0, 0), blur)
        if streak and i % streak_every == 0:
            kernel = np.zeros((streak, streak), np.float32)
            kernel[streak // 2, :] = 1.0 / streak
            gray = cv2.filter2D(gray, -1, kernel)
        gain = (1.0 + amp * math.sin(2.0 * math.pi * i / period)) * (step if i >= step_at else 1.0)
        if gain == 1.0 and not args.noise:
            return gray
        g = gray.astype(np.float32) * gain
        if args.noise:
            g += rng.normal(0.0, args.noise, g.shape).astype(np.float32)
        return np.clip(g + 0.5, 0, 255).astype(np.uint8)

    frames_module.decode_frame = perturbed
    return cli_main(argv[cut + 1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
