"""The layers are visible and kept: what each folder of ``epi_vo`` may import, no import circle, no
private name taken from another module, no module over 700 lines.

    cli.py  ->  ros/  ->  runner/  ->  io/  ->  core/
            ->  tools/ ->  runner/  ->  io/  ->  core/

* core/: numpy, cv2 and the standard library only (plus the optimiser the metric-scale work adds); no
  threads, processes or their queues: the per-frame step computes, a runner decides what runs where;
* runner/: core, io and the standard library's threads and processes: what runs ahead of and beside the step,
  and the one frame handler of both front doors (decode with io, process, outputs as plain records that the
  node publishes and the replay writes); never rclpy;
* io/: core, rosbags, mcap, yaml; never rclpy;
* ros/: core, io, rclpy and ROS message packages (and rich for the monitor); never tools;
* tools/: core, io, evo, matplotlib, tqdm; never rclpy, never ros;
* cli.py: anything, lazily.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "epi_vo"
LAYERS = ("core", "io", "runner", "ros", "tools")
ROS_PACKAGES = {"rclpy", "builtin_interfaces", "diagnostic_msgs", "geometry_msgs", "nav_msgs", "rcl_interfaces",
                "rosgraph_msgs", "sensor_msgs", "std_msgs", "std_srvs", "tf2_msgs", "tf2_ros", "lifecycle_msgs"}
THIRD_PARTY = {
    "core": {"numpy", "cv2", "gtsam", "scipy"},
    "io": {"numpy", "cv2", "rosbags", "mcap", "yaml"},
    "runner": {"numpy", "cv2"},
    "ros": {"numpy", "cv2", "rich"} | ROS_PACKAGES,  # rich: the monitor's terminal view
    "tools": {"numpy", "cv2", "evo", "matplotlib", "tqdm", "rosbags", "mcap", "yaml"},
}
MAY_IMPORT = {"core": {"core"}, "io": {"core", "io"}, "runner": {"core", "io", "runner"},
              "ros": {"core", "io", "runner", "ros"}, "tools": {"core", "io", "runner", "tools"}}
# What runs where is the runner's: the core computes in the calling thread.
CORE_REFUSES = {"threading", "concurrent", "subprocess", "multiprocessing", "queue", "pickle", "asyncio"}
MAX_LINES = 700


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(module imported, names taken from it, line) for every import of a file, relative ones resolved."""
    tree = ast.parse(path.read_text(), str(path))
    here = ".".join(path.relative_to(PKG.parent).with_suffix("").parts)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                base = here.split(".")[: -node.level]
                mod = ".".join(base + ([mod] if mod else []))
            found.append((mod, [a.name for a in node.names], node.lineno))
    return found


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "epi_vo" and parts[1] in LAYERS else None


def test_every_module_is_in_a_layer() -> None:
    loose = [m for m in MODULES if m not in ("epi_vo", "epi_vo.cli") and _layer(m) is None]
    assert not loose, f"modules outside core/ io/ runner/ ros/ tools/: {loose}"
    assert {_layer(m) for m in MODULES} >= set(LAYERS)


@pytest.mark.parametrize("module", [m for m in MODULES if _layer(m)])
def test_imports_point_one_way(module: str) -> None:
    layer = _layer(module)
    assert layer is not None
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    bad = []
    for imported, _, line in _imports(MODULES[module]):
        top = imported.split(".")[0]
        if top == "epi_vo":
            target = _layer(imported) or ("cli" if imported == "epi_vo.cli" else "epi_vo")
            if target not in MAY_IMPORT[layer]:
                bad.append(f"line {line}: {imported} ({layer} may import {sorted(MAY_IMPORT[layer])})")
        elif layer == "core" and top in CORE_REFUSES:
            bad.append(f"line {line}: {imported} (threads and processes belong to epi_vo.runner)")
        elif top not in stdlib and top not in THIRD_PARTY[layer]:
            bad.append(f"line {line}: {imported} (third-party packages of {layer}: {sorted(THIRD_PARTY[layer])})")
    assert not bad, f"{module}: " + "; ".join(bad)


def test_no_private_names_from_other_modules() -> None:
    bad = []
    for module, path in MODULES.items():
        for imported, names, line in _imports(path):
            if imported.startswith("epi_vo") and imported != module:
                bad += [f"{module}:{line} takes {imported}.{n}" for n in names if n.startswith("_")]
                if any(p.startswith("_") and p != "__init__" for p in imported.split(".")):
                    bad.append(f"{module}:{line} imports private module {imported}")
    assert not bad, bad


def test_no_import_circle() -> None:
    graph = {m: set() for m in MODULES}
    for module, path in MODULES.items():
        for imported, names, _ in _imports(path):
            for cand in [imported] + [f"{imported}.{n}" for n in names]:
                if cand in MODULES and cand != module and not (module.startswith(cand + ".")):
                    graph[module].add(cand)
    # Package __init__ files that re-export their own submodules are not circles: drop parent -> child edges.
    for module in graph:
        graph[module] = {t for t in graph[module] if not t.startswith(module + ".")}
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        path.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                raise AssertionError("import circle: " + " -> ".join([*path[path.index(t):], t]))
            if t not in state:
                visit(t)
        path.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_no_module_over_700_lines() -> None:
    long = {m: n for m, p in MODULES.items() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def test_core_runs_without_ros_and_io_libraries() -> None:
    """Importing the whole core in a fresh interpreter loads no rclpy, rosbags, mcap, yaml or evo."""
    import subprocess

    code = ("import sys, importlib, pkgutil, epi_vo.core as c\n"
            "for m in pkgutil.walk_packages(c.__path__, 'epi_vo.core.'): importlib.import_module(m.name)\n"
            "bad = sorted({n.split('.')[0] for n in sys.modules} & {'rclpy', 'rosbags', 'mcap', 'yaml', 'evo'})\n"
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "", f"the core pulled in: {out.stdout.strip()}"


def _reads_reason_text(node: ast.AST) -> bool:
    """``x.reason`` (or ``x["reason"]``) searched or compared: ``... in r.reason``, ``r.reason == ...``,
    ``r.reason.startswith(...)``."""
    def is_reason(n: ast.AST) -> bool:
        return (isinstance(n, ast.Attribute) and n.attr == "reason") or (
            isinstance(n, ast.Subscript) and isinstance(n.slice, ast.Constant) and n.slice.value == "reason")

    if isinstance(node, ast.Compare):
        return (any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops) and is_reason(node.comparators[-1])) or (
            any(isinstance(op, (ast.Eq, ast.NotEq)) for op in node.ops)
            and any(is_reason(n) and isinstance(o, ast.Constant) for n in (node.left, *node.comparators)
                    for o in (node.left, *node.comparators)))
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and is_reason(node.func.value)
            and node.func.attr in ("startswith", "endswith", "find", "index", "count"))


def test_no_code_branches_on_a_reason_text() -> None:
    """Decisions are values (``FrameResult.decisions``, ``epi_vo.core.decisions``): no module of epi_vo searches
    or compares a ``reason`` sentence, which is rendered for people (``epi_vo.core.reasons``)."""
    bad = [f"{module}:{node.lineno}" for module, path in MODULES.items()
           for node in ast.walk(ast.parse(path.read_text(), str(path))) if _reads_reason_text(node)]
    assert not bad, bad
