"""Soak: many frames through the pipeline while resident memory is watched (``epi-vo soak``).

The frames of a (short) bag are played forward, backward, forward, ... with stamps increasing at the
bag's frame rate, so 52 recorded frames become any number of frames of continuous, trackable motion.
Every result also goes through what both front doors do with it (odometry conversion, diagnostics
status, JSON record), so their per-frame state is soaked too. Images are decoded once, up front: the
soak measures the pipeline, not the JPEG decoder.

Resident memory is the kernel's ``VmRSS`` of this process. The verdict compares every sample after the
warm-up with the sample at the end of the warm-up: growth below ``max_growth_percent`` passes.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.errors import BagError
from epi_vo.io import bagio, checks
from epi_vo.io.msgconv import decode_frame
from epi_vo.runner import make_pipeline
from epi_vo.runner.outputs import OutputMaker

DEFAULT_BAG = Path(__file__).resolve().parents[2] / "bags" / "general_motion" / "bag"


def rss_bytes(pid: int | str = "self") -> int:
    """Resident set size (VmRSS) of process ``pid`` in bytes, from ``/proc/<pid>/status`` (Linux)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    msg = f"/proc/{pid}/status has no VmRSS line"
    raise OSError(msg)


@dataclass(frozen=True)
class SoakFrames:
    """Decoded gray frames of a bag, the camera they were taken with, and the bag's frame period."""

    grays: tuple[NDArray[np.uint8], ...]
    camera: CameraModel
    period_ns: int


def load_frames(bag: str | Path = DEFAULT_BAG) -> SoakFrames:
    """Decode every image of ``bag`` (one calibration assumed: the first frame's camera_info)."""
    grays = []
    stamps = []
    camera: CameraModel | None = None
    with bagio.open_camera_bag(bag) as b:
        for frame in b.iter_frames():
            if camera is None:
                if frame.camera_info_msg is None:
                    msg = f"bag {bag} has no camera_info"
                    raise BagError(msg)
                camera = CameraModel.from_camera_info(frame.camera_info_msg)
            grays.append(decode_frame(frame.image_msg, b.image_is_compressed))
            stamps.append(frame.stamp_ns)
    if camera is None or len(grays) < 3:
        msg = f"bag {bag} has {len(grays)} images; a soak needs at least 3"
        raise BagError(msg)
    period = int(np.median(np.diff(stamps))) if len(stamps) > 1 else 0
    return SoakFrames(tuple(grays), camera, period if period > 0 else 66_666_667)


def ping_pong(n_source: int, i: int) -> int:
    """Source frame of soak frame ``i``: 0, 1, ..., n-1, n-2, ..., 1, 0, 1, ... (the motion reverses smoothly)."""
    cycle = 2 * n_source - 2
    k = i % cycle
    return k if k < n_source else cycle - k


@dataclass(frozen=True)
class SoakSample:
    """Memory and speed after ``frame`` frames; ``ms_per_frame`` is the median of the last interval."""

    frame: int
    rss_mb: float
    growth_percent: float  # against the sample at the end of the warm-up (0 during the warm-up)
    ms_per_frame: float
    elapsed_s: float


@dataclass(frozen=True)
class SoakResult:
    frames: int
    warmup_frames: int
    samples: tuple[SoakSample, ...]
    rss_warm_mb: float
    max_growth_percent: float  # largest growth of any sample after the warm-up
    final_growth_percent: float
    tracked_percent: float  # frames with a pose
    states: dict[str, int]
    limit_percent: float

    @property
    def passed(self) -> bool:
        return self.max_growth_percent < self.limit_percent


def run_soak(n_frames: int, frames: SoakFrames | None = None, cfg: VoConfig | None = None, *,
             warmup: int = 500, sample_every: int = 500, max_growth_percent: float = 5.0,
             on_sample: Callable[[SoakSample], None] | None = None) -> SoakResult:
    """Run ``n_frames`` frames through one :class:`VoPipeline` and sample resident memory.

    Samples are taken at frame ``warmup`` and every ``sample_every`` frames, and after the last frame.
    """
    if n_frames <= warmup:
        msg = f"a soak of {n_frames} frames needs more than the {warmup} warm-up frames"
        raise ValueError(msg)
    frames = frames or load_frames()
    pipeline = make_pipeline(cfg or VoConfig())
    outputs = OutputMaker()
    states: Counter[str] = Counter()
    n_pose = 0
    samples: list[SoakSample] = []
    times: list[float] = []
    rss_warm = math.nan
    t_start = time.monotonic()
    n_src = len(frames.grays)

    def sample(i: int) -> None:
        rss = rss_bytes() / 2**20
        growth = 0.0 if i <= warmup else 100.0 * (rss - rss_warm) / rss_warm
        s = SoakSample(i, rss, growth, statistics.median(times) if times else math.nan, time.monotonic() - t_start)
        samples.append(s)
        times.clear()
        if on_sample is not None:
            on_sample(s)

    for i in range(n_frames):
        gray = frames.grays[ping_pong(n_src, i)]
        result = pipeline.process(gray, frames.camera, (i + 1) * frames.period_ns)
        # What the front doors do with each result (their per-frame state soaks too).
        json.dumps(outputs.outputs(result, "epi_vo", "soak").record)
        times.append(result.timings_ms.get("total", math.nan))
        states[result.state.value] += 1
        n_pose += int(result.has_pose)
        done = i + 1
        if done == warmup:
            sample(done)
            rss_warm = samples[-1].rss_mb
        elif done == n_frames or (done > warmup and (done - warmup) % sample_every == 0):
            sample(done)
    after = [s.growth_percent for s in samples if s.frame > warmup]
    return SoakResult(n_frames, warmup, tuple(samples), rss_warm, max(after), after[-1], 100.0 * n_pose / n_frames,
                      dict(states), max_growth_percent)


def format_sample(s: SoakSample) -> str:
    return f"{s.frame:>8d} {s.rss_mb:>9.1f} {s.growth_percent:>+9.2f} {s.ms_per_frame:>10.2f} {s.elapsed_s:>9.1f}"


SAMPLE_HEADER = f"{'frame':>8} {'RSS MB':>9} {'growth %':>9} {'ms/frame':>10} {'elapsed s':>9}"


def format_verdict(r: SoakResult) -> str:
    verdict = "PASS" if r.passed else "FAIL"
    return (f"{verdict}: {r.frames} frames, RSS {r.rss_warm_mb:.1f} MB after {r.warmup_frames} warm-up frames, "
            f"max growth {r.max_growth_percent:+.2f} % (final {r.final_growth_percent:+.2f} %, limit "
            f"{r.limit_percent:g} %); with pose {r.tracked_percent:.1f} %; states "
            + ", ".join(f"{k} {v}" for k, v in sorted(r.states.items())))


def run(args: argparse.Namespace) -> int:
    """``epi-vo soak``: print RSS over time and the verdict; exit status 0 on PASS, 1 on FAIL."""
    from epi_vo.io.params import load_config

    checks.number(args.warmup, "--warmup", minimum=0)
    checks.number(args.every, "--every", minimum=1)
    checks.number(args.max_growth, "--max-growth", positive=True)
    if args.frames <= args.warmup or args.every <= 0:
        print(f"epi-vo: error: --frames ({args.frames}) must exceed --warmup ({args.warmup}) and --every must be "
              "positive", file=sys.stderr)
        return 2
    frames = load_frames(args.bag or DEFAULT_BAG)
    print(f"epi_vo soak: {args.frames} frames of {args.bag or DEFAULT_BAG} ({len(frames.grays)} frames played "
          f"forward and backward), warm-up {args.warmup}, RSS every {args.every} frames", flush=True)
    print(SAMPLE_HEADER, flush=True)
    result = run_soak(args.frames, frames, load_config(args.params), warmup=args.warmup, sample_every=args.every,
                      max_growth_percent=args.max_growth,
                      on_sample=lambda s: print(format_sample(s), flush=True))
    print(format_verdict(result))
    return 0 if result.passed else 1
