#!/usr/bin/env bash
# The whole test suite, from a fresh clone: builds .venv if needed, then runs pytest.
# Extra arguments go to pytest (e.g. scripts/run_tests.sh -k gp -x).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/python -m pytest "$@"
