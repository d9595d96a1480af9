"""Feature frontend: grid-bucketed corner detection, KLT tracking, ORB matching.

Pure functions on arrays; the pipeline owns the state (previous pyramid, tracks). Points are (N, 2)
float32 pixel coordinates of the raw image (before undistortion), as OpenCV's trackers want them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.config import Frontend, VoConfig
from epi_vo.core.decisions import Decision, Note, note

F32 = NDArray[np.float32]
Mask = NDArray[np.bool_]

# Iterations stop when the window moves less than a hundredth of a pixel (Lucas-Kanade) or three hundredths
# (corner refinement): an order below the tracks' own noise, so a later iteration changes no decision; the
# counts only bound the work on a window that does not converge (an ambiguous or blurred patch).
_LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.03)


def cell_index(pts: F32, width: int, height: int, rows: int, cols: int) -> NDArray[np.int64]:
    """The bucketing grid's cell (row-major, ``rows`` x ``cols`` over a ``width`` x ``height`` image) of each
    raw pixel (N, 2)."""
    c = np.clip((pts[:, 0] * cols / width).astype(np.int64), 0, cols - 1)
    r = np.clip((pts[:, 1] * rows / height).astype(np.int64), 0, rows - 1)
    return r * cols + c


def bucket_select(pts: F32, scores: NDArray[np.float64] | None, existing: F32, width: int, height: int,
                  cfg: VoConfig) -> Mask:
    """Choose candidates so that every grid cell holds at most its share of ``cfg.max_features``.

    Candidates are taken in order of decreasing ``scores`` (given order when None); cells already
    holding ``existing`` points get fewer new ones. Spreading features over the image keeps the
    two-view geometry well conditioned (a cluster of points behaves like a plane or a narrow FOV).
    """
    n_cells = cfg.grid_rows * cfg.grid_cols
    quota = -(-cfg.max_features // n_cells)  # ceil
    counts = np.bincount(cell_index(existing, width, height, cfg.grid_rows, cfg.grid_cols),
                         minlength=n_cells) if existing.shape[0] else np.zeros(n_cells, np.int64)
    order = np.argsort(-scores, kind="stable") if scores is not None else np.arange(pts.shape[0])
    cells = cell_index(pts, width, height, cfg.grid_rows, cfg.grid_cols)
    keep = np.zeros(pts.shape[0], dtype=bool)
    budget = cfg.max_features - existing.shape[0]
    for i in order:
        if budget <= 0:
            break
        cell = cells[i]
        if counts[cell] < quota:
            counts[cell] += 1
            keep[i] = True
            budget -= 1
    return keep


# ORB's default border (edgeThreshold = patchSize = 31) leaves no detectable pixel below ~2 x 31.
_ORB_MIN_SIDE_PX = 64


def min_image_side(cfg: VoConfig) -> int:
    """Smallest image width and height (px, after downscaling) the configured frontend can use.

    KLT needs its window twice over (corner refinement and the LK search); ORB its descriptor border.
    """
    if cfg.frontend is Frontend.ORB:
        return _ORB_MIN_SIDE_PX
    return 2 * cfg.klt_window_px + 2


def image_problem(width: int, height: int, cfg: VoConfig) -> str | None:
    """Why the frontend cannot use a ``width`` x ``height`` image, or None when it can."""
    need = min_image_side(cfg)
    if width < need or height < need:
        return (f"image {width}x{height} is too small for the {cfg.frontend} frontend (needs at least "
                f"{need} px per side)")
    return None


def detect_corners(gray: NDArray[np.uint8], existing: F32, cfg: VoConfig) -> F32:
    """New Shi-Tomasi corners away from ``existing`` points, bucketed over the grid (M, 2) float32.

    Corners are searched on the half-resolution image (``cv2.pyrDown``): the minimum-eigenvalue map of a
    full 640x480 frame alone costs ~5 ms, a quarter of that at half size, and KLT tracks the patch
    around a point whatever its sub-pixel origin. Coordinates map back by ``x = 2 x_half + 0.5``.
    """
    h, w = gray.shape
    need = cfg.max_features - existing.shape[0]
    if need <= 0:
        return np.zeros((0, 2), np.float32)
    half = cv2.pyrDown(gray)
    mask = np.full(half.shape, 255, np.uint8)
    radius = max(1, round(cfg.min_feature_distance_px / 2))
    for x, y in ((existing - 0.5) / 2).astype(np.int32):
        cv2.circle(mask, (int(x), int(y)), radius, 0, -1)
    found = cv2.goodFeaturesToTrack(half, maxCorners=3 * cfg.max_features, qualityLevel=cfg.corner_quality,
                                    minDistance=cfg.min_feature_distance_px / 2, mask=mask, blockSize=3)
    if found is None:
        return np.zeros((0, 2), np.float32)
    corners: F32 = (found.reshape(-1, 2) * 2.0 + 0.5).astype(np.float32)
    # goodFeaturesToTrack returns corners by decreasing quality: keep that order.
    corners = corners[bucket_select(corners, None, existing, w, h, cfg)]
    if corners.shape[0]:
        # Back to full-resolution corner positions (a 5x5 gradient fit per corner, ~0.2 ms for 200).
        corners = cast(F32, cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (2, 2), (-1, -1), _SUBPIX_CRITERIA))
    return corners.reshape(-1, 2)


# Exposure changes: Lucas-Kanade assumes each patch keeps its brightness, and a gain change between two
# frames biases every track (a 20 % change: 0.7 px on a synthetic texture) or loses them. The gain is
# measured on the tracks themselves (the median ratio of 5x5 patch means at both ends, over the leading
# EXPOSURE_MAX_TRACKS rows; from the image means when fewer than EXPOSURE_MIN_TRACKS survived). When it
# moves the mean grey level by EXPOSURE_MIN_LEVELS or more, the current image is scaled onto the previous
# one and tracked again; the second attempt is taken unless it keeps fewer of those tracks. When the whole
# image's mean grey level moved by EXPOSURE_MIN_LEVELS, its ratio is tracked again too (a large step keeps
# mostly the patches it changed least, which show none of it or a part), and the guess keeping the most
# tracks is taken. Without an exposure change the estimate still moves by a few levels (under 5: each patch's
# view changes): the threshold is about twice that noise. The track counts bound the median's noise from
# below and its cost from above.
EXPOSURE_MIN_LEVELS = 10.0
EXPOSURE_MIN_TRACKS = 20
EXPOSURE_MAX_TRACKS = 100


class KltTracks(NamedTuple):
    """``track_klt``'s result: the tracked points (N, 2), the tracks kept, the exposure gain the current
    image was tracked with, and each point's forward-backward error (N,) in pixels."""

    pts: F32
    ok: Mask
    gain: float
    fb: NDArray[np.float32]


def fb_noise_px(fb: NDArray[np.float32]) -> float:
    """Per-axis RMS (px) of the forward-backward errors of the kept tracks: the tracking noise this
    frame shows (NaN without tracks). LK's error from a patch deformed by perspective comes back the
    same way and cancels in it, so the real tracking error is several times larger (see
    ``VoConfig.twist_noise_fb_factor``)."""
    return math.sqrt(float(np.mean(np.square(fb, dtype=np.float64))) / 2.0) if fb.size else math.nan


def track_klt(gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], pts_prev: F32, cfg: VoConfig,
              gain: float | None = None) -> KltTracks:
    """Pyramidal Lucas-Kanade with a forward-backward check, tracked again on the current image scaled
    to the previous one's exposure when the two differ (``EXPOSURE_MIN_LEVELS``).

    (OpenCV's Python binding does not accept prebuilt pyramids, so each call builds its own.)

    The exposure is judged on the leading ``EXPOSURE_MAX_TRACKS`` rows only, so that a call on more
    rows decides as one on those rows alone did (tracking done ahead: ``epi_vo.runner``); ``gain`` applies
    that earlier decision
    (1.0: none) without judging again.

    Returns the tracked points (N, 2), a mask of tracks that converged both ways, came back within
    ``cfg.klt_max_fb_error_px`` of where they started and stayed inside the image, the gain the
    current image was tracked with and the forward-backward errors.
    """
    n = pts_prev.shape[0]
    if n == 0:
        return KltTracks(np.zeros((0, 2), np.float32), np.zeros(0, bool), 1.0 if gain is None else gain,
                         np.zeros(0, np.float32))
    if gain is not None:
        img = gray_cur if gain == 1.0 else cast(NDArray[np.uint8], cv2.convertScaleAbs(gray_cur, alpha=gain, beta=0.0))
        p1, ok, fb = _klt_both_ways(gray_prev, img, pts_prev, cfg)
        return KltTracks(p1, ok, gain, fb)
    p1, ok, fb = _klt_both_ways(gray_prev, gray_cur, pts_prev, cfg)
    lead = slice(0, EXPOSURE_MAX_TRACKS)
    lead_ok = ok[lead]
    # The tracks a large step lets through at all are those whose grey levels it moved least (dark or flat
    # patches): they may say "no change", or a part of it, while the whole image says the whole step. Both
    # guesses are tried; the one that keeps the most tracks is taken.
    guesses = [g for g in (exposure_change(gray_prev, gray_cur, pts_prev[lead][lead_ok], p1[lead][lead_ok]),
                           _whole_image_change(gray_prev, gray_cur)) if g is not None]
    best = KltTracks(p1, ok, 1.0, fb)
    n_best = int(np.count_nonzero(lead_ok))
    for measured in dict.fromkeys(guesses):
        mapped = cast(NDArray[np.uint8], cv2.convertScaleAbs(gray_cur, alpha=measured, beta=0.0))
        p1_m, ok_m, fb_m = _klt_both_ways(gray_prev, mapped, pts_prev, cfg)
        n_m = int(np.count_nonzero(ok_m[lead]))
        if n_m >= n_best:
            best, n_best = KltTracks(p1_m, ok_m, measured, fb_m), n_m
    return best


def _patch_means(gray: NDArray[np.uint8], pts: F32, r: int = 2) -> NDArray[np.float64]:
    """Mean grey level of the (2r+1)^2 patch around each point (rounded; clipped at the border)."""
    h, w = gray.shape[:2]
    x = np.clip(np.rint(pts[:, 0]).astype(np.int64), r, w - 1 - r)
    y = np.clip(np.rint(pts[:, 1]).astype(np.int64), r, h - 1 - r)
    d = np.arange(-r, r + 1)
    offsets = (d[:, None] * w + d[None, :]).ravel()
    means: NDArray[np.float64] = np.ascontiguousarray(gray).ravel()[(y * w + x)[:, None] + offsets].mean(axis=1)
    return means


def exposure_change(gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], pts_prev: F32, pts_cur: F32
                    ) -> float | None:
    """The gain mapping ``gray_cur``'s exposure onto ``gray_prev``'s: the median ratio of patch means
    at the two ends of the tracks (of the image means with fewer than ``EXPOSURE_MIN_TRACKS``); None
    when it moves the previous image's mean grey level by less than ``EXPOSURE_MIN_LEVELS``, when the
    image means do not change the same way by at least half as much, or when it cannot be measured."""
    if pts_prev.shape[0] >= EXPOSURE_MIN_TRACKS:
        a, b = _patch_means(gray_prev, pts_prev), _patch_means(gray_cur, pts_cur)
        unclipped = (a > 4.0) & (a < 251.0) & (b > 4.0) & (b < 251.0)
        if np.count_nonzero(unclipped) < EXPOSURE_MIN_TRACKS:
            return None
        gain = float(np.median(a[unclipped] / b[unclipped]))
        level = float(np.median(a[unclipped]))
    else:
        level, m = float(cv2.mean(gray_prev)[0]), float(cv2.mean(gray_cur)[0])
        if not m > 1.0:
            return None
        gain = level / m
    if abs(gain - 1.0) * level < EXPOSURE_MIN_LEVELS:
        return None
    if pts_prev.shape[0] >= EXPOSURE_MIN_TRACKS:
        # An exposure change moves the whole image the same way; the tracks' patches alone also change
        # as points move across a vignetted image or over new surroundings (KITTI every 3rd frame: the
        # tracks said +9 to +11 %, the image means -4 to -7 %).
        m_prev, m_cur = float(cv2.mean(gray_prev)[0]), float(cv2.mean(gray_cur)[0])
        whole = m_prev / m_cur if m_cur > 1.0 else 1.0
        if (whole - 1.0) * (gain - 1.0) <= 0.0 or abs(whole - 1.0) < 0.5 * abs(gain - 1.0):
            return None
    return gain


def pyramid_levels(height: int, width: int, cfg: VoConfig) -> int:
    """The pyramid levels above the image that KLT uses on a ``height`` x ``width`` image: ``klt_levels``,
    fewer where a level would be no larger than the window (OpenCV builds no such level)."""
    levels = 0
    while levels < cfg.klt_levels:
        height, width = (height + 1) // 2, (width + 1) // 2
        if height <= cfg.klt_window_px or width <= cfg.klt_window_px:
            break
        levels += 1
    return levels


def pyramid_reach_px(levels: int, cfg: VoConfig) -> float:
    """How far (px) a pyramid of ``levels`` levels follows a point from where its search starts: half a
    window at the coarsest level, ``2**levels`` pixels of the image each."""
    return float((cfg.klt_window_px // 2) * 2**levels)


def image_shift(gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], levels: int) -> NDArray[np.float32]:
    """The whole image's motion ``gray_prev`` -> ``gray_cur`` (px, (2,) float32): the phase correlation of
    the two images ``levels`` halvings down (``pyramid_levels``: the detail KLT itself starts from), zero
    when it cannot be measured."""
    a, b = gray_prev, gray_cur
    for _ in range(levels):
        a, b = cast(NDArray[np.uint8], cv2.pyrDown(a)), cast(NDArray[np.uint8], cv2.pyrDown(b))
    fa, fb_ = a.astype(np.float32), b.astype(np.float32)
    window = cv2.createHanningWindow((fa.shape[1], fa.shape[0]), cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(fa, fb_, window)
    shift = np.array([dx * gray_prev.shape[1] / a.shape[1], dy * gray_prev.shape[0] / a.shape[0]], np.float32)
    return shift if bool(np.all(np.isfinite(shift))) else np.zeros(2, np.float32)


def _whole_image_change(gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8]) -> float | None:
    """The gain mapping ``gray_cur``'s mean grey level onto ``gray_prev``'s, None when it moves it by less
    than ``EXPOSURE_MIN_LEVELS`` (or the current image is black)."""
    m_prev, m_cur = float(cv2.mean(gray_prev)[0]), float(cv2.mean(gray_cur)[0])
    if not m_cur > 1.0 or abs(m_prev - m_cur) < EXPOSURE_MIN_LEVELS:
        return None
    return m_prev / m_cur


def _klt_both_ways(gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], pts_prev: F32,
                   cfg: VoConfig) -> tuple[F32, Mask, NDArray[np.float32]]:
    """KLT from where each point was, or - when the whole image moved further than the pyramid follows
    (``pyramid_reach_px``) - from where the image's motion (``image_shift``) puts it.

    A camera's turn moves the image by an angle times the focal length, whatever the image's size, while
    the pyramid's reach is a fixed number of pixels: a 960 px camera taking off moves its image 100-150 px
    a frame. Started at the whole image's motion, a track has to follow only its own departure from it.
    That motion is one figure for the whole image; a scene of near and far parts (or a mover) can make it
    another part's, so a track lost from there is tracked again from where it was.
    """
    levels = pyramid_levels(gray_prev.shape[0], gray_prev.shape[1], cfg)
    shift = image_shift(gray_prev, gray_cur, levels)
    if float(np.hypot(shift[0], shift[1])) <= pyramid_reach_px(levels, cfg):
        return _klt_from(gray_prev, gray_cur, pts_prev, pts_prev, cfg)
    p1, ok, fb = _klt_from(gray_prev, gray_cur, pts_prev, pts_prev + shift, cfg)
    lost = np.flatnonzero(~ok)
    if lost.size:
        p1_z, ok_z, fb_z = _klt_from(gray_prev, gray_cur, pts_prev[lost], pts_prev[lost], cfg)
        p1[lost], ok[lost], fb[lost] = p1_z, ok_z, fb_z
    return p1, ok, fb


def _klt_from(gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], pts_prev: F32, start: F32,
              cfg: VoConfig) -> tuple[F32, Mask, NDArray[np.float32]]:
    """Pyramidal KLT of ``pts_prev`` with each search started at ``start``, and the forward-backward check."""
    win = (cfg.klt_window_px, cfg.klt_window_px)
    p0 = pts_prev.reshape(-1, 1, 2).astype(np.float32)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(gray_prev, gray_cur, p0,
                                          start.reshape(-1, 1, 2).astype(np.float32), winSize=win,
                                          maxLevel=cfg.klt_levels, criteria=_LK_CRITERIA,
                                          flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    # Backward pass seeded with the start points: a good track converges there at once, so the
    # full-resolution level alone suffices (0.9 ms instead of 1.6 with two levels, 200 points); a bad
    # one does not come back. Without the coarse level the check is also stricter: it drops the few tracks
    # behind occasional rotation errors of tenths of a degree between frames.
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(gray_cur, gray_prev, p1, p0.copy(), winSize=win, maxLevel=0,
                                           criteria=_LK_CRITERIA, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - pts_prev, axis=1)
    h, w = gray_cur.shape[:2]
    inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb <= cfg.klt_max_fb_error_px) & inside
    return p1.astype(np.float32), ok, fb.astype(np.float32)


@dataclass(frozen=True)
class OrbFeatures:
    """ORB keypoints of one image: (N, 2) float32 positions and (N, 32) uint8 descriptors."""

    pts: F32
    descriptors: NDArray[np.uint8]


def make_orb(cfg: VoConfig) -> cv2.ORB:
    return cv2.ORB.create(nfeatures=cfg.orb_features)


def detect_orb(orb: cv2.ORB, gray: NDArray[np.uint8], cfg: VoConfig) -> OrbFeatures:
    """ORB keypoints bucketed over the grid (strongest response first), with their descriptors."""
    kps, desc = orb.detectAndCompute(gray, None)
    if desc is None or not kps:
        return OrbFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8))
    pts = np.array([k.pt for k in kps], dtype=np.float32)
    resp = np.array([k.response for k in kps], dtype=np.float64)
    h, w = gray.shape
    keep = bucket_select(pts, resp, np.zeros((0, 2), np.float32), w, h, cfg)
    return OrbFeatures(pts[keep], cast(NDArray[np.uint8], desc)[keep])


def match_orb(desc_ref: NDArray[np.uint8], desc_cur: NDArray[np.uint8], ratio: float
              ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Hamming kNN matching with Lowe's ratio test and a mutual nearest-neighbour check.

    Returns index arrays ``(i_ref, i_cur)`` of the accepted matches.
    """
    empty = np.zeros(0, np.int64)
    if desc_ref.shape[0] < 2 or desc_cur.shape[0] < 2:
        return empty, empty
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    fwd = bf.knnMatch(desc_ref, desc_cur, k=2)
    bwd = bf.match(desc_cur, desc_ref)
    best_ref_for_cur = np.full(desc_cur.shape[0], -1, np.int64)
    for m in bwd:
        best_ref_for_cur[m.queryIdx] = m.trainIdx
    i_ref, i_cur = [], []
    for pair in fwd:
        if len(pair) < 2:
            continue
        m, second = pair
        if m.distance < ratio * second.distance and best_ref_for_cur[m.trainIdx] == m.queryIdx:
            i_ref.append(m.queryIdx)
            i_cur.append(m.trainIdx)
    return np.asarray(i_ref, np.int64), np.asarray(i_cur, np.int64)


KltTracker = Callable[[NDArray[np.uint8], NDArray[np.uint8], F32, VoConfig], tuple[KltTracks, float]]


def track_klt_now(gray_prev: NDArray[np.uint8], gray_cur: NDArray[np.uint8], pts_prev: F32, cfg: VoConfig
                  ) -> tuple[KltTracks, float]:
    """``track_klt`` computed now (no time spent ahead)."""
    return track_klt(gray_prev, gray_cur, pts_prev, cfg), 0.0


@dataclass(frozen=True)
class Tracked:
    """The features stage's result: the correspondences keyframe -> current image and what tracking saw."""

    pts: F32  # (N, 2) current raw pixels
    rows: NDArray[np.int64]  # (N,) keyframe row of each
    orb: OrbFeatures | None  # this image's ORB features (frontend 'orb')
    ahead_ms: float  # KLT done ahead of this call (ms; 0: now)
    gain: float  # the exposure gain the image was tracked with (1.0: unchanged)
    noise_px: float  # the tracking noise the kept tracks' forward-backward errors show (``fb_noise_px``)

    @property
    def notes(self) -> tuple[Note, ...]:
        """The stage's decision: an image scaled onto the previous exposure to be tracked."""
        return (note(Decision.EXPOSURE_CHANGED, gain=self.gain),) if self.gain != 1.0 else ()


def track(gray: NDArray[np.uint8], cfg: VoConfig, orb: cv2.ORB | None, gray_prev: NDArray[np.uint8] | None,
          pts_prev: F32, rows_prev: NDArray[np.int64], kf_descriptors: NDArray[np.uint8] | None,
          klt: KltTracker = track_klt_now) -> Tracked:
    """Correspondences keyframe -> current image (``Tracked``; the tracking noise is NaN for ORB).

    KLT (``orb`` None) follows the previous frame's points ``pts_prev`` (keyframe rows ``rows_prev``)
    into ``gray`` through ``klt`` (``track_klt``, possibly computed ahead: ``epi_vo.core.workers``); ORB
    detects in ``gray`` and matches against the keyframe's descriptors.
    """
    if orb is None:
        assert gray_prev is not None
        tracks, ms = klt(gray_prev, gray, pts_prev, cfg)
        ok = tracks.ok
        return Tracked(tracks.pts[ok], rows_prev[ok], None, ms, tracks.gain, fb_noise_px(tracks.fb[ok]))
    feats = detect_orb(orb, gray, cfg)
    assert kf_descriptors is not None
    i_kf, i_cur = match_orb(kf_descriptors, feats.descriptors, cfg.orb_ratio)
    return Tracked(feats.pts[i_cur], i_kf, OrbFeatures(feats.pts, feats.descriptors), 0.0, 1.0, math.nan)
