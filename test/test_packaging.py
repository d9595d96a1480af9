"""The package builds as an ament_python package with colcon and its installed scripts run."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from epi_vo.core.config import VoConfig
from epi_vo.io.params import load_config

REPO = Path(__file__).resolve().parent.parent


def test_default_params_file_equals_config_defaults() -> None:
    assert load_config(REPO / "config" / "epi_vo.yaml") == VoConfig()


def test_package_xml_declares_runtime_dependencies() -> None:
    text = (REPO / "package.xml").read_text()
    for dep in ("rclpy", "sensor_msgs", "nav_msgs", "geometry_msgs", "diagnostic_msgs", "std_srvs"):
        assert f"<exec_depend>{dep}</exec_depend>" in text
    assert "<build_type>ament_python</build_type>" in text
    assert yaml.safe_load((REPO / "config" / "epi_vo.yaml").read_text())["/**"]["ros__parameters"]


@pytest.mark.slow
def test_colcon_build_installs_scripts_into_lib(tmp_path: Path) -> None:
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.exists():
        pytest.fail("colcon is not installed in the test environment (scripts/setup.sh installs it)")
    src = tmp_path / "ws" / "src" / "epi_vo"
    files = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout.split()
    for f in files:
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
    assert (install / "share" / "ament_index" / "resource_index" / "packages" / "epi_vo").is_file()
    assert (install / "share" / "epi_vo" / "config" / "epi_vo.yaml").is_file()
    site = next((install / "lib").glob("python3*/site-packages"))
    run = subprocess.run([str(install / "lib" / "epi_vo" / "epi-vo"), "params"], capture_output=True, text=True,
                         env=dict(env, PYTHONPATH=str(site)), timeout=120)
    assert run.returncode == 0, run.stderr
    assert load_config_text(run.stdout) == VoConfig()


def load_config_text(text: str) -> VoConfig:
    from epi_vo.core.config import from_dict

    return from_dict(yaml.safe_load(text)["/**"]["ros__parameters"])
