#!/usr/bin/env bash
# Set up (first run only) and run the whole test suite, one test process per CPU core (at
# most four; each starts its own stations, PostgreSQL and Redis). Extra arguments go to
# pytest: `-n 0` runs every test in this one process.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh test
cores=$(nproc 2>/dev/null || echo 1)
exec .venv/bin/python -m pytest -n "$(( cores < 4 ? cores : 4 ))" --dist worksteal "$@"
