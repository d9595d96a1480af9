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
want=$(sha256sum requirements.txt setup.py | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "setup: installing pinned requirements (first run takes a few minutes)"
  .venv/bin/python -m pip install --quiet --upgrade pip 2>&1 | grep -v WARNING || true
  .venv/bin/python -m pip install --quiet -r requirements.txt 2>&1 | grep -v -E "^WARNING: Location|^$" || true
  .venv/bin/python -m pip install --quiet --no-deps -e . 2>&1 | grep -v -E "^WARNING: Location|^$" || true
  .venv/bin/python -c "import cv2, rosbags, evo, mcap, epi_vo" || { echo "setup: import check failed" >&2; exit 1; }
  echo "$want" > "$stamp"
fi
