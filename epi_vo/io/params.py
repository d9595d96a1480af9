"""ROS 2 parameter files: read the ``ros__parameters`` of ``vo_node`` (or ``/**``) into a ``VoConfig``,
and write a config back as such a file (``epi-vo params``).

Every name in a file must be a parameter: a pipeline knob (``epi_vo.core.config``), a node option
(``epi_vo.io.node_options``) or a ROS node parameter; any other is an error naming it with the closest
parameter name.
"""

from __future__ import annotations

import enum
from pathlib import Path
from typing import Any

import yaml

from epi_vo.core.config import (
    PIPELINE_NAMES,
    VoConfig,
    config_fields,
    field_doc,
    from_dict,
    is_parameter_name,
    unknown_names_text,
)
from epi_vo.core.errors import ConfigError
from epi_vo.io.node_options import (
    NODE_DOCS,
    NODE_OPTION_NAMES,
    CameraExtrinsic,
    NodeOptions,
    is_read_only,
    make_node_options,
)
from epi_vo.io.paths import refuse_special_file


def load_params_file(path: str | Path, node_name: str = "vo_node") -> dict[str, Any]:
    """Read the ``ros__parameters`` of a ROS 2 parameter file (``/**`` or the node's own key).

    Returns every parameter found (pipeline and node parameters alike); the caller splits them.
    """
    path = Path(path)
    refuse_special_file(path, "parameter file", ConfigError)
    try:
        doc = yaml.safe_load(path.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read parameter file {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"parameter file {path} is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset "
                          f"{exc.start})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"parameter file {path} is not valid YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"parameter file {path}: expected a mapping of node names to ros__parameters")
    params: dict[str, Any] = {}
    for key in ("/**", node_name, f"/{node_name}"):
        block = doc.get(key)
        if isinstance(block, dict) and isinstance(block.get("ros__parameters"), dict):
            params.update(block["ros__parameters"])
    if not params and doc:
        raise ConfigError(f"parameter file {path}: no '/**' or '{node_name}' block with ros__parameters")
    return params


def load_config(path: str | Path | None = None) -> VoConfig:
    """The pipeline config from a ROS 2 parameter file.

    The node's own parameters and the ROS ones (``NODE_PARAMETER_NAMES``, ``ROS_PARAMETER_NAMES``) are
    accepted and ignored; any other name that is not a pipeline knob is an error naming it (with the
    closest parameter name), reported together with every bad value.
    """
    if path is None:
        return VoConfig()
    params = load_params_file(path)
    unknown = [k for k in params if not is_parameter_name(k) and k not in NODE_OPTION_NAMES]
    unknown_text = f"unknown parameters: {unknown_names_text(unknown)}" if unknown else ""
    try:
        cfg = from_dict({k: v for k, v in params.items() if k in PIPELINE_NAMES})
    except ConfigError as exc:
        raise ConfigError(f"parameter file {path}: {exc}" + (f"; {unknown_text}" if unknown else "")) from None
    if unknown:
        raise ConfigError(f"parameter file {path}: invalid epi_vo parameters: {unknown_text}")
    return cfg


def load_node_options(path: str | Path | None = None) -> NodeOptions:
    """vo_node's own parameters in a ROS 2 parameter file (defaults for those it does not set), for the
    offline tools that honour some of them (``epi-vo replay``: ``map_frame_id``); ConfigError naming
    every bad value. The file's other names are ``load_config``'s to check."""
    if path is None:
        return NodeOptions()
    params = load_params_file(path)
    try:
        return make_node_options({k: v for k, v in params.items() if k in NODE_OPTION_NAMES})
    except ConfigError as exc:
        raise ConfigError(f"parameter file {path}: {exc}") from None


def load_extrinsic(path: str | Path | None = None) -> CameraExtrinsic | None:
    """The camera mounting a parameter file declares (it sets ``camera_xyz`` or ``camera_rpy``; the other one
    takes its default), None when it declares none: then the offline tools take the default mounting (a level
    camera at base_link), as vo_node's defaults do. ConfigError naming a bad value, as :func:`load_node_options`."""
    if path is None or not {"camera_xyz", "camera_rpy"} & set(load_params_file(path)):
        return None
    opts = load_node_options(path)
    return CameraExtrinsic(opts.camera_xyz, opts.camera_rpy)


def to_params_yaml(cfg: VoConfig, extra: dict[str, Any] | None = None, node: NodeOptions | None = None) -> str:
    """The config as a ROS 2 parameter file (``/**: ros__parameters:``) with doc comments.

    With ``node``, the node's own parameters follow the pipeline's, each with its doc comment (the form
    of ``config/epi_vo.yaml``); ``extra`` names are appended without a comment. Parameters the node
    declares read-only (a change needs a restart) say so in their comment.
    """
    lines = ["/**:", "  ros__parameters:"]
    if node is not None:
        lines.append("    # ---- vo_node: frames, camera extrinsic, input, outputs, diagnostics")
        for name in NODE_OPTION_NAMES:
            lines.append(f"    # {NODE_DOCS[name]}{_RESTART if is_read_only(name) else ''}")
            lines.append(f"    {name}: {_yaml_value(getattr(node, name))}")
        lines.append("    # ---- pipeline (epi_vo.core.config.VoConfig)")
    for f in config_fields():
        lines.append(f"    # {field_doc(f)}{_RESTART if is_read_only(f.name) else ''}")
        lines.append(f"    {f.name}: {_yaml_value(getattr(cfg, f.name))}")
    for name, value in (extra or {}).items():
        lines.append(f"    {name}: {_yaml_value(value)}")
    return "\n".join(lines) + "\n"


_RESTART = " [read-only: restart to change]"


def _yaml_value(value: Any) -> str:
    """One YAML scalar or flow list (tuples as lists), without the document end marker."""
    if isinstance(value, tuple):
        value = list(value)
    if isinstance(value, enum.Enum):  # a mode: its text
        value = value.value
    return yaml.safe_dump(value, default_flow_style=True).strip().replace("\n...", "")
