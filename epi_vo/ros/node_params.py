"""``vo_node``'s ROS parameters: declared from one table (VoConfig's fields, then NodeOptions'), with
descriptors (doc, range, choices, read-only), the check of a runtime change, and what is logged about them.

Start-up and runtime changes go through the same validation (``epi_vo.core.config.from_dict`` and
``epi_vo.io.node_options``); a topic parameter is also checked by rclpy's own name validation, so a bad
one is refused with its name before anything is created. Parameters that need a restart are declared
read-only, so ROS itself refuses a change of them; a runtime change of a pipeline knob is accepted here
and applied by the node at its next frame.
"""

from __future__ import annotations

import enum
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import NameValidationException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.validate_full_topic_name import validate_full_topic_name
from rclpy.validate_topic_name import validate_topic_name

from epi_vo.core.config import (
    VoConfig,
    allowed_range,
    config_fields,
    field_doc,
    from_dict,
    shown,
    unknown_names_text,
)
from epi_vo.core.errors import ConfigError
from epi_vo.io.node_options import (
    NODE_CHOICES,
    NODE_DOCS,
    NODE_OPTION_NAMES,
    NodeOptions,
    apply_changes,
    is_read_only,
    make_node_options,
    node_option_problems,
)

READ_ONLY_NOTE = " (read-only: restart the node to change it)"
TOPIC_PARAMETERS = ("wheel_odometry_topic",)  # parameters that name a topic the node subscribes to
RCLError = rclpy_implementation.RCLError


def descriptor(name: str, doc: str, lo: float | None, hi: float | None, choices: tuple[str, ...] | None,
               is_int: bool) -> ParameterDescriptor:
    """The ROS descriptor of one parameter: its doc line, range or choices, and whether it is read-only."""
    read_only = is_read_only(name)
    d = ParameterDescriptor(description=doc + (READ_ONLY_NOTE if read_only else ""), read_only=read_only)
    if choices:
        d.additional_constraints = "one of: " + ", ".join(choices)
    if lo is not None and hi is not None:
        if is_int:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return d


def declare_all(node: Any) -> tuple[VoConfig, NodeOptions]:
    """Declare every pipeline and node parameter on ``node``; ConfigError naming every bad one at once.

    A parameter already declared (a managed node configured again, or whose first configure failed) is
    not declared again: its current value is read and checked like the others."""
    problems: list[str] = []
    values: dict[str, Any] = {}
    for f in config_fields():
        lo, hi = allowed_range(f) or (None, None)  # a knob's 'off' value too; validate() checks the gap
        choices = f.metadata.get("choices")
        is_int = isinstance(f.default, int) and not isinstance(f.default, bool)
        desc = descriptor(f.name, field_doc(f), lo, hi, choices, is_int)
        values[f.name] = _declare(node, f.name, f.default, desc, problems)
    node_values: dict[str, Any] = {}
    defaults = NodeOptions()
    for name in NODE_OPTION_NAMES:
        default = getattr(defaults, name)
        if isinstance(default, tuple):
            default = list(default)
        desc = descriptor(name, NODE_DOCS[name], None, None, NODE_CHOICES.get(name), False)
        node_values[name] = _declare(node, name, default, desc, problems)
    cfg = VoConfig()
    try:
        cfg = from_dict({k: v for k, v in values.items() if v is not None})
    except ConfigError as exc:
        problems.append(str(exc).removeprefix("invalid epi_vo parameters: "))
    declared = {k: v for k, v in node_values.items() if v is not None}
    problems += node_option_problems(declared)
    problems += topic_problems(node, values)
    if problems:
        raise ConfigError("invalid vo_node parameters: " + "; ".join(problems))
    return cfg, make_node_options(declared)


def topic_name_problem(node: Any, name: str) -> str | None:
    """Why rcl would refuse ``name`` as a topic of ``node`` (its syntax, or once expanded with the node's
    name and namespace and remapped), or None: rclpy's own validation, before anything is created."""
    try:
        validate_topic_name(name)
        validate_full_topic_name(node.resolve_topic_name(name))
    except NameValidationException as exc:
        return str(exc).splitlines()[0].removeprefix("Invalid topic name: ").rstrip(":")
    except RCLError as exc:  # resolving: an unknown substitution, a repeated '/'
        return str(exc).removeprefix("failed to resolve name: ").split(", at /")[0]
    return None


def topic_problems(node: Any, values: dict[str, Any]) -> list[str]:
    """Every topic parameter among ``values`` that rcl would refuse, naming it and its value."""
    problems = []
    for name in TOPIC_PARAMETERS:
        v = values.get(name)
        if isinstance(v, str) and (why := topic_name_problem(node, v)) is not None:
            problems.append(f"{name}={v!r} (not a valid ROS topic name: {why})")
    return problems


def _declare(node: Any, name: str, default: Any, desc: ParameterDescriptor, problems: list[str]) -> Any:
    if isinstance(default, enum.Enum):  # a mode: declared as its text, converted back in VoConfig / NodeOptions
        default = default.value
    if node.has_parameter(name):  # the managed node's second configure: read the value it has now
        return node.get_parameter(name).value
    try:
        return node.declare_parameter(name, default, desc).value
    except Exception as exc:  # rclpy raises several exception types for a bad override
        problems.append(f"{name}: {exc}")
        return None


def warn_undeclared_overrides(node: Any) -> None:
    """ROS's rule stays (an override of a parameter the node does not declare is ignored), but a
    misspelt name must not pass unnoticed: warn once, naming them and the closest parameter."""
    # rclpy has no public accessor for the overrides it was given (--params-file, -p): read its
    # attribute, and say nothing when a future rclpy renames it.
    overrides = getattr(node, "_parameter_overrides", None) or {}
    unknown = sorted(n for n in overrides if not node.has_parameter(n) and not n.startswith("qos_overrides."))
    if not unknown:
        return
    node.get_logger().warning("ignoring parameter overrides that vo_node does not declare: "
                              + unknown_names_text(unknown))


def effective_parameters_text(cfg: VoConfig, opts: NodeOptions) -> str:
    """The line logged at start-up (and at each configure): every parameter's effective value."""
    lines = [f"{f.name}={shown(getattr(cfg, f.name))}" for f in config_fields()]
    lines += [f"{k}={shown(v)}" for k, v in opts.__dict__.items()]
    return "epi_vo parameters: " + ", ".join(lines)


def check_change(cfg: VoConfig, opts: NodeOptions, parameters: list[Any]
                 ) -> tuple[SetParametersResult, VoConfig, NodeOptions]:
    """The answer to a set-parameters request (rclpy Parameter objects) and the config it leads to.

    Refused (``successful`` false, ``reason`` naming every problem) when a value fails the start-up
    validation; the config and options are then returned unchanged.
    """
    changes = {p.name: p.value for p in parameters}
    try:
        new_cfg, new_opts = apply_changes(cfg, opts, changes)
    except ConfigError as exc:
        return SetParametersResult(successful=False, reason=f"refused: {exc}"), cfg, opts
    return SetParametersResult(successful=True, reason=""), new_cfg, new_opts
