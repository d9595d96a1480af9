"""``epi-vo benchmark``: epi_vo and the seed article's reference pipeline, side by side, in one run.

For every bundled bag (``bags/<name>/bag`` with ``bags/<name>/groundtruth_tum.txt``) and the shared
KITTI clip when present, both pipelines see the same decoded frames. Reported per pipeline: tracked %
(frames with a pose), ATE as % of the ground-truth path after Sim(3) alignment, RPE rotation
(deg/frame), translation-direction error (deg), median ms/frame (processing only: bag reading and
image decoding excluded for both) and its 95th percentile, and the number of frames whose position moved
(on a pure-rotation bag any movement is invented translation).

Metric scale: bags with a known floor height or a wheel odometry topic get one more epi_vo row per
metric scale source (``METRIC_VARIANTS``: the ground-robot bag with ``ground_plane`` and
``wheel_odometry``, the KITTI clip with ``ground_plane`` at 1.65 m). Those rows also print the
step-length scale (estimate / ground truth, median over frames) and the ATE after an SE(3) alignment
only (no scale), as % of the path: the figures that say whether the output is metres.

Covariance consistency (epi_vo rows): the mean NEES of the position and of the rotation (3 dof each, ideal
3) of the tracking frames against the covariance published in /vo/odometry, and the % of them inside the
chi-square 3-dof 99 % bound (11.345), after the one global scale (Sim(3) anchored at the odometry origin;
SE(3) once metric scale is established), and the same for the twist: the replay's own figures
(:mod:`epi_vo.tools.consistency`, ``ReplaySummary.metrics``). ``e2e fps`` is the
replay's end-to-end rate (reading, decoding, VO, writing: ``ReplaySummary.end_to_end_fps``).

Ground truth against the images (:mod:`epi_vo.tools.gt_check`, once per dataset): a NEES takes the ground
truth as exact, so each dataset's ground truth is checked against its own images first. Where the images
contradict it (the KITTI clip's first 12 frames), the epi_vo rows also get the NEES from the first frame
it is confirmed at (``nees_*_checked``: anchored there, each covariance given the anchor's), printed
below the table with the check's verdict; the table's NEES stays the one over all frames.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from epi_vo.core.config import VoConfig
from epi_vo.core.errors import EpiVoError, EvaluationError, OutputError
from epi_vo.core.frame import FrameResult
from epi_vo.core.scale import Units
from epi_vo.core.transforms import quat_xyzw_from_rotation
from epi_vo.io import bagio, tum
from epi_vo.io.params import load_config
from epi_vo.io.trajectory import StampedPoses
from epi_vo.tools.bench_record import RecordHeader, load_now, write_record
from epi_vo.tools.evaluation import evaluate_trajectory, metric_poses, replay_dir_nees
from epi_vo.tools.gt_check import AGREE_EXCESS_PX, GroundTruthCheck, check_ground_truth
from epi_vo.tools.perturb import scaled_focal
from epi_vo.tools.reference import ReferencePipeline
from epi_vo.tools.replay import run_replay


@dataclass(frozen=True)
class BenchRow:
    bag: str
    pipeline: str
    frames: int
    tracked_percent: float
    ate_percent: float
    rpe_rot_deg: float
    trans_dir_deg: float
    ms_per_frame: float
    moving_frames: int
    gt_path_length: float
    step_scale: float = math.nan  # median |estimated step| / |GT step| (metric rows)
    ate_se3_percent: float = math.nan  # ATE after SE(3) alignment only, % of path (metric rows)
    nees_pos: float = math.nan  # mean position NEES of the tracking frames (3 dof; consistent: 3)
    nees_pos_inside_percent: float = math.nan  # % of them within CHI2_3DOF_99
    nees_rot: float = math.nan  # the same for the rotation
    nees_rot_inside_percent: float = math.nan
    nees_frames: int = 0  # tracking frames evaluated
    nees_twist_lin: float = math.nan  # mean NEES of the linear velocity against the twist covariance (3 dof)
    nees_twist_ang: float = math.nan  # the same for the angular velocity
    nees_twist_lin_inside_percent: float = math.nan  # % of the judged twists within CHI2_3DOF_99 (linear)
    nees_twist_ang_inside_percent: float = math.nan  # the same for the angular velocity
    e2e_fps: float = math.nan  # end-to-end frames/s of the replay (nan: not measured, reference rows)
    held_poses: int = 0  # poses published before metric scale (held, VO units): not in the trajectory metrics
    ms_p95: float = math.nan  # 95th percentile of the per-frame processing time (ms)
    gt_checked_from: int | None = None  # the frame the ground truth is confirmed from, when the images contradict
    nees_pos_checked: float = math.nan  # ... it before: the NEES from there (anchored there), as nees_pos
    nees_pos_checked_inside_percent: float = math.nan
    nees_rot_checked: float = math.nan
    nees_rot_checked_inside_percent: float = math.nan
    keyframes: int = 0  # keyframes the run made (epi_vo rows)
    metric_after_s: float = math.nan  # metric rows: seconds from the first frame to the first pose in metres
    # (inf: never established)
    moved_max: float = math.nan  # largest distance of a published position from the first, estimate units
    moved_depth_percent: float = math.nan  # that, as % of the median depth of the run's own map points (epi_vo
    # rows; 0 when it never moved, inf when it moved without a map point)

    @property
    def keyframes_per_frame(self) -> float:
        return self.keyframes / self.frames if self.frames else math.nan


# Metric scale sources the benchmark runs on top of the default configuration, per dataset name.
METRIC_VARIANTS: dict[str, tuple[tuple[str, dict[str, object]], ...]] = {
    "ground_robot": (
        ("ground_plane", {"scale_source": "ground_plane", "camera_height_m": 0.45}),
        ("wheel_odometry", {"scale_source": "wheel_odometry", "wheel_odometry_topic": "/wheel/odom"}),
    ),
    # KITTI's camera is level (its README): the first floor must lie within 10 deg of level, not 35.
    "kitti06_0-50": (("ground_plane", {"scale_source": "ground_plane", "camera_height_m": 1.65,
                                       "ground_max_tilt_deg": 10.0}),),
}


def _repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def find_datasets(bags_dir: str | Path | None, kitti_dir: str | Path | None) -> list[tuple[str, Path, Path]]:
    """(name, bag path, ground-truth TUM) for every bundled bag and the KITTI clip when present."""
    root = _repo_root()
    bags = Path(bags_dir) if bags_dir else root / "bags"
    found = []
    for d in sorted(p for p in bags.iterdir() if p.is_dir()) if bags.is_dir() else []:
        if (d / "bag").is_dir() and (d / "groundtruth_tum.txt").is_file():
            found.append((d.name, d / "bag", d / "groundtruth_tum.txt"))
    kitti = Path(kitti_dir) if kitti_dir else root.parent / "shared" / "data" / "kitti06_0-50"
    if (kitti / "bag").is_dir() and (kitti / "groundtruth_tum.txt").is_file():
        found.append((kitti.name, kitti / "bag", kitti / "groundtruth_tum.txt"))
    return found


def _moving_frames(positions: np.ndarray) -> int:
    if positions.shape[0] < 2:
        return 0
    return int(np.count_nonzero(np.linalg.norm(np.diff(positions, axis=0), axis=1) > 1e-9))


def _metrics_row(name: str, pipeline: str, frames: int, n_pose: int, ms: float, stamps: np.ndarray,
                 positions: np.ndarray, quats: np.ndarray, gt: StampedPoses,
                 evaluated: StampedPoses | None = None) -> BenchRow:
    """One table row; the trajectory metrics over ``evaluated`` (default: every pose)."""
    gt_len = float(np.sum(np.linalg.norm(np.diff(gt[1], axis=0), axis=1)))
    ate = rpe = tdir = step_scale = ate_se3 = math.nan
    try:
        m = evaluate_trajectory(evaluated if evaluated is not None else (stamps, positions, quats), gt)
        ate, rpe, tdir = m.ate_percent_of_path, m.rpe_rot_deg_per_frame, m.trans_direction_err_deg
        step_scale, ate_se3 = m.step_scale_median, m.ate_se3_percent_of_path
    except EpiVoError:
        pass
    if gt_len < 1e-6:
        ate = tdir = math.nan  # no path: ATE % and direction are undefined (pure rotation)
    return BenchRow(name, pipeline, frames, 100.0 * n_pose / max(frames, 1), ate, rpe, tdir, ms,
                    _moving_frames(positions), gt_len, step_scale, ate_se3)


class _Displacement:
    """How far a run's published positions wander from its first, against the depth of its own map: on a
    camera that does not move, any displacement is invented, and only its size against the scene says how
    much (the run's units are its own)."""

    def __init__(self) -> None:
        self.first: np.ndarray | None = None
        self.largest = 0.0
        self.depths: list[float] = []

    def __call__(self, result: FrameResult) -> None:
        if not result.has_pose:
            return
        p = np.asarray(result.position, dtype=np.float64)
        if self.first is None:
            self.first = p.copy()
        self.largest = max(self.largest, float(np.linalg.norm(p - self.first)))
        if result.points_w.shape[0]:
            self.depths.append(float(np.median(np.linalg.norm(result.points_w - p, axis=1))))

    def depth_percent(self) -> float:
        if self.largest == 0.0:
            return 0.0
        return 100.0 * self.largest / float(np.median(self.depths)) if self.depths else math.inf


def _metric_after_s(records: list[dict], metric_row: bool) -> float:
    """Seconds from the first frame to the first pose in metres; inf when none (NaN for a row without a
    metric scale source)."""
    if not metric_row or not records:
        return math.nan
    first = next((r for r in records if r.get("metric_scale") and r.get("has_pose")), None)
    return math.inf if first is None else (int(first["stamp_ns"]) - int(records[0]["stamp_ns"])) * 1e-9


def bench_epi_vo(name: str, bag: Path, gt_path: Path, cfg: VoConfig, label: str = "epi_vo",
                 checked: GroundTruthCheck | None = None, focal_rel: float = 0.0) -> BenchRow:
    """One epi_vo row; with ``checked`` that found the ground truth contradicted before some frame, also
    the NEES from that frame on; ``focal_rel``: camera_info's focal length scaled by 1 + focal_rel
    (:func:`epi_vo.tools.perturb.scaled_focal`; 0: as recorded)."""
    gt = tum.read_tum(gt_path)
    moved = _Displacement()
    with tempfile.TemporaryDirectory() as tmp:
        # KLT in line: per-frame times as a live node has them; the replay judges its covariance itself
        summary = run_replay(bag, tmp, cfg, gt_tum=gt_path, lookahead=False, on_result=moved,
                             camera_info_edit=scaled_focal(focal_rel) if focal_rel else None)
        stamps, positions, quats = tum.read_tum(Path(tmp) / "trajectory.tum")
        records = [json.loads(line) for line in (Path(tmp) / "frames.jsonl").read_text(encoding="utf-8").splitlines()
                   if line.strip()]
        evaluated, held = metric_poses((stamps, positions, quats), records)  # the metric ones, once metres
        totals = [r["timings_ms"]["total"] for r in records if "total" in r.get("timings_ms", {})]
        from_nees = None
        if checked is not None and checked.disagreeing and checked.confirmed_from_ns is not None:
            try:
                from_nees = replay_dir_nees(tmp, from_ns=checked.confirmed_from_ns)
            except EvaluationError:
                from_nees = None
    row = _metrics_row(name, label, summary.frames, summary.frames_with_pose, summary.ms_per_frame,
                       stamps, positions, quats, gt, evaluated)
    if summary.units != Units.METRES:  # VO units: the metric figures say nothing
        row = dataclasses.replace(row, step_scale=math.nan, ate_se3_percent=math.nan)
    # end_to_end_fps: a newer ReplaySummary field; an older summary has none (n/a).
    row = dataclasses.replace(row, e2e_fps=float(getattr(summary, "end_to_end_fps", math.nan) or math.nan),
                              held_poses=held, ms_p95=_p95(totals), keyframes=summary.keyframes,
                              metric_after_s=_metric_after_s(records, cfg.scale_source.metric),
                              moved_max=moved.largest, moved_depth_percent=moved.depth_percent())
    m = summary.metrics or {}
    if "nees_frames" in m:  # tools.consistency: the published pose and twist against the ground truth
        row = dataclasses.replace(row, nees_pos=m["nees_pos"], nees_pos_inside_percent=m["nees_pos_inside_percent"],
                                  nees_rot=m["nees_rot"], nees_rot_inside_percent=m["nees_rot_inside_percent"],
                                  nees_frames=m["nees_frames"], nees_twist_lin=m["nees_twist_linear"],
                                  nees_twist_ang=m["nees_twist_angular"],
                                  nees_twist_lin_inside_percent=m["nees_twist_linear_inside_percent"],
                                  nees_twist_ang_inside_percent=m["nees_twist_angular_inside_percent"])
    if from_nees is not None:
        row = dataclasses.replace(row, gt_checked_from=checked.confirmed_from if checked else None,
                                  nees_pos_checked=from_nees.mean_nees_pos,
                                  nees_pos_checked_inside_percent=from_nees.inside_pos_percent,
                                  nees_rot_checked=from_nees.mean_nees_rot,
                                  nees_rot_checked_inside_percent=from_nees.inside_rot_percent)
    return row


def format_checks(checks: list[tuple[str, GroundTruthCheck | None, str]], rows: list[BenchRow]) -> str:
    """The ground-truth check's verdict per dataset and, where it found the ground truth contradicted,
    the epi_vo rows' NEES from the frame it is confirmed at."""
    lines = ["Ground truth against the images (SIFT matches of frames 4 apart; median Sampson distance under the "
             "ground truth's relative pose against the images' own fitted pose; it agrees when it adds at most "
             f"{AGREE_EXCESS_PX} px):"]
    for name, check, error in checks:
        lines.append(f"  {name}: " + (f"not checked: {error}" if check is None else f"ground truth {check.summary()}"))
        for r in rows:
            if r.bag == name and r.gt_checked_from is not None:
                lines.append(f"    {r.pipeline} from frame {r.gt_checked_from} (anchored there): NEES pos "
                             f"{r.nees_pos_checked:.2f} ({r.nees_pos_checked_inside_percent:.1f} % in 3σ), rot "
                             f"{r.nees_rot_checked:.2f} ({r.nees_rot_checked_inside_percent:.1f} %)")
    return "\n".join(lines)


def bench_reference(name: str, bag_path: Path, gt_path: Path) -> BenchRow:
    gt = tum.read_tum(gt_path)
    stamps, positions, quats, times = [], [], [], []
    frames = n_ok = 0
    ref: ReferencePipeline | None = None
    with bagio.open_camera_bag(bag_path) as bag:
        for frame in bag.iter_frames():
            frames += 1
            # A frame epi_vo's replay would reject before decoding (undecodable message, bad stamp, no
            # camera_info, undecodable pixels) is a frame without a pose for the reference too.
            gray = bag.usable_gray(frame)
            if gray is None:
                continue
            if ref is None:
                info = frame.camera_info_msg
                ref = ReferencePipeline(np.asarray(info.k, np.float64).reshape(3, 3), np.asarray(info.d, np.float64))
            r = ref.process(gray, frame.stamp_ns * 1e-9)
            times.append(r.ms)
            if r.ok:
                n_ok += 1
                stamps.append(r.stamp_s)
                positions.append(r.T_w_c[:3, 3])
                quats.append(quat_xyzw_from_rotation(r.T_w_c[:3, :3]))
    positions_array = np.array(positions).reshape(-1, 3)
    row = _metrics_row(name, "reference", frames, n_ok, float(np.median(times)) if times else math.nan,
                       np.array(stamps), positions_array, np.array(quats).reshape(-1, 4), gt)
    moved = float(np.linalg.norm(positions_array - positions_array[0], axis=1).max()) if n_ok else 0.0
    # unit steps: no metres, and no map whose depth would give its displacement a size
    return dataclasses.replace(row, step_scale=math.nan, ate_se3_percent=math.nan, ms_p95=_p95(times),
                               moved_max=moved)


def _p95(times_ms: list[float]) -> float:
    return float(np.percentile(times_ms, 95)) if times_ms else math.nan


def format_table(rows: list[BenchRow]) -> str:
    head = (f"{'bag':<16} {'pipeline':<22} {'frames':>6} {'tracked%':>8} {'ATE%path':>9} {'RPErot°/f':>10} "
            f"{'tdir°':>7} {'ms/frame':>9} {'p95ms':>7} {'moving':>7} {'scale':>6} {'held':>5} {'SE3ATE%':>8} "
            f"{'NEES pos':>9} "
            f"{'in 3σ pos %':>11} {'NEES rot':>9} {'in 3σ rot %':>11} {'NEES v':>8} {'in 3σ v %':>9} {'NEES w':>8} "
            f"{'in 3σ w %':>9} {'e2e fps':>8}")
    lines = [head, "-" * len(head)]

    def f(x: float, nd: int = 3) -> str:
        return "n/a" if not math.isfinite(x) else f"{x:.{nd}f}"

    for r in rows:
        lines.append(f"{r.bag:<16} {r.pipeline:<22} {r.frames:>6} {r.tracked_percent:>8.1f} {f(r.ate_percent):>9} "
                     f"{f(r.rpe_rot_deg, 4):>10} {f(r.trans_dir_deg, 2):>7} {r.ms_per_frame:>9.2f} "
                     f"{f(r.ms_p95, 2):>7} {r.moving_frames:>7} {f(r.step_scale):>6} {r.held_poses:>5} "
                     f"{f(r.ate_se3_percent, 2):>8} "
                     f"{f(r.nees_pos, 3):>9} {f(r.nees_pos_inside_percent, 1):>11} {f(r.nees_rot, 3):>9} "
                     f"{f(r.nees_rot_inside_percent, 1):>11} {f(r.nees_twist_lin, 2):>8} "
                     f"{f(r.nees_twist_lin_inside_percent, 1):>9} {f(r.nees_twist_ang, 2):>8} "
                     f"{f(r.nees_twist_ang_inside_percent, 1):>9} "
                     f"{f(r.e2e_fps, 1):>8}")
    return "\n".join(lines)


def _check_output_file(output: str) -> Path:
    """Fail before a long run, not after it, when ``--output`` cannot be a file."""
    out = Path(output)
    if out.is_dir():
        raise OutputError(f"--output {out} is a directory; name the JSON file to write")
    if not out.parent.is_dir():
        what = "does not exist" if not out.parent.exists() else "is not a directory"
        raise OutputError(f"cannot write {out}: {out.parent} {what}")
    return out


LEGEND = ("ATE after Sim(3) alignment (evo); 'moving' = frames whose position changed (on pure_rotation "
          "any is invented translation); ms/frame = median processing time, decoding excluded (p95ms: its 95th "
          "percentile); metric rows "
          "(epi_vo[source]): scale = median estimated / GT step length, SE3ATE% = ATE with SE(3) alignment only "
          "(no scale), % of path; held = poses published before the source established metres (held at the "
          "map's origin, VO units): a metric row's trajectory figures are over its other poses.\n"
          "NEES pos / rot = mean normalised estimation error squared of the tracking "
          "frames against the published /vo/odometry covariance (3 dof, consistent: 3), after the global scale "
          "(Sim(3) anchored at the odometry origin; SE(3) when metric); in 3σ % = share within the chi-square "
          "3-dof 99 % bound 11.345 (n/a: no tracking frame, e.g. a static or rotating camera); NEES v / w = "
          "the same for the published twist (linear / angular velocity) against the ground truth's velocity, "
          "with their share inside the same bound (in 3σ v / w %); "
          "e2e fps = end-to-end replay frames/s.")


def row_dict(r: BenchRow) -> dict[str, object]:
    """A row for JSON (n/a is null: strict JSON has no NaN)."""
    d = dataclasses.asdict(r)
    d["keyframes_per_frame"] = r.keyframes_per_frame
    return {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in d.items()}


def run_benchmark(bags_dir: str | None, kitti_dir: str | None, params: str | None, output: str | None,
                  record_dir: Path | None = None) -> int:
    """The bundled bags (and the KITTI clip): the table on stdout, as JSON in ``output``, and as a dated
    record (``bench_record``) under ``record_dir`` when given."""
    header = RecordHeader.now()
    started = time.perf_counter()
    cfg = load_config(params)
    out = _check_output_file(output) if output else None
    if bags_dir is not None and not Path(bags_dir).is_dir():
        raise EpiVoError(f"benchmark: --bags {bags_dir} is not a directory")
    datasets = find_datasets(bags_dir, kitti_dir)
    if not datasets:
        raise EpiVoError("benchmark: no bags found (expected bags/<name>/bag with groundtruth_tum.txt)")
    rows: list[BenchRow] = []
    checks: list[tuple[str, GroundTruthCheck | None, str]] = []
    for name, bag, gt in datasets:
        start = len(rows)
        try:
            check: GroundTruthCheck | None = check_ground_truth(bag, tum.read_tum(gt))
            checks.append((name, check, ""))
        except EpiVoError as exc:
            check = None
            checks.append((name, None, str(exc)))
        rows.append(bench_epi_vo(name, bag, gt, cfg, checked=check))
        for label, values in METRIC_VARIANTS.get(name, ()):
            rows.append(bench_epi_vo(name, bag, gt, dataclasses.replace(cfg, **values), f"epi_vo[{label}]",
                                     checked=check))
        rows.append(bench_reference(name, bag, gt))
        print("\n".join(format_table(rows[start:]).splitlines()[2:]), flush=True)
    table, checked = format_table(rows), format_checks(checks, rows)
    print()
    print(table)
    print("\n" + LEGEND)
    print()
    print(checked)
    if out is not None:
        try:
            out.write_text(json.dumps([row_dict(r) for r in rows], indent=2, allow_nan=False) + "\n")
        except OSError as exc:
            raise OutputError(f"cannot write {out}: {exc.strerror or exc}") from None
    if record_dir is not None:
        elapsed = time.perf_counter() - started
        markdown = "\n\n".join([
            header.markdown("epi-vo benchmark: the bundled bags and the KITTI clip",
                            {"benchmark time": f"{elapsed:.0f} s", "load average at the end": load_now()}),
            "```\n" + table + "\n```", LEGEND.replace("\n", "\n\n"), "```\n" + checked + "\n```"])
        md, js = write_record(record_dir, "bundled", markdown,
                              {"header": dataclasses.asdict(header), "benchmark_s": elapsed, "legend": LEGEND,
                               "rows": [row_dict(r) for r in rows]}, header.date, header.commit)
        print(f"\nrecorded in {md} and {js}")
    return 0
