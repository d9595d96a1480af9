#!/usr/bin/env python3
"""The scenario distribution: families x seeds of rendered sequences with exact ground truth, cached.

Each family (bags/scenario_families.py: forward, sideways, orbit, planar_wall, floor_wall, floor_robot,
road, pure_rotation, low_parallax, static_mover, moving_mover, fast, handheld, handheld_hd, long_loop) draws
per seed its scene (layout, textures, how much texture the floor has), its trajectory within the family's
envelope, and the camera's faults (bags/camera_faults.py: noise, motion blur, gain and vignetting, JPEG,
rolling shutter, dropped frames and stamp jitter, a burnt-in timestamp, a slightly wrong CameraInfo).
Rendering is make_bags' renderer; a sequence is deterministic per (family, seed, profile) on the same
numpy and OpenCV.

A sequence is written as the bundled bags are (``bag/`` MCAP with ``/camera/image_raw/compressed``,
``/camera/camera_info`` (what is *declared*), ``/ground_truth/pose``, and ``/wheel/odom`` for the floor
robot; ``groundtruth_tum.txt``), plus ``scenario.json``: everything drawn (scene, trajectory, faults, the
true and the declared camera, what a metric scale source needs) so a failure can be explained. The ground
truth is the true camera motion: the pose of the image's centre row in the middle of its exposure (the
first frame is the identity), stamped with the image's header stamp.

Cache: ``$EPI_VO_SCENARIO_CACHE`` or ``~/.cache/epi_vo/scenarios`` holds
``<profile>-<key>/<family>/<family>-s<seed>/``; the key hashes the generator's source files, the profile
and the numpy / OpenCV / scikit-image versions, so a changed generator renders afresh. Sequences are
rendered in a process pool, each written to a temporary directory and renamed into place when complete.

    .venv/bin/python bags/scenarios.py                       # the whole distribution (14 families x 8 seeds)
    .venv/bin/python bags/scenarios.py --profile subset      # the test suite's subset (one short seed each)
    .venv/bin/python bags/scenarios.py --families road --seeds 0 3 --cache /tmp/scen
"""

from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import itertools
import json
import math
import multiprocessing
import os
import shutil
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import camera_faults as cf
import cv2
import make_bags as mb
import numpy as np
import scenario_families as sf
import skimage
from numpy.typing import NDArray
from rosbags.rosbag2 import StoragePlugin, Writer

HERE = Path(__file__).resolve().parent
FAMILIES = sf.FAMILIES
GENERATOR_FILES = ("make_bags.py", "scenario_scenes.py", "scenario_families.py", "camera_faults.py", "scenarios.py")
CACHE_ENV = "EPI_VO_SCENARIO_CACHE"
SEEDS_PER_FAMILY = 8
CLEARANCE_ATTEMPTS = 20  # a draw that comes too near a surface is drawn again (the seed's next draw)
MOVER_CLEARANCE_M = 1.0
WHEEL_SUBSTEPS = 10  # a wheel step's true distance is summed over this many pieces of the base path


@dataclass(frozen=True)
class Profile:
    """Which seeds, at what size and how many frames: ``width`` None renders at the family's own size,
    ``max_frames`` None all of the family's frames (else the first ones: the same scene, trajectory and
    faults, shorter)."""

    name: str
    seeds: tuple[int, ...]
    width: int | None = None
    max_frames: int | None = None


# The test suite's subset: one seed per family at 320 px and 40 frames. Seed 1 is a mildly faulted camera
# (harshness 1/8-2/8): the faults are exercised, and the figures are those of a camera that works.
SUBSET_SEED = 1
PROFILES = {
    "distribution": Profile("distribution", tuple(range(SEEDS_PER_FAMILY))),
    "subset": Profile("subset", (SUBSET_SEED,), width=320, max_frames=40),
}


def default_cache_root() -> Path:
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else Path.home() / ".cache" / "epi_vo" / "scenarios"


def generator_key(profile: Profile) -> str:
    """Hash of the generator's sources, the profile and the libraries that decide the bytes."""
    digest = hashlib.sha256()
    for name in GENERATOR_FILES:
        digest.update(name.encode() + b"\0" + (HERE / name).read_bytes())
    digest.update(repr((profile, np.__version__, cv2.__version__, skimage.__version__)).encode())
    return digest.hexdigest()[:12]


def _streams(family: str, seed: int) -> list[np.random.Generator]:
    """Independent generators of (trajectory, scene, faults, image noise, wheels, stamps) for a seed."""
    return [np.random.default_rng([zlib.crc32(family.encode()), seed, k]) for k in range(6)]


@dataclass(frozen=True)
class Scenario:
    """One seed of one family: the family's constants, what it drew, its faults and how many draws it took."""

    family: sf.Family
    seed: int
    drawn: sf.Drawn
    faults: cf.CameraFaults
    attempts: int
    streams: tuple[np.random.Generator, ...]


def _clearance(family: sf.Family, drawn: sf.Drawn) -> tuple[float, float]:
    """(least distance camera-scene, least distance camera-mover) over the family's frames (m)."""
    times = np.arange(family.frames) / family.fps
    T = np.stack([drawn.pose_at(t) for t in times])
    scene = mb.min_clearance_m(drawn.quads, T)
    movers = min((mb.quad_distance(q, T[i, :3, 3]) for i, t in enumerate(times) for m in drawn.movers
                  for q in m.quads_at(t)), default=math.inf)
    return scene, movers


def build_scenario(family_name: str, seed: int) -> Scenario:
    """Draw seed ``seed`` of a family (again until it keeps its clearances). SceneError when no draw does."""
    family = sf.FAMILIES[family_name]
    streams = _streams(family_name, seed)
    tr, scn, fault_rng = streams[0], streams[1], streams[2]
    for attempt in range(1, CLEARANCE_ATTEMPTS + 1):
        drawn = family.draw(tr, scn)
        scene, movers = _clearance(family, drawn)
        if scene >= family.min_clearance_m and movers >= MOVER_CLEARANCE_M:
            harshness = ((seed % SEEDS_PER_FAMILY) + float(fault_rng.uniform())) / SEEDS_PER_FAMILY
            faults = cf.draw_faults(fault_rng, harshness, family.envelope, family.frames)
            return Scenario(family, seed, drawn, faults, attempt, tuple(streams))
    msg = f"{family_name} seed {seed}: no draw in {CLEARANCE_ATTEMPTS} keeps the family's clearances"
    raise mb.SceneError(msg)


# --- wheels -------------------------------------------------------------------------------------------------


def simulate_wheels(model: sf.WheelModel, stamps_ns: NDArray[np.int64], rng: np.random.Generator) -> mb.WheelOdometry:
    """Dead-reckoned wheel odometry at ``stamps_ns`` with make_bags' error model (bags/README.md) and the
    seed's drawn scale error and yaw-rate bias: each step's true distance and heading change become a
    measured speed ``(1 + scale_error) v_true (1 + n_v)`` and yaw rate ``w_true + bias + n_w``, integrated
    with the unicycle model at the step's mid heading."""
    times = (stamps_ns - mb.START_NS).astype(np.float64) / mb.NS_PER_S
    edges = np.concatenate([[times[0] - (times[1] - times[0])], times])
    dt = np.diff(edges)
    fine = np.concatenate([np.linspace(a, b, WHEEL_SUBSTEPS + 1)[:-1] for a, b in itertools.pairwise(edges)]
                          + [edges[-1:]])
    base = np.array([model.base_at(float(t)) for t in fine])
    pieces = np.hypot(np.diff(base[:, 0]), np.diff(base[:, 1]))
    distance = pieces.reshape(-1, WHEEL_SUBSTEPS).sum(axis=1)
    turn = base[WHEEL_SUBSTEPS::WHEEL_SUBSTEPS, 2] - base[:-1:WHEEL_SUBSTEPS, 2]
    v = (1.0 + model.scale_error) * distance / dt * (1.0 + rng.normal(0.0, model.speed_noise, dt.size))
    w = turn / dt + model.yaw_rate_bias_rad_s + rng.normal(0.0, model.yaw_rate_noise_rad_s, dt.size)
    pose = np.zeros((stamps_ns.size, 3))
    for k in range(1, stamps_ns.size):
        x, y, yaw = pose[k - 1]
        mid = yaw + 0.5 * w[k] * dt[k]
        pose[k] = (x + v[k] * dt[k] * math.cos(mid), y + v[k] * dt[k] * math.sin(mid), yaw + w[k] * dt[k])
    travelled = np.concatenate([[0.0], np.cumsum(np.abs(v[1:]) * dt[1:])])
    pose_var = np.zeros((stamps_ns.size, 6))
    pose_var[:, 0] = pose_var[:, 1] = 0.01**2 + (0.03 * travelled) ** 2
    pose_var[:, 2:5] = 1e-6
    pose_var[:, 5] = 0.01**2 + (0.01 * (times - times[0])) ** 2
    twist_var = np.zeros((stamps_ns.size, 6))
    twist_var[:, 0] = (0.005 + model.speed_noise * np.abs(v)) ** 2
    twist_var[:, 1:5] = 1e-6
    twist_var[:, 5] = model.yaw_rate_noise_rad_s**2 + model.yaw_rate_bias_rad_s**2
    diagonal = np.arange(6) * 7
    pose_cov, twist_cov = np.zeros((stamps_ns.size, 36)), np.zeros((stamps_ns.size, 36))
    pose_cov[:, diagonal], twist_cov[:, diagonal] = pose_var, twist_var
    return mb.WheelOdometry(stamps_ns.copy(), pose, np.column_stack([v, w]), pose_cov, twist_cov)


# --- rendering one sequence -------------------------------------------------------------------------------


def _size(family: sf.Family, profile: Profile) -> tuple[int, int]:
    if profile.width is None:
        return family.size
    w, h = family.size
    return profile.width, round(profile.width * h / w / 2) * 2


def _camera_json(camera: mb.CameraModel) -> dict[str, object]:
    return {"width": camera.width, "height": camera.height, "K": camera.K.tolist(), "D": camera.D.tolist()}


def _tum_line(stamp: int, T: mb.Matrix4) -> str:
    values = " ".join(f"{v:.9f}" for v in (*T[:3, 3], *mb.quat_xyzw_from_rotation(T[:3, :3])))
    return f"{mb.format_stamp(stamp)} {values}"


def render_sequence(family_name: str, seed: int, profile: Profile, out_dir: Path) -> dict[str, object]:
    """Render one sequence into ``out_dir`` (bag/, groundtruth_tum.txt, scenario.json); returns scenario.json.

    Raises SceneError when a frame has a pixel that sees no surface (a scene that is not closed)."""
    cpu0, wall0 = time.process_time(), time.perf_counter()
    scen = build_scenario(family_name, seed)
    fam, drawn, faults = scen.family, scen.drawn, scen.faults
    noise_rng, wheel_rng, stamp_rng = scen.streams[3], scen.streams[4], scen.streams[5]
    width, height = _size(fam, profile)
    frames = min(fam.frames, profile.max_frames or fam.frames)
    true_cam = cf.true_camera(width, height, drawn.focal_ratio * width, faults)
    declared = cf.declared_camera(true_cam, faults)
    renderer = mb.Renderer(drawn.quads, true_cam)
    blur = cf.MotionBlur(true_cam)
    vignetting = cf.vignette(true_cam, faults.vignetting)
    times = np.arange(fam.frames) / fam.fps
    stamps = cf.header_stamps(times, faults, stamp_rng)[:frames]
    kept = [i for i in range(frames) if i not in set(faults.dropped)]
    T_c0_w = mb.invert_se3(drawn.pose_at(0.0))
    bands = cf.row_bands(height, faults)
    wheel = None
    if drawn.wheel is not None:
        last = int(stamps[kept[-1]]) + mb.WHEEL_TAIL_NS
        wheel_stamps = np.arange(mb.WHEEL_FIRST_NS, last + 1, mb.WHEEL_PERIOD_NS, dtype=np.int64)
        wheel = simulate_wheels(drawn.wheel, wheel_stamps, wheel_rng)
    depths, mover_share, smears, gt_lines = [], [], [], []
    bag_dir = out_dir / "bag"
    out_dir.mkdir(parents=True, exist_ok=True)
    with Writer(bag_dir, version=mb.ROS_BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
        ts = mb.TYPESTORE
        image_conn = writer.add_connection(mb.IMAGE_TOPIC, mb.IMAGE_MSGTYPE, typestore=ts)
        info_conn = writer.add_connection(mb.CAMERA_INFO_TOPIC, mb.CAMERA_INFO_MSGTYPE, typestore=ts)
        pose_conn = writer.add_connection(mb.GROUND_TRUTH_TOPIC, mb.POSE_MSGTYPE, typestore=ts)
        wheel_conn = writer.add_connection(mb.WHEEL_ODOM_TOPIC, mb.ODOMETRY_MSGTYPE, typestore=ts) if wheel else None
        next_wheel = 0
        for i in kept:
            t, stamp = float(times[i]), int(stamps[i])
            row_bands = [mb.RowBand(a, b, drawn.pose_at(t + dt), tuple(q for m in drawn.movers for q in
                                                                       m.quads_at(t + dt))) for a, b, dt in bands]
            ideal = renderer.render_bands(row_bands)
            if float(ideal.coverage.min()) < 1.0:
                msg = f"{family_name} seed {seed}: frame {i} has pixels that see no surface"
                raise mb.SceneError(msg)
            depths.append(float(np.median(ideal.depth)))
            if ideal.mover_coverage is not None:
                mover_share.append(float(ideal.mover_coverage.mean()))
            image, smear = blur.apply(ideal.image, ideal.depth, drawn.pose_at, t, faults.exposure_ms * 1e-3)
            smears.append(smear)
            pixels = cf.sensor(image, faults.gain[i], vignetting, faults, noise_rng)
            if faults.overlay_corner is not None:
                cf.burn_overlay(pixels, stamp, faults.overlay_corner)
            while wheel is not None and next_wheel < wheel.stamps_ns.size and wheel.stamps_ns[next_wheel] < stamp:
                msg_bytes = ts.serialize_cdr(mb.odometry_msg(wheel, next_wheel), mb.ODOMETRY_MSGTYPE)
                writer.write(wheel_conn, int(wheel.stamps_ns[next_wheel]), msg_bytes)
                next_wheel += 1
            T_c0_ci = T_c0_w @ drawn.pose_at(t)
            for conn, message, msgtype in (
                (image_conn, mb.compressed_image_msg(pixels, stamp, faults.jpeg_quality), mb.IMAGE_MSGTYPE),
                (info_conn, mb.camera_info_msg(declared, stamp), mb.CAMERA_INFO_MSGTYPE),
                (pose_conn, mb.pose_msg(T_c0_ci, stamp), mb.POSE_MSGTYPE),
            ):
                writer.write(conn, stamp, ts.serialize_cdr(message, msgtype))
            gt_lines.append(_tum_line(stamp, T_c0_ci))
        while wheel is not None and next_wheel < wheel.stamps_ns.size:
            msg_bytes = ts.serialize_cdr(mb.odometry_msg(wheel, next_wheel), mb.ODOMETRY_MSGTYPE)
            writer.write(wheel_conn, int(wheel.stamps_ns[next_wheel]), msg_bytes)
            next_wheel += 1
    header = ("# timestamp tx ty tz qx qy qz qw: camera optical frame pose relative to the first frame (T_c0_ci), "
              "metres: the image's centre row in the middle of its exposure; stamps equal the image header stamps")
    (out_dir / "groundtruth_tum.txt").write_text("\n".join([header, *gt_lines]) + "\n")
    T_all = np.stack([drawn.pose_at(float(times[i])) for i in kept])
    rel = np.stack([T_c0_w @ T for T in T_all])
    cos_angles = np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    info: dict[str, object] = {
        "family": family_name, "seed": seed, "profile": profile.name, "summary": fam.summary,
        "static_camera": fam.static, "size": [width, height], "fps": fam.fps, "frames_rendered": frames,
        "frames_written": len(kept), "duration_s": float(times[frames - 1]),
        "path_length_m": float(np.linalg.norm(np.diff(T_all[:, :3, 3], axis=0), axis=1).sum()),
        "max_rotation_deg": math.degrees(math.acos(float(cos_angles.min()))),
        "scene_depth_median_m": float(np.median(depths)), "motion_blur_px_max": float(max(smears)),
        "mover_share_median": float(np.median(mover_share)) if mover_share else None,
        "mover_share_max": float(max(mover_share)) if mover_share else None,
        "metric": drawn.metric, "draw_attempts": scen.attempts, "focal_ratio": drawn.focal_ratio,
        "camera_true": _camera_json(true_cam), "camera_declared": _camera_json(declared),
        "faults": faults.to_json(), "scene_and_trajectory": drawn.draws,
        "wheel_messages": 0 if wheel is None else int(wheel.stamps_ns.size),
        "render_cpu_s": time.process_time() - cpu0, "render_wall_s": time.perf_counter() - wall0,
    }
    (out_dir / "scenario.json").write_text(json.dumps(info, indent=1, default=_json_default) + "\n")
    return info


def _json_default(x: object) -> object:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON: {type(x).__name__}")


# --- the cache -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CachedSequence:
    """A rendered sequence in the cache."""

    family: str
    seed: int
    path: Path

    @property
    def info(self) -> dict[str, object]:
        return json.loads((self.path / "scenario.json").read_text())


def sequence_dir(root: Path, profile: Profile, family: str, seed: int) -> Path:
    return root / f"{profile.name}-{generator_key(profile)}" / family / f"{family}-s{seed}"


def _render_into_cache(task: tuple[str, int, Profile, str]) -> tuple[str, int, float, float]:
    """Worker: render one sequence into a temporary directory beside its place and rename it there."""
    family, seed, profile, final = task
    cv2.setNumThreads(1)  # one process per core: the pool is the parallelism
    target = Path(final)
    tmp = target.with_name(f"{target.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    info = render_sequence(family, seed, profile, tmp)
    try:
        tmp.rename(target)
    except OSError:  # another process finished the same sequence first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)
    return family, seed, float(info["render_cpu_s"]), float(info["render_wall_s"])


@dataclass(frozen=True)
class EnsureResult:
    sequences: list[CachedSequence]
    rendered: int  # sequences rendered by this call (the rest were cached)
    render_cpu_s: float  # CPU seconds of those renders
    wall_s: float  # this call's wall time


def ensure(profile: Profile, families: Sequence[str] | None = None, seeds: Sequence[int] | None = None,
           root: Path | None = None, jobs: int = 2,
           progress: Callable[[str], None] | None = None) -> EnsureResult:
    """Every (family, seed) of the profile in the cache, rendering the missing ones in ``jobs`` processes."""
    started = time.perf_counter()
    root = root or default_cache_root()
    names = list(families or sf.FAMILIES)
    unknown = [n for n in names if n not in sf.FAMILIES]
    if unknown:
        msg = f"unknown scenario families {unknown}; known: {', '.join(sf.FAMILIES)}"
        raise ValueError(msg)
    seq = [CachedSequence(f, s, sequence_dir(root, profile, f, s)) for f in names for s in (seeds or profile.seeds)]
    missing = [x for x in seq if not (x.path / "scenario.json").is_file()]
    # the costliest first, so the pool's last task is a short one
    missing.sort(key=lambda x: -sf.FAMILIES[x.family].frames * math.prod(_size(sf.FAMILIES[x.family], profile)))
    cpu = 0.0
    if missing:
        for x in missing:
            x.path.parent.mkdir(parents=True, exist_ok=True)
        tasks = [(x.family, x.seed, profile, str(x.path)) for x in missing]
        if jobs <= 1:
            results = map(_render_into_cache, tasks)
            for family, seed, c, w in results:
                cpu += c
                if progress:
                    progress(f"rendered {family}-s{seed}: {c:.1f} s CPU, {w:.1f} s")
        else:
            # spawned, not forked: a process that has run OpenCV's thread pool can hang a forked child in it
            spawn = multiprocessing.get_context("spawn")
            with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=spawn) as pool:
                for family, seed, c, w in pool.map(_render_into_cache, tasks):
                    cpu += c
                    if progress:
                        progress(f"rendered {family}-s{seed}: {c:.1f} s CPU, {w:.1f} s")
    return EnsureResult(seq, len(missing), cpu, time.perf_counter() - started)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile", choices=sorted(PROFILES), default="distribution")
    parser.add_argument("--families", nargs="+", choices=sorted(sf.FAMILIES), help="only these families")
    parser.add_argument("--seeds", nargs="+", type=int, help="only these seeds (default: the profile's)")
    parser.add_argument("--cache", type=Path, default=None, help=f"cache root (default ${CACHE_ENV} or "
                                                                 "~/.cache/epi_vo/scenarios)")
    parser.add_argument("--jobs", type=int, default=2, help="processes rendering at once (default 2)")
    args = parser.parse_args(argv)
    profile = PROFILES[args.profile]
    result = ensure(profile, args.families, args.seeds, args.cache, args.jobs, progress=print)
    seqs = result.sequences
    total_cpu = sum(float(s.info["render_cpu_s"]) for s in seqs)
    print(f"{len(seqs)} sequences under {seqs[0].path.parents[1]} ({result.rendered} rendered now, "
          f"{result.render_cpu_s:.0f} s CPU, {result.wall_s:.0f} s wall); rendering all of them takes "
          f"{total_cpu:.0f} s CPU: {total_cpu / 2 / 60:.1f} min on a quiet 2-core machine")
    return 0


if __name__ == "__main__":
    sys.exit(main())
