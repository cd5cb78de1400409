#!/usr/bin/env bash
# Set up (first run only) and run the end-to-end demo. Extra arguments go to `steelscan demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh run
exec .venv/bin/steelscan demo "$@"
