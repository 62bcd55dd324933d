#!/usr/bin/env bash
# The main job, from a fresh clone: builds .venv if needed, then runs the demo.
# Extra arguments go to the demo (see: .venv/bin/dgp-demo --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/python -m dgp_ros.demo "$@"
