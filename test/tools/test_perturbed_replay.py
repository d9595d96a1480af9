"""scripts/perturbed_replay.py, the source of the README's robustness figures: it replays what it says
(frames skipped, dropped, exposure changed). A subprocess: it patches the replay's reader and decoder."""

from __future__ import annotations

import itertools
import json
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "general_motion" / "bag"


def _run(tmp_path: Path, *opts: str, bag: Path = BAG) -> list[dict]:
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "perturbed_replay.py"), *opts, "--", "replay",
                           str(bag), "--output", str(out), "--no-progress"], capture_output=True, text=True,
                          timeout=600, check=False)
    # Frames left out by --start / --every are what the replay reports as not read (exit status 3).
    assert done.returncode == 0 or (done.returncode == 3 and "could be read" in done.stderr), done.stderr
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


def test_start_and_every_pick_the_frames(tmp_path: Path) -> None:
    records = _run(tmp_path, "--start", "40", "--every", "3")
    assert len(records) == 4  # frames 40, 43, 46, 49 of 52
    stamps = [r["stamp"] for r in records]
    assert all(abs((b - a) - 3 / 15) < 0.01 for a, b in itertools.pairwise(stamps))


def test_an_exposure_step_is_reported_where_it_happens(tmp_path: Path) -> None:
    records = _run(tmp_path, "--start", "30", "--gain-step", "0.6@5")
    said = [i for i, r in enumerate(records) if "exposure changed: the image was scaled by 1.6" in r["reason"]]
    assert said == [5]
    assert all(r["has_pose"] for r in records)


def test_a_rotating_camera_with_a_wrong_focal_length_moves_nowhere_and_names_the_focal_length(tmp_path: Path) -> None:
    """pure_rotation with camera_info's fx and fy x 0.9: before the focal check it initialised a planar
    map and moved on 36 frames. Now every frame holds the position at the origin, and the rotation-only
    frames the calibration makes look like parallax name the true focal length (1 / 0.9 of it)."""
    records = _run(tmp_path, "--focal-scale", "0.9", bag=REPO / "bags" / "pure_rotation" / "bag")
    assert len(records) == 52 and all(r["has_pose"] for r in records)
    assert all(r["position"] == [0.0, 0.0, 0.0] for r in records)
    assert sum(r["state"] == "rotation_only" for r in records) >= 45
    named = [r["focal_ratio"] for r in records if r["reason"].startswith("pure rotation if the focal length were")]
    assert len(named) >= 30 and None not in named
    assert all(abs(ratio * 0.9 - 1.0) < 0.01 for ratio in named)
    assert sum(r["focal_ratio"] is not None for r in records) == len(named)
    notes = json.loads((tmp_path / "out" / "stats.json").read_text())["notes"]
    assert [n for n in notes if n.startswith("check the camera calibration")] == [
        f"check the camera calibration: {len(named)} frames fit a pure rotation under a focal length "
        f"{statistics.median(named):.3f} x camera_info's (median; per frame: focal_ratio)"]
