"""The pose covariance's keyframe steps against the ground truth, from replays with ground truth.

The published rotation covariance grows by one step per keyframe (a random walk). This checks the two
things that model assumes, per replay output directory (``epi-vo replay BAG --output DIR`` of a bag
with ground truth):

* each keyframe step's rotation error against the covariance the step added: the step NEES (3 dof,
  consistent: 3) and the RMS error against the RMS predicted sigma, per axis (deg);
* that consecutive steps are independent: the lag-1 correlation of the step errors per axis (0 for a
  random walk) and the variance of the sum of ``m`` consecutive steps over ``m`` x a step's variance
  (1 for a random walk; above 1: the errors add up coherently, a drift).

A step's error is the difference of two consecutive tracking keyframes' rotation errors (odometry
frame, anchored at the odometry origin as the benchmark's NEES is); its covariance the difference of
their published rotation blocks.

It also prints every tracking frame's rotation NEES relative to the keyframe it was estimated from,
by the number of frames since that keyframe (3 at every count if the covariance relative to the
keyframe grows as the error does; on ground_robot 1.45, 0.53, 0.41 at 1, 2, 3 frames: it grows, the
error does not).

    .venv/bin/epi-vo replay bags/ground_robot --output /tmp/gr
    .venv/bin/python scripts/keyframe_steps.py /tmp/gr/bag [more replay dirs]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Steps:
    steps: int
    nees_mean: float
    nees_median: float
    rms_error_deg: np.ndarray  # (3,) per axis
    rms_sigma_deg: np.ndarray  # (3,)
    lag1: np.ndarray  # (3,)
    sum_ratio: np.ndarray  # (3,) var(sum of m steps) / (m var(step))


def step_statistics(errors: np.ndarray, covariances: np.ndarray, m: int = 10) -> Steps:
    """``errors`` (K, 3): the rotation error (rad) of K consecutive keyframes; ``covariances`` (K, 3, 3):
    their published rotation covariances. Steps whose covariance did not grow (not positive definite)
    get no NEES."""
    e = np.asarray(errors, dtype=np.float64)
    P = np.asarray(covariances, dtype=np.float64)
    d, dP = np.diff(e, axis=0), np.diff(P, axis=0)
    nees = np.array([x @ np.linalg.solve(Q, x) for x, Q in zip(d, dP, strict=True)
                     if np.linalg.eigvalsh(0.5 * (Q + Q.T))[0] > 0.0])
    lag1 = np.array([np.corrcoef(d[:-1, k], d[1:, k])[0, 1] if d.shape[0] > 2 else np.nan for k in range(3)])
    groups = d.shape[0] // m
    if groups:
        sums = d[: groups * m].reshape(groups, m, 3).sum(axis=1)
        ratio = (sums**2).mean(axis=0) / (m * (d**2).mean(axis=0))
    else:
        ratio = np.full(3, np.nan)
    sigma = np.sqrt(np.mean(np.einsum("nii->ni", dP), axis=0)) if dP.size else np.full(3, np.nan)
    return Steps(int(d.shape[0]), float(nees.mean()) if nees.size else float("nan"),
                 float(np.median(nees)) if nees.size else float("nan"),
                 np.degrees(np.sqrt((d**2).mean(axis=0))) if d.size else np.full(3, np.nan),
                 np.degrees(sigma), lag1, ratio)


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3)."""
    from epi_vo.tools.evaluation import rotation_vectors

    return rotation_vectors(R)


def since_keyframe_nees(R_est: np.ndarray, R_gt: np.ndarray, P_rot: np.ndarray, pairs: list[tuple[int, int, int]],
                        cap: int = 8) -> dict[int, tuple[int, float]]:
    """The rotation NEES of each frame relative to its keyframe, by the number of frames since it.

    ``R_est`` / ``R_gt`` (N, 3, 3) the published and true rotations, ``P_rot`` (N, 3, 3) the published
    rotation covariances (odometry frame); ``pairs`` (keyframe row, frame row, frames since the keyframe).
    A frame's error relative to its keyframe is ``log((R_gt_k^T R_gt_i)^T R_est_k^T R_est_i)``, in the
    keyframe's frame; its predicted covariance what the frame's covariance added to the keyframe's,
    rotated there (pairs where it did not grow are left out). Returns {frames since (capped at
    ``cap``): (frames, mean NEES)}: 3 at every count if the pose's covariance relative to its keyframe
    grows as its error does."""
    by: dict[int, list[float]] = {}
    for k, i, n in pairs:
        rel_gt = R_gt[k].T @ R_gt[i]
        rel_est = R_est[k].T @ R_est[i]
        e = _rotvec((rel_gt.T @ rel_est)[None])[0]
        Q = R_est[k].T @ (P_rot[i] - P_rot[k]) @ R_est[k]
        Q = 0.5 * (Q + Q.T)
        if np.linalg.eigvalsh(Q)[0] > 0.0:
            by.setdefault(min(n, cap), []).append(float(e @ np.linalg.solve(Q, e)))
    return {n: (len(v), float(np.mean(v))) for n, v in sorted(by.items())}


def _load(directory: Path) -> tuple[list[dict], dict[int, int], np.ndarray, np.ndarray, np.ndarray]:
    """A replay output directory's frame records, the odometry row of each stamp, the published and true
    rotations (odometry frame, anchored at the odometry origin) and the published rotation covariances."""
    from epi_vo.core.transforms import invert_T
    from epi_vo.io import tum
    from epi_vo.io.odometry_bag import read_odometry
    from epi_vo.tools import evaluation as ev

    records = [json.loads(line) for line in (directory / "frames.jsonl").read_text().splitlines() if line.strip()]
    odometry = read_odometry(directory / "output.mcap")
    gt_stamps, gt_pos, gt_quat = (np.asarray(a, dtype=np.float64) for a in tum.read_tum(directory / "groundtruth.tum"))
    j = ev.nearest_rows(gt_stamps, odometry.stamps_ns * 1e-9)
    T_est = ev.poses_from_xyz_quat(odometry.positions, odometry.quats_xyzw)
    T_gt = ev.poses_from_xyz_quat(gt_pos[j], gt_quat[j]) @ invert_T(ev.default_T_base_cam())
    R = T_gt[0, :3, :3] @ T_est[0, :3, :3].T  # the odometry origin's alignment
    R_gt = np.einsum("ij,njk->nik", R.T, T_gt[:, :3, :3])  # the truth in the odometry frame
    row = {int(s): i for i, s in enumerate(odometry.stamps_ns)}
    return records, row, T_est[:, :3, :3], R_gt, odometry.pose_covariance[:, 3:, 3:]


def replay_steps(directory: Path, m: int = 10) -> Steps:
    """``step_statistics`` of a replay output directory's tracking keyframes."""
    records, row, R_est, R_gt, P_rot = _load(directory)
    errors = _rotvec(np.einsum("nij,nkj->nik", R_gt, R_est))  # log(R_gt R_est^T): in the odometry frame
    rows = [row[r["stamp_ns"]] for r in records
            if r.get("is_keyframe") and r.get("state") == "tracking" and r.get("stamp_ns") in row]
    return step_statistics(errors[rows], P_rot[rows], m)


def replay_since_keyframe(directory: Path) -> dict[int, tuple[int, float]]:
    """``since_keyframe_nees`` of a replay output directory: every tracking frame against the tracking
    keyframe it was estimated from (the last one before it)."""
    records, row, R_est, R_gt, P_rot = _load(directory)
    pairs, last = [], None
    for r in records:
        i = row.get(r.get("stamp_ns", -1))
        if i is None:
            continue
        if r.get("state") == "tracking" and last is not None:
            pairs.append((last[0], i, r["index"] - last[1]))
        if r.get("is_keyframe"):
            last = (i, r["index"]) if r.get("state") == "tracking" else None
    return since_keyframe_nees(R_est, R_gt, P_rot, pairs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="epi-vo replay output directories with ground truth")
    parser.add_argument("-m", type=int, default=10, help="steps summed for the coherence ratio")
    args = parser.parse_args(argv)

    def axes(a: np.ndarray, nd: int) -> str:
        return " / ".join(f"{x:.{nd}f}" for x in a)

    for d in args.dirs:
        if not (d / "groundtruth.tum").is_file():
            print(f"{d}: no groundtruth.tum (not a replay output with ground truth)", file=sys.stderr)
            return 2
        s = replay_steps(d, args.m)
        print(f"{d}: {s.steps} keyframe steps, rotation step NEES mean {s.nees_mean:.2f} (median "
              f"{s.nees_median:.2f}); RMS step error {axes(s.rms_error_deg, 4)} deg against predicted "
              f"{axes(s.rms_sigma_deg, 4)}; lag-1 correlation {axes(s.lag1, 2)}; sum of {args.m} steps "
              f"{axes(s.sum_ratio, 2)} x independent")
        since = replay_since_keyframe(d)
        print("  rotation NEES relative to the keyframe, by frames since it: " + ", ".join(
            f"{n}{'+' if n == max(since) and n >= 8 else ''}: {v:.2f} ({c})" for n, (c, v) in since.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
