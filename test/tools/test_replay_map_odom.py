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


def _outputs(directory: Path) -> tuple[dict[int, np.ndarray], dict[int, dict[tuple[str, str], np.ndarray]]]:
    """/vo/odometry poses and /tf transforms ((parent, child) -> T) by stamp (ns)."""
    odom: dict[int, np.ndarray] = {}
    tf: dict[int, dict[tuple[str, str], np.ndarray]] = {}
    with AnyReader([directory / "output.mcap"]) as reader:
        for connection, log_ns, raw in reader.messages():
            if connection.topic == "/vo/odometry":
                m = reader.deserialize(raw, connection.msgtype)
                odom[log_ns] = _T(m.pose.pose.position, m.pose.pose.orientation)
            elif connection.topic == "/tf":
                m = reader.deserialize(raw, connection.msgtype)
                tf[log_ns] = {(t.header.frame_id, t.child_frame_id): _T(t.transform.translation, t.transform.rotation)
                              for t in m.transforms}
    return odom, tf


def test_replay_writes_tf_and_with_map_frame_id_keeps_the_odometry_continuous(tmp_path: Path) -> None:
    """The window on (4 keyframes, in line) on general_motion, replayed twice through the command line:
    without ``map_frame_id`` /tf carries odom -> base_link only, equal to /vo/odometry at every frame; with
    ``map_frame_id: map`` in the parameter file also map -> odom, the identity until the window's first
    correction and not after, and map -> odom x /vo/odometry is the first replay's pose at every frame;
    stats.json says which."""
    runs = {}
    for name, extra in (("jumping", ""), ("continuous", "    map_frame_id: map\n")):
        params = tmp_path / f"{name}.yaml"
        params.write_text("/**:\n  ros__parameters:\n    ba_window_keyframes: 4\n    ba_solver: inline\n" + extra)
        assert main(["replay", str(BAG), "--output", str(tmp_path / name), "--params", str(params),
                     "--no-progress"]) == 0
        runs[name] = _outputs(tmp_path / name)
        stats = json.loads((tmp_path / name / "stats.json").read_text())
        assert stats["map_frame_id"] == ("map" if extra else "")
    (odom_a, tf_a), (odom_b, tf_b) = runs["jumping"], runs["continuous"]
    assert sorted(odom_a) == sorted(odom_b) == sorted(tf_a) == sorted(tf_b) and len(odom_a) == 52
    moved = []
    for stamp in sorted(odom_a):
        assert set(tf_a[stamp]) == {("odom", "base_link")}
        assert set(tf_b[stamp]) == {("odom", "base_link"), ("map", "odom")}
        np.testing.assert_allclose(tf_a[stamp]["odom", "base_link"], odom_a[stamp], atol=1e-12)
        np.testing.assert_allclose(tf_b[stamp]["odom", "base_link"], odom_b[stamp], atol=1e-12)
        M = tf_b[stamp]["map", "odom"]
        np.testing.assert_allclose(M @ odom_b[stamp], odom_a[stamp], atol=1e-9)
        moved.append(rotation_angle_deg(M[:3, :3]) > 1e-6 or float(np.linalg.norm(M[:3, 3])) > 1e-9)
    assert not moved[0] and moved[-1] and sum(moved) >= 30, sum(moved)  # first correction at frame 18
    first = moved.index(True)
    stamps = sorted(odom_a)
    jump = invert_T(odom_a[stamps[first - 1]]) @ odom_a[stamps[first]]
    step = invert_T(odom_b[stamps[first - 1]]) @ odom_b[stamps[first]]
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

    run_replay(BAG, tmp_path / "a", VoConfig())
    run_replay(BAG, tmp_path / "b", dataclasses.replace(VoConfig()), map_frame_id="map")
    (odom_a, _), (odom_b, tf_b) = _outputs(tmp_path / "a"), _outputs(tmp_path / "b")
    for stamp, T in odom_a.items():
        np.testing.assert_array_equal(odom_b[stamp], T)
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
