"""The published covariance on the real Tello clip (../shared/data/tello_semicircle_206f, when present):
the pose NEES of what ``epi-vo benchmark`` judges (``tools.benchmark.bench_epi_vo``).

The clip's first frames have no map (initialising, its reference keyframe re-anchored while the position
is held): what is published then carries the "unknown" variance, and the map that follows must not. Its
ground truth judges positions (its README), so the position NEES is asserted: issue 41's target, 1-6."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest

from epi_vo.core.config import VoConfig
from epi_vo.tools.benchmark import BenchRow, bench_epi_vo

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
TELLO = DATA / "tello_semicircle_206f"
KITTI = DATA / "kitti06_0-50"


def bench_clip(clip: Path) -> BenchRow:
    """The benchmark's row of epi_vo on a real clip with the default parameters (skipped when absent)."""
    if not ((clip / "bag").is_dir() and (clip / "groundtruth_tum.txt").is_file()):
        pytest.skip(f"{clip} not present")
    logging.getLogger("epi_vo").setLevel(logging.ERROR)
    return bench_epi_vo(clip.name, clip / "bag", clip / "groundtruth_tum.txt", VoConfig())


@pytest.mark.xfail(strict=True, reason="issue 41 open: the held start's motion is now estimated from the parallax "
                   "its frames saw (about the ground truth's), but the position NEES is 0.62 (docs/covariance.md)")
def test_the_tello_clips_position_covariance_is_consistent_after_a_held_start() -> None:
    """Before: the pre-map "unknown" 1e4 was carried into the map, position NEES 0.01 (a real error
    divided by 1e4 for the whole run). The map now starts from its estimate plus the motion the held time
    allowed (the map's first speed over it), and the NEES is in 1-6."""
    row = bench_clip(TELLO)
    assert row.nees_frames > 150
    assert math.isfinite(row.nees_pos) and 1.0 <= row.nees_pos <= 6.0, f"position NEES {row.nees_pos:.3g}"


def test_the_kitti_drives_position_covariance_covers_its_steps_shared_rotation_error() -> None:
    """A forward drive: each keyframe step's E reads part of its turn as a sideways direction of travel, the
    same way step after step, and the map's points (with depths, where a rotation and a sideways translation
    differ) measure it (``rotation_bias_cov``). Carried as an error the steps share, it moves the later
    positions through the lever arm: the position NEES was 12.9 with the steps' errors independent. The
    rotation (86.6, 120.8 before) is still far over-confident: not this test's."""
    row = bench_clip(KITTI)
    assert row.nees_frames > 40
    assert math.isfinite(row.nees_pos) and 1.0 <= row.nees_pos <= 6.0, f"position NEES {row.nees_pos:.3g}"
    assert row.nees_rot < 100.0, f"rotation NEES {row.nees_rot:.3g}"
