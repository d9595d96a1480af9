"""The summary of many replays: one row per bag from its output directory, as CSV, Markdown and HTML.

A bag's row comes from the files in its output directory alone (``epi-vo summarize`` rebuilds the summary
of runs made anywhere, e.g. one bag per cluster job):

- ``stats.json``: written last, atomically, by every replay that ran to its end
  (:func:`epi_vo.tools.replay_outputs.write_stats`); without it the directory holds no finished replay;
- ``status.json``: written by fleet replay (:mod:`epi_vo.tools.fleet`) around each bag: ``running`` when the
  bag starts (so a worker that was killed leaves it), then its outcome with a one-line reason. A single-bag
  ``epi-vo replay`` writes none: its status then follows from ``stats.json``.

Statuses: ``ok``; ``problems`` (ran to the end, but frames were rejected or messages skipped: the
single-bag exit status 3); ``failed`` (the bag could not be replayed, or every frame was rejected);
``interrupted`` (a signal stopped it; its outputs are finalised and agree, but cover only part of the bag);
``incomplete`` (no ``stats.json`` and nothing says why: still running, killed, or not run); ``not run``.
Every status but ``ok`` and ``problems`` counts as failed in the exit code (:func:`exit_code`).
"""

from __future__ import annotations

import csv
import enum
import html
import io
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from epi_vo.core.errors import OutputError
from epi_vo.core.frame import Model, TrackingState
from epi_vo.tools.replay import CALIBRATION_NOTE, ReplaySummary
from epi_vo.tools.replay_outputs import STATS_FILE, STATUS_FILE

SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
INDEX_HTML = "index.html"
REPORT_HTML = "report.html"  # what ``epi-vo report`` writes into a replay's directory
EXIT_PROBLEMS = 3  # as a single replay whose frames were rejected or messages skipped
EXIT_BAGS_FAILED = 4  # some bag failed; apart from 2 ("arguments unusable": nothing was run)


class BagStatus(enum.Enum):
    OK = "ok"
    PROBLEMS = "problems"
    FAILED = "failed"
    INTERRUPTED = "interrupted"
    INCOMPLETE = "incomplete"
    NOT_RUN = "not run"
    RUNNING = "running"  # only in status.json while the bag is being replayed

    @property
    def failed(self) -> bool:
        return self not in (BagStatus.OK, BagStatus.PROBLEMS)


@dataclass(frozen=True)
class BagRow:
    """One bag of a fleet: what happened to it and, when its replay finished, its figures."""

    name: str  # the output directory's name under the fleet's output
    bag: str
    status: BagStatus
    reason: str  # one line; empty when ok (unless the replay asks to check the camera calibration)
    run: str  # this run: "replayed", "skipped: complete", "report only", "not run", or "" (summarize)
    output_dir: str
    summary: ReplaySummary | None = None  # None when the replay did not finish
    report: str = ""  # report.html when there is one

    @property
    def metric(self) -> bool:
        return self.summary is not None and self.summary.metric_from_frame is not None


def status_of(summary: ReplaySummary) -> tuple[BagStatus, str]:
    """The status and reason of a replay that ran to its end."""
    line = summary.problem_line()
    if summary.frames and summary.rejected_frames >= summary.frames:
        return BagStatus.FAILED, line or "every frame was rejected"
    if summary.has_problems:
        return BagStatus.PROBLEMS, line
    # A bag that replayed cleanly may still say that its calibration looks wrong (rotation-only frames
    # that are pure only under another focal length): a fleet operator wants to see that in the row.
    return BagStatus.OK, next((n for n in summary.notes if n.startswith(CALIBRATION_NOTE)), "")


def read_stats(directory: Path) -> ReplaySummary | None:
    """The replay summary in ``directory/stats.json``; None when there is none or it cannot be read."""
    try:
        return load_stats(directory)
    except OutputError:
        return None


def load_stats(directory: Path) -> ReplaySummary | None:
    """The replay summary in ``directory/stats.json``; None when there is none. OutputError naming the file
    and the problem when there is one that is not a stats.json of epi-vo replay (not JSON, a field missing
    or of the wrong type): such a file was edited or damaged, and a summary made from it would be wrong."""
    path = directory / STATS_FILE
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeError) as exc:
        raise OutputError(f"{path}: cannot read: {exc}") from None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise OutputError(f"{path}: not JSON ({exc})") from None
    if not isinstance(data, dict):
        raise OutputError(f"{path}: expected a JSON object, not {type(data).__name__}")
    try:
        return ReplaySummary.from_json(data)
    except OutputError as exc:
        raise OutputError(f"{path}: {str(exc).removeprefix('stats.json: ')}") from None


def read_status(directory: Path) -> dict[str, Any]:
    """``directory/status.json`` as a dict (empty when there is none or it cannot be read)."""
    try:
        data = json.loads((directory / STATUS_FILE).read_text(encoding="utf-8"))
    except (OSError, UnicodeError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """``path`` replaced in one step (temporary file renamed over it): readers never see half a file."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def row_from_directory(directory: Path, name: str | None = None) -> BagRow:
    """The row of one replay output directory, from its ``stats.json`` and ``status.json``. OutputError
    when its stats.json is not one (see :func:`load_stats`)."""
    summary = load_stats(directory)
    recorded = read_status(directory)
    bag = str(recorded.get("bag") or (summary.bag if summary else ""))
    run = str(recorded.get("run", ""))
    report = str(directory / REPORT_HTML) if (directory / REPORT_HTML).is_file() else ""
    try:
        recorded_status = BagStatus(recorded["status"]) if "status" in recorded else None
    except ValueError:
        recorded_status = None
    reason = str(recorded.get("reason", ""))
    if recorded_status is None:  # a single-bag replay (no fleet bookkeeping): stats.json says it all
        if summary is not None:
            status, reason = status_of(summary)
        else:
            status, reason = BagStatus.INCOMPLETE, f"no {STATS_FILE}: not run, failed or still running (see its log)"
    elif recorded_status is BagStatus.RUNNING:
        status, reason = BagStatus.INCOMPLETE, "replay started but never finished (its process was killed?)"
    elif recorded_status in (BagStatus.OK, BagStatus.PROBLEMS) and summary is None:
        status, reason = BagStatus.INCOMPLETE, f"{STATS_FILE} is missing or unreadable"
    else:
        status = recorded_status
    if status in (BagStatus.INTERRUPTED, BagStatus.INCOMPLETE, BagStatus.NOT_RUN):
        summary = None  # what is there (if anything) covers part of the bag only
    return BagRow(name or directory.name, bag, status, reason, run, str(directory), summary, report)


def find_output_dirs(paths: Sequence[str | Path]) -> list[Path]:
    """Replay output directories: each path that is one (it holds stats.json, status.json or frames.jsonl), or
    the ones directly under it. OutputError when a path is neither."""
    found: list[Path] = []
    for p in map(Path, paths):
        if _is_output_dir(p):
            found.append(p)
            continue
        if not p.is_dir():
            raise OutputError(f"{p} is no directory")
        children = sorted(c for c in p.iterdir() if c.is_dir() and _is_output_dir(c))
        if not children:
            raise OutputError(f"{p} holds no replay outputs (no {STATS_FILE}, {STATUS_FILE} or frames.jsonl in it "
                              "or in a directory directly under it)")
        found.extend(children)
    return found


def _is_output_dir(p: Path) -> bool:
    return p.is_dir() and any((p / f).is_file() for f in (STATS_FILE, STATUS_FILE, "frames.jsonl"))


def exit_code(rows: Sequence[BagRow]) -> int:
    """The exit status of a fleet or a summary (docs/tools.md): ``EXIT_BAGS_FAILED`` when a bag failed
    (any status but ok and problems; how many, the summary's counts line says), else ``EXIT_PROBLEMS``
    when a bag had rejected frames or skipped messages (a single replay's exit status then), else 0."""
    if any(r.status.failed for r in rows):
        return EXIT_BAGS_FAILED
    return EXIT_PROBLEMS if any(r.status is BagStatus.PROBLEMS for r in rows) else 0


# --------------------------------------------------------------------------------------------------
# Writing

_STATES = [s.value for s in TrackingState]
_MODELS = [m.value for m in Model]
CSV_COLUMNS = ["name", "bag", "status", "reason", "run", "frames", "with_pose_percent", "keyframes",
               *(f"state_{s}" for s in _STATES), *(f"model_{m}" for m in _MODELS), "scale_source",
               "metric_scale", "metric_from_frame", "units", "gt_source", "ate_rmse", "ate_percent_of_path",
               "rpe_rot_deg_per_frame", "rpe_trans_rmse", "nees_pos", "nees_rot", "nees_twist_linear",
               "nees_twist_angular", "ms_per_frame", "end_to_end_fps", "wall_s", "output_dir", "report"]


def csv_record(row: BagRow) -> dict[str, str]:
    """The CSV cells of a row (empty where there is no value: no finished replay, no ground truth)."""
    s = row.summary
    cells: dict[str, Any] = {"name": row.name, "bag": row.bag, "status": row.status.value, "reason": row.reason,
                             "run": row.run, "output_dir": row.output_dir, "report": row.report}
    if s is not None:
        m = s.metrics or {}
        cells |= {"frames": s.frames, "with_pose_percent": _num(s.tracked_percent, 1), "keyframes": s.keyframes,
                  **{f"state_{k}": s.states.get(k, 0) for k in _STATES},
                  **{f"model_{k}": s.models.get(k, 0) for k in _MODELS},
                  "scale_source": s.scale_source, "metric_scale": "yes" if row.metric else "no",
                  "metric_from_frame": "" if s.metric_from_frame is None else s.metric_from_frame,
                  "units": s.units, "gt_source": s.gt_source,
                  "ate_rmse": _num(m.get("ate_rmse"), 6), "ate_percent_of_path": _num(m.get("ate_percent_of_path"), 4),
                  "rpe_rot_deg_per_frame": _num(m.get("rpe_rot_deg_per_frame"), 5),
                  "rpe_trans_rmse": _num(m.get("rpe_trans_rmse"), 6),
                  **{k: _num(m.get(k), 3) for k in ("nees_pos", "nees_rot", "nees_twist_linear", "nees_twist_angular")},
                  "ms_per_frame": _num(s.ms_per_frame, 3),
                  "end_to_end_fps": _num(s.end_to_end_fps, 1), "wall_s": _num(s.wall_s, 3)}
    return {c: str(cells.get(c, "")) for c in CSV_COLUMNS}


def _num(x: Any, digits: int) -> str:
    if x is None or not isinstance(x, int | float) or not math.isfinite(x):
        return ""
    return f"{x:.{digits}f}"


def render_csv(rows: Sequence[BagRow]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(csv_record(r) for r in rows)
    return buf.getvalue()


def counts_line(rows: Sequence[BagRow]) -> str:
    """'5 bags: 3 ok, 1 problems, 1 failed (2 skipped: complete)'."""
    counts = {s: sum(r.status is s for r in rows) for s in BagStatus}
    parts = [f"{n} {s.value}" for s, n in counts.items() if n]
    skipped = sum(r.run.startswith("skipped") for r in rows)
    tail = f" ({skipped} skipped: complete from an earlier run)" if skipped else ""
    return f"{len(rows)} bag(s): {', '.join(parts) or 'none'}{tail}"


_MD_HEADER = ["bag", "status", "frames", "pose %", "keyframes", "states", "models", "scale", "ATE % path",
              "RPE rot deg/f", "ms/frame", "frames/s", "run", "reason"]


def _md_cells(row: BagRow) -> list[str]:
    s = row.summary
    if s is None:
        figures = [""] * 10
    else:
        m = s.metrics or {}
        scale = s.scale_source + (f": metric from frame {s.metric_from_frame}" if row.metric else
                                  (": not established" if s.scale_source != "none" else ""))
        figures = [str(s.frames), _num(s.tracked_percent, 1), str(s.keyframes),
                   ", ".join(f"{k} {v}" for k, v in sorted(s.states.items())),
                   ", ".join(f"{k} {v}" for k, v in sorted(s.models.items())), scale,
                   _num(m.get("ate_percent_of_path"), 3), _num(m.get("rpe_rot_deg_per_frame"), 4),
                   _num(s.ms_per_frame, 2), _num(s.end_to_end_fps, 1)]
    return [row.name, row.status.value, *figures, row.run, row.reason]


def render_markdown(rows: Sequence[BagRow]) -> str:
    def esc(text: str) -> str:
        return text.replace("|", "\\|").replace("\n", " ")

    lines = ["# epi_vo replay summary", "", counts_line(rows), "",
             "| " + " | ".join(_MD_HEADER) + " |", "|" + "---|" * len(_MD_HEADER)]
    lines += ["| " + " | ".join(esc(c) for c in _md_cells(r)) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def render_index(rows: Sequence[BagRow], base: Path) -> str:
    """index.html: the summary table, each bag's name linking its report.html (paths relative to ``base``)."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in _MD_HEADER)
    body = []
    for r in rows:
        cells = [html.escape(c) for c in _md_cells(r)]
        if r.report:
            href = Path(os.path.relpath(r.report, base)).as_posix()
            cells[0] = f'<a href="{html.escape(href)}">{cells[0]}</a>'
        body.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    return ("<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>epi_vo replay summary</title><style>"
            "body{font-family:system-ui,sans-serif;margin:18px}table{border-collapse:collapse;font-size:.9em}"
            "th,td{border:1px solid #ddd;padding:3px 8px;text-align:left}th{background:#f0f2f5}</style></head>"
            f"<body><h1>epi_vo replay summary</h1><p>{html.escape(counts_line(rows))}</p>"
            f"<table><tr>{head}</tr>{''.join(body)}</table></body></html>\n")


def summary_paths(out: Path) -> list[Path]:
    """Every path :func:`write_summary` may write in ``out`` (the files and their temporaries)."""
    return [out / n for name in (SUMMARY_CSV, SUMMARY_MD, INDEX_HTML) for n in (name, f".{name}.tmp")]


def write_summary(out: Path, rows: Sequence[BagRow], *, index: bool) -> list[Path]:
    """``out/summary.csv`` and ``out/summary.md`` (and ``out/index.html`` when ``index``); their paths."""
    written = []
    try:
        for name, text in ((SUMMARY_CSV, render_csv(rows)), (SUMMARY_MD, render_markdown(rows)),
                           *([(INDEX_HTML, render_index(rows, out))] if index else [])):
            tmp = out / f".{name}.tmp"
            tmp.write_text(text, encoding="utf-8")
            os.replace(tmp, out / name)
            written.append(out / name)
    except OSError as exc:
        raise OutputError(f"cannot write the summary in {out}: {exc.strerror or exc}") from None
    return written


def summarize(paths: Sequence[str | Path], output: str | Path | None = None, *,
              force: bool = False) -> tuple[list[BagRow], list[Path]]:
    """``epi-vo summarize``: the rows of the replay output directories in ``paths`` (see
    :func:`find_output_dirs`) and the summary files written for them into ``output`` (default: the one path
    given, be it an output directory or one holding them; with several paths ``output`` must be given).

    A summary already there that lists bags this one would not (a fleet's larger summary, or a file of
    another kind) is not replaced unless ``force``: OutputError names it.
    """
    dirs = find_output_dirs(paths)
    if output is None:
        if len(paths) != 1:
            raise OutputError(f"{len(paths)} directories given: say where the summary goes with --output")
        output = paths[0]
    out = Path(output)
    rows = [row_from_directory(d) for d in dirs]
    if not force:
        _check_not_dropping(out / SUMMARY_CSV, rows)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create {out}: {exc.strerror or exc}") from None
    return rows, write_summary(out, rows, index=any(r.report for r in rows))


def _check_not_dropping(path: Path, rows: Sequence[BagRow]) -> None:
    """OutputError when ``path`` exists and is not a summary of (at most) the bags in ``rows``."""
    if not path.exists():
        return
    try:
        with path.open(newline="", encoding="utf-8") as f:
            names = [r.get("name") for r in csv.DictReader(f)]
    except (OSError, UnicodeError, csv.Error) as exc:
        raise OutputError(f"{path} exists and cannot be read as a summary ({exc}): not replaced; pass --force to "
                          "replace it, or --output to write elsewhere") from None
    if any(n is None for n in names):
        raise OutputError(f"{path} exists and is not an epi-vo summary: not replaced; pass --force to replace it, "
                          "or --output to write elsewhere")
    dropped = sorted(set(names) - {r.name for r in rows})
    if dropped:
        raise OutputError(f"{path} lists {len(names)} bag(s), {len(dropped)} of which this summary of {len(rows)} "
                          f"would drop (e.g. {dropped[0]}): not replaced; pass --force to replace it, or --output "
                          "to write elsewhere")
