"""No output of a replay lands on an input: an output that is an input (also through a symlink or a hard
link), or lies inside a bag directory, is refused before anything is written, for one bag and for a fleet
(epi_vo.tools.replay_outputs.check_outputs_clear)."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest
from bag_copies import BAGS, copy_frames, storage_file

from epi_vo.cli import main


def _tree(root: Path) -> dict[str, str]:
    """Every file under ``root`` with its SHA-256 (symlinks as their target text)."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink():
            out[str(p.relative_to(root))] = "-> " + os.readlink(p)
        elif p.is_file():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_frames(BAGS / "planar" / "bag", tmp_path_factory.mktemp("src") / "planar", 12)


def _refused(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("epi-vo: error: refused: output "), err
    assert all(w in lines[0] for w in words), err
    return lines[0]


def test_a_bag_named_as_an_output_is_refused_untouched(small_bag: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """``epi-vo replay D/output.mcap -o D``: the bag keeps every byte, nothing is written in D."""
    d = tmp_path / "D"
    d.mkdir()
    shutil.copy(storage_file(small_bag), d / "output.mcap")
    before = _tree(d)
    assert main(["replay", str(d / "output.mcap"), "-o", str(d), "--no-progress"]) == 2
    _refused(capsys, "would overwrite the input", "output.mcap")
    assert _tree(d) == before


def test_outputs_linked_to_an_input_are_refused(small_bag: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """OUT/output.mcap a symlink to the bag, OUT/trajectory.tum a hard link to the ground truth: both would be
    truncated through the link."""
    bag = tmp_path / "bag.mcap"
    shutil.copy(storage_file(small_bag), bag)
    gt = tmp_path / "gt.tum"
    shutil.copy(BAGS / "planar" / "groundtruth_tum.txt", gt)
    before = _tree(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "output.mcap").symlink_to(bag)
    assert main(["replay", str(bag), "-o", str(out), "--no-progress"]) == 2
    _refused(capsys, str(out / "output.mcap"), str(bag))
    (out / "output.mcap").unlink()
    os.link(gt, out / "trajectory.tum")
    assert main(["replay", str(bag), "-o", str(out), "--gt", str(gt), "--no-progress"]) == 2
    _refused(capsys, "trajectory.tum", str(gt))
    (out / "trajectory.tum").unlink()
    assert _tree(tmp_path) == {**before}
    # The ground truth a previous run kept beside its outputs cannot be the ground truth of a run into them.
    assert main(["replay", str(bag), "-o", str(out), "--gt", str(out / "groundtruth.tum"), "--no-progress"]) == 2


def test_a_bag_directory_is_no_output_directory(small_bag: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    bag = shutil.copytree(small_bag, tmp_path / "run1")
    before = _tree(bag)
    assert main(["replay", str(bag), "-o", str(bag), "--no-progress"]) == 2
    _refused(capsys, "would write into the input", str(bag))
    assert main(["replay", str(bag), "-o", str(bag / "out"), "--no-progress"]) == 2
    _refused(capsys, "would write into the input")
    assert _tree(bag) == before


def test_a_fleet_whose_outputs_would_overwrite_another_bag_runs_nothing(small_bag: Path, tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A bag D/g.mcap writes into D/g/; a bag stored at D/g/output.mcap would be overwritten by it. The whole
    fleet is refused before anything is written: no summary claims an "ok" built on a destroyed input."""
    d = tmp_path / "D"
    (d / "g").mkdir(parents=True)
    shutil.copy(storage_file(small_bag), d / "g.mcap")
    shutil.copy(storage_file(small_bag), d / "g" / "output.mcap")
    before = _tree(d)
    assert main(["replay", str(d / "**" / "*.mcap"), "-o", str(d), "--no-progress", "-j", "1"]) == 2
    _refused(capsys, str(d / "g" / "output.mcap"), "would overwrite the input")
    assert _tree(d) == before
    assert not (d / "summary.csv").exists()
    # Into a directory apart from the inputs, both are replayed, each once.
    out = tmp_path / "out"
    assert main(["replay", str(d / "**" / "*.mcap"), "-o", str(out), "--no-progress", "-j", "1"]) == 0
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["g", "output"]
    assert _tree(d) == before


def test_a_parameter_file_is_an_input_too(small_bag: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    params = out / "stats.json"  # an odd name, but a file the replay would replace
    params.write_text("/**:\n  ros__parameters:\n    max_features: 400\n")
    assert main(["replay", str(small_bag), "-o", str(out), "--params", str(params), "--no-progress"]) == 2
    _refused(capsys, "stats.json", "would overwrite the input")
    assert params.read_text().startswith("/**:")


def test_find_overlap_known_answers(tmp_path: Path) -> None:
    from epi_vo.io.paths import find_overlap

    bag_dir = tmp_path / "bag"
    bag_dir.mkdir()
    (bag_dir / "metadata.yaml").write_text("x")
    f = tmp_path / "a.mcap"
    f.write_text("x")
    assert find_overlap([f, bag_dir], [tmp_path / "out" / "a.mcap", tmp_path / "bag2" / "x"]) is None
    assert find_overlap([f], [tmp_path / "x" / ".." / "a.mcap"]).input == f  # the same path, spelt otherwise
    assert find_overlap([bag_dir], [bag_dir / "sub" / "output.mcap"]).input == bag_dir
    assert find_overlap([bag_dir], [bag_dir]).input == bag_dir
    (tmp_path / "hard").hardlink_to(f)
    assert find_overlap([f], [tmp_path / "hard"]).output == tmp_path / "hard"
