"""A distribution run against an earlier one (``epi-vo benchmark --suite distribution --baseline RECORD.json``):
per family and pipeline, the figures that judge a change to the pipeline, before -> after, and the real clips.

The rule it serves: a change is judged on every family, median and p90, with and without it. The baseline is
the JSON of an earlier dated record (``docs/benchmarks/*-distribution.json``) or of a run with ``--set``
(an ablation: the same pipeline with one rule switched off). Only families and seeds both runs have are compared.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from epi_vo.core.errors import EpiVoError
from epi_vo.tools import distribution_table as dt

# The figures compared (metric key, which statistic): a family's verdict is read from these.
COMPARED: tuple[tuple[str, str], ...] = (
    ("ate_percent", "median"), ("ate_percent", "p90"), ("tracked_percent", "median"),
    ("moved_depth_percent", "worst"), ("keyframes_per_frame", "median"), ("metric_after_s", "median"),
    ("step_scale", "p90"), ("ate_se3_percent", "p90"), ("nees_pos", "median"), ("nees_rot", "median"),
    ("ms_per_frame", "median"),
)
REAL_COMPARED = ("tracked_percent", "ate_percent", "step_scale", "ate_se3_percent", "nees_pos", "nees_rot")


def load_baseline(path: str | Path) -> dict[str, Any]:
    """The JSON of a distribution record; EpiVoError naming the file when it is none."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeError, ValueError) as exc:
        raise EpiVoError(f"benchmark: --baseline {p}: cannot read it as a benchmark record ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("sequences"), list):
        raise EpiVoError(f"benchmark: --baseline {p}: not the JSON of a distribution record (no 'sequences')")
    return data


def _sequence_values(data: dict[str, Any]) -> dict[tuple[str, int], dict[str, dict[str, Any]]]:
    """(family, seed) -> pipeline -> row of a record's JSON."""
    out: dict[tuple[str, int], dict[str, dict[str, Any]]] = {}
    for s in data["sequences"]:
        out[(str(s["family"]), int(s["seed"]))] = {str(r["pipeline"]): r for r in s["rows"]}
    return out


def _value(row: dict[str, Any] | None, metric: dt.Metric) -> float:
    """A row's figure as the table reads it (None in JSON is a figure that could not be had)."""
    if row is None:
        return math.nan
    raw = row.get(metric.key)
    v = math.nan if raw is None else float(raw)
    if metric.kind == "scale":
        return 100.0 * (v - 1.0) if math.isfinite(v) else math.nan
    if metric.kind == "high" and math.isnan(v) and metric.failed == "fail":
        return math.inf
    return v


def _stat(rows: Sequence[dict[str, Any] | None], metric: dt.Metric) -> dt.Stat | None:
    return dt.summarise([_value(r, metric) for r in rows], metric.kind)


def _pick(stat: dt.Stat | None, which: str) -> float:
    return math.nan if stat is None else float(getattr(stat, which))


def compare(baseline: dict[str, Any], current: dict[str, Any]) -> str:
    """Markdown: per family (on the seeds both runs have) and epi_vo pipeline, before -> after."""
    before, after = _sequence_values(baseline), _sequence_values(current)
    common = [k for k in after if k in before]
    if not common:
        return "No family and seed in common with the baseline."
    static = {(str(s["family"]), int(s["seed"])): bool(s["static"]) for s in current["sequences"]}
    header = ["family", "pipeline", "seeds"] + [f"{dt.METRIC_BY_KEY[k].label} {w}" for k, w in COMPARED]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    families = list(dict.fromkeys(f for f, _ in common))
    for family in families:
        keys = [k for k in common if k[0] == family]
        is_static = static[keys[0]]
        pipelines = [p for p in dict.fromkeys(p for k in keys for p in after[k]) if p.startswith(dt.EPI_VO)]
        for pipeline in pipelines:
            cells = []
            for key, which in COMPARED:
                metric = dt.METRIC_BY_KEY[key]
                if not metric.applies(is_static, pipeline):
                    cells.append("")
                    continue
                b = _pick(_stat([before[k].get(pipeline) for k in keys], metric), which)
                a = _pick(_stat([after[k].get(pipeline) for k in keys], metric), which)
                cells.append(_arrow(b, a, metric))
            lines.append("| " + " | ".join([family, pipeline, str(len(keys)), *cells]) + " |")
    out = ["Before -> after on the seeds both runs have (median, p90, or the worst seed, as the column says; "
           "`fail`: no figure).", "", "\n".join(lines)]
    real = _compare_real(baseline.get("real") or [], current.get("real") or [])
    if real:
        out += ["", "Real clips, before -> after:", "", real]
    return "\n".join(out)


def _arrow(b: float, a: float, metric: dt.Metric) -> str:
    if math.isnan(b) and math.isnan(a):
        return ""
    return f"{dt.fmt(b, metric.digits, metric.failed)} -> {dt.fmt(a, metric.digits, metric.failed)}"


def _compare_real(before: Sequence[dict[str, Any]], after: Sequence[dict[str, Any]]) -> str:
    old = {(str(r["bag"]), str(r["pipeline"])): r for r in before}
    header = ["clip", "pipeline"] + [dt.METRIC_BY_KEY[k].label for k in REAL_COMPARED]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in after:
        key = (str(r["bag"]), str(r["pipeline"]))
        if key not in old or not key[1].startswith(dt.EPI_VO):
            continue
        cells = [_arrow(_value(old[key], dt.METRIC_BY_KEY[k]), _value(r, dt.METRIC_BY_KEY[k]), dt.METRIC_BY_KEY[k])
                 for k in REAL_COMPARED]
        lines.append("| " + " | ".join([key[0], key[1], *cells]) + " |")
    return "\n".join(lines) if len(lines) > 2 else ""
