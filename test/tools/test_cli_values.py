"""Numbers and ROS names on the command line that cannot be used: one line naming the option and the value,
exit status 2, no traceback, before anything acts on them (a NaN timeout would never expire, a rate of
1e-300 would overflow the first wait, rclpy would raise on a bad topic name after DDS started).

The commands that start rclpy run in a subprocess with DDS on loopback and a domain of their own; a run that
hangs on a defect reaches the generous bound and fails instead of blocking the suite.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from bag_copies import BAGS, REPO
from ros_fixtures import RosTestEnv, ros_test_env

from epi_vo.cli import main

HANG_BOUND_S = 120  # these runs take a second or two: only a hang reaches it
BAG = str(BAGS / "planar" / "bag")


@pytest.fixture(scope="module")
def ros_env() -> Iterator[RosTestEnv]:
    with ros_test_env() as env:
        yield env


CASES = [
    (["play", BAG, "--rate", "1e-300"], "rate must be 0 (as fast as acknowledged) or at least 0.001, got 1e-300"),
    (["play", BAG, "--rate", "nan"], "rate must be a finite number >= 0, got nan"),
    (["play", BAG, "--start-delay", "1e300"], "start_delay must be at most"),
    (["play", BAG, "--remap-image", "bad topic!"], "remap_image 'bad topic!' is not a valid ROS 2 topic name"),
    (["play", BAG, "--remap-camera-info", "cam//info"], "remap_camera_info 'cam//info' is not a valid ROS 2 topic"),
    (["play", BAG, "--namespace", "bad ns"], "namespace 'bad ns' is not a valid ROS 2 namespace"),
    (["monitor", "--odometry-topic", "bad topic!", "--once", "--timeout", "5"],
     "--odometry-topic 'bad topic!' is not a valid ROS 2 topic name"),
    (["monitor", "--vo-units-topic", "vo//units", "--once", "--timeout", "5"],
     "--vo-units-topic 'vo//units' is not a valid ROS 2 topic name"),
    (["monitor", "--node-name", "bad name", "--once", "--timeout", "5"],
     "--node-name 'bad name' is not a valid ROS 2 node name"),
    (["monitor", "--timeout", "nan", "--once"], "--timeout must be a finite number, not nan"),
    (["monitor", "--timeout", "-1", "--once"], "--timeout must be a positive number, not -1.0"),
    (["latency", "--rates", "0"], "--rates must be a positive number, not 0.0"),
    (["latency", "--rates", "30,nan"], "--rates must be a finite number, not nan"),
    (["latency", "--rates", "30,fast"], "--rates must be comma-separated numbers, not 'fast'"),
    (["latency", "--rates", "1e9"], "--rates must be at most 1000, not 1000000000.0"),
    (["latency", "--rates", "30", "--seconds", "0.01"], "--seconds 0.01 at 30 Hz publishes no frame"),
]


def _id(args: list[str]) -> str:
    return " ".join(a for a in args if a != BAG)


@pytest.mark.parametrize(("args", "said"), CASES, ids=[_id(c[0]) for c in CASES])
def test_ros_commands_refuse_unusable_values(ros_env: RosTestEnv, args: list[str], said: str) -> None:
    done = subprocess.run([sys.executable, "-m", "epi_vo.cli", *args], capture_output=True, text=True, cwd=REPO,
                          env={**ros_env.env, "PYTHONPATH": str(REPO)}, timeout=HANG_BOUND_S, check=False)
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("epi-vo: error: ") and said in lines[0], done.stderr


OFFLINE = [
    (["soak", "--warmup", "-5", "--frames", "10"], "--warmup must be at least 0, not -5"),
    (["soak", "--every", "0", "--frames", "10", "--warmup", "2"], "--every must be at least 1, not 0"),
    (["soak", "--max-growth", "nan", "--frames", "10", "--warmup", "2"], "--max-growth must be a finite number"),
    (["inspect", BAG, "--stamp", "nan"], "--stamp must be a finite number, not nan"),
    (["inspect", BAG, "--stamp", "-3"], "--stamp must be at least 0, not -3.0"),
    (["replay", BAG, "-o", "unused", "--rate", "inf"], "--rate must be a finite number, not inf"),
]


@pytest.mark.parametrize(("args", "said"), OFFLINE, ids=[_id(c[0]) for c in OFFLINE])
def test_offline_commands_refuse_unusable_values(args: list[str], said: str, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # nothing may be written: inspect's picture, replay's outputs
    assert main(args) == 2
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("epi-vo: error: ") and said in lines[0], captured.err
    assert not list(tmp_path.iterdir())


def test_ros_names_agree_with_rcl(ros_env: RosTestEnv) -> None:
    """The name checks accept what rcl accepts and refuse what it refuses (or what DDS could not carry:
    '//' and overlong names, which rcl's first check lets through and its full-name check refuses)."""
    from rclpy.validate_namespace import validate_namespace
    from rclpy.validate_node_name import validate_node_name
    from rclpy.validate_topic_name import validate_topic_name

    from epi_vo.io import checks

    def ok(fn: object, *a: str) -> bool:
        try:
            fn(*a)  # type: ignore[operator]
        except Exception:  # ConfigError from ours, rclpy's own exceptions from rcl's
            return False
        return True

    names = ["camera/image_raw", "/camera/image_raw", "~/x", "~", "bad topic!", "a/", "/", "", "1abc", "a/1b",
             "{node}/x", "a{b}", "a~b", "_a/b_", "vo/odometry", "/a/b/c", "a-b", "/ns/", "ns", "x.y", "ä"]
    for n in names:
        assert ok(checks.topic_name, n, "t") == ok(validate_topic_name, n), n
        assert ok(checks.namespace, n, "n") == ok(validate_namespace, n if n.startswith("/") else f"/{n}"), n
        if not n.startswith("/"):
            assert ok(checks.node_name, n, "n") == ok(validate_node_name, n), n
    assert not ok(checks.topic_name, "a//b", "t") and not ok(checks.topic_name, "x" * 300, "t")
