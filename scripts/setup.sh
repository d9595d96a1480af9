#!/usr/bin/env bash
# Create .venv (Python 3.11) with the pinned requirements and the package (editable). Idempotent: a
# second run with unchanged requirements only checks and returns.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
stamp=.venv/.epi_vo-requirements.sha256
want=$(sha256sum requirements.txt bags/requirements.txt setup.py | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "setup: installing pinned requirements (first run takes a few minutes)"
  .venv/bin/python -m pip install --quiet --upgrade pip 2>&1 | grep -v WARNING || true
  .venv/bin/python -m pip install --quiet -r requirements.txt 2>&1 | grep -v -E "^WARNING: Location|^$" || true
  # The bundled bags' generator (bags/make_bags.py) and its tests: small, and without it those tests skip.
  .venv/bin/python -m pip install --quiet -r bags/requirements.txt 2>&1 | grep -v -E "^WARNING: Location|^$" || true
  .venv/bin/python -m pip install --quiet --no-deps -e . 2>&1 | grep -v -E "^WARNING: Location|^$" || true
  .venv/bin/python -c "import cv2, rosbags, evo, mcap, skimage, epi_vo" || { echo "setup: import check failed" >&2; exit 1; }
  echo "$want" > "$stamp"
fi
# The report test renders report.html in a real headless browser (Debian's chromium). Installed when
# missing and this user can (root with apt-get); otherwise that one test is skipped outside CI.
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "setup: installing chromium (headless browser for the report test)"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "setup: could not install chromium; the browser test will be skipped outside CI" >&2
fi
