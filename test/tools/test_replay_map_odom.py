"""``epi-vo replay`` with vo_node's ``map_frame_id`` (REP-105): /tf in output.mcap as the node broadcasts it."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader

from epi_vo.cli import main
from epi_vo.core.config import VoConfig
from epi_vo.core.transforms import invert_T, make_T, rotation_angle_deg, rotation_from_quat_xyzw

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "general_motion" / "bag"


def _T(t: object, r: object) -> np.ndarray:
    return make_T(rotation_from_quat_xyzw([r.x, r.y, r.z, r.w]), [t.x, t.y, t.z])  # type: ignore[attr-defined]


def _outputs(directory: Path, topic: str = "/vo/odometry"
             ) -> tuple[dict[int, np.ndarray], dict[int, dict[tuple[str, str], np.ndarray]]]:
    """``topic``'s poses (/vo/odometry or /vo/odometry/vo_units) and /tf transforms ((parent, child) -> T)
    by stamp (ns)."""
    odom: dict[int, np.ndarray] = {}
    tf: dict[int, dict[tuple[str, str], np.ndarray]] = {}
    with AnyReader([directory / "output.mcap"]) as reader:
        for connection, log_ns, raw in reader.messages():
            if connection.topic == topic:
                m = reader.deserialize(raw, connection.msgtype)
                odom[log_ns] = _T(m.pose.pose.position, m.pose.pose.orientation)
            elif connection.topic == "/tf":
                m = reader.deserialize(raw, connection.msgtype)
                tf[log_ns] = {(t.header.frame_id, t.child_frame_id): _T(t.transform.translation, t.transform.rotation)
                              for t in m.transforms}
    return odom, tf


def _replay_twice(tmp_path: Path, bag: Path, params: str) -> dict[str, Path]:
    """The bag replayed through the command line without and with ``map_frame_id: map``."""
    runs = {}
    for name, extra in (("jumping", ""), ("continuous", "    map_frame_id: map\n")):
        path = tmp_path / f"{name}.yaml"
        path.write_text("/**:\n  ros__parameters:\n    ba_window_keyframes: 4\n    ba_solver: inline\n" + params
                        + extra)
        assert main(["replay", str(bag), "--output", str(tmp_path / name), "--params", str(path),
                     "--no-progress"]) == 0
        stats = json.loads((tmp_path / name / "stats.json").read_text())
        assert stats["map_frame_id"] == ("map" if extra else "")
        runs[name] = tmp_path / name
    return runs


def test_in_metres_map_frame_id_keeps_the_odometry_continuous_and_tf_carries_the_corrections(
        tmp_path: Path) -> None:
    """The window on (4 keyframes, in line) on ground_robot with metres from the floor, replayed twice:
    without ``map_frame_id`` /tf carries odom -> base_link only, equal to /vo/odometry at every frame; with
    ``map_frame_id: map`` also map -> odom once the odometry is metric (none in VO units: a correction in VO
    units is no transform of a robot's map), the identity until the window's first correction in metres
    and not after, and map -> odom x /vo/odometry is the first replay's pose at every frame."""
    runs = _replay_twice(tmp_path, REPO / "bags" / "ground_robot" / "bag",
                         "    scale_source: ground_plane\n    camera_height_m: 0.45\n")
    (odom_a, tf_a), (odom_b, tf_b) = _outputs(runs["jumping"]), _outputs(runs["continuous"])
    metric = {int(r["stamp_ns"]) for r in map(json.loads, (runs["jumping"] / "frames.jsonl").read_text().splitlines())
              if r["metric_scale"] and r["has_pose"]}
    assert sorted(odom_a) == sorted(odom_b) and sorted(tf_a) == sorted(tf_b) and len(metric) >= 200
    moved = []
    for stamp in sorted(tf_a):
        assert set(tf_a[stamp]) == {("odom", "base_link")}
        assert set(tf_b[stamp]) == ({("odom", "base_link"), ("map", "odom")} if stamp in metric
                                    else {("odom", "base_link")})
        np.testing.assert_allclose(tf_a[stamp]["odom", "base_link"], odom_a[stamp], atol=1e-12)
        np.testing.assert_allclose(tf_b[stamp]["odom", "base_link"], odom_b[stamp], atol=1e-12)
        if stamp in metric:
            M = tf_b[stamp]["map", "odom"]
            np.testing.assert_allclose(M @ odom_b[stamp], odom_a[stamp], atol=1e-9)
            moved.append(rotation_angle_deg(M[:3, :3]) > 1e-6 or float(np.linalg.norm(M[:3, 3])) > 1e-9)
    assert not moved[0] and moved[-1] and sum(moved) >= 30, sum(moved)
    stamps = sorted(s for s in tf_a if s in metric)
    first = moved.index(True)
    jump = invert_T(odom_a[stamps[first - 1]]) @ odom_a[stamps[first]]
    step = invert_T(odom_b[stamps[first - 1]]) @ odom_b[stamps[first]]
    assert float(np.linalg.norm(jump[:3, 3] - step[:3, 3])) > 1e-4  # the jump is the correction's (0.5 mm)


def test_in_vo_units_tf_holds_the_position_and_the_vo_unit_odometry_stays_continuous(tmp_path: Path) -> None:
    """The window on general_motion in VO units: /tf carries odom -> base_link only, with or without
    ``map_frame_id`` (the position held where tracking started, as /vo/odometry); /vo/odometry/vo_units
    jumps by the window's corrections without ``map_frame_id`` and stays continuous with it."""
    runs = _replay_twice(tmp_path, BAG, "")
    (held_a, tf_a), (held_b, tf_b) = _outputs(runs["jumping"]), _outputs(runs["continuous"])
    vo_a, _ = _outputs(runs["jumping"], "/vo/odometry/vo_units")
    vo_b, _ = _outputs(runs["continuous"], "/vo/odometry/vo_units")
    assert sorted(vo_a) == sorted(vo_b) == sorted(tf_a) == sorted(tf_b) == sorted(held_a) and len(vo_a) == 52
    for stamp in sorted(vo_a):
        for tf, held in ((tf_a, held_a), (tf_b, held_b)):
            assert set(tf[stamp]) == {("odom", "base_link")}
            np.testing.assert_allclose(tf[stamp]["odom", "base_link"], held[stamp], atol=1e-12)
            np.testing.assert_array_equal(held[stamp][:3, 3], np.zeros(3))
    differs = [not np.allclose(vo_a[s], vo_b[s], atol=1e-9) for s in sorted(vo_a)]
    assert not differs[0] and differs[-1] and sum(differs) >= 30, sum(differs)  # once the window is full
    first = differs.index(True)
    stamps = sorted(vo_a)
    jump = invert_T(vo_a[stamps[first - 1]]) @ vo_a[stamps[first]]
    step = invert_T(vo_b[stamps[first - 1]]) @ vo_b[stamps[first]]
    assert float(np.linalg.norm(jump[:3, 3] - step[:3, 3])) > 0.005  # the jump is the correction's


def test_a_bad_map_frame_id_in_the_parameter_file_is_an_error_naming_it(tmp_path: Path, capsys: object) -> None:
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    map_frame_id: '  '\n")
    assert main(["replay", str(BAG), "--output", str(tmp_path / "o"), "--params", str(params), "--no-progress"]) == 2
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert "map_frame_id" in err and not (tmp_path / "o" / "stats.json").exists()


def test_the_default_config_is_unchanged_by_the_tf_output(tmp_path: Path) -> None:
    """Without the window there is no correction: map -> odom stays the identity and the odometry is the
    same with or without ``map_frame_id``."""
    from epi_vo.tools.replay import run_replay

    cfg = dataclasses.replace(VoConfig(), scale_source="ground_plane", camera_height_m=0.45)
    bag = REPO / "bags" / "ground_robot" / "bag"
    run_replay(bag, tmp_path / "a", cfg)
    run_replay(bag, tmp_path / "b", cfg, map_frame_id="map")
    (odom_a, _), (odom_b, tf_b) = _outputs(tmp_path / "a"), _outputs(tmp_path / "b")
    assert sum(("map", "odom") in tf for tf in tf_b.values()) >= 200
    for stamp, T in odom_a.items():
        np.testing.assert_array_equal(odom_b[stamp], T)
        if ("map", "odom") in tf_b.get(stamp, {}):
            np.testing.assert_array_equal(tf_b[stamp]["map", "odom"], np.eye(4))


def test_map_frame_id_values() -> None:
    from epi_vo.io.node_options import node_option_problems

    assert node_option_problems({"map_frame_id": ""}) == [] and node_option_problems({"map_frame_id": "map"}) == []
    assert node_option_problems({"map_frame_id": " map"}) == [
        "map_frame_id=' map' ('' or a frame name: whitespace or a control character)"]
    assert node_option_problems({"map_frame_id": 3}) == ["map_frame_id=3 ('' or a frame name: not a string)"]
    assert node_option_problems({"map_frame_id": "odom"}) == [
        "map_frame_id='odom' (must differ from frame_id and child_frame_id)"]
    assert node_option_problems({"map_frame_id": "world", "frame_id": "world"}) != []
