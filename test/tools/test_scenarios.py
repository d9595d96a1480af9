"""bags/scenarios.py, the scenario distribution: every family draws within its envelope, the faults within
the ranges real cameras show, the ground truth is the camera's motion in the images, the wheels measure
it with the drawn errors, the renders are deterministic and the cache follows the generator's source."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from epi_vo.io import bagio, tum
from epi_vo.tools.evaluation import poses_from_xyz_quat

SEEDS = range(8)


def test_fourteen_families_each_draw_within_their_envelope(scenario_generator: object) -> None:
    gen = scenario_generator
    assert len(gen.FAMILIES) >= 12
    for name, family in gen.FAMILIES.items():
        T = family.duration_s
        times = np.linspace(0.0, T, 25)
        for seed in SEEDS:
            scen = gen.build_scenario(name, seed)
            again = gen.build_scenario(name, seed)
            poses = np.stack([scen.drawn.pose_at(t) for t in times])
            np.testing.assert_array_equal(poses, np.stack([again.drawn.pose_at(t) for t in times]))
            assert scen.drawn.quads == again.drawn.quads and scen.faults == again.faults
            centres = poses[:, :3, 3]
            moved = float(np.linalg.norm(centres - centres[0], axis=1).max())
            if family.static:
                assert moved == 0.0, (name, seed)
            else:
                assert moved > 0.1, (name, seed, moved)
            f = scen.faults
            assert seed / 8 <= f.harshness < (seed + 1) / 8
            assert math.hypot(*f.principal_point_error_px) <= 4.0 + 1e-12
            assert abs(f.focal_error) <= 0.015 + 1e-12 and abs(f.k1) <= 0.05 + 1e-12
            assert f.line_time_us == 0.0 or 20.0 <= f.line_time_us <= 40.0
            assert 35 <= f.jpeg_quality <= 95 and 0.6 - 1e-9 <= min(f.gain) and max(f.gain) <= 1.6 + 1e-9
            assert family.envelope.exposure_ms[0] <= f.exposure_ms <= family.envelope.exposure_ms[1]
            assert all(0 < i < family.frames - 1 for i in f.dropped)
            if name == "floor_robot":
                h = scen.drawn.metric["camera_height_m"]
                pitch = scen.drawn.draws["pitch_deg"]
                assert 0.2 <= h <= 1.7 and 0.0 <= pitch <= 25.0
                assert scen.drawn.metric["wheel_odometry_topic"] == "/wheel/odom" and scen.drawn.wheel is not None
                # on the flat floor the camera stays at its height (world y 0) and keeps its pitch
                np.testing.assert_allclose(centres[:, 1], 0.0, atol=1e-12)
                optical_axis_down = np.degrees(np.arcsin(poses[:, 1, 2]))
                np.testing.assert_allclose(optical_axis_down, pitch, atol=1e-9)
            if name == "road":
                assert 1.2 <= scen.drawn.metric["camera_height_m"] <= 1.8
                turn = abs(scen.drawn.draws["turn_deg"])
                assert 25.0 <= turn <= 60.0
            if name == "long_loop":  # one full loop: it ends where it started, facing the same way
                end = scen.drawn.pose_at(T)
                np.testing.assert_allclose(end[[0, 2], 3], poses[0][[0, 2], 3], atol=1e-9)


def test_some_seeds_are_clean_and_some_harsh(scenario_generator: object) -> None:
    gen = scenario_generator
    faults = [gen.build_scenario("forward", seed).faults for seed in SEEDS]
    assert faults[0].read_noise < 1.2 and faults[0].jpeg_quality >= 88 and faults[0].exposure_ms < 3.0
    assert faults[7].read_noise > 2.5 and faults[7].jpeg_quality <= 60


def test_rolling_shutter_bands_cover_the_image_over_the_sensor_readout(scenario_generator: object) -> None:
    import camera_faults as cf

    gen = scenario_generator
    faults = dataclasses.replace(gen.build_scenario("fast", 0).faults, line_time_us=30.0)
    for height in (240, 360, 480):
        bands = cf.row_bands(height, faults)
        assert bands[0][0] == 0 and bands[-1][1] == height
        assert all(a[1] == b[0] for a, b in itertools.pairwise(bands))
        # a whole readout lasts 480 lines of 30 us, whatever the rendered height
        first, last = bands[0], bands[-1]
        spread = (last[2] - first[2]) / ((last[0] + last[1] - first[0] - first[1]) / 2.0)
        assert spread * height == pytest.approx(30e-6 * 480, rel=1e-9)
        assert first[2] == pytest.approx(-last[2])
    assert cf.row_bands(240, dataclasses.replace(faults, line_time_us=0.0)) == [(0, 240, 0.0)]


def _epipolar_px(K: np.ndarray, D: np.ndarray, T_i: np.ndarray, T_j: np.ndarray, pts_i: np.ndarray,
                 pts_j: np.ndarray) -> np.ndarray:
    """Sampson distance (px) of tracks i -> j under the relative pose of the ground truth, undistorted with the
    true lens."""
    a = cv2.undistortPoints(pts_i.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    b = cv2.undistortPoints(pts_j.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    T_j_i = np.linalg.inv(T_j) @ T_i
    t = T_j_i[:3, 3]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T_j_i[:3, :3]
    x1, x2 = np.column_stack([a, np.ones(len(a))]), np.column_stack([b, np.ones(len(b))])
    Ex1, Etx2 = x1 @ E.T, x2 @ E
    num = np.einsum("ij,ij->i", x2, Ex1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return np.sqrt(num / den) * K[0, 0]


def test_the_ground_truth_is_the_motion_the_images_show(scenario_subset: list) -> None:
    """KLT tracks two frames apart (the overlay's rows masked), undistorted with the *true* lens, lie on the
    epipolar lines of the ground truth's relative pose: median Sampson distance under 0.3 px on the median
    pair, for every family whose camera moves and that has no mover (a mover's tracks follow the mover)."""
    judged = 0
    for seq in scenario_subset:
        info = seq.info
        if info["static_camera"] or info["mover_share_median"] is not None:
            continue
        K, D = np.array(info["camera_true"]["K"]), np.array(info["camera_true"]["D"])
        stamps, p, q = tum.read_tum(seq.path / "groundtruth_tum.txt")
        T = poses_from_xyz_quat(p, q)
        with bagio.open_camera_bag(seq.path / "bag") as bag:
            images = [bag.usable_gray(f) for f in bag.iter_frames()]
        assert len(images) == len(stamps) == info["frames_written"]
        mask = np.full(images[0].shape, 255, np.uint8)
        band = max(12, images[0].shape[0] // 12)
        corner = info["faults"]["overlay_corner"]
        if corner is not None:  # the burnt-in timestamp does not move: its rows are left out
            rows = slice(0, band) if corner.startswith("top") else slice(-band, None)
            mask[rows] = 0
        medians = []
        for i in range(0, len(images) - 2, 2):
            pts = cv2.goodFeaturesToTrack(images[i], 400, 0.005, 5, mask=mask)
            nxt, ok, _ = cv2.calcOpticalFlowPyrLK(images[i], images[i + 2], pts, None, winSize=(15, 15), maxLevel=3)
            back, ok2, _ = cv2.calcOpticalFlowPyrLK(images[i + 2], images[i], nxt, None, winSize=(15, 15), maxLevel=3)
            good = (ok[:, 0] == 1) & (ok2[:, 0] == 1) & (np.linalg.norm(back - pts, axis=2)[:, 0] < 0.3)
            if good.sum() >= 20:
                medians.append(float(np.median(_epipolar_px(K, D, T[i], T[i + 2], pts[good], nxt[good]))))
        assert len(medians) >= 10, seq.family
        assert float(np.median(medians)) < 0.3, (seq.family, medians)
        judged += 1
    assert judged >= 10


def test_the_bag_declares_the_wrong_camera_and_carries_what_the_scale_sources_need(scenario_subset: list) -> None:
    by_family = {s.family: s for s in scenario_subset}
    for seq in scenario_subset:
        info = seq.info
        with bagio.open_camera_bag(seq.path / "bag") as bag:
            frame = next(iter(bag.iter_frames()))
            K = np.asarray(frame.camera_info_msg.k, dtype=np.float64).reshape(3, 3)
            D = np.asarray(frame.camera_info_msg.d, dtype=np.float64)
        np.testing.assert_allclose(K, info["camera_declared"]["K"], rtol=0, atol=1e-12)
        assert not D.any()  # the true lens' k1 is not declared
        true = np.array(info["camera_true"]["K"])
        pp = (K[:2, 2] - true[:2, 2]) * 640.0 / info["size"][0]
        np.testing.assert_allclose(pp, info["faults"]["principal_point_error_px"], atol=1e-9)
        assert K[0, 0] / true[0, 0] - 1.0 == pytest.approx(info["faults"]["focal_error"], abs=1e-12)
    assert by_family["road"].info["metric"]["camera_height_m"] > 1.0
    assert by_family["floor_robot"].info["metric"]["wheel_odometry_topic"] == "/wheel/odom"


def test_the_wheels_measure_the_robot_with_the_drawn_errors(scenario_subset: list) -> None:
    seq = next(s for s in scenario_subset if s.family == "floor_robot")
    info = seq.info
    T_base_camera = np.array(info["metric"]["T_base_camera"])
    with bagio.open_camera_bag(seq.path / "bag", wheel_topic="/wheel/odom") as bag:
        wheel = bag.read_wheel_odometry()
    assert wheel is not None and wheel.stamps_ns.size == info["wheel_messages"]
    assert np.all(np.diff(wheel.stamps_ns) == 20_000_000)  # 50 Hz
    stamps, p, q = tum.read_tum(seq.path / "groundtruth_tum.txt")
    T_c0_ci = poses_from_xyz_quat(p, q)
    base = np.stack([T_base_camera @ T @ np.linalg.inv(T_base_camera) for T in T_c0_ci])[:, :3, 3]
    gt_distance = float(np.linalg.norm(np.diff(base, axis=0), axis=1).sum())
    inside = (wheel.stamps_ns >= int(stamps[0] * 1e9)) & (wheel.stamps_ns <= int(stamps[-1] * 1e9))
    w = wheel.positions[inside]
    wheel_distance = float(np.linalg.norm(np.diff(w[:, :2], axis=0), axis=1).sum())
    scale_error = info["scene_and_trajectory"]["wheel_scale_error"]
    # the wheel stamps are 20 ms apart, the images' up to 40 ms past them: a fraction of a step either end
    assert wheel_distance / gt_distance == pytest.approx(1.0 + scale_error, abs=0.03)


def test_a_render_is_deterministic_and_the_cache_follows_the_source(scenario_generator: object, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    gen = scenario_generator
    tiny = gen.Profile("tiny", (6,), width=160, max_frames=4)
    first, second = tmp_path / "a", tmp_path / "b"
    info_a = gen.render_sequence("handheld", 6, tiny, first)
    info_b = gen.render_sequence("handheld", 6, tiny, second)
    assert info_a["faults"]["overlay_corner"] is not None  # a harsh seed: blur, rolling shutter, overlay ...
    assert (first / "bag" / "bag.mcap").read_bytes() == (second / "bag" / "bag.mcap").read_bytes()
    assert (first / "groundtruth_tum.txt").read_text() == (second / "groundtruth_tum.txt").read_text()
    timing = {"render_cpu_s", "render_wall_s"}
    assert {k: v for k, v in info_a.items() if k not in timing} == {k: v for k, v in info_b.items() if k not in timing}
    assert json.loads((first / "scenario.json").read_text())["frames_written"] == info_a["frames_written"]

    key = gen.generator_key(tiny)
    assert key != gen.generator_key(gen.PROFILES["subset"])
    copy = tmp_path / "generator"
    copy.mkdir()
    for name in gen.GENERATOR_FILES:
        shutil.copy(gen.HERE / name, copy / name)
    monkeypatch.setattr(gen, "HERE", copy)
    assert gen.generator_key(tiny) == key
    (copy / "camera_faults.py").write_text((copy / "camera_faults.py").read_text() + "\n# changed\n")
    assert gen.generator_key(tiny) != key
