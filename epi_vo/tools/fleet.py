"""Fleet replay: many bags, each replayed in its own process, one summary.

``epi-vo replay BAG... --output OUT --jobs N`` (several bags, a directory holding bags, or a glob) replays
each bag exactly as a single-bag run would, into ``OUT/<name>/``, then writes ``OUT/summary.csv``,
``OUT/summary.md`` and, with ``--report``, ``OUT/index.html`` (:mod:`epi_vo.tools.fleet_summary`).

* **Processes.** A ``ProcessPoolExecutor`` (forkserver context where there is one, else spawn; never fork:
  the parent may hold threads and open bags) with one fresh process per bag (``max_tasks_per_child=1``),
  so a bag that exhausts memory or crashes OpenCV takes only itself down. A worker that dies breaks the
  pool: the bags that were then running are retried once in a new pool, and a bag whose worker dies twice
  is failed ("worker process died").
* **Complete.** A bag's directory is complete when its replay wrote ``stats.json`` (last, atomically) and
  ``status.json`` says the fleet finished it, for the same bag and the same parameters; a re-run skips it
  (``--force`` redoes it; with ``--report`` a missing report is made without replaying).
* **Signals.** SIGINT, SIGTERM or SIGHUP to the fleet (Ctrl-C reaches every process of the group; a
  signal to the parent alone is passed on through a shared event): bags not started are not run, running
  ones stop between two frames with their outputs finalised (as a single-bag replay does) and marked
  ``interrupted`` in ``status.json``; bags finished before keep their valid outputs. Exit status 130 (129
  for SIGHUP).
* **Inputs are never outputs.** Before anything is written, every output of every bag and the summary are
  checked against every bag (and the parameter file): one that would overwrite an input or write into a
  bag directory refuses the whole fleet (:func:`epi_vo.tools.replay_outputs.check_outputs_clear`).
* **Exit status** otherwise: :func:`epi_vo.tools.fleet_summary.exit_code` (0 every bag ok, 3 some with
  problems, 4 some failed; docs/tools.md).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import logging
import multiprocessing
import os
import queue
import signal
import time
from collections.abc import Callable, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from epi_vo.core.config import VoConfig
from epi_vo.core.errors import EpiVoError, Interrupted
from epi_vo.io.node_options import CameraExtrinsic
from epi_vo.tools.fleet_bags import output_names
from epi_vo.tools.fleet_summary import (
    REPORT_HTML,
    BagRow,
    BagStatus,
    read_stats,
    read_status,
    status_of,
    summary_paths,
    write_json_atomic,
    write_summary,
)
from epi_vo.tools.replay import ReplaySummary, StopRequest, extrinsic_record, gt_choice, run_replay, stop_on_signals
from epi_vo.tools.replay_outputs import STATUS_FILE, check_outputs_clear, ensure_output_dir, output_paths

_log = logging.getLogger(__name__)

PROGRESS_EVERY_S = 0.2  # a worker reports its frames at most this often


# --------------------------------------------------------------------------------------------------
# One bag (in a worker process)


@dataclass(frozen=True)
class FleetJob:
    """What a worker needs to replay one bag into ``output``."""

    index: int
    name: str
    bag: str
    output: str
    cfg: VoConfig
    image_topic: str | None = None
    camera_info_topic: str | None = None
    report: bool = False
    force: bool = False
    map_frame_id: str = ""
    gt_topic: str | None = None  # the ground-truth topic of every bag (default: the one named as such)
    no_gt: bool = False  # no ground truth, whatever the bags hold
    extrinsic: CameraExtrinsic | None = None  # the camera mounting of every bag (None: the default)


_worker_events: Any = None  # the progress queue of this worker process (set by _init_worker)
_worker_stop: Any = None  # the fleet's stop event


def _init_worker(events: Any, stop: Any, log_level: int) -> None:
    """In each worker: signals are the fleet's to handle (the parent sets ``stop``); a replay in progress
    still installs its own handlers, so Ctrl-C at a terminal stops it at a frame boundary. Log records go to
    stderr as the parent's do, at its level."""
    global _worker_events, _worker_stop
    _worker_events, _worker_stop = events, stop
    logging.basicConfig(level=log_level, format="%(levelname)s %(name)s: %(message)s")
    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)


def _send(*event: Any) -> None:
    if _worker_events is not None:
        with contextlib.suppress(Exception):  # progress is best effort: never fail a bag for it
            _worker_events.put_nowait(event)


def parameters_json(cfg: VoConfig) -> Any:
    """The parameters as ``stats.json`` holds them (JSON types), to compare a finished run's with."""
    return json.loads(json.dumps(ReplaySummary(
        bag="", image_topic="", camera_info_topic="", frames=0, frames_with_pose=0, tracked_percent=0.0,
        keyframes=0, states={}, models={}, ms_per_frame=0.0, stage_ms={}, path_length=0.0,
        parameters=asdict(cfg)).to_json()["parameters"]))


def completed(job: FleetJob) -> ReplaySummary | None:
    """The finished replay in the job's directory when it is complete for this job (see module doc)."""
    out = Path(job.output)
    summary = read_stats(out)
    status = read_status(out)
    if summary is None or status.get("status") not in (BagStatus.OK.value, BagStatus.PROBLEMS.value,
                                                          BagStatus.FAILED.value):
        return None
    if summary.bag != job.bag or summary.parameters != parameters_json(job.cfg) or \
            summary.map_frame_id != job.map_frame_id or _extrinsic_json_of(summary) != _extrinsic_json(job.extrinsic):
        return None
    if job.image_topic not in (None, summary.image_topic) or \
            job.camera_info_topic not in (None, summary.camera_info_topic):
        return None
    if summary.gt_choice != gt_choice(gt_topic=job.gt_topic, no_gt=job.no_gt):
        return None
    return summary


def _extrinsic_json(extrinsic: CameraExtrinsic | None) -> dict[str, Any]:
    """What stats.json says of the extrinsic of a job (its source and parameters), to compare a finished run's with."""
    record = extrinsic_record(extrinsic, np.eye(4))
    return {k: v for k, v in record.items() if k != "T_base_cam"}


def _extrinsic_json_of(summary: ReplaySummary) -> dict[str, Any]:
    """A finished run's extrinsic (source and parameters); an older stats.json without one was made with the
    default (the replay took no extrinsic from the parameters then)."""
    if summary.extrinsic is None:
        return _extrinsic_json(None)
    return {k: v for k, v in summary.extrinsic.items() if k != "T_base_cam"}


def replay_one(job: FleetJob) -> BagRow:
    """Replay one bag into its directory (in a worker process); never raises for a bad bag: the row says."""
    out = Path(job.output)
    _send("start", job.index, os.getpid())
    for handler in logging.getLogger().handlers:  # one bag per worker: its records say which
        handler.setFormatter(logging.Formatter(f"%(levelname)s [{job.name}] %(name)s: %(message)s"))
    if _worker_stop is not None and _worker_stop.is_set():
        return _row(job, BagStatus.NOT_RUN, "the fleet was interrupted before this bag started", "not run")
    previous = None if job.force else completed(job)
    if previous is not None:
        (status, reason), run = status_of(previous), "skipped: complete"
        _send("frames", job.index, previous.frames, previous.frames)
        if job.report and not (out / REPORT_HTML).is_file():
            problem = _report(out)
            if problem:
                return _finish(job, BagStatus.FAILED, problem, "report only", previous)
            return _finish(job, status, reason, "report only", previous)
        return _row(job, status, reason, run, previous)
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / STATUS_FILE, {"bag": job.bag, "name": job.name, "status": BagStatus.RUNNING.value,
                                              "reason": "", "run": "replayed", "pid": os.getpid()})
    except OSError as exc:
        return _row(job, BagStatus.FAILED, f"cannot write in {out}: {exc.strerror or exc}", "replayed")
    progress = _FrameProgress(job.index)
    try:
        summary = run_replay(job.bag, out, job.cfg, image_topic=job.image_topic,
                             camera_info_topic=job.camera_info_topic, on_result=progress.frame,
                             on_open=progress.total, map_frame_id=job.map_frame_id, gt_topic=job.gt_topic,
                             no_gt=job.no_gt, extrinsic=job.extrinsic)
    except Interrupted as exc:
        by = "the fleet was interrupted" if _worker_stop is not None and _worker_stop.is_set() else \
            _signal_name(exc.signum)
        return _finish(job, BagStatus.INTERRUPTED, f"{by} after {progress.done} frame(s): outputs finalised up to "
                       "there, not complete", "replayed")
    except EpiVoError as exc:
        return _finish(job, BagStatus.FAILED, _one_line(str(exc)), "replayed")
    except (OSError, UnicodeError) as exc:
        return _finish(job, BagStatus.FAILED, _one_line(f"{type(exc).__name__}: {exc}"), "replayed")
    except Exception as exc:  # a bug must not take the other bags down: the row says what it was
        _log.exception("replay of %s failed", job.bag)
        return _finish(job, BagStatus.FAILED, _one_line(f"internal error: {type(exc).__name__}: {exc}"), "replayed")
    finally:
        progress.flush()
    status, reason = status_of(summary)
    if job.report:
        problem = _report(out)
        if problem:
            status, reason = BagStatus.FAILED, problem
    return _finish(job, status, reason, "replayed", summary)


def _report(out: Path) -> str:
    """Write the bag's report; the problem in one line, or '' when it was written."""
    try:
        from epi_vo.tools.report import write_report  # matplotlib and evo: only when reports are asked for

        write_report(out)
    except (EpiVoError, OSError, ValueError) as exc:
        return _one_line(f"report: {exc}")
    return ""


class _FrameProgress:
    """on_result / on_open callbacks of a worker's replay: frames reported in batches, the fleet's stop event
    checked after every frame (a replay stopped this way finalises its outputs as for a signal)."""

    def __init__(self, index: int) -> None:
        self._index = index
        self.done = 0
        self._unsent = 0
        self._last = time.monotonic()

    def total(self, frames: int) -> None:
        _send("total", self._index, frames)

    def frame(self, _result: object) -> None:
        self.done += 1
        self._unsent += 1
        if time.monotonic() - self._last > PROGRESS_EVERY_S:
            self.flush()
        if _worker_stop is not None and _worker_stop.is_set():
            raise Interrupted(signal.SIGINT)

    def flush(self) -> None:
        if self._unsent:
            _send("frames", self._index, self._unsent, None)
            self._unsent = 0
        self._last = time.monotonic()


def _finish(job: FleetJob, status: BagStatus, reason: str, run: str, summary: ReplaySummary | None = None) -> BagRow:
    row = _row(job, status, reason, run, summary)
    with contextlib.suppress(OSError):  # a directory that cannot be written: the row still says why
        write_json_atomic(Path(job.output) / STATUS_FILE, {"bag": job.bag, "name": job.name, "status": status.value,
                                                           "reason": reason, "run": run})
    return row


def _row(job: FleetJob, status: BagStatus, reason: str, run: str, summary: ReplaySummary | None = None) -> BagRow:
    report = Path(job.output) / REPORT_HTML
    return BagRow(job.name, job.bag, status, reason, run, job.output, summary,
                  str(report) if report.is_file() else "")


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


# --------------------------------------------------------------------------------------------------
# The fleet (in the parent)


@dataclass(frozen=True)
class FleetResult:
    rows: list[BagRow]
    summary_files: list[Path]
    signum: int | None  # the signal that stopped the fleet, None when it ran to the end


def run_fleet(bags: Sequence[Path], output_dir: str | Path, cfg: VoConfig, *, jobs: int | None = None,
              force: bool = False, report: bool = False, progress: bool = False, image_topic: str | None = None,
              camera_info_topic: str | None = None, on_row: Callable[[BagRow], None] | None = None,
              map_frame_id: str = "", gt_topic: str | None = None, no_gt: bool = False,
              inputs: Sequence[str | Path] = (), extrinsic: CameraExtrinsic | None = None) -> FleetResult:
    """Replay ``bags`` (see :func:`epi_vo.tools.fleet_bags.find_bags`) into ``output_dir/<name>/`` with ``jobs``
    processes (default: the number of cores) and write the summary. See the module doc for resume, signals and
    failures. ``inputs``: other files the run reads (a parameter file); ``extrinsic``: the camera mounting
    (``run_replay``'s).

    Raises:
        OutputError: an output of some bag (or the summary) would overwrite an input or write into a bag
            directory (checked for every bag before anything is written: nothing runs then), the output
            directory cannot be created or the summary not written.
    """
    names = output_names(bags)
    planned = [*summary_paths(Path(output_dir)), *(p for name in names for p in output_paths(Path(output_dir) / name))]
    check_outputs_clear([*bags, *inputs], planned)
    out = ensure_output_dir(output_dir)
    # Absolute bag paths: stats.json then names the bag whatever the directory a later run starts from.
    todo = [FleetJob(i, name, str(bag.absolute()), str(out / name), cfg, image_topic, camera_info_topic, report,
                     force, map_frame_id, gt_topic, no_gt, extrinsic)
            for i, (bag, name) in enumerate(zip(bags, names, strict=True))]
    rows: dict[int, BagRow] = {}
    attempts = dict.fromkeys(range(len(todo)), 0)
    workers = max(1, min(jobs or os.cpu_count() or 1, len(todo)))
    with stop_on_signals() as stop, _Bars(progress, len(todo)) as bars:
        while todo and not stop.requested:
            broken = _run_pool(todo, workers, stop, bars, rows, on_row)
            todo = []
            for job in broken:
                attempts[job.index] += job.index in bars.started
                if stop.requested and job.index in bars.started:
                    rows[job.index] = _finish(job, BagStatus.INTERRUPTED, "worker process ended by the interruption",
                                              "replayed")
                elif attempts[job.index] >= 2:
                    rows[job.index] = _finish(job, BagStatus.FAILED, "worker process died (crashed or killed) twice",
                                              "replayed")
                else:
                    todo.append(job)
                    continue
                bars.bag_done(rows[job.index])
            workers = 1  # after a worker died, one bag at a time: a second death then names its bag
    for i, (bag, name) in enumerate(zip(bags, names, strict=True)):
        if i not in rows:
            rows[i] = _row(FleetJob(i, name, str(bag.absolute()), str(out / name), cfg), BagStatus.NOT_RUN,
                           "the fleet was interrupted before this bag started", "not run")
    ordered = [rows[i] for i in range(len(bags))]
    files = write_summary(out, ordered, index=report)
    return FleetResult(ordered, files, stop.signum if stop.requested else None)


def _context() -> multiprocessing.context.BaseContext:
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
    if ctx.get_start_method() == "forkserver":
        # Workers fork from a server that imported the replay (numpy, cv2, rosbags) once.
        ctx.set_forkserver_preload(["epi_vo.tools.fleet"])
    return ctx


def _run_pool(todo: Sequence[FleetJob], jobs: int, stop: StopRequest, bars: _Bars, rows: dict[int, BagRow],
              on_row: Callable[[BagRow], None] | None) -> list[FleetJob]:
    """Run ``todo`` in one pool; fills ``rows``; returns the jobs whose worker died (the pool broke)."""
    ctx = _context()
    events = ctx.Queue()
    stop_event = ctx.Event()
    broken: list[FleetJob] = []
    pool = cf.ProcessPoolExecutor(max_workers=min(jobs, len(todo)), mp_context=ctx, initializer=_init_worker,
                                  initargs=(events, stop_event, logging.getLogger().getEffectiveLevel()),
                                  max_tasks_per_child=1)
    try:
        futures = {pool.submit(replay_one, job): job for job in todo}
        pending = set(futures)
        while pending:
            done, pending = cf.wait(pending, timeout=0.1)
            _drain(events, bars)
            if stop.requested and not stop_event.is_set():
                stop_event.set()  # workers stop between two frames; bags not started are not run
                for f in pending:
                    f.cancel()
            for f in done:
                job = futures[f]
                if f.cancelled():
                    continue
                try:
                    row = f.result()
                except BrokenProcessPool:
                    broken.append(job)
                    continue
                except Exception as exc:  # e.g. the job could not be sent to the worker
                    row = _finish(job, BagStatus.FAILED, _one_line(f"{type(exc).__name__}: {exc}"), "replayed")
                rows[job.index] = row
                bars.bag_done(row)
                if on_row is not None:
                    on_row(row)
        _drain(events, bars)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        events.close()
        events.join_thread()
    return broken


def _drain(events: Any, bars: _Bars) -> None:
    while True:
        try:
            event = events.get_nowait()
        except (queue.Empty, OSError, ValueError):
            return
        bars.event(event)


class _Bars:
    """Two tqdm bars, bags and frames (the frame total grows as workers open their bags); a terminal that went
    away ends the bars, never the fleet."""

    def __init__(self, enabled: bool, n_bags: int) -> None:
        self._bags: Any = None
        self._frames: Any = None
        self._totals: dict[int, int] = {}
        self.started: set[int] = set()  # bags whose worker began (a "start" event arrived)
        if enabled:
            from tqdm import tqdm

            self._bags = tqdm(total=n_bags, unit="bag", desc="bags  ", position=0)
            self._frames = tqdm(total=0, unit="frame", desc="frames", position=1)

    def __enter__(self) -> _Bars:
        return self

    def __exit__(self, *exc: object) -> None:
        for bar in (self._frames, self._bags):
            if bar is not None:
                with contextlib.suppress(OSError, ValueError):
                    bar.close()
        self._bags = self._frames = None

    def _guard(self, action: Callable[[], object]) -> None:
        try:
            action()
        except (OSError, ValueError):  # stderr closed or gone
            self._bags = self._frames = None

    def event(self, event: tuple[Any, ...]) -> None:
        kind, index = event[0], event[1]
        if kind == "start":
            self.started.add(index)
        if self._frames is None:
            return
        if kind == "total":
            self._totals[index] = int(event[2])
            self._frames.total = sum(self._totals.values())
            self._guard(self._frames.refresh)
        elif kind == "frames":
            if event[3] is not None:  # a skipped bag: its frames count as done
                self._totals[index] = int(event[3])
                self._frames.total = sum(self._totals.values())
            self._guard(lambda: self._frames.update(int(event[2])))

    def bag_done(self, row: BagRow) -> None:
        if self._bags is not None:
            bags = self._bags
            self._guard(lambda: (bags.set_postfix_str(f"{row.name}: {row.status.value}"), bags.update(1)))
