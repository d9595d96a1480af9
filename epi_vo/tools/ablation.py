"""``epi-vo benchmark --suite distribution --ablate``: every gate of the pipeline judged with and without it.

A rule earns its place on the distribution and the real clips, not on one bag. For each rule of ``RULES`` (or
those named) the distribution is run once with the rule switched off (the parameter set to the value that
lets everything through) and compared, family by family, with the run of the defaults. A rule *pays* when
some family or real clip is clearly worse without it; it *costs* when only better; *no effect* when nothing
moves: such a rule is a candidate for removal. The verdict uses ``clearly``: a figure moved by more than
``REL_CHANGE`` of itself and more than its absolute floor, so that the renders' and OpenCV's small
variations do not decide.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from epi_vo.core.errors import EpiVoError
from epi_vo.tools import distribution_table as dt
from epi_vo.tools.bench_record import RecordHeader, write_record
from epi_vo.tools.distribution import run_distribution
from epi_vo.tools.distribution_compare import compare


@dataclass(frozen=True)
class Rule:
    name: str  # the VoConfig field
    off: object  # the value that lets everything through
    guards: str  # what the rule is for, in a few words


RULES: tuple[Rule, ...] = (
    Rule("init_min_parallax_deg", 0.01, "the first map waits for parallax"),
    Rule("static_min_spread", 0.0, "a still camera's still features cover the image"),
    Rule("e_map_max_rotation_diff_deg", 45.0, "E far from the map's pose: the map decides (a mover took E)"),
    Rule("plane_e_min_parallax_deg", 0.0, "with a plane, the pose from E only above this parallax"),
    Rule("min_positive_depth_ratio", 0.0, "cheirality: most inliers in front of both views"),
    Rule("min_triangulation_angle_deg", 0.0, "no depth from a small ray angle"),
    Rule("max_reprojection_error_px", 100.0, "triangulated points must reproject"),
    Rule("klt_max_fb_error_px", 50.0, "KLT tracks must track back"),
    Rule("kf_min_tracked_ratio", 0.0, "a keyframe when the keyframe's features are lost"),
    Rule("kf_min_inliers", 8, "a keyframe when inliers fall"),
    Rule("kf_max_interval_s", 3600.0, "a keyframe at least every interval"),
)

# A figure moved "clearly": by more than this fraction of itself and more than the floor of its kind.
REL_CHANGE = 0.10
FLOORS = {"ate_percent": 0.05, "ate_se3_percent": 0.05, "tracked_percent": 1.0, "moved_depth_percent": 0.2,
          "metric_after_s": 0.2, "step_scale": 1.0}
# (metric key, statistic) judged per family and epi_vo pipeline; (metric key) per real clip.
JUDGED: tuple[tuple[str, str], ...] = (("ate_percent", "median"), ("ate_percent", "p90"), ("tracked_percent", "median"),
                                       ("moved_depth_percent", "worst"), ("metric_after_s", "median"),
                                       ("step_scale", "p90"), ("ate_se3_percent", "p90"))
REAL_JUDGED = ("ate_percent", "tracked_percent", "step_scale", "ate_se3_percent")


def _stat(data: dict[str, Any], family: str, pipeline: str, key: str, which: str) -> float:
    s = data["families"].get(family, {}).get(pipeline, {}).get(key)
    if s is None:
        return math.nan
    v = s.get(which)
    return math.inf if v is None else float(v)  # a figure that could not be had is the worst


def _worse(before: float, after: float, key: str) -> int:
    """+1 clearly worse, -1 clearly better, 0 neither (NaN: not judged)."""
    if math.isnan(before) or math.isnan(after) or before == after:
        return 0
    low_is_bad = key == "tracked_percent"
    if math.isinf(before) or math.isinf(after):
        return (1 if math.isinf(after) else -1) * (-1 if low_is_bad else 1)
    delta = after - before
    if abs(delta) <= max(REL_CHANGE * abs(before), FLOORS.get(key, 0.0)):
        return 0
    return (-1 if delta > 0 else 1) if low_is_bad else (1 if delta > 0 else -1)


def judge(base: dict[str, Any], off: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(what is clearly worse without the rule, what is clearly better), as 'family pipeline figure' items."""
    worse, better = [], []
    for family, pipes in base["families"].items():
        for pipeline in pipes:
            if not pipeline.startswith(dt.EPI_VO):
                continue
            for key, which in JUDGED:
                b, a = _stat(base, family, pipeline, key, which), _stat(off, family, pipeline, key, which)
                v = _worse(b, a, key)
                item = f"{family} {pipeline} {key} {which} {dt.fmt(b, 2)} -> {dt.fmt(a, 2)}"
                (worse if v > 0 else better if v < 0 else []).append(item)
    old = {(r["bag"], r["pipeline"]): r for r in base.get("real", [])}
    for r in off.get("real", []):
        k = (r["bag"], r["pipeline"])
        if k not in old or not k[1].startswith(dt.EPI_VO):
            continue
        for key in REAL_JUDGED:
            b = math.inf if old[k].get(key) is None else float(old[k][key])
            a = math.inf if r.get(key) is None else float(r[key])
            if key == "step_scale":
                b, a = abs(b - 1.0) * 100.0, abs(a - 1.0) * 100.0
            v = _worse(b, a, key)
            item = f"{k[0]} {k[1]} {key} {dt.fmt(b, 2)} -> {dt.fmt(a, 2)}"
            (worse if v > 0 else better if v < 0 else []).append(item)
    return worse, better


def verdict(worse: Sequence[str], better: Sequence[str]) -> str:
    if worse and better:
        return "mixed"
    return "pays" if worse else "costs" if better else "no effect"


def _run(suite: str, params: str | None, overrides: Sequence[str], **kw: Any) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="epi_vo_ablation_") as tmp, contextlib.redirect_stdout(io.StringIO()):
        run_distribution(suite, params, record_dir=Path(tmp), reference=False, overrides=overrides, **kw)
        data: dict[str, Any] = json.loads(next(Path(tmp).glob("*.json")).read_text(encoding="utf-8"))
    return data


def run_ablation(suite: str, params: str | None, names: Sequence[str] | None, *, record_dir: Path | None,
                 **kw: Any) -> int:
    """Run the defaults and each rule switched off; print and record the verdicts."""
    header = RecordHeader.now()
    known = {r.name: r for r in RULES}
    unknown = [n for n in names or () if n not in known]
    if unknown:
        raise EpiVoError(f"benchmark: --ablate {', '.join(unknown)}: no such rule (rules: {', '.join(known)})")
    rules = [known[n] for n in names] if names else list(RULES)
    print("the defaults ...", file=sys.stderr, flush=True)
    base = _run(suite, params, (), **kw)
    rows, details, record = [], [], []
    for rule in rules:
        print(f"without {rule.name} ({rule.name}={rule.off}) ...", file=sys.stderr, flush=True)
        off = _run(suite, params, (f"{rule.name}={rule.off}",), **kw)
        worse, better = judge(base, off)
        v = verdict(worse, better)
        rows.append(f"| `{rule.name}` | {rule.guards} | {rule.off} | **{v}** | {len(worse)} | {len(better)} |")
        details.append(f"#### `{rule.name}` off ({rule.off}): {v}\n\n"
                       + ("Worse without it: " + "; ".join(worse) + "\n\n" if worse else "")
                       + ("Better without it: " + "; ".join(better) + "\n\n" if better else "")
                       + "<details>\n\n" + compare(base, off) + "\n\n</details>")
        record.append({"rule": rule.name, "off": rule.off, "verdict": v, "worse": worse, "better": better})
    table = ("| rule | what it guards | off value | verdict | figures worse without it | better without it |\n"
             "|---|---|---|---|---|---|\n" + "\n".join(rows))
    printed = table + "\n\n" + "\n\n".join(details)
    print(printed)
    if record_dir is not None:
        title = f"epi-vo benchmark --suite {suite} --ablate: every rule with and without it"
        md, js = write_record(record_dir, f"{suite}-ablation", header.markdown(title, {}) + "\n\n" + printed,
                              {"header": dataclasses.asdict(header), "rules": record}, header.date, header.commit)
        print(f"\nrecorded in {md} and {js}")
    return 0
