#!/usr/bin/env python3
"""Render synthetic scenes with exact camera motion and write them as small ROS 2 bags (MCAP).

Each bag holds a compressed mono image stream, its camera_info and the ground-truth pose, so the tests
and the demo have sequences whose answer is known exactly; ``ground_robot`` (a wheeled robot's camera over
a paved floor) also holds simulated 50 Hz wheel odometry with a documented error model (bags/README.md).
In ``static_mover`` and ``moving_mover`` an object (``Mover``: a rigid group of quads with its own pose per
frame) moves independently of the camera; its per-frame image share and bounding box are written to
``mover_coverage.txt`` and its pose to ``<mover>_pose_tum.txt``, while the ground truth stays the camera's.
Everything is deterministic: the scenes, the trajectories and the sensor noise (seeded per bag) give the
same bytes on every run with the same OpenCV and numpy.

Conventions
-----------
- World frame of every scene: x right, y down, z forward (a level camera's optical frame). The ground
  plane is ``y = GROUND_Y_M`` (``y = ROBOT_FLOOR_Y_M`` in the ground-robot arena).
- ``T_w_c`` (4, 4) maps points from the camera optical frame (x right, y down, z forward) into the world.
- The written ground truth is ``T_c0_ci = inv(T_w_c0) @ T_w_ci``: the pose of frame i in the optical
  frame of frame 0, so frame 0 is the identity. Quaternions are written ``quat_xyzw``.
- Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).

Rendering
---------
Scenes are planar textured rectangles ("quads"). For every supersampled pixel the renderer casts the
pixel's ray, intersects it analytically with each quad's plane (the static scene's, then the movers' placed
at the frame's pose), keeps the nearest hit in front of the near plane (a per-pixel z-buffer on the depth
along the optical axis), and samples the quad's texture at
the hit point with trilinear mipmapping (``cv2.remap`` on a Gaussian pyramid). Ray casting makes
perspective and occlusion exact and clips quads that reach behind the camera without special cases.
A lens-distorted camera is rendered the same way: each distorted pixel's ray is its undistorted
normalized coordinate, so the image is the exact plumb_bob image of the scene with no second
resampling. The 2x supersampled image is reduced with ``INTER_AREA`` (2x2 box anti-aliasing), blurred
by a small Gaussian point-spread function (the optics; it also keeps the JPEG frames small) and Gaussian
sensor noise is added.

Run ``.venv/bin/python bags/make_bags.py`` (``--only NAME``, ``--out DIR``) to regenerate the bags.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import math
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import skimage.data
from numpy.typing import NDArray
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

# --- camera and stream --------------------------------------------------------------------------------

IMAGE_WIDTH = 640
IMAGE_HEIGHT = 480
FX = FY = 500.0
CX = 319.5
CY = 239.5
# plumb_bob order: k1, k2, p1, p2, k3. Mild barrel distortion with a little decentring.
DISTORTION_GENERAL = (-0.08, 0.02, 0.0005, -0.0005, 0.0)
FPS = 15
START_NS = 1_000 * 1_000_000_000  # first stamp: 1000.0 s
NS_PER_S = 1_000_000_000
JPEG_QUALITY = 90
LENS_BLUR_SIGMA_PX = 0.6  # Gaussian point-spread function of the optics, in output pixels
NOISE_SIGMA = 1.5  # gray levels, Gaussian, added after the optics like a real sensor's read noise
SUPERSAMPLE = 2  # render at 2x and reduce with INTER_AREA: 2x2 box anti-aliasing
NEAR_M = 0.1  # near plane in the camera frame: hits closer than this along z are discarded
MIN_CLEARANCE_M = 1.5  # default: no quad may come nearer than this to any camera centre (BagSpec.min_clearance_m)
ROS_BAG_VERSION = 8  # rosbag2 metadata version, as in shared/data/kitti06_0-50

IMAGE_TOPIC = "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
GROUND_TRUTH_TOPIC = "/ground_truth/pose"
WHEEL_ODOM_TOPIC = "/wheel/odom"  # only in bags with wheel odometry (ground_robot)
CAMERA_FRAME_ID = "camera_optical_frame"
WORLD_FRAME_ID = "world"
ODOM_FRAME_ID = "odom"
BASE_FRAME_ID = "base_link"

GROUND_Y_M = 1.6  # the camera starts 1.6 m above the ground (y points down)

Matrix4 = NDArray[np.float64]
FloatImage = NDArray[np.float32]


class SceneError(Exception):
    """A scene or trajectory that breaks the rules the bags promise (clearance, full coverage)."""


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with optional plumb_bob distortion.

    ``K`` (3, 3) intrinsics; ``D`` (5,) plumb_bob coefficients k1, k2, p1, p2, k3.
    """

    width: int
    height: int
    K: NDArray[np.float64]
    D: NDArray[np.float64]

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(self.D != 0.0))


def make_camera(distortion: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0)) -> CameraModel:
    """The 640x480 camera of every bag, fx = fy = 500, principal point at the image centre."""
    K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    return CameraModel(IMAGE_WIDTH, IMAGE_HEIGHT, K, np.asarray(distortion, dtype=np.float64))


@dataclass(frozen=True)
class Quad:
    """A textured rectangle in the world.

    The texture's top-left corner sits at ``origin_w`` (3,), its columns run along ``edge_u_w`` (3,)
    and its rows along ``edge_v_w`` (3,); the two edges are orthogonal and span the whole rectangle
    (metres, world frame). The texture repeats ``repeat_u`` x ``repeat_v`` times, mirrored at each
    seam so tiles join without edges. Rendered intensity is ``gain * texture + offset``.
    """

    origin_w: tuple[float, float, float]
    edge_u_w: tuple[float, float, float]
    edge_v_w: tuple[float, float, float]
    texture: str
    repeat_u: float = 1.0
    repeat_v: float = 1.0
    gain: float = 1.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        eu, ev = np.asarray(self.edge_u_w), np.asarray(self.edge_v_w)
        # Texture coordinates are projections on the edges: only exact for a rectangle.
        if abs(float(eu @ ev)) > 1e-9 * float(np.linalg.norm(eu) * np.linalg.norm(ev)):
            msg = f"quad edges are not orthogonal: {self.edge_u_w} and {self.edge_v_w}"
            raise SceneError(msg)


def transform_quad(quad: Quad, T: Matrix4) -> Quad:
    """The quad moved by the rigid transform ``T`` (4, 4): corners ``R X + t``, edges ``R e``."""
    R, t = T[:3, :3], T[:3, 3]
    origin = R @ np.asarray(quad.origin_w, dtype=np.float64) + t
    eu, ev = R @ np.asarray(quad.edge_u_w, dtype=np.float64), R @ np.asarray(quad.edge_v_w, dtype=np.float64)
    return Quad(
        tuple(float(v) for v in origin),
        tuple(float(v) for v in eu),
        tuple(float(v) for v in ev),
        quad.texture,
        quad.repeat_u,
        quad.repeat_v,
        quad.gain,
        quad.offset,
    )


@dataclass(frozen=True)
class Mover:
    """A rigid group of quads that moves on its own (a panel, a cart): ``quads`` are given in the mover's
    own frame, and at frame i they stand in the world at ``T_w_o[i] @ X`` (``T_w_o`` (N, 4, 4), one pose per
    image). The renderer z-buffers them against the static scene in every frame; the ground truth stays
    the camera's pose only."""

    name: str
    quads: tuple[Quad, ...]
    T_w_o: NDArray[np.float64]

    def quads_at(self, frame_index: int) -> tuple[Quad, ...]:
        """The mover's quads in the world at frame ``frame_index``."""
        return tuple(transform_quad(q, self.T_w_o[frame_index]) for q in self.quads)


@dataclass(frozen=True)
class WheelOdometry:
    """Simulated wheel odometry of a ground robot, one row per ``/wheel/odom`` message.

    ``stamps_ns`` (K,) int64, strictly increasing; ``pose`` (K, 3) x, y (m) and yaw (rad) of base_link in
    odom; ``twist`` (K, 2) the measured forward speed (m/s) and yaw rate (rad/s) in base_link;
    ``pose_covariance`` and ``twist_covariance`` (K, 36) row-major 6x6 over (x, y, z, rot x, rot y, rot z).
    """

    stamps_ns: NDArray[np.int64]
    pose: NDArray[np.float64]
    twist: NDArray[np.float64]
    pose_covariance: NDArray[np.float64]
    twist_covariance: NDArray[np.float64]


@dataclass(frozen=True)
class BagSpec:
    """Everything one bag is made from: scene, camera, trajectory ``T_w_c`` (N, 4, 4) and noise seed.

    Optional, for bags that need them: the smallest allowed camera-to-quad distance ``min_clearance_m``,
    the JPEG quality, wheel odometry to write on ``/wheel/odom``, and the height ``floor_y_m`` (world y)
    of a floor whose image share and image motion ``make_bag`` measures (and bounds, ``MAX_FLOOR_FLOW_PX``),
    and independently moving objects ``movers`` (their per-frame image share and bounding box go to
    ``mover_coverage.txt``, their poses to ``mover_pose_tum.txt``).
    """

    name: str
    quads: tuple[Quad, ...]
    camera: CameraModel
    T_w_c: NDArray[np.float64]
    noise_seed: int
    min_clearance_m: float = MIN_CLEARANCE_M
    jpeg_quality: int = JPEG_QUALITY
    wheel_odom: WheelOdometry | None = None
    floor_y_m: float | None = None
    movers: tuple[Mover, ...] = ()

    def moving_quads_at(self, frame_index: int) -> tuple[Quad, ...]:
        """The quads of every mover, placed in the world at frame ``frame_index``."""
        return tuple(q for mover in self.movers for q in mover.quads_at(frame_index))


# --- small geometry helpers -----------------------------------------------------------------------------


def rot_x(angle_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_rotation(yaw_rad: float, pitch_rad: float, roll_rad: float) -> NDArray[np.float64]:
    """``R_w_c`` of a camera that pans by yaw (about world y, positive turns right), then tilts by pitch
    (about its x, positive looks up: the optical axis turns towards -y) and rolls (about its z)."""
    return rot_y(yaw_rad) @ rot_x(pitch_rad) @ rot_z(roll_rad)


def se3(R: NDArray[np.float64], t: Sequence[float] | NDArray[np.float64]) -> Matrix4:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def invert_se3(T: Matrix4) -> Matrix4:
    R = T[:3, :3]
    return se3(R.T, -R.T @ T[:3, 3])


def quat_xyzw_from_rotation(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w) of rotation matrix ``R`` (3, 3), with w >= 0 (Shepperd's method)."""
    trace = float(np.trace(R))
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def poses_relative_to_first(T_w_c: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_c0_ci = inv(T_w_c0) @ T_w_ci`` for every pose in ``T_w_c`` (N, 4, 4): frame 0 becomes identity.

    The translation is formed as ``R_w_c0^T (c_i - c_0)`` so that a camera centre that does not move
    gives exactly zero (the pure-rotation bag relies on it).
    """
    R_w_c0, c0 = T_w_c[0, :3, :3], T_w_c[0, :3, 3]
    relative = np.empty_like(T_w_c)
    for i, T in enumerate(T_w_c):
        relative[i] = se3(R_w_c0.T @ T[:3, :3], R_w_c0.T @ (T[:3, 3] - c0) + 0.0)  # + 0.0 turns -0.0 into 0.0
    return relative


def stamp_ns(frame_index: int) -> int:
    """Stamp of frame i: 1000 s + i / 15 s, rounded to the nearest integer nanosecond."""
    return START_NS + (frame_index * NS_PER_S + FPS // 2) // FPS


# --- textures ---------------------------------------------------------------------------------------------

# Photographs bundled with scikit-image (public domain or CC0, see bags/README.md).
PHOTO_TEXTURES = (
    "astronaut",
    "brick",
    "camera",
    "chelsea",
    "coffee",
    "coins",
    "grass",
    "gravel",
    "hubble_deep_field",
    "rocket",
    "text",
)
# Photographs used only on the movers, so a mover never looks like the background (not in PHOTO_TEXTURES,
# which the poster mosaic cycles through).
MOVER_TEXTURES = ("immunohistochemistry",)
MOSAIC_TEXTURE = "poster_mosaic"
MOSAIC_GRID = (6, 9)  # rows, columns of photographs on the poster wall
MOSAIC_TILE_PX = 256
MOSAIC_SEED = 7
PAVING_TEXTURE = "paving"
PAVING_GRID = 12  # slabs per side of the paving texture
PAVING_SLAB_PX = 256  # slab pitch in texels, joint included
PAVING_JOINT_PX = 4  # joint (grout) on each side of a slab: 8 texels between two slabs, and at a mirrored seam
PAVING_SOURCES = ("gravel", "brick", "grass")  # photographs with detail everywhere
PAVING_SEED = 11


def _poster_mosaic() -> NDArray[np.uint8]:
    """A wall of square photo crops (``MOSAIC_GRID`` of ``MOSAIC_TILE_PX`` pixels), seeded.

    Each tile is a different crop (60-100 % of the short side, random position) of the photographs in
    turn, so no two tiles are alike and every view of the wall holds several photographs: small tiles
    keep large uniform regions (a cup's black inside) from filling the image.
    """
    rng = np.random.default_rng(MOSAIC_SEED)
    rows, cols = MOSAIC_GRID
    tiles = []
    for index in range(rows * cols):
        photo = load_texture(PHOTO_TEXTURES[index % len(PHOTO_TEXTURES)])
        h, w = photo.shape
        side = int(min(h, w) * rng.uniform(0.6, 1.0))
        top, left = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        crop = photo[top : top + side, left : left + side]
        shrink = cv2.INTER_AREA if side >= MOSAIC_TILE_PX else cv2.INTER_LINEAR
        tiles.append(cv2.resize(crop, (MOSAIC_TILE_PX, MOSAIC_TILE_PX), interpolation=shrink))
    return np.vstack([np.hstack(tiles[r * cols : (r + 1) * cols]) for r in range(rows)])


def _paving() -> NDArray[np.uint8]:
    """A square of ``PAVING_GRID`` x ``PAVING_GRID`` paving slabs separated by dark joints, seeded.

    Every slab is a different crop (35-75 % of the short side, random position, turned by a random
    multiple of 90 deg and maybe mirrored) of a photograph with detail everywhere (``PAVING_SOURCES``:
    gravel, bricks, grass), at its own brightness and contrast. The joints give strong corners where
    the floor is seen from afar and foreshortened; the photographs give corners close by.
    """
    rng = np.random.default_rng(PAVING_SEED)
    inner = PAVING_SLAB_PX - 2 * PAVING_JOINT_PX
    side_px = PAVING_GRID * PAVING_SLAB_PX
    paving = np.full((side_px, side_px), 38.0, np.float32)  # grout
    for index in range(PAVING_GRID * PAVING_GRID):
        photo = load_texture(PAVING_SOURCES[int(rng.integers(len(PAVING_SOURCES)))])
        h, w = photo.shape
        side = int(min(h, w) * rng.uniform(0.35, 0.75))
        top, left = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        crop = np.rot90(photo[top : top + side, left : left + side], int(rng.integers(4)))
        if rng.uniform() < 0.5:
            crop = crop[:, ::-1]
        slab = cv2.resize(np.ascontiguousarray(crop), (inner, inner), interpolation=cv2.INTER_AREA).astype(np.float32)
        gain, offset = rng.uniform(0.55, 1.1), rng.uniform(-10.0, 45.0)
        row, col = divmod(index, PAVING_GRID)
        y0, x0 = row * PAVING_SLAB_PX + PAVING_JOINT_PX, col * PAVING_SLAB_PX + PAVING_JOINT_PX
        paving[y0 : y0 + inner, x0 : x0 + inner] = gain * slab + offset
    return np.clip(np.rint(paving), 0, 255).astype(np.uint8)


# Textures made by code rather than read from a photograph: name -> a function returning the grayscale
# uint8 image (deterministic). The scenario families (bags/scenarios.py) register their own here.
TEXTURE_MAKERS: dict[str, Callable[[], NDArray[np.uint8]]] = {}


@functools.cache
def load_texture(name: str) -> NDArray[np.uint8]:
    """Grayscale uint8 texture by name: a scikit-image photograph, the poster mosaic or the paving built
    from them, or one of ``TEXTURE_MAKERS``."""
    if name == MOSAIC_TEXTURE:
        return _poster_mosaic()
    if name == PAVING_TEXTURE:
        return _paving()
    if name in TEXTURE_MAKERS:
        return np.ascontiguousarray(TEXTURE_MAKERS[name](), dtype=np.uint8)
    if name not in PHOTO_TEXTURES and name not in MOVER_TEXTURES:
        known = (*PHOTO_TEXTURES, *MOVER_TEXTURES, MOSAIC_TEXTURE, PAVING_TEXTURE, *TEXTURE_MAKERS)
        msg = f"unknown texture {name!r}; expected one of {known}"
        raise SceneError(msg)
    image = np.asarray(getattr(skimage.data, name)())
    if image.ndim == 3:
        image = cv2.cvtColor(image[..., :3], cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(image, dtype=np.uint8)


def texture_aspect(name: str) -> float:
    """Height over width of a texture."""
    h, w = load_texture(name).shape
    return h / w


@functools.cache
def texture_pyramid(name: str) -> tuple[FloatImage, ...]:
    """Mipmap pyramid (float32, level 0 full size) of a texture, down to about 8 pixels."""
    levels = [load_texture(name).astype(np.float32)]
    while min(levels[-1].shape) >= 16:
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


# --- scene building ---------------------------------------------------------------------------------------

DOWN_W = np.array([0.0, 1.0, 0.0])


def wall_quad(
    center_w: Sequence[float],
    facing_w: Sequence[float],
    width_m: float,
    height_m: float | None,
    texture: str,
    *,
    tile_m: float | None = None,
    gain: float = 1.0,
    offset: float = 0.0,
) -> Quad:
    """An upright rectangle centred at ``center_w`` whose front faces the horizontal direction ``facing_w``.

    The texture reads upright and unmirrored from the front. ``height_m=None`` keeps the texture's
    aspect ratio; ``tile_m`` repeats the texture every ``tile_m`` metres horizontally (None: stretch once).
    """
    facing = np.asarray(facing_w, dtype=np.float64)
    facing = facing / np.linalg.norm(facing)
    right = np.cross(DOWN_W, -facing)  # viewer looks along -facing with y down: right = down x forward
    aspect = texture_aspect(texture)
    if height_m is None:
        height_m = width_m * aspect
    if tile_m is None:
        repeat_u, repeat_v = 1.0, 1.0
    else:
        repeat_u, repeat_v = width_m / tile_m, height_m / (tile_m * aspect)
    origin = np.asarray(center_w, dtype=np.float64) - 0.5 * width_m * right - 0.5 * height_m * DOWN_W
    return Quad(
        tuple(origin), tuple(width_m * right), tuple(height_m * DOWN_W), texture, repeat_u, repeat_v, gain, offset
    )


def horizontal_quad(
    y_m: float,
    x_range: tuple[float, float],
    z_range: tuple[float, float],
    texture: str,
    tile_m: float,
    gain: float = 1.0,
    offset: float = 0.0,
) -> Quad:
    """A horizontal rectangle at height ``y_m`` (ground or ceiling), texture tiled every ``tile_m`` metres."""
    width, depth = x_range[1] - x_range[0], z_range[1] - z_range[0]
    return Quad(
        (x_range[0], y_m, z_range[1]),
        (width, 0.0, 0.0),
        (0.0, 0.0, -depth),
        texture,
        width / tile_m,
        depth / (tile_m * texture_aspect(texture)),
        gain,
        offset,
    )


def box_quads(
    center_x: float,
    center_z: float,
    size_x: float,
    size_z: float,
    height: float,
    texture: str,
    gain: float = 1.0,
    offset: float = 0.0,
    ground_y_m: float = GROUND_Y_M,
) -> list[Quad]:
    """An axis-aligned box standing on the ground (``y = ground_y_m``): four sides facing outwards and a
    tiled top.

    The side faces (normals along x) are shaded 15 % darker and the top 10 % brighter, as under sky light.
    """
    cy = ground_y_m - 0.5 * height
    hx, hz = 0.5 * size_x, 0.5 * size_z
    sides = [
        wall_quad((center_x, cy, center_z - hz), (0, 0, -1), size_x, height, texture, gain=gain, offset=offset),
        wall_quad((center_x, cy, center_z + hz), (0, 0, 1), size_x, height, texture, gain=gain, offset=offset),
        wall_quad((center_x - hx, cy, center_z), (-1, 0, 0), size_z, height, texture, gain=0.85 * gain, offset=offset),
        wall_quad((center_x + hx, cy, center_z), (1, 0, 0), size_z, height, texture, gain=0.85 * gain, offset=offset),
    ]
    top = horizontal_quad(
        ground_y_m - height,
        (center_x - hx, center_x + hx),
        (center_z - hz, center_z + hz),
        texture,
        max(size_x, size_z),
        1.1 * gain,
        offset,
    )
    return [*sides, top]


def courtyard_scene() -> tuple[Quad, ...]:
    """A closed courtyard 14 m wide (ground, four facades, a ceiling that is never in view) with posters
    on the facades, and boxes, pillars and a free-standing billboard spread over 2.5-13 m in front of the
    start pose, so tracked points cover many depths rather than crowding on the far wall."""
    x_wall, z_back, z_front, y_top = 7.0, 16.0, -8.0, GROUND_Y_M - 18.0
    wall_h, wall_cy = GROUND_Y_M - y_top, 0.5 * (GROUND_Y_M + y_top)
    z_mid, z_len = 0.5 * (z_back + z_front), z_back - z_front
    quads: list[Quad] = [
        horizontal_quad(GROUND_Y_M, (-x_wall, x_wall), (z_front, z_back), "gravel", 3.0, 0.9),
        horizontal_quad(y_top, (-x_wall, x_wall), (z_front, z_back), "hubble_deep_field", 12.0, 0.6),
        # The back wall's bricks are toned down: at full contrast they would take most corners.
        wall_quad((0.0, wall_cy, z_back), (0, 0, -1), 2 * x_wall, wall_h, "brick", tile_m=3.0, gain=0.6, offset=40.0),
        wall_quad((0.0, wall_cy, z_front), (0, 0, 1), 2 * x_wall, wall_h, "brick", tile_m=3.0, gain=0.8),
        wall_quad((-x_wall, wall_cy, z_mid), (1, 0, 0), z_len, wall_h, "brick", tile_m=2.5, gain=0.7, offset=20.0),
        wall_quad((x_wall, wall_cy, z_mid), (-1, 0, 0), z_len, wall_h, "grass", tile_m=3.5, gain=1.1),
        # posters 5 cm in front of the facades
        wall_quad((-4.0, -1.0, z_back - 0.05), (0, 0, -1), 5.0, None, "rocket"),
        wall_quad((1.0, -3.8, z_back - 0.05), (0, 0, -1), 4.5, None, "astronaut"),
        wall_quad((4.8, -0.3, z_back - 0.05), (0, 0, -1), 3.5, None, "hubble_deep_field"),
        wall_quad((-x_wall + 0.05, -1.0, 9.0), (1, 0, 0), 4.0, None, "chelsea"),
        wall_quad((-x_wall + 0.05, -2.0, 13.5), (1, 0, 0), 3.5, None, "camera"),
        wall_quad((x_wall - 0.05, -1.0, 8.0), (-1, 0, 0), 4.0, None, "coffee"),
        wall_quad((x_wall - 0.05, -2.5, 13.0), (-1, 0, 0), 3.5, None, "coins"),
        # a free-standing billboard with open space below it (occlusion edges against the back wall)
        wall_quad((2.2, -0.6, 11.0), (0, 0, -1), 3.0, None, "text", gain=0.9, offset=15.0),
    ]
    quads += box_quads(2.0, 3.1, 1.0, 1.0, 1.0, "coffee")
    quads += box_quads(-2.7, 5.0, 1.0, 1.0, 1.4, "chelsea")
    quads += box_quads(-3.6, 7.4, 0.8, 0.8, 0.9, "coffee", gain=0.9)
    quads += box_quads(1.3, 6.2, 0.8, 0.8, 1.6, "gravel", gain=1.1)
    quads += box_quads(-1.8, 6.5, 0.5, 0.5, 3.5, "brick", gain=0.9)
    quads += box_quads(3.25, 7.0, 1.5, 1.0, 2.6, "coins", gain=1.2)
    quads += box_quads(-0.1, 9.0, 1.4, 1.2, 2.0, "camera")
    quads += box_quads(-4.25, 10.0, 1.5, 1.5, 3.0, "rocket")
    quads += box_quads(4.6, 11.5, 1.2, 1.2, 1.8, "hubble_deep_field", gain=1.3, offset=20.0)
    quads += box_quads(0.9, 12.5, 0.6, 0.6, 4.5, "grass")
    return tuple(quads)


def smooth_trajectory(
    n_frames: int, position: Callable[[float], Sequence[float]], angles: Callable[[float], Sequence[float]]
) -> NDArray[np.float64]:
    """``T_w_c`` (N, 4, 4) sampled at s = i / (N - 1) from a position and (yaw, pitch, roll) in radians."""
    poses = []
    for i in range(n_frames):
        s = i / (n_frames - 1)
        yaw, pitch, roll = angles(s)
        poses.append(se3(camera_rotation(yaw, pitch, roll), position(s)))
    return np.stack(poses)


def general_motion_spec(n_frames: int = 52) -> BagSpec:
    """Courtyard scene, distorted camera, walking pace (about 1.2 m/s) along a gentle S curve: 3.8 m
    forward, +-0.5 m sideways, 0.12 m up (4.4 m path). The camera keeps looking towards a point about
    6 m ahead (yaw against the sideways motion, +-5 deg) as a person walking would; pitch and roll stay
    within 1.5 deg."""
    deg = math.pi / 180.0

    def position(s: float) -> tuple[float, float, float]:
        return 0.5 * math.sin(2 * math.pi * s), -0.12 * math.sin(math.pi * s), 3.8 * s

    def angles(s: float) -> tuple[float, float, float]:
        yaw = -5.0 * deg * math.sin(2 * math.pi * s) + 1.5 * deg * math.sin(math.pi * s)
        pitch = 1.5 * deg * math.sin(3 * math.pi * s)
        roll = 1.5 * deg * math.sin(math.pi * s + 0.3)
        return yaw, pitch, roll

    return BagSpec(
        "general_motion",
        courtyard_scene(),
        make_camera(DISTORTION_GENERAL),
        smooth_trajectory(n_frames, position, angles),
        noise_seed=1,
    )


def pure_rotation_spec(n_frames: int = 52) -> BagSpec:
    """Courtyard scene, camera centre fixed at (0.3, -0.1, 1.0): pan -11 -> +11 deg, tilt within 3 deg."""
    deg = math.pi / 180.0

    def position(s: float) -> tuple[float, float, float]:
        return 0.3, -0.1, 1.0

    def angles(s: float) -> tuple[float, float, float]:
        yaw = 22.0 * deg * (s - 0.5) + 1.0 * deg * math.sin(2 * math.pi * s)
        pitch = 3.0 * deg * math.sin(math.pi * s) - 1.0 * deg
        roll = 1.0 * deg * math.sin(2 * math.pi * s)
        return yaw, pitch, roll

    return BagSpec(
        "pure_rotation", courtyard_scene(), make_camera(), smooth_trajectory(n_frames, position, angles), noise_seed=2
    )


def planar_scene() -> tuple[Quad, ...]:
    """One 12 m x 8 m poster wall (9 x 6 photographs) 3.5 m ahead, turned 15 deg about the vertical, so the
    part in view lies 3-4 m away."""
    facing = rot_y(15.0 * math.pi / 180.0) @ np.array([0.0, 0.0, -1.0])
    return (wall_quad((0.0, 0.0, 3.5), facing, 12.0, None, MOSAIC_TEXTURE),)


def planar_spec(n_frames: int = 60) -> BagSpec:
    """Single plane; camera moves 0.7 m sideways and 0.35 m forward (0.78 m) with a few degrees of rotation."""
    deg = math.pi / 180.0

    def position(s: float) -> tuple[float, float, float]:
        return -0.35 + 0.7 * s, 0.05 * math.sin(math.pi * s), 0.35 * s

    def angles(s: float) -> tuple[float, float, float]:
        yaw = -2.0 * deg + 5.0 * deg * s
        pitch = 1.5 * deg * math.sin(2 * math.pi * s)
        roll = 1.0 * deg * math.sin(math.pi * s)
        return yaw, pitch, roll

    return BagSpec("planar", planar_scene(), make_camera(), smooth_trajectory(n_frames, position, angles), noise_seed=3)


# --- ground robot: a wheeled robot's camera over a paved floor, with wheel odometry ----------------------
#
# The robot's frames follow ROS (REP 103/105): base_link x forward, y left, z up, origin on the floor under
# the axle centre; odom is base_link at the first wheel message. The planar robot trajectory is given in a
# floor frame "plane" (x forward, y left, z up, origin on the floor) that coincides with base_link at the
# first image stamp; the scene world is the usual x right, y down, z forward frame with the floor at
# y = ROBOT_FLOOR_Y_M, so every camera centre is at world y = 0.

ROBOT_FRAMES = 300  # 20 s at 15 Hz
CAMERA_XYZ_IN_BASE_M = (0.20, 0.0, 0.45)  # optical centre 0.20 m ahead of the base origin, 0.45 m above the floor
CAMERA_RPY_IN_BASE_RAD = (0.0, math.radians(15.0), 0.0)  # pitched 15 deg down, no roll, no yaw
ROBOT_FLOOR_Y_M = CAMERA_XYZ_IN_BASE_M[2]  # world y of the floor
ROBOT_MIN_CLEARANCE_M = 0.3  # the floor is 0.45 m below the camera; structures stay >= 2 m from the path
ROBOT_JPEG_QUALITY = 75  # 300 rich floor frames at quality 90 would make a 22 MB bag; at 75 it stays under 15 MB
MAX_FLOOR_FLOW_PX = 40.0  # largest image motion of a visible floor point between frames (KLT, 15 px, 3 levels)
# (centre s, duration s, peak yaw rate deg/s) of the raised-cosine turns (they must not overlap: the speed
# follows |yaw rate|); positive turns left
ROBOT_TURNS = ((3.0, 3.2, 20.0), (8.3, 4.0, -20.0), (13.2, 3.0, 20.0), (17.3, 3.0, -16.0))
ROBOT_MAX_YAW_RATE_DEG_S = 20.0  # at this yaw rate the robot is down to ROBOT_TURN_SPEED_M_S
ROBOT_TURN_SPEED_M_S = 0.4
# optical frame (x right, y down, z forward) in a body frame (x forward, y left, z up)
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# the floor frame in the scene world: plane x -> world z, plane y -> world -x, plane z -> world -y
T_WORLD_PLANE = se3(R_BODY_OPTICAL.T, (0.0, ROBOT_FLOOR_Y_M, 0.0))

WHEEL_RATE_HZ = 50
WHEEL_PERIOD_NS = NS_PER_S // WHEEL_RATE_HZ
WHEEL_FIRST_NS = START_NS - 500_000_000 + 7_000_000  # 0.493 s before the first image, 7 ms off the image grid
WHEEL_TAIL_NS = 100_000_000  # wheel messages continue up to 0.1 s after the last image
WHEEL_SCALE_ERROR = 0.025  # measured distance = 1.025 x true (wheel radius 2.5 % too large)
WHEEL_YAW_RATE_BIAS_RAD_S = math.radians(0.5)  # added to the yaw rate (positive: drifts to the left)
WHEEL_SPEED_NOISE = 0.01  # Gaussian, relative to the speed, independent per 20 ms step
WHEEL_YAW_RATE_NOISE_RAD_S = math.radians(0.5)  # Gaussian, independent per 20 ms step
WHEEL_NOISE_SEED = 5
_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(8)


def rpy_rotation(roll: float, pitch: float, yaw: float) -> NDArray[np.float64]:
    """ROS fixed-axis roll, pitch, yaw: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def base_camera_transform() -> Matrix4:
    """``T_base_camera``: the camera optical frame in base_link (the mounting documented in bags/README.md)."""
    roll, pitch, yaw = CAMERA_RPY_IN_BASE_RAD
    return se3(rpy_rotation(roll, pitch, yaw) @ R_BODY_OPTICAL, CAMERA_XYZ_IN_BASE_M)


def planar_pose(x: float, y: float, yaw: float) -> Matrix4:
    """SE(3) of a planar pose: position (x, y, 0), rotation ``yaw`` about z."""
    return se3(rot_z(yaw), (x, y, 0.0))


def robot_speed(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """True forward speed (m/s) at ``t`` seconds after the first image: a cruise speed of 0.55-0.68 m/s
    (a rolling start that speeds up, with a gentle 7 s oscillation) that drops towards 0.4 m/s in the turns,
    as a robot slows down to turn: ``0.4 + (cruise - 0.4) (1 - |yaw rate| / ROBOT_MAX_YAW_RATE)``."""
    t = np.asarray(t, dtype=np.float64)
    cruise = 0.6 + 0.05 * np.tanh((t - 1.5) / 1.5) + 0.03 * np.sin(2.0 * math.pi * t / 7.0)
    turning = np.abs(robot_yaw_rate(t)) / math.radians(ROBOT_MAX_YAW_RATE_DEG_S)
    return ROBOT_TURN_SPEED_M_S + (cruise - ROBOT_TURN_SPEED_M_S) * (1.0 - turning)


def robot_yaw_rate(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """True yaw rate (rad/s): raised-cosine turns ``ROBOT_TURNS``, zero in between."""
    t = np.asarray(t, dtype=np.float64)
    rate = np.zeros_like(t)
    for centre, duration, peak_deg in ROBOT_TURNS:
        tau = t - centre
        bump = 0.5 * math.radians(peak_deg) * (1.0 + np.cos(2.0 * math.pi * tau / duration))
        rate = rate + np.where(np.abs(tau) < 0.5 * duration, bump, 0.0)
    return rate


def robot_yaw(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """True heading (rad) in the plane frame: the exact integral of ``robot_yaw_rate`` from 0 to ``t``."""

    def turned(tt: NDArray[np.float64]) -> NDArray[np.float64]:
        total = np.zeros_like(tt)
        for centre, duration, peak_deg in ROBOT_TURNS:
            tau = np.clip(tt - centre, -0.5 * duration, 0.5 * duration)
            total = total + 0.5 * math.radians(peak_deg) * (
                tau + 0.5 * duration + duration / (2.0 * math.pi) * np.sin(2.0 * math.pi * tau / duration)
            )
        return total

    t = np.asarray(t, dtype=np.float64)
    return turned(t) - turned(np.zeros_like(t))


def _integrate(f: Callable[[NDArray[np.float64]], NDArray[np.float64]], a: float, b: float) -> float:
    """Integral of a smooth ``f`` over [a, b]: 8-point Gauss-Legendre on pieces of at most 20 ms."""
    pieces = max(1, math.ceil(abs(b - a) / 0.02))
    edges = np.linspace(a, b, pieces + 1)
    half, mid = 0.5 * np.diff(edges), 0.5 * (edges[1:] + edges[:-1])
    nodes = mid[:, None] + half[:, None] * _GAUSS_NODES[None, :]
    return float((f(nodes) * _GAUSS_WEIGHTS[None, :] * half[:, None]).sum())


def robot_base_poses(times_s: Sequence[float] | NDArray[np.float64]) -> NDArray[np.float64]:
    """True base_link poses (N, 3): x, y (m) and yaw (rad) in the plane frame at ``times_s`` (seconds after
    the first image), integrated from the unicycle model ``x' = v cos(yaw)``, ``y' = v sin(yaw)``."""
    times = np.asarray(times_s, dtype=np.float64)
    grid = np.unique(np.concatenate([times, [0.0]]))
    start = int(np.searchsorted(grid, 0.0))
    vx = lambda t: robot_speed(t) * np.cos(robot_yaw(t))  # noqa: E731
    vy = lambda t: robot_speed(t) * np.sin(robot_yaw(t))  # noqa: E731
    xy = np.zeros((len(grid), 2))
    for i in range(start + 1, len(grid)):
        xy[i] = xy[i - 1] + (_integrate(vx, grid[i - 1], grid[i]), _integrate(vy, grid[i - 1], grid[i]))
    for i in range(start - 1, -1, -1):
        xy[i] = xy[i + 1] - (_integrate(vx, grid[i], grid[i + 1]), _integrate(vy, grid[i], grid[i + 1]))
    index = np.searchsorted(grid, times)
    return np.column_stack([xy[index], robot_yaw(times)])


def robot_camera_poses(base_poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_w_c`` (N, 4, 4) of the camera for base poses (N, 3) x, y, yaw in the plane frame."""
    T_base_camera = base_camera_transform()
    return np.stack([T_WORLD_PLANE @ planar_pose(x, y, yaw) @ T_base_camera for x, y, yaw in base_poses])


def wheel_stamps_ns(n_frames: int) -> NDArray[np.int64]:
    """``/wheel/odom`` stamps: every 20 ms from ``WHEEL_FIRST_NS`` to at most 0.1 s after the last image."""
    last = stamp_ns(n_frames - 1) + WHEEL_TAIL_NS
    return np.arange(WHEEL_FIRST_NS, last + 1, WHEEL_PERIOD_NS, dtype=np.int64)


def simulate_wheel_odometry(stamps: NDArray[np.int64], seed: int = WHEEL_NOISE_SEED) -> WheelOdometry:
    """Dead-reckoned wheel odometry at ``stamps`` (K,) from the true robot motion, with the error model of
    bags/README.md: for each step the true distance and heading change of the base are turned into a
    measured speed ``v = (1 + WHEEL_SCALE_ERROR) v_true (1 + n_v)`` and yaw rate ``w = w_true + bias + n_w``
    (``v_true``, ``w_true`` the step's mean true values, ``n_v``, ``n_w`` Gaussian), and the pose is
    integrated with the unicycle model at the step's mid heading. The first message is the odom origin;
    every message carries the speed and yaw rate measured over the 20 ms before its stamp."""
    rng = np.random.default_rng(seed)
    times = (stamps - START_NS).astype(np.float64) / NS_PER_S
    edges = np.concatenate([[times[0] - (times[1] - times[0])], times])  # step k ends at stamp k
    dt = np.diff(edges)
    distance = np.array([_integrate(robot_speed, a, b) for a, b in itertools.pairwise(edges)])
    turn = np.diff(robot_yaw(edges))
    v_true, w_true = distance / dt, turn / dt
    n_v = rng.normal(0.0, WHEEL_SPEED_NOISE, len(dt))
    n_w = rng.normal(0.0, WHEEL_YAW_RATE_NOISE_RAD_S, len(dt))
    v = (1.0 + WHEEL_SCALE_ERROR) * v_true * (1.0 + n_v)
    w = w_true + WHEEL_YAW_RATE_BIAS_RAD_S + n_w
    pose = np.zeros((len(stamps), 3))
    for k in range(1, len(stamps)):
        x, y, yaw = pose[k - 1]
        mid = yaw + 0.5 * w[k] * dt[k]
        pose[k] = (x + v[k] * dt[k] * math.cos(mid), y + v[k] * dt[k] * math.sin(mid), yaw + w[k] * dt[k])
    travelled = np.concatenate([[0.0], np.cumsum(np.abs(v[1:]) * dt[1:])])
    elapsed = times - times[0]
    pose_var = np.zeros((len(stamps), 6))
    pose_var[:, 0] = pose_var[:, 1] = 0.01**2 + (0.03 * travelled) ** 2  # 1 cm + 3 % of the distance
    pose_var[:, 2:5] = 1e-6  # z, roll, pitch: the robot stays on the flat floor
    pose_var[:, 5] = 0.01**2 + (0.01 * elapsed) ** 2  # 0.6 deg + 0.6 deg/s of unknown yaw-rate bias
    twist_var = np.zeros((len(stamps), 6))
    twist_var[:, 0] = (0.005 + WHEEL_SPEED_NOISE * np.abs(v)) ** 2
    twist_var[:, 1:5] = 1e-6  # no sideways, vertical or tilting motion (non-holonomic, planar)
    twist_var[:, 5] = WHEEL_YAW_RATE_NOISE_RAD_S**2 + WHEEL_YAW_RATE_BIAS_RAD_S**2
    diagonal = np.arange(6) * 7  # indices of the diagonal in a row-major 6x6
    pose_cov, twist_cov = np.zeros((len(stamps), 36)), np.zeros((len(stamps), 36))
    pose_cov[:, diagonal], twist_cov[:, diagonal] = pose_var, twist_var
    return WheelOdometry(stamps.copy(), pose, np.column_stack([v, w]), pose_cov, twist_cov)


def ground_robot_scene() -> tuple[Quad, ...]:
    """A walled yard 15 m x 24 m paved with photographic slabs (0.5 m, ``paving``), brick and grass walls
    6 m high with posters, and boxes and pillars 2-4 m beside the path and ahead of it."""
    floor_y = ROBOT_FLOOR_Y_M
    x_left, x_right, z_back, z_front = -8.5, 6.5, -4.0, 20.0  # world x is right (-plane y), z is forward
    wall_h = 6.0
    wall_cy = floor_y - 0.5 * wall_h
    x_mid, x_len = 0.5 * (x_left + x_right), x_right - x_left
    z_mid, z_len = 0.5 * (z_back + z_front), z_front - z_back
    quads: list[Quad] = [
        # the floor reaches 0.1 m under the walls, so no ray can pass between them
        horizontal_quad(floor_y, (x_left - 0.1, x_right + 0.1), (z_back - 0.1, z_front + 0.1), PAVING_TEXTURE, 6.0),
        wall_quad((x_mid, wall_cy, z_front), (0, 0, -1), x_len + 0.2, wall_h, "brick", tile_m=2, gain=0.7, offset=30.0),
        wall_quad((x_mid, wall_cy, z_back), (0, 0, 1), x_len + 0.2, wall_h, "brick", tile_m=2.0, gain=0.8),
        wall_quad((x_left, wall_cy, z_mid), (1, 0, 0), z_len + 0.2, wall_h, "brick", tile_m=2.5, gain=0.7, offset=20.0),
        wall_quad((x_right, wall_cy, z_mid), (-1, 0, 0), z_len + 0.2, wall_h, "grass", tile_m=3.0, gain=1.1),
        # posters 5 cm in front of the walls
        wall_quad((-3.0, floor_y - 2.2, z_front - 0.05), (0, 0, -1), 3.0, None, "rocket"),
        wall_quad((2.5, floor_y - 1.8, z_front - 0.05), (0, 0, -1), 3.0, None, "astronaut"),
        wall_quad((x_left + 0.05, floor_y - 1.6, 5.0), (1, 0, 0), 2.5, None, "chelsea"),
        wall_quad((x_left + 0.05, floor_y - 2.0, 12.0), (1, 0, 0), 3.0, None, "camera"),
        wall_quad((x_right - 0.05, floor_y - 1.7, 9.0), (-1, 0, 0), 2.5, None, "coffee"),
    ]
    boxes = (  # world x, world z, size x, size z, height, texture, gain
        (2.4, 3.5, 0.8, 0.8, 0.7, "coffee", 1.0),
        (-4.2, 6.0, 0.3, 0.3, 2.5, "brick", 0.9),
        (2.3, 7.5, 1.0, 0.8, 1.0, "coins", 1.2),
        (1.0, 11.0, 0.3, 0.3, 2.5, "gravel", 1.1),
        (-4.8, 13.0, 1.2, 1.2, 1.2, "chelsea", 1.0),
        (1.0, 13.2, 0.6, 0.6, 0.8, "hubble_deep_field", 1.3),
        (-3.6, 15.5, 0.4, 0.4, 3.0, "grass", 1.0),
    )
    for x, z, sx, sz, height, texture, gain in boxes:
        quads += box_quads(x, z, sx, sz, height, texture, gain, ground_y_m=floor_y)
    return tuple(quads)


def ground_robot_spec(n_frames: int = ROBOT_FRAMES) -> BagSpec:
    """A differential-drive robot's forward camera (0.45 m high, pitched 15 deg down) crossing a paved yard
    at 0.42-0.65 m/s with smooth left and right turns (up to 25 deg/s), with 50 Hz wheel odometry."""
    times = np.array([(stamp_ns(i) - START_NS) / NS_PER_S for i in range(n_frames)])
    T_w_c = robot_camera_poses(robot_base_poses(times))
    return BagSpec(
        "ground_robot",
        ground_robot_scene(),
        make_camera(),
        T_w_c,
        noise_seed=4,
        min_clearance_m=ROBOT_MIN_CLEARANCE_M,
        jpeg_quality=ROBOT_JPEG_QUALITY,
        wheel_odom=simulate_wheel_odometry(wheel_stamps_ns(n_frames)),
        floor_y_m=ROBOT_FLOOR_Y_M,
    )


# --- independently moving objects: "a moving object never moves the camera" ----------------------------

MOVER_TEXTURE = "immunohistochemistry"  # stained tissue: blobs and corners everywhere, unlike any background
STATIC_MOVER_FRAMES = 120  # 8 s at 15 Hz
STATIC_MOVER_CAMERA_XYZ = (0.3, -0.1, -2.0)  # level, looking along +z: the written rotation is exactly identity
PANEL_SIZE_M = (3.0, 0.12, 2.4)  # width (x), thickness (z), height of the panel (standing on the ground)
STATIC_MOVER_JPEG_QUALITY = 85  # 120 detailed frames at quality 90 would make a 9.5 MB bag; at 85 it stays under 8 MB
MOVING_MOVER_FRAMES = 105  # 7 s at 15 Hz
MOVING_MOVER_JPEG_QUALITY = 85  # at quality 90 the bag would be 8.6 MB; at 85 it is 7.0 MB
MOVING_MOVER_CAMERA_HEIGHT_M = 1.55  # above the ground: a camera carried at eye height
MOVING_MOVER_CAMERA_PITCH_DEG = -8.0  # looking a little down, at the ground ahead (rot_x: positive tilts up)
CART_SIZE_M = (1.3, 2.6, 2.0)  # width (x), length (z, its direction of travel), height
CART_CROSSING_M = 7.6  # sideways travel of the cart over the sequence (world x, from -3.8 m to +3.8 m)
CART_SLOWDOWN_M = 0.4  # amplitude of the sine that slows the cart while it is in front of the camera
CART_DEPTH_M = (4.1, 3.7)  # cart centre ahead of the camera's path (world z) at the first and the last frame


def ground_box_mover(name: str, size_m: tuple[float, float, float], T_w_o: NDArray[np.float64], texture: str) -> Mover:
    """A box standing on the ground that moves rigidly: in its own frame (x right, y down, z forward) the
    footprint ``size_m[0]`` x ``size_m[1]`` is centred on the origin and the box rises ``size_m[2]`` above
    y = 0; ``T_w_o`` (N, 4, 4) places it in the world at each frame."""
    size_x, size_z, height = size_m
    quads = box_quads(0.0, 0.0, size_x, size_z, height, texture, ground_y_m=0.0)
    return Mover(name, tuple(quads), T_w_o)


def ground_poses(
    n_frames: int, xz: Callable[[float], tuple[float, float]], yaw: Callable[[float], float]
) -> NDArray[np.float64]:
    """Poses (N, 4, 4) of an object on the courtyard ground: position (x, z) and heading ``yaw`` (rad, about
    the vertical, positive turns right as for the camera), sampled at s = i / (N - 1)."""
    poses = []
    for i in range(n_frames):
        s = i / (n_frames - 1)
        x, z = xz(s)
        poses.append(se3(rot_y(yaw(s)), (x, GROUND_Y_M, z)))
    return np.stack(poses)


def static_mover_spec(n_frames: int = STATIC_MOVER_FRAMES) -> BagSpec:
    """Courtyard seen by a camera that never moves (every pose exactly the same, rotation exactly identity),
    while a large textured panel (3.0 m x 2.4 m, 12 cm thick, standing on the ground) sweeps across the view
    from left to right at 0.6 m/s, 3.4-3.9 m in front of the camera, coming a little nearer and turning by
    14 deg: it covers 21-45 % of the image (at least 25 % on 88 % of the frames), so a pipeline that trusts
    the majority of its tracks may think the camera moves."""
    deg = math.pi / 180.0
    cx, _, cz = STATIC_MOVER_CAMERA_XYZ

    def xz(s: float) -> tuple[float, float]:
        return cx - 2.4 + 4.8 * s, cz + 3.9 - 0.5 * s + 0.15 * math.sin(math.pi * s)

    def yaw(s: float) -> float:
        return -8.0 * deg + 14.0 * deg * s

    T_w_c = np.stack([se3(np.eye(3), STATIC_MOVER_CAMERA_XYZ)] * n_frames)
    panel = ground_box_mover("panel", PANEL_SIZE_M, ground_poses(n_frames, xz, yaw), MOVER_TEXTURE)
    return BagSpec(
        "static_mover",
        courtyard_scene(),
        make_camera(),
        T_w_c,
        noise_seed=6,
        jpeg_quality=STATIC_MOVER_JPEG_QUALITY,
        movers=(panel,),
    )


def moving_mover_scene() -> tuple[Quad, ...]:
    """The courtyard without its nearest box (1 m at x 2.0 m, z 3.1 m), which stands on the cart's path."""
    lo, hi = np.array([1.5, 2.6]) - 1e-9, np.array([2.5, 3.6]) + 1e-9  # its footprint (world x, z)

    def on_box(quad: Quad) -> bool:
        origin, eu, ev = (np.asarray(v) for v in (quad.origin_w, quad.edge_u_w, quad.edge_v_w))
        corners = np.array([origin, origin + eu, origin + ev, origin + eu + ev])[:, [0, 2]]
        return bool(np.all((corners >= lo) & (corners <= hi)))

    return tuple(q for q in courtyard_scene() if not on_box(q))


def moving_mover_spec(n_frames: int = MOVING_MOVER_FRAMES) -> BagSpec:
    """Courtyard (without the box on the cart's path), a camera carried at eye height (1.55 m, looking 8 deg
    down) at walking pace (1 m/s, 7.2 m along a gentle S curve, yaw within 5 deg) and a tall cart (1.3 m x
    2.6 m, 2.0 m high) that drives ahead of the camera, 3.9-4.3 m in front of it, and crosses its path
    from left to right: 1.5 m/s sideways at the ends, slowing to 0.7 m/s while in front of the camera, and
    0.95 m/s forward, always heading where it goes. It is in view on every frame and fills 30-36 % of the
    image while wholly in view."""
    deg = math.pi / 180.0
    cam_x, cam_y, cam_z0, cam_dz = 0.4, GROUND_Y_M - MOVING_MOVER_CAMERA_HEIGHT_M, -6.3, 7.0

    def position(s: float) -> tuple[float, float, float]:
        return cam_x * math.sin(2 * math.pi * s), cam_y - 0.05 * math.sin(math.pi * s), cam_z0 + cam_dz * s

    def angles(s: float) -> tuple[float, float, float]:
        yaw = -4.0 * deg * math.sin(2 * math.pi * s) + 1.0 * deg * math.sin(math.pi * s)
        pitch = MOVING_MOVER_CAMERA_PITCH_DEG * deg + 1.0 * deg * math.sin(3 * math.pi * s)
        roll = 1.0 * deg * math.sin(math.pi * s + 0.3)
        return yaw, pitch, roll

    # The cart in the world: sideways x(s) = -a/2 + a s - b sin(2 pi (s - 1/2)) (slowest at s = 1/2), and
    # forward z(s) = z0 + dz s; it heads along its velocity (dx/ds, dz/ds).
    a, b = CART_CROSSING_M, CART_SLOWDOWN_M
    z0, dz = cam_z0 + CART_DEPTH_M[0], cam_dz + CART_DEPTH_M[1] - CART_DEPTH_M[0]

    def xz(s: float) -> tuple[float, float]:
        return -0.5 * a + a * s - b * math.sin(2 * math.pi * (s - 0.5)), z0 + dz * s

    def yaw(s: float) -> float:
        return math.atan2(a - 2 * math.pi * b * math.cos(2 * math.pi * (s - 0.5)), dz)

    cart = ground_box_mover("cart", CART_SIZE_M, ground_poses(n_frames, xz, yaw), MOVER_TEXTURE)
    return BagSpec(
        "moving_mover",
        moving_mover_scene(),
        make_camera(),
        smooth_trajectory(n_frames, position, angles),
        noise_seed=7,
        jpeg_quality=MOVING_MOVER_JPEG_QUALITY,
        movers=(cart,),
    )


SPECS: dict[str, Callable[[], BagSpec]] = {
    "general_motion": general_motion_spec,
    "pure_rotation": pure_rotation_spec,
    "planar": planar_spec,
    "ground_robot": ground_robot_spec,
    "static_mover": static_mover_spec,
    "moving_mover": moving_mover_spec,
}


def quad_distance(quad: Quad, point_w: NDArray[np.float64]) -> float:
    """Euclidean distance (m) from ``point_w`` (3,) to the nearest point of the rectangle."""
    origin, eu, ev = (np.asarray(v) for v in (quad.origin_w, quad.edge_u_w, quad.edge_v_w))
    rel = point_w - origin
    a = float(np.clip(rel @ eu / (eu @ eu), 0.0, 1.0))
    b = float(np.clip(rel @ ev / (ev @ ev), 0.0, 1.0))
    return float(np.linalg.norm(rel - a * eu - b * ev))


def min_clearance_m(quads: Sequence[Quad], T_w_c: NDArray[np.float64]) -> float:
    """Smallest distance between any camera centre of ``T_w_c`` (N, 4, 4) and any quad."""
    return min(quad_distance(q, T[:3, 3]) for T in T_w_c for q in quads)


def mover_clearance_m(spec: BagSpec) -> float:
    """Smallest distance between the camera centre of each frame and the movers' quads at that frame
    (inf without movers)."""
    return min(
        (quad_distance(q, T[:3, 3]) for i, T in enumerate(spec.T_w_c) for q in spec.moving_quads_at(i)),
        default=math.inf,
    )


def mover_stats(mover_coverage: FloatImage) -> tuple[float, tuple[int, int, int, int]]:
    """Share of the image's pixels that see a mover (sub-pixel exact) and the inclusive bounding box
    ``(x0, y0, x1, y1)`` of the pixels at least half on a mover (all -1 when there are none)."""
    fraction = float(mover_coverage.mean())
    rows = np.flatnonzero((mover_coverage >= 0.5).any(axis=1))
    cols = np.flatnonzero((mover_coverage >= 0.5).any(axis=0))
    if rows.size == 0:
        return fraction, (-1, -1, -1, -1)
    return fraction, (int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1]))


def mover_coverage_lines(stats: Sequence[tuple[float, tuple[int, int, int, int]]]) -> list[str]:
    """Lines of ``mover_coverage.txt``: a ``#`` header, then ``frame fraction x0 y0 x1 y1`` per frame."""
    lines = [
        "# frame fraction x0 y0 x1 y1: share of the image's pixels that see a mover (0-1, supersampled), and the "
        "inclusive bounding box (pixels, x right, y down) of the pixels at least half on a mover; -1 -1 -1 -1 "
        "when none"
    ]
    for i, (fraction, (x0, y0, x1, y1)) in enumerate(stats):
        lines.append(f"{i} {fraction:.6f} {x0} {y0} {x1} {y1}")
    return lines


def mover_tum_lines(mover: Mover, T_w_c0: Matrix4) -> list[str]:
    """TUM lines of a mover's pose in the ground truth's ``world`` (the optical frame of frame 0)."""
    lines = [
        f"# timestamp tx ty tz qx qy qz qw: pose of the mover {mover.name!r} (its own frame: origin at the "
        "centre of its footprint on the ground, x right, y down, z forward at rest) in the optical frame of "
        "camera frame 0 (the ground truth's world), metres; stamps equal the bag image stamps"
    ]
    T_c0_w = invert_se3(T_w_c0)
    for i, T_w_o in enumerate(mover.T_w_o):
        T = T_c0_w @ T_w_o
        q = quat_xyzw_from_rotation(T[:3, :3])
        values = " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q))
        lines.append(f"{format_stamp(stamp_ns(i))} {values}")
    return lines


# --- renderer -------------------------------------------------------------------------------------------


def distort_normalized(
    xn: NDArray[np.float64], yn: NDArray[np.float64], D: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """plumb_bob forward model on normalized coordinates (the model cv2.projectPoints applies)."""
    k1, k2, p1, p2, k3 = D
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return xd, yd


def pixel_rays(camera: CameraModel, supersample: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Normalized ray coordinates (x/z, y/z), each (H*s, W*s), of the supersampled pixel centres.

    Sub-pixel j of pixel u sits at u + (j + 0.5) / s - 0.5. For a distorted camera the coordinates
    are undistorted: ``cv2.undistortPoints`` gives the start, fixed-point iterations of the plumb_bob
    model polish it to below 1e-10 (5e-8 px) so the rendered image is the exact distorted image of the scene.
    """
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    us = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
    vs = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
    u_grid, v_grid = np.meshgrid(us, vs)
    K = camera.K
    if not camera.is_distorted:
        return (u_grid - K[0, 2]) / K[0, 0], (v_grid - K[1, 2]) / K[1, 1]
    pixels = np.stack([u_grid.ravel(), v_grid.ravel()], axis=1).reshape(-1, 1, 2)
    xn_start = cv2.undistortPoints(pixels, K, camera.D).reshape(-1, 2)
    xd_target = (u_grid.ravel() - K[0, 2]) / K[0, 0]
    yd_target = (v_grid.ravel() - K[1, 2]) / K[1, 1]
    xn, yn = xn_start[:, 0].astype(np.float64), xn_start[:, 1].astype(np.float64)
    for _ in range(50):
        xd, yd = distort_normalized(xn, yn, camera.D)
        xn, yn = xn + (xd_target - xd), yn + (yd_target - yd)
    xd, yd = distort_normalized(xn, yn, camera.D)
    residual = max(float(np.abs(xd - xd_target).max()), float(np.abs(yd - yd_target).max()))
    if residual > 1e-10:
        msg = f"undistortion did not converge (normalized residual {residual:.2e}); distortion too strong"
        raise SceneError(msg)
    return xn.reshape(u_grid.shape), yn.reshape(u_grid.shape)


def _clip_near(corners_c: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sutherland-Hodgman clip of a polygon (M, 3) in the camera frame to z >= NEAR_M."""
    out = []
    m = len(corners_c)
    for i in range(m):
        a, b = corners_c[i], corners_c[(i + 1) % m]
        a_in, b_in = a[2] >= NEAR_M, b[2] >= NEAR_M
        if a_in:
            out.append(a)
        if a_in != b_in:
            out.append(a + (NEAR_M - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(out).reshape(-1, 3)


def _sample_trilinear(
    pyramid: Sequence[FloatImage], fu: FloatImage, fv: FloatImage, level: FloatImage, inside: NDArray[np.bool_]
) -> FloatImage:
    """Sample a mipmap pyramid at fractional texture coordinates ``fu``, ``fv`` in [0, 1] with per-pixel
    level of detail ``level`` (0 = full resolution), blending the two nearest levels."""
    level = np.clip(level, 0.0, len(pyramid) - 1.0)
    lo = int(np.floor(level[inside].min()))
    hi = min(int(np.ceil(level[inside].max())), len(pyramid) - 1)
    result = np.zeros(fu.shape, np.float32)
    # Pixel coordinates of level 0 (pixel centres at integers). ``cv2.pyrDown`` centres pixel i of a level
    # on pixel 2i of the level below, so level k's coordinate is x0 / 2^k. (Until 2026-11-25 each level was
    # addressed as fu * its width - 0.5, which puts level 1 half a level-0 texel off level 0, level 2 1.5
    # texels: a texture slid over its surface as the level of detail changed with distance, a systematic
    # image motion on a floor approached by the camera; ground_robot's pipeline yaw drifted 0.96 deg in
    # 300 frames from it, -0.007 deg per keyframe.)
    h0, w0 = pyramid[0].shape
    x0 = fu * w0 - 0.5
    y0 = fv * h0 - 0.5
    for index in range(lo, hi + 1):
        weight = np.clip(1.0 - np.abs(level - index), 0.0, 1.0).astype(np.float32)
        map_x = (x0 / 2.0**index).astype(np.float32)
        map_y = (y0 / 2.0**index).astype(np.float32)
        result += weight * cv2.remap(pyramid[index], map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return result


def _mirror_fold(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fold a coordinate in texture repeats onto [0, 1], mirroring every other tile (seamless tiling)."""
    m = np.mod(x, 2.0)
    return np.where(m > 1.0, 2.0 - m, m)


def sensor_image(ideal: FloatImage, noise_rng: np.random.Generator | None) -> NDArray[np.uint8]:
    """Quantize an ideal image (H, W) to uint8, first adding Gaussian noise of ``NOISE_SIGMA`` gray levels
    drawn from ``noise_rng`` (if given)."""
    image = ideal
    if noise_rng is not None:
        image = ideal + noise_rng.normal(0.0, NOISE_SIGMA, ideal.shape).astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class RenderResult:
    """A noise-free rendering: ``image`` (H, W) float32 gray levels after the optics, ``coverage`` (H, W) fraction of
    sub-pixels that hit a quad, ``depth`` (H, W) mean z in the camera frame of the covered sub-pixels, and
    (when moving quads were given) ``mover_coverage`` (H, W) fraction of sub-pixels whose visible surface
    is a moving quad."""

    image: FloatImage
    coverage: FloatImage
    depth: FloatImage
    mover_coverage: FloatImage | None = None


@dataclass(frozen=True)
class RowBand:
    """Output rows ``first_row`` up to (not including) ``stop_row`` seen from ``T_w_c`` (4, 4), with the
    movers' quads ``moving_quads`` placed for that instant. A rolling-shutter sensor reads its rows out one
    after the other while the camera moves: each band of rows is rendered at its own pose."""

    first_row: int
    stop_row: int
    T_w_c: Matrix4
    moving_quads: tuple[Quad, ...] = ()


class Renderer:
    """Ray-casting renderer of a fixed scene for a fixed camera; ``render(T_w_c)`` gives the uint8 image."""

    def __init__(self, quads: Sequence[Quad], camera: CameraModel, supersample: int = SUPERSAMPLE) -> None:
        self.quads = tuple(quads)
        self.camera = camera
        self.supersample = supersample
        self._xn, self._yn = pixel_rays(camera, supersample)

    def render_ideal(self, T_w_c: Matrix4, moving_quads: Sequence[Quad] = ()) -> RenderResult:
        """Noise-free image of the scene seen from ``T_w_c`` (4, 4), with coverage and depth.

        ``moving_quads`` (already placed in the world for this frame, ``BagSpec.moving_quads_at``) are
        z-buffered against the static scene; the result then also holds their per-pixel coverage.
        """
        return self.render_bands((RowBand(0, self.camera.height, T_w_c, tuple(moving_quads)),))

    def render_bands(self, bands: Sequence[RowBand]) -> RenderResult:
        """Noise-free image whose row bands are each seen from their own pose (a rolling shutter), with
        coverage and depth; the bands should cover every row once (rows no band covers see nothing). The
        optics' blur is applied to the whole image after the bands are put together."""
        shape = self._xn.shape
        zbuf = np.full(shape, np.inf)
        image = np.zeros(shape, np.float32)
        on_mover = np.zeros(shape, bool) if any(band.moving_quads for band in bands) else None
        s = self.supersample
        for band in bands:
            rows = slice(band.first_row * s, band.stop_row * s)
            T_c_w = invert_se3(np.asarray(band.T_w_c, dtype=np.float64))
            R_c_w, t_c_w = T_c_w[:3, :3], T_c_w[:3, 3]
            target = _Target(zbuf[rows], image[rows], None if on_mover is None else on_mover[rows],
                             self._xn[rows], self._yn[rows])
            for quad in self.quads:
                self._draw_quad(quad, R_c_w, t_c_w, target, False)
            for quad in band.moving_quads:
                self._draw_quad(quad, R_c_w, t_c_w, target, True)
        covered = np.isfinite(zbuf)
        size = (self.camera.width, self.camera.height)
        mover_coverage = None
        if on_mover is not None:
            mover_coverage = cv2.resize(on_mover.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        coverage = cv2.resize(covered.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        depth_sum = cv2.resize(np.where(covered, zbuf, 0.0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
        depth = np.where(coverage > 0, depth_sum / np.maximum(coverage, 1.0 / (s * s)), np.inf).astype(np.float32)
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        blurred = cv2.GaussianBlur(small, (0, 0), LENS_BLUR_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
        return RenderResult(blurred, coverage, depth, mover_coverage)

    def render(self, T_w_c: Matrix4, noise_rng: np.random.Generator | None = None) -> NDArray[np.uint8]:
        """uint8 image from ``T_w_c`` (4, 4); sensor noise when a generator is given, none otherwise."""
        return sensor_image(self.render_ideal(T_w_c).image, noise_rng)

    def _draw_quad(self, quad: Quad, R_c_w: NDArray[np.float64], t_c_w: NDArray[np.float64], target: _Target,
                   is_mover: bool = False) -> None:
        """Ray-cast one quad into the supersampled rows of ``target`` where it is nearer than their z-buffer
        (image and z-buffer updated); where it is drawn, the mover mask (if any) records whether the quad is
        a moving one."""
        origin_c = R_c_w @ np.asarray(quad.origin_w) + t_c_w
        eu_c = R_c_w @ np.asarray(quad.edge_u_w)
        ev_c = R_c_w @ np.asarray(quad.edge_v_w)
        corners_c = np.array([origin_c, origin_c + eu_c, origin_c + eu_c + ev_c, origin_c + ev_c])
        polygon_c = _clip_near(corners_c)
        if len(polygon_c) < 3:
            return  # entirely behind the near plane
        # Rays can only hit the quad inside the bounding box of its (near-clipped) projection.
        x_proj, y_proj = polygon_c[:, 0] / polygon_c[:, 2], polygon_c[:, 1] / polygon_c[:, 2]
        in_box = (
            (target.xn >= x_proj.min())
            & (target.xn <= x_proj.max())
            & (target.yn >= y_proj.min())
            & (target.yn <= y_proj.max())
        )
        rows, cols = np.flatnonzero(in_box.any(axis=1)), np.flatnonzero(in_box.any(axis=0))
        if rows.size == 0 or cols.size == 0:
            return
        window = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        xn, yn = target.xn[window], target.yn[window]

        # Plane n . X = d in the camera frame; the ray X = z (xn, yn, 1) meets it at z = d / (n . ray).
        normal_c = np.cross(eu_c, ev_c)
        plane_d = float(normal_c @ origin_c)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = plane_d / (normal_c[0] * xn + normal_c[1] * yn + normal_c[2])
            # Rectangle coordinates of the hit: a = (X - origin) . eu / |eu|^2, likewise b along ev.
            a = (z * (eu_c[0] * xn + eu_c[1] * yn + eu_c[2]) - eu_c @ origin_c) / (eu_c @ eu_c)
            b = (z * (ev_c[0] * xn + ev_c[1] * yn + ev_c[2]) - ev_c @ origin_c) / (ev_c @ ev_c)
        zbuf_window = target.zbuf[window]
        visible = (z > NEAR_M) & (z < zbuf_window) & (a >= 0.0) & (a <= 1.0) & (b >= 0.0) & (b <= 1.0)
        if not visible.any():
            return

        # Texture coordinates in repeats (unfolded) drive the level of detail: texels per sub-pixel.
        tex_h, tex_w = load_texture(quad.texture).shape
        u_rep, v_rep = a * quad.repeat_u, b * quad.repeat_v
        safe_u, safe_v = np.where(visible, u_rep, 0.0), np.where(visible, v_rep, 0.0)
        dux, duy = (np.abs(g) * tex_w for g in _gradients(safe_u, visible))
        dvx, dvy = (np.abs(g) * tex_h for g in _gradients(safe_v, visible))
        footprint = np.maximum(np.hypot(dux, dvx), np.hypot(duy, dvy))
        level = np.log2(np.maximum(footprint, 1.0)).astype(np.float32)
        fu = _mirror_fold(safe_u).astype(np.float32)
        fv = _mirror_fold(safe_v).astype(np.float32)
        sample = _sample_trilinear(texture_pyramid(quad.texture), fu, fv, level, visible)
        shaded = quad.gain * sample + quad.offset
        image_window = target.image[window]
        image_window[visible] = shaded[visible]
        zbuf_window[visible] = z[visible]
        if target.on_mover is not None:
            target.on_mover[window][visible] = is_mover


@dataclass(frozen=True)
class _Target:
    """Views of the supersampled rows one pose draws into: z-buffer, image, mover mask (None without
    movers) and the rays' normalized coordinates of those rows."""

    zbuf: NDArray[np.float64]
    image: FloatImage
    on_mover: NDArray[np.bool_] | None
    xn: NDArray[np.float64]
    yn: NDArray[np.float64]


def _gradients(
    values: NDArray[np.float64], valid: NDArray[np.bool_]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-pixel derivatives along x and y of a field defined where ``valid``; one-sided at the edges
    of the valid region so a silhouette does not inflate the footprint."""
    gx = np.zeros_like(values)
    gy = np.zeros_like(values)
    if values.shape[1] > 1:
        dx = np.diff(values, axis=1)
        ok = valid[:, 1:] & valid[:, :-1]
        dx = np.where(ok, dx, np.nan)
        fwd = np.concatenate([dx, np.full((values.shape[0], 1), np.nan)], axis=1)
        bwd = np.concatenate([np.full((values.shape[0], 1), np.nan), dx], axis=1)
        gx = np.where(np.isnan(fwd), np.nan_to_num(bwd), fwd)
    if values.shape[0] > 1:
        dy = np.diff(values, axis=0)
        ok = valid[1:, :] & valid[:-1, :]
        dy = np.where(ok, dy, np.nan)
        fwd = np.concatenate([dy, np.full((1, values.shape[1]), np.nan)], axis=0)
        bwd = np.concatenate([np.full((1, values.shape[1]), np.nan), dy], axis=0)
        gy = np.where(np.isnan(fwd), np.nan_to_num(bwd), fwd)
    return gx, gy


# --- bag writing ----------------------------------------------------------------------------------------

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
IMAGE_MSGTYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_MSGTYPE = "sensor_msgs/msg/CameraInfo"
POSE_MSGTYPE = "geometry_msgs/msg/PoseStamped"
ODOMETRY_MSGTYPE = "nav_msgs/msg/Odometry"


def _header(stamp: int, frame_id: str) -> object:
    types = TYPESTORE.types
    time_msg = types["builtin_interfaces/msg/Time"](sec=stamp // NS_PER_S, nanosec=stamp % NS_PER_S)
    return types["std_msgs/msg/Header"](stamp=time_msg, frame_id=frame_id)


def camera_info_msg(camera: CameraModel, stamp: int) -> object:
    """sensor_msgs/CameraInfo: plumb_bob, R = identity, P = [K | 0], no binning, empty ROI."""
    types = TYPESTORE.types
    P = np.hstack([camera.K, np.zeros((3, 1))])
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types[CAMERA_INFO_MSGTYPE](
        header=_header(stamp, CAMERA_FRAME_ID),
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        d=camera.D.astype(np.float64).copy(),
        k=camera.K.ravel().astype(np.float64),
        r=np.eye(3).ravel(),
        p=P.ravel(),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def compressed_image_msg(image: NDArray[np.uint8], stamp: int, quality: int = JPEG_QUALITY) -> object:
    """sensor_msgs/CompressedImage with a mono JPEG of the given quality."""
    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        msg = "cv2.imencode failed to encode a JPEG frame"
        raise SceneError(msg)
    return TYPESTORE.types[IMAGE_MSGTYPE](
        header=_header(stamp, CAMERA_FRAME_ID), format="jpeg", data=np.asarray(encoded, dtype=np.uint8).ravel()
    )


def pose_msg(T_c0_ci: Matrix4, stamp: int) -> object:
    """geometry_msgs/PoseStamped in frame ``world`` (= optical frame of frame 0)."""
    types = TYPESTORE.types
    qx, qy, qz, qw = quat_xyzw_from_rotation(T_c0_ci[:3, :3])
    tx, ty, tz = T_c0_ci[:3, 3]
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(tx), y=float(ty), z=float(tz)),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(qw)),
    )
    return types[POSE_MSGTYPE](header=_header(stamp, WORLD_FRAME_ID), pose=pose)


def odometry_msg(wheel: WheelOdometry, k: int) -> object:
    """nav_msgs/Odometry of wheel message ``k``: base_link in odom, twist in base_link, with covariances."""
    types = TYPESTORE.types
    x, y, yaw = (float(v) for v in wheel.pose[k])
    qx, qy, qz, qw = quat_xyzw_from_rotation(rot_z(yaw))
    v, w = (float(value) for value in wheel.twist[k])
    Vector3 = types["geometry_msgs/msg/Vector3"]
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(qw)),
    )
    twist = types["geometry_msgs/msg/Twist"](linear=Vector3(x=v, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=w))
    return types[ODOMETRY_MSGTYPE](
        header=_header(int(wheel.stamps_ns[k]), ODOM_FRAME_ID),
        child_frame_id=BASE_FRAME_ID,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose, covariance=wheel.pose_covariance[k].astype(np.float64).copy()
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist, covariance=wheel.twist_covariance[k].astype(np.float64).copy()
        ),
    )


def wheel_tum_lines(wheel: WheelOdometry) -> list[str]:
    """TUM lines of the wheel odometry: base_link in odom at every ``/wheel/odom`` stamp."""
    lines = [
        "# timestamp tx ty tz qx qy qz qw: wheel odometry, base_link (x forward, y left, z up) pose in odom, "
        "metres; odom is base_link at the first message; stamps equal the /wheel/odom header stamps"
    ]
    for stamp, (x, y, yaw) in zip(wheel.stamps_ns, wheel.pose, strict=True):
        q = quat_xyzw_from_rotation(rot_z(float(yaw)))
        values = " ".join(f"{v:.9f}" for v in (x, y, 0.0, *q))
        lines.append(f"{format_stamp(int(stamp))} {values}")
    return lines


def floor_depth(camera: CameraModel, T_w_c: Matrix4, floor_y_m: float) -> NDArray[np.float64]:
    """Per pixel (H, W), the camera-frame z at which the pixel's ray meets the floor ``y = floor_y_m``
    (world, y down); inf where the ray does not reach it in front of the camera."""
    xn, yn = pixel_rays(camera, 1)
    R, c = T_w_c[:3, :3], T_w_c[:3, 3]
    down = R[1, 0] * xn + R[1, 1] * yn + R[1, 2]  # world y component of the ray (x, y, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (floor_y_m - c[1]) / down
    return np.where((down > 0.0) & (z > NEAR_M), z, np.inf)


def floor_fraction(result: RenderResult, camera: CameraModel, T_w_c: Matrix4, floor_y_m: float) -> float:
    """Share of the pixels of a rendering whose depth is that of the floor (within 1 %)."""
    z_floor = floor_depth(camera, T_w_c, floor_y_m)
    on_floor = np.isfinite(z_floor) & (np.abs(result.depth - z_floor) <= 0.01 * z_floor)
    return float(on_floor.mean())


def max_floor_flow_px(camera: CameraModel, T_w_c: NDArray[np.float64], floor_y_m: float, step_px: int = 4) -> float:
    """Largest image motion (px) from one frame to the next of the floor points under a grid of pixels
    (every ``step_px``, and the last row and column), occlusion ignored. Pinhole cameras only."""
    rows = np.unique(np.append(np.arange(0, camera.height, step_px), camera.height - 1))
    cols = np.unique(np.append(np.arange(0, camera.width, step_px), camera.width - 1))
    largest = 0.0
    for T_a, T_b in itertools.pairwise(T_w_c):
        z = floor_depth(camera, T_a, floor_y_m)[np.ix_(rows, cols)]
        u, v = np.meshgrid(cols.astype(np.float64), rows.astype(np.float64))
        keep = np.isfinite(z)
        K = camera.K
        X_a = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)[keep]
        T_b_a = invert_se3(T_b) @ T_a
        X_b = X_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
        u_b = K[0, 0] * X_b[:, 0] / X_b[:, 2] + K[0, 2]
        v_b = K[1, 1] * X_b[:, 1] / X_b[:, 2] + K[1, 2]
        largest = max(largest, float(np.hypot(u_b - u[keep], v_b - v[keep]).max()))
    return largest


def format_stamp(stamp: int) -> str:
    return f"{stamp // NS_PER_S}.{stamp % NS_PER_S:09d}"


def tum_lines(T_c0_ci: NDArray[np.float64]) -> list[str]:
    """TUM ground truth lines for ``T_c0_ci`` (N, 4, 4), with the convention as a leading comment."""
    lines = [
        "# timestamp tx ty tz qx qy qz qw: camera optical frame (x right, y down, z forward) pose relative to "
        "frame 0 (T_c0_ci), metres; stamps equal the bag image stamps"
    ]
    for i, T in enumerate(T_c0_ci):
        q = quat_xyzw_from_rotation(T[:3, :3])
        values = " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q))
        lines.append(f"{format_stamp(stamp_ns(i))} {values}")
    return lines


@dataclass(frozen=True)
class BagSummary:
    """What ``make_bag`` wrote: frame count, path length (m), largest rotation from frame 0 (deg), bytes,
    clearance (m), seconds taken."""

    name: str
    frames: int
    path_length_m: float
    max_rotation_deg: float
    bag_bytes: int
    min_clearance_m: float
    seconds: float
    floor_fraction_min: float | None = None  # bags with a floor: share of floor pixels, smallest over the frames
    floor_fraction_median: float | None = None
    max_floor_flow_px: float | None = None
    wheel_messages: int = 0
    mover_fractions: tuple[float, ...] = ()  # bags with movers: share of mover pixels per frame
    mover_clearance_m: float | None = None


def make_bag(spec: BagSpec, out_dir: Path) -> BagSummary:
    """Render ``spec`` and write ``out_dir/<name>/bag/`` (MCAP) and ``out_dir/<name>/groundtruth_tum.txt``
    (and ``wheel_odom_tum.txt`` when the spec has wheel odometry).

    Raises SceneError when a camera comes nearer than ``spec.min_clearance_m`` to the scene, a frame has a
    pixel that sees no quad, or (bags with a floor) a floor point moves more than ``MAX_FLOOR_FLOW_PX``
    between two frames.
    """
    started = time.monotonic()
    clearance = min_clearance_m(spec.quads, spec.T_w_c)
    if clearance < spec.min_clearance_m:
        msg = f"{spec.name}: a camera comes {clearance:.2f} m from the scene (minimum {spec.min_clearance_m} m)"
        raise SceneError(msg)
    for mover in spec.movers:
        if mover.T_w_o.shape != spec.T_w_c.shape:
            msg = f"{spec.name}: mover {mover.name!r} has {len(mover.T_w_o)} poses for {len(spec.T_w_c)} frames"
            raise SceneError(msg)
    mover_clearance = mover_clearance_m(spec)
    if mover_clearance < spec.min_clearance_m:
        msg = f"{spec.name}: a mover comes {mover_clearance:.2f} m from the camera (minimum {spec.min_clearance_m} m)"
        raise SceneError(msg)
    floor_flow = None
    if spec.floor_y_m is not None:
        floor_flow = max_floor_flow_px(spec.camera, spec.T_w_c, spec.floor_y_m)
        if floor_flow > MAX_FLOOR_FLOW_PX:
            msg = f"{spec.name}: a floor point moves {floor_flow:.1f} px in a frame (at most {MAX_FLOOR_FLOW_PX})"
            raise SceneError(msg)
    floor_fractions: list[float] = []
    mover_frames: list[tuple[float, tuple[int, int, int, int]]] = []
    wheel = spec.wheel_odom
    renderer = Renderer(spec.quads, spec.camera)
    rng = np.random.default_rng(spec.noise_seed)
    T_c0_ci = poses_relative_to_first(spec.T_w_c)

    bag_root = out_dir / spec.name
    bag_dir = bag_root / "bag"
    if bag_dir.exists():
        shutil.rmtree(bag_dir)  # rosbags' Writer refuses to overwrite
    bag_root.mkdir(parents=True, exist_ok=True)
    with Writer(bag_dir, version=ROS_BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
        image_conn = writer.add_connection(IMAGE_TOPIC, IMAGE_MSGTYPE, typestore=TYPESTORE)
        info_conn = writer.add_connection(CAMERA_INFO_TOPIC, CAMERA_INFO_MSGTYPE, typestore=TYPESTORE)
        pose_conn = writer.add_connection(GROUND_TRUTH_TOPIC, POSE_MSGTYPE, typestore=TYPESTORE)
        wheel_conn = None
        if wheel is not None:
            wheel_conn = writer.add_connection(WHEEL_ODOM_TOPIC, ODOMETRY_MSGTYPE, typestore=TYPESTORE)
        next_wheel = 0

        def write_wheel_until(stamp_limit: float) -> None:
            """Write the wheel messages stamped before ``stamp_limit``, in stamp order."""
            nonlocal next_wheel
            while wheel is not None and next_wheel < len(wheel.stamps_ns) and wheel.stamps_ns[next_wheel] < stamp_limit:
                message = TYPESTORE.serialize_cdr(odometry_msg(wheel, next_wheel), ODOMETRY_MSGTYPE)
                writer.write(wheel_conn, int(wheel.stamps_ns[next_wheel]), message)
                next_wheel += 1

        for i, T_w_c in enumerate(spec.T_w_c):
            ideal = renderer.render_ideal(T_w_c, spec.moving_quads_at(i))
            if ideal.mover_coverage is not None:
                mover_frames.append(mover_stats(ideal.mover_coverage))
            if float(ideal.coverage.min()) < 1.0:
                msg = f"{spec.name}: frame {i} has pixels that see no quad"
                raise SceneError(msg)
            if spec.floor_y_m is not None:
                floor_fractions.append(floor_fraction(ideal, spec.camera, T_w_c, spec.floor_y_m))
            image = sensor_image(ideal.image, rng)
            stamp = stamp_ns(i)
            write_wheel_until(stamp)
            for conn, message, msgtype in (
                (image_conn, compressed_image_msg(image, stamp, spec.jpeg_quality), IMAGE_MSGTYPE),
                (info_conn, camera_info_msg(spec.camera, stamp), CAMERA_INFO_MSGTYPE),
                (pose_conn, pose_msg(T_c0_ci[i], stamp), POSE_MSGTYPE),
            ):
                writer.write(conn, stamp, TYPESTORE.serialize_cdr(message, msgtype))
        write_wheel_until(math.inf)
    (bag_root / "groundtruth_tum.txt").write_text("\n".join(tum_lines(T_c0_ci)) + "\n")
    if wheel is not None:
        (bag_root / "wheel_odom_tum.txt").write_text("\n".join(wheel_tum_lines(wheel)) + "\n")
    if spec.movers:
        (bag_root / "mover_coverage.txt").write_text("\n".join(mover_coverage_lines(mover_frames)) + "\n")
        for mover in spec.movers:
            lines = mover_tum_lines(mover, spec.T_w_c[0])
            (bag_root / f"{mover.name}_pose_tum.txt").write_text("\n".join(lines) + "\n")

    steps = np.diff(spec.T_w_c[:, :3, 3], axis=0)
    cos_angles = (np.trace(T_c0_ci[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0
    max_rotation = math.degrees(math.acos(float(np.clip(cos_angles, -1.0, 1.0).min())))
    size = sum(f.stat().st_size for f in bag_dir.iterdir())
    return BagSummary(
        spec.name,
        len(spec.T_w_c),
        float(np.linalg.norm(steps, axis=1).sum()),
        max_rotation,
        size,
        clearance,
        time.monotonic() - started,
        min(floor_fractions) if floor_fractions else None,
        float(np.median(floor_fractions)) if floor_fractions else None,
        floor_flow,
        0 if wheel is None else len(wheel.stamps_ns),
        tuple(fraction for fraction, _ in mover_frames),
        mover_clearance if spec.movers else None,
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent, help="output folder")
    parser.add_argument("--only", choices=sorted(SPECS), action="append", help="make only this bag (repeatable)")
    args = parser.parse_args(argv)
    names = args.only or list(SPECS)
    for name in names:
        summary = make_bag(SPECS[name](), args.out)
        print(
            f"{summary.name}: {summary.frames} frames, path {summary.path_length_m:.2f} m, "
            f"max rotation from frame 0 {summary.max_rotation_deg:.1f} deg, clearance {summary.min_clearance_m:.2f} m, "
            f"{summary.bag_bytes / 1e6:.2f} MB, {summary.seconds:.0f} s"
        )
        if summary.floor_fraction_min is not None:
            print(
                f"  floor share of the pixels: min {summary.floor_fraction_min:.1%}, median "
                f"{summary.floor_fraction_median:.1%}; largest floor motion {summary.max_floor_flow_px:.1f} px/frame"
            )
        if summary.wheel_messages:
            print(f"  {summary.wheel_messages} wheel odometry messages on {WHEEL_ODOM_TOPIC}")
        if summary.mover_fractions:
            fractions = np.array(summary.mover_fractions)
            seen = fractions[fractions > 0.0]
            print(
                f"  mover: on {seen.size}/{fractions.size} frames, share of the pixels min {fractions.min():.1%}, "
                f"median {np.median(fractions):.1%}, max {fractions.max():.1%} (median {np.median(seen):.1%} "
                f"where seen), >= 25 % on {np.mean(fractions >= 0.25):.0%} of the frames; "
                f"nearest {summary.mover_clearance_m:.2f} m from the camera"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
