"""Camera model built from sensor_msgs/CameraInfo fields.

Pixel conventions: ``pts`` are (N, 2) float pixel coordinates of the *raw* (distorted) image;
``uv`` are (N, 2) pixel coordinates of the ideal pinhole camera with the same K (undistorted);
``xn`` are (N, 2) normalized image coordinates, ``xn = K^-1 [uv; 1]``. All thresholds of the
two-view geometry are expressed in ``uv`` pixels.

Distortion models follow ROS (REP-104 / image_geometry): ``plumb_bob`` (k1 k2 p1 p2 k3),
``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6), ``equidistant`` (fisheye k1 k2 k3 k4, OpenCV
``cv2.fisheye``). Reference: Hartley & Zisserman sec. 7.4 (radial distortion).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.errors import CameraModelError, quoted

# Iterative undistortion: OpenCV's default 5 iterations leave ~0.1 px error at the corners of a
# moderately distorted lens; 30 iterations converge to < 1e-4 px for the models we accept.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)


class DistortionModel(enum.Enum):
    PLUMB_BOB = "plumb_bob"
    RATIONAL_POLYNOMIAL = "rational_polynomial"
    EQUIDISTANT = "equidistant"


# Accepted lengths of D per model (OpenCV coefficient order).
_D_LENGTHS = {
    DistortionModel.PLUMB_BOB: (4, 5),
    DistortionModel.RATIONAL_POLYNOMIAL: (8,),
    DistortionModel.EQUIDISTANT: (4,),
}


class CameraModelCache:
    """Builds a CameraModel only when the camera_info content changes, not once per frame.

    Holds one model: a calibration that keeps changing must not grow memory.
    """

    def __init__(self) -> None:
        self._key: tuple[Any, ...] | None = None
        self._camera: CameraModel | None = None

    def get(self, msg: Any) -> CameraModel:
        """The model of a CameraInfo-like ``msg``; raises CameraModelError as ``from_camera_info``."""
        key = (int(msg.width), int(msg.height), str(msg.distortion_model), tuple(np.asarray(msg.k).tolist()),
               tuple(np.asarray(msg.d).tolist()), _binning_roi(msg))
        if key != self._key or self._camera is None:
            self._camera = CameraModel.from_camera_info(msg)
            self._key = key
        return self._camera


# Plausible intrinsics. Focal lengths outside [_MIN_FOCAL, _MAX_FOCAL] x the larger image side are
# a field of view over ~175 deg (pinhole) or under ~0.6 deg: no real camera, but a unit or typing
# mistake (fx = 1e-300 makes every normalized coordinate, and so the covariance, non-finite). The
# principal point must lie within one image size of the image.
_MIN_FOCAL, _MAX_FOCAL = 0.02, 100.0
# Distortion coefficients beyond this magnitude come from no lens model fit.
_MAX_ABS_DISTORTION = 1.0e4


def _binning_roi(msg: Any) -> tuple[int, int, int, int, int, int]:
    """(binning_x, binning_y, roi x, y, width, height) of a CameraInfo-like message; 0 binning -> 1."""
    roi = getattr(msg, "roi", None)
    vals = [int(getattr(msg, "binning_x", 0) or 0), int(getattr(msg, "binning_y", 0) or 0)]
    vals += [int(getattr(roi, f, 0) or 0) for f in ("x_offset", "y_offset", "width", "height")]
    return (max(vals[0], 1), max(vals[1], 1), vals[2], vals[3], vals[4], vals[5])


def _undistort_pinhole(pts: NDArray[np.float64], K: NDArray[np.float64], D: NDArray[np.float64]
                       ) -> NDArray[np.float64]:
    """Normalized coordinates of distorted pixels, converged iteration on OpenCV 4.x and 5.x."""
    src = pts.reshape(-1, 1, 2)
    iter_fn = getattr(cv2, "undistortPointsIter", None)  # OpenCV 4.x spelling
    if iter_fn is not None:
        out = iter_fn(src, K, D, np.eye(3), np.eye(3), _UNDISTORT_CRITERIA)
    else:  # OpenCV 5.x: criteria is an argument of undistortPoints itself
        out = cv2.undistortPoints(src, K, D, R=np.eye(3), P=np.eye(3), criteria=_UNDISTORT_CRITERIA)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics and distortion of one camera at one resolution.

    Attributes:
        width, height: image size in pixels the calibration is valid for.
        K: (3, 3) intrinsic matrix.
        D: (n,) distortion coefficients in OpenCV order for ``model``.
        model: the distortion model.
    """

    width: int
    height: int
    K: NDArray[np.float64]
    D: NDArray[np.float64]
    model: DistortionModel
    # How the image relates to the calibrated sensor (binning_x, binning_y, roi x, y, w, h); K and the
    # size above are already those of the image.
    binning_roi: tuple[int, int, int, int, int, int] = (1, 1, 0, 0, 0, 0)

    @classmethod
    def from_camera_info(cls, msg: Any) -> CameraModel:
        """Build from any object with CameraInfo fields (width, height, distortion_model, d, k, and
        optionally binning_x, binning_y, roi).

        Binning and region of interest are honoured as image_geometry does: the calibration (K, D,
        width, height) is of the full-resolution sensor, the image is its ``roi`` (full-resolution
        pixels; width/height 0 = the whole sensor) reduced by ``binning_x`` x ``binning_y`` (0 or
        1 = none). The model returned is that of the published image: ``fx / binning_x``,
        ``(cx - roi.x_offset) / binning_x`` (same for y), size ``roi.width // binning_x`` x
        ``roi.height // binning_y``; D is unchanged (it acts on normalized coordinates).

        Raises:
            CameraModelError: uncalibrated (K[0] == 0), non-finite or implausible K or D, unknown
                distortion model, distortion vector of the wrong length, zero image size, a region of
                interest outside the calibrated image, or binning leaving no pixel.
        """
        width, height = int(msg.width), int(msg.height)
        K = np.asarray(msg.k, dtype=np.float64)
        D = np.asarray(msg.d, dtype=np.float64)
        model = str(msg.distortion_model)
        bx, by, rx, ry, rw, rh = _binning_roi(msg)
        if (bx, by, rx, ry, rw, rh) == (1, 1, 0, 0, 0, 0):
            return cls.create(width, height, K, D, model)
        full = cls.create(width, height, K, D, model)  # validates the full-resolution calibration
        if rw == 0 and rh == 0:
            rw, rh = width - rx, height - ry
        if rx < 0 or ry < 0 or rw <= 0 or rh <= 0 or rx + rw > width or ry + rh > height:
            raise CameraModelError(
                f"camera_info roi (x_offset {rx}, y_offset {ry}, {rw}x{rh}) is not inside the calibrated "
                f"{width}x{height} image")
        if rw // bx == 0 or rh // by == 0:
            raise CameraModelError(f"camera_info binning {bx}x{by} leaves no pixel of the {rw}x{rh} roi")
        Kr = full.K.copy()
        Kr[0, 0] /= bx
        Kr[1, 1] /= by
        Kr[0, 2] = (Kr[0, 2] - rx) / bx
        Kr[1, 2] = (Kr[1, 2] - ry) / by
        return cls.create(rw // bx, rh // by, Kr, full.D.copy(), model, binning_roi=(bx, by, rx, ry, rw, rh))

    @classmethod
    def create(cls, width: int, height: int, K: NDArray[np.float64] | list[float],
               D: NDArray[np.float64] | list[float], distortion_model: str = "plumb_bob", *,
               binning_roi: tuple[int, int, int, int, int, int] = (1, 1, 0, 0, 0, 0)) -> CameraModel:
        """Validated constructor; see :meth:`from_camera_info` for the errors raised."""
        K = np.asarray(K, dtype=np.float64).reshape(-1)
        D = np.asarray(D, dtype=np.float64).reshape(-1)
        if K.size != 9:
            raise CameraModelError(f"camera_info K has {K.size} values, expected 9")
        K = K.reshape(3, 3)
        if not np.all(np.isfinite(K)):
            raise CameraModelError(f"camera_info K is not finite: {K.reshape(-1).tolist()}")
        if K[0, 0] == 0.0:
            raise CameraModelError("camera is uncalibrated: camera_info K[0] (fx) is 0")
        if K[0, 0] <= 0.0 or K[1, 1] <= 0.0 or K[2, 2] != 1.0 or np.any(K[2, :2] != 0.0) or K[1, 0] != 0.0:
            raise CameraModelError(f"camera_info K is not an intrinsic matrix: {K.reshape(-1).tolist()}")
        if K[0, 1] != 0.0:
            # OpenCV's distortion functions ignore skew; accepting it would silently mis-project.
            raise CameraModelError(f"camera_info K has skew K[1] = {K[0, 1]}; skewed intrinsics are not supported")
        if not np.all(np.isfinite(D)):
            raise CameraModelError(f"camera_info D is not finite: {quoted(D.tolist())}")
        if width <= 0 or height <= 0:
            raise CameraModelError(f"camera_info image size {width}x{height} is empty")
        side = float(max(width, height))
        for name, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
            if not _MIN_FOCAL * side <= f <= _MAX_FOCAL * side:
                raise CameraModelError(
                    f"camera_info focal length {name} = {f:.6g} px is implausible for a {width}x{height} image "
                    f"(expected {_MIN_FOCAL * side:.6g} to {_MAX_FOCAL * side:.6g} px)")
        for name, c, size in (("cx", K[0, 2], width), ("cy", K[1, 2], height)):
            if not -size <= c <= 2 * size:
                raise CameraModelError(
                    f"camera_info principal point {name} = {c:.6g} px is far outside the {width}x{height} image "
                    f"(expected {-size} to {2 * size} px)")
        if D.size and float(np.max(np.abs(D))) > _MAX_ABS_DISTORTION:
            raise CameraModelError(f"camera_info D has implausible coefficients: {quoted(D.tolist())}")
        try:
            model = DistortionModel(distortion_model)
        except ValueError:
            known = ", ".join(m.value for m in DistortionModel)
            raise CameraModelError(
                f"unknown distortion model {quoted(distortion_model)} (supported: {known})") from None
        if D.size == 0 or not np.any(D):
            # Many drivers publish an empty D for rectified images: no distortion at all.
            D = np.zeros(4 if model is DistortionModel.EQUIDISTANT else 5)
            if model is DistortionModel.RATIONAL_POLYNOMIAL:
                D = np.zeros(8)
        if D.size not in _D_LENGTHS[model]:
            raise CameraModelError(
                f"distortion model '{model.value}' needs {' or '.join(map(str, _D_LENGTHS[model]))} "
                f"coefficients, camera_info D has {D.size}")
        K.setflags(write=False)
        D.setflags(write=False)
        return cls(int(width), int(height), K, D, model, binning_roi)

    # ------------------------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(self.D != 0.0))

    def check_image_size(self, width: int, height: int) -> None:
        """Raise :class:`CameraModelError` when an image does not have the calibrated size."""
        if (width, height) != (self.width, self.height):
            bx, by, rx, ry, rw, rh = self.binning_roi
            how = "" if (bx, by, rx, ry) == (1, 1, 0, 0) else (
                f" (after binning {bx}x{by} of the roi {rw}x{rh} at ({rx}, {ry}) of the calibrated image)")
            raise CameraModelError(
                f"image size {width}x{height} does not match camera_info size {self.width}x{self.height}{how}")

    def same_as(self, other: CameraModel) -> bool:
        """Same image size, model, intrinsics and distortion (a tracked keyframe stays valid)."""
        return (self.width, self.height, self.model) == (other.width, other.height, other.model) \
            and np.array_equal(self.K, other.K) and np.array_equal(self.D, other.D)

    def scaled(self, factor: float) -> CameraModel:
        """The same camera for images resized by ``factor`` (pixel-centre convention of cv2.resize)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return CameraModel.create(round(self.width * factor), round(self.height * factor), K, self.D.copy(),
                                  self.model.value)

    def normalize(self, pts: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
        """(N, 2) raw pixels -> (N, 2) normalized coordinates (undistorted, K removed)."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] == 0:
            return np.zeros((0, 2))
        if self.model is DistortionModel.EQUIDISTANT:
            if not self.is_distorted:
                return self._normalize_pinhole(pts)
            # Limitation: cv2.fisheye caps the distorted angle at pi/2; rays beyond ~86 deg off axis
            # come back wrong. Such rays carry no usable two-view geometry for a pinhole-model VO.
            out = cv2.fisheye.undistortPoints(pts.reshape(-1, 1, 2), self.K, self.D,
                                              R=np.eye(3), P=np.eye(3), criteria=_UNDISTORT_CRITERIA)
            return np.asarray(out, dtype=np.float64).reshape(-1, 2)
        if not self.is_distorted:
            return self._normalize_pinhole(pts)
        return _undistort_pinhole(pts, self.K, self.D)

    def _normalize_pinhole(self, pts: NDArray[np.float64]) -> NDArray[np.float64]:
        y = (pts[:, 1] - self.K[1, 2]) / self.K[1, 1]
        x = (pts[:, 0] - self.K[0, 2]) / self.K[0, 0]
        return np.stack([x, y], axis=1)

    def undistort(self, pts: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
        """(N, 2) raw pixels -> (N, 2) pixels of the ideal pinhole camera with the same K."""
        return self.to_pixels(self.normalize(pts))

    def to_pixels(self, xn: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 2) normalized coordinates -> (N, 2) ideal pinhole pixels."""
        K = self.K
        u = K[0, 0] * xn[:, 0] + K[0, 2]
        v = K[1, 1] * xn[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1)

    def project(self, X_c: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 3) points in the camera optical frame -> (N, 2) raw (distorted) pixels."""
        X_c = np.asarray(X_c, dtype=np.float64).reshape(-1, 1, 3)
        zero = np.zeros(3)
        if self.model is DistortionModel.EQUIDISTANT and self.is_distorted:
            out, _ = cv2.fisheye.projectPoints(X_c, zero, zero, self.K, self.D)
        else:
            out, _ = cv2.projectPoints(X_c, zero, zero, self.K, self.D)
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)

    def describe(self) -> str:
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        return (f"{self.width}x{self.height} fx={fx:.2f} fy={fy:.2f} cx={cx:.2f} cy={cy:.2f} "
                f"{self.model.value} D={np.round(self.D, 6).tolist()}")

