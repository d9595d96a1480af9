"""The floor seen between two keyframes: the plane-induced homography of the image region below the horizon.

A keyframe's map holds few points on a sparsely textured floor (asphalt, concrete): the tracker's corners go
where the image is richest (facades, boxes), the few on a road are lane markings that slide along themselves
(the aperture problem), and those on a far road are triangulated at small angles. Yet the floor fills the
lower image. Between two keyframes whose relative motion ``(R, t)`` the VO measured, every floor point moves
by the homography its plane induces (H&Z 13.1):

    X_cur = (R + t m^T) X_kf,    m = -n_up / h,

``n_up`` the floor's upward unit normal and ``h`` the camera's height above it, both in the keyframe's camera
frame, ``h`` in the map's units (those of ``t``). ``m`` (three numbers) is fitted directly to the images:
the keyframe's pixels below the horizon of the mounting's up, those with the strongest gradients, warped
into the next keyframe's image by the homography, their brightness difference (after a gain and an offset)
minimised by Gauss-Newton, coarse to fine on image pyramids (a direct, photometric alignment: every edge of
a lane marking, a crack or the asphalt's grain constrains ``m`` through the one homography they share, so
no single pixel needs to be a corner). A search over the height along the expected normal starts it. Pixels
that are no floor (a parked car, a facade's foot) fit it poorly and are weighted down (Huber).
``camera_height_m`` over ``h`` is the map's scale error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.camera import CameraModel
from epi_vo.core.floor import GroundPlane

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

# Rays at least this far below the horizon are sought on the floor: nearer the horizon a floor point's depth
# (h / tan of the angle: 11 camera heights at 5 deg) grows past what a keyframe step's parallax measures.
FLOOR_MIN_DEPRESSION_DEG = 5.0
# Pyramid levels of the alignment below the half-resolution image it starts from: a floor point a camera
# height below moves tens of pixels over a keyframe step; each level halves that.
FLOOR_LEVELS = 3
FLOOR_PIXELS = 1500  # pixels of the floor region aligned per level, spread over it (``_spread``)
# The search's heights, as multiples of the step's length: from a robot camera a few centimetres above a
# floor it crosses in metre steps to a camera 40 steps above it.
FLOOR_SEARCH_HEIGHTS = np.geomspace(0.03, 40.0, 32)
# With metric scale known the height is the camera's: the search stays within this factor of it (the map's
# scale error a keyframe step can have accumulated, with room).
FLOOR_GUESS_RANGE = 1.5
# The texture is compared without its local mean over a few pixels of each level: exposure changes and
# vignetting vary over tens of pixels, the floor's texture over one or two.
FLOOR_HIGH_PASS_PX = 3.0
# A pixel whose texture differs between the two images (at the same place, over 5x5) by less than this share
# of the texture itself did not move: static (an overlay), not floor.
FLOOR_STATIC_SHARE = 0.3
FLOOR_GN_STEPS = 4  # Gauss-Newton steps per level: the search starts each within its convergence
# The floor's normal is where the declared mounting says within this (1 sigma, deg): a road's camera level to a
# few degrees, a robot's as mounted, the floor's slope. Weak: one step's homography measures the tilt itself.
FLOOR_NORMAL_SIGMA_DEG = 3.0
# The VO's rotation between two keyframes is right within this (1 sigma, deg): what the floor's alignment may
# move it by.
FLOOR_ROTATION_SIGMA_DEG = 0.2
FLOOR_HUBER = 1.345  # Huber's constant, in robust standard deviations of the residuals (95 % efficiency)
# A floor whose height the fit knows no better than this (relative, 1 sigma) is not seen: the floor region's
# parallax over the step is too small to tell a floor from a far surface (a floor seen from tens of steps
# above it, or the top of a far wall taken for one: the floor's side of a camera not mounted as declared).
# A floor a few steps below gives 2-7 %.
FLOOR_MAX_REL_STD = 0.075
# The photometric residuals of neighbouring pixels are not independent (the image's blur, its JPEG blocks,
# the warp's interpolation): the fit's covariance counts one independent residual per this many pixels.
FLOOR_PIXELS_PER_SAMPLE = 16.0


@dataclass(frozen=True)
class FloorView:
    """A keyframe's image, kept by the ``ground_plane`` scale source for the step to the next keyframe."""

    gray: NDArray[np.uint8]
    camera: CameraModel
    stamp_ns: int


@dataclass(frozen=True)
class FloorFit:
    """What :func:`floor_between` found: the floor in the current camera's frame (its height in map units),
    or why there is none (``why``), with the pixels it aligned and the share of them that fit."""

    plane: GroundPlane | None
    n_pixels: int
    fit_share: float = 0.0
    why: str = ""


def floor_region(camera: CameraModel, up: F64, min_depression_deg: float = FLOOR_MIN_DEPRESSION_DEG
                 ) -> NDArray[np.uint8]:
    """255 where the pixel's ray points at least ``min_depression_deg`` below the horizon of ``up`` (unit, the
    camera frame); computed on a grid of 8 px and scaled up (the horizon is a straight line but for the lens)."""
    step = 8
    gx, gy = np.meshgrid(np.arange(0, camera.width, step, dtype=np.float64) + step / 2.0,
                         np.arange(0, camera.height, step, dtype=np.float64) + step / 2.0)
    xn = camera.normalize(np.column_stack([gx.ravel(), gy.ravel()]))
    rays = np.column_stack([xn, np.ones(xn.shape[0])])
    sin_dep = -(rays @ up) / np.linalg.norm(rays, axis=1)
    coarse = np.where(sin_dep >= math.sin(math.radians(min_depression_deg)), 255, 0).astype(np.uint8)
    mask = np.asarray(cv2.resize(coarse.reshape(gx.shape), (camera.width, camera.height),
                                 interpolation=cv2.INTER_NEAREST), np.uint8)
    return mask


@dataclass(frozen=True)
class _Level:
    """One pyramid level's samples: the keyframe's brightness and rays at its strongest floor pixels, and the
    current image with its gradients; ``scale`` full-resolution pixels per pixel of this level."""

    i_kf: F64
    rays: F64  # (N, 3) normalised rays of the samples (keyframe camera)
    cur: NDArray[np.float32]
    grad_x: NDArray[np.float32]
    grad_y: NDArray[np.float32]
    scale: float


def _high_pass(img: NDArray[np.uint8]) -> NDArray[np.float32]:
    """The image less its local mean (Gaussian, FLOOR_HIGH_PASS_PX): what a gain or offset of the exposure,
    or the lens's vignetting (the same floor darker in the other image's corner), leaves alike."""
    f = img.astype(np.float32)
    out: NDArray[np.float32] = f - cv2.GaussianBlur(f, (0, 0), FLOOR_HIGH_PASS_PX)
    return out


def _levels(base: NDArray[np.uint8], other: NDArray[np.uint8], camera: CameraModel, mask: NDArray[np.uint8],
            t: F64) -> list[_Level]:
    """The pyramid (coarsest first), from half resolution down FLOOR_LEVELS - 1 more halvings: samples of
    ``base`` (its floor region ``mask``), to be warped into ``other`` (``t``: the translation to it).

    The samples are, in each cell of a grid over the region, the pixel whose brightness changes most with
    the floor's height: a change of height moves a floor pixel along its epipolar line, away from the
    epipole, so what counts is the gradient across that direction. An edge along it (a lane marking seen
    from a car driving along it) slides along itself whatever the height and says nothing. Pixels whose
    texture did not change between the two images are static (a timestamp burnt into the image, the car's
    own bonnet) and are left out."""
    kf = np.asarray(cv2.pyrDown(base), np.uint8)
    cur = np.asarray(cv2.pyrDown(other), np.uint8)
    region = cv2.resize(mask, (kf.shape[1], kf.shape[0]), interpolation=cv2.INTER_NEAREST)
    out = []
    scale = 2.0
    for level in range(FLOOR_LEVELS):
        if level:
            kf, cur = np.asarray(cv2.pyrDown(kf), np.uint8), np.asarray(cv2.pyrDown(cur), np.uint8)
            region = cv2.resize(region, (kf.shape[1], kf.shape[0]), interpolation=cv2.INTER_NEAREST)
            scale *= 2.0
        kf_f = _high_pass(kf)
        cur_f = _high_pass(cur)
        h_img, w_img = kf.shape
        xs_all, ys_all = np.meshgrid(np.arange(w_img, dtype=np.float64), np.arange(h_img, dtype=np.float64))
        full = np.column_stack([((xs_all + 0.5) * scale - 0.5).ravel(), ((ys_all + 0.5) * scale - 0.5).ravel()])
        p = (full - camera.K[:2, 2]) / np.array([camera.K[0, 0], camera.K[1, 1]])  # pinhole: for a direction
        flow = t[:2][None, :] - p * t[2]  # the epipolar direction of each pixel (the rotation aside)
        flow /= np.maximum(np.linalg.norm(flow, axis=1), 1e-12)[:, None]
        gx_kf = cv2.Sobel(kf_f, cv2.CV_32F, 1, 0, ksize=3).ravel() / 8.0
        gy_kf = cv2.Sobel(kf_f, cv2.CV_32F, 0, 1, ksize=3).ravel() / 8.0
        strength = np.abs(gx_kf * flow[:, 0] + gy_kf * flow[:, 1]).reshape(h_img, w_img)
        changed = cv2.blur(np.abs(cur_f - kf_f), (5, 5)) >= FLOOR_STATIC_SHARE * cv2.blur(np.abs(kf_f), (5, 5))
        strength[(region == 0) | ~changed] = 0.0
        strength[:2, :] = strength[-2:, :] = 0.0
        strength[:, :2] = strength[:, -2:] = 0.0
        idx = _spread(strength)
        n = idx.size
        if n < 16:
            continue
        ys, xs = np.divmod(idx, w_img)
        xn = camera.normalize(full[idx])
        out.append(_Level(kf_f[ys, xs].astype(np.float64), np.column_stack([xn, np.ones(n)]), cur_f,
                          np.asarray(cv2.Sobel(cur_f, cv2.CV_32F, 1, 0, ksize=3) / 8.0, np.float32),
                          np.asarray(cv2.Sobel(cur_f, cv2.CV_32F, 0, 1, ksize=3) / 8.0, np.float32), scale))
    return out[::-1]


def _spread(strength: NDArray[np.float32]) -> NDArray[np.int64]:
    """Up to FLOOR_PIXELS samples spread over the region (``strength`` > 0): the strongest pixel of each cell
    of a grid whose cells share the region evenly. The strongest pixels of the whole region would gather on
    what is richest in it (a box's print, a wall's foot), not on the floor that fills it."""
    h, w = strength.shape
    area = int(np.count_nonzero(strength > 0))
    if area == 0:
        return np.zeros(0, np.int64)
    c = max(1, int(math.sqrt(area / FLOOR_PIXELS)))
    hc, wc = h // c, w // c
    cells = strength[:hc * c, :wc * c].reshape(hc, c, wc, c).transpose(0, 2, 1, 3).reshape(hc * wc, c * c)
    best = np.argmax(cells, axis=1)
    keep = cells[np.arange(best.size), best] > 0
    cy, cx = np.divmod(np.arange(best.size), wc)
    by, bx = np.divmod(best, c)
    idx = ((cy * c + by) * w + cx * c + bx)[keep]
    if idx.size > FLOOR_PIXELS:
        flat = strength.ravel()
        idx = idx[np.argpartition(-flat[idx], FLOOR_PIXELS - 1)[:FLOOR_PIXELS]]
    out: NDArray[np.int64] = idx.astype(np.int64)
    return out


def _warp(lv: _Level, camera: CameraModel, H: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """The samples' positions in the other image's level (N, 2) under the homography ``H`` (normalised
    coordinates), their normalised coordinates there, and which are in front of the camera and inside."""
    q = lv.rays @ H.T
    ahead = q[:, 2] > 1e-9
    q = np.where(ahead[:, None], q, np.array([0.0, 0.0, 1.0]))
    p = q[:, :2] / q[:, 2:3]
    px = camera.project(q) if camera.is_distorted else np.column_stack(
        [camera.K[0, 0] * p[:, 0] + camera.K[0, 2], camera.K[1, 1] * p[:, 1] + camera.K[1, 2]])
    uv = (px + 0.5) / lv.scale - 0.5
    h, w = lv.cur.shape
    inside = ahead & (uv[:, 0] >= 0.0) & (uv[:, 1] >= 0.0) & (uv[:, 0] <= w - 1.0) & (uv[:, 1] <= h - 1.0)
    return uv, p, inside


def _sample(img: NDArray[np.float32], uv: F64) -> F64:
    """Bilinear samples of ``img`` at ``uv`` (N, 2), in its pixels."""
    if uv.shape[0] == 0:
        return np.zeros(0)
    m = uv.astype(np.float32).reshape(-1, 1, 2)
    out = cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(out, np.float64).reshape(-1)


def _residuals(lv: _Level, camera: CameraModel, H: F64) -> tuple[F64, NDArray[np.bool_], F64, F64]:
    """Photometric residuals (high-passed brightness) of the inside samples, which samples, the warped
    normalised coordinates and level pixels."""
    uv, p, inside = _warp(lv, camera, H)
    return _sample(lv.cur, uv[inside]) - lv.i_kf[inside], inside, p, uv


def _huber(r: F64) -> tuple[F64, float]:
    """Huber weights of the residuals and their robust standard deviation (MAD)."""
    sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-3)
    k = FLOOR_HUBER * sigma
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12)), sigma


@dataclass(frozen=True)
class _Plane:
    """The floor's homography ``H = exp(w) R - u n^T`` between two views (``X_other = H X_base`` for the
    floor's points): ``u`` the translation over the floor's distance (the base camera's height), ``n`` its
    upward normal in the base frame, ``n = normalize(up + a e1 + b e2)`` about the expected ``up``, ``w`` a
    small rotation of the VO's ``R``. Parameters ``theta = (u, a, b, w)``."""

    R: F64
    up: F64
    e: F64  # (3, 2): two unit vectors across ``up``

    @staticmethod
    def about(R: F64, up: F64) -> _Plane:
        e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        return _Plane(R, up, np.column_stack([e1, np.cross(up, e1)]))

    def normal(self, theta: F64) -> F64:
        v = self.up + self.e @ theta[3:5]
        out: F64 = v / np.linalg.norm(v)
        return out

    def H(self, theta: F64) -> F64:
        turn = np.asarray(cv2.Rodrigues(theta[5:8])[0], np.float64)
        out: F64 = turn @ self.R - np.outer(theta[:3], self.normal(theta))
        return out


def _skew_rows(a: F64) -> F64:
    """(N, 3, 3): the cross-product matrix of each row of ``a``."""
    out = np.zeros((a.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -a[:, 2], a[:, 1]
    out[:, 1, 0], out[:, 1, 2] = a[:, 2], -a[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -a[:, 1], a[:, 0]
    return out


def _search(lv: _Level, camera: CameraModel, plane: _Plane, t: F64, heights: list[float]) -> float | None:
    """The height (along the expected normal, the step ``t`` as the VO measured it) whose homography explains
    the level's samples best. Every hypothesis is judged on all the samples alike: a truncated quadratic at
    FLOOR_HUBER of the residuals' least robust spread among the hypotheses, a sample warped out of view
    counting as truncated (a height that sends the floor out of view explains nothing)."""
    runs = []
    for h in heights:
        r, inside, *_ = _residuals(lv, camera, plane.R - np.outer(t / h, plane.up))
        if r.size >= 16:
            runs.append((h, r, int(inside.size)))
    if not runs:
        return None
    sigma = min(_huber(r)[1] for _, r, _ in runs)
    cap = (FLOOR_HUBER * sigma) ** 2
    costs = [(float(np.sum(np.minimum(r * r, cap))) + (n - r.size) * cap, h) for h, r, n in runs]
    return min(costs)[1]


def _align(base: NDArray[np.uint8], other: NDArray[np.uint8], camera: CameraModel, R: F64, t: F64, up: F64,
           heights: list[float], normal_sigma_deg: float) -> tuple[F64, F64, F64, float, int] | str:
    """The floor's homography aligning ``base``'s floor region with ``other`` (``X_other = R X_base + t``
    as the VO measured it, ``up`` the floor's expected upward normal in ``base``'s frame): its ``u`` (the
    step over the base camera's height) and normal, the covariance of ``u``, the share of the samples that
    fit, and their count; or why not.

    The step's direction is the homography's own (a direction the VO has a few degrees off would tilt the
    floor's fit), its length the VO's; the rotation is the VO's, refined with the prior
    FLOOR_ROTATION_SIGMA_DEG (a tenth of a degree of pitch moves a floor point seen 10 m ahead by a twentieth
    of its parallax over a two-metre step). The normal's tilt from ``up``
    has the prior ``normal_sigma_deg``: the mounting (or the floor seen so far) says where the floor is
    within a few degrees, while one step's homography trades the floor's tilt against its height."""
    levels = _levels(base, other, camera, floor_region(camera, up), t)
    if not levels:
        return "no floor region below the horizon"
    plane = _Plane.about(R, up)
    h0 = _search(levels[0], camera, plane, t, heights)
    if h0 is None:
        return "the floor region leaves the view at every height"
    theta = np.concatenate([t / h0, np.zeros(5)])
    prior = np.diag([0.0, 0.0, 0.0] + [1.0 / math.tan(math.radians(normal_sigma_deg)) ** 2] * 2
                    + [1.0 / math.radians(FLOOR_ROTATION_SIGMA_DEG) ** 2] * 3)
    A = np.eye(8)
    share, n_used = 0.0, 0
    for lv in levels:
        for _ in range(FLOOR_GN_STEPS):
            r, inside, p, uv = _residuals(lv, camera, plane.H(theta))
            if r.size < 16:
                return "the floor's fit left the view"
            w, sigma = _huber(r)
            x = lv.rays[inside]
            # d p / d theta through q = H x: dq/du = -(n.x) I, dq/dn = -u x^T, dq/dw = -[R' x]x (R' = exp(w) R)
            q = x @ plane.H(theta).T
            n = plane.normal(theta)
            nx = x @ n
            v = plane.up + plane.e @ theta[3:5]
            dn = (np.eye(3) - np.outer(n, n)) @ plane.e / float(np.linalg.norm(v))  # (3, 2)
            rx = q + np.outer(nx, theta[:3])  # R' x
            dq = np.empty((x.shape[0], 3, 8))
            dq[:, :, 0:3] = -nx[:, None, None] * np.eye(3)[None, :, :]
            dq[:, :, 3:5] = -theta[:3][None, :, None] * (x @ dn)[:, None, :]
            dq[:, :, 5:8] = -_skew_rows(rx)
            dp = (dq[:, :2, :] - p[inside][:, :, None] * dq[:, 2:3, :]) / q[:, 2, None, None]
            gx, gy = _sample(lv.grad_x, uv[inside]), _sample(lv.grad_y, uv[inside])
            J = (gx[:, None] * camera.K[0, 0] * dp[:, 0, :] + gy[:, None] * camera.K[1, 1] * dp[:, 1, :]) / lv.scale
            # The data's information: the residuals' variance, FLOOR_PIXELS_PER_SAMPLE pixels per independent one.
            info = 1.0 / (sigma**2 * FLOOR_PIXELS_PER_SAMPLE)
            Jw = J * w[:, None]
            A = info * np.einsum("ki,kj->ij", Jw, J) + prior  # einsum, not BLAS: no worker threads left spinning
            g = info * np.einsum("ki,k->i", Jw, r) + prior @ theta
            try:
                delta = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                return "the floor's fit is singular"
            theta = theta + delta
            if float(np.linalg.norm(delta[:3])) < 1e-6 * float(np.linalg.norm(theta[:3])) \
                    and float(np.linalg.norm(delta[3:])) < 1e-7:
                break
        share = float(np.mean(w >= 1.0)) * r.size / max(inside.size, 1)
        n_used = int(r.size)
    try:
        cov = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return "the floor's fit is singular"
    return np.asarray(theta[:3], np.float64), plane.normal(theta), np.asarray(cov[:3, :3], np.float64), share, n_used


def floor_between(view: FloorView, gray: NDArray[np.uint8], camera: CameraModel, R_cur_kf: F64, t_cur_kf: F64,
                  up: F64, *, max_tilt_deg: float, h_guess: float | None = None,
                  normal_sigma_deg: float = FLOOR_NORMAL_SIGMA_DEG) -> FloorFit:
    """The floor between the keyframe ``view`` and the image ``gray`` (the next keyframe, ``camera``), whose
    motion is ``X_cur = R_cur_kf X_kf + t_cur_kf`` (map units): the plane-induced homography of the floor
    region (module doc), its normal within ``max_tilt_deg`` of ``up`` (unit, the keyframe's camera frame),
    ``normal_sigma_deg`` its prior about it. ``h_guess``: the height expected (map units, metric scale known):
    searched within a factor FLOOR_GUESS_RANGE of it, not over every height.

    A camera moving forward sees in the newer image the floor it saw farther ahead in the older one, while
    the older image's near floor has left the view: the newer image's floor region is aligned with the
    older image then (the homography of the inverse motion), the older one's otherwise. The height is the
    step's length in map units over the homography's step over the height. The plane returned is in the
    current camera's frame: its upward normal and the current camera centre's height above it; ``rel_std``
    the fit's relative standard error of the height."""
    t = np.asarray(t_cur_kf, np.float64).reshape(3)
    step = float(np.linalg.norm(t))
    if not step > 0.0 or not camera.same_as(view.camera) or gray.shape != view.gray.shape:
        return FloorFit(None, 0, why="no step between two views of one camera")
    if h_guess is not None and h_guess > 0.0:
        heights = [float(h) * h_guess for h in np.geomspace(1.0 / FLOOR_GUESS_RANGE, FLOOR_GUESS_RANGE, 13)]
    else:
        heights = [float(h) * step for h in FLOOR_SEARCH_HEIGHTS]
    c_cur = -R_cur_kf.T @ t  # the current camera centre in the keyframe frame
    forward = float(c_cur[2]) > 0.0
    # Moving forward: the current image's floor in the keyframe's image, X_kf = R^T X_cur + c_cur.
    fit = _align(gray, view.gray, camera, R_cur_kf.T, c_cur, R_cur_kf @ up, heights, normal_sigma_deg) if forward \
        else _align(view.gray, gray, camera, R_cur_kf, t, up, heights, normal_sigma_deg)
    if isinstance(fit, str):
        return FloorFit(None, 0, why=fit)
    u, n_up, cov_u, share, n_used = fit
    norm_u = float(np.linalg.norm(u))
    if not (math.isfinite(norm_u) and norm_u > 0.0):
        return FloorFit(None, n_used, share, why="the floor's fit diverged")
    if float(n_up @ (R_cur_kf @ up if forward else up)) < math.cos(math.radians(max_tilt_deg)):
        return FloorFit(None, n_used, share, why="the floor's fit left the floor's directions")
    rel_std = math.sqrt(max(float(u @ cov_u @ u), 0.0)) / norm_u**2
    h_base = step / norm_u
    if forward:
        normal, height = n_up, h_base
    else:
        # the keyframe's floor: the current camera centre's height above it, its normal turned into the frame
        normal, height = R_cur_kf @ n_up, h_base + float(n_up @ c_cur)
    if not (height > 0.0 and math.isfinite(rel_std)):
        return FloorFit(None, n_used, share, why="the floor's fit puts the camera below it")
    if rel_std > FLOOR_MAX_REL_STD:
        return FloorFit(None, n_used, share, why=f"the floor's height is known only to {100 * rel_std:.0f} %: "
                                                 "too far below for the step's parallax")
    return FloorFit(GroundPlane(normal, height, n_used, rel_std), n_used, share)
