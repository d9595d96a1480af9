#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite. DDS stays on this machine: every process started
# from here inherits ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, and the tests give each ROS process a
# domain id of its own (test/conftest.py); the one set here is only a loopback-safe default.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( ($$ % 90) + 10 ))}
.venv/bin/ruff check epi_vo test bags
.venv/bin/mypy  # strict on epi_vo/core; io/, runner/ and the replay relaxed (setup.cfg [mypy])
exec .venv/bin/python -m pytest "$@"
