"""A benchmark's figures as a dated record: ``docs/benchmarks/<date>-<suite>.md`` and the same as JSON.

The benchmark code writes these files, not a person: every figure quoted elsewhere points at one. The
header says where the figures come from (date, commit and whether the tree had changes, the machine and
its load when the run started, the command, the library versions) so that two records can be compared
knowing what differed.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import subprocess
import sys
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from epi_vo.core.errors import OutputError

# Distributions whose versions decide the figures (the pipeline's and the reference's numerics, the
# evaluation, the bag reading, and the renderer's textures for the scenario distribution).
LIBRARIES = ("numpy", "opencv-python-headless", "scipy", "gtsam", "evo", "rosbags", "mcap", "scikit-image")


def repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def default_record_dir() -> Path | None:
    """``docs/benchmarks`` of the source tree the package runs from; None when it is not a source tree
    (an installed package has no docs/ beside it)."""
    docs = repo_root() / "docs"
    return docs / "benchmarks" if docs.is_dir() else None


def _git(*args: str) -> str:
    try:
        done = subprocess.run(["git", "-C", str(repo_root()), *args], capture_output=True, text=True, timeout=20,
                              check=False)
    except (OSError, subprocess.SubprocessError):
        return ""
    return done.stdout.strip() if done.returncode == 0 else ""


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


@dataclass(frozen=True)
class RecordHeader:
    """Where a benchmark's figures come from."""

    date: str
    started: str  # ISO time (UTC) the run started
    commit: str
    tree_changes: bool  # the working tree differed from the commit
    machine: str
    cores: int
    load_average: tuple[float, float, float] | None
    command: str
    python: str
    libraries: dict[str, str]

    @classmethod
    def now(cls, argv: list[str] | None = None) -> RecordHeader:
        started = datetime.datetime.now(datetime.UTC)
        try:
            load = tuple(round(v, 2) for v in os.getloadavg())
        except OSError:
            load = None
        return cls(started.date().isoformat(), started.isoformat(timespec="seconds"),
                   _git("rev-parse", "HEAD") or "unknown", bool(_git("status", "--porcelain", "--untracked-files=no")),
                   f"{platform.node()}: {_cpu_model()}, {platform.system()} {platform.release()}", os.cpu_count() or 0,
                   load, "epi-vo " + " ".join(sys.argv[1:] if argv is None else argv),
                   platform.python_version(), {name: _version(name) for name in LIBRARIES})

    def markdown(self, title: str, timings: dict[str, str]) -> str:
        load = "n/a" if self.load_average is None else ", ".join(f"{v:.2f}" for v in self.load_average)
        lines = [f"# {title}", "",
                 f"- date: {self.date} (started {self.started})",
                 f"- commit: `{self.commit}`" + (" with uncommitted changes" if self.tree_changes else ""),
                 f"- machine: {self.machine}; {self.cores} cores; load average at the start {load}",
                 f"- command: `{self.command}`",
                 f"- python {self.python}; " + ", ".join(f"{k} {v}" for k, v in self.libraries.items())]
        lines += [f"- {k}: {v}" for k, v in timings.items()]
        return "\n".join(lines)


def load_now() -> str:
    """The load average now (1, 5, 15 min), for a record's timings: ms/frame depends on it."""
    try:
        return ", ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def jsonable(x: Any) -> Any:
    """Strict JSON: non-finite floats become null, tuples lists, dataclass-like rows dicts."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def record_stem(directory: Path, suite: str, date: str, commit: str) -> str:
    """``<date>-<suite>``, or ``<date>-<suite>-<commit 7>`` when a record of that day and suite was taken at
    another commit: a record is replaced only by a run of the same commit, so a day's baseline and the run
    of the change it judges stand side by side."""
    stem = f"{date}-{suite}"
    try:
        earlier = json.loads((directory / f"{stem}.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeError, ValueError):
        return stem
    taken_at = earlier.get("header", {}).get("commit") if isinstance(earlier, dict) else None
    return stem if taken_at in (None, commit) else f"{stem}-{commit[:7]}"


def write_record(directory: Path, suite: str, markdown: str, data: dict[str, Any], date: str,
                 commit: str = "unknown") -> tuple[Path, Path]:
    """``<directory>/<stem>.md`` and ``.json`` (``record_stem``). OutputError when they cannot be written."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        stem = record_stem(directory, suite, date, commit)
        md, js = directory / f"{stem}.md", directory / f"{stem}.json"
        md.write_text(markdown.rstrip() + "\n", encoding="utf-8")
        js.write_text(json.dumps(jsonable(data), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"cannot write the benchmark record under {directory}: {exc.strerror or exc}") from None
    return md, js
