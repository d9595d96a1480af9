"""``epi-vo benchmark --suite distribution``: epi_vo and the seed reference on the scenario distribution and
the real clips, in one run, per family.

The sequences come from the scenario generator (``bags/scenarios.py`` of the source tree; rendered into
its cache when missing, see docs/distribution.md). Every sequence is replayed by epi_vo with the default
(or ``--params``) configuration, by epi_vo with each metric scale source its family carries
(``ground_plane`` at the drawn camera height on the road and floor-robot families, ``wheel_odometry`` on
the floor robot), and by the seed article's reference pipeline, on the same decoded frames. The real clips
of ``../shared/data`` (KITTI, also with ``ground_plane`` at 1.65 m; the Tello semicircle) are rows of
their own. Sequences run in ``jobs`` processes side by side (ms/frame is measured so: each process then has
one core; OpenCV runs single-threaded in them).

The table (:mod:`epi_vo.tools.distribution_table`) is printed and written as a dated record
(:mod:`epi_vo.tools.bench_record`) with every sequence's figures in its JSON.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import importlib
import logging
import multiprocessing
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import yaml

from epi_vo.core.config import VoConfig, from_dict
from epi_vo.core.errors import ConfigError, EpiVoError
from epi_vo.io import tum
from epi_vo.io.params import load_config
from epi_vo.tools import distribution_table as dt
from epi_vo.tools.bench_record import RecordHeader, jsonable, load_now, repo_root, write_record
from epi_vo.tools.benchmark import METRIC_VARIANTS, BenchRow, bench_epi_vo, bench_reference, row_dict
from epi_vo.tools.distribution_compare import compare, load_baseline
from epi_vo.tools.distribution_spread import (
    real_spread,
    real_spread_compare,
    real_spread_table,
    spread,
    spread_compare,
    spread_table,
)
from epi_vo.tools.gt_check import GroundTruthCheck, check_ground_truth

REAL_CLIPS = ("kitti06_0-50", "tello_semicircle_206f")
SUITES = ("bundled", "distribution", "subset")


def load_generator() -> ModuleType:
    """The scenario generator (``bags/scenarios.py``), a script of the source tree rather than a module of
    the package: its folder goes on ``sys.path`` (as its own tests do). EpiVoError when it is not there or
    its requirements (bags/requirements.txt) are missing."""
    bags = repo_root() / "bags"
    if not (bags / "scenarios.py").is_file():
        raise EpiVoError(f"benchmark: the scenario generator {bags / 'scenarios.py'} is not here: the distribution "
                         "runs from a source tree")
    if str(bags) not in sys.path:
        sys.path.insert(0, str(bags))
    try:
        return importlib.import_module("scenarios")
    except ImportError as exc:
        raise EpiVoError(f"benchmark: the scenario generator needs {exc.name} (pip install -r bags/requirements.txt)"
                         ) from None


def metric_variants(family_sources: Sequence[str], metric: dict[str, Any]) -> list[tuple[str, dict[str, object]]]:
    """(label, config changes) of each metric scale source a sequence carries what it needs for."""
    out: list[tuple[str, dict[str, object]]] = []
    for source in family_sources:
        if source == "ground_plane" and metric.get("camera_height_m"):
            out.append((source, {"scale_source": source, "camera_height_m": float(metric["camera_height_m"])}))
        elif source == "wheel_odometry" and metric.get("wheel_odometry_topic"):
            out.append((source, {"scale_source": source, "wheel_odometry_topic": str(metric["wheel_odometry_topic"])}))
    return out


@dataclass(frozen=True)
class SequenceTask:
    family: str
    seed: int
    path: Path
    info: dict[str, Any]
    sources: tuple[str, ...]
    cfg: VoConfig
    reference: bool = True
    focal_rel: float = 0.0  # non-zero: a twin run, epi_vo alone under camera_info's focal times 1 + focal_rel


def bench_sequence(task: SequenceTask) -> dt.SequenceResult:
    """Every pipeline on one rendered sequence (a twin run: epi_vo alone, under the perturbed calibration)."""
    bag, gt = task.path / "bag", task.path / "groundtruth_tum.txt"
    name = f"{task.family}-s{task.seed}"
    size = tuple(int(v) for v in task.info["size"])
    harsh, static = float(task.info["faults"]["harshness"]), bool(task.info["static_camera"])
    if task.focal_rel:
        twin = bench_epi_vo(name, bag, gt, task.cfg, focal_rel=task.focal_rel)
        return dt.SequenceResult(task.family, task.seed, harsh, (size[0], size[1]), static, (twin,))
    rows = [bench_epi_vo(name, bag, gt, task.cfg)]
    for label, values in metric_variants(task.sources, task.info.get("metric", {})):
        rows.append(bench_epi_vo(name, bag, gt, dataclasses.replace(task.cfg, **values), f"epi_vo[{label}]"))
    if task.reference:
        rows.append(bench_reference(name, bag, gt))
    return dt.SequenceResult(task.family, task.seed, harsh, (size[0], size[1]), static, tuple(rows))


@dataclass(frozen=True)
class RealTask:
    name: str
    bag: Path
    gt: Path
    cfg: VoConfig
    reference: bool = True
    focal_rel: float = 0.0  # a twin run: camera_info's focal length scaled by 1 + focal_rel


def bench_real(task: RealTask) -> list[BenchRow]:
    """A real clip, as the bundled benchmark runs it: its ground truth checked against its images first."""
    try:
        check: GroundTruthCheck | None = check_ground_truth(task.bag, tum.read_tum(task.gt))
    except EpiVoError:
        check = None
    rows = [bench_epi_vo(task.name, task.bag, task.gt, task.cfg, checked=check, focal_rel=task.focal_rel)]
    for label, values in METRIC_VARIANTS.get(task.name, ()):
        rows.append(bench_epi_vo(task.name, task.bag, task.gt, dataclasses.replace(task.cfg, **values),
                                 f"epi_vo[{label}]", checked=check, focal_rel=task.focal_rel))
    if task.reference:
        rows.append(bench_reference(task.name, task.bag, task.gt))
    return rows


def real_tasks(clips: Sequence[tuple[str, Path, Path]], cfg: VoConfig, reference: bool,
               perturb: Sequence[float] = ()) -> list[RealTask]:
    """Every clip as recorded (with the reference pipeline when ``reference``), then every clip again per
    perturbation (epi_vo alone), in that order: ``run_distribution`` reads the results back by it."""
    tasks = [RealTask(name, bag, gt, cfg, reference) for name, bag, gt in clips]
    for rel in perturb:
        tasks += [RealTask(name, bag, gt, cfg, False, rel) for name, bag, gt in clips]
    return tasks


def _run_task(task: SequenceTask | RealTask) -> dt.SequenceResult | list[BenchRow]:
    return bench_sequence(task) if isinstance(task, SequenceTask) else bench_real(task)


def _init_worker() -> None:
    cv2.setNumThreads(1)  # one process per core: the pool is the parallelism
    _quiet_alignment()


def _quiet_alignment() -> None:
    """A camera that never moves has no alignment to fit: the table says so (``–`` or ``fail``), so the
    evaluation's warning about it would only repeat that for every static sequence."""
    logging.getLogger("epi_vo.tools.evaluation").setLevel(logging.ERROR)


def real_clips(data_dir: Path | None) -> list[tuple[str, Path, Path]]:
    """(name, bag, ground truth) of the real clips present in ``data_dir`` (default ../shared/data)."""
    root = data_dir or repo_root().parent / "shared" / "data"
    found = []
    for name in REAL_CLIPS:
        d = root / name
        if (d / "bag").is_dir() and (d / "groundtruth_tum.txt").is_file():
            found.append((name, d / "bag", d / "groundtruth_tum.txt"))
    return found


def run_tasks(tasks: Sequence[SequenceTask | RealTask], jobs: int, progress: Callable[[str], None] | None = None
              ) -> list[dt.SequenceResult | list[BenchRow]]:
    """The tasks' results in their order, ``jobs`` processes at a time (in this process for 1)."""
    def said(result: dt.SequenceResult | list[BenchRow]) -> dt.SequenceResult | list[BenchRow]:
        if progress is not None:
            if isinstance(result, dt.SequenceResult):
                ate = ", ".join(f"{r.pipeline} {dt.fmt(r.ate_percent, 2)}" for r in result.rows)
                progress(f"  {result.family}-s{result.seed}: ATE % {ate}")
            else:
                progress(f"  {result[0].bag}: done")
        return result

    if jobs <= 1:
        _quiet_alignment()
        return [said(_run_task(t)) for t in tasks]
    # spawned, not forked: a process that has run OpenCV's thread pool can hang a forked child in it
    spawn = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=spawn, initializer=_init_worker) as pool:
        return [said(r) for r in pool.map(_run_task, tasks)]


def run_distribution(suite: str, params: str | None, *, families: Sequence[str] | None = None,
                     seeds: Sequence[int] | None = None, jobs: int = 2, cache: str | None = None,
                     data_dir: str | None = None, real: bool = True, record_dir: Path | None = None,
                     reference: bool = True, overrides: Sequence[str] = (), baseline: str | None = None,
                     perturb: Sequence[float] = ()) -> int:
    """Render (if needed) and judge the distribution (or its subset), print the tables and record them.
    ``overrides`` (``NAME=VALUE``) change the parameters after ``params`` (an ablation switches one rule off
    so); ``baseline`` is an earlier record's JSON to print the per-family before -> after against;
    ``perturb``: relative focal length changes, each a twin run of epi_vo on every sequence
    (:mod:`epi_vo.tools.distribution_spread`)."""
    header = RecordHeader.now()
    started = time.perf_counter()
    cfg = with_overrides(load_config(params), overrides)
    before = load_baseline(baseline) if baseline else None
    if jobs < 1:
        raise EpiVoError(f"benchmark: --jobs must be at least 1, got {jobs}")
    gen = load_generator()
    profile = gen.PROFILES[suite]
    unknown = sorted(set(families or ()) - set(gen.FAMILIES))
    if unknown:
        raise EpiVoError(f"benchmark: unknown families {', '.join(unknown)} (known: {', '.join(gen.FAMILIES)})")
    print(f"rendering what is not cached yet ({suite}) ...", file=sys.stderr, flush=True)
    rendered = gen.ensure(profile, families, seeds, Path(cache) if cache else None, jobs,
                          progress=lambda line: print("  " + line, file=sys.stderr, flush=True))
    render_total_cpu = sum(float(s.info["render_cpu_s"]) for s in rendered.sequences)
    tasks: list[SequenceTask | RealTask] = []
    for s in rendered.sequences:
        fam = gen.FAMILIES[s.family]
        tasks.append(SequenceTask(s.family, s.seed, s.path, s.info, fam.scale_sources, cfg, reference))
    for rel in perturb:
        tasks += [SequenceTask(s.family, s.seed, s.path, s.info, (), cfg, False, rel) for s in rendered.sequences]
    clips = real_clips(Path(data_dir) if data_dir else None) if real else []
    tasks += real_tasks(clips, cfg, reference, perturb)
    bench_started = time.perf_counter()
    print(f"benchmarking {len(rendered.sequences)} sequences and {len(clips)} real clips in {jobs} processes ...",
          file=sys.stderr, flush=True)
    results = run_tasks(tasks, jobs, progress=lambda line: print(line, file=sys.stderr, flush=True))
    n_main = len(rendered.sequences)
    seq_results = [r for r in results[:n_main] if isinstance(r, dt.SequenceResult)]
    twins = [r for r in results[n_main:] if isinstance(r, dt.SequenceResult)]
    runs = {0.0: seq_results} | {rel: twins[i * n_main:(i + 1) * n_main] for i, rel in enumerate(perturb)}
    real_results = [r for r in results if isinstance(r, list)]
    n_real = len(clips)
    real_rows = [row for r in real_results[:n_real] for row in r]
    real_runs = {0.0: real_rows} | {rel: [row for r in real_results[(i + 1) * n_real:(i + 2) * n_real] for row in r]
                                    for i, rel in enumerate(perturb)}
    bench_s = time.perf_counter() - bench_started
    stats = dt.family_stats(seq_results)
    goals = dt.targets(stats, seq_results, real_rows)
    timings = {
        "scenario cache": str(rendered.sequences[0].path.parents[1]) if rendered.sequences else "-",
        "render time": f"{render_total_cpu:.0f} s CPU for all {len(rendered.sequences)} sequences "
                       f"({render_total_cpu / 2 / 60:.1f} min on a quiet 2-core machine); this run rendered "
                       f"{rendered.rendered} in {rendered.wall_s:.0f} s",
        "benchmark time": f"{bench_s:.0f} s in {jobs} processes ({len(tasks)} tasks)",
        "load average at the end": load_now(),
    }
    body = [dt.family_tables(stats, seq_results)]
    if real_rows:
        body.append("### Real clips\n\n" + dt.real_table(real_rows))
    body.append("### The generalization issue's targets\n\n" + dt.targets_list(goals))
    data = {
        "header": dataclasses.asdict(header), "suite": suite, "timings": timings,
        "overrides": list(overrides), "baseline": baseline,
        "render_cpu_s": render_total_cpu, "benchmark_s": bench_s, "total_s": time.perf_counter() - started,
        "families": {f: {p: {k: st.to_json() for k, st in by_key.items()} for p, by_key in by_pipe.items()}
                     for f, by_pipe in stats.items()},
        "targets": [dataclasses.asdict(t) for t in goals],
        "sequences": [{"family": r.family, "seed": r.seed, "harshness": r.harshness, "size": r.size,
                       "static": r.static, "scenario": _scenario_summary(s.info),
                       "rows": [row_dict(row) for row in r.rows]}
                      for r, s in zip(seq_results, rendered.sequences, strict=True)],
        "real": [row_dict(r) for r in real_rows],
    }
    if perturb:
        spread_data = spread(runs)
        data["spread"] = spread_data
        body.append("### Run-to-run spread under a calibration nobody could tell apart\n\n"
                    + spread_table(spread_data))
        if real_rows:
            data["real_spread"] = real_spread(real_runs)
            body.append(real_spread_table(data["real_spread"]))
    if before is not None:
        body.append(f"### Against the baseline {baseline}\n\n" + compare(before, jsonable(data)))
        if perturb:
            body.append(spread_compare(before, jsonable(data)))
            if real_rows:
                body.append(real_spread_compare(before, jsonable(data)))
    body.append(READING)
    printed = "\n\n".join(body)
    print(printed)
    if record_dir is not None:
        title = f"epi-vo benchmark --suite {suite}: the scenario distribution and the real clips"
        markdown = "\n\n".join([header.markdown(title, timings), printed,
                                "### Every sequence\n\n<details>\n\n" + dt.sequence_table(seq_results)
                                + "\n\n</details>"])
        md, js = write_record(record_dir, suite, markdown, jsonable(data), header.date, header.commit)
        print(f"\nrecorded in {md} and {js}")
    return 0


def with_overrides(cfg: VoConfig, overrides: Sequence[str]) -> VoConfig:
    """``cfg`` with ``NAME=VALUE`` changes (VALUE read as YAML, as a parameter file would give it); ConfigError
    naming a malformed one or a bad value."""
    values: dict[str, Any] = {}
    for item in overrides:
        name, sep, text = item.partition("=")
        if not sep or not name.strip():
            raise ConfigError(f"benchmark: --set {item!r}: expected NAME=VALUE")
        try:
            values[name.strip()] = yaml.safe_load(text) if text.strip() else ""
        except yaml.YAMLError:
            raise ConfigError(f"benchmark: --set {item!r}: the value is no YAML scalar") from None
    return from_dict(values, base=cfg) if values else cfg


def _scenario_summary(info: dict[str, Any]) -> dict[str, Any]:
    keys = ("frames_written", "fps", "path_length_m", "max_rotation_deg", "scene_depth_median_m",
            "motion_blur_px_max", "mover_share_median", "faults", "metric", "focal_ratio", "render_cpu_s")
    return {k: info.get(k) for k in keys}


READING = """### How to read these tables

Each cell is `median / p90 / worst` over the family's seeds (seeds span clean to harsh cameras); p90 and
worst are on the side that is bad for the figure: the 10th percentile and the smallest for `pose %`, the
magnitude for `step scale − 1 %`, the farthest from 3 (by ratio) for a NEES. `fail`: the figure could not
be computed where it applies (too few poses, an estimate that never moved); `never`: metres never came;
`(n/m)`: only n of the m seeds had something to judge. ATE is after a Sim(3) alignment, as % of the ground
truth's path; `SE3 ATE` after SE(3) only (metres as published). `frames moved` counts frames whose
position changed on a camera that never moves; `% of the map's depth` is the largest displacement from the
first pose against the median depth of the run's own map points (0 when it never moved). `metres after s`
is the time from the first frame to the first pose in metres. ms/frame is the median processing time per
frame (decoding excluded), measured with the sequences running side by side in the pool's processes.
docs/distribution.md describes the families, their envelopes and the camera faults."""
