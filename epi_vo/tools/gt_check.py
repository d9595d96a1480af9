"""Does the ground truth agree with the images? A check before the ground truth judges a covariance.

A covariance check (NEES) takes the ground truth as exact. When the ground truth's relative poses are
wrong by as much as the estimate's, the NEES measures the ground truth. This check asks the images:
for pairs of frames ``gap`` apart it matches SIFT features between the two images (an estimator of its
own, independent of the pipeline's KLT), fits the images' own relative pose (5-point RANSAC and
``recoverPose``) and measures the median Sampson distance (px) of the matches under that pose and under
the ground truth's relative pose. Where the ground truth is right, both are at the image noise; where it
is wrong, the ground truth's is several times the images' own.

A camera that does not translate between the two frames (pure rotation, a static camera: the ground
truth's baseline below ``MIN_BASELINE`` of its mean step) has no epipolar geometry: the pair is judged by
the transfer distance under the rotation's homography K R K^-1 instead (the images' own: a fitted
homography).

A scene that is one plane (bags/planar) leaves the images' own pose ambiguous (the plane's two
solutions: its rotation and direction columns say nothing there) but the distances still judge the
ground truth, with less sensitivity: 0.4 deg of ground-truth error over 4 frames adds 0.5 px there,
2-3 px in a general scene.

Found with it: the KITTI clip's ground truth contradicts its images over its first 12
frames (median Sampson distance 0.9-2.5 px under the ground truth against 0.10-0.15 px under the images'
own pose; relative rotations 0.3-0.5 deg apart over 4 frames), and agrees from frame 12 on (0.13-0.36 px
against 0.09-0.21 px).
"""

from __future__ import annotations

import argparse
import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core import geometry
from epi_vo.core.camera import CameraModel
from epi_vo.core.errors import EpiVoError
from epi_vo.core.geometry import skew
from epi_vo.core.transforms import rotation_angle_deg
from epi_vo.io import bagio, tum
from epi_vo.io.trajectory import StampedPoses
from epi_vo.tools.evaluation import nearest_rows, poses_from_xyz_quat

F64 = NDArray[np.float64]

DEFAULT_GAP = 4  # frames between the two images of a pair (pairs follow each other: 0-4, 4-8, ...)
AGREE_EXCESS_PX = 0.5  # the ground truth agrees when it moves the matches by at most this beyond the image noise
MIN_MATCHES = 30  # fewer matches than this: the pair is not judged
MIN_BASELINE = 1e-3  # a baseline below this share of the ground truth's mean step is "no translation"
RANSAC_PX = 1.0  # the images' own fit's inlier threshold (px)
MAX_TIME_DIFF = 0.01  # s between an image stamp and its ground-truth pose


@dataclass(frozen=True)
class PairCheck:
    """One pair of frames: ``first`` and ``second`` are frame indices (0-based, in bag order, as the
    replay's frames.jsonl), ``first_ns`` / ``second_ns`` their image stamps."""

    first: int
    second: int
    first_ns: int
    second_ns: int
    matches: int  # inliers of the images' own fit: the matches measured
    gt_px: float  # median distance of the matches under the ground truth's relative pose (px)
    image_px: float  # the same under the images' own relative pose
    rotation_deg: float  # angle between the two relative rotations
    direction_deg: float  # angle between the two translation directions (NaN: no translation)
    model: str  # "epipolar" or "rotation" (no translation: homography transfer)
    agrees: bool | None  # None: not judged (too few matches)
    motion: int = 1  # which of the motions in view: 1 the dominant, 2 the next (a mover dominated)


@dataclass(frozen=True)
class GroundTruthCheck:
    pairs: list[PairCheck]
    confirmed_from: int | None  # first frame from which every judged pair agrees (None: the last disagrees)
    confirmed_from_ns: int | None

    @property
    def disagreeing(self) -> list[PairCheck]:
        return [p for p in self.pairs if p.agrees is False]

    def summary(self) -> str:
        judged = [p for p in self.pairs if p.agrees is not None]
        if not judged:
            return "not judged: no pair of frames with enough matches"
        bad = self.disagreeing
        if not bad:
            return (f"agrees with the images at all {len(judged)} pairs (median distance under the ground truth "
                    f"{_span(p.gt_px for p in judged)} px, under the images' own pose "
                    f"{_span(p.image_px for p in judged)} px)")
        where = ", ".join(f"{p.first}-{p.second}" for p in bad)
        tail = ("the last pair disagrees: no frame is confirmed" if self.confirmed_from is None
                else f"confirmed from frame {self.confirmed_from}")
        return (f"contradicts the images at {len(bad)} of {len(judged)} pairs ({where}: "
                f"{_span(p.gt_px for p in bad)} px under the ground truth against {_span(p.image_px for p in bad)} "
                f"px under the images' own pose, rotations {_span((p.rotation_deg for p in bad), 2)} deg apart); "
                f"{tail}")


def _span(values: Iterator[float] | list[float], nd: int = 2) -> str:
    v = [x for x in values if math.isfinite(x)]
    if not v:
        return "n/a"
    lo, hi = min(v), max(v)
    return f"{lo:.{nd}f}" if round(lo, nd) == round(hi, nd) else f"{lo:.{nd}f}-{hi:.{nd}f}"


def excess_px(gt_px: float, image_px: float) -> float:
    """What the ground truth's pose adds to the matches' distance beyond the images' own (the image
    noise), in quadrature: sqrt(gt^2 - own^2), 0 when the ground truth fits as well."""
    return math.sqrt(max(gt_px * gt_px - image_px * image_px, 0.0))


def agrees(gt_px: float, image_px: float) -> bool:
    """The ground truth's pose moves the matches by at most ``AGREE_EXCESS_PX`` beyond the image noise:
    its error is below what a pose covariance of a few tenths of a pixel describes."""
    return excess_px(gt_px, image_px) <= AGREE_EXCESS_PX


def sampson_px(E: F64, x1: F64, x2: F64, f: float) -> F64:
    """Sampson distances (px, at focal length ``f``) of normalised correspondences x1 -> x2 under E
    (x2^T E x1 = 0)."""
    return f * np.sqrt(geometry.sampson_distance_sq(E, x1, x2))


def transfer_px(H: F64, x1: F64, x2: F64, f: float) -> F64:
    """Distances (px) of x2 from H x1 (normalised coordinates, H between them)."""
    return f * np.sqrt(geometry.transfer_errors_sq(H, x1, x2)[0])


def refine_pose(R: F64, t: F64, x1: F64, x2: F64, f: float) -> tuple[F64, F64]:
    """The images' own pose at their own noise, not at RANSAC's minimal sample's: Levenberg-Marquardt on
    the Sampson distances (``geometry.refine_relative_pose``), from RANSAC's pose."""
    out = geometry.refine_relative_pose(R, t, x1, x2)
    return (R, t / np.linalg.norm(t)) if out is None else (out[0], out[1])


def _fit_motion(x1: F64, x2: F64, R_gt: F64, t_gt: F64, f: float, translates: bool
                ) -> tuple[NDArray[np.bool_], float, float, float, float] | None:
    """The images' own motion fitted to x1 -> x2 (RANSAC, refined) and the ground truth against its
    inliers: (inliers, gt_px, image_px, rotation_deg, direction_deg); None when no model is found."""
    thr = RANSAC_PX / f
    if translates:
        E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), cv2.RANSAC, 0.999, thr)
        if E is None or E.shape != (3, 3) or mask is None:
            return None
        inl = mask.ravel() > 0
        _, R_im, t_im, _ = cv2.recoverPose(E, x1[inl], x2[inl], np.eye(3))
        R_im, t_im = refine_pose(R_im, t_im.ravel(), x1[inl], x2[inl], f)
        t_dir = t_gt / np.linalg.norm(t_gt)
        gt = sampson_px(skew(t_dir) @ R_gt, x1[inl], x2[inl], f)
        im = sampson_px(skew(t_im) @ R_im, x1[inl], x2[inl], f)
        direction = math.degrees(math.acos(min(1.0, abs(float(t_im @ t_dir)))))
    else:
        H, mask = cv2.findHomography(x1, x2, cv2.RANSAC, thr)
        if H is None or mask is None or abs(np.linalg.det(H)) < 1e-12:
            return None
        inl = mask.ravel() > 0
        gt = transfer_px(R_gt, x1[inl], x2[inl], f)
        im = transfer_px(H, x1[inl], x2[inl], f)
        R_im = geometry.rotation_from_homography(H, np.eye(3))  # normalised coordinates: K = I
        direction = math.nan
    return inl, float(np.median(gt)), float(np.median(im)), rotation_angle_deg(R_im @ R_gt.T), direction


def check_pair(x1: F64, x2: F64, T_w_c1: F64, T_w_c2: F64, f: float, translates: bool
               ) -> tuple[int, float, float, float, float, int] | None:
    """(matches, gt_px, image_px, rotation_deg, direction_deg, motion) for normalised matches x1 -> x2
    between two images whose ground-truth camera poses (camera into world) are ``T_w_c1``, ``T_w_c2``;
    None when no motion with ``MIN_MATCHES`` is found.

    The images' own motion is the one their matches support most. An independently moving object can
    support more matches than the static scene (static_mover: 21 px "disagreement" with a camera that
    does not move), so when the ground truth disagrees with it, the second motion is fitted to the
    matches left (``motion`` 2) and the ground truth is judged against that one if it agrees there."""
    T21 = np.linalg.inv(T_w_c2) @ T_w_c1  # x2 = R x1 + t
    R_gt, t_gt = T21[:3, :3], T21[:3, 3]
    left = np.arange(len(x1))
    first: tuple[int, float, float, float, float, int] | None = None
    for motion in (1, 2):
        if left.size < MIN_MATCHES:
            break
        fit = _fit_motion(x1[left], x2[left], R_gt, t_gt, f, translates)
        if fit is None or int(fit[0].sum()) < MIN_MATCHES:
            break
        inl, gt_px, im_px, rot, direction = fit
        result = (int(inl.sum()), gt_px, im_px, rot, direction, motion)
        if agrees(gt_px, im_px):
            return result
        first = first or result
        left = left[~inl]
    return first


def check_ground_truth(bag_path: str | Path, gt: StampedPoses, gap: int = DEFAULT_GAP,
                       max_features: int = 2000) -> GroundTruthCheck:
    """Check ``gt`` (TUM: stamps s, positions, x y z w quaternions of the camera's optical frame) against
    the images of the bag at ``bag_path`` (see module doc). Frames without a ground-truth pose within
    ``MAX_TIME_DIFF`` or with an image that cannot be decoded are left out of the pairs.

    Raises:
        EpiVoError: the bag cannot be read, ``gap`` < 1, or the ground truth cannot be used, with the reason:
            fewer than two poses, a zero quaternion, no image within ``MAX_TIME_DIFF`` of a pose (the two
            time ranges are named), no decodable image with camera_info among those that have one, or no two
            frames ``gap`` apart that both have one.
    """
    if gap < 1:
        raise EpiVoError(f"ground-truth check: gap must be at least 1 frame, not {gap}")
    gt_s, gt_p, gt_q = (np.asarray(a, dtype=np.float64) for a in gt)
    if gt_s.size < 2:
        raise EpiVoError("ground-truth check: fewer than two ground-truth poses")
    order = np.argsort(gt_s, kind="stable")  # nearest_rows needs the stamps in order; a file need not be
    gt_s, gt_p, gt_q = gt_s[order], gt_p[order], gt_q[order]
    zero = np.flatnonzero(np.linalg.norm(gt_q, axis=1) == 0.0)
    if zero.size:
        raise EpiVoError(f"ground-truth check: the ground-truth pose at {gt_s[zero[0]]:.6f} s has a zero quaternion "
                         "(no orientation)")
    steps = np.linalg.norm(np.diff(gt_p, axis=0), axis=1)
    min_baseline = MIN_BASELINE * float(np.mean(steps)) if np.mean(steps) > 0.0 else math.inf
    sift = cv2.SIFT_create(max_features)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    camera: CameraModel | None = None
    kept: list[tuple[int, int, F64, F64, np.ndarray]] = []  # index, stamp, T_w_c, keypoints (px), descriptors
    image_s: list[float] = []  # stamps of the images looked at
    with_gt = 0  # of them, those with a ground-truth pose within MAX_TIME_DIFF
    with bagio.open_camera_bag(bag_path, no_ground_truth=True) as bag:
        for index, frame in enumerate(bag.iter_frames()):
            if index % gap:
                continue
            image_s.append(frame.stamp_ns * 1e-9)
            j = int(nearest_rows(gt_s, np.array([frame.stamp_ns * 1e-9]))[0])
            if abs(gt_s[j] - frame.stamp_ns * 1e-9) > MAX_TIME_DIFF:
                continue
            with_gt += 1
            gray = bag.usable_gray(frame)
            if gray is None:
                continue
            if camera is None:  # the pipeline's camera model: distortion models, binning and roi
                camera = CameraModel.from_camera_info(frame.camera_info_msg)
            kps, desc = sift.detectAndCompute(gray, None)
            pts = np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)
            T = poses_from_xyz_quat(gt_p[j:j + 1], gt_q[j:j + 1])[0]
            kept.append((index, int(frame.stamp_ns), T, pts, desc))
    if not with_gt:
        raise EpiVoError(f"ground-truth check: no image of {bag_path} is within {MAX_TIME_DIFF} s of a ground-truth "
                         f"pose (images {min(image_s, default=math.nan):.3f}-{max(image_s, default=math.nan):.3f} s, "
                         f"ground truth {gt_s[0]:.3f}-{gt_s[-1]:.3f} s)")
    if camera is None:
        raise EpiVoError(f"ground-truth check: {bag_path} has no decodable image with camera_info among the "
                         f"{with_gt} frame(s) that have a ground-truth pose")
    f = float(camera.fx)
    pairs: list[PairCheck] = []
    for (i1, s1, T1, p1, d1), (i2, s2, T2, p2, d2) in itertools.pairwise(kept):
        if i2 - i1 != gap:
            continue
        matches = _ratio_matches(matcher, d1, d2)
        translates = float(np.linalg.norm(T2[:3, 3] - T1[:3, 3])) > min_baseline
        if len(matches) < MIN_MATCHES:
            pairs.append(PairCheck(i1, i2, s1, s2, len(matches), math.nan, math.nan, math.nan, math.nan,
                                   "epipolar" if translates else "rotation", None))
            continue
        a = np.array([m.queryIdx for m in matches])
        b = np.array([m.trainIdx for m in matches])
        x1, x2 = camera.normalize(p1[a]), camera.normalize(p2[b])
        model = "epipolar" if translates else "rotation"
        checked = check_pair(x1, x2, T1, T2, f, translates)
        if checked is None:
            pairs.append(PairCheck(i1, i2, s1, s2, 0, math.nan, math.nan, math.nan, math.nan, model, None))
            continue
        n, gt_px, im_px, rot, direction, motion = checked
        pairs.append(PairCheck(i1, i2, s1, s2, n, gt_px, im_px, rot, direction, model, agrees(gt_px, im_px),
                               motion))
    if not pairs:
        raise EpiVoError(f"ground-truth check: no two frames {gap} apart both have a ground-truth pose and a "
                         f"decodable image ({len(kept)} of the {len(image_s)} frames looked at, every {gap}th, have)")
    return GroundTruthCheck(pairs, *_confirmed_from(pairs, kept))


def _ratio_matches(matcher: cv2.BFMatcher, d1: np.ndarray | None, d2: np.ndarray | None) -> list:
    if d1 is None or d2 is None or len(d1) < 2 or len(d2) < 2:
        return []
    return [m for m, n in (x for x in matcher.knnMatch(d1, d2, k=2) if len(x) == 2) if m.distance < 0.7 * n.distance]


def _confirmed_from(pairs: list[PairCheck], kept: list) -> tuple[int | None, int | None]:
    """The first frame from which every judged pair agrees: the second frame of the last disagreeing
    pair, or the first frame kept when none disagrees; None when the last judged pair disagrees."""
    bad = [p for p in pairs if p.agrees is False]
    if not bad:
        return (kept[0][0], kept[0][1]) if kept else (None, None)
    last = bad[-1]
    if not any(p.agrees for p in pairs if p.first >= last.second):
        return None, None
    return last.second, last.second_ns


def format_check(check: GroundTruthCheck) -> str:
    lines = [f"{'pair':>9} {'matches':>7} {'model':>8} {'motion':>6} {'GT px':>7} {'own px':>7} {'excess':>7} "
             f"{'rot°':>6} {'dir°':>6}  agrees"]
    for p in check.pairs:
        verdict = "n/a" if p.agrees is None else ("yes" if p.agrees else "NO")
        lines.append(f"{p.first:>4}-{p.second:<4} {p.matches:>7} {p.model:>8} {p.motion:>6} {p.gt_px:>7.3f} "
                     f"{p.image_px:>7.3f} {excess_px(p.gt_px, p.image_px):>7.3f} {p.rotation_deg:>6.3f} "
                     f"{p.direction_deg:>6.2f}  {verdict}")
    lines.append(f"ground truth {check.summary()}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """``epi-vo gtcheck BAG --gt FILE [--gap N]``: print the check; exit status 0 when the ground truth
    agrees with the images at every judged pair, 1 when some pair disagrees; EpiVoError (exit status 2, one
    line with the reason) when the ground truth cannot be used or no pair could be judged."""
    bag = Path(args.bag)
    gt_file = args.gt
    if gt_file is None:  # the bundled layout: <name>/bag beside <name>/groundtruth_tum.txt
        candidates = [bag / "groundtruth_tum.txt", bag.parent / "groundtruth_tum.txt"]
        gt_file = next((c for c in candidates if c.is_file()), None)
        if gt_file is None:
            raise EpiVoError(f"gtcheck: no --gt given and no {candidates[1]}")
    check = check_ground_truth(bag, tum.read_tum(gt_file), gap=args.gap)
    print(format_check(check), flush=True)
    if not any(p.agrees is not None for p in check.pairs):  # no verdict: never "agrees"
        raise EpiVoError(f"ground-truth check: {check.summary()}")
    return 1 if check.disagreeing else 0
