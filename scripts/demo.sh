#!/usr/bin/env bash
# Set up (if needed) and run the VO on the bundled general-motion bag; outputs go to out/demo.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/epi-vo replay bags/general_motion/bag --output out/demo "$@"
