"""The data of a replay report: pure functions of the files in an ``epi-vo replay`` output directory.

- :func:`load_run` reads ``frames.jsonl``, ``trajectory.tum``, ``stats.json`` and ``groundtruth.tum``;
- :func:`gt_alignment` aligns the ground truth onto the estimate (``epi_vo.tools.report_views`` draws both);
- :func:`timeline` gives the per-frame series of the frame records;
- :func:`spans` finds the runs of frames that are not ``tracking``, with their reasons;
- :func:`error_series` gives ATE over time and RPE per frame, computed with evo;
- :func:`run_scale` gives the run's scale source and units, :func:`scale_series` the scale per frame.

Frames. The estimate holds camera poses T_w_c, w = the first camera's optical frame (x right,
y down, z forward), in the run's units: metres when a metric scale source (``scale_source``
ground_plane or wheel_odometry) was established, VO units otherwise (``stats.json`` ``units``; an
output directory older than the scale sources has no such key and is in VO units). The ground truth
is brought into the estimate's frame: evo's Umeyama fit p_gt ~= s R p_est + t
(the one :mod:`epi_vo.tools.evaluation` uses for ATE) is inverted, p = R^T (p_gt - t) / s. When that
fit is degenerate (an estimate that never moves, as under pure rotation, or moves along one line) the
ground truth is only origin-aligned: its first matched pose is put on the estimate's, in its own
units, since there is no scale to recover.
"""

from __future__ import annotations

import collections
import copy
import enum
import json
import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from evo.core import geometry, sync
from evo.core.metrics import APE, RPE, PoseRelation, Unit
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from epi_vo.core.config import config_fields
from epi_vo.core.errors import EpiVoError, ReportError
from epi_vo.core.frame import Model, TrackingState
from epi_vo.core.scale import Units
from epi_vo.io import tum
from epi_vo.io.trajectory import StampedPoses
from epi_vo.tools.evaluation import (
    MIN_MATCHED_POSES,
    TrajectoryMetrics,
    evaluate_trajectory,
    metric_poses,
    to_evo_trajectory,
)
from epi_vo.tools.json_check import fields_problem
from epi_vo.tools.replay import stats_problem
from epi_vo.tools.replay_outputs import PathLength

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

REPORT_HTML = "report.html"
REPORT_PNG_DIR = "report"

# Keys every frame record must have for the report (FrameResult.to_record writes more).
_RECORD_KEYS = ("index", "stamp", "state", "has_pose", "is_keyframe", "model", "rh", "n_features", "n_tracked",
                "n_inliers", "inlier_ratio", "median_parallax_deg", "n_triangulated", "positive_depth_ratio",
                "median_reproj_err_px", "timings_ms", "reason")
_OPT = float | None  # a measurement written as null when it was not finite
# The type of every key FrameResult.to_record writes (checked where present: older records lack some).
RECORD_TYPES: dict[str, Any] = {
    "index": int, "stamp": float, "stamp_ns": int, "state": TrackingState, "has_pose": bool, "is_keyframe": bool,
    "model": Model, "rh": _OPT, "n_features": int, "n_tracked": int, "n_inliers": int, "inlier_ratio": _OPT,
    "median_parallax_deg": _OPT, "n_triangulated": int, "positive_depth_ratio": _OPT,
    "median_reproj_err_px": _OPT, "relative_scale": _OPT, "n_keyframes": int, "position": list[float],
    "quat_xyzw": list[float], "covariance_diagonal": list[float], "n_points": int, "timings_ms": dict[str, float],
    "reason": str, "skipped": bool, "rejected": bool, "units": str, "scale_source": str, "metric_scale": bool,
    "scale": _OPT, "scale_rel_std": _OPT, "floor_pitch_deg": _OPT, "floor_roll_deg": _OPT, "scale_reason": str,
    "static_score": _OPT, "n_moving": int, "moving_fraction": _OPT, "moving_region": list[int] | None,
    "focal_ratio": _OPT, "track_noise_px": _OPT, "n_refined": int | None, "window_correction": _OPT,
    "window_correction_deg": _OPT, "wheel_messages": dict[str, int] | None,
}

# A trajectory.tum row belongs to the frame record with the nearest stamp within this. TUM stamps carry
# 9 decimals, but float64 seconds near the Unix epoch resolve only ~0.24 us; 0.1 ms is still far below
# any camera frame interval.
_STAMP_MATCH_TOL_S = 1e-4
# Ground-truth pairing, as evaluate_trajectory's default max_time_diff (same poses, same metrics).
_GT_MAX_TIME_DIFF_S = 0.01

NO_SIM3 = "no Sim(3) alignment exists (the estimate does not move, or moves along a line)"

TRACKING = "tracking"
# Presentation only: one colour per tracking state (span shading in the plots, chips in the table).
STATE_COLOURS = {"initializing": "#9ecae1", "rotation_only": "#fdae6b", "static": "#bcbddc", "lost": "#fb8072",
                 TRACKING: "#b8e186"}
MODEL_COLOURS = {"E": "#1f77b4", "H": "#ff7f0e", "none": "#7f7f7f"}
EST_COLOUR = "#1f77b4"
GT_COLOUR = "#d62728"


# ==================================================================================================
# Data
# ==================================================================================================


@dataclass(frozen=True)
class Run:
    """The files of one replay output directory."""

    directory: Path
    records: tuple[dict[str, Any], ...]  # frames.jsonl, one per input frame, in file order
    est: StampedPoses  # trajectory.tum: T_w_c of the frames with a pose (the run's units, see run_scale)
    est_frame_index: NDArray[np.int64]  # (N,) record "index" of each trajectory row
    gt: StampedPoses | None  # groundtruth.tum (ground-truth units), None when the run had none
    stats: dict[str, Any] | None  # stats.json, None when absent


def load_run(directory: str | Path) -> Run:
    """Read a replay output directory (see :mod:`epi_vo.tools.replay` for its files).

    Raises:
        ReportError: the directory is missing, lacks frames.jsonl or trajectory.tum, or a file is
            malformed (the message names the file and, for frames.jsonl, the line).
    """
    d = Path(directory)
    if not d.exists():
        msg = f"{d}: no such directory"
        raise ReportError(msg)
    if not d.is_dir():
        msg = f"{d}: not a directory"
        raise ReportError(msg)
    frames_path = d / "frames.jsonl"
    if not frames_path.is_file():
        msg = f"{d} is not an 'epi-vo replay' output directory: frames.jsonl is missing"
        raise ReportError(msg)
    records = _read_records(frames_path)
    if not (d / "trajectory.tum").is_file():
        msg = f"{d} is not an 'epi-vo replay' output directory: trajectory.tum is missing"
        raise ReportError(msg)
    est = _read_tum(d / "trajectory.tum")
    est_frame_index = _frame_index_of_stamps(records, est.stamps_s, d / "trajectory.tum")
    gt = _read_tum(d / "groundtruth.tum") if (d / "groundtruth.tum").is_file() else None
    stats = None
    if (d / "stats.json").is_file():
        try:
            stats = json.loads((d / "stats.json").read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            msg = f"{d / 'stats.json'}: cannot read: {exc}"
            raise ReportError(msg) from None
        if not isinstance(stats, dict):
            msg = f"{d / 'stats.json'}: expected a JSON object"
            raise ReportError(msg)
        problem = stats_problem(stats, str(d / "stats.json"))
        if problem:
            raise ReportError(problem)
    return Run(d, records, est, est_frame_index, gt, stats)


def _read_records(path: Path) -> tuple[dict[str, Any], ...]:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        msg = f"{path}: cannot read: {exc}"
        raise ReportError(msg) from None
    records = []
    for line_number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            msg = f"{path}:{line_number}: not JSON ({exc.msg})"
            raise ReportError(msg) from None
        if not isinstance(rec, dict):
            msg = f"{path}:{line_number}: expected a JSON object (a frame record)"
            raise ReportError(msg)
        missing = [k for k in _RECORD_KEYS if k not in rec]
        if missing:
            msg = f"{path}:{line_number}: frame record without {', '.join(missing)}"
            raise ReportError(msg)
        problem = fields_problem(rec, RECORD_TYPES, f"{path}:{line_number}")
        if problem:
            raise ReportError(problem)
        records.append(rec)
    if not records:
        msg = f"{path}: no frame records"
        raise ReportError(msg)
    return tuple(records)


def _read_tum(path: Path) -> StampedPoses:
    try:
        return tum.read_tum(path)
    except EpiVoError as exc:  # bagio says BagError; here it is a report input
        raise ReportError(str(exc)) from None


def _frame_index_of_stamps(records: Sequence[dict[str, Any]], stamps_s: F64, path: Path) -> NDArray[np.int64]:
    """Record ``index`` of the record nearest in stamp to each of ``stamps_s``; ReportError if none is near."""
    rec_stamps = np.array([float(r["stamp"]) for r in records])
    rec_index = np.array([int(r["index"]) for r in records], dtype=np.int64)
    if stamps_s.size == 0:
        return np.zeros(0, dtype=np.int64)
    nearest = np.abs(stamps_s[:, None] - rec_stamps[None, :]).argmin(axis=1)
    off = np.abs(rec_stamps[nearest] - stamps_s)
    if (off > _STAMP_MATCH_TOL_S).any():
        bad = int(np.argmax(off > _STAMP_MATCH_TOL_S))
        msg = (f"{path}: pose at stamp {stamps_s[bad]:.9f} s has no frame record in frames.jsonl "
               f"(nearest {off[bad]:.3g} s away)")
        raise ReportError(msg)
    return rec_index[nearest]


def run_parameters(run: Run) -> tuple[dict[str, Any], str]:
    """The pipeline parameters of the run and where they come from: ``"stats.json"`` or ``"defaults"``.

    ``stats.json`` is searched for a ``params`` / ``parameters`` / ``config`` object; without one the
    run is described by the built-in defaults (``epi-vo params``).
    """
    for key in ("params", "parameters", "config"):
        value = (run.stats or {}).get(key)
        if isinstance(value, dict) and value:
            return dict(value), "stats.json"
    return {f.name: f.default for f in config_fields()}, "defaults"


# --- ground-truth alignment -----------------------------------------------------------------------


class AlignmentKind(enum.Enum):
    SIM3 = "sim3"  # Umeyama with scale, p_gt ~= s R p_est + t
    ORIGIN = "origin"  # Sim(3) degenerate: first matched GT pose put on the estimate's (SE(3), no scale)
    NONE = "none"  # ground truth present but unusable (note says why)


@dataclass(frozen=True)
class GtAlignment:
    """How the ground truth relates to the estimate."""

    kind: AlignmentKind
    T_gt_est: F64  # (4, 4) similarity taking estimate-frame points into the GT frame (identity for NONE)
    scale: float  # s of p_gt ~= s R p_est + t (estimate -> GT units); NaN unless SIM3
    matched_poses: int  # poses paired by stamp
    note: str  # human-readable description


class _Paired(NamedTuple):
    est: PoseTrajectory3D | None  # stamp-matched estimate, unaligned (None: alignment NONE)
    gt: PoseTrajectory3D | None  # stamp-matched ground truth
    est_aligned: PoseTrajectory3D | None  # est with the Sim(3) applied (GT frame and units); est when not SIM3
    alignment: GtAlignment


def _pair(run: Run) -> _Paired | None:
    """Pair the estimate with the ground truth by stamp and align it, as evaluate_trajectory does."""
    if run.gt is None:
        return None
    try:
        traj_est = to_evo_trajectory(metric_poses(run.est, run.records)[0], "estimated trajectory")
        traj_gt = to_evo_trajectory(run.gt, "ground-truth trajectory")
        traj_gt, traj_est = sync.associate_trajectories(traj_gt, traj_est, max_diff=_GT_MAX_TIME_DIFF_S)
    except (EpiVoError, sync.SyncException) as exc:
        note = f"ground truth not usable: {exc}"
        return _Paired(None, None, None, GtAlignment(AlignmentKind.NONE, np.eye(4), math.nan, 0, note))
    n = traj_est.num_poses
    if n < MIN_MATCHED_POSES:
        note = f"ground truth not usable: only {n} poses matched by stamp within {_GT_MAX_TIME_DIFF_S} s"
        return _Paired(None, None, None, GtAlignment(AlignmentKind.NONE, np.eye(4), math.nan, n, note))
    est_aligned = copy.deepcopy(traj_est)
    try:
        r, t, s = est_aligned.align(traj_gt, correct_scale=True)
    except geometry.GeometryException:
        # Umeyama's covariance has rank < 2: the estimate held its position (pure rotation) or moved along
        # one line, and no unique Sim(3) exists. Put the first GT pose on the first estimate pose so that
        # at least the shapes can be compared.
        T = np.asarray(traj_gt.poses_se3[0]) @ np.linalg.inv(np.asarray(traj_est.poses_se3[0]))
        note = ("Sim(3) alignment degenerate (the estimate does not move, or moves along a line); ground truth "
                "origin-aligned, in its own units")
        return _Paired(traj_est, traj_gt, traj_est, GtAlignment(AlignmentKind.ORIGIN, T, math.nan, n, note))
    T = np.eye(4)
    T[:3, :3] = float(s) * np.asarray(r)
    T[:3, 3] = np.asarray(t)
    note = f"ground truth Sim(3)-aligned onto the estimate (Umeyama, scale estimate->GT {float(s):.4g})"
    return _Paired(traj_est, traj_gt, est_aligned, GtAlignment(AlignmentKind.SIM3, T, float(s), n, note))


def gt_alignment(run: Run) -> GtAlignment | None:
    """The alignment of the ground truth to the estimate; None when the run has no ground truth."""
    paired = _pair(run)
    return None if paired is None else paired.alignment


def gt_in_estimate_frame(run: Run, alignment: GtAlignment) -> F64:
    """(M, 3) ground-truth positions (all of them, not only the paired ones) in the estimate's frame w.

    ``p = T_gt_est^-1 p_gt``, i.e. R^T (p_gt - t) / s for a Sim(3); empty for an unusable alignment.
    """
    if run.gt is None or alignment.kind is AlignmentKind.NONE:
        return np.zeros((0, 3))
    T_est_gt = np.linalg.inv(alignment.T_gt_est)
    return run.gt.positions_xyz @ T_est_gt[:3, :3].T + T_est_gt[:3, 3]


# --- scale ------------------------------------------------------------------------------------------


def units_name(units: str) -> str:
    """'m' -> 'm', anything else (VO units, 'vo') -> 'VO units'."""
    return "m" if units == "m" else "VO units"


@dataclass(frozen=True)
class RunScale:
    """Where the run's scale came from and the units of its trajectory."""

    source: str  # none / ground_plane / wheel_odometry
    units: str  # 'm' or 'vo', of the trajectory at the end of the run
    metric_from_frame: int | None  # first frame whose position was metric; None: never (or source none)


def run_scale(run: Run) -> RunScale:
    """From ``stats.json`` (``scale_source``, ``units``, ``metric_from_frame``), else from the frame records;
    an output directory from before the scale sources has neither: source none, VO units."""
    stats, recs = run.stats or {}, run.records
    source = stats.get("scale_source") or next((str(r["scale_source"]) for r in recs if r.get("scale_source")),
                                               "none")
    units = stats.get("units") or str(recs[-1].get("units") or "vo")
    metric_from = stats.get("metric_from_frame") if "metric_from_frame" in stats else \
        next((int(r["index"]) for r in recs if r.get("metric_scale")), None)
    return RunScale(str(source), "m" if units == "m" else "vo",
                    None if metric_from is None else int(metric_from))


@dataclass(frozen=True)
class ScaleSeries:
    """Per-frame scale of a run with a metric scale source (one entry per record, None -> NaN).

    ``scale`` is metres per VO unit of the first map where metric scale was established (NaN before:
    the records' 1.0 there is a placeholder, not a measurement); ``lower`` / ``upper`` the 1-sigma band
    ``scale * (1 -/+ scale_rel_std)``.
    """

    source: str
    frame_index: NDArray[np.int64]
    metric: NDArray[np.bool_]
    scale: F64
    lower: F64
    upper: F64
    floor_pitch_deg: F64  # NaN unless ground_plane measured the floor at that frame
    floor_roll_deg: F64

    @property
    def has_floor(self) -> bool:
        return bool(np.isfinite(self.floor_pitch_deg).any() or np.isfinite(self.floor_roll_deg).any())


def scale_series(run: Run) -> ScaleSeries | None:
    """The scale over frames; None for a run in VO units by choice (source none, or records without scale)."""
    source = run_scale(run).source
    if source == "none":
        return None
    recs = run.records

    def series(key: str) -> F64:
        return np.array([_num(r.get(key)) for r in recs])

    metric = np.array([bool(r.get("metric_scale")) for r in recs])
    scale = np.where(metric, series("scale"), math.nan)
    rel = series("scale_rel_std")
    return ScaleSeries(source, np.array([int(r["index"]) for r in recs], dtype=np.int64), metric, scale,
                       scale * (1.0 - rel), scale * (1.0 + rel), series("floor_pitch_deg"), series("floor_roll_deg"))


# --- timeline ---------------------------------------------------------------------------------------


def _num(value: Any) -> float:
    return math.nan if value is None else float(value)


def _param_number(value: Any) -> float:
    """A parameter shown against a series: NaN (not drawn) unless it is a number."""
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else math.nan


@dataclass(frozen=True)
class Timeline:
    """Per-frame series of the frame records, one entry per record (None in a record -> NaN)."""

    frame_index: NDArray[np.int64]
    stamp_s: F64
    state: tuple[str, ...]
    is_keyframe: NDArray[np.bool_]
    model: tuple[str, ...]  # "E" / "H" / "none"
    rh: F64
    n_features: F64
    n_tracked: F64
    n_inliers: F64
    inlier_ratio: F64
    median_parallax_deg: F64
    n_triangulated: F64
    positive_depth_ratio: F64
    median_reproj_err_px: F64
    stage_ms: dict[str, F64]  # per pipeline stage (every timings_ms key but "total"), first-seen order
    total_ms: F64
    rh_threshold: float  # H is chosen above this
    rh_threshold_source: str  # "stats.json" or "defaults"

    @property
    def keyframe_index(self) -> NDArray[np.int64]:
        return self.frame_index[self.is_keyframe]


def timeline(run: Run) -> Timeline:
    recs = run.records

    def series(key: str) -> F64:
        return np.array([_num(r[key]) for r in recs])

    stages = list(dict.fromkeys(k for r in recs for k in r["timings_ms"] if k != "total"))
    params, source = run_parameters(run)
    return Timeline(
        frame_index=np.array([int(r["index"]) for r in recs], dtype=np.int64),
        stamp_s=series("stamp"),
        state=tuple(str(r["state"]) for r in recs),
        is_keyframe=np.array([bool(r["is_keyframe"]) for r in recs]),
        model=tuple(str(r["model"]) for r in recs),
        rh=series("rh"), n_features=series("n_features"), n_tracked=series("n_tracked"),
        n_inliers=series("n_inliers"), inlier_ratio=series("inlier_ratio"),
        median_parallax_deg=series("median_parallax_deg"), n_triangulated=series("n_triangulated"),
        positive_depth_ratio=series("positive_depth_ratio"), median_reproj_err_px=series("median_reproj_err_px"),
        stage_ms={s: np.array([_num(r["timings_ms"].get(s)) for r in recs]) for s in stages},
        total_ms=np.array([_num(r["timings_ms"].get("total")) for r in recs]),
        rh_threshold=_param_number(params.get("rh_threshold")), rh_threshold_source=source)


# --- spans ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Span:
    """A maximal run of consecutive frames in one state other than ``tracking``."""

    state: str  # initializing / rotation_only / lost
    start_index: int  # record index of the first frame
    end_index: int  # record index of the last frame (inclusive)
    start_stamp_s: float
    end_stamp_s: float
    n_frames: int
    reasons: tuple[str, ...]  # distinct non-empty reasons, in order of first appearance

    @property
    def duration_s(self) -> float:
        return self.end_stamp_s - self.start_stamp_s


def spans(run: Run) -> list[Span]:
    """Contiguous spans of frames whose state is not ``tracking``; a change of state starts a new span."""
    out: list[Span] = []
    group: list[dict[str, Any]] = []

    def close() -> None:
        if group:
            reasons = tuple(dict.fromkeys(str(r["reason"]) for r in group if r["reason"]))
            out.append(Span(str(group[0]["state"]), int(group[0]["index"]), int(group[-1]["index"]),
                            float(group[0]["stamp"]), float(group[-1]["stamp"]), len(group), reasons))
            group.clear()

    for rec in run.records:
        if rec["state"] == TRACKING or (group and rec["state"] != group[0]["state"]):
            close()
        if rec["state"] != TRACKING:
            group.append(rec)
    close()
    return out


def reason_groups(reasons: Sequence[str]) -> list[tuple[str, int]]:
    """Reasons that differ only in their numbers, grouped: (first example, how many distinct reasons)."""
    groups: dict[str, list[str]] = collections.defaultdict(list)
    for reason in reasons:
        groups[re.sub(r"\d+(\.\d+)?", "#", reason)].append(reason)
    return [(members[0], len(members)) for members in groups.values()]


# --- errors against ground truth ----------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorSeries:
    """Per-frame errors of the estimate against ground truth (evo), over the stamp-matched poses."""

    frame_index: NDArray[np.int64]  # (M,) record index of each matched pose
    stamp_s: F64  # (M,)
    ate: F64  # (M,) APE translation after Sim(3) alignment, GT units; NaN when the alignment is degenerate
    rpe_frame_index: NDArray[np.int64]  # (M-1,) record index of the later pose j of each pair (j-1, j)
    rpe_rot_deg: F64  # (M-1,) relative rotation angle error, deg per frame (alignment-free)
    rpe_trans: F64  # (M-1,) relative translation error of the aligned estimate, GT units; NaN when degenerate
    alignment: GtAlignment

    @property
    def ate_rmse(self) -> float:
        return float(np.sqrt(np.mean(self.ate**2))) if self.ate.size else math.nan


def error_series(run: Run) -> ErrorSeries | None:
    """ATE over time and RPE per frame, as :func:`epi_vo.tools.evaluation.evaluate_trajectory` computes them.

    ATE: evo APE (translation part) of the Sim(3)-aligned estimate (``align(correct_scale=True)``).
    RPE: evo RPE over consecutive matched poses (delta 1 frame); the rotation angle on the unaligned
    estimate (a world transform cancels in T_i^-1 T_j), the translation on the aligned one.
    None when the run has no usable ground truth.
    """
    paired = _pair(run)
    if paired is None or paired.est is None or paired.gt is None or paired.est_aligned is None:
        return None  # no ground truth, or alignment NONE
    stamps = np.asarray(paired.est.timestamps, dtype=np.float64)
    frame_index = _frame_index_of_stamps(run.records, stamps, run.directory / "trajectory.tum")
    m = stamps.shape[0]
    rpe_rot = RPE(PoseRelation.rotation_angle_deg, delta=1, delta_unit=Unit.frames, all_pairs=False)
    rpe_rot.process_data((paired.gt, paired.est))
    rpe_ids = np.asarray(rpe_rot.delta_ids, dtype=np.int64)
    ate = np.full(m, math.nan)
    rpe_trans = np.full(rpe_ids.shape[0], math.nan)
    if paired.alignment.kind is AlignmentKind.SIM3:
        ape = APE(PoseRelation.translation_part)
        ape.process_data((paired.gt, paired.est_aligned))
        ate = np.asarray(ape.error, dtype=np.float64)
        rpe_t = RPE(PoseRelation.translation_part, delta=1, delta_unit=Unit.frames, all_pairs=False)
        rpe_t.process_data((paired.gt, paired.est_aligned))
        rpe_trans = np.asarray(rpe_t.error, dtype=np.float64)
    return ErrorSeries(frame_index, stamps, ate, frame_index[rpe_ids], np.asarray(rpe_rot.error, dtype=np.float64),
                       rpe_trans, paired.alignment)


# --- run figures ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunFigures:
    """The numbers of the report's summary table, from the frame records (and evo for GT metrics)."""

    frames: int
    frames_with_pose: int
    keyframes: int
    states: dict[str, int]
    models: dict[str, int]
    ms_per_frame: float  # median of timings_ms.total
    stage_ms: dict[str, float]  # median per stage
    path_length: float  # of the estimate, in scale.units
    metrics: TrajectoryMetrics | None
    metrics_note: str
    scale: RunScale

    @property
    def tracked_percent(self) -> float:
        return 100.0 * self.frames_with_pose / self.frames


def run_figures(run: Run) -> RunFigures:
    tl = timeline(run)
    metrics, note = None, ""
    if run.gt is None:
        note = "no ground truth"
    else:
        try:
            est, held = metric_poses(run.est, run.records)
            metrics = evaluate_trajectory(est, run.gt, max_time_diff=_GT_MAX_TIME_DIFF_S)
            if held:
                note = f"{held} pose(s) held before metric scale was established are not in the metrics"
        except EpiVoError as exc:
            note = f"metrics not computed: {exc}"
    path = PathLength()  # the replay's rule (stats.json path_length), from the records
    for r in run.records:
        if r.get("has_pose") and isinstance(r.get("position"), list):
            path.add(np.asarray(r["position"], dtype=np.float64),
                     Units.METRES if r.get("units") == Units.METRES else Units.VO)
    scale = run_scale(run)
    return RunFigures(
        frames=len(run.records), frames_with_pose=sum(bool(r["has_pose"]) for r in run.records),
        keyframes=int(tl.is_keyframe.sum()), states=dict(collections.Counter(tl.state)),
        models=dict(collections.Counter(tl.model)), ms_per_frame=_nanmedian(tl.total_ms),
        stage_ms={k: _nanmedian(v) for k, v in tl.stage_ms.items()},
        path_length=path.length(Units.METRES if scale.units == Units.METRES else Units.VO), metrics=metrics,
        metrics_note=note, scale=scale)


def _nanmedian(a: F64) -> float:
    return float(np.nanmedian(a)) if np.isfinite(a).any() else math.nan


# ==================================================================================================
# Drawing (matplotlib object API, Agg; no pyplot)
# ==================================================================================================


def fmt_num(x: float | None, spec: str = ".4g") -> str:
    return "n/a" if x is None or not math.isfinite(x) else format(x, spec)


# ==================================================================================================
# Report
# ==================================================================================================
