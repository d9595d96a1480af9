#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite. DDS stays on this machine: every process started
# from here inherits ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, and the tests give each ROS process a
# domain id of its own (test/ros_fixtures.py); the one claimed here (scripts/ros_domain.sh) is for anything else.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
[[ -n "${ROS_DOMAIN_ID:-}" ]] || { source scripts/ros_domain.sh && claim_ros_domain_id; }
.venv/bin/ruff check epi_vo test bags
.venv/bin/mypy  # strict on epi_vo/core; io/, runner/ and the replay relaxed (setup.cfg [mypy])
exec .venv/bin/python -m pytest "$@"
