"""Fleet replay (``epi-vo replay`` over several bags) and ``epi-vo summarize``.

Small bags are written by fixtures into tmp_path (the first frames of bundled bags); one more is broken.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from bag_copies import BAGS, REPO, TYPESTORE, copy_frames
from rosbags.highlevel import AnyReader

from epi_vo.cli import main
from epi_vo.tools.fleet_bags import find_bags, is_fleet, output_names
from epi_vo.tools.fleet_summary import EXIT_BAGS_FAILED, BagRow, BagStatus, exit_code, row_from_directory
from epi_vo.tools.replay import run_replay


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three bags of 30 frames (general_motion, planar, pure_rotation) and a broken one."""
    d = tmp_path_factory.mktemp("fleet")
    for name in ("general_motion", "planar"):
        copy_frames(BAGS / name / "bag", d / name, 30)
    (d / "zz_broken.mcap").write_bytes(b"\x89MCAP0\r\n this is no bag")
    return d


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with (out / "summary.csv").open(newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def _records(out: Path) -> list[dict]:
    """frames.jsonl without the measured times (the only thing two runs of one bag may differ in)."""
    recs = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    for r in recs:
        r.pop("timings_ms")
    return recs


@pytest.fixture(scope="module")
def fleet_run(fleet_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    out = tmp_path_factory.mktemp("fleet_out")
    rc = main(["replay", str(fleet_dir), "--output", str(out), "--jobs", "2", "--no-progress"])
    return out, rc


def test_one_row_per_bag_and_the_broken_one_failed(fleet_run: tuple[Path, int]) -> None:
    out, rc = fleet_run
    rows = _summary(out)
    assert list(rows) == ["general_motion", "planar", "zz_broken"]
    assert rc == EXIT_BAGS_FAILED  # one bag failed
    for name in ("general_motion", "planar"):
        r = rows[name]
        assert r["status"] == "ok" and r["reason"] == "" and r["run"] == "replayed", r
        assert int(r["frames"]) == 30 and float(r["with_pose_percent"]) > 80
        assert int(r["keyframes"]) >= 2 and int(r["state_tracking"]) > 0
        assert float(r["ate_percent_of_path"]) < 10 and float(r["rpe_rot_deg_per_frame"]) < 0.2  # ground truth in bag
        assert 0.1 < float(r["nees_pos"]) < 20 and 0.1 < float(r["nees_twist_angular"]) < 20  # the covariance judged
        assert r["scale_source"] == "none" and r["metric_scale"] == "no"
        assert float(r["ms_per_frame"]) > 0 and float(r["end_to_end_fps"]) > 0
    broken = rows["zz_broken"]
    assert broken["status"] == "failed" and "zz_broken.mcap" in broken["reason"] and broken["frames"] == ""
    assert broken["nees_pos"] == ""
    md = (out / "summary.md").read_text()
    assert "3 bag(s): 2 ok, 1 failed" in md and md.count("\n| ") == 4  # header + three rows
    assert not (out / "index.html").exists()  # only with --report


def test_each_bag_as_its_single_run(fleet_run: tuple[Path, int], fleet_dir: Path, tmp_path: Path) -> None:
    out, _ = fleet_run
    for name in ("general_motion", "planar"):
        single = tmp_path / name
        run_replay(fleet_dir / name, single)
        assert sorted(p.name for p in single.iterdir()) == sorted(
            p.name for p in (out / name).iterdir() if p.name != "status.json")
        assert (out / name / "trajectory.tum").read_bytes() == (single / "trajectory.tum").read_bytes()
        assert _records(out / name) == _records(single)
    assert json.loads((out / "zz_broken" / "status.json").read_text())["status"] == "failed"


def test_resume_skips_complete_bags_and_force_redoes_them(fleet_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ["replay", str(fleet_dir / "general_motion"), str(fleet_dir / "zz_broken.mcap"), "-o", str(out),
            "--no-progress"]
    assert main(args) == EXIT_BAGS_FAILED
    files = [out / "general_motion" / f for f in ("stats.json", "trajectory.tum", "frames.jsonl", "output.mcap")]
    before = [f.stat().st_mtime_ns for f in files]
    assert main(args) == EXIT_BAGS_FAILED
    assert [f.stat().st_mtime_ns for f in files] == before  # not replayed
    rows = _summary(out)
    assert rows["general_motion"]["run"] == "skipped: complete" and rows["general_motion"]["status"] == "ok"
    assert int(rows["general_motion"]["frames"]) == 30
    assert rows["zz_broken"]["run"] == "replayed" and rows["zz_broken"]["status"] == "failed"  # tried again
    assert "skipped: complete" in (out / "summary.md").read_text()
    # Other parameters: not the same replay, so done again.
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    max_features: 400\n")
    assert main([*args, "--params", str(params)]) == EXIT_BAGS_FAILED
    assert _summary(out)["general_motion"]["run"] == "replayed"
    before = [f.stat().st_mtime_ns for f in files]
    assert main([*args, "--params", str(params), "--force"]) == EXIT_BAGS_FAILED
    assert _summary(out)["general_motion"]["run"] == "replayed"
    assert all(f.stat().st_mtime_ns != b for f, b in zip(files, before, strict=True))
    # vo_node's map_frame_id changes /vo/odometry and /tf: not the same replay either.
    params.write_text("/**:\n  ros__parameters:\n    max_features: 400\n    map_frame_id: map\n")
    assert main([*args, "--params", str(params)]) == EXIT_BAGS_FAILED
    assert _summary(out)["general_motion"]["run"] == "replayed"
    assert json.loads((out / "general_motion" / "stats.json").read_text())["map_frame_id"] == "map"
    assert main([*args, "--params", str(params)]) == EXIT_BAGS_FAILED
    assert _summary(out)["general_motion"]["run"] == "skipped: complete"


def test_summarize_rebuilds_the_summary(fleet_run: tuple[Path, int], tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    out, _ = fleet_run
    expected = _summary(out)
    dest = tmp_path / "again"
    assert main(["summarize", str(out), "--output", str(dest)]) == EXIT_BAGS_FAILED
    rows = _summary(dest)
    assert list(rows) == list(expected)
    for name, row in rows.items():
        for key in ("status", "reason", "frames", "keyframes", "state_tracking", "model_E", "ate_percent_of_path",
                    "ms_per_frame", "end_to_end_fps"):
            assert row[key] == expected[name][key], (name, key)
    assert "2 ok, 1 failed" in capsys.readouterr().out
    # Output directories of single-bag runs (one bag per cluster job): no status.json, stats.json says it all.
    single = tmp_path / "jobs"
    run_replay(Path(expected["planar"]["bag"]), single / "planar")
    (single / "lost").mkdir()
    (single / "lost" / "frames.jsonl").write_text("")  # started, never finished
    assert main(["summarize", str(single)]) == EXIT_BAGS_FAILED
    rows = _summary(single)
    assert rows["planar"]["status"] == "ok" and rows["planar"]["frames"] == "30"
    assert rows["lost"]["status"] == "incomplete" and "stats.json" in rows["lost"]["reason"]


def test_a_clean_bag_whose_replay_asks_to_check_the_calibration_says_so_in_its_row(
        fleet_run: tuple[Path, int], tmp_path: Path) -> None:
    """The replay's note on rotation-only frames that are pure only under another focal length becomes the
    reason of an ok row (``status_of``, as a fleet records it at the bag's end and ``summarize`` reads a
    single-bag output); other notes do not."""
    out, _ = fleet_run
    copy = tmp_path / "planar"
    shutil.copytree(out / "planar", copy)
    (copy / "status.json").unlink()  # a single-bag replay's directory
    assert row_from_directory(copy).status is BagStatus.OK and row_from_directory(copy).reason == ""
    note = ("check the camera calibration: 44 frames fit a pure rotation under a focal length 1.111 x "
            "camera_info's (median; per frame: focal_ratio)")
    stats = json.loads((copy / "stats.json").read_text())
    stats["notes"] = ["the bag announces 29 images on /camera/image_raw, 30 were read", note]
    (copy / "stats.json").write_text(json.dumps(stats))
    row = row_from_directory(copy)
    assert row.status is BagStatus.OK and row.reason == note


def test_summarize_of_nothing_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["summarize", str(tmp_path)]) == 2
    assert "holds no replay outputs" in capsys.readouterr().err


def test_which_arguments_make_a_fleet(fleet_dir: Path) -> None:
    assert not is_fleet([str(fleet_dir / "planar")])  # one bag: the single-bag replay, outputs in OUT/
    assert not is_fleet([str(fleet_dir / "missing")])  # its error, as before
    assert is_fleet([str(fleet_dir)])
    assert is_fleet([str(fleet_dir / "planar"), str(fleet_dir / "general_motion")])
    assert is_fleet([str(fleet_dir / "p*")])
    assert [p.name for p in find_bags([str(fleet_dir / "*")])] == ["general_motion", "planar", "zz_broken.mcap"]
    # A storage file of a bag directory stands for the directory (once, whatever its split files).
    assert [p.name for p in find_bags([str(fleet_dir / "**" / "*.mcap")])] == ["general_motion", "planar",
                                                                              "zz_broken.mcap"]
    assert [p.name for p in find_bags([str(fleet_dir), str(fleet_dir / "planar")])] == [
        "general_motion", "planar", "zz_broken.mcap"]  # each once


def test_a_directory_whose_bags_are_one_level_down_says_how_to_name_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """bags/ itself: bags/<name>/bag. A directory is a fleet of the bags directly in it, so this one
    is none; the error names the glob that is ('bags/*', whose directories each hold a bag)."""
    assert main(["replay", str(BAGS), "--output", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "holds no bag itself but its sub-directories hold 6" in err and f"'{BAGS / '*'}'" in err
    assert not (tmp_path / "o").exists()
    assert [p.parent.name for p in find_bags([str(BAGS / "*")])] == [
        "general_motion", "ground_robot", "moving_mover", "planar", "pure_rotation", "static_mover"]


def test_output_names_are_unique() -> None:
    bags = [BAGS / "general_motion" / "bag", BAGS / "planar" / "bag", Path("/data/run1.mcap"), Path("/x/run2")]
    assert output_names(bags) == ["general_motion-bag", "planar-bag", "run1", "run2"]
    assert output_names([Path("/a/x/bag"), Path("/b/x/bag")]) == ["a-x-bag", "b-x-bag"]


def test_exit_code_says_failed_bags_apart_from_unusable_arguments() -> None:
    """Any number of failed bags is exit status 4 (never 2, "arguments unusable", nor a signal's 129 / 130);
    bags with problems only, 3, as a single replay with rejected frames."""
    def row(status: BagStatus) -> BagRow:
        return BagRow("n", "b", status, "", "", "")

    assert exit_code([row(BagStatus.OK)] * 3) == 0
    assert exit_code([row(BagStatus.OK), row(BagStatus.PROBLEMS)]) == 3
    for n in (1, 2, 129, 130, 500):
        assert exit_code([row(BagStatus.FAILED), row(BagStatus.INCOMPLETE), row(BagStatus.OK)][:2] * n) == 4


def test_gt_file_is_for_one_bag_only(fleet_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["replay", str(fleet_dir), "-o", str(tmp_path / "o"), "--gt", str(tmp_path / "gt.tum")])
    assert rc == 2 and "--gt" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------------
# Interrupt


def _count_lines(path: Path) -> int:
    try:
        return path.read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def _default_signals() -> None:
    """In the child: SIGINT handled as usual even when pytest runs as a background job (which ignores it)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_interrupt_leaves_finished_bags_valid(fleet_dir: Path, tmp_path: Path) -> None:
    bags = tmp_path / "bags"
    bags.mkdir()
    copy_frames(fleet_dir / "planar", bags / "a_short", 20)
    copy_frames(BAGS / "general_motion" / "bag", bags / "b_long", 52, repeat=6)  # ~600 frames
    copy_frames(fleet_dir / "planar", bags / "c_short", 20)
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "epi_vo.cli", "replay", str(bags), "-o", str(out), "--jobs", "1",
                             "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, preexec_fn=_default_signals)
    try:
        deadline = time.monotonic() + 120.0
        # The first bag finished and the second is being replayed (10 of its ~600 frames written).
        while not (out / "a_short" / "stats.json").exists() or _count_lines(out / "b_long" / "frames.jsonl") < 10:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the first bag did not finish or the second did not start"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, (proc.returncode, stderr)
    assert "Traceback" not in stderr and "interrupted" in stderr
    rows = _summary(out)
    assert rows["a_short"]["status"] == "ok" and rows["a_short"]["frames"] == "20"
    assert rows["b_long"]["status"] == "interrupted", rows["b_long"]
    assert "the fleet was interrupted after" in rows["b_long"]["reason"]
    assert rows["c_short"]["status"] == "not run"
    # The finished bag: every output complete and readable.
    stats = json.loads((out / "a_short" / "stats.json").read_text())
    recs = _records(out / "a_short")
    assert stats["frames"] == len(recs) == 20
    with AnyReader([out / "a_short" / "output.mcap"], default_typestore=TYPESTORE) as reader:
        assert sum(1 for c, _, _ in reader.messages() if c.topic == "/vo/odometry") == 20
    tum = np.loadtxt(out / "a_short" / "trajectory.tum", ndmin=2)
    assert tum.shape[0] == sum(r["has_pose"] for r in recs)
    # The interrupted one is marked, never taken for complete; its outputs still agree on the frames written.
    long_dir = out / "b_long"
    assert not (long_dir / "stats.json").exists()
    assert json.loads((long_dir / "status.json").read_text())["status"] == "interrupted"
    recs = _records(long_dir)
    assert 10 <= len(recs) < 600
    with AnyReader([long_dir / "output.mcap"], default_typestore=TYPESTORE) as reader:
        assert sum(1 for c, _, _ in reader.messages() if c.topic == "/vo/odometry") == len(recs)
    # Resume: the finished bag is skipped, the others are replayed.
    mtime = (out / "a_short" / "stats.json").stat().st_mtime_ns
    assert main(["replay", str(bags / "a_short"), str(bags / "c_short"), "-o", str(out), "--no-progress"]) == 0
    assert (out / "a_short" / "stats.json").stat().st_mtime_ns == mtime
    rows = _summary(out)
    assert rows["a_short"]["run"] == "skipped: complete" and rows["c_short"]["status"] == "ok"
    # summarize sees the interrupted bag for what it is.
    assert main(["summarize", str(out)]) == EXIT_BAGS_FAILED
    assert _summary(out)["b_long"]["status"] == "interrupted"


def test_a_bag_directory_without_metadata_gets_its_row(fleet_dir: Path, tmp_path: Path) -> None:
    """A recorder that died leaves its bag directory without metadata.yaml: a directory of bags still
    finds its storage file, which replays (here: a good one) or fails with its reason (a truncated one),
    instead of being passed over in silence."""
    day = tmp_path / "day"
    (day / "crashed_good").mkdir(parents=True)
    (day / "crashed_bad").mkdir()
    (day / "notes").mkdir()
    (day / "notes" / "readme.txt").write_text("not a bag")
    shutil.copy(next((fleet_dir / "planar").glob("*.mcap")), day / "crashed_good" / "crashed_good_0.mcap")
    (day / "crashed_bad" / "crashed_bad_0.mcap").write_bytes(b"\x89MCAP0\r\n truncated by a power cut")
    assert [p.name for p in find_bags([str(day)])] == ["crashed_bad_0.mcap", "crashed_good_0.mcap"]
    out = tmp_path / "out"
    rc = main(["replay", str(day), "--output", str(out), "--jobs", "1", "--no-progress"])
    rows = _summary(out)
    assert set(rows) == {"crashed_bad_0", "crashed_good_0"}
    assert rows["crashed_good_0"]["status"] == "ok" and int(rows["crashed_good_0"]["frames"]) == 30
    assert rows["crashed_bad_0"]["status"] == "failed" and rows["crashed_bad_0"]["reason"]
    assert rc == EXIT_BAGS_FAILED
