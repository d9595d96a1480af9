"""Per-family statistics of the scenario distribution's benchmark rows, and their markdown tables.

Every figure of a family is given as ``median / p90 / worst`` over its seeds, where p90 and worst are
taken on the side that is bad for that figure (``Metric.kind``):

- ``high``: larger is worse (ATE, errors, time, frames moved); p90 is the 90th percentile, worst the largest.
  A figure that could not be computed on a family where it applies (no pose, a degenerate alignment) is a
  failure and counts as infinitely bad ("fail");
- ``low``: smaller is worse (frames with a pose); p90 is the 10th percentile, worst the smallest;
- ``scale``: the step scale's error ``100 (s - 1)`` %; median signed, p90 of its magnitude, worst the
  signed value farthest from 0;
- ``nees``: a mean NEES (consistent: 3); median, p90 the 90th percentile (over-confidence), worst the
  value farthest from 3 by ratio; a run with nothing to judge is left out (the count says how many were
  judged).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from epi_vo.tools.benchmark import BenchRow

EPI_VO = "epi_vo"
REFERENCE = "reference"


@dataclass(frozen=True)
class SequenceResult:
    """The benchmark rows of one rendered sequence (epi_vo, its metric variants, the reference)."""

    family: str
    seed: int
    harshness: float
    size: tuple[int, int]
    static: bool
    rows: tuple[BenchRow, ...]


@dataclass(frozen=True)
class Metric:
    key: str  # BenchRow attribute
    label: str
    kind: str  # high, low, scale, nees
    applies: Callable[[bool, str], bool]  # (static family, pipeline label)
    digits: int = 2
    failed: str = "fail"  # how an infinitely bad value reads


def _moving(static: bool, pipeline: str) -> bool:
    return not static


def _any(static: bool, pipeline: str) -> bool:
    return True


def _static(static: bool, pipeline: str) -> bool:
    return static


def _epi(static: bool, pipeline: str) -> bool:
    return pipeline.startswith(EPI_VO)


def _epi_static(static: bool, pipeline: str) -> bool:
    return static and pipeline.startswith(EPI_VO)


def _metric(static: bool, pipeline: str) -> bool:
    return pipeline.startswith(EPI_VO + "[")


METRICS: tuple[Metric, ...] = (
    Metric("ate_percent", "ATE % of path (Sim3)", "high", _moving),
    Metric("rpe_rot_deg", "RPE rot °/frame", "high", _any, 3),
    Metric("trans_dir_deg", "t-dir °", "high", _moving, 1),
    Metric("tracked_percent", "pose %", "low", _any, 1),
    Metric("keyframes_per_frame", "KF/frame", "high", _epi, 2),
    Metric("ms_per_frame", "ms/frame", "high", _any, 1),
    Metric("moving_frames", "frames moved", "high", _static, 0),
    Metric("moved_depth_percent", "moved, % of depth", "high", _epi_static, 2),
    Metric("metric_after_s", "metres after s", "high", _metric, 2, "never"),
    Metric("step_scale", "step scale − 1 %", "scale", _metric, 1),
    Metric("ate_se3_percent", "SE3 ATE %", "high", _metric, 2),
    Metric("nees_pos", "NEES pos", "nees", _epi, 2),
    Metric("nees_rot", "NEES rot", "nees", _epi, 2),
    Metric("nees_twist_lin", "NEES v", "nees", _epi, 2),
    Metric("nees_twist_ang", "NEES ω", "nees", _epi, 2),
)
METRIC_BY_KEY = {m.key: m for m in METRICS}


@dataclass(frozen=True)
class Stat:
    """median / p90 / worst of one figure over a family's seeds; ``judged`` of ``seeds`` had a value."""

    median: float
    p90: float
    worst: float
    judged: int
    seeds: int

    def to_json(self) -> dict[str, Any]:
        return {"median": self.median, "p90": self.p90, "worst": self.worst, "judged": self.judged,
                "seeds": self.seeds}


def _percentile(sorted_values: Sequence[float], q: float) -> float:
    """Linear-interpolation percentile of ascending values that may end in inf (inf if it touches one)."""
    n = len(sorted_values)
    pos = q / 100.0 * (n - 1)
    lo, hi = math.floor(pos), math.ceil(pos)
    a, b = sorted_values[lo], sorted_values[hi]
    if math.isinf(a) or math.isinf(b):
        return a if lo == hi or pos == lo else (b if math.isinf(b) else a)
    return a + (b - a) * (pos - lo)


def value_of(row: BenchRow, metric: Metric) -> float:
    v = float(row.keyframes_per_frame if metric.key == "keyframes_per_frame" else getattr(row, metric.key))
    if metric.kind == "scale":
        return 100.0 * (v - 1.0) if math.isfinite(v) else math.nan
    if metric.kind == "high" and math.isnan(v) and metric.failed == "fail":
        return math.inf  # where the figure applies, not having it is the failure
    return v


def summarise(values: Sequence[float], kind: str) -> Stat | None:
    """The statistic of one figure over seeds (NaN: not judged); None when no seed was judged."""
    judged = [v for v in values if not math.isnan(v)]
    if not judged:
        return None
    n = len(values)
    if kind == "high":
        s = sorted(judged)
        return Stat(_percentile(s, 50), _percentile(s, 90), s[-1], len(judged), n)
    if kind == "low":
        s = sorted(judged)
        return Stat(_percentile(s, 50), _percentile(s, 10), s[0], len(judged), n)
    if kind == "scale":
        mags = sorted(abs(v) for v in judged)
        worst = max(judged, key=abs)
        return Stat(float(np.median(judged)), _percentile(mags, 90), worst, len(judged), n)
    # nees: a ratio to 3 either way is equally bad
    s = sorted(judged)
    worst = max(judged, key=lambda v: abs(math.log(max(v, 1e-12) / 3.0)))
    return Stat(_percentile(s, 50), _percentile(s, 90), worst, len(judged), n)


def family_stats(results: Sequence[SequenceResult]) -> dict[str, dict[str, dict[str, Stat]]]:
    """family -> pipeline -> metric key -> Stat, for the metrics that apply."""
    out: dict[str, dict[str, dict[str, Stat]]] = {}
    families = list(dict.fromkeys(r.family for r in results))
    for family in families:
        seqs = [r for r in results if r.family == family]
        pipelines = list(dict.fromkeys(row.pipeline for r in seqs for row in r.rows))
        out[family] = {}
        for pipeline in pipelines:
            rows = [row for r in seqs for row in r.rows if row.pipeline == pipeline]
            stats = {}
            for m in METRICS:
                if m.applies(seqs[0].static, pipeline):
                    stat = summarise([value_of(row, m) for row in rows], m.kind)
                    if stat is not None:
                        stats[m.key] = stat
            out[family][pipeline] = stats
    return out


# --- markdown ---------------------------------------------------------------------------------------------


def fmt(v: float, digits: int, failed: str = "fail") -> str:
    if math.isnan(v):
        return "–"
    if math.isinf(v):
        return failed
    if v != 0 and abs(v) < 10 ** -digits:
        return f"{v:.1e}"
    return f"{v:.{digits}f}"


def cell(stat: Stat | None, metric: Metric) -> str:
    if stat is None:
        return "–"
    text = " / ".join(fmt(v, metric.digits, metric.failed) for v in (stat.median, stat.p90, stat.worst))
    return text + (f" ({stat.judged}/{stat.seeds})" if stat.judged < stat.seeds else "")


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def family_tables(stats: dict[str, dict[str, dict[str, Stat]]], results: Sequence[SequenceResult]) -> str:
    """The per-family tables: tracking and accuracy; static families; metric scale; covariance."""
    meta = {r.family: r for r in results}
    parts = []
    keys = ("ate_percent", "rpe_rot_deg", "trans_dir_deg", "tracked_percent", "keyframes_per_frame", "ms_per_frame")
    rows = []
    for family, by_pipe in stats.items():
        size = "x".join(str(v) for v in meta[family].size)
        for pipeline in (EPI_VO, REFERENCE):
            if pipeline in by_pipe:
                rows.append([family, size, pipeline, *(cell(by_pipe[pipeline].get(k), METRIC_BY_KEY[k]) for k in keys)])
    parts.append("### Tracking and accuracy (median / p90 / worst over the seeds)\n\n"
                 + _table(["family", "size", "pipeline", *(METRIC_BY_KEY[k].label for k in keys)], rows))
    rows = []
    for family, by_pipe in stats.items():
        if meta[family].static:
            for pipeline in (EPI_VO, REFERENCE):
                if pipeline in by_pipe:
                    rows.append([family, pipeline, cell(by_pipe[pipeline].get("moving_frames"),
                                                        METRIC_BY_KEY["moving_frames"]),
                                 cell(by_pipe[pipeline].get("moved_depth_percent"),
                                      METRIC_BY_KEY["moved_depth_percent"])])
    if rows:
        parts.append("### Static camera: invented motion\n\n"
                     + _table(["family", "pipeline", "frames moved", "largest displacement, % of the map's depth"],
                              rows))
    keys = ("metric_after_s", "step_scale", "ate_se3_percent", "ate_percent", "tracked_percent")
    rows = [[family, pipeline, *(cell(st.get(k), METRIC_BY_KEY[k]) for k in keys)]
            for family, by_pipe in stats.items() for pipeline, st in by_pipe.items() if pipeline.startswith("epi_vo[")]
    if rows:
        parts.append("### Metric scale\n\n" + _table(["family", "source", "metres after s", "step scale − 1 %",
                                                       "SE3 ATE %", "ATE % (Sim3)", "pose %"], rows))
    keys = ("nees_pos", "nees_rot", "nees_twist_lin", "nees_twist_ang")
    rows = [[family, pipeline, *(cell(st.get(k), METRIC_BY_KEY[k]) for k in keys)]
            for family, by_pipe in stats.items() for pipeline, st in by_pipe.items() if pipeline.startswith(EPI_VO)]
    parts.append("### Covariance: mean NEES of the tracking frames (3 dof, consistent: 3)\n\n"
                 + _table(["family", "pipeline", "position", "rotation", "twist v", "twist ω"], rows))
    return "\n\n".join(parts)


def real_table(rows: Sequence[BenchRow]) -> str:
    """The real clips, one row per pipeline run."""
    def f(v: float, digits: int = 2, failed: str = "fail") -> str:
        return fmt(v, digits, failed)

    body = [[r.bag, r.pipeline, str(r.frames), f(r.tracked_percent, 1), f(r.ate_percent), f(r.rpe_rot_deg, 3),
             f(r.trans_dir_deg, 1), f(r.keyframes_per_frame) if r.pipeline.startswith(EPI_VO) else "–",
             f(r.metric_after_s, 2, "never"), f(r.step_scale, 3), f(r.ate_se3_percent), f(r.nees_pos), f(r.nees_rot),
             f(r.nees_twist_lin), f(r.nees_twist_ang), f(r.ms_per_frame, 1)] for r in rows]
    return _table(["clip", "pipeline", "frames", "pose %", "ATE %", "RPE rot °/f", "t-dir °", "KF/frame",
                   "metres after s", "step scale", "SE3 ATE %", "NEES pos", "NEES rot", "NEES v", "NEES ω",
                   "ms/frame"], body)


def sequence_table(results: Sequence[SequenceResult]) -> str:
    """Every sequence and pipeline: the figures behind the statistics."""
    body = []
    for r in results:
        for row in r.rows:
            body.append([r.family, str(r.seed), f"{r.harshness:.2f}", row.pipeline, str(row.frames),
                         fmt(row.tracked_percent, 1), fmt(value_of(row, METRIC_BY_KEY["ate_percent"]), 2)
                         if not r.static else "–", fmt(row.rpe_rot_deg, 3), fmt(row.trans_dir_deg, 1),
                         fmt(row.keyframes_per_frame, 2) if row.pipeline.startswith(EPI_VO) else "–",
                         str(row.moving_frames), fmt(row.moved_depth_percent, 2),
                         fmt(row.metric_after_s, 2, "never"), fmt(row.step_scale, 3), fmt(row.ate_se3_percent, 2),
                         fmt(row.nees_pos, 2), fmt(row.nees_rot, 2), fmt(row.ms_per_frame, 1)])
    return _table(["family", "seed", "harsh", "pipeline", "frames", "pose %", "ATE %", "RPE °/f", "t-dir °",
                   "KF/f", "moved", "moved % depth", "metres after s", "scale", "SE3 ATE %", "NEES pos", "NEES rot",
                   "ms/f"], body)


# --- the generalization issue's targets ----------------------------------------------------------------------

PLANAR_FAMILIES = ("planar_wall", "floor_wall")
METRIC_FAMILIES = ("road", "floor_robot")
HANDHELD_FAMILIES = ("handheld", "handheld_hd")  # the handheld target: at 320 px wide and a phone's 1280x720


@dataclass(frozen=True)
class Target:
    what: str
    measured: str
    met: bool | None  # None: not measured in this run


def _get(stats: dict, family: str, pipeline: str, key: str) -> Stat | None:
    return stats.get(family, {}).get(pipeline, {}).get(key)


def targets(stats: dict[str, dict[str, dict[str, Stat]]], results: Sequence[SequenceResult],
            real: Sequence[BenchRow]) -> list[Target]:
    """The targets of the generalization issue, each with what this run measured and whether it is met."""
    out: list[Target] = []
    static = {r.family for r in results if r.static}
    for family in stats:
        if family in static:
            continue
        ours, ref = _get(stats, family, EPI_VO, "ate_percent"), _get(stats, family, REFERENCE, "ate_percent")
        if ours and ref:
            out.append(Target(f"{family}: p90 ATE <= half the reference's median",
                              f"{fmt(ours.p90, 2)} vs {fmt(0.5 * ref.median, 2)}", ours.p90 <= 0.5 * ref.median))
    for family in PLANAR_FAMILIES:
        if (st := _get(stats, family, EPI_VO, "ate_percent")) is not None:
            out.append(Target(f"{family}: median ATE <= 1 %, p90 <= 2 %", f"{fmt(st.median, 2)}, {fmt(st.p90, 2)}",
                              st.median <= 1.0 and st.p90 <= 2.0))
    for family in sorted(static):
        if (st := _get(stats, family, EPI_VO, "moved_depth_percent")) is not None:
            out.append(Target(f"{family}: moves <= 1 % of the scene depth on every seed", f"worst {fmt(st.worst, 2)} %",
                              st.worst <= 1.0))
    for family in METRIC_FAMILIES:
        pipe = "epi_vo[ground_plane]"
        t, sc, se3 = (_get(stats, family, pipe, k) for k in ("metric_after_s", "step_scale", "ate_se3_percent"))
        if t is not None:
            out.append(Target(f"{family} ground_plane: metres within 1 s on the median seed",
                              f"{fmt(t.median, 2, 'never')} s", t.median <= 1.0))
        if sc is not None and se3 is not None:
            out.append(Target(f"{family} ground_plane: p90 step scale within 3 %, SE(3) ATE <= 3 %",
                              f"{fmt(sc.p90, 1)} %, {fmt(se3.p90, 2)} %", sc.p90 <= 3.0 and se3.p90 <= 3.0))
    for family in HANDHELD_FAMILIES:
        pose, kf = (_get(stats, family, EPI_VO, k) for k in ("tracked_percent", "keyframes_per_frame"))
        if pose is not None and kf is not None:
            measured = f"{fmt(pose.median, 1)} % ({fmt(pose.worst, 1)}), {fmt(kf.median, 2)} ({fmt(kf.worst, 2)})"
            out.append(Target(f"{family}: a pose on >= 97 % of frames, <= 1 keyframe in 4 (median seed; worst in "
                              "brackets)", measured, pose.median >= 97.0 and kf.median <= 0.25))
    for family, by_pipe in stats.items():
        st = by_pipe.get(EPI_VO, {})
        if "nees_pos" in st and "nees_rot" in st:
            p, r = st["nees_pos"], st["nees_rot"]
            out.append(Target(f"{family}: median NEES pos and rot in 1-6, p90 <= 12",
                              f"pos {fmt(p.median, 2)} / {fmt(p.p90, 2)}, rot {fmt(r.median, 2)} / {fmt(r.p90, 2)}",
                              1 <= p.median <= 6 and 1 <= r.median <= 6 and p.p90 <= 12 and r.p90 <= 12))
    vga = [row.ms_per_frame for r in results if r.size == (640, 480) for row in r.rows if row.pipeline == EPI_VO]
    if vga:
        median = float(np.median(vga))
        out.append(Target("median <= 8 ms/frame at 640x480", f"{fmt(median, 1)} ms", median <= 8.0))
    for row in real:
        if row.bag.startswith("kitti") and row.pipeline.startswith(EPI_VO):
            out.append(Target(f"KITTI clip {row.pipeline}: no worse than the baseline record",
                              f"ATE {fmt(row.ate_percent, 2)} %, t-dir {fmt(row.trans_dir_deg, 2)} deg, step scale "
                              f"{fmt(row.step_scale, 3)}, metres after {fmt(row.metric_after_s, 2, 'never')} s", None))
        if row.bag.startswith("tello") and row.pipeline == EPI_VO:
            out.append(Target("Tello semicircle: ATE <= 0.6 %, a pose on >= 99 % of frames",
                              f"{fmt(row.ate_percent, 2)} %, {fmt(row.tracked_percent, 1)} %",
                              row.ate_percent <= 0.6 and row.tracked_percent >= 99.0))
            out.append(Target("Tello semicircle: position NEES in 1-6", fmt(row.nees_pos, 2), 1 <= row.nees_pos <= 6))
    return out


def targets_list(items: Sequence[Target]) -> str:
    mark = {True: "met", False: "**not met**", None: "compare with the baseline"}
    return "\n".join(f"- {t.what}: {t.measured} ({mark[t.met]})" for t in items)
