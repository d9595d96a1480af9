"""Checks of values given on a command line or in options (no rclpy): numbers that must be finite and in a
range, and ROS 2 names. Each returns the value when it is usable and raises ConfigError with one line
naming the option and the value otherwise, before anything acts on it (rclpy would raise its own
exception with a traceback for a bad name; a NaN timeout would never expire).

ROS 2 names follow rcl / rmw (design article "Topic and Service name mapping to DDS", ``rmw_validate_*``):
a name's tokens are separated by '/', hold only ASCII letters, digits and '_' and do not start with a digit;
no empty token ('//'), no trailing '/'; a topic may be relative, start with '~' (the node's private
namespace) and use ``{substitution}`` tokens; a namespace is absolute ('' and 'ns' are taken as '/' and
'/ns', as rclpy does); a node name is one token.
"""

from __future__ import annotations

import math
import re
from typing import Any

from epi_vo.core.errors import ConfigError, quoted

ROS_NAME_MAX_CHARS = 255  # rmw's limit on a topic name, a namespace and a node name (RMW_*_MAX_NAME_LENGTH)
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# A topic token may hold {substitutions} ('{node}', 'cam_{ns}'), as rcl's topic name expansion allows.
_TOPIC_TOKEN = re.compile(r"(?:[A-Za-z_]|\{[A-Za-z_][A-Za-z0-9_]*\})(?:[A-Za-z0-9_]|\{[A-Za-z_][A-Za-z0-9_]*\})*")


def number(value: Any, name: str, *, minimum: float | None = None, maximum: float | None = None,
           positive: bool = False, integer: bool = False) -> float:
    """``value`` when it is a finite number (an integer with ``integer``), above 0 with ``positive``, and
    within [``minimum``, ``maximum``]; ConfigError naming ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{name} must be a number, not {quoted(value)}")
    if not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, not {value}")
    if integer and value != int(value):
        raise ConfigError(f"{name} must be a whole number, not {value}")
    if positive and value <= 0:
        raise ConfigError(f"{name} must be a positive number, not {value}")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{name} must be at least {minimum:g}, not {value}")
    if maximum is not None and value > maximum:
        raise ConfigError(f"{name} must be at most {maximum:g}, not {value}")
    return value


def _name_problem(text: str, *, allow_tilde: bool, allow_substitution: bool) -> str | None:
    if not text:
        return "is empty"
    if len(text) > ROS_NAME_MAX_CHARS:
        return f"is longer than {ROS_NAME_MAX_CHARS} characters"
    body = text
    if allow_tilde and body.startswith("~"):
        body = body[1:]
        if body and not body.startswith("/"):
            return "has '~' not followed by '/'"
    body = body.removeprefix("/")
    if not body:
        return None if text in ("/", "~", "~/") else "names nothing"
    if body.endswith("/"):
        return "ends with '/'"
    for token in body.split("/"):
        if not token:
            return "has an empty token ('//')"
        if allow_substitution and _TOPIC_TOKEN.fullmatch(token):
            continue
        if not _TOKEN.fullmatch(token):
            if token[0].isdigit():
                return f"has a token starting with a digit ({quoted(token)})"
            return (f"has characters other than letters, digits and '_' in {quoted(token)}"
                    + ("" if allow_tilde else " ('~' only begins a topic name)"))
    return None


def topic_name(value: str, name: str) -> str:
    """``value`` when it is a valid ROS 2 topic name (absolute, relative or '~/...'); ConfigError otherwise."""
    problem = _name_problem(value, allow_tilde=True, allow_substitution=True)
    if problem is not None or value in ("/", "~/"):
        raise ConfigError(f"{name} {quoted(value)} is not a valid ROS 2 topic name: {problem or 'names nothing'}")
    return value


def namespace(value: str, name: str) -> str:
    """``value`` when it is a valid ROS 2 namespace ('' is the root; a relative one is taken from the root, as
    rclpy does); ConfigError otherwise."""
    if value in ("", "/"):
        return value
    problem = _name_problem(value if value.startswith("/") else f"/{value}", allow_tilde=False,
                            allow_substitution=False)
    if problem is not None:
        raise ConfigError(f"{name} {quoted(value)} is not a valid ROS 2 namespace: {problem}")
    return value


def node_name(value: str, name: str) -> str:
    """``value`` when it is a node name ('vo_node') or a fully qualified one ('/robot1/vo_node');
    ConfigError otherwise."""
    if value.startswith("/"):
        problem = _name_problem(value, allow_tilde=False, allow_substitution=False) or \
            (None if value.strip("/") else "names no node")
    elif not value:
        problem = "is empty"
    elif len(value) > ROS_NAME_MAX_CHARS:
        problem = f"is longer than {ROS_NAME_MAX_CHARS} characters"
    else:
        problem = None if _TOKEN.fullmatch(value) else "must hold only letters, digits and '_', not start with a digit"
    if problem is not None:
        raise ConfigError(f"{name} {quoted(value)} is not a valid ROS 2 node name: {problem}")
    return value
