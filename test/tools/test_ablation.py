"""Every rule judged with and without it (epi_vo.tools.ablation): the verdict's arithmetic on made-up
figures, and the command on the subset."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from epi_vo.tools.ablation import RULES, judge, run_ablation, verdict


def _data(ate_median: float, pose: float, real_ate: float | None) -> dict[str, Any]:
    stat = {"median": ate_median, "p90": ate_median * 2, "worst": ate_median * 3, "judged": 8, "seeds": 8}
    return {"families": {"road": {"epi_vo": {"ate_percent": stat,
                                             "tracked_percent": {"median": pose, "p90": pose, "worst": pose}}},
                         "reference": {}},
            "real": [{"bag": "tello", "pipeline": "epi_vo", "ate_percent": real_ate, "tracked_percent": 99.0}]}


def test_a_family_clearly_worse_without_the_rule_means_it_pays() -> None:
    worse, better = judge(_data(1.0, 100.0, 0.5), _data(1.5, 100.0, 0.5))
    assert [w.split()[:4] for w in worse] == [["road", "epi_vo", "ate_percent", "median"],
                                               ["road", "epi_vo", "ate_percent", "p90"]]
    assert better == [] and verdict(worse, better) == "pays"


def test_small_moves_decide_nothing_and_a_lost_figure_is_the_worst() -> None:
    assert judge(_data(1.0, 100.0, 0.5), _data(1.04, 99.5, 0.52)) == ([], [])  # within 10 % / the floors
    assert verdict([], []) == "no effect"
    worse, better = judge(_data(1.0, 100.0, 0.5), _data(1.0, 100.0, None))  # the clip failed without the rule
    assert worse == ["tello epi_vo ate_percent 0.50 -> fail"] and better == []
    worse, better = judge(_data(1.0, 100.0, 0.5), _data(0.5, 80.0, 0.5))  # better ATE, fewer poses
    assert verdict(worse, better) == "mixed"
    assert worse == ["road epi_vo tracked_percent median 100.00 -> 80.00"]


def test_every_rule_names_a_parameter_and_its_off_value_is_valid() -> None:
    from epi_vo.core.config import from_dict

    for rule in RULES:
        from_dict({rule.name: rule.off})


def test_the_command_records_a_verdict_per_rule(scenario_subset: list, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    root = str(scenario_subset[0].path.parents[2])
    assert run_ablation("subset", None, ["kf_max_interval_s", "e_map_max_rotation_diff_deg"], record_dir=tmp_path,
                        families=["floor_robot", "static_mover"], jobs=1, cache=root, real=False) == 0
    printed = capsys.readouterr().out
    data = json.loads(next(tmp_path.glob("*-subset-ablation.json")).read_text())
    assert [r["rule"] for r in data["rules"]] == ["kf_max_interval_s", "e_map_max_rotation_diff_deg"]
    for r in data["rules"]:
        assert r["verdict"] == verdict(r["worse"], r["better"])
        assert f"| `{r['rule']}` |" in printed and f"**{r['verdict']}**" in printed


def test_an_unknown_rule_is_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    from epi_vo.cli import main

    assert main(["benchmark", "--suite", "subset", "--ablate", "no_such_rule", "--no-record"]) == 2
    err = capsys.readouterr().err
    assert "no_such_rule: no such rule" in err and len(err.strip().splitlines()) == 1
