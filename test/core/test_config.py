"""Tests for epi_vo.core.config: defaults, validation of every field at once, ROS 2 parameter files."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import pytest

from epi_vo.core.config import (
    FRONTENDS,
    NODE_PARAMETER_NAMES,
    ROBUST_METHODS,
    BaSolver,
    Frontend,
    RobustMethod,
    ScaleSourceKind,
    VoConfig,
    config_fields,
    field_doc,
    from_dict,
    is_parameter_name,
    validate,
)
from epi_vo.core.errors import ConfigError, EpiVoError
from epi_vo.io.params import load_config, load_params_file, to_params_yaml

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULTS_YAML = REPO_ROOT / "config" / "epi_vo.yaml"


def _write(tmp_path: Path, text: str, name: str = "params.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# --- defaults ------------------------------------------------------------------------------------------


def test_defaults_validate() -> None:
    cfg = VoConfig()
    validate(cfg)  # raises on any bad default
    assert cfg.essential_method == "magsac"
    assert cfg.max_features == 200
    assert cfg.klt_window_px % 2 == 1


def test_every_field_has_a_doc_line_and_a_typed_default() -> None:
    for f in config_fields():
        assert field_doc(f).strip(), f"{f.name} has no doc line"
        mode = f.metadata["mode"]
        if mode is not None:  # a mode: a member of its enum, whose texts are the choices
            assert isinstance(f.default, mode) and f.metadata["choices"] == tuple(m.value for m in mode)
        else:
            assert type(f.default) in (int, float, str, bool), f"{f.name} default {f.default!r}"
    assert {"essential_method", "homography_method"} <= {f.name for f in config_fields()}
    assert "magsac" in ROBUST_METHODS and "klt" in FRONTENDS


def test_a_mode_given_as_text_is_its_member_and_a_text_no_member_has_is_named() -> None:
    """Modes are converted once, where the config is made (a constructor, ``from_dict``, the node's
    parameters): code compares members, and a member still writes as its text."""
    cfg = from_dict({"frontend": "orb", "scale_source": "ground_plane", "camera_height_m": 1.0,
                     "essential_method": "ransac", "ba_solver": "inline"})
    assert cfg.frontend is Frontend.ORB and cfg.scale_source is ScaleSourceKind.GROUND_PLANE
    assert cfg.essential_method is RobustMethod.RANSAC and cfg.ba_solver is BaSolver.INLINE
    assert VoConfig(frontend="orb").frontend is Frontend.ORB  # type: ignore[arg-type]
    assert json.dumps({"frontend": cfg.frontend}) == '{"frontend": "orb"}'
    assert cfg.scale_source.metric and not ScaleSourceKind.NONE.metric
    with pytest.raises(ConfigError, match=r"frontend='sift' \(choose one of klt, orb\).*ba_solver=2 \(choose one of "
                       r"process, inline\)"):
        from_dict({"frontend": "sift", "ba_solver": 2})


def test_config_is_frozen() -> None:
    cfg = VoConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.max_features = 10  # type: ignore[misc]


@pytest.mark.skipif(not DEFAULTS_YAML.exists(),
                    reason=f"{DEFAULTS_YAML.relative_to(REPO_ROOT)} not written yet (created by another change)")
def test_defaults_equal_config_yaml() -> None:
    assert load_config(DEFAULTS_YAML) == VoConfig()


@pytest.mark.skipif(not DEFAULTS_YAML.exists(),
                    reason=f"{DEFAULTS_YAML.relative_to(REPO_ROOT)} not written yet (created by another change)")
def test_config_yaml_lists_every_field() -> None:
    params = load_params_file(DEFAULTS_YAML)
    missing = [f.name for f in config_fields() if f.name not in params]
    assert not missing, f"config/epi_vo.yaml lacks {missing}"


# --- from_dict / validate ------------------------------------------------------------------------------------


def test_a_camera_height_the_code_cannot_use_is_refused() -> None:
    """5e-324 m passed '> 0' and then raised 'math domain error' in the floor's scale (log of the height over
    the floor's, which underflowed to 0): replay exit 1, live 89 of 120 frames 'internal error'. A camera
    height is a physical length: 1 cm to 100 m, or 0 (not set)."""
    for bad in (5e-324, 0.009, 101.0):
        with pytest.raises(ConfigError, match=rf"camera_height_m={bad!r} \((minimum 0.01, or 0|maximum 100.0)\)"):
            validate(dataclasses.replace(VoConfig(), scale_source="none", camera_height_m=bad))
    validate(dataclasses.replace(VoConfig(), camera_height_m=0.0))
    validate(dataclasses.replace(VoConfig(), scale_source="ground_plane", camera_height_m=0.01))


def test_from_dict_known_answer() -> None:
    cfg = from_dict({"max_features": 500, "frontend": "orb", "ransac_threshold_px": 0.75})
    assert cfg == dataclasses.replace(VoConfig(), max_features=500, frontend="orb", ransac_threshold_px=0.75)


def test_from_dict_keeps_base() -> None:
    base = dataclasses.replace(VoConfig(), min_inliers=40)
    assert from_dict({}, base=base) is not None
    assert from_dict({}, base=base).min_inliers == 40
    assert from_dict({"grid_rows": 4}, base=base) == dataclasses.replace(base, grid_rows=4)


def test_from_dict_reports_every_bad_field_at_once() -> None:
    bad = {
        "max_features": -5,
        "essential_method": "bogus_sac",
        "klt_window_px": 20,
        "score_sigma_px": "one",
        "rh_threshold": math.nan,
    }
    with pytest.raises(ConfigError) as info:
        from_dict(bad)
    msg = str(info.value)
    assert msg.startswith("invalid epi_vo parameters: ")
    assert "max_features=-5 (minimum 20)" in msg
    assert "essential_method='bogus_sac' (choose one of magsac, ransac" in msg
    assert "klt_window_px=20 (must be odd)" in msg
    assert "score_sigma_px='one' (expected float)" in msg
    assert "rh_threshold=nan (not finite)" in msg
    good_names = {f.name for f in config_fields()} - set(bad)
    assert not any(re.search(rf"\b{name}=", msg) for name in good_names)


@pytest.mark.parametrize(("name", "value", "fragment"), [
    ("ransac_confidence", 1.5, "ransac_confidence=1.5 (maximum 0.999999)"),
    ("frontend", "sift", "frontend='sift' (choose one of klt, orb)"),
    ("min_inliers", 25.0, "min_inliers=25.0 (expected int)"),
    ("max_features", True, "max_features=True (expected int)"),
    ("ransac_threshold_px", True, "ransac_threshold_px=True (expected float)"),
    ("lost_position_variance", math.inf, "lost_position_variance=inf (not finite)"),
])
def test_from_dict_single_bad_value(name: str, value: object, fragment: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(fragment)):
        from_dict({name: value})


@pytest.mark.parametrize("value", ["21", None])
def test_from_dict_wrong_type_for_klt_window(value: object) -> None:
    with pytest.raises(ConfigError, match=r"klt_window_px=.*\(expected int\)"):
        from_dict({"klt_window_px": value})


@pytest.mark.parametrize("value", ["false", 0, 1, None])
def test_from_dict_a_switch_takes_true_or_false_only(value: object) -> None:
    with pytest.raises(ConfigError, match=r"ba_wait=.*\(expected bool\)"):
        from_dict({"ba_wait": value})
    assert from_dict({"ba_wait": False}).ba_wait is False


def test_from_dict_unknown_parameter() -> None:
    with pytest.raises(ConfigError, match=r"unknown parameters: max_featurez \(did you mean max_features\?\)$"):
        from_dict({"max_featurez": 300})
    with pytest.raises(ConfigError, match=r"unknown parameters: zzz$"):  # nothing close: no suggestion
        from_dict({"zzz": 300})
    # Unknown names and bad values are reported together.
    with pytest.raises(ConfigError, match=r"min_inliers=2 \(minimum 8\).*unknown parameters: a_knob, b_knob"):
        from_dict({"b_knob": 1, "min_inliers": 2, "a_knob": 2})


def test_from_dict_a_removed_parameter_says_what_replaced_it() -> None:
    with pytest.raises(ConfigError, match=r"unknown parameters: rotation_only_parallax_deg \(removed: pure "
                                          r"rotation is chosen by GRIC"):
        from_dict({"rotation_only_parallax_deg": 0.3})
    with pytest.raises(ConfigError, match=r"init_max_direction_sigma_deg \(removed: a first map is not refused "
                                          r"for E's direction sigma.*init_max_rotation_sigma_deg \(removed"):
        from_dict({"init_max_rotation_sigma_deg": 0.25, "init_max_direction_sigma_deg": 8.0})


def test_from_dict_widens_ints_to_floats() -> None:
    cfg = from_dict({"ransac_threshold_px": 2, "kf_max_interval_s": 3})
    assert cfg.ransac_threshold_px == 2.0 and type(cfg.ransac_threshold_px) is float
    assert type(cfg.kf_max_interval_s) is float
    validate(cfg)


def test_config_error_is_an_epi_vo_error() -> None:
    with pytest.raises(EpiVoError):
        from_dict({"max_features": 0})


# --- ROS 2 parameter files ------------------------------------------------------------------------------------


@pytest.mark.parametrize("node_key", ["/**", "vo_node", "/vo_node"])
def test_load_params_file_node_keys(tmp_path: Path, node_key: str) -> None:
    path = _write(tmp_path, f"{node_key}:\n  ros__parameters:\n    max_features: 450\n    frame_id: map\n")
    assert load_params_file(path) == {"max_features": 450, "frame_id": "map"}
    assert load_config(path) == dataclasses.replace(VoConfig(), max_features=450)  # node parameter: ignored


def test_load_params_file_other_node_name(tmp_path: Path) -> None:
    path = _write(tmp_path, "replay:\n  ros__parameters:\n    grid_rows: 3\n")
    assert load_params_file(path, node_name="replay") == {"grid_rows": 3}
    with pytest.raises(ConfigError, match=r"no '/\*\*' or 'vo_node' block with ros__parameters"):
        load_params_file(path)


def test_load_params_file_merges_wildcard_and_node_blocks(tmp_path: Path) -> None:
    path = _write(tmp_path, "/**:\n  ros__parameters:\n    grid_rows: 3\n    grid_cols: 5\n"
                            "vo_node:\n  ros__parameters:\n    grid_cols: 7\n")
    assert load_params_file(path) == {"grid_rows": 3, "grid_cols": 7}


def test_load_params_file_invalid_yaml(tmp_path: Path) -> None:
    path = _write(tmp_path, "/**:\n  ros__parameters:\n    max_features: [300\n")
    with pytest.raises(ConfigError, match=rf"parameter file {re.escape(str(path))} is not valid YAML"):
        load_params_file(path)


def test_load_params_file_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match=rf"cannot read parameter file {re.escape(str(path))}: No such file"):
        load_params_file(path)


@pytest.mark.parametrize("text", ["vo_node:\n  max_features: 300\n", "max_features: 300\n"])
def test_load_params_file_without_ros_parameters(tmp_path: Path, text: str) -> None:
    with pytest.raises(ConfigError, match=r"no '/\*\*' or 'vo_node' block with ros__parameters"):
        load_params_file(_write(tmp_path, text))


@pytest.mark.parametrize("text", ["- 1\n- 2\n", "just a string\n"])
def test_load_params_file_not_a_mapping(tmp_path: Path, text: str) -> None:
    with pytest.raises(ConfigError, match="expected a mapping of node names to ros__parameters"):
        load_params_file(_write(tmp_path, text))


def test_load_config_rejects_bad_values_in_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "/**:\n  ros__parameters:\n    max_features: 5\n    frontend: sift\n")
    with pytest.raises(ConfigError, match=r"frontend='sift'.*max_features=5"):
        load_config(path)


def test_load_config_none_is_defaults() -> None:
    assert load_config(None) == VoConfig()


def test_load_config_reads_exponent_floats_like_ros(tmp_path: Path) -> None:
    path = _write(tmp_path, "/**:\n  ros__parameters:\n    lost_position_variance: 1.0e4\n    corner_quality: 5e-3\n")
    cfg = load_config(path)
    assert cfg.lost_position_variance == 1.0e4
    assert cfg.corner_quality == 5e-3


# --- writing parameter files ---------------------------------------------------------------------------------


@pytest.mark.parametrize("cfg", [
    VoConfig(),
    dataclasses.replace(VoConfig(), frontend="orb", max_features=1234, corner_quality=1e-5, klt_window_px=31,
                        lost_position_variance=1e12, rh_threshold=0.5, homography_method="ransac"),
])
def test_to_params_yaml_round_trip(tmp_path: Path, cfg: VoConfig) -> None:
    path = _write(tmp_path, to_params_yaml(cfg))
    assert load_config(path) == cfg


def test_to_params_yaml_layout_and_extra(tmp_path: Path) -> None:
    text = to_params_yaml(VoConfig(), extra={"image_topic": "/camera/image_raw", "publish_tf": True})
    lines = text.splitlines()
    assert lines[:2] == ["/**:", "  ros__parameters:"]
    assert "    # features kept per keyframe, spread over the grid [20 to 5000]" in lines  # its range
    assert "    max_features: 200" in lines
    assert "    essential_method: magsac" in lines
    assert "..." not in text
    params = load_params_file(_write(tmp_path, text))
    assert params["image_topic"] == "/camera/image_raw"
    assert params["publish_tf"] is True
    assert len(params) == len(config_fields()) + 2


# --- names that are not parameters ---------------------------------------------------------------------------


def test_unknown_names_in_a_params_file_are_errors_with_the_closest_name(tmp_path: Path) -> None:
    path = _write(tmp_path, "vo_node:\n  ros__parameters:\n    max_featurs: 50\n    kf_min_inlier: 30\n"
                            "    colour: red\n    frame_idd: map\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == (
        f"parameter file {path}: invalid epi_vo parameters: unknown parameters: colour, frame_idd (did you mean "
        "frame_id?), kf_min_inlier (did you mean kf_min_inliers?), max_featurs (did you mean max_features?)")


def test_unknown_names_and_bad_values_are_reported_together(tmp_path: Path) -> None:
    path = _write(tmp_path, "/**:\n  ros__parameters:\n    min_inliers: 2\n    max_featurs: 50\n")
    with pytest.raises(ConfigError, match=r"min_inliers=2 \(minimum 8\); unknown parameters: max_featurs \(did you "
                                          r"mean max_features\?\)$"):
        load_config(path)


def test_node_and_ros_parameters_are_valid_names_in_a_params_file(tmp_path: Path) -> None:
    """The ROS form with the node's own parameters (config/epi_vo.yaml plus NodeOptions): accepted, ignored."""
    node_params = "".join(f"    {name}: {value}\n" for name, value in [
        ("frame_id", "odom"), ("child_frame_id", "base_link"), ("map_frame_id", "map"),
        ("camera_xyz", "[0.2, 0.0, 0.5]"),
        ("camera_rpy", "[0.0, 0.0, 0.0]"), ("image_transport", "compressed"), ("qos_reliability", "reliable"),
        ("qos_depth", 5), ("queue_size", 2), ("process_every_frame", "true"), ("queue_max_mb", 64.0),
        ("publish_tf", "false"),
        ("publish_debug_image", "false"), ("path_max_length", 100), ("watchdog_timeout_s", 1.0),
        ("camera_info_wait_s", 0.2), ("hardware_id", "cam"), ("tf_timeout_s", 2.0), ("use_sim_time", "true"),
        ("start_type_description_service", "false"),
        ("qos_overrides./camera/image_raw.subscription.depth", 3)])
    assert len(NODE_PARAMETER_NAMES) == 18 and all(f"    {n}:" in node_params for n in NODE_PARAMETER_NAMES)
    path = _write(tmp_path, "vo_node:\n  ros__parameters:\n    max_features: 300\n" + node_params
                  + "    qos_overrides:\n      /camera/camera_info:\n        subscription:\n          depth: 4\n")
    assert load_config(path) == dataclasses.replace(VoConfig(), max_features=300)


@pytest.mark.parametrize(("name", "ok"), [("max_features", True), ("frame_id", True), ("use_sim_time", True),
                                          ("qos_overrides", True), ("qos_overrides./a.publisher.depth", True),
                                          ("image_topic", False), ("qos_override", False), ("", False), (3, False)])
def test_is_parameter_name(name: object, ok: bool) -> None:
    assert is_parameter_name(name) is ok


def test_node_parameter_names_match_the_node_options() -> None:
    """config.NODE_PARAMETER_NAMES (no rclpy) lists exactly the node's own options (epi_vo/node.py)."""
    pytest.importorskip("rclpy")
    from epi_vo.ros.node import NodeOptions

    assert set(NODE_PARAMETER_NAMES) == {f.name for f in dataclasses.fields(NodeOptions)}


def test_params_file_that_is_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "params.yaml"
    path.write_bytes(b"/**:\n  ros__parameters:\n    max_features: 300 # \xe9t\xe9\n")
    with pytest.raises(ConfigError, match=rf"parameter file {re.escape(str(path))} is not UTF-8 text \(byte 0xe9 at "
                                          r"offset 48\)$"):
        load_config(path)


def test_params_path_that_is_a_directory(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=rf"cannot read parameter file {re.escape(str(tmp_path))}: Is a directory"):
        load_config(tmp_path)


def test_a_live_node_is_told_when_the_window_would_stall_its_frames() -> None:
    from epi_vo.core.config import live_advice

    assert live_advice(VoConfig()) == []  # no window
    assert live_advice(from_dict({"ba_window_keyframes": 8, "ba_wait": False})) == []
    (advice,) = live_advice(from_dict({"ba_window_keyframes": 8}))
    assert "ba_wait: false" in advice and "waits" in advice
