"""The scenario families: what each draws per seed (scene, trajectory) within its envelope.

A family is a function ``(trajectory rng, scene rng) -> Drawn``: the quads of the scene, the camera's
pose as a function of time (``pose_at(t)``: ``T_w_c`` (4, 4) at t seconds after the first frame, so a
rolling shutter's rows and an exposure's instants have exact poses), the movers, what a metric scale
source needs, and the drawn parameters (for scenario.json). ``FAMILIES`` lists them with their constants
(image size, frame rate, frames, fault envelope). docs/distribution.md describes every envelope.

Conventions are make_bags': world x right, y down, z forward; the camera starts near the origin at y ~ 0
and the floor is at ``y = camera height``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import make_bags as mb
import numpy as np
import scenario_scenes as sc
from camera_faults import FaultEnvelope
from numpy.typing import NDArray

Matrix4 = NDArray[np.float64]
PoseFn = Callable[[float], Matrix4]
DEG = math.pi / 180.0
WHEEL_TOPIC = mb.WHEEL_ODOM_TOPIC
DEFAULT_ENVELOPE = FaultEnvelope()


@dataclass(frozen=True)
class MovingObject:
    """A rigid group of quads (in its own frame) placed in the world at ``pose_at(t)``."""

    name: str
    quads: tuple[mb.Quad, ...]
    pose_at: PoseFn

    def quads_at(self, t: float) -> tuple[mb.Quad, ...]:
        T = self.pose_at(t)
        return tuple(mb.transform_quad(q, T) for q in self.quads)


@dataclass(frozen=True)
class WheelModel:
    """A ground robot's base motion and its wheel odometry's errors (make_bags' model, drawn per seed).

    ``base_at(t)``: (x, y, yaw) of base_link in the floor frame (x forward, y left, z up; base_link at t = 0
    is the origin) at t seconds after the first image, also a little before it and after the last."""

    base_at: Callable[[float], tuple[float, float, float]]
    scale_error: float
    yaw_rate_bias_rad_s: float
    speed_noise: float = mb.WHEEL_SPEED_NOISE
    yaw_rate_noise_rad_s: float = mb.WHEEL_YAW_RATE_NOISE_RAD_S


@dataclass(frozen=True)
class Drawn:
    """What one seed of a family drew."""

    quads: tuple[mb.Quad, ...]
    pose_at: PoseFn
    focal_ratio: float  # focal length / image width
    movers: tuple[MovingObject, ...] = ()
    metric: dict[str, object] = field(default_factory=dict)  # what a metric scale source needs
    wheel: WheelModel | None = None
    floor_y_m: float | None = None  # the floor's world y, where there is one the robot drives on
    draws: dict[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class Family:
    """A family's constants: image size, frame rate and frames of the full distribution, the camera's
    least distance to any surface, whether its camera centre stays put, and its fault envelope."""

    name: str
    draw: Callable[[np.random.Generator, np.random.Generator], Drawn]
    summary: str
    size: tuple[int, int]
    fps: float
    frames: int
    min_clearance_m: float = 0.5
    static: bool = False
    envelope: FaultEnvelope = DEFAULT_ENVELOPE
    scale_sources: tuple[str, ...] = ()

    @property
    def duration_s(self) -> float:
        return (self.frames - 1) / self.fps


# --- smooth random motion ------------------------------------------------------------------------------------


def wave(rng: np.random.Generator, amplitude: float, duration: float, freq_hz: tuple[float, float] = (0.1, 0.5),
         terms: int = 3) -> Callable[[float], float]:
    """A smooth random signal: a sum of ``terms`` sines of random frequency and phase whose largest
    magnitude over ``[0, duration]`` is ``amplitude``."""
    freqs = rng.uniform(*freq_hz, terms)
    phases = rng.uniform(0.0, 2.0 * math.pi, terms)
    weights = rng.uniform(0.5, 1.0, terms)
    grid = np.linspace(0.0, duration, 200)
    peak = float(np.abs(np.sin(2 * math.pi * freqs[None, :] * grid[:, None] + phases) @ weights).max())
    k = amplitude / max(peak, 1e-9)

    def f(t: float) -> float:
        return k * float(np.sin(2 * math.pi * freqs * t + phases) @ weights)

    return f


def posed(position: Callable[[float], tuple[float, float, float]],
          angles: Callable[[float], tuple[float, float, float]]) -> PoseFn:
    """``pose_at(t)`` from a position and (yaw, pitch, roll) in make_bags' camera convention."""

    def pose_at(t: float) -> Matrix4:
        return mb.se3(mb.camera_rotation(*angles(t)), position(t))

    return pose_at


def look_angles(position: NDArray[np.float64], target: NDArray[np.float64]) -> tuple[float, float]:
    """(yaw, pitch) that point the optical axis from ``position`` at ``target`` (make_bags' convention)."""
    d = target - position
    return math.atan2(d[0], d[2]), math.atan2(-d[1], math.hypot(d[0], d[2]))


def sample_path(pose_at: PoseFn, duration: float, n: int = 60) -> NDArray[np.float64]:
    """(n, 2) world x, z of the camera centre over ``[0, duration]``."""
    return np.array([pose_at(t)[[0, 2], 3] for t in np.linspace(0.0, duration, n)])


def walk_jitter(rng: np.random.Generator, duration: float, rot_deg: float, bob_m: float
                ) -> tuple[Callable[[float], NDArray[np.float64]], Callable[[float], NDArray[np.float64]]]:
    """Small random (yaw, pitch, roll) and (x, y, z) offsets of a carried camera: ``rot_deg`` and ``bob_m``
    at most, slow (0.2-1 Hz)."""
    rot = [wave(rng, rot_deg * DEG, duration, (0.2, 1.0)) for _ in range(3)]
    pos = [wave(rng, bob_m, duration, (0.2, 1.0)) for _ in range(3)]
    return (lambda t: np.array([f(t) for f in rot])), (lambda t: np.array([f(t) for f in pos]))


# --- the families ----------------------------------------------------------------------------------------------


def _floor_richness(rng: np.random.Generator) -> str:
    return str(rng.choice(["rich", "faint", "sparse"], p=[0.5, 0.25, 0.25]))


def draw_forward(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Walking down a corridor or hall: 2.4-6 m wide, 2.6-4.5 m high, walls in 6-10 m stretches of their own
    look, the floor rich, faint or sparse; 0.7-1.6 m/s, swaying, yaw +-1-5 deg."""
    fam = FAMILIES["forward"]
    T = fam.duration_s
    width, height = float(scn.uniform(2.4, 6.0)), float(scn.uniform(2.6, 4.5))
    cam_h = float(tr.uniform(1.2, min(1.7, height - 0.6)))
    speed = float(tr.uniform(0.7, 1.6))
    room = 0.5 * width - 0.7
    x0 = float(tr.uniform(-0.5, 0.5)) * room
    sway = wave(tr, float(tr.uniform(0.05, 0.3)) * min(1.0, room / 0.6), T)
    yaw, pitch0 = wave(tr, float(tr.uniform(1.0, 5.0)) * DEG, T), -float(tr.uniform(0.0, 5.0)) * DEG
    nod, roll = wave(tr, 1.5 * DEG, T), wave(tr, 1.5 * DEG, T)
    bob = wave(tr, 0.03, T, (0.8, 2.0))

    def position(t: float) -> tuple[float, float, float]:
        return float(np.clip(x0 + sway(t), -room, room)), bob(t), speed * t

    def angles(t: float) -> tuple[float, float, float]:
        return yaw(t), pitch0 + nod(t), roll(t)

    z_end = speed * T + float(scn.uniform(15.0, 40.0))
    floor_look = sc.draw_floor(scn, _floor_richness(scn))
    top = sc.Look(str(scn.choice([sc.PLASTER, sc.CONCRETE, "hubble_deep_field"])), 3.0, 0.9)
    x0w, x1w, y_top = -0.5 * width, 0.5 * width, cam_h - height
    quads = [sc.floor(cam_h, (x0w - 0.1, x1w + 0.1), (-3.1, z_end + 0.1), floor_look),
             sc.floor(y_top, (x0w - 0.1, x1w + 0.1), (-3.1, z_end + 0.1), top),
             sc.wall((0.0, 0.5 * (cam_h + y_top), z_end), (0, 0, -1), width + 0.2, height + 0.2, sc.draw_look(scn)),
             sc.wall((0.0, 0.5 * (cam_h + y_top), -3.0), (0, 0, 1), width + 0.2, height + 0.2, sc.draw_look(scn))]
    looks = []
    for x, facing in ((x0w, (1, 0, 0)), (x1w, (-1, 0, 0))):
        z = -3.0
        while z < z_end:
            length = min(float(scn.uniform(6.0, 10.0)), z_end - z)
            look = sc.draw_look(scn, (*sc.RICH_TEXTURES, sc.PLASTER), (1.5, 3.5))
            looks.append(look.texture)
            quads.append(sc.wall((x, 0.5 * (cam_h + y_top), z + 0.5 * length), facing, length + 0.05, height + 0.2,
                                 look))
            z += length
    return Drawn(tuple(quads), posed(position, angles), float(tr.uniform(0.65, 0.95)),
                 draws={"width_m": width, "height_m": height, "camera_height_m": cam_h, "speed_m_s": speed,
                        "floor": floor_look.texture, "walls": looks})


def draw_sideways(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Strafing sideways at 0.3-0.9 m/s in front of boxes, pillars and walls 2.5-18 m away, yaw offset
    +-15 deg, looking 0-10 deg down."""
    fam = FAMILIES["sideways"]
    T = fam.duration_s
    cam_h = float(tr.uniform(1.2, 1.8))
    speed, sign = float(tr.uniform(0.3, 0.9)), float(tr.choice([-1.0, 1.0]))
    drift = float(tr.uniform(-0.1, 0.1))
    yaw0, pitch0 = float(tr.uniform(-15.0, 15.0)) * DEG, -float(tr.uniform(0.0, 10.0)) * DEG
    jr, jp = walk_jitter(tr, T, 2.0, 0.03)

    def position(t: float) -> tuple[float, float, float]:
        j = jp(t)
        return sign * speed * (t - 0.5 * T) + j[0], j[1], drift * t + j[2]

    def angles(t: float) -> tuple[float, float, float]:
        j = jr(t)
        return yaw0 + j[0], pitch0 + 0.5 * j[1], 0.5 * j[2]

    pose_at = posed(position, angles)
    path = sample_path(pose_at, T)
    quads, draws = sc.yard(scn, path, cam_h, margin_m=(6.0, 14.0), wall_height=(4.0, 10.0),
                           floor_look=sc.draw_floor(scn, _floor_richness(scn)), n_boxes=(3, 6), box_margin_m=2.5,
                           box_z_min=float(path[:, 1].max()) + 2.5)
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.65, 0.95)),
                 draws={**draws, "camera_height_m": cam_h, "speed_m_s": speed, "yaw0_deg": yaw0 / DEG})


def draw_orbit(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Circling 40-100 deg around a cluster of boxes at 3-6 m, looking at it."""
    fam = FAMILIES["orbit"]
    T = fam.duration_s
    cam_h = float(tr.uniform(1.0, 1.8))
    radius = float(tr.uniform(3.0, 6.0))
    phi0 = float(tr.uniform(-0.5, 0.5)) * math.pi
    sweep = float(tr.uniform(40.0, 100.0)) * DEG * float(tr.choice([-1.0, 1.0]))
    target_h = float(tr.uniform(0.5, 1.2))
    breathe, lift = wave(tr, 0.1 * radius, T), wave(tr, 0.1, T)
    wob = [wave(tr, 1.5 * DEG, T, (0.3, 1.0)) for _ in range(3)]
    centre = np.array([0.0, cam_h - target_h, radius])  # the orbit's centre, ahead of the start pose

    def position(t: float) -> NDArray[np.float64]:
        phi = phi0 + sweep * t / T
        r = radius + breathe(t)
        return np.array([r * math.sin(phi), lift(t), radius - r * math.cos(phi)])

    def pose_at(t: float) -> Matrix4:
        p = position(t)
        yaw, pitch = look_angles(p, centre)
        return mb.se3(mb.camera_rotation(yaw + wob[0](t), pitch + wob[1](t), wob[2](t)), p)

    path = sample_path(pose_at, T)
    cluster: list[mb.Quad] = []
    for _ in range(int(scn.integers(2, 5))):
        x, z = centre[0] + scn.uniform(-1.0, 1.0), centre[2] + scn.uniform(-1.0, 1.0)
        size = float(scn.uniform(0.4, 1.0))
        texture = str(scn.choice(sc.RICH_TEXTURES))
        cluster += mb.box_quads(float(x), float(z), size, size, float(scn.uniform(0.8, 2.5)), texture,
                                float(scn.uniform(0.8, 1.3)), ground_y_m=cam_h)
    quads, draws = sc.yard(scn, np.vstack([path, centre[[0, 2]]]), cam_h, margin_m=(4.0, 8.0),
                           wall_height=(4.0, 10.0), floor_look=sc.draw_floor(scn, _floor_richness(scn)),
                           n_boxes=(0, 3), box_margin_m=2.0)
    return Drawn(tuple(cluster + quads), pose_at, float(tr.uniform(0.65, 0.95)),
                 draws={**draws, "radius_m": radius, "sweep_deg": sweep / DEG, "camera_height_m": cam_h})


def _plane_look(scn: np.random.Generator) -> sc.Look:
    if scn.uniform() < 0.4:
        return sc.Look(mb.MOSAIC_TEXTURE, float(scn.uniform(8.0, 14.0)))
    return sc.draw_look(scn, tile_m=(1.5, 4.0))


def _translation_with_turn(tr: np.random.Generator, T: float, direction: NDArray[np.float64], length: float,
                           yaw0: float, pitch0: float, turn_deg: tuple[float, float]) -> PoseFn:
    """Translating ``length`` m along ``direction`` (with a little wobble) while turning by ``turn_deg``."""
    turn = float(tr.uniform(*turn_deg)) * DEG * float(tr.choice([-1.0, 1.0]))
    wob = [wave(tr, 0.03, T) for _ in range(3)]
    nod, roll = wave(tr, float(tr.uniform(1.0, 3.0)) * DEG, T), wave(tr, float(tr.uniform(0.5, 2.0)) * DEG, T)
    split = float(tr.uniform(0.3, 0.7))

    def position(t: float) -> NDArray[np.float64]:
        return length * (t / T - 0.5) * direction + np.array([f(t) for f in wob])

    def angles(t: float) -> tuple[float, float, float]:
        return yaw0 + split * turn * (t / T - 0.5), pitch0 + (1 - split) * turn * (t / T - 0.5) + nod(t), roll(t)

    return posed(position, angles)


def draw_planar_wall(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """One textured plane fills the view: a wall 2.5-6 m ahead, turned up to 35 deg about the vertical and
    10 deg about the horizontal; the camera translates 0.8-2.8 m (mostly along the wall) turning 2-8 deg."""
    fam = FAMILIES["planar_wall"]
    T = fam.duration_s
    distance = float(scn.uniform(2.5, 6.0))
    tilt_y, tilt_x = float(scn.uniform(-35.0, 35.0)) * DEG, float(scn.uniform(-10.0, 10.0)) * DEG
    look = _plane_look(scn)
    R = mb.rot_y(tilt_y) @ mb.rot_x(tilt_x)
    plane = sc.wall((0.0, 0.0, 0.0), (0, 0, -1), 60.0, 40.0, look)
    quads = (mb.transform_quad(plane, mb.se3(R, (0.0, 0.0, distance))),)
    along = R @ np.array([1.0, 0.0, 0.0])
    towards = R @ np.array([0.0, 0.0, 1.0])
    gamma, delta = float(tr.uniform(-40.0, 40.0)) * DEG, float(tr.uniform(-15.0, 15.0)) * DEG
    direction = math.cos(gamma) * along + math.sin(gamma) * towards
    direction = math.cos(delta) * direction + math.sin(delta) * np.array([0.0, 1.0, 0.0])
    length = float(tr.uniform(0.8, 2.8))
    pose_at = _translation_with_turn(tr, T, direction, length, float(tr.uniform(-5.0, 5.0)) * DEG,
                                     float(tr.uniform(-3.0, 3.0)) * DEG, (2.0, 8.0))
    return Drawn(quads, pose_at, float(tr.uniform(0.65, 0.95)),
                 draws={"distance_m": distance, "tilt_deg": (tilt_y / DEG, tilt_x / DEG), "texture": look.texture,
                        "tile_m": look.tile_m, "path_m": length})


def draw_floor_wall(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Two planes: a floor 1-1.8 m below the camera and an upright wall 3-7 m ahead turned up to 30 deg;
    the camera looks 5-20 deg down at their corner and translates 0.8-2.5 m, turning 2-6 deg."""
    fam = FAMILIES["floor_wall"]
    T = fam.duration_s
    cam_h, distance = float(tr.uniform(1.0, 1.8)), float(scn.uniform(3.0, 7.0))
    turn = float(scn.uniform(-30.0, 30.0)) * DEG
    R = mb.rot_y(turn)
    floor_look = sc.draw_floor(scn, str(scn.choice(["rich", "faint", "sparse"])))
    wall_look = _plane_look(scn)
    upright = sc.wall((0.0, cam_h - 15.0, 0.0), (0, 0, -1), 80.0, 30.0, wall_look)
    quads = (mb.transform_quad(upright, mb.se3(R, (0.0, 0.0, distance))),
             sc.floor(cam_h, (-60.0, 60.0), (-20.0, distance + 60.0), floor_look))
    gamma = float(tr.uniform(-40.0, 40.0)) * DEG
    along, towards = R @ np.array([1.0, 0.0, 0.0]), R @ np.array([0.0, 0.0, 1.0])
    direction = math.cos(gamma) * along + math.sin(gamma) * towards
    length = float(tr.uniform(0.8, 2.5))
    pose_at = _translation_with_turn(tr, T, direction, length, float(tr.uniform(-8.0, 8.0)) * DEG,
                                     -float(tr.uniform(5.0, 20.0)) * DEG, (2.0, 6.0))
    return Drawn(quads, pose_at, float(tr.uniform(0.65, 0.95)), metric={"camera_height_m": cam_h},
                 draws={"camera_height_m": cam_h, "wall_distance_m": distance, "wall_turn_deg": turn / DEG,
                        "floor": floor_look.texture, "wall": wall_look.texture, "path_m": length})


def _unicycle(v: Callable[[NDArray[np.float64]], NDArray[np.float64]],
              w: Callable[[NDArray[np.float64]], NDArray[np.float64]], t0: float, t1: float
              ) -> Callable[[float], tuple[float, float, float]]:
    """(x, y, yaw)(t) of a unicycle with speed ``v(t)`` and yaw rate ``w(t)``, at the origin at t = 0,
    integrated on a 1 ms grid (trapezoid) over ``[t0, t1]`` and interpolated between."""
    grid = np.arange(t0, t1 + 1e-3, 1e-3)
    yaw = np.concatenate([[0.0], np.cumsum(0.5 * (w(grid[1:]) + w(grid[:-1])) * np.diff(grid))])
    speed = v(grid)
    vx, vy = speed * np.cos(yaw), speed * np.sin(yaw)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * np.diff(grid))])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (vy[1:] + vy[:-1]) * np.diff(grid))])
    at0 = [float(np.interp(0.0, grid, a)) for a in (x, y, yaw)]
    x, y, yaw = x - at0[0], y - at0[1], yaw - at0[2]
    c, s = math.cos(-at0[2]), math.sin(-at0[2])
    x, y = c * x - s * y, s * x + c * y

    def base_at(t: float) -> tuple[float, float, float]:
        return float(np.interp(t, grid, x)), float(np.interp(t, grid, y)), float(np.interp(t, grid, yaw))

    return base_at


def _turns(tr: np.random.Generator, T: float, count: int, peak_deg_s: tuple[float, float]
           ) -> list[tuple[float, float, float]]:
    """``count`` raised-cosine turns (centre s, duration s, peak rad/s) in order, not overlapping."""
    turns, start = [], float(tr.uniform(0.3, 1.0))
    for _ in range(count):
        duration = float(tr.uniform(1.5, 3.0))
        peak = float(tr.uniform(*peak_deg_s)) * DEG * float(tr.choice([-1.0, 1.0]))
        turns.append((start + 0.5 * duration, duration, peak))
        start += duration + float(tr.uniform(0.2, 1.0))
        if start > T:
            break
    return turns


def _yaw_rate(turns: list[tuple[float, float, float]]) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    def w(t: NDArray[np.float64]) -> NDArray[np.float64]:
        rate = np.zeros_like(t)
        for centre, duration, peak in turns:
            tau = t - centre
            rate += np.where(np.abs(tau) < 0.5 * duration, 0.5 * peak * (1 + np.cos(2 * math.pi * tau / duration)), 0)
        return rate

    return w


def draw_floor_robot(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """A wheeled robot's camera 0.2-1.7 m above a rich, faint or sparse floor, pitched 0-25 deg down; 1-3
    turns of 10-35 deg/s at 0.3-1 m/s (slower where the floor would move more than the trackers follow),
    50 Hz wheel odometry with a drawn scale error (+-3 %) and yaw-rate bias (+-0.6 deg/s)."""
    fam = FAMILIES["floor_robot"]
    T = fam.duration_s
    h, pitch = float(tr.uniform(0.2, 1.7)), float(tr.uniform(0.0, 25.0)) * DEG
    x_offset = float(tr.uniform(0.0, 0.25))
    focal_ratio = float(tr.uniform(0.65, 0.95))
    cruise = float(tr.uniform(0.3, 1.0))
    turns = _turns(tr, T, int(tr.integers(1, 4)), (10.0, 35.0))
    w = _yaw_rate(turns)
    peak = max(abs(p) for _, _, p in turns)
    T_base_camera = mb.se3(mb.rpy_rotation(0.0, pitch, 0.0) @ mb.R_BODY_OPTICAL, (x_offset, 0.0, h))
    T_world_plane = mb.se3(mb.R_BODY_OPTICAL.T, (0.0, h, 0.0))
    width, height = fam.size
    camera = mb.CameraModel(width, height, np.array([[focal_ratio * width, 0, (width - 1) / 2],
                                                     [0, focal_ratio * width, (height - 1) / 2], [0, 0, 1.0]]),
                            np.zeros(5))
    flow_cap = mb.MAX_FLOOR_FLOW_PX * width / 640.0
    speed_scale = 1.0
    for _ in range(4):  # slow down until the floor's image motion stays within what the trackers follow
        k = speed_scale

        def v(t: NDArray[np.float64], k: float = k) -> NDArray[np.float64]:
            start = 0.75 + 0.25 * np.tanh((t + 0.5) / 0.7)
            return k * cruise * start * (1.0 - 0.4 * np.abs(w(t)) / peak)

        base_at = _unicycle(v, w, -1.0, T + 0.5)
        frames = np.array([T_world_plane @ mb.planar_pose(*base_at(i / fam.fps)) @ T_base_camera
                           for i in range(fam.frames)])
        flow = mb.max_floor_flow_px(camera, frames, h, step_px=8)
        if flow <= flow_cap:
            break
        speed_scale *= 0.95 * flow_cap / flow

    def pose_at(t: float) -> Matrix4:
        return T_world_plane @ mb.planar_pose(*base_at(t)) @ T_base_camera

    path = sample_path(pose_at, T)
    floor_look = sc.draw_floor(scn, _floor_richness(scn))
    quads, draws = sc.yard(scn, path, h, margin_m=(3.0, 8.0), wall_height=(2.5, 6.0), floor_look=floor_look,
                           n_boxes=(3, 7), box_margin_m=1.0)
    wheel = WheelModel(base_at, float(tr.uniform(-0.03, 0.03)), float(tr.uniform(-0.6, 0.6)) * DEG)
    return Drawn(tuple(quads), pose_at, focal_ratio,
                 metric={"camera_height_m": h, "wheel_odometry_topic": WHEEL_TOPIC,
                         "T_base_camera": T_base_camera.tolist()},
                 wheel=wheel, floor_y_m=h,
                 draws={**draws, "camera_height_m": h, "pitch_deg": pitch / DEG, "camera_x_in_base_m": x_offset,
                        "cruise_m_s": cruise * speed_scale, "speed_scale": speed_scale, "floor_flow_px": flow,
                        "turns": [(c, d, p / DEG) for c, d, p in turns], "wheel_scale_error": wheel.scale_error,
                        "wheel_yaw_rate_bias_deg_s": wheel.yaw_rate_bias_rad_s / DEG})


def draw_road(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Driving a road with a curve at 5-11 m/s (10 Hz): 8-25 m straight, then an arc of 40-120 m radius
    turning 25-60 deg, then straight; camera 1.2-1.8 m high in the right lane, level to 4 deg down; sparse
    asphalt with lane markings between facades 6-12 m to the sides."""
    fam = FAMILIES["road"]
    T = fam.duration_s
    speed, cam_h = float(tr.uniform(5.0, 11.0)), float(tr.uniform(1.2, 1.8))
    path_m = speed * T
    straight = float(tr.uniform(8.0, 25.0))
    turn = float(tr.uniform(25.0, 60.0)) * DEG
    radius = min(float(tr.uniform(40.0, 120.0)), 0.7 * (path_m - straight) / turn)
    curve = sc.RoadCurve(straight, radius, turn * float(tr.choice([-1.0, 1.0])))
    lane = float(tr.uniform(1.5, 2.2))
    drift, steer = wave(tr, 0.2, T), wave(tr, 0.7 * DEG, T)
    pitch0 = -float(tr.uniform(0.0, 4.0)) * DEG
    bounce, roll, heave = wave(tr, 0.3 * DEG, T, (0.5, 2.0)), wave(tr, 0.5 * DEG, T), wave(tr, 0.02, T, (0.5, 2.0))
    surge = wave(tr, 1.0, T)  # metres ahead of or behind a constant speed (at most 3 m/s faster or slower)

    def pose_at(t: float) -> Matrix4:
        s = speed * t + surge(t)
        psi = curve.heading(s)
        xz = curve.point(s) + (lane + drift(t)) * np.array([math.cos(psi), -math.sin(psi)])
        return mb.se3(mb.camera_rotation(psi + steer(t), pitch0 + bounce(t), roll(t)), (xz[0], heave(t), xz[1]))

    quads, draws = sc.road_scene(scn, curve, path_m + 70.0, cam_h)
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.55, 0.8)), metric={"camera_height_m": cam_h},
                 draws={**draws, "camera_height_m": cam_h, "speed_m_s": speed, "straight_m": straight,
                        "radius_m": radius, "turn_deg": curve.turn_rad / DEG, "lane_offset_m": lane})


def draw_pure_rotation(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """The camera centre never moves: a pan sweeping 10-30 deg, tilt 1-4 deg, roll up to 1.5 deg."""
    fam = FAMILIES["pure_rotation"]
    T = fam.duration_s
    cam_h = float(tr.uniform(1.2, 1.8))
    pan = wave(tr, float(tr.uniform(5.0, 15.0)) * DEG, T, (0.05, 0.3))
    tilt, roll = wave(tr, float(tr.uniform(1.0, 4.0)) * DEG, T), wave(tr, float(tr.uniform(0.0, 1.5)) * DEG, T)
    yaw0, pitch0 = float(tr.uniform(-10.0, 10.0)) * DEG, -float(tr.uniform(0.0, 8.0)) * DEG
    pose_at = posed(lambda t: (0.0, 0.0, 0.0), lambda t: (yaw0 + pan(t), pitch0 + tilt(t), roll(t)))
    quads, draws = sc.yard(scn, np.zeros((1, 2)), cam_h, margin_m=(5.0, 12.0), wall_height=(4.0, 10.0),
                           floor_look=sc.draw_floor(scn, _floor_richness(scn)), n_boxes=(3, 6), box_margin_m=2.5,
                           box_z_min=2.0)
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.65, 0.95)), draws={**draws, "camera_height_m": cam_h})


def draw_low_parallax(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Everything is 15-60 m away and the camera moves only 0.15-0.5 m, turning 2-8 deg."""
    fam = FAMILIES["low_parallax"]
    T = fam.duration_s
    cam_h = float(tr.uniform(1.2, 1.8))
    heading = float(tr.uniform(0.0, 2.0 * math.pi))
    direction = np.array([math.cos(heading), 0.0, math.sin(heading)])
    length = float(tr.uniform(0.15, 0.5))
    pose_at = _translation_with_turn(tr, T, direction, length, float(tr.uniform(-5.0, 5.0)) * DEG,
                                     -float(tr.uniform(0.0, 6.0)) * DEG, (2.0, 8.0))
    quads, draws = sc.yard(scn, sample_path(pose_at, T), cam_h, margin_m=(25.0, 60.0), wall_height=(8.0, 25.0),
                           floor_look=sc.draw_floor(scn, "rich"), n_boxes=(3, 6), box_margin_m=15.0, box_z_min=15.0)
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.65, 0.95)),
                 draws={**draws, "camera_height_m": cam_h, "path_m": length})


def _crossing_mover(tr: np.random.Generator, T: float, cam_h: float, ahead: Callable[[float], NDArray[np.float64]],
                    depth_m: tuple[float, float]) -> tuple[MovingObject, dict[str, object]]:
    """A panel or a cart (make_bags' mover texture) crossing the view 3-6 m ahead of ``ahead(t)`` (a point on
    the floor below the camera), 0.5-1.5 m/s sideways, passing the middle of the view mid-sequence."""
    depth, speed = float(tr.uniform(*depth_m)), float(tr.uniform(0.5, 1.5))
    sign, offset = float(tr.choice([-1.0, 1.0])), float(tr.uniform(-0.5, 0.5))
    t_mid = 0.5 * T + float(tr.uniform(-0.15, 0.15)) * T
    if tr.uniform() < 0.5:
        kind, size = "panel", (float(tr.uniform(2.0, 3.5)), 0.12, float(tr.uniform(1.6, 2.6)))
    else:
        kind, size = "cart", (float(tr.uniform(1.0, 1.6)), float(tr.uniform(1.5, 3.0)), float(tr.uniform(1.2, 2.2)))
    turn = wave(tr, 10.0 * DEG, T)
    quads = tuple(mb.box_quads(0.0, 0.0, size[0], size[1], size[2], mb.MOVER_TEXTURE, ground_y_m=0.0))

    def pose_at(t: float) -> Matrix4:
        base = ahead(t)
        x = base[0] + offset + sign * speed * (t - t_mid)
        yaw = (0.0 if kind == "panel" else sign * 0.5 * math.pi) + turn(t)
        return mb.se3(mb.rot_y(yaw), (x, cam_h, base[2] + depth))

    return MovingObject(kind, quads, pose_at), {"mover": kind, "mover_size_m": size, "mover_depth_m": depth,
                                                "mover_speed_m_s": speed}


def draw_static_mover(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """A camera that never moves and a panel or cart crossing its view 3.2-6 m away at 0.5-1.5 m/s."""
    fam = FAMILIES["static_mover"]
    T = fam.duration_s
    cam_h = float(tr.uniform(1.2, 1.8))
    yaw0, pitch0 = float(tr.uniform(-10.0, 10.0)) * DEG, -float(tr.uniform(0.0, 8.0)) * DEG
    pose_at = posed(lambda t: (0.0, 0.0, 0.0), lambda t: (yaw0, pitch0, 0.0))
    mover, mdraws = _crossing_mover(tr, T, cam_h, lambda t: np.zeros(3), (3.2, 6.0))
    lane = np.array([mover.pose_at(t)[[0, 2], 3] for t in np.linspace(0.0, T, 30)])
    quads, draws = sc.yard(scn, np.vstack([np.zeros((1, 2)), lane]), cam_h, margin_m=(6.0, 14.0),
                           wall_height=(4.0, 10.0), floor_look=sc.draw_floor(scn, _floor_richness(scn)),
                           n_boxes=(2, 5), box_margin_m=2.0, box_z_min=2.0)
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.65, 0.95)), movers=(mover,),
                 draws={**draws, **mdraws, "camera_height_m": cam_h})


def draw_moving_mover(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Walking forward at 0.6-1.4 m/s (gentle S, 3-10 deg down) while a panel or cart crosses 3.5-6 m ahead."""
    fam = FAMILIES["moving_mover"]
    T = fam.duration_s
    cam_h, speed = float(tr.uniform(1.3, 1.7)), float(tr.uniform(0.6, 1.4))
    sway, yaw = wave(tr, 0.3, T), wave(tr, 4.0 * DEG, T)
    pitch0 = -float(tr.uniform(3.0, 10.0)) * DEG
    jr, jp = walk_jitter(tr, T, 1.0, 0.03)

    def position(t: float) -> NDArray[np.float64]:
        return np.array([sway(t), 0.0, speed * t]) + jp(t)

    pose_at = posed(lambda t: tuple(position(t)), lambda t: (yaw(t) + jr(t)[0], pitch0 + jr(t)[1], jr(t)[2]))
    mover, mdraws = _crossing_mover(tr, T, cam_h, lambda t: np.array([0.0, 0.0, speed * t]), (3.5, 6.0))
    lane = np.array([mover.pose_at(t)[[0, 2], 3] for t in np.linspace(0.0, T, 30)])
    path = sample_path(pose_at, T)
    quads, draws = sc.yard(scn, np.vstack([path, lane]), cam_h, margin_m=(5.0, 12.0), wall_height=(4.0, 10.0),
                           floor_look=sc.draw_floor(scn, _floor_richness(scn)), n_boxes=(2, 5), box_margin_m=2.0)
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.65, 0.95)), movers=(mover,),
                 draws={**draws, **mdraws, "camera_height_m": cam_h, "speed_m_s": speed})


def draw_fast(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """Fast: 1.5-3.5 m/s forward while the view swings +-yaw at 40-120 deg/s peak (0.3-0.6 Hz), pitch and
    roll swinging too; long exposures (the envelope's 8-30 ms)."""
    fam = FAMILIES["fast"]
    T = fam.duration_s
    cam_h, speed = float(tr.uniform(1.2, 1.8)), float(tr.uniform(1.5, 3.5))
    rate, freq = float(tr.uniform(40.0, 120.0)) * DEG, float(tr.uniform(0.3, 0.6))
    amp, phase = rate / (2 * math.pi * freq), float(tr.uniform(0.0, 2.0 * math.pi))
    pitch, roll = wave(tr, float(tr.uniform(3.0, 10.0)) * DEG, T, (0.3, 1.0)), wave(tr, float(tr.uniform(2.0, 6.0))
                                                                                     * DEG, T, (0.3, 1.0))
    sway = wave(tr, 0.5, T)

    def position(t: float) -> tuple[float, float, float]:
        return sway(t), 0.0, speed * t

    def angles(t: float) -> tuple[float, float, float]:
        return amp * (math.sin(2 * math.pi * freq * t + phase) - math.sin(phase)), pitch(t), roll(t)

    pose_at = posed(position, angles)
    quads, draws = sc.yard(scn, sample_path(pose_at, T), cam_h, margin_m=(5.0, 12.0), wall_height=(4.0, 10.0),
                           floor_look=sc.draw_floor(scn, _floor_richness(scn)), n_boxes=(3, 6), box_margin_m=2.0)
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.65, 0.95)),
                 draws={**draws, "camera_height_m": cam_h, "speed_m_s": speed, "peak_yaw_rate_deg_s": rate / DEG})


def draw_handheld(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """A phone carried through a room (1-3 of its walls plain plaster), walking 0.4-1 m/s and turning 30-100
    deg towards a side, with hand shake: 0.5-2.5 deg at 2-8 Hz, a 1-3 cm step bob."""
    return _handheld(FAMILIES["handheld"].duration_s, tr, scn)


def draw_handheld_hd(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """``draw_handheld``'s walk with a phone's own video: 1280x720 at 30 frames a second. The same hand shake
    moves the image four times as many pixels as at 320 px wide, and blurs it as many."""
    return _handheld(FAMILIES["handheld_hd"].duration_s, tr, scn)


def _handheld(T: float, tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    cam_h, speed = float(tr.uniform(1.3, 1.7)), float(tr.uniform(0.4, 1.0))
    sweep = float(tr.uniform(30.0, 100.0)) * DEG * float(tr.choice([-1.0, 1.0]))
    shake = [wave(tr, float(tr.uniform(0.5, 2.5)) * DEG, T, (2.0, 8.0), 4) for _ in range(3)]
    step_hz, bob = float(tr.uniform(1.6, 2.2)), float(tr.uniform(0.01, 0.03))
    pitch0 = -float(tr.uniform(0.0, 10.0)) * DEG
    drift = wave(tr, 0.3, T)

    def position(t: float) -> tuple[float, float, float]:
        return drift(t) + 0.5 * bob * math.sin(math.pi * step_hz * t), bob * math.sin(2 * math.pi * step_hz * t), \
            speed * t

    def angles(t: float) -> tuple[float, float, float]:
        ease = 0.5 - 0.5 * math.cos(math.pi * min(t / T, 1.0))
        return sweep * ease + shake[0](t), pitch0 + shake[1](t), shake[2](t)

    pose_at = posed(position, angles)
    path = sample_path(pose_at, T)
    width, depth = float(scn.uniform(6.0, 10.0)), float(scn.uniform(2.5, 5.0))
    x_range = (float(path[:, 0].min()) - 0.5 * width, float(path[:, 0].max()) + 0.5 * width)
    z_range = (-2.0, float(path[:, 1].max()) + depth)
    height = float(scn.uniform(2.6, 3.2))
    plain = set(scn.choice(4, int(scn.integers(1, 4)), replace=False).tolist())
    looks = [sc.Look(sc.PLASTER, 3.0, float(scn.uniform(0.8, 1.1))) if i in plain else sc.draw_look(scn)
             for i in range(4)]
    quads = sc.closed_box(x_range, z_range, cam_h, cam_h - height, sc.draw_floor(scn, _floor_richness(scn)), looks,
                          sc.Look(sc.PLASTER, 3.0))
    quads += sc.posters(scn, x_range, z_range, cam_h, height, int(scn.integers(1, 4)), sides=[
        i for i in range(4) if i not in plain])
    quads += sc.boxes(scn, int(scn.integers(2, 6)), (x_range[0] + 0.5, x_range[1] - 0.5),
                      (z_range[0] + 0.5, z_range[1] - 0.5), cam_h, sc.path_clearance(path, 0.8), (0.4, 1.5),
                      (0.5, 2.0))
    return Drawn(tuple(quads), pose_at, float(tr.uniform(0.7, 0.95)),
                 draws={"room_x_m": x_range, "room_z_m": z_range, "plain_walls": sorted(plain),
                        "camera_height_m": cam_h, "speed_m_s": speed, "sweep_deg": sweep / DEG,
                        "shake_deg": [abs(f(0.3)) for f in shake], "step_hz": step_hz, "bob_m": bob})


def draw_long_loop(tr: np.random.Generator, scn: np.random.Generator) -> Drawn:
    """One full loop around a building-like block (3-6 m square) on an ellipse 2-4 m beyond it, looking
    where it goes: the end is the start again."""
    fam = FAMILIES["long_loop"]
    T = fam.duration_s
    cam_h = float(tr.uniform(1.2, 1.8))
    side = float(scn.uniform(3.0, 6.0))
    half_diag = side / math.sqrt(2.0)
    a, b = (half_diag + float(tr.uniform(2.0, 4.0)) for _ in range(2))
    sign = float(tr.choice([-1.0, 1.0]))  # +1: the loop turns right (clockwise seen from above)
    wobble, breathe = float(tr.uniform(0.0, 0.1)), wave(tr, 0.3, T)
    yaw_w, pitch0, roll = wave(tr, 3.0 * DEG, T), -float(tr.uniform(0.0, 6.0)) * DEG, wave(tr, 1.0 * DEG, T)
    centre = np.array([sign * a, 0.0])  # the start (phi = 0) is the ellipse's point nearest the origin: the origin

    def point(t: float) -> NDArray[np.float64]:
        s = t / T
        phi = 2 * math.pi * (s + wobble * math.sin(2 * math.pi * s) / (2 * math.pi))  # 0 .. 2 pi exactly
        return np.array([sign * a * (1.0 - math.cos(phi)), b * math.sin(phi)])

    def pose_at(t: float) -> Matrix4:
        p, q = point(t), point(t + 1e-3)
        heading = math.atan2(q[0] - p[0], q[1] - p[1])
        return mb.se3(mb.camera_rotation(heading + yaw_w(t), pitch0, roll(t)), (p[0], breathe(t) * 0.05, p[1]))

    path = sample_path(pose_at, T, 120)
    block = mb.box_quads(float(centre[0]), float(centre[1]), side, side, float(scn.uniform(2.5, 5.0)),
                         str(scn.choice(sc.RICH_TEXTURES)), ground_y_m=cam_h)
    inside = sc.path_clearance(path, 1.5)

    def outside(x: float, z: float, r: float) -> bool:
        return inside(x, z, r) and ((x - centre[0]) / (a + r)) ** 2 + ((z - centre[1]) / (b + r)) ** 2 > 1.0

    quads, draws = sc.yard(scn, path, cam_h, margin_m=(2.5, 6.0), wall_height=(3.0, 8.0),
                           floor_look=sc.draw_floor(scn, _floor_richness(scn)), n_boxes=(2, 5), box_margin_m=1.5,
                           keep_clear=outside)
    return Drawn(tuple(block + quads), pose_at, float(tr.uniform(0.65, 0.95)),
                 draws={**draws, "block_m": side, "ellipse_m": (a, b), "camera_height_m": cam_h,
                        "direction": "clockwise" if sign > 0 else "anticlockwise"})


FAMILIES: dict[str, Family] = {f.name: f for f in (
    Family("forward", draw_forward, "walking down a corridor or hall", (320, 240), 15.0, 80),
    Family("sideways", draw_sideways, "strafing sideways past boxes and walls", (320, 240), 15.0, 60),
    Family("orbit", draw_orbit, "circling a cluster of boxes, looking at it", (320, 240), 15.0, 80),
    Family("planar_wall", draw_planar_wall, "one textured plane fills the view", (640, 480), 15.0, 60, 1.5),
    Family("floor_wall", draw_floor_wall, "a floor and one wall", (640, 480), 15.0, 60, 0.9,
           scale_sources=()),
    Family("floor_robot", draw_floor_robot, "a wheeled robot's camera over a floor, with wheel odometry",
           (480, 360), 15.0, 90, 0.15, scale_sources=("ground_plane", "wheel_odometry")),
    Family("road", draw_road, "driving a road with a curve", (480, 360), 10.0, 80, 1.0,
           scale_sources=("ground_plane",)),
    Family("pure_rotation", draw_pure_rotation, "the camera only turns", (320, 240), 15.0, 60, 1.0, static=True),
    Family("low_parallax", draw_low_parallax, "a short baseline before a far scene", (320, 240), 15.0, 60, 1.0),
    Family("static_mover", draw_static_mover, "a still camera, an object crossing the view", (320, 240), 15.0, 60,
           1.0, static=True),
    Family("moving_mover", draw_moving_mover, "walking while an object crosses ahead", (320, 240), 15.0, 80, 1.0),
    Family("fast", draw_fast, "fast motion and swinging view, long exposures", (320, 240), 15.0, 60, 1.0,
           envelope=FaultEnvelope(exposure_ms=(8.0, 30.0))),
    Family("handheld", draw_handheld, "a phone carried through a room with plain walls, hand shake", (320, 240),
           15.0, 100, 0.4, envelope=FaultEnvelope(exposure_ms=(5.0, 25.0), overlay_probability=0.8)),
    Family("handheld_hd", draw_handheld_hd, "a phone's 1280x720 video carried through a room, hand shake",
           (1280, 720), 30.0, 100, 0.4, envelope=FaultEnvelope(exposure_ms=(5.0, 25.0), overlay_probability=0.8)),
    Family("long_loop", draw_long_loop, "one full loop around a block", (320, 240), 10.0, 120, 1.0),
)}
