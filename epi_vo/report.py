"""Plots and a self-contained HTML report of an ``epi-vo replay`` output directory.

Data and drawing are kept apart. The data functions are pure functions of the files in the directory
and are what the tests check:

- :func:`load_run` reads ``frames.jsonl``, ``trajectory.tum``, ``stats.json`` and ``groundtruth.tum``;
- :func:`trajectory_views` gives the estimate and the aligned ground truth in a top and a side view;
- :func:`timeline` gives the per-frame series of the frame records;
- :func:`spans` finds the runs of frames that are not ``tracking``, with their reasons;
- :func:`error_series` gives ATE over time and RPE per frame, computed with evo.

The drawing functions turn those into PNGs with matplotlib's object API: a bare
``matplotlib.figure.Figure`` renders through Agg, and pyplot (hence any display) is never imported.
:func:`write_report` writes ``DIR/report/{trajectory,timeline,errors}.png`` and ``DIR/report.html``,
one file that embeds the PNGs as data URIs and needs nothing else.

Frames. The estimate holds camera poses T_w_c, w = the first camera's optical frame (x right,
y down, z forward), in VO units. The top view is the x-z plane (x right, z forward, seen from above),
the side view the z-y plane with -y drawn upwards. The ground truth is drawn in the estimate's frame:
evo's Umeyama fit p_gt ~= s R p_est + t (the one :mod:`epi_vo.evaluation` uses for ATE) is inverted,
p = R^T (p_gt - t) / s. When that fit is degenerate (an estimate that never moves, as under pure
rotation, or moves along one line) the ground truth is only origin-aligned: its first matched pose is
put on the estimate's, in its own units, since there is no scale to recover.
"""

from __future__ import annotations

import argparse
import base64
import collections
import copy
import datetime
import enum
import html
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
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from numpy.typing import NDArray

from epi_vo import bagio
from epi_vo.config import config_fields, field_doc
from epi_vo.errors import EpiVoError, ReportError
from epi_vo.evaluation import (
    MIN_MATCHED_POSES,
    StampedPoses,
    TrajectoryMetrics,
    evaluate_trajectory,
    to_evo_trajectory,
)

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

REPORT_HTML = "report.html"
REPORT_PNG_DIR = "report"

# Keys every frame record must have for the report (FrameResult.to_record writes more).
_RECORD_KEYS = ("index", "stamp", "state", "has_pose", "is_keyframe", "model", "rh", "n_features", "n_tracked",
                "n_inliers", "inlier_ratio", "median_parallax_deg", "n_triangulated", "positive_depth_ratio",
                "median_reproj_err_px", "timings_ms", "reason")

# A trajectory.tum row belongs to the frame record with the nearest stamp within this. TUM stamps carry
# 9 decimals, but float64 seconds near the Unix epoch resolve only ~0.24 us; 0.1 ms is still far below
# any camera frame interval.
_STAMP_MATCH_TOL_S = 1e-4
# Ground-truth pairing, as evaluate_trajectory's default max_time_diff (same poses, same metrics).
_GT_MAX_TIME_DIFF_S = 0.01

_NO_SIM3 = "no Sim(3) alignment exists (the estimate does not move, or moves along a line)"

TRACKING = "tracking"
# Presentation only: one colour per tracking state (span shading in the plots, chips in the table).
STATE_COLOURS = {"initializing": "#9ecae1", "rotation_only": "#fdae6b", "lost": "#fb8072", TRACKING: "#b8e186"}
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
    est: StampedPoses  # trajectory.tum: T_w_c of the frames with a pose (VO units)
    est_frame_index: NDArray[np.int64]  # (N,) record "index" of each trajectory row
    gt: StampedPoses | None  # groundtruth.tum (ground-truth units), None when the run had none
    stats: dict[str, Any] | None  # stats.json, None when absent


def load_run(directory: str | Path) -> Run:
    """Read a replay output directory (see :mod:`epi_vo.replay` for its files).

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
    est = StampedPoses(*_read_tum(d / "trajectory.tum"))
    est_frame_index = _frame_index_of_stamps(records, est.stamps_s, d / "trajectory.tum")
    gt = StampedPoses(*_read_tum(d / "groundtruth.tum")) if (d / "groundtruth.tum").is_file() else None
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
        records.append(rec)
    if not records:
        msg = f"{path}: no frame records"
        raise ReportError(msg)
    return tuple(records)


def _read_tum(path: Path) -> tuple[F64, F64, F64]:
    try:
        return bagio.read_tum(path)
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
        traj_est = to_evo_trajectory(run.est, "estimated trajectory")
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


# --- trajectory views -----------------------------------------------------------------------------


def top_view(p: F64) -> F64:
    """(N, 3) optical-frame points -> (N, 2) top view: (x right, z forward)."""
    return np.column_stack([p[:, 0], p[:, 2]]) if p.size else np.zeros((0, 2))


def side_view(p: F64) -> F64:
    """(N, 3) optical-frame points -> (N, 2) side view: (z forward, -y up); the optical y axis points down."""
    return np.column_stack([p[:, 2], -p[:, 1]]) if p.size else np.zeros((0, 2))


class View(NamedTuple):
    """One 2-D projection of the trajectories (all arrays in the same plot coordinates)."""

    title: str
    xlabel: str
    ylabel: str
    est: F64  # (N, 2) estimated camera centres
    gt: F64  # (M, 2) ground truth in the estimate's frame (empty without a usable ground truth)
    keyframes: F64  # (K, 2) estimated camera centres of the keyframes
    heading: F64  # (N, 2) projection of each estimated camera's forward (optical z) axis, unit 3-D vector


@dataclass(frozen=True)
class TrajectoryViews:
    top: View
    side: View
    est_frame_index: NDArray[np.int64]  # (N,) record index of each estimated pose
    keyframe_index: NDArray[np.int64]  # (K,) record index of each keyframe with a pose
    alignment: GtAlignment | None  # None: no ground truth


def trajectory_views(run: Run) -> TrajectoryViews:
    """The estimate, its keyframes and the aligned ground truth in the top (x-z) and side (z, -y) views."""
    p = run.est.positions_xyz
    kf_records = {int(r["index"]) for r in run.records if r["is_keyframe"]}
    kf_mask = np.array([i in kf_records for i in run.est_frame_index], dtype=bool)
    forward = _forward_axes(run.est.quats_xyzw)
    alignment = gt_alignment(run)
    gt = gt_in_estimate_frame(run, alignment) if alignment is not None else np.zeros((0, 3))
    top = View("top view (x-z)", "x (right) [VO units]", "z (forward) [VO units]",
               top_view(p), top_view(gt), top_view(p[kf_mask]), top_view(forward))
    side = View("side view (z-y)", "z (forward) [VO units]", "-y (up) [VO units]",
                side_view(p), side_view(gt), side_view(p[kf_mask]), side_view(forward))
    return TrajectoryViews(top, side, run.est_frame_index, run.est_frame_index[kf_mask], alignment)


def _forward_axes(quats_xyzw: F64) -> F64:
    """(N, 4) quaternions of R_w_c -> (N, 3) third column of R_w_c: the camera's optical axis in w."""
    if quats_xyzw.size == 0:
        return np.zeros((0, 3))
    q = quats_xyzw / np.linalg.norm(quats_xyzw, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.column_stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


# --- timeline ---------------------------------------------------------------------------------------


def _num(value: Any) -> float:
    return math.nan if value is None else float(value)


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
        rh_threshold=float(params.get("rh_threshold", math.nan)), rh_threshold_source=source)


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
    """ATE over time and RPE per frame, as :func:`epi_vo.evaluation.evaluate_trajectory` computes them.

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
    path_length: float  # of the estimate, VO units
    metrics: TrajectoryMetrics | None
    metrics_note: str

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
            metrics = evaluate_trajectory(run.est, run.gt, max_time_diff=_GT_MAX_TIME_DIFF_S)
        except EpiVoError as exc:
            note = f"metrics not computed: {exc}"
    steps = np.diff(run.est.positions_xyz, axis=0)
    return RunFigures(
        frames=len(run.records), frames_with_pose=sum(bool(r["has_pose"]) for r in run.records),
        keyframes=int(tl.is_keyframe.sum()), states=dict(collections.Counter(tl.state)),
        models=dict(collections.Counter(tl.model)), ms_per_frame=_nanmedian(tl.total_ms),
        stage_ms={k: _nanmedian(v) for k, v in tl.stage_ms.items()},
        path_length=float(np.linalg.norm(steps, axis=1).sum()) if steps.size else 0.0,
        metrics=metrics, metrics_note=note)


def _nanmedian(a: F64) -> float:
    return float(np.nanmedian(a)) if np.isfinite(a).any() else math.nan


# ==================================================================================================
# Drawing (matplotlib object API, Agg; no pyplot)
# ==================================================================================================


def draw_trajectory(views: TrajectoryViews, path: Path) -> Path:
    """trajectory.png: top and side views, estimate (keyframes marked) and aligned ground truth."""
    fig = Figure(figsize=(13, 6.5), dpi=100)
    fig.subplots_adjust(left=0.06, right=0.985, top=0.86, bottom=0.14, wspace=0.16)
    axes = fig.subplots(1, 2)
    gt_label = "ground truth"
    if views.alignment is not None:
        gt_label += {AlignmentKind.SIM3: " (Sim(3)-aligned)", AlignmentKind.ORIGIN: " (origin-aligned, own units)",
                     AlignmentKind.NONE: " (not usable)"}[views.alignment.kind]
    for ax, view in zip(axes, (views.top, views.side), strict=True):
        pts = np.vstack([view.est, view.gt]) if view.gt.size else view.est
        extent = float(np.ptp(pts, axis=0).max()) if pts.size else 0.0
        if view.est.size:
            ax.plot(view.est[:, 0], view.est[:, 1], "-", color=EST_COLOUR, lw=2.2, label="estimate")
            # Camera heading (optical axis) at ~20 poses: the only visible motion under pure rotation.
            step = max(1, math.ceil(view.est.shape[0] / 20))
            h = view.heading[::step]
            norm = np.linalg.norm(h, axis=1, keepdims=True)
            h = np.divide(h, norm, out=np.zeros_like(h), where=norm > 1e-9) * (0.08 * extent if extent > 1e-9 else 0.6)
            ax.quiver(view.est[::step, 0], view.est[::step, 1], h[:, 0], h[:, 1], angles="xy", scale_units="xy",
                      scale=1, color="#555555", width=0.003, alpha=0.7, label="heading (optical axis)")
            ax.plot(view.keyframes[:, 0], view.keyframes[:, 1], "^", ms=7, mfc=EST_COLOUR, mec="black", mew=0.6,
                    ls="none", label=f"keyframes ({view.keyframes.shape[0]})")
            ax.plot(*view.est[0], "o", ms=9, mfc="#2ca02c", mec="black", label="start")
            ax.plot(*view.est[-1], "s", ms=8, mfc="black", mec="black", label="end")
        else:
            ax.text(0.5, 0.5, "no estimated poses", transform=ax.transAxes, ha="center", va="center")
        if view.gt.size:  # drawn over the estimate (dashed), which it hides where the two agree
            ax.plot(view.gt[:, 0], view.gt[:, 1], "--", color=GT_COLOUR, lw=1.4, label=gt_label, zorder=4)
        if pts.size and extent < 1e-9:  # a single point: give the equal-aspect box a size
            cx, cy = pts[0]
            ax.set_xlim(cx - 1.0, cx + 1.0)
            ax.set_ylim(cy - 1.0, cy + 1.0)
            ax.set_aspect("equal", adjustable="box")
        else:
            ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(view.title)
        ax.set_xlabel(view.xlabel)
        ax.set_ylabel(view.ylabel)
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    if labels:  # nothing drawn (every frame rejected, no ground truth): no legend (ncol must be > 0)
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9, frameon=False)
    title = "Trajectory (camera optical frame of the first image)"
    if views.alignment is not None:
        title += f"\n{views.alignment.note}"
    fig.suptitle(title, fontsize=11)
    return _save(fig, path)


def _shade(ax: Any, span_list: Sequence[Span], keyframes: NDArray[np.int64]) -> None:
    for s in span_list:
        ax.axvspan(s.start_index - 0.5, s.end_index + 0.5, color=STATE_COLOURS.get(s.state, "#dddddd"), alpha=0.45,
                   lw=0, zorder=0)
    if keyframes.size:
        ax.plot(keyframes, np.full(keyframes.shape, 1.0), "|", color="black", ms=9, mew=1.2, clip_on=False,
                transform=ax.get_xaxis_transform(), zorder=5)


def _state_legend(fig: Figure, span_list: Sequence[Span]) -> None:
    states = list(dict.fromkeys(s.state for s in span_list))
    handles: list[Any] = [Patch(color=STATE_COLOURS.get(s, "#dddddd"), alpha=0.6, label=s) for s in states]
    handles.append(Line2D([], [], marker="|", color="black", ls="none", ms=9, mew=1.2, label="keyframe"))
    fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 1.0), ncol=len(handles), fontsize=9,
               frameon=False)


def draw_timeline(tl: Timeline, span_list: Sequence[Span], path: Path) -> Path:
    """timeline.png: stacked per-frame panels sharing the frame axis."""
    # Fixed margins: constrained layout would double the drawing time of this figure.
    fig = Figure(figsize=(13, 17), dpi=100)
    fig.subplots_adjust(left=0.065, right=0.935, top=0.955, bottom=0.035, hspace=0.3)
    axes = fig.subplots(6, 1, sharex=True)
    x = tl.frame_index
    kf = tl.keyframe_index

    ax = axes[0]
    ax.plot(x, tl.n_features, "-", color="#444444", lw=1.2, label="features")
    ax.plot(x, tl.n_tracked, "-", color="#1f77b4", lw=1.2, label="tracked")
    ax.plot(x, tl.n_inliers, "-", color="#2ca02c", lw=1.2, label="inliers")
    ax.set_ylabel("count")
    ax.set_ylim(bottom=0)
    axr = ax.twinx()
    axr.plot(x, tl.inlier_ratio, ":", color="#9467bd", lw=1.6, marker=".", ms=3, label="inlier ratio")
    axr.set_ylim(0, 1.05)
    axr.set_ylabel("inlier ratio")
    _legend_pair(ax, axr)
    ax.set_title("features, tracked, inliers")

    ax = axes[1]
    rh_plot = np.where(np.isfinite(tl.rh), tl.rh, 0.0)
    ax.plot(x, tl.rh, "-", color="#999999", lw=0.8)
    models = np.array(tl.model)
    for name, colour in MODEL_COLOURS.items():
        mask = models == name
        if mask.any():
            ax.plot(x[mask], rh_plot[mask], "x" if name == "none" else "o", ls="none", ms=5, color=colour,
                    label=f"model {name} ({int(mask.sum())})")
    if math.isfinite(tl.rh_threshold):
        ax.axhline(tl.rh_threshold, ls="--", color="black", lw=1,
                   label=f"rh_threshold {tl.rh_threshold:g} ({tl.rh_threshold_source})")
    ax.set_ylim(0, 1)
    ax.set_ylabel("RH = S_H/(S_H+S_E)")
    ax.legend(loc="upper right", fontsize=8, ncol=4)
    ax.set_title("model choice (H above the threshold) and RH")

    ax = axes[2]
    ax.plot(x, tl.median_parallax_deg, "-", color="#8c564b", marker=".", ms=4, lw=1.2)
    ax.set_ylabel("deg")
    ax.set_ylim(bottom=0)
    ax.set_title("median parallax (rotation removed)")

    ax = axes[3]
    ax.bar(x, np.nan_to_num(tl.n_triangulated), width=0.8, color="#17becf", label="triangulated points")
    ax.set_ylabel("points")
    ax.set_ylim(bottom=0)
    _say_if_empty(ax, tl.n_triangulated, "no points triangulated in this run")
    axr = ax.twinx()
    axr.plot(x, tl.positive_depth_ratio, "o", color="#d62728", ms=4, label="positive-depth ratio")
    axr.set_ylim(0, 1.1)
    axr.set_ylabel("ratio")
    _legend_pair(ax, axr)
    ax.set_title("triangulation (keyframes) and cheirality")

    ax = axes[4]
    ax.plot(x, tl.median_reproj_err_px, "-", color="#e377c2", marker="o", ms=4, lw=1.2)
    ax.set_ylabel("px")
    ax.set_ylim(bottom=0)
    _say_if_empty(ax, tl.median_reproj_err_px, "no triangulated points, no reprojection error")
    ax.set_title("median reprojection error of triangulated points")

    ax = axes[5]
    if tl.stage_ms:
        ax.stackplot(x, *[np.nan_to_num(v) for v in tl.stage_ms.values()], labels=list(tl.stage_ms), alpha=0.85)
    ax.plot(x, tl.total_ms, "-", color="black", lw=1, label="total")
    ax.set_ylabel("ms")
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper right", fontsize=8, ncol=len(tl.stage_ms) + 1, framealpha=0.9)
    ax.set_title("processing time per stage (stacked)")
    ax.set_xlabel("frame index")

    for ax in axes:
        _shade(ax, span_list, kf)
        ax.grid(True, alpha=0.3)
    if x.size:
        axes[-1].set_xlim(x[0] - 0.5, x[-1] + 0.5)
    _state_legend(fig, span_list)
    return _save(fig, path)


def _say_if_empty(ax: Any, y: F64, text: str) -> None:
    if not (np.isfinite(y) & (y != 0)).any():
        ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=10, color="#555555")


def _legend_pair(ax: Any, axr: Any) -> None:
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = axr.get_legend_handles_labels()
    axr.legend(h1 + h2, l1 + l2, loc="lower right", fontsize=8, ncol=4)


def draw_errors(err: ErrorSeries, span_list: Sequence[Span], keyframes: NDArray[np.int64], path: Path) -> Path:
    """errors.png: ATE over time (Sim(3)-aligned) and RPE rotation / translation per frame."""
    fig = Figure(figsize=(13, 9), dpi=100)
    fig.subplots_adjust(left=0.065, right=0.985, top=0.92, bottom=0.06, hspace=0.32)
    axes = fig.subplots(3, 1, sharex=True)
    panels = (
        (axes[0], err.frame_index, err.ate, "GT units", f"ATE over time (Sim(3)-aligned), RMSE {_fmt(err.ate_rmse)}"),
        (axes[1], err.rpe_frame_index, err.rpe_rot_deg, "deg / frame",
         f"RPE rotation, RMSE {_fmt(_rmse(err.rpe_rot_deg))} deg/frame"),
        (axes[2], err.rpe_frame_index, err.rpe_trans, "GT units / frame",
         f"RPE translation (Sim(3)-aligned), RMSE {_fmt(_rmse(err.rpe_trans))}"),
    )
    for ax, x, y, ylabel, title in panels:
        if np.isfinite(y).any():
            ax.plot(*_break_at_gaps(x, y), "-", color="#d62728", marker=".", ms=4, lw=1.2)
            ax.set_ylim(bottom=0)
        else:
            ax.text(0.5, 0.5, f"undefined: {_NO_SIM3}",
                    transform=ax.transAxes, ha="center", va="center", fontsize=10, color="#555555")
            ax.set_yticks([])
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        _shade(ax, span_list, keyframes)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("frame index")
    if err.frame_index.size:
        axes[-1].set_xlim(err.frame_index[0] - 0.5, err.frame_index[-1] + 0.5)
    _state_legend(fig, span_list)
    return _save(fig, path)


def _break_at_gaps(x: NDArray[np.int64], y: F64) -> tuple[F64, F64]:
    """Insert a NaN where frames are missing (no pose), so that no line is drawn across them."""
    gaps = np.flatnonzero(np.diff(x) > 1) + 1
    return np.insert(x.astype(np.float64), gaps, math.nan), np.insert(y, gaps, math.nan)


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, format="png")
    return path


def _rmse(a: F64) -> float:
    return float(np.sqrt(np.mean(a**2))) if a.size else math.nan


def _fmt(x: float | None, spec: str = ".4g") -> str:
    return "n/a" if x is None or not math.isfinite(x) else format(x, spec)


# ==================================================================================================
# Report
# ==================================================================================================


def write_report(directory: str | Path) -> Path:
    """Write ``DIR/report/*.png`` and the self-contained ``DIR/report.html``; return the HTML's path.

    Raises:
        ReportError: the directory cannot be read as a replay output (see :func:`load_run`), or the
            report cannot be written into it.
    """
    run = load_run(directory)
    try:
        return _write_report(run)
    except OSError as exc:  # DIR/report or report.html not writable, a file where a directory goes, disk full
        where = f" ({exc.filename})" if exc.filename else ""
        msg = f"cannot write the report in {run.directory}: {exc.strerror or exc}{where}"
        raise ReportError(msg) from None


def _write_report(run: Run) -> Path:
    png_dir = run.directory / REPORT_PNG_DIR
    png_dir.mkdir(exist_ok=True)
    views = trajectory_views(run)
    tl = timeline(run)
    span_list = spans(run)
    err = error_series(run)
    pngs = [(draw_trajectory(views, png_dir / "trajectory.png"), "Trajectory: top view (x right, z forward) and "
             "side view (z forward, -y up), estimate in VO units with its keyframes; ground truth in the same frame."),
            (draw_timeline(tl, span_list, png_dir / "timeline.png"), "Per-frame timeline. Shaded: frames not "
             "tracking, by state; ticks at the top of each panel: keyframes.")]
    errors_png = png_dir / "errors.png"
    if err is not None:
        pngs.append((draw_errors(err, span_list, tl.keyframe_index, errors_png),
                     "Errors against ground truth (evo): ATE of the Sim(3)-aligned estimate over time, RPE between "
                     "consecutive frames."))
    else:
        errors_png.unlink(missing_ok=True)  # a stale plot of an earlier report would contradict this one
    page = render_html(run, run_figures(run), span_list, views.alignment, pngs)
    out = run.directory / REPORT_HTML
    out.write_text(page, encoding="utf-8")
    return out


def run(args: argparse.Namespace) -> int:
    """``epi-vo report DIR``: write the report and print the HTML's path."""
    print(write_report(args.dir))
    return 0


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;background:#f4f5f7;color:#222}
main{max-width:1320px;margin:0 auto;padding:18px 28px 40px;background:#fff}
h1{font-size:1.5em;margin:.3em 0}
h2{font-size:1.15em;margin:1.4em 0 .5em;border-bottom:1px solid #ddd;padding-bottom:3px}
table{border-collapse:collapse;font-size:.9em;margin:.3em 0}
th,td{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#f0f2f5;font-weight:600}td.num{text-align:right;font-variant-numeric:tabular-nums}
.kv th{width:16em}.chip{display:inline-block;padding:1px 7px;border-radius:8px;font-size:.9em}
figure{margin:.8em 0}figure img{max-width:100%;border:1px solid #e3e3e3}
figcaption{font-size:.85em;color:#555}.note{color:#8a5a00}.muted{color:#777}
code{background:#f0f2f5;padding:0 3px;border-radius:3px}
"""

# After load, count the images the browser actually decoded (tests read it with --dump-dom).
_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; });
  document.body.setAttribute('data-images', String(imgs.length));
  document.body.setAttribute('data-loaded', String(ok.length));
});
"""


def render_html(run: Run, figs: RunFigures, span_list: Sequence[Span], alignment: GtAlignment | None,
                pngs: Sequence[tuple[Path, str]]) -> str:
    """The report page: inline CSS, PNGs as base64 data URIs, no external resource."""
    e = html.escape
    stats = run.stats or {}
    parts = [f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<title>epi_vo report: {e(run.directory.name)}</title><style>{_CSS}</style></head><body><main>",
             f"<h1>epi_vo report: {e(run.directory.name)}</h1>",
             f"<p class=\"muted\">{e(str(run.directory.resolve()))} &middot; generated "
             f"{e(datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M:%S %Z'))}</p>"]

    unknown = "unknown (no stats.json)" if run.stats is None else "unknown"
    gt_source = stats.get("gt_source") or ("groundtruth.tum" if run.gt is not None else "none")
    parts.append("<h2>Input</h2>")
    parts.append(_kv_table([("bag", e(str(stats.get("bag", unknown)))),
                            ("image topic", e(str(stats.get("image_topic", unknown)))),
                            ("camera_info topic", e(str(stats.get("camera_info_topic", unknown)))),
                            ("ground truth", e(str(gt_source)))]))

    parts.append("<h2>Summary</h2>")
    rows = [("frames", f"{figs.frames}"),
            ("with a pose", f"{figs.frames_with_pose} ({figs.tracked_percent:.1f} %)"),
            ("states", ", ".join(f"{_chip(s)} {n} ({100.0 * n / figs.frames:.1f} %)"
                                 for s, n in sorted(figs.states.items()))),
            ("keyframes", f"{figs.keyframes}"),
            ("models", ", ".join(f"{e(m)} {n}" for m, n in sorted(figs.models.items()))),
            ("time per frame (median)", f"{_fmt(figs.ms_per_frame, '.2f')} ms total; " +
             ", ".join(f"{e(k)} {_fmt(v, '.2f')}" for k, v in figs.stage_ms.items()) + " ms"),
            ("path length (estimate)", f"{figs.path_length:.3f} VO units")]
    m = figs.metrics
    if m is not None:
        no_sim3 = f"undefined: {_NO_SIM3}"
        rows += [("matched poses (GT)", f"{m.matched_poses}"),
                 ("ATE RMSE (Sim(3))", f"{_fmt(m.ate_rmse)} GT units ({_fmt(m.ate_percent_of_path)} % of path), "
                                       f"scale estimate&rarr;GT {_fmt(m.sim3_scale)}"
                  if math.isfinite(m.ate_rmse) else no_sim3),
                 ("RPE rotation RMSE", f"{_fmt(m.rpe_rot_deg_per_frame)} deg/frame"),
                 ("RPE translation RMSE", f"{_fmt(m.rpe_trans_rmse)} GT units/frame"
                  if math.isfinite(m.rpe_trans_rmse) else no_sim3),
                 ("translation direction error", f"{_fmt(m.trans_direction_err_deg)} deg (mean over "
                                                 f"{m.trans_direction_pairs} steps)"
                  if m.trans_direction_pairs else "undefined: no step with a direction in both trajectories")]
    else:
        rows.append(("ATE / RPE", f"<span class=\"muted\">{e(figs.metrics_note)}</span>"))
    parts.append(_kv_table(rows))
    notes = [str(n) for n in stats.get("notes", []) or []]
    if alignment is not None and alignment.kind is not AlignmentKind.SIM3:
        notes.append(alignment.note)
    parts.extend(f"<p class=\"note\">note: {e(n)}</p>" for n in notes)

    parts.append(f"<h2 id=\"spans\">Degenerate and lost spans ({len(span_list)})</h2>")
    if span_list:
        head = ("<table class=\"spans\"><tr><th>state</th><th>frames</th><th>count</th><th>stamps [s]</th>"
                "<th>duration [s]</th><th>reasons</th></tr>")
        body = []
        for s in span_list:
            reasons = "<br>".join(e(ex) + (f" <span class=\"muted\">(and {n - 1} more like it)</span>" if n > 1 else "")
                                  for ex, n in reason_groups(s.reasons)) or "<span class=\"muted\">-</span>"
            frames = f"{s.start_index}" if s.end_index == s.start_index else f"{s.start_index}&ndash;{s.end_index}"
            body.append(f"<tr><td>{_chip(s.state)}</td><td class=\"num\">{frames}</td>"
                        f"<td class=\"num\">{s.n_frames}</td><td class=\"num\">{s.start_stamp_s:.3f}&ndash;"
                        f"{s.end_stamp_s:.3f}</td><td class=\"num\">{s.duration_s:.3f}</td><td>{reasons}</td></tr>")
        parts.append(head + "".join(body) + "</table>")
    else:
        parts.append("<p>None: every frame was tracking.</p>")
    parts.append("<h2>Parameters</h2>")
    params, source = run_parameters(run)
    docs = {f.name: field_doc(f) for f in config_fields()}
    if source == "stats.json":
        parts.append("<p>As used by the replay (from <code>stats.json</code>).</p>")
    else:
        parts.append("<p>Not recorded in <code>stats.json</code>: the built-in defaults are shown "
                     "(<code>epi-vo params</code>); a <code>--params</code> file given to the replay would not "
                     "be reflected here.</p>")
    # Collapsed: the plots, not 40 numbers, are what a reader scrolls to.
    parts.append(f"<details><summary>{len(params)} values</summary><table><tr><th>parameter</th><th>value</th>"
                 "<th>meaning</th></tr>" +
                 "".join(f"<tr><td><code>{e(k)}</code></td><td>{e(json.dumps(v))}</td><td>{e(docs.get(k, ''))}"
                         f"</td></tr>" for k, v in params.items()) + "</table></details>")

    parts.append("<h2>Plots</h2>")
    for png, caption in pngs:
        data = base64.b64encode(png.read_bytes()).decode("ascii")
        parts.append(f"<figure id=\"{e(png.stem)}\"><img alt=\"{e(png.stem)}\" src=\"data:image/png;base64,{data}\">"
                     f"<figcaption>{e(caption)}</figcaption></figure>")

    parts.append(f"</main><script>{_SCRIPT}</script></body></html>\n")
    return "\n".join(parts)


def _kv_table(rows: Sequence[tuple[str, str]]) -> str:
    """Rows of already-escaped HTML."""
    return "<table class=\"kv\">" + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _chip(state: str) -> str:
    return (f"<span class=\"chip\" style=\"background:{STATE_COLOURS.get(state, '#dddddd')}\">"
            f"{html.escape(state)}</span>")
