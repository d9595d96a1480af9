"""What real cameras do to an image, drawn per seed for the scenario families (bags/scenarios.py).

A seed's ``harshness`` h in [0, 1) scales every fault: each magnitude is drawn as
``lo + (hi - lo) * clip(h * U(0.5, 1.5), 0, 1)`` and each fault that is present or absent (rolling shutter,
dropped frames, overlay) is present with a probability that grows with h, so a distribution of seeds
spans clean-ish to harsh cameras. The ranges (``RANGES``) follow what real cameras show:

- sensor noise: read noise (gray levels) plus shot noise whose variance grows with the signal;
- motion blur: the image integrated over the exposure time while the camera moves (each pixel smeared
  along its own image motion, from its depth and the camera's motion over the exposure);
- gain changes (an auto-exposure stepping) and vignetting (darker corners);
- JPEG artefacts (the quality drawn);
- rolling shutter: rows read out one after the other, 20-40 us a row of a 480-row sensor (the readout time
  does not depend on the size the sequence is rendered at), rendered as bands of rows at their own poses;
- frame drops (single frames and bursts) and stamp jitter (the header stamp off the capture time);
- a static overlay: a timestamp burnt into the image, the same place in every frame;
- a CameraInfo slightly wrong: principal point up to 4 px off (in a 640-wide image; scaled with the width),
  focal length up to 1.5 % off, and a radial distortion (|k1| up to 0.05) in the image that it does not
  declare. The image is made by the true camera; only what is declared is wrong.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import cv2
import make_bags as mb
import numpy as np
from numpy.typing import NDArray

SENSOR_ROWS = 480  # rows of the sensor whose readout the rolling shutter models
REFERENCE_WIDTH = 640  # the principal point error is given in pixels of an image this wide
MAX_BANDS = 16  # rolling shutter: bands of rows rendered each at its own pose
MIN_BAND_ROWS = 8
BLUR_STEP_PX = 0.5  # motion blur: one sample of the exposure per this much image motion

# (lo, hi) of each magnitude; the harshness picks where in the range a seed falls.
RANGES: dict[str, tuple[float, float]] = {
    "read_noise": (0.6, 4.0),  # gray levels, 1 sigma
    "shot_noise": (0.0, 0.12),  # variance per gray level of signal
    "vignetting": (0.0, 0.45),  # relative darkening at the image corners
    "gain_step": (0.02, 0.16),  # 1 sigma of the log-gain change at an auto-exposure step
    "gain_steps_per_frame": (0.0, 0.06),
    "jpeg_quality": (95.0, 35.0),
    "line_time_us": (20.0, 40.0),  # rolling shutter, per row of a SENSOR_ROWS sensor
    "drop_rate": (0.01, 0.06),
    "stamp_jitter_ms": (0.0, 4.0),  # 1 sigma
    "principal_point_px": (0.0, 4.0),
    "focal_error": (0.0, 0.015),
    "k1": (0.0, 0.05),
}


@dataclass(frozen=True)
class FaultEnvelope:
    """What a family allows of the faults: the exposure time (ms) and how likely the overlay is."""

    exposure_ms: tuple[float, float] = (1.0, 12.0)
    overlay_probability: float = 0.35


@dataclass(frozen=True)
class CameraFaults:
    """The faults of one seed (see the module doc); ``to_json`` gives them for scenario.json."""

    harshness: float
    read_noise: float
    shot_noise: float
    exposure_ms: float
    vignetting: float
    gain: tuple[float, ...]  # per rendered frame, multiplying the scene's radiance
    jpeg_quality: int
    line_time_us: float  # 0: a global shutter
    dropped: tuple[int, ...]  # frame indices not written
    stamp_jitter_ms: float
    overlay_corner: str | None  # None: no overlay
    principal_point_error_px: tuple[float, float]  # declared minus true, in pixels of a REFERENCE_WIDTH image
    focal_error: float  # declared / true - 1 (fx and fy alike)
    k1: float  # the true lens' radial distortion, not declared

    def to_json(self) -> dict[str, object]:
        d = asdict(self)
        gains = np.asarray(self.gain)
        d["gain"] = {"min": float(gains.min()), "max": float(gains.max()),
                     "steps": int(np.count_nonzero(np.abs(np.diff(gains)) > 1e-12))}
        d["dropped"] = list(self.dropped)
        return d


def _magnitude(rng: np.random.Generator, name: str, h: float) -> float:
    lo, hi = RANGES[name]
    return lo + (hi - lo) * float(np.clip(h * rng.uniform(0.5, 1.5), 0.0, 1.0))


def _present(rng: np.random.Generator, h: float) -> bool:
    return bool(rng.uniform() < 0.15 + 0.7 * h)


def draw_faults(rng: np.random.Generator, harshness: float, envelope: FaultEnvelope, n_frames: int) -> CameraFaults:
    """The faults of a seed of ``n_frames`` frames at ``harshness`` (0 clean .. 1 harsh)."""
    h = harshness
    read, shot = _magnitude(rng, "read_noise", h), _magnitude(rng, "shot_noise", h)
    lo, hi = envelope.exposure_ms
    exposure = lo + (hi - lo) * float(np.clip(h * rng.uniform(0.5, 1.5), 0.0, 1.0))
    vignetting = _magnitude(rng, "vignetting", h)
    # auto-exposure: the gain steps now and then and settles; the total stays within 0.6-1.6
    step_sigma, rate = _magnitude(rng, "gain_step", h), _magnitude(rng, "gain_steps_per_frame", h)
    log_gain = np.zeros(n_frames)
    for i in range(1, n_frames):
        log_gain[i] = log_gain[i - 1] + (rng.normal(0.0, step_sigma) if rng.uniform() < rate else 0.0)
        log_gain[i] = float(np.clip(log_gain[i], math.log(0.6), math.log(1.6)))
    quality = round(_magnitude(rng, "jpeg_quality", h))
    line_time = float(rng.uniform(*RANGES["line_time_us"])) if _present(rng, h) else 0.0
    dropped: list[int] = []
    if _present(rng, h) and n_frames > 4:
        drop_rate = _magnitude(rng, "drop_rate", h)
        dropped = [i for i in range(1, n_frames - 1) if rng.uniform() < drop_rate]
        if rng.uniform() < h:  # a burst: the driver stalled
            start = int(rng.integers(1, max(2, n_frames - 5)))
            dropped += list(range(start, min(start + int(rng.integers(2, 5)), n_frames - 1)))
    jitter = _magnitude(rng, "stamp_jitter_ms", h)
    corners = ("top_left", "top_right", "bottom_left", "bottom_right")
    overlay = str(corners[int(rng.integers(4))]) if rng.uniform() < envelope.overlay_probability * (0.5 + h) \
        else None
    pp = _magnitude(rng, "principal_point_px", h)
    angle = rng.uniform(0.0, 2.0 * math.pi)
    focal = _magnitude(rng, "focal_error", h) * (1.0 if rng.uniform() < 0.5 else -1.0)
    k1 = _magnitude(rng, "k1", h) * (1.0 if rng.uniform() < 0.5 else -1.0)
    return CameraFaults(h, read, shot, exposure, vignetting, tuple(float(v) for v in np.exp(log_gain)), int(quality),
                        line_time, tuple(sorted(set(dropped))), jitter, overlay,
                        (pp * math.cos(angle), pp * math.sin(angle)), focal, k1)


# --- the two cameras -------------------------------------------------------------------------------------


def true_camera(width: int, height: int, focal_px: float, faults: CameraFaults) -> mb.CameraModel:
    """The camera the images are made with: principal point at the image centre, the undeclared k1."""
    K = np.array([[focal_px, 0.0, (width - 1) / 2.0], [0.0, focal_px, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return mb.CameraModel(width, height, K, np.array([faults.k1, 0.0, 0.0, 0.0, 0.0]))


def declared_camera(true: mb.CameraModel, faults: CameraFaults) -> mb.CameraModel:
    """What the CameraInfo says: focal length and principal point a little off, no distortion."""
    K = true.K.copy()
    K[0, 0] *= 1.0 + faults.focal_error
    K[1, 1] *= 1.0 + faults.focal_error
    scale = true.width / REFERENCE_WIDTH
    K[0, 2] += faults.principal_point_error_px[0] * scale
    K[1, 2] += faults.principal_point_error_px[1] * scale
    return mb.CameraModel(true.width, true.height, K, np.zeros(5))


# --- rolling shutter ---------------------------------------------------------------------------------------


def row_bands(height: int, faults: CameraFaults) -> list[tuple[int, int, float]]:
    """(first row, stop row, time offset s from the image's centre row) of each band the image is rendered
    in: one band (offset 0) for a global shutter."""
    if faults.line_time_us <= 0.0:
        return [(0, height, 0.0)]
    count = max(1, min(MAX_BANDS, height // MIN_BAND_ROWS))
    edges = np.linspace(0, height, count + 1).round().astype(int)
    line_s = faults.line_time_us * 1e-6 * SENSOR_ROWS / height  # a whole readout lasts SENSOR_ROWS lines
    centre = (height - 1) / 2.0
    return [(int(a), int(b), ((a + b - 1) / 2.0 - centre) * line_s) for a, b in itertools.pairwise(edges)]


# --- motion blur ------------------------------------------------------------------------------------------


def _project(camera: mb.CameraModel, X_c: NDArray[np.float64]) -> NDArray[np.float64]:
    """(..., 3) camera points -> (..., 2) pixels of the (distorted) camera; NaN behind it."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(X_c[..., 2] > mb.NEAR_M, X_c[..., 2], np.nan)
        xd, yd = mb.distort_normalized(X_c[..., 0] / z, X_c[..., 1] / z, camera.D)
    K = camera.K
    return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)


class MotionBlur:
    """Smears a rendered image along each pixel's image motion over the exposure time."""

    def __init__(self, camera: mb.CameraModel) -> None:
        self.camera = camera
        xn, yn = mb.pixel_rays(camera, 1)
        self._rays = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float32), np.arange(camera.height, dtype=np.float32))
        self._u, self._v = u, v

    def apply(self, image: NDArray[np.float32], depth: NDArray[np.float32], pose_at: Callable[[float], mb.Matrix4],
              t: float, exposure_s: float) -> tuple[NDArray[np.float32], float]:
        """The image integrated over ``[t - exposure/2, t + exposure/2]`` and the longest smear (px).

        Each pixel's scene point (its ray at its rendered depth, seen at ``t``) is projected at the start
        and the end of the exposure; the blurred pixel averages the image sampled back along that
        motion (``BLUR_STEP_PX`` apart). Moving objects are smeared with the camera's motion only.
        """
        if exposure_s <= 0.0:
            return image, 0.0
        T_mid = pose_at(t)
        finite = np.isfinite(depth)
        X_c = self._rays * np.where(finite, depth, 1.0)[..., None]
        X_w = X_c @ T_mid[:3, :3].T + T_mid[:3, 3]
        ends = []
        for tau in (-0.5 * exposure_s, 0.5 * exposure_s):
            T = pose_at(t + tau)
            ends.append(_project(self.camera, (X_w - T[:3, 3]) @ T[:3, :3]))
        motion = ends[1] - ends[0]
        motion[~(finite & np.isfinite(motion).all(axis=-1))] = 0.0
        longest = float(np.hypot(motion[..., 0], motion[..., 1]).max())
        samples = int(np.clip(math.ceil(longest / BLUR_STEP_PX) + 1, 2, 33))
        total = np.zeros_like(image)
        for f in np.linspace(-0.5, 0.5, samples):
            map_x = (self._u - f * motion[..., 0]).astype(np.float32)
            map_y = (self._v - f * motion[..., 1]).astype(np.float32)
            total += cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return total / samples, longest


# --- photometry, overlay -------------------------------------------------------------------------------------


def vignette(camera: mb.CameraModel, strength: float) -> NDArray[np.float32]:
    """(H, W) factor 1 at the centre falling as the squared radius to ``1 - strength`` at the corners."""
    h, w = camera.height, camera.width
    u, v = np.meshgrid(np.arange(w) - (w - 1) / 2.0, np.arange(h) - (h - 1) / 2.0)
    r2 = (u * u + v * v) / (((w - 1) / 2.0) ** 2 + ((h - 1) / 2.0) ** 2)
    return (1.0 - strength * r2).astype(np.float32)


def sensor(image: NDArray[np.float32], gain: float, vignetting: NDArray[np.float32], faults: CameraFaults,
           rng: np.random.Generator) -> NDArray[np.uint8]:
    """Radiance times gain and vignetting, plus read and shot noise, quantised to uint8 (clipping)."""
    signal = image * np.float32(gain) * vignetting
    sigma = np.sqrt(faults.read_noise**2 + faults.shot_noise * np.maximum(signal, 0.0)).astype(np.float32)
    noisy = signal + sigma * rng.standard_normal(signal.shape, dtype=np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def burn_overlay(image: NDArray[np.uint8], stamp_ns: int, corner: str) -> None:
    """A camera's timestamp (date, time to the millisecond) and name burnt into a corner, in place: white
    text with a dark outline, at the same place in every frame."""
    seconds, ns = divmod(stamp_ns, mb.NS_PER_S)
    hh, rest = divmod(seconds % 86400, 3600)
    text = f"2026-11-28 {hh:02d}:{rest // 60:02d}:{rest % 60:02d}.{ns // 1_000_000:03d} CAM1"
    h, w = image.shape
    scale = 0.45 * h / 240.0
    thickness = max(1, round(h / 240.0))
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    margin = max(4, h // 60)
    x = margin if corner.endswith("left") else w - tw - margin
    y = margin + th if corner.startswith("top") else h - margin - base
    cv2.putText(image, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 0, thickness + 2, cv2.LINE_AA)
    cv2.putText(image, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, thickness, cv2.LINE_AA)


# --- stamps ------------------------------------------------------------------------------------------------


def header_stamps(times_s: NDArray[np.float64], faults: CameraFaults, rng: np.random.Generator) -> NDArray[np.int64]:
    """Header stamps (ns) of frames captured at ``times_s`` (seconds after the first, at the centre row,
    mid-exposure): 1000 s + the capture time + a jitter (Gaussian, clipped at 2.5 sigma), kept strictly
    increasing."""
    jitter = np.clip(rng.normal(0.0, 1.0, times_s.shape), -2.5, 2.5) * faults.stamp_jitter_ms * 1e-3
    stamps = mb.START_NS + np.rint((times_s + jitter) * mb.NS_PER_S).astype(np.int64)
    for i in range(1, stamps.size):
        stamps[i] = max(stamps[i], stamps[i - 1] + 1_000_000)
    return stamps
