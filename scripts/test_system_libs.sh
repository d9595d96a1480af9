#!/usr/bin/env bash
# The replay accuracy tests on the libraries a ROS 2 Jazzy robot on Ubuntu 24.04 imports (system OpenCV
# 4.6, numpy 1.26, scipy 1.11: requirements-jazzy.txt), in their own .venv-jazzy beside the pinned .venv.
# Idempotent, as scripts/setup.sh: a second run with unchanged requirements only checks and runs the tests.
# Runs every bundled bag (and the KITTI clip when present) against ATE bounds (test/tools/test_bag_accuracy.py),
# the refit OpenCV 4.6 needs (test/core/test_polish.py) and shows the golden test skipping (its exact poses
# belong to the pinned libraries). Extra arguments go to pytest. docs/library_versions.md says why.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv-jazzy
if [ ! -x "$VENV/bin/python" ]; then
  echo "test_system_libs: creating $VENV with $($PY --version)"
  "$PY" -m venv "$VENV"
fi
stamp=$VENV/.epi_vo-requirements.sha256
want=$(sha256sum requirements-jazzy.txt setup.py | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "test_system_libs: installing requirements-jazzy.txt (first run takes a few minutes)"
  "$VENV/bin/python" -m pip install --quiet --upgrade pip 2>&1 | grep -v WARNING || true
  "$VENV/bin/python" -m pip install --quiet -r requirements-jazzy.txt 2>&1 | grep -v -E "^WARNING: Location|^$" || true
  "$VENV/bin/python" -m pip install --quiet --no-deps -e . 2>&1 | grep -v -E "^WARNING: Location|^$" || true
  echo "$want" > "$stamp"
fi
# The environment must be the one it claims to be: the Jazzy robot's OpenCV, numpy and scipy.
"$VENV/bin/python" - <<'PY' || { rm -f "$stamp"; echo "test_system_libs: $VENV is not the Jazzy library set" >&2; exit 1; }
import re
import cv2, numpy, scipy, evo, rosbags, epi_vo  # noqa: F401
want = {m.group(1).lower(): m.group(2) for m in re.finditer(r"^([A-Za-z0-9_.-]+)==(\S+)", open("requirements-jazzy.txt").read(), re.M)}
have = {"opencv-python-headless": cv2.__version__, "numpy": numpy.__version__, "scipy": scipy.__version__}
bad = [f"{k} {v} (want {want[k]})" for k, v in have.items() if not want[k].startswith(v)]
assert not bad, bad
print("test_system_libs: OpenCV", cv2.__version__, "numpy", numpy.__version__, "scipy", scipy.__version__)
PY
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
[[ -n "${ROS_DOMAIN_ID:-}" ]] || { source scripts/ros_domain.sh && claim_ros_domain_id; }
exec "$VENV/bin/python" -m pytest -p no:cacheprovider -rs test/tools/test_bag_accuracy.py test/core/test_polish.py \
  test/tools/test_golden.py "$@"
