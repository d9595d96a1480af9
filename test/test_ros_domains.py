"""The test suite's ROS domain ids (test/ros_fixtures.py, scripts/ros_domain.sh): every concurrent session
(pytest runs, xdist workers, .ci/run) claims one no other holds. Each test claims in a lock directory of its
own (tmp_path), so it takes nothing from a real run; no DDS is started here."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from ros_fixtures import DomainIdError, claim_domain_id, domain_id_range

REPO = Path(__file__).resolve().parents[1]
HOLDER = """
import sys
sys.path.insert(0, {test!r})
from pathlib import Path
from ros_fixtures import claim_domain_id
domain_id, _fd = claim_domain_id(range({lo}, {hi}), Path({locks!r}), start={start})
print(domain_id, flush=True)
sys.stdin.read()  # hold the claim until the test closes stdin
"""


def _holder(locks: Path, ids: range, start: int) -> tuple[subprocess.Popen[str], int]:
    """A process that claims a domain id (from ``start``) and holds it until its stdin closes."""
    code = HOLDER.format(test=str(REPO / "test"), lo=ids.start, hi=ids.stop, locks=str(locks), start=start)
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    return proc, int(proc.stdout.readline())


def _release(proc: subprocess.Popen[str]) -> None:
    assert proc.stdin is not None
    proc.stdin.close()
    assert proc.wait(timeout=60) == 0


def test_concurrent_sessions_whose_pids_agree_get_different_domains(tmp_path: Path) -> None:
    """Two processes starting from the same id (as two pids equal modulo the range do) get two ids."""
    ids = range(200, 205)
    first, first_id = _holder(tmp_path, ids, start=7)
    try:
        second, second_id = _holder(tmp_path, ids, start=7)
        try:
            assert first_id == 202 and second_id == 203
            mine, fd = claim_domain_id(ids, tmp_path, start=7)  # a third: the next free one
            os.close(fd)
            assert mine == 204
        finally:
            _release(second)
    finally:
        _release(first)


def test_a_claim_ends_with_its_process(tmp_path: Path) -> None:
    """The id of a session that ended (or crashed: the kernel drops its lock) is free again."""
    ids = range(200, 202)
    proc, held = _holder(tmp_path, ids, start=0)
    _release(proc)
    again, fd = claim_domain_id(ids, tmp_path, start=0)
    os.close(fd)
    assert again == held == 200


def test_every_id_claimed_is_an_error_naming_the_range(tmp_path: Path) -> None:
    ids = range(200, 201)
    proc, _ = _holder(tmp_path, ids, start=0)
    try:
        with pytest.raises(DomainIdError, match=r"every ROS domain id 200-200 is claimed.*EPI_VO_TEST_DOMAIN_IDS"):
            claim_domain_id(ids, tmp_path)
    finally:
        _release(proc)


def test_the_range_is_handed_by_the_environment() -> None:
    assert domain_id_range("") == range(50, 100)
    assert domain_id_range("200-209") == range(200, 210)
    assert domain_id_range("7") == range(7, 8)
    for bad in ("209-200", "a-b", "230-240", "-3"):
        with pytest.raises(DomainIdError, match="not a range LO-HI of ROS domain ids within 0-232"):
            domain_id_range(bad)


def test_ci_shell_claims_exclude_the_fixtures_claims(tmp_path: Path) -> None:
    """scripts/ros_domain.sh (.ci/run, scripts/test.sh) and the fixtures lock the same files: a shell holding
    an id keeps the tests' processes off it, and the shell exports both DDS variables."""
    env = {**os.environ, "EPI_VO_ROS_DOMAIN_LOCKS": str(tmp_path), "EPI_VO_TEST_DOMAIN_IDS": "200-201"}
    env.pop("ROS_DOMAIN_ID", None)
    script = ("source scripts/ros_domain.sh && claim_ros_domain_id && "
              'echo "$ROS_DOMAIN_ID $ROS_AUTOMATIC_DISCOVERY_RANGE" && read -r _')
    shell = subprocess.Popen(["bash", "-c", script], cwd=REPO, env=env, stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    assert shell.stdout is not None
    try:
        shell_id, discovery = shell.stdout.readline().split()
        assert discovery == "LOCALHOST" and int(shell_id) in (200, 201)
        for start in (0, 1):  # wherever the fixtures start, they get the other id
            mine, fd = claim_domain_id(range(200, 202), tmp_path, start=start)
            os.close(fd)
            assert mine == 401 - int(shell_id)
        proc, _ = _holder(tmp_path, range(200, 202), start=0)
        try:  # both taken: the shell's claim fails with the range named
            taken = subprocess.run(["bash", "-c", "source scripts/ros_domain.sh && claim_ros_domain_id"], cwd=REPO,
                                   env=env, capture_output=True, text=True)
            assert taken.returncode == 1 and "every ROS domain id 200-201 is claimed" in taken.stderr
        finally:
            _release(proc)
    finally:
        assert shell.stdin is not None
        shell.stdin.close()
        shell.wait(timeout=60)
