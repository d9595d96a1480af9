"""Does a value read from a result file (``stats.json``, a ``frames.jsonl`` record) have the type its writer
gives it? One line naming the field when not, so that ``summarize`` and ``report`` refuse a file that was
edited or damaged instead of failing somewhere inside with a traceback.

Types are written as the writers declare them: ``int``, ``float`` (any JSON number but a boolean, and
finite: the writers put null where a value is not finite), ``str``, ``bool``, ``dict[str, T]``, ``list[T]``,
``T | None``, ``Any`` and enums (the value must be one of the enum's values).
"""

from __future__ import annotations

import enum
import math
import types
import typing
from collections.abc import Mapping
from typing import Any

from epi_vo.core.errors import quoted


def type_problem(value: Any, tp: Any, where: str) -> str | None:
    """Why ``value`` is not of type ``tp`` (naming ``where``, e.g. ``stats.json: frames``), or None."""
    if tp is Any:
        return None
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        problems = [type_problem(value, t, where) for t in typing.get_args(tp)]
        if all(p is not None for p in problems):
            names = " or ".join(_name(t) for t in typing.get_args(tp))
            return f"{where} is {quoted(value)}, expected {names}"
        return None
    if tp is type(None):
        return None if value is None else f"{where} is {quoted(value)}, expected null"
    if origin is dict:
        if not isinstance(value, dict):
            return f"{where} is {quoted(value)}, expected an object"
        key_tp, value_tp = typing.get_args(tp)
        for k, v in value.items():
            problem = type_problem(k, key_tp, f"{where} key") or type_problem(v, value_tp, f"{where}.{k}")
            if problem:
                return problem
        return None
    if origin in (list, tuple):
        if not isinstance(value, list):
            return f"{where} is {quoted(value)}, expected a list"
        (item_tp, *_) = typing.get_args(tp) or (Any,)
        for i, v in enumerate(value):
            problem = type_problem(v, item_tp, f"{where}[{i}]")
            if problem:
                return problem
        return None
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        if value in {m.value for m in tp}:
            return None
        return f"{where} is {quoted(value)}, expected one of {', '.join(repr(m.value) for m in tp)}"
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"{where} is {quoted(value)}, expected a number"
        return None if math.isfinite(value) else f"{where} is {value}, expected a finite number"
    if tp is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else \
            f"{where} is {quoted(value)}, expected an integer"
    if tp in (str, bool):
        return None if isinstance(value, tp) else f"{where} is {quoted(value)}, expected {_name(tp)}"
    raise TypeError(f"type_problem: unsupported type {tp!r}")  # a programming error: a writer's new type


def fields_problem(data: Mapping[str, Any], field_types: Mapping[str, Any], where: str) -> str | None:
    """The first field of ``data`` present in ``field_types`` whose value is not of its type, or None."""
    for name, tp in field_types.items():
        if name in data:
            problem = type_problem(data[name], tp, f"{where}: {name}")
            if problem:
                return problem
    return None


def _name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is dict:
        return "an object"
    if origin in (list, tuple):
        return "a list"
    if tp is type(None):
        return "null"
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is str:
        return "a string"
    if tp is bool:
        return "true or false"
    return getattr(tp, "__name__", None) or str(tp)
