"""Scene building blocks of the scenario families (bags/scenarios.py): textures made by code, and closed
rooms, yards, corridors and a curving road drawn at random from make_bags' textured quads.

Every scene is closed (a floor, walls and a ceiling or sky around everything the camera can see), so
every ray of every frame hits a surface; the renderer's coverage check holds for any camera pose inside.

Conventions are make_bags': world x right, y down, z forward; a floor at ``y = ground_y`` lies below a
camera at y = 0 when ``ground_y > 0``. Texture names are make_bags' photographs and the ones made here
(registered in ``make_bags.TEXTURE_MAKERS``), each deterministic (fixed seeds).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import make_bags as mb
import numpy as np
from numpy.typing import NDArray

# --- textures made by code ------------------------------------------------------------------------------

ASPHALT = "asphalt"  # road surface: fine low-contrast grain, a few patches and cracks
ROAD = "road"  # 8 m x 12 m of asphalt with two edge lines and one centre dash (mirror-tiled along the road)
CONCRETE = "concrete"  # a floor with little texture: broad blotches, faint grain, sparse stains
PLASTER = "plaster"  # a wall with almost no texture: the sensor's noise is most of what a tracker sees
ROAD_WIDTH_M = 8.0
ROAD_TILE_M = 12.0
ROAD_PX_PER_M = 100  # texels per metre of the road texture (1 cm)
# Photographs with detail everywhere, for walls, boxes and posters (make_bags.PHOTO_TEXTURES minus the
# text sample, whose large blank margins make a poorer wall).
RICH_TEXTURES = ("astronaut", "brick", "camera", "chelsea", "coffee", "coins", "grass", "gravel",
                 "hubble_deep_field", "rocket")
FLOOR_RICH = ((mb.PAVING_TEXTURE, 6.0), ("gravel", 2.5), ("brick", 2.0))  # (texture, tile m)
FLOOR_SPARSE = ((CONCRETE, 5.0), (ASPHALT, 4.0))


def _noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> NDArray[np.float32]:
    """Gaussian white noise smoothed by a Gaussian of ``sigma_px``, scaled to unit standard deviation."""
    field = rng.normal(0.0, 1.0, shape).astype(np.float32)
    if sigma_px > 0:
        field = cv2.GaussianBlur(field, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    return field / max(float(field.std()), 1e-6)


def _stains(rng: np.random.Generator, image: NDArray[np.float32], count: int, radius_px: tuple[float, float],
            depth: tuple[float, float]) -> None:
    """Darken ``count`` soft round stains into ``image`` (in place): the sparse corners of a plain floor."""
    h, w = image.shape
    mask = np.zeros((h, w), np.float32)
    for _ in range(count):
        centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        axes = (int(rng.uniform(*radius_px)), int(rng.uniform(*radius_px)))
        cv2.ellipse(mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(*depth)), -1)
    image -= cv2.GaussianBlur(mask, (0, 0), 1.5)


def _cracks(rng: np.random.Generator, image: NDArray[np.float32], count: int, darkness: float) -> None:
    """Thin dark random-walk lines (cracks), in place."""
    h, w = image.shape
    mask = np.zeros((h, w), np.float32)
    for _ in range(count):
        point = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        heading = rng.uniform(0, 2 * math.pi)
        for _ in range(int(rng.integers(15, 40))):
            heading += rng.normal(0.0, 0.5)
            nxt = point + 8.0 * np.array([math.cos(heading), math.sin(heading)])
            cv2.line(mask, (int(point[0]), int(point[1])), (int(nxt[0]), int(nxt[1])), darkness, 1)
            point = nxt
    image -= cv2.GaussianBlur(mask, (0, 0), 0.7)


def _to_uint8(image: NDArray[np.float32]) -> NDArray[np.uint8]:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _asphalt_base(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.float32]:
    image = 95.0 + 5.0 * _noise(rng, shape, 0.8) + 6.0 * _noise(rng, shape, 30.0)
    _stains(rng, image, 10, (15.0, 60.0), (6.0, 14.0))
    _cracks(rng, image, 5, 30.0)
    return image


def make_asphalt() -> NDArray[np.uint8]:
    return _to_uint8(_asphalt_base(np.random.default_rng(101), (1024, 1024)))


def make_road() -> NDArray[np.uint8]:
    """8 m across (u) by 12 m along (v) at 1 cm a texel: asphalt, 15 cm edge lines 0.3 m inside each edge,
    and a 3 m centre dash in the middle of the tile (so the mirrored tiles give one dash every 12 m)."""
    px = ROAD_PX_PER_M
    w, h = int(ROAD_WIDTH_M * px), int(ROAD_TILE_M * px)
    image = _asphalt_base(np.random.default_rng(102), (h, w))
    paint = np.zeros((h, w), np.float32)
    for left in (0.30, ROAD_WIDTH_M - 0.45):
        paint[:, int(left * px):int((left + 0.15) * px)] = 1.0
    centre = int(0.5 * ROAD_WIDTH_M * px)
    paint[int(4.5 * px):int(7.5 * px), centre - 6:centre + 6] = 1.0
    worn = np.clip(0.85 + 0.15 * _noise(np.random.default_rng(103), (h, w), 2.0), 0.5, 1.0)
    image = image * (1.0 - paint) + paint * 200.0 * worn
    return _to_uint8(image)


def make_concrete() -> NDArray[np.uint8]:
    rng = np.random.default_rng(104)
    image = 128.0 + 8.0 * _noise(rng, (1024, 1024), 40.0) + 1.5 * _noise(rng, (1024, 1024), 1.0)
    _stains(rng, image, 25, (3.0, 10.0), (15.0, 30.0))
    return _to_uint8(image)


def make_plaster() -> NDArray[np.uint8]:
    rng = np.random.default_rng(105)
    return _to_uint8(170.0 + 2.0 * _noise(rng, (512, 512), 30.0) + 0.8 * _noise(rng, (512, 512), 1.5))


mb.TEXTURE_MAKERS.update({ASPHALT: make_asphalt, ROAD: make_road, CONCRETE: make_concrete, PLASTER: make_plaster})


# --- drawing what the scene looks like ----------------------------------------------------------------------


@dataclass(frozen=True)
class Look:
    """How a surface looks: texture, tile size (m; None stretches it once) and shading."""

    texture: str
    tile_m: float | None = None
    gain: float = 1.0
    offset: float = 0.0


def draw_look(rng: np.random.Generator, textures: Sequence[str] = RICH_TEXTURES,
              tile_m: tuple[float, float] = (2.0, 4.0)) -> Look:
    """A random wall look: one of ``textures``, tiled every ``tile_m`` metres, shaded at random."""
    texture = str(textures[int(rng.integers(len(textures)))])
    return Look(texture, float(rng.uniform(*tile_m)), float(rng.uniform(0.7, 1.2)), float(rng.uniform(-10, 25)))


def draw_floor(rng: np.random.Generator, richness: str) -> Look:
    """A floor look of the given texture richness: 'rich' (paving, gravel, bricks) or 'sparse' (concrete,
    asphalt); 'faint' is a rich one at a quarter of its contrast."""
    if richness == "sparse":
        texture, tile = FLOOR_SPARSE[int(rng.integers(len(FLOOR_SPARSE)))]
        return Look(texture, tile * float(rng.uniform(0.8, 1.25)))
    texture, tile = FLOOR_RICH[int(rng.integers(len(FLOOR_RICH)))]
    if richness == "faint":  # a rich pattern at low contrast around mid grey
        return Look(texture, tile, 0.25, 95.0)
    return Look(texture, tile * float(rng.uniform(0.8, 1.25)), float(rng.uniform(0.8, 1.1)))


SKY = Look(PLASTER, 40.0, 1.2, 20.0)  # bright and almost without texture


def wall(center_w: Sequence[float], facing_w: Sequence[float], width_m: float, height_m: float, look: Look) -> mb.Quad:
    return mb.wall_quad(center_w, facing_w, width_m, height_m, look.texture, tile_m=look.tile_m or width_m,
                        gain=look.gain, offset=look.offset)


def floor(y_m: float, x_range: tuple[float, float], z_range: tuple[float, float], look: Look) -> mb.Quad:
    return mb.horizontal_quad(y_m, x_range, z_range, look.texture, look.tile_m or (x_range[1] - x_range[0]),
                              look.gain, look.offset)


def closed_box(x_range: tuple[float, float], z_range: tuple[float, float], floor_y: float, top_y: float,
               floor_look: Look, wall_looks: Sequence[Look], top_look: Look) -> list[mb.Quad]:
    """Floor, ceiling and four inward-facing walls (left, right, back = far z, front = near z) of a room.
    The floor and the ceiling reach 0.1 m beyond the walls and the walls 0.1 m beyond each other, so no
    ray slips through a corner."""
    (x0, x1), (z0, z1) = x_range, z_range
    height, cy = floor_y - top_y, 0.5 * (floor_y + top_y)
    xm, zm, xl, zl = 0.5 * (x0 + x1), 0.5 * (z0 + z1), x1 - x0, z1 - z0
    left, right, back, front = wall_looks
    return [
        floor(floor_y, (x0 - 0.1, x1 + 0.1), (z0 - 0.1, z1 + 0.1), floor_look),
        floor(top_y, (x0 - 0.1, x1 + 0.1), (z0 - 0.1, z1 + 0.1), top_look),
        wall((x0, cy, zm), (1, 0, 0), zl + 0.2, height + 0.2, left),
        wall((x1, cy, zm), (-1, 0, 0), zl + 0.2, height + 0.2, right),
        wall((xm, cy, z1), (0, 0, -1), xl + 0.2, height + 0.2, back),
        wall((xm, cy, z0), (0, 0, 1), xl + 0.2, height + 0.2, front),
    ]


def posters(rng: np.random.Generator, x_range: tuple[float, float], z_range: tuple[float, float], floor_y: float,
            wall_height: float, count: int, sides: Sequence[int] = (0, 1, 2, 3)) -> list[mb.Quad]:
    """``count`` photographs hung 5 cm in front of the walls of a room (``sides``: 0 left, 1 right, 2 back,
    3 front, as :func:`closed_box`), at random places and sizes."""
    (x0, x1), (z0, z1) = x_range, z_range
    quads: list[mb.Quad] = []
    if not sides:
        return quads
    for _ in range(count):
        side = int(sides[int(rng.integers(len(sides)))])
        size = float(rng.uniform(1.0, 3.0))
        height = floor_y - float(rng.uniform(0.9, max(1.0, min(wall_height - 0.5 * size, 3.5))))
        texture = str(RICH_TEXTURES[int(rng.integers(len(RICH_TEXTURES)))])
        if side < 2:  # left / right wall: along z
            along = float(rng.uniform(z0 + size, max(z0 + size, z1 - size)))
            x = x0 + 0.05 if side == 0 else x1 - 0.05
            quads.append(mb.wall_quad((x, height, along), (1 - 2 * side, 0, 0), size, None, texture))
        else:
            along = float(rng.uniform(x0 + size, max(x0 + size, x1 - size)))
            z = z1 - 0.05 if side == 2 else z0 + 0.05
            quads.append(mb.wall_quad((along, height, z), (0, 0, -1 if side == 2 else 1), size, None, texture))
    return quads


def boxes(rng: np.random.Generator, count: int, x_range: tuple[float, float], z_range: tuple[float, float],
          floor_y: float, keep_clear: Callable[[float, float, float], bool],
          size_m: tuple[float, float] = (0.4, 1.6), height_m: tuple[float, float] = (0.6, 3.0)) -> list[mb.Quad]:
    """Up to ``count`` upright boxes and pillars on the floor at random places in the zone, each with a
    random photograph; a box whose footprint (centre x, centre z, half diagonal) ``keep_clear`` refuses
    (too near the camera's path) is drawn again, at most 20 times."""
    quads: list[mb.Quad] = []
    for _ in range(count):
        for _ in range(20):
            sx, sz = float(rng.uniform(*size_m)), float(rng.uniform(*size_m))
            x, z = float(rng.uniform(*x_range)), float(rng.uniform(*z_range))
            height = float(rng.uniform(*height_m))
            if rng.uniform() < 0.25:  # a pillar: narrow and tall
                sx = sz = float(rng.uniform(0.25, 0.5))
                height = float(rng.uniform(2.0, 4.0))
            if keep_clear(x, z, 0.5 * math.hypot(sx, sz)):
                texture = str(RICH_TEXTURES[int(rng.integers(len(RICH_TEXTURES)))])
                quads += mb.box_quads(x, z, sx, sz, height, texture, float(rng.uniform(0.8, 1.3)), 0.0,
                                      ground_y_m=floor_y)
                break
    return quads


def path_clearance(path_xz: NDArray[np.float64], margin_m: float) -> Callable[[float, float, float], bool]:
    """A ``keep_clear`` test for :func:`boxes`: the footprint stays ``margin_m`` beyond every path point."""

    def ok(x: float, z: float, radius: float) -> bool:
        return bool(np.min(np.hypot(path_xz[:, 0] - x, path_xz[:, 1] - z)) >= radius + margin_m)

    return ok


def yard(rng: np.random.Generator, path_xz: NDArray[np.float64], floor_y: float, *, margin_m: tuple[float, float],
         wall_height: tuple[float, float], floor_look: Look, n_boxes: tuple[int, int], box_margin_m: float,
         n_posters: tuple[int, int] = (3, 6), box_z_min: float | None = None,
         keep_clear: Callable[[float, float, float], bool] | None = None) -> tuple[list[mb.Quad], dict]:
    """A walled yard around a camera path ``path_xz`` (M, 2): walls ``margin_m`` beyond the path's extent on
    each side (drawn per side), a ceiling of sky at the walls' top, posters, and boxes and pillars at least
    ``box_margin_m`` from the path (and beyond ``box_z_min`` when given: where the camera looks; or where
    ``keep_clear`` allows). Returns the quads and what was drawn."""
    lo, hi = path_xz.min(axis=0), path_xz.max(axis=0)
    x_range = (float(lo[0] - rng.uniform(*margin_m)), float(hi[0] + rng.uniform(*margin_m)))
    z_range = (float(lo[1] - rng.uniform(*margin_m)), float(hi[1] + rng.uniform(*margin_m)))
    height = float(rng.uniform(*wall_height))
    looks = [draw_look(rng) for _ in range(4)]
    quads = closed_box(x_range, z_range, floor_y, floor_y - height, floor_look, looks, SKY)
    quads += posters(rng, x_range, z_range, floor_y, height, int(rng.integers(n_posters[0], n_posters[1] + 1)))
    n = int(rng.integers(n_boxes[0], n_boxes[1] + 1))
    z_lo = z_range[0] + 0.8 if box_z_min is None else max(z_range[0] + 0.8, box_z_min)
    quads += boxes(rng, n, (x_range[0] + 0.8, x_range[1] - 0.8), (z_lo, max(z_lo, z_range[1] - 0.8)), floor_y,
                   keep_clear or path_clearance(path_xz, box_margin_m))
    draws = {"x_range_m": x_range, "z_range_m": z_range, "wall_height_m": height, "floor": floor_look.texture,
             "floor_tile_m": floor_look.tile_m, "walls": [look.texture for look in looks], "boxes_drawn": n}
    return quads, draws


# --- a curving road ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RoadCurve:
    """A road centreline: straight for ``straight_m``, then an arc of ``radius_m`` turning ``turn_rad``
    (positive: right, towards +x), then straight; it starts at the origin heading +z."""

    straight_m: float
    radius_m: float
    turn_rad: float

    @property
    def arc_m(self) -> float:
        return self.radius_m * abs(self.turn_rad)

    def heading(self, s: float) -> float:
        """Heading (rad, about world y, positive turns right) at arc length ``s``."""
        return math.copysign(min(max(s - self.straight_m, 0.0), self.arc_m) / self.radius_m, self.turn_rad)

    def point(self, s: float) -> NDArray[np.float64]:
        """(x, z) of the centreline at arc length ``s`` (m)."""
        s1 = min(s, self.straight_m)
        x, z = 0.0, s1
        if s > self.straight_m:
            a = min(s - self.straight_m, self.arc_m)
            psi = self.heading(self.straight_m + a)
            sign = math.copysign(1.0, self.turn_rad)
            # a circle of radius R about the centre (sign R, straight_m), starting at heading 0
            x += sign * self.radius_m * (1.0 - math.cos(psi))
            z += self.radius_m * abs(math.sin(psi))
            rest = s - self.straight_m - self.arc_m
            if rest > 0:
                x += rest * math.sin(psi)
                z += rest * math.cos(psi)
        return np.array([x, z])


def _forward(psi: float) -> NDArray[np.float64]:
    return np.array([math.sin(psi), 0.0, math.cos(psi)])


def _right(psi: float) -> NDArray[np.float64]:
    return np.array([math.cos(psi), 0.0, -math.sin(psi)])


def _strip(centre_xz: NDArray[np.float64], psi: float, length: float, width: float, y: float, look: Look,
           tile_across_m: float, tile_along_m: float) -> mb.Quad:
    """A horizontal strip centred at ``centre_xz`` along heading ``psi``; texture u across, v along."""
    fwd, right = _forward(psi), _right(psi)
    centre = np.array([centre_xz[0], y, centre_xz[1]])
    origin = centre - 0.5 * width * right + 0.5 * length * fwd
    return mb.Quad(tuple(origin), tuple(width * right), tuple(-length * fwd), look.texture, width / tile_across_m,
                   length / tile_along_m, look.gain, look.offset)


def road_scene(rng: np.random.Generator, curve: RoadCurve, length_m: float, ground_y: float) -> tuple[list[mb.Quad],
                                                                                                       dict]:
    """A road of ``length_m`` along ``curve`` (lane markings on sparse asphalt) between verges, facades of
    random photographs at random distances each side, a few parked boxes, all inside a sky box."""
    quads: list[mb.Quad] = []
    verge = draw_floor(rng, "rich")
    extent = length_m + 200.0
    quads += closed_box((-extent, extent), (-60.0, extent), ground_y + 0.02, ground_y - 80.0,
                        Look(verge.texture, verge.tile_m, verge.gain * 0.8, verge.offset), [SKY] * 4, SKY)
    road_look = Look(ROAD, None, float(rng.uniform(0.85, 1.1)), float(rng.uniform(-10, 10)))
    pieces = [(0.0, curve.straight_m + 1.0)]
    a = curve.straight_m
    while a < curve.straight_m + curve.arc_m:
        step = min(5.0, curve.straight_m + curve.arc_m - a)
        pieces.append((a, a + step))
        a += step
    pieces.append((a, length_m))
    pieces = [(max(s0 - 5.0, -5.0) if i == 0 else s0, s1) for i, (s0, s1) in enumerate(pieces) if s1 > s0]
    side_offset = [float(rng.uniform(6.0, 12.0)) for _ in range(2)]
    facades = []
    for s0, s1 in pieces:
        mid = 0.5 * (s0 + s1)
        psi = curve.heading(mid)
        centre = curve.point(mid)
        length = s1 - s0 + 0.3  # overlap the next piece: no gap on the inside of the curve
        quads.append(_strip(centre, psi, length, ROAD_WIDTH_M, ground_y, road_look, ROAD_WIDTH_M, ROAD_TILE_M))
        for side, sign in enumerate((-1.0, 1.0)):
            look = draw_look(rng, tile_m=(2.5, 5.0))
            height = float(rng.uniform(4.0, 12.0))
            base = centre + sign * side_offset[side] * _right(psi)[[0, 2]]
            quads.append(mb.wall_quad((base[0], ground_y - 0.5 * height, base[1]), -sign * _right(psi), length + 1.0,
                                      height, look.texture, tile_m=look.tile_m, gain=look.gain, offset=look.offset))
            facades.append(look.texture)
    parked = 0
    for _ in range(int(rng.integers(2, 6))):
        s = float(rng.uniform(5.0, length_m - 5.0))
        psi = curve.heading(s)
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        where = curve.point(s) + sign * float(rng.uniform(4.6, 5.4)) * _right(psi)[[0, 2]]
        texture = str(RICH_TEXTURES[int(rng.integers(len(RICH_TEXTURES)))])
        car = mb.box_quads(0.0, 0.0, 1.8, 4.4, float(rng.uniform(1.4, 1.9)), texture, float(rng.uniform(0.8, 1.2)),
                           ground_y_m=0.0)
        T = mb.se3(mb.rot_y(psi), (where[0], ground_y, where[1]))
        quads += [mb.transform_quad(q, T) for q in car]
        parked += 1
    draws = {"verge": verge.texture, "facade_offset_m": side_offset, "facades": facades, "parked_boxes": parked,
             "road_pieces": len(pieces)}
    return quads, draws
