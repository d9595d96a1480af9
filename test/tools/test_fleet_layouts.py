"""Fleet layouts a robot's logs have: standard rosbag2 directories found by the README's glob, symlink loops
(the glob ends), special files named as bags (refused, never opened), a second run whose output lies inside
the input tree (its outputs are no bags), and the exit status of a fleet with failed bags (4, apart from 2).

Commands that would hang on a defect (a FIFO opened for reading, a glob following symlink loops) run in a
subprocess with a generous bound: a hang is then a failure, not a stuck suite.
"""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from bag_copies import BAGS, REPO, copy_frames, storage_file

from epi_vo.cli import main

HANG_BOUND_S = 300  # far beyond the few seconds these runs take: only a hang reaches it


def _rows(out: Path) -> dict[str, dict[str, str]]:
    with (out / "summary.csv").open(newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def _cli(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "epi_vo.cli", *args], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=HANG_BOUND_S, check=False)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """logs/run1/ and logs/day2/run2/ as ros2 bag record leaves them (run1.mcap + metadata.yaml), and a lone
    logs/day2/loose.mcap."""
    root = tmp_path_factory.mktemp("logs") / "logs"
    copy_frames(BAGS / "planar" / "bag", root / "run1", 10)
    copy_frames(BAGS / "general_motion" / "bag", root / "day2" / "run2", 10)
    shutil.copy(storage_file(root / "run1"), root / "day2" / "loose.mcap")
    return root


def test_the_readme_glob_finds_rosbag2_directories_once(logs: Path) -> None:
    from epi_vo.tools.fleet_bags import find_bags

    found = find_bags([str(logs / "**" / "*.mcap")])
    assert [p.relative_to(logs).as_posix() for p in found] == ["day2/loose.mcap", "day2/run2", "run1"]
    # A bag directory and its storage file named together are one bag.
    again = find_bags([str(logs / "**" / "*.mcap"), str(logs / "run1"), str(storage_file(logs / "run1"))])
    assert len(again) == 4 and sum(p.name == "run1" for p in again) == 1


def test_a_second_run_into_the_input_tree_takes_no_output_for_a_bag(logs: Path, tmp_path: Path) -> None:
    tree = shutil.copytree(logs, tmp_path / "logs")
    pattern = str(tree / "**" / "*.mcap")
    out = tree / "out"
    assert main(["replay", pattern, "-o", str(out), "--no-progress", "-j", "1"]) == 0
    first = _rows(out)
    assert sorted(first) == ["loose", "run1", "run2"] and all(r["status"] == "ok" for r in first.values())
    assert main(["replay", pattern, "-o", str(out), "--no-progress", "-j", "1"]) == 0
    second = _rows(out)
    assert sorted(second) == ["loose", "run1", "run2"]
    assert all(r["run"] == "skipped: complete" for r in second.values())
    # Another output directory in the tree: the first run's outputs are still not bags.
    assert main(["replay", pattern, "-o", str(tree / "out2"), "--no-progress", "-j", "1"]) == 0
    assert sorted(_rows(tree / "out2")) == ["loose", "run1", "run2"]


def test_a_glob_through_symlink_loops_ends(logs: Path, tmp_path: Path) -> None:
    """Two links back to ancestors: a walk that follows them grows without end (2^depth paths)."""
    tree = shutil.copytree(logs, tmp_path / "logs")
    (tree / "day2" / "up").symlink_to("..")
    (tree / "run1" / "up2").symlink_to("../..")
    (tree / "link_to_run1").symlink_to("run1")  # a symlinked bag named by '*' is still found
    done = _cli("replay", str(tree / "**" / "*.mcap"), "-o", str(tmp_path / "out"), "--no-progress", "-j", "1")
    assert done.returncode == 0, done.stderr
    assert sorted(_rows(tmp_path / "out")) == ["loose", "run1", "run2"]
    done = _cli("replay", str(tree / "*"), "-o", str(tmp_path / "out3"), "--no-progress", "-j", "1")
    assert done.returncode == 0, done.stderr
    rows = _rows(tmp_path / "out3")  # day2's two bags, and run1 once (link_to_run1 is the same bag)
    assert len(rows) == 3 and sum(n in ("run1", "link_to_run1") for n in rows) == 1


def test_a_fifo_named_as_a_bag_is_refused_never_opened(logs: Path, tmp_path: Path) -> None:
    fifo = tmp_path / "camera.mcap"
    os.mkfifo(fifo)
    done = _cli("replay", str(fifo), "-o", str(tmp_path / "out"), "--no-progress")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip() == (f"epi-vo: error: {fifo} is a FIFO (named pipe), not a bag file or bag directory: "
                                   "refused (reading it could block or never end)")
    assert not (tmp_path / "out").exists()
    # Its ground truth or parameter file a FIFO: refused the same way, before any output is written.
    for flag, what in (("--gt", "TUM trajectory file"), ("--params", "parameter file")):
        done = _cli("replay", str(logs / "run1"), "-o", str(tmp_path / "out"), flag, str(fifo), "--no-progress")
        assert done.returncode == 2 and f"is a FIFO (named pipe), not a {what}" in done.stderr, done.stderr
        assert not (tmp_path / "out").exists()
    # In a directory of bags: its row says why, the others are replayed.
    d = tmp_path / "day"
    d.mkdir()
    os.mkfifo(d / "stuck.mcap")
    shutil.copy(storage_file(logs / "run1"), d / "good.mcap")
    done = _cli("replay", str(d), "-o", str(tmp_path / "fleet"), "--no-progress", "-j", "1")
    rows = _rows(tmp_path / "fleet")
    assert done.returncode == 4, done.stderr
    assert rows["good"]["status"] == "ok"
    assert rows["stuck"]["status"] == "failed" and "FIFO (named pipe)" in rows["stuck"]["reason"]
    # A bag directory whose storage file is a FIFO, and a device.
    bag = shutil.copytree(logs / "run1", tmp_path / "run1")
    storage_file(bag).unlink()
    os.mkfifo(bag / "run1.mcap")
    done = _cli("replay", str(bag), "-o", str(tmp_path / "out"), "--no-progress")
    assert done.returncode == 2 and "run1.mcap is a FIFO (named pipe), not a file of a bag" in done.stderr
    done = _cli("replay", os.devnull, "-o", str(tmp_path / "out"), "--no-progress")
    assert done.returncode == 2 and "is a character device, not a bag file" in done.stderr


def test_failed_bags_exit_4_never_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two bags failed: exit status 4 and the counts line says two (2 would read "arguments unusable")."""
    d = tmp_path / "d"
    d.mkdir()
    copy_frames(BAGS / "planar" / "bag", d / "good", 8)
    (d / "a_broken.mcap").write_bytes(b"\x89MCAP0\r\n not a bag")
    (d / "b_broken.mcap").write_bytes(b"\x89MCAP0\r\n not a bag either")
    assert main(["replay", str(d), "-o", str(tmp_path / "out"), "--no-progress", "-j", "1"]) == 4
    assert "3 bag(s): 1 ok, 2 failed" in capsys.readouterr().out
    assert main(["summarize", str(tmp_path / "out")]) == 4
