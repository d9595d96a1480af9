"""scripts/prior_draws.py: replays over draws of the scale source's prior carry the drawn error into metres."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from script_module import load_script

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "ground_robot" / "bag"
prior_draws = load_script("prior_draws")


def test_the_draws_are_seeded_normals() -> None:
    assert prior_draws.draw_z(2) == random.Random(2).gauss(0.0, 1.0)
    assert prior_draws.draw_z(2) == pytest.approx(2.34, abs=0.01)  # the 2.3-sigma draw used below


def test_a_mismeasured_camera_height_is_the_scale_error_and_the_nees_shows_it(tmp_path: Path) -> None:
    """Seed 2 draws a camera height 4.6 % too high (z = 2.34 at 2 %): the metric trajectory is 4.6 % long
    (step scale), and its position NEES is above what the exact height gives (2.53): the claimed
    2 % now shows as error."""
    (d,) = prior_draws.run_draws(BAG, tmp_path, "ground_plane", 1, seed0=2, camera_height=0.45)
    assert d.value == pytest.approx(0.45 * (1.0 + 0.02 * d.z))
    assert d.metrics["step_scale_median"] == pytest.approx(1.0 + 0.02 * d.z, abs=0.005)
    assert 3.0 < d.metrics["nees_pos"] < 8.0
    assert d.metrics["ate_se3_percent_of_path"] > 1.0  # the exact height: 0.04 %


def test_scaled_wheels_scale_the_metres(tmp_path: Path) -> None:
    """Seed 104 (z = 1.96 at 3 %): the wheel positions x 1.033, so the steps are 1.033 x the bag's own wheel
    error (1.021) long."""
    (d,) = prior_draws.run_draws(BAG, tmp_path, "wheel_odometry", 1, seed0=104)
    assert d.value == pytest.approx((1.0 + 0.03 * d.z) / 1.025)
    assert d.metrics["step_scale_median"] == pytest.approx(1.021 * d.value, rel=0.003)
    assert (tmp_path / "draw_104" / "trajectory.tum").is_file()


def test_no_draw_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert prior_draws.main([str(BAG), "/nonexistent", "--source", "ground_plane", "--draws", "0"]) == 2
    assert "--draws must be at least 1" in capsys.readouterr().err
