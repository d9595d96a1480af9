"""The floor's plane-induced homography between two keyframes (``core/floor_view``), and the ``ground_plane``
scale source's use of it where the map holds no floor points.

The two images are ray-cast here: a camera ``HEIGHT_M`` above a floor of fine random texture (gravel-like: no
corner stands out), pitched down, driving forward with a small turn; above the floor's horizon a far wall of
its own texture. The motion is given in map units (metres over ``MAP_SCALE``), as the VO would measure it.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.floor import LEVEL_UP
from epi_vo.core.floor_view import FloorView, floor_between
from epi_vo.core.scale import GroundPlaneScale, KeyframeStep, ScaleFilter, WheelOdometry

W, H, F = 320, 240, 260.0
HEIGHT_M = 1.5
MAP_SCALE = 2.5  # metres per map unit: the height found must be HEIGHT_M / MAP_SCALE
TEXTURE_PX_PER_M = 100.0


def _camera() -> CameraModel:
    return CameraModel.create(W, H, [F, 0.0, (W - 1) / 2.0, 0.0, F, (H - 1) / 2.0, 0.0, 0.0, 1.0], [0.0] * 5)


def _rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _texture(seed: int, size: int) -> np.ndarray:
    """Fine random texture with some coarser structure, 0-255 float32."""
    rng = np.random.default_rng(seed)
    fine = cv2.GaussianBlur(rng.normal(0.0, 1.0, (size, size)).astype(np.float32), (0, 0), 1.5)
    coarse = cv2.GaussianBlur(rng.normal(0.0, 1.0, (size, size)).astype(np.float32), (0, 0), 8.0)
    t = fine / fine.std() + 0.5 * coarse / coarse.std()
    return np.asarray(np.clip(128.0 + 30.0 * t, 0.0, 255.0), np.float32)


FLOOR_TEX = _texture(1, 4000)  # 40 m x 40 m of floor
WALL_TEX = _texture(2, 2000)


def _render(R_w_c: np.ndarray, c_w: np.ndarray) -> np.ndarray:
    """The image of a camera at ``c_w`` (world: x right, y down, z ahead; the floor is y = HEIGHT_M) turned by
    ``R_w_c``; a wall 40 m ahead (z = 40) above the floor."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([(u - (W - 1) / 2.0) / F, (v - (H - 1) / 2.0) / F, np.ones_like(u)], axis=-1) @ R_w_c.T
    with np.errstate(divide="ignore", invalid="ignore"):
        lam_floor = np.where(rays[..., 1] > 1e-9, (HEIGHT_M - c_w[1]) / rays[..., 1], np.inf)
        lam_wall = np.where(rays[..., 2] > 1e-9, (40.0 - c_w[2]) / rays[..., 2], np.inf)
    floor = lam_floor < lam_wall
    lam = np.where(floor, lam_floor, lam_wall)
    X = c_w + lam[..., None] * rays
    fx = (X[..., 0] * TEXTURE_PX_PER_M + FLOOR_TEX.shape[1] / 2.0).astype(np.float32)
    fz = (X[..., 2] * TEXTURE_PX_PER_M + 200.0).astype(np.float32)
    wy = (X[..., 1] * TEXTURE_PX_PER_M + WALL_TEX.shape[0] / 2.0).astype(np.float32)
    on_floor = cv2.remap(FLOOR_TEX, fx, fz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    on_wall = cv2.remap(WALL_TEX, (X[..., 0] * TEXTURE_PX_PER_M + 1000.0).astype(np.float32), wy, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT)
    img = np.where(floor, on_floor, on_wall)
    noise = np.random.default_rng(3).normal(0.0, 1.0, img.shape)
    return np.asarray(np.clip(img + noise, 0, 255), np.uint8)


Views = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _two_views(pitch_deg: float, step_m: float, yaw_deg: float) -> Views:
    """Keyframe and current image, and the motion X_cur = R X_kf + t with t in map units."""
    R_kf = _rot_x(-pitch_deg)  # camera-to-world: the optical axis turned down towards +y
    c_kf = np.zeros(3)
    R_cur = _rot_y(yaw_deg) @ R_kf
    c_cur = np.array([0.0, 0.0, step_m])
    R = R_cur.T @ R_kf
    t = R_cur.T @ (c_kf - c_cur)
    return _render(R_kf, c_kf), _render(R_cur, c_cur), R, t / MAP_SCALE


@pytest.mark.parametrize(("pitch_deg", "step_m", "yaw_deg"), [(10.0, 0.8, 1.0), (20.0, 0.4, -2.0), (3.0, 1.5, 0.5)])
def test_the_floor_is_found_at_the_cameras_height_in_map_units(pitch_deg: float, step_m: float, yaw_deg: float) -> None:
    kf, cur, R, t = _two_views(pitch_deg, step_m, yaw_deg)
    up_true = _rot_x(-pitch_deg).T @ np.array([0.0, -1.0, 0.0])  # the floor's up in the camera frame
    camera = _camera()
    fit = floor_between(FloorView(kf, camera, 0), cur, camera, R, t, up_true, max_tilt_deg=35.0)
    assert fit.plane is not None, fit.why
    h_map = HEIGHT_M / MAP_SCALE
    assert fit.plane.height == pytest.approx(h_map, rel=0.02)
    up_cur = R @ up_true
    assert math.degrees(math.acos(min(1.0, float(fit.plane.normal_up @ up_cur)))) < 1.0
    # its own standard error is no promise of a few hundredths when it is right to 2 %: it is of that order
    assert 0.0 < fit.plane.rel_std < 0.05


def test_the_floor_is_found_with_the_mounting_a_few_degrees_off() -> None:
    """The declared mounting (a level camera) is 6 deg from the truth: the normal's prior is a prior, the
    images move the fit to the floor."""
    kf, cur, R, t = _two_views(6.0, 0.8, 1.0)
    camera = _camera()
    fit = floor_between(FloorView(kf, camera, 0), cur, camera, R, t, LEVEL_UP, max_tilt_deg=35.0)
    assert fit.plane is not None, fit.why
    assert fit.plane.height == pytest.approx(HEIGHT_M / MAP_SCALE, rel=0.04)
    assert fit.plane.pitch_deg == pytest.approx(6.0, abs=2.0)


def test_no_step_no_floor() -> None:
    kf, cur, R, _ = _two_views(10.0, 0.8, 1.0)
    camera = _camera()
    fit = floor_between(FloorView(kf, camera, 0), cur, camera, R, np.zeros(3), LEVEL_UP, max_tilt_deg=35.0)
    assert fit.plane is None and fit.why


def test_ground_plane_measures_the_scale_from_the_images_where_the_map_holds_no_floor() -> None:
    """The map's points of the step are all on a wall (no floor among them): the floor's homography between the
    two keyframes' images gives the measurement, camera_height_m over the height in map units."""
    pitch = 10.0
    kf, cur, R, t = _two_views(pitch, 0.8, 1.0)
    camera = _camera()
    up = _rot_x(-pitch).T @ np.array([0.0, -1.0, 0.0])
    cfg = VoConfig()
    src = GroundPlaneScale(filter=ScaleFilter(cfg.scale_drift_per_keyframe), camera_height_m=HEIGHT_M,
                           max_tilt_deg=cfg.ground_max_tilt_deg, inlier_ratio=cfg.ground_inlier_ratio,
                           min_points=cfg.ground_min_points).with_mounting_up(up)
    src = src.viewing(kf, camera, 100)
    rng = np.random.default_rng(0)
    wall = np.column_stack([rng.uniform(-3, 3, 60), rng.uniform(-3, 0.5, 60), np.full(60, 16.0)]) / MAP_SCALE
    step = KeyframeStep(wall, float(np.linalg.norm(t)), 100, 200, R, t, cur, camera)
    after, measured = src.measure(step, WheelOdometry())
    assert measured is not None, after.reason
    assert math.exp(measured[0]) == pytest.approx(MAP_SCALE, rel=0.02)
    assert after.plane is not None and after.plane.height == pytest.approx(HEIGHT_M / MAP_SCALE, rel=0.02)
    # without the images (a step that brings none) the map's points alone decide: no floor, and why
    alone, none = src.measure(KeyframeStep(wall, float(np.linalg.norm(t)), 100, 200), WheelOdometry())
    assert none is None and "no floor plane" in alone.reason
