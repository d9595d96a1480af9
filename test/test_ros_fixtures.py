"""The test suite's ROS_DOMAIN_ID claim: two test processes on one machine never share a domain."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from ros_fixtures import DOMAIN_ID_BASE, DOMAIN_ID_SPAN, claim_domain_id

HOLDER = (
    "import sys; sys.path.insert(0, {test_dir!r}); import ros_fixtures; "
    "print(ros_fixtures.pick_domain_id(), flush=True); sys.stdin.read()"
)


def test_a_domain_held_by_another_process_is_not_claimed_and_is_free_again_after_it(tmp_path: Path) -> None:
    env = dict(os.environ, TMPDIR=str(tmp_path))
    code = HOLDER.format(test_dir=str(Path(__file__).parent))
    with subprocess.Popen([sys.executable, "-c", code], env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                          text=True) as holder:
        assert holder.stdout is not None and holder.stdin is not None
        held = int(holder.stdout.readline())
        assert DOMAIN_ID_BASE <= held < DOMAIN_ID_BASE + DOMAIN_ID_SPAN
        mine, fd = claim_domain_id(held - DOMAIN_ID_BASE, tmp_path)
        assert mine == DOMAIN_ID_BASE + (held - DOMAIN_ID_BASE + 1) % DOMAIN_ID_SPAN
        os.close(fd)
        holder.stdin.close()  # the holder ends: its lock goes with it
        assert holder.wait(timeout=60) == 0
    again, fd = claim_domain_id(held - DOMAIN_ID_BASE, tmp_path)
    os.close(fd)
    assert again == held


def test_every_domain_held_is_a_clear_error(tmp_path: Path) -> None:
    fds = [claim_domain_id(0, tmp_path)[1] for _ in range(DOMAIN_ID_SPAN)]
    try:
        with pytest.raises(RuntimeError, match="every ROS_DOMAIN_ID 50-99 is held"):
            claim_domain_id(7, tmp_path)
    finally:
        for fd in fds:
            os.close(fd)
