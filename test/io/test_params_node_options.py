"""The node's own parameters without rclpy (epi_vo.io.node_options) and their place in `epi-vo params` /
config/epi_vo.yaml (epi_vo.io.params)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from epi_vo.core.config import PIPELINE_NAMES, VoConfig
from epi_vo.core.errors import ConfigError
from epi_vo.io.node_options import (
    NODE_DOCS,
    NODE_OPTION_NAMES,
    ImageTransport,
    NodeOptions,
    QosReliability,
    apply_changes,
    changed_names,
    is_read_only,
    make_node_options,
)
from epi_vo.io.params import load_config, load_params_file, to_params_yaml

REPO = Path(__file__).resolve().parents[2]


def test_every_option_has_a_doc_line_and_the_defaults_a_robot_stack_expects() -> None:
    assert set(NODE_DOCS) == set(NODE_OPTION_NAMES)
    assert all(NODE_DOCS[n].strip() for n in NODE_OPTION_NAMES)
    opts = NodeOptions()
    assert (opts.frame_id, opts.child_frame_id, opts.image_transport, opts.hardware_id) == \
        ("odom", "base_link", "auto", "")
    assert opts.tf_timeout_s > 0 and opts.publish_tf


def test_read_only_split() -> None:
    for name in ("frame_id", "child_frame_id", "camera_xyz", "image_transport", "qos_reliability", "qos_depth",
                 "tf_timeout_s", "publish_tf", "hardware_id", "scale_source", "wheel_odometry_topic"):
        assert is_read_only(name), name
    for name in ("max_features", "frontend", "min_inliers", "queue_size", "watchdog_timeout_s"):
        assert not is_read_only(name), name


def test_make_node_options_known_answer_and_array_values() -> None:
    import array

    opts = make_node_options({"camera_xyz": array.array("d", [0.1, 0.0, 0.5]), "camera_rpy": [0, 0, 1],
                              "qos_depth": 7, "watchdog_timeout_s": 2, "image_transport": "raw"})
    assert opts == dataclasses.replace(NodeOptions(), camera_xyz=(0.1, 0.0, 0.5), camera_rpy=(0.0, 0.0, 1.0),
                                       qos_depth=7, watchdog_timeout_s=2.0, image_transport="raw")
    assert isinstance(opts.watchdog_timeout_s, float)
    # the modes are converted once, here: the node compares members
    assert opts.image_transport is ImageTransport.RAW and opts.qos_reliability is QosReliability.BEST_EFFORT
    assert make_node_options({"qos_reliability": "reliable"}).qos_reliability is QosReliability.RELIABLE


def test_make_node_options_names_every_bad_value() -> None:
    with pytest.raises(ConfigError) as info:
        make_node_options({"image_transport": "theora", "camera_xyz": [1.0, float("nan"), 0.0], "camera_rpy": "up",
                           "qos_depth": 0, "tf_timeout_s": -1.0, "watchdog_timeout_s": 0.0, "frame_id": " "})
    text = str(info.value)
    assert text.startswith("invalid vo_node parameters: ")
    for part in ("image_transport='theora' (choose one of auto, raw, compressed)",
                 "camera_xyz=[1.0, nan, 0.0] (expected 3 finite numbers)", "camera_rpy='up' (expected 3 finite",
                 "qos_depth=0 (an integer, minimum 1)", "tf_timeout_s=-1.0 (0 to 3600 s)",
                 "watchdog_timeout_s=0.0 (must be > 0)",
                 "frame_id=' ' (not a frame name: whitespace or a control character)"):
        assert part in text, (part, text)


def test_apply_changes_accepts_a_valid_knob() -> None:
    cfg, opts = apply_changes(VoConfig(), NodeOptions(), {"max_features": 300, "queue_size": 4, "use_sim_time": True})
    assert cfg == dataclasses.replace(VoConfig(), max_features=300)
    assert opts == dataclasses.replace(NodeOptions(), queue_size=4)
    assert changed_names(VoConfig(), cfg) == ["max_features=300"]
    assert changed_names(cfg, cfg) == []


def test_apply_changes_refuses_with_every_reason() -> None:
    with pytest.raises(ConfigError) as info:
        apply_changes(VoConfig(), NodeOptions(), {"frontend": "sift", "max_features": 10, "frame_id": "map",
                                                  "queue_size": 0})
    text = str(info.value)
    for part in ("frame_id is read-only (restart the node to change it)",
                 "frontend='sift' (choose one of klt, orb)", "max_features=10 (minimum 20)",
                 "queue_size=0 (an integer, minimum 1)"):
        assert part in text, (part, text)


def test_apply_changes_checks_the_whole_config_not_only_the_change() -> None:
    """An even KLT window is refused whatever else is valid: the same validate() as at start-up."""
    with pytest.raises(ConfigError, match=r"klt_window_px=16 \(must be odd\)"):
        apply_changes(VoConfig(), NodeOptions(), {"klt_window_px": 16})


def test_params_yaml_with_node_options_has_one_comment_each_and_round_trips(tmp_path: Path) -> None:
    text = to_params_yaml(VoConfig(), node=NodeOptions())
    lines = text.splitlines()
    assert lines[:2] == ["/**:", "  ros__parameters:"]
    for name in (*NODE_OPTION_NAMES, *PIPELINE_NAMES):
        (i,) = [k for k, line in enumerate(lines) if line.startswith(f"    {name}:")]
        assert lines[i - 1].startswith("    # "), name
    assert f"    # {NODE_DOCS['frame_id']} [read-only: restart to change]" in lines
    assert f"    # {NODE_DOCS['queue_size']}" in lines
    assert "    camera_xyz: [0.0, 0.0, 0.0]" in lines and "    hardware_id: ''" in lines
    path = tmp_path / "params.yaml"
    path.write_text(text)
    params = load_params_file(path)
    assert make_node_options({k: v for k, v in params.items() if k in NODE_OPTION_NAMES}) == NodeOptions()
    assert load_config(path) == VoConfig()


def test_config_file_is_the_params_output() -> None:
    """config/epi_vo.yaml is `epi-vo params` (regenerate with `.venv/bin/epi-vo params > config/epi_vo.yaml`)."""
    out = subprocess.run([sys.executable, "-m", "epi_vo.cli", "params"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert (REPO / "config" / "epi_vo.yaml").read_text() == out.stdout
    block = yaml.safe_load(out.stdout)["/**"]["ros__parameters"]
    assert set(block) == set(NODE_OPTION_NAMES) | set(PIPELINE_NAMES)


def test_a_node_option_misspelt_in_a_params_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    path.write_text("/**:\n  ros__parameters:\n    tf_timeout: 1.0\n    tf_timeout_s: 1.0\n")
    with pytest.raises(ConfigError, match=r"unknown parameters: tf_timeout \(did you mean"):
        load_config(path)
