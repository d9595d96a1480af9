"""The scenario distribution's subset in the default suite: one short seed per family (seed 1, 320 px wide,
40 frames; rendered into the scenario cache when missing), replayed by epi_vo with the default
configuration and with each metric scale source its family carries, against bounds that catch a family
falling back.

``TODAY`` holds what this commit's pipeline measures on the subset (``epi-vo benchmark --suite subset``
prints the same figures). A bound is ``max(BOUND_FACTOR x today, today + floor)``: a family whose ATE
doubles fails (for any ATE above the floor, 0.1 % of the path), while small changes of the inputs (another
CPU's rounding in OpenCV) do not. When a family improves for good, lower its entry here so the bound
follows it. The whole distribution (``epi-vo benchmark --suite distribution``) is what judges a change;
this subset only keeps a family from silently falling back.

The figures are deterministic: the renders are (bags/scenarios.py) and so is a replay; no figure is a time.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from epi_vo.core.config import VoConfig
from epi_vo.tools import distribution_table as dt
from epi_vo.tools.distribution import SequenceTask, run_distribution, run_tasks

BOUND_FACTOR = 1.6  # below 2: a doubling is caught
ATE_FLOOR = 0.1  # % of the path: a near-perfect family may vary by this much without failing
POSE_MARGIN = 10.0  # percentage points of frames with a pose a family may lose
MOVED_FLOOR = 0.5  # % of the map's depth a still camera may be moved by (the target: 1 %)
RPE_FLOOR = 0.02  # deg/frame
SE3_FLOOR = 0.2  # % of the path

# What epi_vo measures on each family's subset sequence as the code is (`epi-vo benchmark --suite subset`; a
# change that moves them updates them and says why in its commit): ATE % of the path
# (Sim(3); static families: none), frames with a pose %, RPE rotation deg/frame; static families: the
# largest displacement as % of the map's depth; metric rows: SE(3)-only ATE %.
TODAY: dict[str, dict[str, float]] = {
    "forward": {"ate": 1.355, "pose": 100.0},
    "sideways": {"ate": 1.656, "pose": 100.0},
    "orbit": {"ate": 0.3331, "pose": 100.0},
    "planar_wall": {"ate": 2.338, "pose": 100.0},
    "floor_wall": {"ate": 1.494, "pose": 100.0},
    "floor_robot": {"ate": 0.847, "pose": 100.0, "ground_plane_se3": 0.454, "wheel_odometry_se3": 0.812},
    "road": {"ate": 0.418, "pose": 100.0, "ground_plane_se3": 0.658},
    "pure_rotation": {"rpe": 0.1702, "pose": 100.0, "moved": 0.0},
    "low_parallax": {"ate": 5.322, "pose": 100.0},
    "static_mover": {"rpe": 0.0, "pose": 100.0, "moved": 0.0},
    "moving_mover": {"ate": 7.318, "pose": 100.0},
    "fast": {"ate": 3.662, "pose": 100.0},
    "handheld": {"ate": 0.2989, "pose": 100.0},
    "handheld_hd": {"ate": 8.615, "pose": 100.0},
    "long_loop": {"ate": 1.599, "pose": 100.0},
}


def bound(today: float, floor: float) -> float:
    return max(BOUND_FACTOR * today, today + floor)


@pytest.fixture(scope="module")
def subset_results(scenario_generator: object, scenario_subset: list) -> dict[str, dt.SequenceResult]:
    gen = scenario_generator
    tasks = [SequenceTask(s.family, s.seed, s.path, s.info, gen.FAMILIES[s.family].scale_sources, VoConfig(),
                          reference=False) for s in scenario_subset]
    return {r.family: r for r in run_tasks(tasks, jobs=2)}


def test_every_family_has_bounds(scenario_generator: object) -> None:
    assert set(TODAY) == set(scenario_generator.FAMILIES)


def test_a_doubled_ate_exceeds_every_bound() -> None:
    for family, today in TODAY.items():
        if "ate" in today and today["ate"] > ATE_FLOOR:
            assert 2.0 * today["ate"] > bound(today["ate"], ATE_FLOOR), family


@pytest.mark.parametrize("family", sorted(TODAY))
def test_the_family_does_not_fall_back(subset_results: dict[str, dt.SequenceResult], family: str) -> None:
    today = TODAY[family]
    rows = {row.pipeline: row for row in subset_results[family].rows}
    vo = rows["epi_vo"]
    assert vo.tracked_percent >= today["pose"] - POSE_MARGIN, (family, vo.tracked_percent)
    if "ate" in today:
        ate, limit = (vo.ate_percent if math.isfinite(vo.ate_percent) else math.inf), bound(today["ate"], ATE_FLOOR)
        assert ate <= limit, f"{family}: ATE {ate:.3f} % of the path > {limit:.3f}"
    if "rpe" in today:
        assert vo.rpe_rot_deg <= bound(today["rpe"], RPE_FLOOR), (family, vo.rpe_rot_deg)
    if "moved" in today:
        assert vo.moved_depth_percent <= bound(today["moved"], MOVED_FLOOR), (family, vo.moved_depth_percent)
    for source in ("ground_plane", "wheel_odometry"):
        if f"{source}_se3" in today:
            row = rows[f"epi_vo[{source}]"]
            assert math.isfinite(row.metric_after_s), f"{family} {source}: metres never came"
            limit = bound(today[f"{source}_se3"], SE3_FLOOR)
            se3 = row.ate_se3_percent if math.isfinite(row.ate_se3_percent) else math.inf
            assert se3 <= limit, f"{family} {source}: SE(3) ATE {se3:.3f} % > {limit:.3f}"


def test_the_command_records_the_tables_with_the_reference_side_by_side(scenario_subset: list, tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    root = scenario_subset[0].path.parents[2]
    assert run_distribution("subset", None, families=["static_mover", "floor_robot"], jobs=1, cache=str(root),
                            real=False, record_dir=tmp_path) == 0
    printed = capsys.readouterr().out
    md, js = sorted(tmp_path.glob("*-subset.md")), sorted(tmp_path.glob("*-subset.json"))
    assert len(md) == len(js) == 1
    text = md[0].read_text()
    for part in ("- commit: `", "- render time: ", "- benchmark time: ", "| floor_robot | 320x240 | epi_vo |",
                 "| floor_robot | 320x240 | reference |", "| static_mover | reference |",
                 "| floor_robot | epi_vo[wheel_odometry] |", "### The generalization issue's targets",
                 "### Every sequence"):
        assert part in text, part
    assert "### Tracking and accuracy" in printed
    data = json.loads(js[0].read_text())
    seqs = {s["family"]: s for s in data["sequences"]}
    assert {r["pipeline"] for r in seqs["floor_robot"]["rows"]} == {
        "epi_vo", "epi_vo[ground_plane]", "epi_vo[wheel_odometry]", "reference"}
    assert seqs["floor_robot"]["scenario"]["metric"]["wheel_odometry_topic"] == "/wheel/odom"
    fam = data["families"]["floor_robot"]["epi_vo"]["ate_percent"]
    assert fam["seeds"] == 1 and fam["median"] == pytest.approx(TODAY["floor_robot"]["ate"], abs=1e-3)


def test_a_rule_is_judged_with_and_without_it_against_a_baseline(scenario_subset: list, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """An ablation: the run with one parameter changed (--set) printed family by family against the run
    without (--baseline); the changed parameter and the baseline are in the record."""
    root = str(scenario_subset[0].path.parents[2])
    assert run_distribution("subset", None, families=["floor_robot"], jobs=1, cache=root, real=False,
                            record_dir=tmp_path / "a", reference=False) == 0
    base_json = next((tmp_path / "a").glob("*-subset.json"))
    capsys.readouterr()
    assert run_distribution("subset", None, families=["floor_robot"], jobs=1, cache=root, real=False,
                            record_dir=tmp_path / "b", reference=False, overrides=["kf_min_parallax_deg=4.0"],
                            baseline=str(base_json)) == 0
    printed = capsys.readouterr().out
    before = json.loads(base_json.read_text())
    after = json.loads(next((tmp_path / "b").glob("*-subset.json")).read_text())
    assert after["overrides"] == ["kf_min_parallax_deg=4.0"] and after["baseline"] == str(base_json)
    kf = [after["families"]["floor_robot"]["epi_vo"]["keyframes_per_frame"]["median"],
          before["families"]["floor_robot"]["epi_vo"]["keyframes_per_frame"]["median"]]
    assert kf[0] < kf[1]  # fewer keyframes with a larger parallax gate
    section = printed.split("### Against the baseline", 1)[1]
    row = next(line for line in section.splitlines() if line.startswith("| floor_robot | epi_vo | 1 |"))
    assert f"{kf[1]:.2f} -> {kf[0]:.2f}" in row
    assert "| floor_robot | epi_vo[ground_plane] | 1 |" in section
    assert "reference" not in section


def test_a_record_is_replaced_only_by_a_run_of_the_same_commit(tmp_path: Path) -> None:
    from epi_vo.tools.bench_record import write_record

    md, _ = write_record(tmp_path, "distribution", "a", {"header": {"commit": "1" * 40}}, "2026-11-28", "1" * 40)
    assert md.name == "2026-11-28-distribution.md"
    md2, _ = write_record(tmp_path, "distribution", "b", {"header": {"commit": "1" * 40}}, "2026-11-28", "1" * 40)
    assert md2 == md and md.read_text() == "b\n"
    md3, js3 = write_record(tmp_path, "distribution", "c", {"header": {"commit": "2" * 40}}, "2026-11-28", "2" * 40)
    assert md3.name == "2026-11-28-distribution-2222222.md" and js3.name == "2026-11-28-distribution-2222222.json"
    assert md.read_text() == "b\n"  # the other commit's record stands beside it


@pytest.mark.parametrize(("args", "text"), [
    (["--suite", "distribution", "--bags", "bags"], "--bags is an option of the bundled suite"),
    (["--baseline", "x.json"], "--baseline is an option of --suite distribution and subset"),
    (["--suite", "subset", "--set", "kf_min_parallax_deg", "--no-record"], "expected NAME=VALUE"),
    (["--suite", "subset", "--set", "kf_min_parallax=2", "--no-record"], "kf_min_parallax_deg"),
    (["--suite", "subset", "--set", "kf_min_parallax_deg=-1", "--no-record"], "kf_min_parallax_deg"),
    (["--suite", "subset", "--baseline", "/nonexistent/x.json", "--no-record"], "--baseline /nonexistent/x.json"),
    (["--suite", "subset", "--families", "nope", "--no-record"], "unknown families nope"),
    (["--suite", "subset", "--jobs", "0", "--no-record"], "--jobs must be at least 1"),
    (["--perturb", "0.001"], "--perturb is an option of --suite distribution and subset"),
    (["--suite", "subset", "--perturb", "0", "--no-record"], "--perturb 0: a focal length change must be"),
    (["--suite", "subset", "--perturb", "0.001", "0.5", "--no-record"], "--perturb 0.5:"),
    (["--suite", "subset", "--ablate", "--perturb", "0.001", "--no-record"], "leave --set, --baseline and --perturb"),
])
def test_bad_arguments_are_one_line_errors_before_anything_runs(args: list[str], text: str,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    from epi_vo.cli import main

    assert main(["benchmark", *args]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and text in captured.err and len(captured.err.strip().splitlines()) == 1
