#!/usr/bin/env bash
# The main job, from a fresh clone: builds .venv if needed, then runs the demo.
# Extra arguments go to the demo (see: .venv/bin/dgp-demo --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
# one BLAS thread per process: small matrices, several processes (see dgp_ros/__init__.py)
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
exec .venv/bin/python -m dgp_ros.apps.demo "$@"
