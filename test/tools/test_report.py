"""Tests of epi_vo.tools.report: the plot data on synthetic run directories with known answers, a report of a
real replay, and the report rendered by a real headless browser."""

from __future__ import annotations

import base64
import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from epi_vo.cli import main
from epi_vo.core.config import VoConfig
from epi_vo.core.errors import ReportError
from epi_vo.io import tum
from epi_vo.io.params import load_config
from epi_vo.tools.evaluation import evaluate_trajectory
from epi_vo.tools.replay import run_replay
from epi_vo.tools.report import write_report
from epi_vo.tools.report_data import (
    AlignmentKind,
    RunScale,
    Span,
    error_series,
    gt_alignment,
    gt_in_estimate_frame,
    load_run,
    reason_groups,
    run_figures,
    run_scale,
    scale_series,
    spans,
    timeline,
)
from epi_vo.tools.report_views import trajectory_views

REPO = Path(__file__).resolve().parents[2]

# ==================================================================================================
# Synthetic run directories
# ==================================================================================================

N_FRAMES = 44
RATE_HZ = 15.0
STAMP0 = 1000.0
ROTATION_ONLY_REASON = ("pure rotation: homography explains the motion (RH 0.50, parallax 0.0{k} deg, rotation "
                        "{k}.5 deg); translation not observable, position held")
# Frame index -> (state, reason). Frames not listed are tracking with no reason.
STATES: dict[int, tuple[str, str]] = {
    0: ("initializing", "first frame: reference keyframe set"),
    1: ("initializing", "low parallax (0.40 deg < 0.5): waiting for baseline, position held"),
    **{i: ("rotation_only", ROTATION_ONLY_REASON.format(k=i - 14)) for i in range(15, 20)},
    **{i: ("lost", "too few inliers (12 < 25): no pose") for i in range(20, 23)},
    23: ("initializing", "tracking lost: restarting from the held pose"),
    24: ("initializing", "low parallax (0.21 deg < 0.5): waiting for baseline, position held"),
    30: ("tracking", "planar or low-parallax view (RH 0.46): pose from map points"),  # a reason, still tracking
    42: ("rotation_only", ROTATION_ONLY_REASON.format(k=7)),
    43: ("rotation_only", ROTATION_ONLY_REASON.format(k=8)),
}
EXPECTED_SPANS = [
    ("initializing", 0, 1, (STATES[0][1], STATES[1][1])),
    ("rotation_only", 15, 19, tuple(ROTATION_ONLY_REASON.format(k=k) for k in range(1, 6))),
    ("lost", 20, 22, ("too few inliers (12 < 25): no pose",)),
    ("initializing", 23, 24, (STATES[23][1], STATES[24][1])),
    ("rotation_only", 42, 43, (STATES[42][1], STATES[43][1])),
]
KEYFRAMES = (0, 2, 8, 14, 25, 31, 37)
OFFSET_FRAMES = (5, 12, 27, 33, 38)  # ground truth displaced here (all have a pose)

# Known Sim(3) from estimate to ground truth: p_gt = S * R @ p_est + t.
SIM3_SCALE = 2.5
SIM3_R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
SIM3_T = np.array([1.0, -2.0, 3.0])
OFFSET_DIR = np.array([0.6, 0.0, 0.8])  # unit, ground-truth frame


def _state(i: int) -> tuple[str, str]:
    return STATES.get(i, ("tracking", ""))


def _stamp(i: int) -> float:
    return STAMP0 + i / RATE_HZ


def _yaw(i: int) -> float:
    """Camera rotation about the optical y axis (rad): R_w_c = Ry(yaw)."""
    return 0.03 * i


def _record(i: int) -> dict:
    """A frame record with values that are simple functions of i (None where a record has None)."""
    state, reason = _state(i)
    lost = state == "lost"
    kf = i in KEYFRAMES
    rh = None if lost else 0.01 * i
    return {
        "index": i, "stamp": _stamp(i), "stamp_ns": round(_stamp(i) * 1e9), "state": state, "has_pose": not lost,
        "is_keyframe": kf, "model": "none" if lost else ("H" if 0.01 * i > 0.3 else "E"), "rh": rh,
        "n_features": 200, "n_tracked": 190 - i, "n_inliers": 0 if lost else 150 - i,
        "inlier_ratio": None if lost else (150 - i) / (190 - i), "median_parallax_deg": None if lost else 0.1 * i,
        "n_triangulated": 40 + i if kf else 0, "positive_depth_ratio": 0.9 if kf else None,
        "median_reproj_err_px": 0.01 * i if kf else None, "relative_scale": None, "n_keyframes": 1,
        "position": [0.0, 0.0, 0.0], "quat_xyzw": [0.0, 0.0, 0.0, 1.0], "covariance_diagonal": [1.0] * 6,
        "n_points": 0, "timings_ms": {"frontend": 10.0 + i, "models": 2.0, "pose": 1.0 + 0.5 * i, "mapping": 0.25,
                                      "total": 13.25 + 1.5 * i}, "reason": reason,
    }


def _estimate(moving: bool = True) -> tuple[NDArray[np.int64], NDArray, NDArray, NDArray]:
    """Frames with a pose, their stamps, positions (a 3-D curve, or all zero) and quaternions (Ry(yaw))."""
    frames = np.array([i for i in range(N_FRAMES) if _state(i)[0] != "lost"])
    s = frames.astype(float)
    pos = np.column_stack([np.sin(0.2 * s), 0.3 * np.cos(0.3 * s), 0.5 * s]) if moving else np.zeros((len(s), 3))
    quats = Rotation.from_rotvec(np.outer([_yaw(i) for i in frames], [0.0, 1.0, 0.0])).as_quat()  # xyzw
    return frames, np.array([_stamp(i) for i in frames]), pos, quats


def _offsets(pos: NDArray, frames: NDArray) -> NDArray:
    """(len(frames),) signed offset magnitudes a, non-zero only at OFFSET_FRAMES, with sum(a) = 0 and
    sum(a p) = 0: then Umeyama's means and cross-covariance are those of the exact Sim(3), so the fitted
    alignment is exactly the known one and the ATE at frame k is exactly |a_k|."""
    rows = [int(np.flatnonzero(frames == k)[0]) for k in OFFSET_FRAMES]
    A = np.vstack([np.ones(len(rows)), pos[rows].T])  # (4, 5)
    null = np.linalg.svd(A)[2][-1]
    a = np.zeros(len(frames))
    a[rows] = 0.3 * null / np.abs(null).max()
    return a


@dataclass(frozen=True)
class Synthetic:
    directory: Path
    frames: NDArray[np.int64]  # frames with a pose
    pos: NDArray  # (N, 3) estimate
    quats: NDArray  # (N, 4) xyzw
    offsets: NDArray  # (N,) signed offset along OFFSET_DIR, ground-truth units


def make_run(directory: Path, *, gt: bool = True, moving: bool = True) -> Synthetic:
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "frames.jsonl").write_text("".join(json.dumps(_record(i)) + "\n" for i in range(N_FRAMES)))
    frames, stamps, pos, quats = _estimate(moving)
    tum.write_tum(directory / "trajectory.tum", stamps, pos, quats)
    offsets = _offsets(pos, frames) if (gt and moving) else np.zeros(len(frames))
    if gt:
        gt_pos = SIM3_SCALE * pos @ SIM3_R.T + SIM3_T + np.outer(offsets, OFFSET_DIR)
        gt_quats = (Rotation.from_matrix(SIM3_R) * Rotation.from_quat(quats)).as_quat()  # R_gt = R @ R_est
        tum.write_tum(directory / "groundtruth.tum", stamps, gt_pos, gt_quats)
    return Synthetic(directory, frames, pos, quats, offsets)


@pytest.fixture
def synthetic(tmp_path: Path) -> Synthetic:
    return make_run(tmp_path / "run")


# ==================================================================================================
# Data: load_run, spans, timeline, views, errors
# ==================================================================================================


def test_load_run_reads_every_file(synthetic: Synthetic) -> None:
    (synthetic.directory / "stats.json").write_text(json.dumps({"bag": "x", "params": {"rh_threshold": 0.3}}))
    run = load_run(synthetic.directory)
    assert len(run.records) == N_FRAMES
    np.testing.assert_array_equal(run.est_frame_index, synthetic.frames)
    np.testing.assert_allclose(run.est.positions_xyz, synthetic.pos)
    assert run.gt is not None and run.gt.positions_xyz.shape == synthetic.pos.shape
    assert run.stats is not None and run.stats["bag"] == "x"
    assert timeline(run).rh_threshold == 0.3 and timeline(run).rh_threshold_source == "stats.json"


def test_spans_are_found_exactly(synthetic: Synthetic) -> None:
    found = spans(load_run(synthetic.directory))
    assert [(s.state, s.start_index, s.end_index, s.reasons) for s in found] == EXPECTED_SPANS
    for s in found:
        assert s.n_frames == s.end_index - s.start_index + 1
        assert s.start_stamp_s == pytest.approx(_stamp(s.start_index))
        assert s.end_stamp_s == pytest.approx(_stamp(s.end_index))


def test_no_spans_when_every_frame_tracks(tmp_path: Path) -> None:
    d = tmp_path / "run"
    d.mkdir()
    recs = [dict(_record(i), state="tracking", reason="", has_pose=True) for i in range(2, 8)]
    (d / "frames.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    (d / "trajectory.tum").write_text("")
    assert spans(load_run(d)) == []


def test_reason_groups_collapse_numbers_only() -> None:
    groups = reason_groups(EXPECTED_SPANS[1][3] + ("homography decomposition ambiguous",))
    assert groups == [(ROTATION_ONLY_REASON.format(k=1), 5), ("homography decomposition ambiguous", 1)]


def test_timeline_series_equal_the_records(synthetic: Synthetic) -> None:
    tl = timeline(load_run(synthetic.directory))
    recs = [_record(i) for i in range(N_FRAMES)]

    def col(key: str) -> NDArray:
        return np.array([math.nan if r[key] is None else float(r[key]) for r in recs])

    np.testing.assert_array_equal(tl.frame_index, np.arange(N_FRAMES))
    np.testing.assert_allclose(tl.stamp_s, col("stamp"))
    for key in ("rh", "n_features", "n_tracked", "n_inliers", "inlier_ratio", "median_parallax_deg",
                "n_triangulated", "positive_depth_ratio", "median_reproj_err_px"):
        np.testing.assert_array_equal(getattr(tl, key), col(key), err_msg=key)  # NaN where the record has None
    assert tl.state == tuple(r["state"] for r in recs)
    assert tl.model == tuple(r["model"] for r in recs)
    np.testing.assert_array_equal(tl.keyframe_index, KEYFRAMES)
    assert list(tl.stage_ms) == ["frontend", "models", "pose", "mapping"]
    for stage, values in tl.stage_ms.items():
        np.testing.assert_array_equal(values, [r["timings_ms"][stage] for r in recs])
    np.testing.assert_array_equal(tl.total_ms, [r["timings_ms"]["total"] for r in recs])
    assert tl.rh_threshold == 0.45 and tl.rh_threshold_source == "defaults"  # no stats.json: VoConfig default


def test_views_use_optical_frame_axes(synthetic: Synthetic) -> None:
    views = trajectory_views(load_run(synthetic.directory))
    p = synthetic.pos
    np.testing.assert_allclose(views.top.est, np.column_stack([p[:, 0], p[:, 2]]))  # x right, z forward
    np.testing.assert_allclose(views.side.est, np.column_stack([p[:, 2], -p[:, 1]]))  # z forward, -y up
    kf_rows = np.isin(synthetic.frames, KEYFRAMES)
    np.testing.assert_allclose(views.top.keyframes, views.top.est[kf_rows])
    np.testing.assert_array_equal(views.keyframe_index, KEYFRAMES)
    # R_w_c = Ry(yaw): the optical axis is (sin yaw, 0, cos yaw); it points straight ahead in frame 0.
    yaw = np.array([_yaw(i) for i in synthetic.frames])
    np.testing.assert_allclose(views.top.heading, np.column_stack([np.sin(yaw), np.cos(yaw)]), atol=1e-9)
    np.testing.assert_allclose(views.side.heading, np.column_stack([np.cos(yaw), np.zeros_like(yaw)]), atol=1e-9)
    assert "x" in views.top.xlabel and "z" in views.top.ylabel
    assert "z" in views.side.xlabel and "-y" in views.side.ylabel


def test_aligned_gt_equals_estimate_where_no_offset(synthetic: Synthetic) -> None:
    run = load_run(synthetic.directory)
    alignment = gt_alignment(run)
    assert alignment is not None and alignment.kind is AlignmentKind.SIM3
    assert alignment.scale == pytest.approx(SIM3_SCALE, rel=1e-9)
    assert alignment.matched_poses == len(synthetic.frames)
    gt_w = gt_in_estimate_frame(run, alignment)
    clean = synthetic.offsets == 0.0
    np.testing.assert_allclose(gt_w[clean], synthetic.pos[clean], atol=1e-9)
    # Where the ground truth was displaced by a d, it is displaced by R^T d / s in the estimate's frame.
    expected = synthetic.pos + np.outer(synthetic.offsets, SIM3_R.T @ OFFSET_DIR) / SIM3_SCALE
    np.testing.assert_allclose(gt_w, expected, atol=1e-9)
    views = trajectory_views(run)
    np.testing.assert_allclose(views.top.gt[clean], views.top.est[clean], atol=1e-9)
    np.testing.assert_allclose(views.side.gt[clean], views.side.est[clean], atol=1e-9)


def test_ate_over_time_is_the_known_offsets(synthetic: Synthetic) -> None:
    run = load_run(synthetic.directory)
    err = error_series(run)
    assert err is not None
    np.testing.assert_array_equal(err.frame_index, synthetic.frames)  # lost frames have no pose, no error
    assert np.count_nonzero(synthetic.offsets) == len(OFFSET_FRAMES)
    np.testing.assert_allclose(err.ate, np.abs(synthetic.offsets), atol=1e-9)
    # RPE between consecutive matched poses: rotations are exact; translation error |d_j - d_i|.
    np.testing.assert_array_equal(err.rpe_frame_index, synthetic.frames[1:])
    np.testing.assert_allclose(err.rpe_rot_deg, 0.0, atol=1e-4)
    np.testing.assert_allclose(err.rpe_trans, np.abs(np.diff(synthetic.offsets)), atol=1e-9)
    # The same numbers as the replay's metrics (epi_vo.tools.evaluation).
    m = evaluate_trajectory(run.est, run.gt)
    assert err.ate_rmse == pytest.approx(m.ate_rmse, rel=1e-9)
    assert float(np.sqrt(np.mean(err.rpe_trans**2))) == pytest.approx(m.rpe_trans_rmse, rel=1e-9)


def test_stationary_estimate_has_no_sim3(tmp_path: Path) -> None:
    syn = make_run(tmp_path / "run", moving=False)
    run = load_run(syn.directory)
    err = error_series(run)
    assert err is not None and err.alignment.kind is AlignmentKind.ORIGIN
    assert np.isnan(err.ate).all() and np.isnan(err.rpe_trans).all()
    np.testing.assert_allclose(err.rpe_rot_deg, 0.0, atol=1e-4)  # rotation needs no alignment
    np.testing.assert_allclose(gt_in_estimate_frame(run, err.alignment), 0.0, atol=1e-12)


def test_without_ground_truth(tmp_path: Path) -> None:
    syn = make_run(tmp_path / "run", gt=False)
    run = load_run(syn.directory)
    assert run.gt is None and gt_alignment(run) is None and error_series(run) is None
    views = trajectory_views(run)
    assert views.top.gt.shape == (0, 2) and views.alignment is None
    out = write_report(syn.directory)
    page = out.read_text()
    assert len(_data_pngs(page)) == 2
    assert not (syn.directory / "report" / "errors.png").exists()
    assert "no ground truth" in page


def test_unusable_ground_truth_is_a_note(tmp_path: Path) -> None:
    syn = make_run(tmp_path / "run")
    tum.write_tum(syn.directory / "groundtruth.tum", [1.0, 2.0, 3.0], np.zeros((3, 3)), [[0, 0, 0, 1.0]] * 3)
    run = load_run(syn.directory)
    alignment = gt_alignment(run)
    assert alignment is not None and alignment.kind is AlignmentKind.NONE and "not usable" in alignment.note
    assert error_series(run) is None
    assert "not usable" in write_report(syn.directory).read_text()


# --- units and scale ---------------------------------------------------------------------------------

METRIC_FROM = 5  # synthetic metric run: metric scale established at this frame


def _metric_record(i: int) -> dict:
    """A frame record of a ground-plane run: VO units before METRIC_FROM, metres from it; floor from frame 3."""
    metric = i >= METRIC_FROM
    floor = i >= 3
    return dict(_record(i), units="m" if metric else "vo", scale_source="ground_plane", metric_scale=metric,
                scale=0.5 + 0.001 * i if metric else 1.0, scale_rel_std=0.02 if metric else None,
                floor_pitch_deg=10.0 + 0.1 * i if floor else None, floor_roll_deg=-1.0 if floor else None,
                scale_reason="" if metric else "1 of 2 scale measurements needed to establish metric scale: VO units")


def _labels(directory: Path) -> set[str]:
    views = trajectory_views(load_run(directory))
    return {views.top.xlabel, views.top.ylabel, views.side.xlabel, views.side.ylabel}


def _summary_row(page: str, name: str) -> str:
    m = re.search(rf"<tr><th>{re.escape(name)}</th><td>(.*?)</td></tr>", page)
    assert m is not None, name
    return m.group(1)


def test_older_output_is_in_vo_units(synthetic: Synthetic) -> None:
    run = load_run(synthetic.directory)  # records and no stats.json without any scale key
    assert (run_scale(run).source, run_scale(run).units, run_scale(run).metric_from_frame) == ("none", "vo", None)
    assert scale_series(run) is None
    assert _labels(synthetic.directory) == {"x (right) [VO units]", "z (forward) [VO units]", "-y (up) [VO units]"}
    page = write_report(synthetic.directory).read_text()
    assert _summary_row(page, "path length (estimate)") == f"{run_figures(run).path_length:.3f} VO units"
    assert _summary_row(page, "scale source") == "none" and _summary_row(page, "metric from frame") == "-"
    assert "the run is in VO units, no scale plot" in page and len(_data_pngs(page)) == 3


def test_metric_records_give_metres_and_the_scale_panel(synthetic: Synthetic) -> None:
    path = synthetic.directory / "frames.jsonl"
    path.write_text("".join(json.dumps(_metric_record(i)) + "\n" for i in range(N_FRAMES)))
    run = load_run(synthetic.directory)  # no stats.json: units and source from the records
    assert run_scale(run) == RunScale("ground_plane", "m", METRIC_FROM)
    sc = scale_series(run)
    assert sc is not None and sc.source == "ground_plane" and sc.has_floor
    np.testing.assert_array_equal(sc.frame_index, np.arange(N_FRAMES))
    i = np.arange(N_FRAMES)
    expected = np.where(i >= METRIC_FROM, 0.5 + 0.001 * i, np.nan)  # the 1.0 before metric is no measurement
    np.testing.assert_allclose(sc.scale, expected)
    np.testing.assert_allclose(sc.lower, expected * 0.98)
    np.testing.assert_allclose(sc.upper, expected * 1.02)
    np.testing.assert_allclose(sc.floor_pitch_deg, np.where(i >= 3, 10.0 + 0.1 * i, np.nan))
    np.testing.assert_allclose(sc.floor_roll_deg, np.where(i >= 3, -1.0, np.nan))
    assert _labels(synthetic.directory) == {"x (right) [m]", "z (forward) [m]", "-y (up) [m]"}
    page = write_report(synthetic.directory).read_text()
    assert _summary_row(page, "path length (estimate)") == f"{run_figures(run).path_length:.3f} m"
    assert _summary_row(page, "units") == "m (metric scale)"
    assert _summary_row(page, "metric from frame") == str(METRIC_FROM)
    # The poses held before metric scale are no positions in metres: left out of the metrics, counted.
    held = sum(1 for i in range(METRIC_FROM) if _record(i)["has_pose"])
    figs = run_figures(run)
    assert held > 0 and figs.metrics is not None
    assert figs.metrics.matched_poses == run.est.stamps_s.size - held
    assert _summary_row(page, "poses evaluated") == (f"{held} pose(s) held before metric scale was established "
                                                     "are not in the metrics")
    assert '<figure id="scale">' in page and "no scale plot" not in page and len(_data_pngs(page)) == 4
    scale_png = synthetic.directory / "report" / "scale.png"
    img = cv2.imread(str(scale_png), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[:2] == (770, 1300)  # two panels: scale and the floor's pitch/roll
    # Rewritten as a VO-units run: the stale scale plot goes.
    path.write_text("".join(json.dumps(_record(i)) + "\n" for i in range(N_FRAMES)))
    page = write_report(synthetic.directory).read_text()
    assert not scale_png.exists() and '<figure id="scale">' not in page


# --- bad input ----------------------------------------------------------------------------------------


def test_missing_directory(tmp_path: Path) -> None:
    with pytest.raises(ReportError, match="no such directory"):
        load_run(tmp_path / "nope")


def test_not_a_directory(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(ReportError, match="not a directory"):
        load_run(tmp_path / "f")


def test_not_a_replay_output(tmp_path: Path) -> None:
    with pytest.raises(ReportError, match=r"frames\.jsonl is missing"):
        load_run(tmp_path)


def test_malformed_record_names_the_line(synthetic: Synthetic) -> None:
    path = synthetic.directory / "frames.jsonl"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], "{not json", *lines[2:]]) + "\n")
    with pytest.raises(ReportError, match=r"frames.jsonl:2: not JSON"):
        load_run(synthetic.directory)
    rec = _record(1)
    del rec["state"], rec["timings_ms"]
    path.write_text("\n".join([lines[0], json.dumps(rec)]) + "\n")
    with pytest.raises(ReportError, match=r"frames.jsonl:2: frame record without state, timings_ms"):
        load_run(synthetic.directory)


def test_pose_without_record(synthetic: Synthetic) -> None:
    with (synthetic.directory / "trajectory.tum").open("a") as f:
        f.write("2000.0 0 0 0 0 0 0 1\n")
    with pytest.raises(ReportError, match=r"2000\.000000000 s has no frame record"):
        load_run(synthetic.directory)


def test_cli_reports_a_bad_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("epi-vo: error: ") and "no such directory" in err and err.count("\n") == 1


def test_cli_prints_the_report_path(synthetic: Synthetic, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(synthetic.directory)]) == 0
    assert capsys.readouterr().out.strip() == str(synthetic.directory / "report.html")


# ==================================================================================================
# A real replay
# ==================================================================================================


def _data_pngs(page: str) -> list[str]:
    return re.findall(r'<img [^>]*src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)


@pytest.fixture(scope="module")
def rotation_report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pure_rotation")
    run_replay(REPO / "bags" / "pure_rotation" / "bag", out)
    path = write_report(out)
    assert path == out / "report.html"
    return path


def test_report_of_a_real_replay(rotation_report: Path) -> None:
    out = rotation_report.parent
    for name in ("trajectory.png", "timeline.png", "errors.png"):
        assert (out / "report" / name).stat().st_size > 10_000, name
    page = rotation_report.read_text()
    pngs = _data_pngs(page)
    assert len(pngs) == 3
    sizes = []
    for data in pngs:
        img = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None
        sizes.append(img.shape[:2])
    assert all(h >= 500 and w >= 1000 for h, w in sizes), sizes
    assert sizes[1][0] > sizes[0][0]  # the timeline is the tall one
    # Self-contained: no resource outside the file.
    assert not re.search(r'(src|href)="(?!data:|#)', page)
    assert "<link" not in page and "@import" not in page and "url(" not in page
    # The span table: the pure-rotation span with its reason.
    table = page[page.index('<table class="spans">'):]
    table = table[:table.index("</table>")]
    assert "rotation_only" in table and "pure rotation: homography explains the motion" in table
    assert "initializing" in table and "first frame: reference keyframe set" in table
    stats = json.loads((out / "stats.json").read_text())
    assert stats["bag"] in page and stats["image_topic"] in page
    assert "from <code>stats.json</code>" in page and "<code>max_features</code>" in page  # the run's parameters


def test_vo_units_replay_says_vo_units(rotation_report: Path) -> None:
    """A default-config replay (scale_source none): VO units on every length, no scale plot."""
    out = rotation_report.parent
    stats = json.loads((out / "stats.json").read_text())
    assert (stats["scale_source"], stats["units"], stats["metric_from_frame"]) == ("none", "vo", None)
    assert _labels(out) == {"x (right) [VO units]", "z (forward) [VO units]", "-y (up) [VO units]"}
    page = rotation_report.read_text()
    assert _summary_row(page, "path length (estimate)") == f"{stats['path_length']:.3f} VO units"
    assert _summary_row(page, "units") == "VO units (no metric scale)"
    assert "the run is in VO units, no scale plot" in page
    assert not (out / "report" / "scale.png").exists() and '<figure id="scale">' not in page


@pytest.fixture(scope="module")
def ground_plane_report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A replay of ground_robot with the floor as scale source (params as a user's YAML would give them)."""
    tmp = tmp_path_factory.mktemp("ground_plane")
    params = tmp / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    scale_source: ground_plane\n    camera_height_m: 0.45\n")
    out = tmp / "out"
    cfg = dataclasses.replace(VoConfig(), scale_source="ground_plane", camera_height_m=0.45)
    assert load_config(params) == cfg
    run_replay(REPO / "bags" / "ground_robot" / "bag", out, cfg)
    return write_report(out)


def test_metric_replay_report(ground_plane_report: Path) -> None:
    out = ground_plane_report.parent
    stats = json.loads((out / "stats.json").read_text())
    assert (stats["scale_source"], stats["units"]) == ("ground_plane", "m")
    assert isinstance(stats["metric_from_frame"], int)
    run = load_run(out)
    assert _labels(out) == {"x (right) [m]", "z (forward) [m]", "-y (up) [m]"}
    page = ground_plane_report.read_text()
    assert _summary_row(page, "path length (estimate)") == f"{stats['path_length']:.3f} m"
    assert _summary_row(page, "scale source") == "ground_plane"
    assert _summary_row(page, "units") == "m (metric scale)"
    assert _summary_row(page, "metric from frame") == str(stats["metric_from_frame"])
    assert "[VO units]" not in page and "no scale plot" not in page
    # The scale panel: embedded, and its data are the records' (metres per VO unit, 1-sigma band, floor).
    # trajectory, timeline, errors, scale and the covariance consistency (NEES)
    assert '<figure id="scale">' in page and '<figure id="nees">' in page and len(_data_pngs(page)) == 5
    assert (out / "report" / "scale.png").stat().st_size > 10_000
    sc = scale_series(run)
    assert sc is not None and sc.has_floor
    recs = run.records
    first = stats["metric_from_frame"]
    assert [bool(r["metric_scale"]) for r in recs] == [r["index"] >= first for r in recs]
    metric = np.array([r["index"] >= first for r in recs])
    np.testing.assert_allclose(sc.scale[metric], [r["scale"] for r in recs if r["metric_scale"]])
    assert np.isnan(sc.scale[~metric]).all()
    rel = np.array([r["scale_rel_std"] for r in recs if r["metric_scale"]], dtype=float)
    np.testing.assert_allclose(sc.upper[metric] - sc.lower[metric], 2 * sc.scale[metric] * rel)
    assert np.all((rel > 0) & (rel < 0.1))
    np.testing.assert_allclose(np.nan_to_num(sc.floor_pitch_deg, nan=-999.0),
                               [-999.0 if r["floor_pitch_deg"] is None else r["floor_pitch_deg"] for r in recs])


# ==================================================================================================
# A real browser
# ==================================================================================================

CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars", "--run-all-compositor-stages-before-draw", "--virtual-time-budget=5000")


@pytest.fixture(scope="module")
def chromium() -> str:
    exe = shutil.which("chromium")
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is not installed; CI must provide it (.ci/run installs it)")
        pytest.skip("chromium is not installed (apt-get install chromium)")
    return exe


def _chromium(exe: str, tmp: Path, page: Path, *args: str) -> subprocess.CompletedProcess[str]:
    profile = tmp / f"profile-{len(list(tmp.glob('profile-*')))}"
    proc = subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args, page.as_uri()],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


def _coloured_fraction(png: Path) -> float:
    """Share of clearly coloured pixels (HSV saturation > 60): plot lines, fills, shading; not text."""
    img = cv2.imread(str(png), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[:2] == (2400, 1280), None if img is None else img.shape
    sat = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)[:, :, 1]
    return float(np.count_nonzero(sat > 60)) / sat.size


def test_browser_renders_the_report(chromium: str, rotation_report: Path, tmp_path: Path) -> None:
    # The page's own script counts the images the browser decoded.
    dom = _chromium(chromium, tmp_path, rotation_report, "--dump-dom").stdout
    body = re.search(r"<body[^>]*>", dom)
    assert body is not None, dom[:500]
    assert 'data-images="3"' in body.group(0) and 'data-loaded="3"' in body.group(0), body.group(0)

    shot = tmp_path / "report.png"
    _chromium(chromium, tmp_path, rotation_report, f"--screenshot={shot}", "--window-size=1280,2400")
    # The same page with the images blanked: what colour the page has without its plots.
    blank_page = tmp_path / "blank.html"
    blank_page.write_text(re.sub(r'src="data:image/png;base64,[^"]*"', 'src="data:,"', rotation_report.read_text()))
    blank_shot = tmp_path / "blank.png"
    _chromium(chromium, tmp_path, blank_page, f"--screenshot={blank_shot}", "--window-size=1280,2400")

    gray = cv2.imread(str(shot), cv2.IMREAD_GRAYSCALE)
    assert gray is not None and float(gray.std()) > 10.0  # not a blank page
    with_plots, without = _coloured_fraction(shot), _coloured_fraction(blank_shot)
    assert with_plots > 0.05, with_plots  # the plots' colours fill a large part of the screen
    assert with_plots > 10 * without, (with_plots, without)


def test_span_type_is_immutable() -> None:
    s = Span("lost", 1, 2, 0.0, 0.1, 2, ("r",))
    with pytest.raises(AttributeError):
        s.state = "tracking"  # type: ignore[misc]
    assert s.duration_s == pytest.approx(0.1)
