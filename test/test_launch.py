"""The launch file, the RViz2 config and the Foxglove layout agree with the node and with what setup.py installs.

The ``launch`` / ``launch_ros`` packages are not on PyPI, so ``launch/vo.launch.py`` is imported here with
small stand-ins for the names it uses (same keyword signatures as Jazzy's), which record what they are given.
:func:`evaluate` then resolves the description as ``ros2 launch`` would for given arguments: launch
configurations, path joins, the package share directory, ``IfCondition`` and typed ``ParameterValue``.
What ``ros2 launch`` does with the result (starting processes) is not run here.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import json
import os
import re
import runpy
import sys
import types
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
LAUNCH_FILE = REPO / "launch" / "vo.launch.py"
RVIZ_FILE = REPO / "config" / "epi_vo.rviz"
FOXGLOVE_FILE = REPO / "config" / "foxglove_layout.json"
NODE_SOURCE = REPO / "epi_vo" / "ros" / "node.py"
PREFIX = "/opt/ws/install/epi_vo"  # stands for the install prefix FindPackageShare would find

# What the displays must show: the node's outputs (relative names, so namespaces apply).
SHOWN_TOPICS = {"odometry": "vo/odometry", "odometry_vo_units": "vo/odometry/vo_units", "path": "vo/path",
                "points": "vo/points", "debug_image": "vo/debug_image"}


# --------------------------------------------------------------------------------------------------------
# Stand-ins for launch / launch_ros
# --------------------------------------------------------------------------------------------------------


class Recorded:
    """Base of the stand-ins: keeps the constructor arguments for :func:`evaluate` and :func:`configurations`."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args
        self.kwargs = kwargs


class LaunchDescription(Recorded):
    def __init__(self, initial_entities: list[Any] | None = None) -> None:
        super().__init__()
        self.entities = list(initial_entities or [])


class DeclareLaunchArgument(Recorded):
    def __init__(self, name: str, *, default_value: Any = None, description: str | None = None,
                 choices: list[str] | None = None) -> None:
        super().__init__(default_value=default_value)
        self.name, self.default_value, self.description, self.choices = name, default_value, description, choices


class IfCondition(Recorded):
    def __init__(self, predicate_expression: Any) -> None:
        super().__init__(predicate_expression)


class UnlessCondition(Recorded):
    def __init__(self, predicate_expression: Any) -> None:
        super().__init__(predicate_expression)


class LaunchConfiguration(Recorded):
    def __init__(self, variable_name: str, *, default: Any = None) -> None:
        super().__init__(default=default)
        self.variable_name = variable_name


class PathJoinSubstitution(Recorded):
    def __init__(self, substitutions: list[Any]) -> None:
        super().__init__(substitutions)


class FindPackageShare(Recorded):
    def __init__(self, package: str) -> None:
        super().__init__(package)
        self.package = package


class ParameterValue(Recorded):
    def __init__(self, value: Any, *, value_type: type | None = None) -> None:
        super().__init__(value)
        self.value_type = value_type


# launch_ros.actions.Node's own keywords, and those it hands on to launch.actions.ExecuteProcess / Action.
_NODE_KEYWORDS = {"executable", "package", "name", "namespace", "exec_name", "parameters", "remappings",
                  "ros_arguments", "arguments"}
_PROCESS_KEYWORDS = {"output", "emulate_tty", "condition", "respawn", "respawn_delay", "additional_env", "env", "cwd",
                     "prefix", "sigterm_timeout", "sigkill_timeout", "shell", "log_cmd", "cached_output", "on_exit"}


class Node(Recorded):
    def __init__(self, **kwargs: Any) -> None:
        unknown = set(kwargs) - _NODE_KEYWORDS - _PROCESS_KEYWORDS
        if unknown:
            msg = f"launch_ros.actions.Node takes no {sorted(unknown)}"
            raise TypeError(msg)
        if "executable" not in kwargs:
            msg = "launch_ros.actions.Node needs executable="
            raise TypeError(msg)
        super().__init__(**kwargs)


class LifecycleNode(Node):
    """launch_ros.actions.LifecycleNode: a Node whose name and namespace are required keywords."""

    def __init__(self, *, name: Any, namespace: Any, **kwargs: Any) -> None:
        super().__init__(name=name, namespace=namespace, **kwargs)


def _stub_modules() -> dict[str, types.ModuleType]:
    names = {
        "launch": {"LaunchDescription": LaunchDescription},
        "launch.actions": {"DeclareLaunchArgument": DeclareLaunchArgument},
        "launch.conditions": {"IfCondition": IfCondition, "UnlessCondition": UnlessCondition},
        "launch.substitutions": {"LaunchConfiguration": LaunchConfiguration,
                                 "PathJoinSubstitution": PathJoinSubstitution},
        "launch_ros": {},
        "launch_ros.actions": {"Node": Node, "LifecycleNode": LifecycleNode},
        "launch_ros.parameter_descriptions": {"ParameterValue": ParameterValue},
        "launch_ros.substitutions": {"FindPackageShare": FindPackageShare},
    }
    modules = {}
    for name, attrs in names.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        modules[name] = module
    return modules


def load_launch_description(path: Path = LAUNCH_FILE) -> LaunchDescription:
    """Import ``path`` with the stand-ins in ``sys.modules`` (restored after) and call its entry point."""
    saved = {name: sys.modules.get(name) for name in _stub_modules()}
    sys.modules.update(_stub_modules())
    try:
        spec = importlib.util.spec_from_file_location("epi_vo_launch_under_test", path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        description = module.generate_launch_description()
    finally:
        for name, previous in saved.items():
            if previous is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = previous
    assert isinstance(description, LaunchDescription)
    return description


# --------------------------------------------------------------------------------------------------------
# Evaluation, as ros2 launch would substitute
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LaunchedNode:
    package: str
    executable: str
    name: str | None
    namespace: str | None
    parameters: list[Any]
    remappings: list[tuple[str, str]]
    arguments: list[str]
    ros_arguments: list[str]
    lifecycle: bool = False  # a launch_ros LifecycleNode (a managed node)


def _resolve(value: Any, configs: Mapping[str, str], share: Mapping[str, str]) -> Any:
    """A substitution (or list of them, concatenated) as the string launch makes of it."""
    if isinstance(value, str):
        return value
    if isinstance(value, LaunchConfiguration):
        if value.variable_name not in configs:
            msg = f"launch configuration {value.variable_name!r} is not declared"
            raise KeyError(msg)
        return configs[value.variable_name]
    if isinstance(value, FindPackageShare):
        return share[value.package]
    if isinstance(value, PathJoinSubstitution):
        return os.path.join(*(_resolve(part, configs, share) for part in value.args[0]))
    if isinstance(value, list | tuple):
        return "".join(_resolve(part, configs, share) for part in value)
    msg = f"cannot substitute {value!r}"
    raise TypeError(msg)


def _parameter(value: Any, configs: Mapping[str, str], share: Mapping[str, str]) -> Any:
    if not isinstance(value, ParameterValue):
        return _resolve(value, configs, share)
    text = _resolve(value.args[0], configs, share)
    if value.value_type is bool:
        parsed = yaml.safe_load(text)
        if not isinstance(parsed, bool):
            msg = f"{text!r} is no bool"
            raise ValueError(msg)
        return parsed
    if value.value_type is str:
        return text
    msg = f"unexpected value_type {value.value_type}"
    raise TypeError(msg)


def _condition_holds(condition: Any, configs: Mapping[str, str], share: Mapping[str, str]) -> bool:
    if condition is None:
        return True
    assert isinstance(condition, IfCondition | UnlessCondition)
    text = _resolve(condition.args[0], configs, share).strip().lower()
    if text not in ("true", "false", "1", "0"):  # launch.conditions.evaluate_condition_expression
        msg = f"{type(condition).__name__}: {text!r} is not a boolean"
        raise ValueError(msg)
    return (text in ("true", "1")) is isinstance(condition, IfCondition)


def declared_arguments(description: LaunchDescription) -> dict[str, DeclareLaunchArgument]:
    return {e.name: e for e in description.entities if isinstance(e, DeclareLaunchArgument)}


def evaluate(description: LaunchDescription, overrides: Mapping[str, str] | None = None,
             share_dir: str = PREFIX + "/share/epi_vo") -> list[LaunchedNode]:
    """The nodes started for ``overrides`` (name -> value, as after ``name:=value``), substitutions done."""
    share = {"epi_vo": share_dir}
    declared = declared_arguments(description)
    overrides = dict(overrides or {})
    unknown = set(overrides) - set(declared)
    assert not unknown, f"not declared: {unknown}"
    configs: dict[str, str] = {}
    for name, arg in declared.items():  # in order, as launch does: a default may use an earlier argument
        value = overrides[name] if name in overrides else _resolve(arg.default_value, configs, share)
        if arg.choices is not None and value not in arg.choices:
            msg = f"{name}:={value} is not one of {arg.choices}"
            raise ValueError(msg)
        configs[name] = value
    nodes = []
    for entity in description.entities:
        if not isinstance(entity, Node):
            continue
        kw = entity.kwargs
        if not _condition_holds(kw.get("condition"), configs, share):
            continue
        params = []
        for p in kw.get("parameters", []):
            if isinstance(p, dict):
                params.append({_resolve(k, configs, share): _parameter(v, configs, share) for k, v in p.items()})
            else:
                params.append(_resolve(p, configs, share))
        nodes.append(LaunchedNode(
            package=_resolve(kw["package"], configs, share),
            executable=_resolve(kw["executable"], configs, share),
            name=None if kw.get("name") is None else _resolve(kw["name"], configs, share),
            namespace=None if kw.get("namespace") is None else _resolve(kw["namespace"], configs, share),
            parameters=params,
            remappings=[(_resolve(a, configs, share), _resolve(b, configs, share))
                        for a, b in kw.get("remappings", [])],
            arguments=[_resolve(a, configs, share) for a in kw.get("arguments", [])],
            ros_arguments=[_resolve(a, configs, share) for a in kw.get("ros_arguments", [])],
            lifecycle=isinstance(entity, LifecycleNode),
        ))
    return nodes


def configurations(obj: Any) -> Iterator[str]:
    """Names of every LaunchConfiguration reachable from ``obj`` (through arguments, lists and dicts)."""
    if isinstance(obj, LaunchConfiguration):
        yield obj.variable_name
    if isinstance(obj, Recorded):
        yield from configurations(list(obj.args) + list(obj.kwargs.values()))
    elif isinstance(obj, dict):
        yield from configurations(list(obj.keys()) + list(obj.values()))
    elif isinstance(obj, list | tuple):
        for item in obj:
            yield from configurations(item)


def setup_kwargs() -> dict[str, Any]:
    """The keyword arguments setup.py passes to setuptools.setup (run in the repository, nothing built)."""
    captured: dict[str, Any] = {}
    fake = types.ModuleType("setuptools")
    fake.__dict__.update(setup=lambda **kw: captured.update(kw), find_packages=lambda **kw: [])
    saved, cwd = sys.modules.get("setuptools"), os.getcwd()
    sys.modules["setuptools"] = fake
    try:
        os.chdir(REPO)  # setup.py globs relative to its folder, as colcon runs it
        runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    finally:
        os.chdir(cwd)
        if saved is None:
            sys.modules.pop("setuptools", None)
        else:
            sys.modules["setuptools"] = saved
    return captured


def installed_files(prefix: str = PREFIX) -> dict[str, str]:
    """Installed path -> source path (relative to the repository) of setup.py's data_files."""
    out = {}
    for dest, sources in setup_kwargs()["data_files"]:
        for src in sources:
            out[os.path.join(prefix, dest, os.path.basename(src))] = src
    return out


def installed_executables() -> set[str]:
    return {spec.split("=")[0].strip() for spec in setup_kwargs()["entry_points"]["console_scripts"]}


def _node_string_calls(*methods: str) -> set[str]:
    """String literals passed as the topic (2nd positional argument) to ``self.<method>(...)`` in node.py."""
    out = set()
    for call in ast.walk(ast.parse(NODE_SOURCE.read_text())):
        if (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and call.func.attr in methods
                and len(call.args) >= 2 and isinstance(call.args[1], ast.Constant)
                and isinstance(call.args[1].value, str)):
            out.add(call.args[1].value)
    return out


def node_published_topics() -> set[str]:
    # the VO outputs are made through a hook (lifecycle publishers in vo_lifecycle_node), /diagnostics directly
    return _node_string_calls("create_publisher", "_create_output_publisher")


def node_input_topics() -> set[str]:
    """The camera topics node.py names (literals ``camera/...``), whatever variable carries them."""
    return {n.value for n in ast.walk(ast.parse(NODE_SOURCE.read_text()))
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and re.fullmatch(r"camera/[a-z_/]+", n.value)}


@pytest.fixture(scope="module")
def description() -> LaunchDescription:
    return load_launch_description()


def _by_executable(nodes: list[LaunchedNode], executable: str) -> LaunchedNode:
    matches = [n for n in nodes if n.executable == executable]
    assert len(matches) == 1, [n.executable for n in nodes]
    return matches[0]


# --------------------------------------------------------------------------------------------------------
# The launch file
# --------------------------------------------------------------------------------------------------------


def test_launch_file_defines_generate_launch_description() -> None:
    tree = ast.parse(LAUNCH_FILE.read_text(), str(LAUNCH_FILE))
    top = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in top


def test_launch_file_imports_only_launch_and_launch_ros() -> None:
    # Anything else would have to be installed next to ros2 launch (and is not stubbed here).
    tree = ast.parse(LAUNCH_FILE.read_text())
    roots = {a.name.split(".")[0] for n in tree.body if isinstance(n, ast.Import) for a in n.names}
    roots |= {n.module.split(".")[0] for n in tree.body if isinstance(n, ast.ImportFrom) and n.module}
    assert roots <= {"launch", "launch_ros", "__future__"}, roots


def test_declares_the_arguments_with_descriptions(description: LaunchDescription) -> None:
    declared = declared_arguments(description)
    assert set(declared) >= {"namespace", "params_file", "image_topic", "camera_info_topic", "image_transport",
                             "use_sim_time", "rviz", "managed"}
    assert all(arg.description for arg in declared.values()), [n for n, a in declared.items() if not a.description]
    assert declared["rviz"].choices == ["true", "false"]
    assert declared["use_sim_time"].choices == ["true", "false"]


def test_every_declared_argument_is_used_and_every_used_one_declared(description: LaunchDescription) -> None:
    declared = declared_arguments(description)
    used = {name for e in description.entities if isinstance(e, Node) for name in configurations(e)}
    assert used == set(declared), f"declared, unused: {set(declared) - used}; used, undeclared: {used - set(declared)}"
    in_defaults = {name for arg in declared.values() for name in configurations(arg)}
    assert in_defaults <= set(declared)


def test_launches_an_installed_executable_of_this_package(description: LaunchDescription) -> None:
    vo = _by_executable(evaluate(description), "vo_node")
    assert vo.package == "epi_vo"
    assert vo.executable in installed_executables()
    # ros2 launch finds executables in <prefix>/lib/<package>: setup.cfg puts the scripts there
    cfg = (REPO / "setup.cfg").read_text()
    assert "install_scripts=$base/lib/epi_vo" in cfg.replace(" ", "")


def test_defaults_start_only_vo_node_with_the_installed_params_file(description: LaunchDescription) -> None:
    nodes = evaluate(description)
    assert [n.executable for n in nodes] == ["vo_node"]
    vo = nodes[0]
    assert vo.name == "vo_node"
    assert vo.namespace == ""
    params_file = PREFIX + "/share/epi_vo/config/epi_vo.yaml"
    assert vo.parameters == [params_file, {"image_transport": "auto", "use_sim_time": False}]
    assert installed_files()[params_file] == "config/epi_vo.yaml"
    assert (REPO / "config" / "epi_vo.yaml").is_file()
    assert vo.remappings == [("camera/image_raw", "camera/image_raw"),
                             ("camera/image_raw/compressed", "camera/image_raw/compressed"),
                             ("camera/camera_info", "camera/camera_info")]
    assert vo.ros_arguments == ["--log-level", "info"]


def test_managed_true_starts_the_lifecycle_node_instead_with_the_same_settings(
        description: LaunchDescription) -> None:
    overrides = {"namespace": "robot1", "image_topic": "/front/image_raw", "use_sim_time": "true"}
    plain = _by_executable(evaluate(description, overrides), "vo_node")
    nodes = evaluate(description, {**overrides, "managed": "true"})
    assert [n.executable for n in nodes] == ["vo_lifecycle_node"]
    managed = nodes[0]
    assert managed.lifecycle and not plain.lifecycle
    assert managed.executable in installed_executables()
    assert dataclasses.replace(managed, executable="vo_node", lifecycle=False) == plain
    assert declared_arguments(description)["managed"].default_value == "false"
    with pytest.raises(ValueError, match="managed:=yes is not one of"):
        evaluate(description, {"managed": "yes"})


def test_arguments_reach_the_node(description: LaunchDescription) -> None:
    vo = _by_executable(evaluate(description, {
        "namespace": "robot1", "params_file": "/tmp/my.yaml", "image_topic": "/front/image_raw",
        "camera_info_topic": "/front/camera_info", "image_transport": "compressed", "use_sim_time": "true",
        "log_level": "debug"}), "vo_node")
    assert vo.namespace == "robot1"
    assert vo.parameters == ["/tmp/my.yaml", {"image_transport": "compressed", "use_sim_time": True}]
    assert vo.remappings == [("camera/image_raw", "/front/image_raw"),
                             ("camera/image_raw/compressed", "/front/image_raw/compressed"),
                             ("camera/camera_info", "/front/camera_info")]
    assert vo.ros_arguments == ["--log-level", "debug"]


def test_remappings_cover_exactly_the_topics_the_node_subscribes(description: LaunchDescription) -> None:
    vo = _by_executable(evaluate(description), "vo_node")
    assert {src for src, _ in vo.remappings} == node_input_topics()


def test_image_transport_choices_and_default_are_those_of_the_node(description: LaunchDescription) -> None:
    from epi_vo.io.node_options import NODE_CHOICES, NodeOptions

    arg = declared_arguments(description)["image_transport"]
    assert arg.choices is not None
    assert set(arg.choices) == set(NODE_CHOICES["image_transport"])
    assert arg.default_value == NodeOptions().image_transport  # the launch file does not change the default
    with pytest.raises(ValueError, match="image_transport:=jpeg is not one of"):
        evaluate(description, {"image_transport": "jpeg"})


def test_rviz_true_adds_rviz2_with_the_installed_config(description: LaunchDescription) -> None:
    nodes = evaluate(description, {"rviz": "true", "namespace": "robot1", "use_sim_time": "true"})
    assert sorted(n.executable for n in nodes) == ["rviz2", "vo_node"]
    rviz = _by_executable(nodes, "rviz2")
    assert rviz.package == "rviz2"
    config = PREFIX + "/share/epi_vo/config/epi_vo.rviz"
    assert rviz.arguments == ["-d", config, "-f", "odom"]  # the fixed frame: the node's frame_id, in metres
    assert installed_files()[config] == "config/epi_vo.rviz"
    assert rviz.parameters == [{"use_sim_time": True}]
    # the config's absolute topics are remapped to relative ones: they resolve in the launch namespace
    assert rviz.namespace == "robot1"
    assert sorted(rviz.remappings) == sorted(("/" + t, t) for t in SHOWN_TOPICS.values())
    assert {src for src, _ in rviz.remappings} == rviz_topics()
    # Without metres the outputs to see are in <frame_id>_vo_units, in no TF tree: RViz2 fixed there.
    vo_units = _by_executable(evaluate(description, {"rviz": "true", "rviz_fixed_frame": "odom_vo_units"}), "rviz2")
    assert vo_units.arguments == ["-d", config, "-f", "odom_vo_units"]


# --------------------------------------------------------------------------------------------------------
# RViz2 config and Foxglove layout
# --------------------------------------------------------------------------------------------------------


def rviz_displays() -> list[dict[str, Any]]:
    return yaml.safe_load(RVIZ_FILE.read_text())["Visualization Manager"]["Displays"]


def rviz_topics() -> set[str]:
    return {d["Topic"]["Value"] for d in rviz_displays() if "Topic" in d}


def test_the_node_publishes_what_the_displays_show() -> None:
    assert set(SHOWN_TOPICS.values()) <= node_published_topics()
    assert "/diagnostics" in node_published_topics()


def test_rviz_config_shows_odometry_path_points_and_debug_image_in_odom() -> None:
    doc = yaml.safe_load(RVIZ_FILE.read_text())
    assert doc["Visualization Manager"]["Global Options"]["Fixed Frame"] == "odom"
    by_topic = {d["Topic"]["Value"]: d for d in rviz_displays() if "Topic" in d}
    expected = {"odometry": "rviz_default_plugins/Odometry", "odometry_vo_units": "rviz_default_plugins/Odometry",
                "path": "rviz_default_plugins/Path", "points": "rviz_default_plugins/PointCloud2",
                "debug_image": "rviz_default_plugins/Image"}
    for key, cls in expected.items():
        display = by_topic["/" + SHOWN_TOPICS[key]]
        assert display["Class"] == cls and display["Enabled"] is True, key
    assert "rviz_default_plugins/TF" in {d["Class"] for d in rviz_displays()}
    assert rviz_topics() == {"/" + t for t in SHOWN_TOPICS.values()}


def test_rviz_fixed_frame_is_the_nodes_default_odometry_frame() -> None:
    from epi_vo.io.node_options import NodeOptions

    fixed = yaml.safe_load(RVIZ_FILE.read_text())["Visualization Manager"]["Global Options"]["Fixed Frame"]
    assert fixed == NodeOptions().frame_id


def _layout_panels(tree: Any) -> Iterator[str]:
    if isinstance(tree, str):
        yield tree
    elif isinstance(tree, dict):
        yield from _layout_panels(tree["first"])
        yield from _layout_panels(tree["second"])


def test_foxglove_layout_shows_odometry_path_points_image_twist_and_diagnostics() -> None:
    layout = json.loads(FOXGLOVE_FILE.read_text())
    panels = layout["configById"]
    assert sorted(_layout_panels(layout["layout"])) == sorted(panels)  # every panel placed, none missing
    kinds = {pid.split("!")[0]: cfg for pid, cfg in panels.items()}
    assert {"3D", "Image", "Plot", "DiagnosticSummary"} <= set(kinds)
    scene_topics = kinds["3D"]["topics"]
    for key in ("odometry", "odometry_vo_units", "path", "points"):
        assert scene_topics["/" + SHOWN_TOPICS[key]]["visible"] is True
    assert kinds["3D"]["followTf"] == "odom"
    assert kinds["Image"]["imageMode"]["imageTopic"] == "/" + SHOWN_TOPICS["debug_image"]
    plotted = [p["value"] for p in kinds["Plot"]["paths"]]
    assert plotted, "the twist plot has no series"
    assert all(v.startswith(("/" + SHOWN_TOPICS["odometry"] + ".twist.twist.",
                             "/" + SHOWN_TOPICS["odometry_vo_units"] + ".twist.twist.")) for v in plotted), plotted
    # the yaw rate (no scale touches it) and the forward speed in metres, and in VO units while there are none
    assert {"/vo/odometry.twist.twist.linear.x", "/vo/odometry.twist.twist.angular.z",
            "/vo/odometry/vo_units.twist.twist.linear.x"} <= set(plotted)
    assert kinds["DiagnosticSummary"]["topicToRender"] == "/diagnostics"
    named = set(scene_topics) | {kinds["Image"]["imageMode"]["imageTopic"], kinds["DiagnosticSummary"]["topicToRender"]}
    published = {t if t.startswith("/") else "/" + t for t in node_published_topics()}
    assert named <= published, named - published


def test_configs_and_launch_file_are_installed() -> None:
    installed = installed_files()
    share = PREFIX + "/share/epi_vo/"
    assert installed[share + "launch/vo.launch.py"] == "launch/vo.launch.py"
    assert installed[share + "config/epi_vo.rviz"] == "config/epi_vo.rviz"
    assert installed[share + "config/foxglove_layout.json"] == "config/foxglove_layout.json"
    assert installed[share + "config/epi_vo.yaml"] == "config/epi_vo.yaml"
    assert all((REPO / src).is_file() for src in installed.values())
