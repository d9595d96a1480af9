"""The run-to-run spread of the distribution benchmark: how far each family's ATE moves when every
sequence is replayed again under a calibration nobody could tell apart (:mod:`epi_vo.tools.perturb`).

A family's median and p90 over 8 seeds move by chance when a seed's run flips between two paths (a
keyframe taken or not, a model chosen near its gate): a change judged on one run can be credited or blamed
for such a flip. With ``--perturb`` the benchmark replays epi_vo (the default configuration) on every
sequence once per perturbation; this module summarises the runs per family (each run's median / p90, the
pooled median / p90 over all seeds of all runs, the largest spread of one seed, the seeds that flip) and
compares the pooled figures with a baseline record that has them.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from typing import Any

from epi_vo.tools import distribution_table as dt

# A seed "flips" when its worst run's ATE is at least this many times its best run's: one path taken half
# again as badly as its twin under a calibration nobody could tell apart (smaller ratios are the tracks'
# ordinary noise on a short path; ATE under FLIP_FLOOR_PERCENT is too small to call either run bad).
FLIP_RATIO = 1.5
FLIP_FLOOR_PERCENT = 0.5

_ATE = dt.METRIC_BY_KEY["ate_percent"]


def _ate(result: dt.SequenceResult) -> float:
    row = next((r for r in result.rows if r.pipeline == dt.EPI_VO), None)
    return math.nan if row is None else dt.value_of(row, _ATE)


def spread(runs: Mapping[float, Sequence[dt.SequenceResult]]) -> dict[str, dict[str, Any]]:
    """Per moving family: {"runs": [{"focal_rel", "median", "p90"}], "pooled": {"median", "p90", "n"},
    "largest_spread", "flipping": [{"seed", "ate": [per run]}]}. ``runs`` maps each perturbation (0.0: the
    recorded calibration) to its results; the epi_vo row's ATE % of path is judged (a failed run is inf: it
    counts in the pooled p90 and makes its seed flip; the largest spread is that of the finite runs)."""
    rels = sorted(runs, key=lambda r: (r != 0.0, r))
    values: dict[str, dict[int, list[float]]] = {}
    for rel in rels:
        for res in runs[rel]:
            if res.static:
                continue
            values.setdefault(res.family, {}).setdefault(res.seed, []).append(_ate(res))
    out: dict[str, dict[str, Any]] = {}
    for family, by_seed in values.items():
        per_run: list[dict[str, Any]] = []
        for i, rel in enumerate(rels):
            stat = dt.summarise([v[i] for v in by_seed.values() if len(v) > i], "high")
            per_run.append({"focal_rel": rel, "median": stat.median if stat else math.nan,
                            "p90": stat.p90 if stat else math.nan})
        pooled = dt.summarise([x for v in by_seed.values() for x in v], "high")
        largest, flipping = 0.0, []
        for seed, vals in sorted(by_seed.items()):
            judged = [x for x in vals if not math.isnan(x)]
            if len(judged) < 2:
                continue
            lo, hi = min(judged), max(judged)
            finite = [x for x in judged if math.isfinite(x)]
            if len(finite) >= 2:  # a failed run is a flip (below), not a spread of some size
                largest = max(largest, max(finite) - min(finite))
            if hi >= FLIP_FLOOR_PERCENT and hi >= FLIP_RATIO * max(lo, 1e-12):
                flipping.append({"seed": seed, "ate": vals})
        out[family] = {"runs": per_run,
                       "pooled": {"median": pooled.median if pooled else math.nan,
                                  "p90": pooled.p90 if pooled else math.nan,
                                  "n": pooled.judged if pooled else 0},
                       "largest_spread": largest, "flipping": flipping}
    return out


def _f(v: float | None) -> str:
    # a record's JSON holds a failed (infinite) figure as null
    return dt.fmt(math.inf if v is None else v, 2)


def spread_table(data: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown: per family each run's ATE median / p90, the pooled ones, the largest spread of one seed and
    the seeds that flip (their ATE % per run)."""
    if not data:
        return "No moving family was run."
    rels = _rels(data)
    head = ["family"] + [f"focal {'recorded' if rel == 0 else f'{rel:+.2%}'}" for rel in rels]
    head += ["pooled", "largest seed spread", f"seeds flipping (worst run >= {FLIP_RATIO} x best)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for family, d in data.items():
        cells = [f"{_f(r['median'])} / {_f(r['p90'])}" for r in d["runs"]]
        flips = ", ".join(f"s{f['seed']} " + "/".join(_f(v) for v in f["ate"]) for f in d["flipping"]) or "–"
        lines.append("| " + " | ".join([family, *cells, f"{_f(d['pooled']['median'])} / {_f(d['pooled']['p90'])}",
                                        _f(d["largest_spread"]), flips]) + " |")
    return ("ATE % of path (Sim3), median / p90 over the seeds per run; pooled: over every seed of every run. "
            "camera_info's focal length scaled as the column says (a calibration nobody could tell apart).\n\n"
            + "\n".join(lines))


def _rels(data: Mapping[str, Any]) -> list[float]:
    return [float(r["focal_rel"]) for r in next(iter(data.values()))["runs"]]


def spread_compare(before: Mapping[str, Any] | None, after: Mapping[str, Any]) -> str:
    """Markdown: the pooled median / p90 per family before -> after, when both records have a spread with the
    same perturbations; else a line saying why there is no comparison."""
    b = (before or {}).get("spread") or {}
    a = after.get("spread") or {}
    if not b or not a:
        return "The baseline has no run-to-run spread to compare with." if a else ""
    if _rels(b) != _rels(a):
        return f"The baseline's perturbations {_rels(b)} are not this run's {_rels(a)}: no pooled comparison."
    lines = ["| family | pooled median | pooled p90 | seeds flipping |", "|---|---|---|---|"]
    for family, d in a.items():
        if family not in b:
            continue
        p, q = b[family]["pooled"], d["pooled"]
        lines.append(f"| {family} | {_f(p['median'])} -> {_f(q['median'])} | {_f(p['p90'])} -> {_f(q['p90'])} | "
                     f"{len(b[family]['flipping'])} -> {len(d['flipping'])} |")
    return "Pooled over the runs, before -> after:\n\n" + "\n".join(lines)


def _spread(v: float | None) -> str:
    # no spread (fewer than two runs with a figure): not a failure
    return "–" if v is None or math.isnan(v) else dt.fmt(v, 2)


def _real_key(row: Any) -> str:
    return f"{row.bag} {row.pipeline}"


def real_spread(runs: Mapping[float, Sequence[Any]]) -> dict[str, dict[str, Any]]:
    """Per real clip and epi_vo pipeline ("<clip> <pipeline>"): {"runs": [{"focal_rel", "ate_percent",
    "ate_se3_percent"}], "median": the median ATE % over the runs, "spread": the largest minus the smallest
    finite one}. ``runs`` maps each perturbation (0.0: as recorded) to that run's rows (``BenchRow``); the
    reference pipeline, run once, is left out."""
    rels = sorted(runs, key=lambda r: (r != 0.0, r))
    out: dict[str, dict[str, Any]] = {}
    for rel in rels:
        for row in runs[rel]:
            if not row.pipeline.startswith(dt.EPI_VO):
                continue
            entry = out.setdefault(_real_key(row), {"runs": []})
            entry["runs"].append({"focal_rel": rel, "ate_percent": float(row.ate_percent),
                                  "ate_se3_percent": float(row.ate_se3_percent)})
    for entry in out.values():
        ates = [r["ate_percent"] for r in entry["runs"]]
        entry["median"] = statistics.median(math.inf if math.isnan(a) else a for a in ates)  # a failed run: the worst
        finite = [a for a in ates if math.isfinite(a)]
        entry["spread"] = max(finite) - min(finite) if len(finite) >= 2 else math.nan
    return out


def real_spread_table(data: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown: each real clip's ATE % (and SE3 ATE % where it is in metres) per run, their median and spread."""
    if not data:
        return ""
    rels = [float(r["focal_rel"]) for r in next(iter(data.values()))["runs"]]
    head = ["clip, pipeline"] + [f"focal {'recorded' if rel == 0 else f'{rel:+.2%}'}" for rel in rels]
    head += ["median", "spread"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for key, d in data.items():
        cells = []
        for r in d["runs"]:
            se3 = r.get("ate_se3_percent")
            ate = r["ate_percent"]
            cells.append(_f(None if ate is None or math.isnan(ate) else ate)
                         + ("" if se3 is None or math.isnan(se3) else f" (SE3 {_f(se3)})"))
        lines.append("| " + " | ".join([key, *cells, _f(d["median"]), _spread(d["spread"])]) + " |")
    return ("The real clips under the same twins: ATE % of path (Sim3) per run (SE3 ATE % where the output "
            "is in metres), their median and spread.\n\n" + "\n".join(lines))


def real_spread_compare(before: Mapping[str, Any] | None, after: Mapping[str, Any]) -> str:
    """Markdown: each real clip's median ATE % over the runs before -> after, when both records have them
    with the same perturbations."""
    b = (before or {}).get("real_spread") or {}
    a = after.get("real_spread") or {}
    if not a:
        return ""
    if not b:
        return "The baseline has no real clips' twins to compare with."
    rels_b = [float(r["focal_rel"]) for r in next(iter(b.values()))["runs"]]
    rels_a = [float(r["focal_rel"]) for r in next(iter(a.values()))["runs"]]
    if rels_b != rels_a:
        return f"The baseline's real-clip perturbations {rels_b} are not this run's {rels_a}: no comparison."
    lines = ["| clip, pipeline | median ATE % over the runs | spread |", "|---|---|---|"]
    for key, d in a.items():
        if key in b:
            lines.append(f"| {key} | {_f(b[key]['median'])} -> {_f(d['median'])} | {_spread(b[key]['spread'])} -> "
                         f"{_spread(d['spread'])} |")
    return "Real clips over the runs, before -> after:\n\n" + "\n".join(lines)
