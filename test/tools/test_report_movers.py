"""The report's static and mover spans (epi_vo.tools.report_movers) and its covariance-consistency figure: known
answers on synthetic records, and replays of the bundled mover bags checked against bags/*/mover_coverage.txt."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from epi_vo.io.trajectory import StampedPoses
from epi_vo.tools.replay import run_replay
from epi_vo.tools.report import write_report
from epi_vo.tools.report_data import Run, load_run, spans
from epi_vo.tools.report_movers import MOVER_FRACTION_MIN, mover_series, mover_spans, static_spans, what_moved

REPO = Path(__file__).resolve().parents[2]
BAGS = REPO / "bags"


def _records(moving: list[tuple[int, float, list[int] | None]], states: list[str]) -> tuple[dict, ...]:
    return tuple({"index": i, "stamp": 10.0 + 0.1 * i, "state": st, "n_moving": n, "moving_fraction": f,
                  "moving_region": box, "static_score": 1.0 - f, "reason": ""}
                 for i, ((n, f, box), st) in enumerate(zip(moving, states, strict=True)))


def _run(records: tuple[dict, ...]) -> Run:
    empty = StampedPoses(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
    return Run(Path("/nonexistent"), records, empty, np.zeros(0, np.int64), None, None)


def test_mover_spans_known_answer() -> None:
    none = (0, 0.0, None)
    moving = [none, (10, 0.1, [5, 6, 50, 60]), (20, 0.2, [40, 2, 90, 70]), none, (1, 0.005, [1, 1, 2, 2]),
              (8, 0.08, [0, 0, 10, 10]), (9, 0.09, [3, 3, 12, 12]), none]
    states = ["tracking", "tracking", "static", "static", "tracking", "tracking", "lost", "tracking"]
    run = _run(_records(moving, states))
    got = mover_spans(run)
    assert [(m.start_index, m.end_index, m.n_frames, m.states) for m in got] == [
        (1, 2, 2, ("tracking", "static")), (5, 6, 2, ("tracking", "lost"))]  # frame 4: 0.5 % < MOVER_FRACTION_MIN
    assert 0.005 < MOVER_FRACTION_MIN <= 0.08
    assert got[0].what == "up to 20 features (20 %) moved on their own, in x 5-90, y 2-70 px"
    assert got[0].start_stamp_s == pytest.approx(10.1) and got[0].end_stamp_s == pytest.approx(10.2)
    st = static_spans(run)
    assert [(s.span.start_index, s.span.end_index, s.what) for s in st] == [
        (2, 3, "up to 20 features (20 %) moved on their own, in x 40-90, y 2-70 px")]
    assert what_moved(mover_series(run), 7, 7) == "nothing moved"


def test_records_without_mover_keys_have_no_movers() -> None:
    recs = tuple({"index": i, "stamp": float(i), "state": "tracking", "reason": ""} for i in range(4))
    run = _run(recs)
    s = mover_series(run)
    assert s.n_moving.tolist() == [0, 0, 0, 0] and np.isnan(s.static_score).all()
    assert mover_spans(run) == [] and static_spans(run) == []


@pytest.fixture(scope="module")
def static_mover(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("static_mover")
    run_replay(BAGS / "static_mover" / "bag", out, gt_tum=BAGS / "static_mover" / "groundtruth_tum.txt")
    write_report(out)
    return out


@pytest.fixture(scope="module")
def moving_mover(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("moving_mover")
    run_replay(BAGS / "moving_mover" / "bag", out, gt_tum=BAGS / "moving_mover" / "groundtruth_tum.txt")
    write_report(out)
    return out


def _coverage(name: str) -> np.ndarray:
    return np.loadtxt(BAGS / name / "mover_coverage.txt")  # frame fraction x0 y0 x1 y1


def test_static_mover_report_marks_the_static_camera(static_mover: Path) -> None:
    run = load_run(static_mover)
    stamps = np.array([r["stamp"] for r in run.records])
    after = {int(r["index"]) for r, t in zip(run.records, stamps, strict=True) if t >= stamps[0] + 1.0}
    st = static_spans(run)
    in_static = {i for s in st for i in range(s.span.start_index, s.span.end_index + 1)}
    assert len(in_static & after) >= 0.9 * len(after)
    assert all(s.what.startswith("up to ") and "moved on their own, in x" in s.what for s in st)
    # The panel moves through the view the whole time: a mover span over the static frames too.
    in_movers = {i for m in mover_spans(run) for i in range(m.start_index, m.end_index + 1)}
    assert len(in_movers & in_static) >= 0.9 * len(in_static)
    page = (static_mover / "report.html").read_text()
    assert "<h2 id=\"movers\">Static camera and moving objects (" in page
    first = st[0]
    assert (f"<tr><td>static camera</td><td class=\"num\">{first.span.start_index}&ndash;{first.span.end_index}"
            f"</td><td class=\"num\">{first.span.n_frames}</td>") in page
    assert first.what in page
    # No tracking frame: no NEES to give (the static frames keep their meaning), said so in the summary.
    assert "0 tracking frames evaluated" in page and "static " in page
    assert not (static_mover / "report" / "nees.png").exists() and "<figure id=\"nees\">" not in page


def test_moving_mover_report_mover_spans_match_the_coverage(moving_mover: Path) -> None:
    run = load_run(moving_mover)
    cov = _coverage("moving_mover")
    fraction = dict(zip(cov[:, 0].astype(int), cov[:, 1], strict=True))
    ms = mover_spans(run)
    assert ms, "no mover span"
    flagged = {i for m in ms for i in range(m.start_index, m.end_index + 1)}
    # Movers are reported only where the cart fills a good part of the view ...
    assert min(fraction[i] for i in flagged) >= 0.2
    # ... and over most of the frames where it covers 30 % or more.
    large = {int(f) for f, c in zip(cov[:, 0], cov[:, 1], strict=True) if c >= 0.3}
    assert len(flagged & large) >= 0.8 * len(large)
    assert all(set(m.states) == {"tracking"} for m in ms)  # the camera kept tracking through them
    assert static_spans(run) == []
    page = (moving_mover / "report.html").read_text()
    for m in ms:
        assert f"<tr><td>movers in view</td><td class=\"num\">{m.start_index}&ndash;{m.end_index}</td>" in page
        assert m.what in page


def test_report_has_the_nees_figure_with_ground_truth(moving_mover: Path) -> None:
    page = (moving_mover / "report.html").read_text()
    assert "<figure id=\"nees\">" in page and (moving_mover / "report" / "nees.png").is_file()
    row = page[page.index("NEES position (3 dof)"):]
    mean = float(row.split("mean ", 1)[1].split(",", 1)[0])
    assert math.isfinite(mean) and mean > 0.0
    recs = [json.loads(line) for line in (moving_mover / "frames.jsonl").read_text().splitlines()]
    n_tracking = sum(r["state"] == "tracking" for r in recs)
    assert f"{n_tracking} tracking frames evaluated (Sim(3)" in page
    # The twist's consistency too: the replay's own figures (stats.json), read back from output.mcap.
    twist = page[page.index("NEES twist (3 dof each)"):]
    lin = float(twist.split("linear velocity mean ", 1)[1].split(",", 1)[0])
    ang = float(twist.split("angular velocity mean ", 1)[1].split(",", 1)[0])
    stats = json.loads((moving_mover / "stats.json").read_text())["metrics"]
    assert lin == pytest.approx(stats["nees_twist_linear"], abs=0.0051)
    assert ang == pytest.approx(stats["nees_twist_angular"], abs=0.0051)
    # nees.png: position, rotation, linear and angular velocity, one panel each (3.75 in x 100 dpi)
    import cv2
    h, _ = cv2.imread(str(moving_mover / "report" / "nees.png")).shape[:2]
    assert h == 1500
    # The timeline has its seventh panel (movers): a taller picture.
    import cv2
    h, w = cv2.imread(str(moving_mover / "report" / "timeline.png")).shape[:2]
    assert (w, h) == (1300, 1960)


def test_report_without_ground_truth_has_no_nees(tmp_path: Path, moving_mover: Path) -> None:
    d = tmp_path / "run"
    d.mkdir()
    for f in ("frames.jsonl", "trajectory.tum", "stats.json", "output.mcap"):
        (d / f).write_bytes((moving_mover / f).read_bytes())
    (d / "report").mkdir()
    (d / "report" / "nees.png").write_bytes(b"stale")
    write_report(d)
    page = (d / "report.html").read_text()
    assert "covariance consistency (NEES)" in page and "no ground truth" in page
    assert not (d / "report" / "nees.png").exists()
    assert len(spans(load_run(d))) >= 1  # the initialising frame
