"""The package builds as an ament_python package with colcon, its installed scripts run, and package.xml
declares what the code imports."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml
from test_launch import evaluate, load_launch_description

from epi_vo.core.config import VoConfig
from epi_vo.io.params import load_config

REPO = Path(__file__).resolve().parent.parent

# Top-level module imported -> its rosdep key; None: PyPI only, no rosdep key (the README says to pip install it).
IMPORT_TO_ROSDEP: dict[str, str | None] = {
    "rclpy": "rclpy",
    "builtin_interfaces": "builtin_interfaces",
    "diagnostic_msgs": "diagnostic_msgs",
    "geometry_msgs": "geometry_msgs",
    "lifecycle_msgs": "lifecycle_msgs",
    "nav_msgs": "nav_msgs",
    "rcl_interfaces": "rcl_interfaces",
    "rosgraph_msgs": "rosgraph_msgs",
    "sensor_msgs": "sensor_msgs",
    "std_msgs": "std_msgs",
    "std_srvs": "std_srvs",
    "tf2_ros": "tf2_ros",
    "tf2_msgs": "tf2_msgs",
    "numpy": "python3-numpy",
    "cv2": "python3-opencv",
    "yaml": "python3-yaml",
    "tqdm": "python3-tqdm",
    "matplotlib": "python3-matplotlib",
    "rich": "python3-rich",
    "scipy": "python3-scipy",
    "gtsam": "gtsam",
    "pytest": "python3-pytest",
    "hypothesis": "python3-hypothesis",
    "rosbags": None,
    "mcap": None,
    "evo": None,
}
# Declared run dependencies no module of epi_vo/ imports, and why they are there.
NOT_IMPORTED = {
    "launch": "launch/vo.launch.py",
    "launch_ros": "launch/vo.launch.py",
    "rviz2": "launch/vo.launch.py rviz:=true, config/epi_vo.rviz",
}


def _package_xml_depends() -> dict[str, list[str]]:
    """Tag (exec_depend, test_depend, depend, ...) -> the keys package.xml lists under it, in order."""
    root = ET.parse(REPO / "package.xml").getroot()
    out: dict[str, list[str]] = {}
    for element in root:
        if element.tag.endswith("depend"):
            out.setdefault(element.tag, []).append((element.text or "").strip())
    return out


def _third_party_imports(folder: Path) -> dict[str, set[str]]:
    """Top-level module -> files under ``folder`` that import it (every import, also inside functions), for
    modules that are neither the standard library, nor epi_vo, nor a module of this repository."""
    local = {p.stem for p in REPO.rglob("*.py") if not any(part.startswith(".venv") for part in p.parts)}
    out: dict[str, set[str]] = {}
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                roots = [a.name.split(".")[0] for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                roots = [node.module.split(".")[0]]
            else:
                continue
            for root in roots:
                if root not in sys.stdlib_module_names and root != "epi_vo" and root not in local:
                    out.setdefault(root, set()).add(str(path.relative_to(REPO)))
    return out


def test_default_params_file_equals_config_defaults() -> None:
    assert load_config(REPO / "config" / "epi_vo.yaml") == VoConfig()


def test_package_xml_declares_runtime_dependencies() -> None:
    text = (REPO / "package.xml").read_text()
    exec_deps = _package_xml_depends()["exec_depend"]
    for dep in ("rclpy", "sensor_msgs", "nav_msgs", "geometry_msgs", "diagnostic_msgs", "std_srvs", "tf2_ros",
                "launch", "launch_ros"):
        assert dep in exec_deps
    assert "<build_type>ament_python</build_type>" in text
    assert yaml.safe_load((REPO / "config" / "epi_vo.yaml").read_text())["/**"]["ros__parameters"]


def test_package_xml_lists_each_dependency_once() -> None:
    deps = _package_xml_depends()
    listed = [key for keys in deps.values() for key in keys]
    assert all(listed), "an empty dependency tag"
    assert len(listed) == len(set(listed)), sorted(k for k in listed if listed.count(k) > 1)


def test_every_module_the_package_imports_has_a_package_xml_dependency() -> None:
    imports = _third_party_imports(REPO / "epi_vo")
    unmapped = {m: sorted(f) for m, f in imports.items() if m not in IMPORT_TO_ROSDEP}
    assert not unmapped, f"add these imports to IMPORT_TO_ROSDEP and package.xml: {unmapped}"
    runtime = set(_package_xml_depends().get("exec_depend", [])) | set(_package_xml_depends().get("depend", []))
    missing = {m: IMPORT_TO_ROSDEP[m] for m in imports if IMPORT_TO_ROSDEP[m] not in runtime | {None}}
    assert not missing, f"imported by epi_vo/ but not an exec_depend of package.xml: {missing}"


def test_every_module_the_tests_import_has_a_package_xml_dependency() -> None:
    imports = _third_party_imports(REPO / "test")
    unmapped = {m: sorted(f) for m, f in imports.items() if m not in IMPORT_TO_ROSDEP}
    assert not unmapped, f"add these imports to IMPORT_TO_ROSDEP and package.xml: {unmapped}"
    deps = _package_xml_depends()
    declared = set(deps.get("exec_depend", [])) | set(deps.get("depend", [])) | set(deps.get("test_depend", []))
    missing = {m: IMPORT_TO_ROSDEP[m] for m in imports if IMPORT_TO_ROSDEP[m] not in declared | {None}}
    assert not missing, f"imported by test/ but not declared in package.xml: {missing}"


def test_package_xml_declares_nothing_the_code_does_not_use() -> None:
    deps = _package_xml_depends()
    used_keys = {IMPORT_TO_ROSDEP.get(m) for m in _third_party_imports(REPO / "epi_vo")}
    stale = [k for k in deps.get("exec_depend", []) if k not in used_keys and k not in NOT_IMPORTED]
    assert not stale, f"exec_depend that no module imports (drop it, or say why in NOT_IMPORTED): {stale}"
    test_keys = {IMPORT_TO_ROSDEP.get(m) for m in _third_party_imports(REPO / "test")}
    stale_tests = [k for k in deps.get("test_depend", []) if k not in test_keys]
    assert not stale_tests, f"test_depend that no test imports: {stale_tests}"


@pytest.mark.slow
def test_colcon_build_installs_scripts_into_lib(tmp_path: Path) -> None:
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.exists():
        pytest.fail("colcon is not installed in the test environment (scripts/setup.sh installs it)")
    src = tmp_path / "ws" / "src" / "epi_vo"
    # the work tree as it is: tracked files and new ones not yet committed (not the ignored ones)
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                           capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        if not (REPO / f).is_file():
            continue  # deleted in the work tree
        if f.startswith("bags/") and not f.endswith((".py", ".md", ".txt")):
            continue  # the bags are not part of the package
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / f, src / f)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    proc = subprocess.run([str(colcon), "build", "--base-paths", "src"], cwd=tmp_path / "ws", env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    install = tmp_path / "ws" / "install" / "epi_vo"
    assert (install / "lib" / "epi_vo" / "epi-vo").is_file()
    assert (install / "lib" / "epi_vo" / "vo_node").is_file()
    assert (install / "lib" / "epi_vo" / "vo_lifecycle_node").is_file()
    assert (install / "share" / "ament_index" / "resource_index" / "packages" / "epi_vo").is_file()
    share = install / "share" / "epi_vo"
    for rel in ("config/epi_vo.yaml", "config/epi_vo.rviz", "config/foxglove_layout.json", "launch/vo.launch.py",
                "package.xml"):
        assert (share / rel).read_bytes() == (REPO / rel).read_bytes(), rel
    # the installed launch file, resolved against the install tree: the files and the executable it names exist
    description = load_launch_description(share / "launch" / "vo.launch.py")
    nodes = evaluate(description, {"rviz": "true"}, share_dir=str(share))
    vo = next(n for n in nodes if n.executable == "vo_node")
    assert os.access(install / "lib" / vo.package / vo.executable, os.X_OK)
    assert Path(vo.parameters[0]).is_file() and Path(vo.parameters[0]).parent == share / "config"
    rviz = next(n for n in nodes if n.executable == "rviz2")
    assert Path(rviz.arguments[1]) == share / "config" / "epi_vo.rviz"
    site = next((install / "lib").glob("python3*/site-packages"))
    run = subprocess.run([str(install / "lib" / "epi_vo" / "epi-vo"), "params"], capture_output=True, text=True,
                         env=dict(env, PYTHONPATH=str(site)), timeout=120)
    assert run.returncode == 0, run.stderr
    printed = tmp_path / "printed.yaml"  # the node's own parameters are in it too: load_config accepts them
    printed.write_text(run.stdout)
    assert load_config(printed) == VoConfig()


def _pins(path: Path) -> dict[str, str]:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = line.split("==")
            pins[name.strip().lower()] = version.strip()
    return pins


def test_the_jazzy_requirements_differ_from_the_pinned_ones_in_the_system_libraries_only() -> None:
    """requirements-jazzy.txt (scripts/test_system_libs.sh) is requirements.txt with the OpenCV, numpy and
    scipy of a ROS 2 Jazzy robot on Ubuntu 24.04: a package pinned in one and not the other, or another
    version, would make its replay figures compare something else than those libraries."""
    pinned, jazzy = _pins(REPO / "requirements.txt"), _pins(REPO / "requirements-jazzy.txt")
    assert set(pinned) == set(jazzy)
    differ = {k: (pinned[k], jazzy[k]) for k in pinned if pinned[k] != jazzy[k]}
    assert differ == {"opencv-python-headless": (pinned["opencv-python-headless"], "4.6.0.66"),
                      "numpy": (pinned["numpy"], "1.26.4"), "scipy": (pinned["scipy"], "1.11.4")}
    assert "bash scripts/test_system_libs.sh" in (REPO / ".ci" / "run").read_text()


def test_the_type_checker_runs_strict_on_the_core_right_after_the_linter() -> None:
    """CI runs scripts/test.sh: ruff, then mypy (pinned) as setup.cfg configures it: strict on epi_vo/core, and
    no section of setup.cfg relaxes the core (the other layers it checks may be relaxed)."""
    import configparser

    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    files = [f.strip() for f in cfg.get("mypy", "files").split(",")]
    assert cfg.getboolean("mypy", "strict") and files[0] == "epi_vo/core", files
    relaxed = [m.strip() for s in cfg.sections() if s.startswith("mypy-") for m in s.removeprefix("mypy-").split(",")]
    assert not any(m.startswith(("epi_vo.core", "epi_vo.*")) for m in relaxed), relaxed
    lines = [ln.split("#")[0].strip() for ln in (REPO / "scripts" / "test.sh").read_text().splitlines()]
    lines = [ln for ln in lines if ln]
    ruff = next(i for i, ln in enumerate(lines) if ln.startswith(".venv/bin/ruff check"))
    assert lines[ruff + 1] == ".venv/bin/mypy"
    assert "mypy" in _pins(REPO / "requirements.txt")
