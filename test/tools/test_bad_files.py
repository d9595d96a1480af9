"""Files and directories the command line is pointed at: every problem is one line naming it and exit status 2
(3 when the replay ran but frames were rejected), never a traceback; every tool that takes ``--params`` refuses
names that are not parameters.

Covers each subcommand that takes a file or directory: replay (bag, --params, --output, --gt, --report), report
DIR, inspect (bag, --params, --output), benchmark (--bags, --params, --output), soak (--bag, --params) and play
(bag; a subprocess with DDS on loopback and a domain of its own).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from test_bad_input import Item, Source, compressed, good_jpeg, info, records, source, truncated, write_bag

from epi_vo.cli import main

REPO = Path(__file__).resolve().parents[2]
SOURCE_BAG = REPO / "bags" / "general_motion" / "bag"

__all__ = ["source"]  # the fixture, shared with test_bad_input


def cli(args: Sequence[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    rc = main(list(args))
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "Traceback" not in out
    return rc, out, err


def one_line_error(rc: int, err: str, *texts: str, code: int = 2) -> None:
    assert rc == code, (rc, err)
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("epi-vo: error: "), err
    for t in texts:
        assert t in lines[0], (t, err)


@pytest.fixture(scope="module")
def bad_metadata_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The general_motion bag with a metadata.yaml that is not UTF-8 (a Latin-1 comment)."""
    bag = tmp_path_factory.mktemp("meta") / "bag"
    shutil.copytree(SOURCE_BAG, bag)
    with (bag / "metadata.yaml").open("ab") as f:
        f.write("# enregistré\n".encode("latin-1"))
    return bag


@pytest.fixture(scope="module")
def params_not_utf8(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("params") / "latin1.yaml"
    path.write_bytes("/**:\n  ros__parameters:\n    # caméra\n    max_features: 300\n".encode("latin-1"))
    return path


@pytest.fixture(scope="module")
def params_misspelt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("params") / "misspelt.yaml"
    path.write_text("vo_node:\n  ros__parameters:\n    max_featurs: 50\n    frame_id: odom\n")
    return path


MISSPELT = "unknown parameters: max_featurs (did you mean max_features?)"
NOT_UTF8 = "is not UTF-8 text (byte 0xe9 at offset"


@pytest.fixture(scope="module")
def all_rejected_bag(tmp_path_factory: pytest.TempPathFactory, source: list[Source]) -> Path:
    """Six frames whose camera is uncalibrated (K = 0): every frame is rejected."""
    items = [Item(compressed(s.jpeg, s.stamp_ns), info(s.info, s.stamp_ns, k=np.zeros(9))) for s in source[:6]]
    return write_bag(tmp_path_factory.mktemp("rejected") / "bag", items)


# ==================================================================================================
# replay
# ==================================================================================================
def test_replay_bag_with_metadata_not_utf8(tmp_path: Path, bad_metadata_bag: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = cli(["replay", str(bad_metadata_bag), "-o", str(tmp_path / "out"), "--no-progress"], capsys)
    one_line_error(rc, err, f"{bad_metadata_bag / 'metadata.yaml'} is not UTF-8 text (byte 0xe9 at offset")


@pytest.mark.parametrize("which", ["not_utf8", "misspelt"])
def test_replay_params(tmp_path: Path, params_not_utf8: Path, params_misspelt: Path, which: str,
                       capsys: pytest.CaptureFixture[str]) -> None:
    params, text = (params_not_utf8, NOT_UTF8) if which == "not_utf8" else (params_misspelt, MISSPELT)
    rc, _, err = cli(["replay", str(SOURCE_BAG), "-o", str(tmp_path / "out"), "--params", str(params),
                      "--no-progress"], capsys)
    one_line_error(rc, err, f"parameter file {params}", text)
    assert not (tmp_path / "out").exists()  # refused before anything was written


def test_replay_params_with_node_parameters_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """config/epi_vo.yaml plus the node's own parameters (as a vo_node parameter file has them) is a valid file."""
    params = tmp_path / "params.yaml"
    params.write_text((REPO / "config" / "epi_vo.yaml").read_text()
                      + "    frame_id: odom\n    image_transport: compressed\n    camera_xyz: [0.2, 0.0, 0.5]\n"
                        "    use_sim_time: true\n    max_features: 150\n")
    rc, _, err = cli(["replay", str(SOURCE_BAG), "-o", str(tmp_path / "out"), "--params", str(params),
                        "--no-progress"], capsys)
    assert rc == 0, err
    assert len(records(tmp_path / "out")) == 52
    import json

    assert json.loads((tmp_path / "out" / "stats.json").read_text())["parameters"]["max_features"] == 150


@pytest.mark.parametrize("case", ["existing_file", "under_a_file", "uncreatable"])
def test_replay_output_that_cannot_be_a_directory(tmp_path: Path, case: str,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("keep me\n")
    output, text = {
        "existing_file": (a_file, f"output {a_file} exists and is not a directory"),
        "under_a_file": (a_file / "out", f"cannot create the output directory {a_file / 'out'}: Not a directory"),
        "uncreatable": (Path("/proc/1/epi_vo_out"), "cannot create the output directory /proc/1/epi_vo_out: "),
    }[case]
    rc, _, err = cli(["replay", str(SOURCE_BAG), "-o", str(output), "--no-progress"], capsys)
    one_line_error(rc, err, text)
    assert a_file.read_text() == "keep me\n"


@pytest.mark.parametrize("name", ["frames.jsonl", "trajectory.tum", "output.mcap"])
def test_replay_output_file_that_is_a_directory(tmp_path: Path, name: str,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "out" / name).mkdir(parents=True)
    rc, _, err = cli(["replay", str(SOURCE_BAG), "-o", str(tmp_path / "out"), "--no-progress"], capsys)
    one_line_error(rc, err, str(tmp_path / "out" / name), "Is a directory")


def test_replay_gt_not_utf8(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gt = tmp_path / "gt.tum"
    gt.write_bytes(b"# \xe9\n1000.0 0 0 0 0 0 0 1\n")
    rc, _, err = cli(["replay", str(SOURCE_BAG), "-o", str(tmp_path / "out"), "--gt", str(gt), "--no-progress"],
                     capsys)
    one_line_error(rc, err, f"cannot read TUM file {gt}")


def test_replay_report_when_every_frame_was_rejected(tmp_path: Path, all_rejected_bag: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """It used to end in a ValueError from the trajectory plot's legend (nothing drawn)."""
    out = tmp_path / "out"
    rc, stdout, err = cli(["replay", str(all_rejected_bag), "-o", str(out), "--no-progress", "--report"], capsys)
    one_line_error(rc, err, "6 of 6 frames rejected", "camera is uncalibrated", code=3)
    assert f"report        {out / 'report.html'}" in stdout
    assert (out / "report.html").stat().st_size > 1000
    assert {p.name for p in (out / "report").iterdir()} == {"trajectory.png", "timeline.png"}
    rc, stdout, err = cli(["report", str(out)], capsys)  # and again on its own
    assert (rc, err, stdout) == (0, "", f"{out / 'report.html'}\n")


# ==================================================================================================
# report
# ==================================================================================================
@pytest.mark.parametrize("case", ["missing", "a_file", "frames_not_utf8", "html_is_a_directory", "png_dir_is_a_file"])
def test_report_dir_problems(tmp_path: Path, all_rejected_bag: Path, case: str,
                             capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    if case == "missing":
        text = f"{out}: no such directory"
    elif case == "a_file":
        out.write_text("x")
        text = f"{out}: not a directory"
    else:
        assert main(["replay", str(all_rejected_bag), "-o", str(out), "--no-progress"]) == 3
        capsys.readouterr()
        if case == "frames_not_utf8":
            (out / "frames.jsonl").write_bytes(b"\xff\n")
            text = "frames.jsonl"
        elif case == "html_is_a_directory":
            (out / "report.html").mkdir()
            text = f"cannot write the report in {out}: Is a directory"
        else:
            (out / "report").write_text("x")
            text = f"cannot write the report in {out}: File exists"
    rc, _, err = cli(["report", str(out)], capsys)
    one_line_error(rc, err, text)


# ==================================================================================================
# inspect
# ==================================================================================================
def test_inspect_bag_with_metadata_not_utf8(tmp_path: Path, bad_metadata_bag: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = cli(["inspect", str(bad_metadata_bag), "--frame", "3", "-o", str(tmp_path / "f.png")], capsys)
    one_line_error(rc, err, "metadata.yaml is not UTF-8 text")


@pytest.mark.parametrize("which", ["not_utf8", "misspelt"])
def test_inspect_params(tmp_path: Path, params_not_utf8: Path, params_misspelt: Path, which: str,
                        capsys: pytest.CaptureFixture[str]) -> None:
    params, text = (params_not_utf8, NOT_UTF8) if which == "not_utf8" else (params_misspelt, MISSPELT)
    rc, _, err = cli(["inspect", str(SOURCE_BAG), "--frame", "3", "--params", str(params), "-o",
                      str(tmp_path / "f.png")], capsys)
    one_line_error(rc, err, text)


def test_inspect_output_paths(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    rc, _, err = cli(["inspect", str(SOURCE_BAG), "--frame", "3", "-o", str(a_file / "f.png")], capsys)
    one_line_error(rc, err, f"cannot write {a_file / 'f.png'}: {a_file} is not a directory")
    # A directory: the picture goes into it under its default name.
    rc, out, err = cli(["inspect", str(SOURCE_BAG), "--frame", "3", "-o", str(tmp_path)], capsys)
    assert rc == 0 and out.splitlines()[0] == str(tmp_path / "frame_3.png"), err
    # Any other name: a PNG with exactly that name (not one with '.png' appended, not a format error).
    rc, out, err = cli(["inspect", str(SOURCE_BAG), "--frame", "3", "-o", str(tmp_path / "pic.txt")], capsys)
    assert rc == 0 and out.splitlines()[0] == str(tmp_path / "pic.txt"), err
    for png in (tmp_path / "frame_3.png", tmp_path / "pic.txt"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_inspect_past_and_at_a_damaged_frame(tmp_path: Path, source: list[Source],
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Frames before the one inspected are handled as the replay handles them (a damaged image is a rejected
    frame, not the end); the damaged frame itself cannot be drawn: one line says why."""
    bag = write_bag(tmp_path / "bag", [good_jpeg(s) for s in source[:12]], damage={("image", 4): truncated(40)})
    rc, _, err = cli(["inspect", str(bag), "--frame", "9", "-o", str(tmp_path / "f9.png")], capsys)
    assert rc == 0 and (tmp_path / "f9.png").is_file(), err
    rc, _, err = cli(["inspect", str(bag), "--frame", "4", "-o", str(tmp_path / "f4.png")], capsys)
    one_line_error(rc, err, "frame 4 (stamp", "was rejected: image message cannot be decoded: its 40 bytes of CDR")


# ==================================================================================================
# benchmark (every check happens before the long run)
# ==================================================================================================
@pytest.mark.parametrize("case", ["params_not_utf8", "params_misspelt", "output_dir", "output_under_file",
                                  "bags_file"])
def test_benchmark_arguments(tmp_path: Path, params_not_utf8: Path, params_misspelt: Path, case: str,
                             capsys: pytest.CaptureFixture[str]) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    args, text = {
        "params_not_utf8": (["--params", str(params_not_utf8)], NOT_UTF8),
        "params_misspelt": (["--params", str(params_misspelt)], MISSPELT),
        "output_dir": (["--output", str(tmp_path)], f"--output {tmp_path} is a directory"),
        "output_under_file": (["--output", str(a_file / "t.json")], f"{a_file} is not a directory"),
        "bags_file": (["--bags", str(a_file)], f"--bags {a_file} is not a directory"),
    }[case]
    rc, out, err = cli(["benchmark", *args], capsys)
    one_line_error(rc, err, text)
    assert out == ""  # nothing ran


# ==================================================================================================
# soak
# ==================================================================================================
def test_soak_bag_problems(tmp_path: Path, bad_metadata_bag: Path, source: list[Source],
                           capsys: pytest.CaptureFixture[str]) -> None:
    soak = ["soak", "--frames", "600", "--warmup", "500"]
    rc, _, err = cli([*soak, "--bag", str(bad_metadata_bag)], capsys)
    one_line_error(rc, err, "metadata.yaml is not UTF-8 text")
    damaged = write_bag(tmp_path / "bag", [good_jpeg(s) for s in source[:5]], damage={("image", 2): truncated(30)})
    rc, _, err = cli([*soak, "--bag", str(damaged)], capsys)
    one_line_error(rc, err, "no image message (its bytes could not be decoded)")


@pytest.mark.parametrize("which", ["not_utf8", "misspelt"])
def test_soak_params(params_not_utf8: Path, params_misspelt: Path, which: str, source: list[Source],
                     tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params, text = (params_not_utf8, NOT_UTF8) if which == "not_utf8" else (params_misspelt, MISSPELT)
    small = write_bag(tmp_path / "bag", [good_jpeg(s) for s in source[:4]])
    rc, _, err = cli(["soak", "--frames", "600", "--warmup", "500", "--bag", str(small), "--params", str(params)],
                     capsys)
    one_line_error(rc, err, text)


# ==================================================================================================
# play (starts rclpy: a subprocess on loopback with its own domain)
# ==================================================================================================
def test_play_bag_with_metadata_not_utf8(bad_metadata_bag: Path) -> None:
    from ros_fixtures import ros_test_env

    with ros_test_env() as ros:
        done = subprocess.run([sys.executable, "-m", "epi_vo.cli", "play", str(bad_metadata_bag), "--start-delay",
                               "0"], capture_output=True, text=True, cwd=REPO, env=ros.env, timeout=60)
    assert "Traceback" not in done.stderr
    one_line_error(done.returncode, done.stderr, f"cannot open bag {bad_metadata_bag}")
