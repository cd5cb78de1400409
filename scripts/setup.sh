#!/usr/bin/env bash
# Set up a fresh machine for steelscan, as far as it is needed:
#   scripts/setup.sh run    the station: system libraries, a virtualenv, the package and the
#                           dashboard's front-end libraries
#   scripts/setup.sh test   (the default) also the test tools ([dev]), the training tools
#                           ([train]: PyTorch, CPU build) and the services and browser the
#                           tests start (PostgreSQL, Redis, Chromium)
# Idempotent: a second run only checks and returns.
set -euo pipefail
cd "$(dirname "$0")/.."
level=${1:-test}
case "$level" in
  run|test) ;;
  *) echo "usage: scripts/setup.sh [run|test]" >&2; exit 2 ;;
esac

need_apt=()
# grep reads all of ldconfig's list: with -q it stops at the first match, and pipefail then
# counts ldconfig's broken pipe as the library missing
ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null || need_apt+=(libusb-1.0-0)
# Open3D's CPU rendering path also wants libgomp; present on Debian images with gcc.
ldconfig -p 2>/dev/null | grep 'libgomp.so.1' >/dev/null || need_apt+=(libgomp1)
if [ "$level" = "test" ]; then
  if [ "${STEELSCAN_BROWSER_TESTS:-1}" = "1" ] && ! command -v chromium >/dev/null 2>&1; then
    need_apt+=(chromium)
  fi
  # the scale-out's services, which the tests start in temporary folders (no system service)
  ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || need_apt+=(postgresql)
  command -v redis-server >/dev/null 2>&1 || need_apt+=(redis-server)
fi
# the dashboard's front-end libraries come from the npm registry (web/package-lock.json)
command -v npm >/dev/null 2>&1 || need_apt+=(nodejs npm)
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "setup: installing system packages: ${need_apt[*]}" >&2
  SUDO=""; [ "$(id -u)" = "0" ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv" >&2
  "$PY" -m venv .venv
fi
# one stamp per level: the test level holds the run level
stamp=.venv/.steelscan-$level
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "setup: installing steelscan ($level) into .venv (first run takes a few minutes)" >&2
  .venv/bin/python -m pip install -q --upgrade pip
  if [ "$level" = "test" ]; then
    # PyTorch for training the crack network: the CPU build (the default one pulls GBs of
    # CUDA); one retry: where only a package mirror answers, each of torch's dependencies
    # would otherwise wait out five retries of the unreachable index
    .venv/bin/python -c 'import torch' 2>/dev/null \
      || .venv/bin/python -m pip install -q --retries 1 'torch==2.13.0' \
        --extra-index-url https://download.pytorch.org/whl/cpu
    .venv/bin/python -m pip install -q -e '.[dev,train]'
    touch .venv/.steelscan-run
  else
    .venv/bin/python -m pip install -q -e .
  fi
  touch "$stamp"
fi

web_stamp=web/node_modules/.steelscan-installed
if [ ! -f "$web_stamp" ] || [ web/package-lock.json -nt "$web_stamp" ]; then
  echo "setup: installing the dashboard's front-end libraries (npm ci in web/)" >&2
  (cd web && npm ci --no-audit --no-fund --loglevel=error >/dev/null)
  touch "$web_stamp"
fi
