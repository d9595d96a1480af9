"""The files of a replay output directory: their names, the rule that none of them lands on an input, and
how they are created and written (see :mod:`epi_vo.tools.replay` for what each holds).

**Overlap.** Before anything is opened for writing, every path a replay may write in its directory
(:func:`output_paths`: its outputs, the fleet's ``status.json``, the report, ``epi-vo recover``'s files) is
checked against every input (the bag, a rosbag2 bag directory as a whole, the ground-truth and parameter
files): an output that is an input, or lies inside an input directory, is refused with an OutputError
(:func:`check_outputs_clear`), so that no input is ever truncated or written into.

**What survives a kill** (SIGKILL, power cut: no chance to finalise): ``frames.jsonl`` and
``trajectory.tum`` are flushed after every frame, so they hold every frame written (the last line may be
cut when the kill came in the middle of a write); ``output.mcap`` is written in chunks, one closed and
flushed every ``OUTPUT_FLUSH_FRAMES`` frames, and lacks its summary and end magic: ``epi-vo recover`` copies
its complete chunks into a readable file; ``stats.json`` is missing (it is written last), which is how a
fleet and ``epi-vo summarize`` tell the directory holds no finished replay.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from epi_vo.core.errors import OutputError
from epi_vo.core.scale import Units
from epi_vo.io.msgconv import ns_to_ros_time
from epi_vo.io.paths import find_overlap, special_file_kind

STATS_FILE = "stats.json"
FRAMES_FILE = "frames.jsonl"
TRAJECTORY_FILE = "trajectory.tum"
OUTPUT_BAG = "output.mcap"
GROUNDTRUTH_FILE = "groundtruth.tum"
STATUS_FILE = "status.json"  # written by fleet replay around each bag
DAMAGED_BAG = "output.mcap.damaged"  # epi-vo recover keeps the damaged output.mcap under this name
# Every name a replay directory may get: the replay's outputs, the fleet's bookkeeping, the report
# (report.html and its report/ directory of figures), recover's files, and the temporaries renamed over them.
DIRECTORY_NAMES = (FRAMES_FILE, TRAJECTORY_FILE, OUTPUT_BAG, GROUNDTRUTH_FILE, STATS_FILE, f".{STATS_FILE}.tmp",
                   STATUS_FILE, f".{STATUS_FILE}.tmp", "report.html", "report", DAMAGED_BAG,
                   f".{OUTPUT_BAG}.recovering")
# output.mcap's chunk is closed, compressed and handed to the OS every this many frames: what a kill can
# cost of it (a second of a 30 Hz camera), against one chunk per frame, which compresses /vo/path's
# repeated poses poorly.
OUTPUT_FLUSH_FRAMES = 30


def output_paths(out: Path) -> list[Path]:
    """Every path a replay, its fleet bookkeeping, its report or ``epi-vo recover`` may write in ``out``."""
    return [out / name for name in DIRECTORY_NAMES]


def check_outputs_clear(inputs: Sequence[str | Path | None], outputs: Sequence[Path]) -> None:
    """OutputError naming the first output that would land on an input (the same file, or a path inside an
    input directory), or that exists as a FIFO or device (opening it for writing could block); nothing is
    opened. ``inputs`` may hold None (an input not given)."""
    given = [Path(p) for p in inputs if p is not None]
    overlap = find_overlap(given, outputs)
    if overlap is not None:
        how = "write into" if overlap.input.is_dir() else "overwrite"
        raise OutputError(f"refused: output {overlap.output} would {how} the input {overlap.input}; "
                          "choose an output directory apart from the inputs")
    for path in outputs:
        kind = special_file_kind(path)
        if kind is not None:
            raise OutputError(f"refused: output {path} exists and is a {kind}; writing it could block")


def os_reason(exc: OSError) -> str:
    where = f" ({exc.filename})" if exc.filename else ""
    return f"{exc.strerror or exc}{where}"


def ensure_output_dir(output_dir: str | Path) -> Path:
    """The output directory, created if needed; OutputError naming the problem when it cannot be."""
    out = Path(output_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"output {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create the output directory {out}: {os_reason(exc)}") from None
    return out


@contextlib.contextmanager
def open_output(path: Path) -> Iterator[IO[str]]:
    try:
        f = path.open("w", encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"cannot create {path}: {os_reason(exc)}") from None
    with f:
        yield f


def write_stats(out: Path, data: dict[str, Any]) -> None:
    """``out/stats.json``, atomically (a temporary file renamed over it): it is written last, so its presence
    means the replay in ``out`` ran to the end (what fleet replay's resume relies on)."""
    path = out / STATS_FILE
    tmp = out / f".{STATS_FILE}.tmp"
    try:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {os_reason(exc)}") from exc


def remove_stats(out: Path) -> None:
    try:
        (out / STATS_FILE).unlink(missing_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot replace {out / STATS_FILE}: {os_reason(exc)}") from exc


def tum_stamp(stamp_ns: int) -> str:
    """The stamp in seconds with 9 decimals, exact (a float would round large stamps)."""
    sec, nanosec = ns_to_ros_time(stamp_ns)
    return f"{sec}.{nanosec:09d}"


class PathLength:
    """The length of a replay's camera path in the units it ends in (``stats.json`` ``path_length``).

    In VO units: the sum of the steps between consecutive poses. In metres: the path of the positions a robot
    could take as metres, as vo/odometry publishes them (``epi_vo.runner.outputs``): a pose before metres were
    established counts as held at the last metric position (or the start), so the first metric pose adds its
    distance from there and the path in VO units before it adds nothing.
    """

    def __init__(self) -> None:
        self._vo = self._metric = 0.0
        self._last: np.ndarray | None = None
        self._held = np.zeros(3)
        self._last_published: np.ndarray | None = None

    def add(self, position: np.ndarray, units: Units) -> None:
        """The camera position of the next frame with a pose, in ``units``."""
        metric = units is Units.METRES
        if self._last is not None:
            self._vo += float(np.linalg.norm(position - self._last))
        self._last = position.copy()
        if metric:
            self._held = position.copy()
        published = self._held
        if self._last_published is not None:
            self._metric += float(np.linalg.norm(published - self._last_published))
        self._last_published = published

    def length(self, units: Units) -> float:
        return self._metric if units is Units.METRES else self._vo


def recorded_extrinsic(stats: Any) -> np.ndarray | None:
    """``T_base_cam`` (4x4) a replay made its odometry with when the parameters declared the extrinsic
    (``stats.json`` ``extrinsic``, source ``parameters``); None for the default (camera level at base_link)
    or a ``stats.json`` older than the record. ValueError when the record is no rigid 4x4 transform."""
    record = stats.get("extrinsic") if isinstance(stats, dict) else None
    if not isinstance(record, dict) or record.get("source") in (None, "default"):
        return None
    try:
        T = np.asarray(record["T_base_cam"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        T = np.zeros((0,))
    R = T[:3, :3] if T.shape == (4, 4) else np.zeros((3, 3))
    if not (T.shape == (4, 4) and np.all(np.isfinite(T)) and np.allclose(R @ R.T, np.eye(3), atol=1e-6)
            and np.linalg.det(R) > 0 and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0])):
        msg = "extrinsic.T_base_cam is no rigid 4x4 transform"
        raise ValueError(msg)
    return T


def read_recorded_extrinsic(directory: str | Path) -> np.ndarray | None:
    """:func:`recorded_extrinsic` of ``directory``'s stats.json (None without one). OSError, ValueError (JSON,
    the record) as reading it raises."""
    path = Path(directory) / "stats.json"
    return recorded_extrinsic(json.loads(path.read_text(encoding="utf-8"))) if path.is_file() else None
