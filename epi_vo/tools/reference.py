"""The seed article's minimal OpenCV pipeline (section 10), chained frame to frame: the benchmark baseline.

Per frame, exactly as the article: ORB (3000 features) on the frame, brute-force Hamming kNN
matching (k=2) against the previous frame with Lowe's ratio test at 0.75, ``findEssentialMat`` with
USAC_MAGSAC (prob 0.999, threshold 1 px), ``recoverPose`` on the E inliers. The translation of every
step is the unit vector recoverPose returns: monocular two-view geometry has no scale, so the
chained trajectory is in "one unit per frame" and only comparable to ground truth after Sim(3)
alignment (see ``epi_vo.tools.evaluation``).

Distortion: the article passes raw pixels with K and says to undistort first when distortion is not
negligible. Here, when D is non-zero, keypoints are undistorted once per frame with
``cv2.undistortPoints(pts, K, D, P=K)`` (ideal pinhole pixels of the same K), so the article's calls
with K stay unchanged.

Conventions: ``recoverPose(E, pts_prev, pts_cur, K)`` returns R, t with X_cur = R X_prev + t, i.e.
T_cur_prev (previous-camera points into the current camera). The pose chain is
T_w_cur = T_w_prev @ inv(T_cur_prev); the first frame defines the world, T_w_c = I.

The knobs below are the article's values, fixed on purpose: this module is the reference the
project's own pipeline is measured against, not a pipeline to tune.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.errors import CameraModelError, ImageConversionError

_ORB_FEATURES = 3000  # cv.ORB_create(nfeatures=3000)
_RATIO = 0.75  # Lowe's ratio test: keep m if m.distance < 0.75 * n.distance
_RANSAC_PROB = 0.999  # findEssentialMat confidence
_RANSAC_THRESHOLD_PX = 1.0  # findEssentialMat inlier threshold, pixels
# The article gives no gate of its own; 8 matches is the usual floor for an E estimate (the 8-point
# algorithm's minimum; the 5-point solver inside RANSAC needs fewer but leaves no redundancy).
_MIN_MATCHES = 8
# Distortion vector lengths OpenCV's pinhole model accepts (0 = no distortion).
_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


@dataclass(frozen=True)
class ReferenceResult:
    """Outcome of one frame. On failure the pose holds: ``T_w_c`` is the previous frame's pose."""

    stamp_s: float  # stamp of the frame, seconds
    ok: bool  # a relative pose was recovered for this frame (the first frame is ok by definition)
    T_w_c: NDArray[
        np.float64
    ]  # (4, 4) camera pose, camera points into world; read-only copy
    n_matches: int  # ratio-test matches with the previous frame
    n_inliers: (
        int  # USAC_MAGSAC inliers of E among those matches (0 when E was not estimated)
    )
    ms: float  # processing time of this frame (detection to pose), milliseconds


class ReferencePipeline:
    """Frame-to-frame monocular VO exactly as the article's section 10; owns the pose chain."""

    def __init__(self, K: NDArray[np.float64], D: NDArray[np.float64]) -> None:
        """Create the pipeline for one calibrated camera.

        Args:
            K: (3, 3) intrinsic matrix of the image resolution that ``process`` will receive.
            D: (n,) OpenCV pinhole distortion coefficients, n in {0, 4, 5, 8, 12, 14}; all zero
                (or empty) means the pixels are used as they are, as in the article.

        Raises:
            CameraModelError: K or D malformed or non-finite, or K not an upper-triangular
                intrinsic matrix with positive focal lengths.
        """
        self._K = _checked_K(K)
        self._D = _checked_D(D)
        self._undistort = bool(np.any(self._D != 0.0))
        self._orb = cv2.ORB_create(nfeatures=_ORB_FEATURES)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._T_w_c = np.eye(4)
        # Previous frame's detections, kept so each frame is detected once: (M, 2) pixels
        # (undistorted when D is non-zero) and the (M, 32) ORB descriptors, or None before the
        # first frame / when the previous frame had no keypoints.
        self._pts_prev: NDArray[np.float64] | None = None
        self._des_prev: NDArray[np.uint8] | None = None
        self._started = False

    def process(self, gray: NDArray[np.uint8], stamp_s: float) -> ReferenceResult:
        """Estimate the pose of a new frame from its predecessor.

        The pair is always (previous frame, this frame), whether or not the previous frame was
        tracked: the article's pipeline is frame to frame. When this frame fails (fewer than 8
        matches, no usable E, recoverPose finds no valid pose) the pose holds, which amounts to
        assuming no motion since the previous frame. A frame with no texture therefore also makes
        the next frame fail (nothing to match against); tracking resumes on the one after.

        Args:
            gray: (H, W) uint8 grayscale image.
            stamp_s: stamp of the image, seconds.

        Returns:
            The frame's result; ``T_w_c`` is the identity on the first frame.

        Raises:
            ImageConversionError: ``gray`` is not a 2-D uint8 array.
        """
        if not isinstance(gray, np.ndarray) or gray.ndim != 2 or gray.dtype != np.uint8:
            got = (
                f"{gray.dtype} array of shape {gray.shape}"
                if isinstance(gray, np.ndarray)
                else type(gray).__name__
            )
            msg = f"ReferencePipeline.process expects a 2-D uint8 grayscale image, got {got}"
            raise ImageConversionError(msg)
        start = time.perf_counter()
        keypoints, des_cur = self._orb.detectAndCompute(gray, None)
        pts_cur = self._keypoint_pixels(keypoints)
        pts_prev, des_prev = self._pts_prev, self._des_prev
        self._pts_prev, self._des_prev = pts_cur, des_cur

        if not self._started:
            self._started = True
            return self._result(stamp_s, True, 0, 0, start)

        if des_prev is None or des_cur is None or pts_prev is None:
            return self._result(stamp_s, False, 0, 0, start)
        # knn[i]: the two nearest current-frame descriptors (trainIdx) of previous descriptor i.
        knn = self._matcher.knnMatch(des_prev, des_cur, k=2)
        # A query with fewer than two neighbours (tiny train set) cannot pass the ratio test.
        good = [
            pair[0]
            for pair in knn
            if len(pair) == 2 and pair[0].distance < _RATIO * pair[1].distance
        ]
        n_matches = len(good)
        if n_matches < _MIN_MATCHES:
            return self._result(stamp_s, False, n_matches, 0, start)
        p_prev = pts_prev[[m.queryIdx for m in good]]
        p_cur = pts_cur[[m.trainIdx for m in good]]

        # findEssentialMat(pts_a, pts_b, K) gives E with x_b^T E x_a = 0, a = previous, b = current.
        E, mask = cv2.findEssentialMat(
            p_prev,
            p_cur,
            self._K,
            method=cv2.USAC_MAGSAC,
            prob=_RANSAC_PROB,
            threshold=_RANSAC_THRESHOLD_PX,
        )
        if (
            E is None
            or mask is None
            or E.ndim != 2
            or E.shape[1] != 3
            or E.shape[0] < 3
        ):
            return self._result(stamp_s, False, n_matches, 0, start)
        # With several solutions OpenCV stacks them as (3k, 3); like the article, take the first.
        E = E[:3]
        inlier = mask.ravel() != 0
        n_inliers = int(np.count_nonzero(inlier))
        if n_inliers < 5 or not np.isfinite(E).all():
            # Fewer than 5 inliers cannot even constrain E (5-point minimum).
            return self._result(stamp_s, False, n_matches, n_inliers, start)

        # recoverPose(E, pts_prev, pts_cur, K): R, t map previous-camera points into the current
        # camera, X_cur = R X_prev + t, with |t| = 1; n_front counts points passing cheirality.
        try:
            n_front, R_cur_prev, t_cur_prev, _ = cv2.recoverPose(
                E, p_prev[inlier], p_cur[inlier], self._K
            )
        except cv2.error:
            return self._result(stamp_s, False, n_matches, n_inliers, start)
        if n_front <= 0 or not (
            np.isfinite(R_cur_prev).all() and np.isfinite(t_cur_prev).all()
        ):
            # No point in front of both cameras: none of the four (R, t) candidates is supported.
            return self._result(stamp_s, False, n_matches, n_inliers, start)

        T_cur_prev = np.eye(4)
        T_cur_prev[:3, :3] = R_cur_prev
        T_cur_prev[:3, 3] = t_cur_prev.ravel()
        self._T_w_c = self._T_w_c @ _inverse_se3(T_cur_prev)
        return self._result(stamp_s, True, n_matches, n_inliers, start)

    def _keypoint_pixels(
        self, keypoints: tuple[cv2.KeyPoint, ...]
    ) -> NDArray[np.float64]:
        """Keypoint positions as (M, 2) pixels, undistorted to ideal pinhole pixels of K when D != 0."""
        pts = np.array([kp.pt for kp in keypoints], dtype=np.float64).reshape(-1, 2)
        if self._undistort and len(pts) > 0:
            pts = cv2.undistortPoints(
                pts.reshape(-1, 1, 2), self._K, self._D, P=self._K
            ).reshape(-1, 2)
        return pts

    def _result(
        self, stamp_s: float, ok: bool, n_matches: int, n_inliers: int, start: float
    ) -> ReferenceResult:
        T_w_c = self._T_w_c.copy()
        T_w_c.flags.writeable = False
        return ReferenceResult(
            stamp_s=float(stamp_s),
            ok=ok,
            T_w_c=T_w_c,
            n_matches=n_matches,
            n_inliers=n_inliers,
            ms=(time.perf_counter() - start) * 1e3,
        )


def _inverse_se3(T_a_b: NDArray[np.float64]) -> NDArray[np.float64]:
    """(4, 4) rigid transform T_a_b -> T_b_a, using R^T instead of a general inverse."""
    T_b_a = np.eye(4)
    T_b_a[:3, :3] = T_a_b[:3, :3].T
    T_b_a[:3, 3] = -T_a_b[:3, :3].T @ T_a_b[:3, 3]
    return T_b_a


def _checked_K(K: NDArray[np.float64]) -> NDArray[np.float64]:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        msg = f"K must be a finite (3, 3) matrix, got shape {K.shape}" + (
            "" if K.shape != (3, 3) else " with non-finite values"
        )
        raise CameraModelError(msg)
    if (
        K[0, 0] <= 0.0
        or K[1, 1] <= 0.0
        or K[1, 0] != 0.0
        or K[2, 0] != 0.0
        or K[2, 1] != 0.0
        or K[2, 2] != 1.0
    ):
        msg = f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (uncalibrated?), got {K.tolist()}"
        raise CameraModelError(msg)
    return K


def _checked_D(D: NDArray[np.float64]) -> NDArray[np.float64]:
    D = np.asarray(D, dtype=np.float64).ravel()
    if D.size not in _DIST_LENGTHS or not np.isfinite(D).all():
        msg = f"D must hold {_DIST_LENGTHS} finite coefficients (OpenCV pinhole model), got {D.tolist()}"
        raise CameraModelError(msg)
    return D
