#!/usr/bin/env bash
# OPTIONAL developer step (never run by CI): a Python venv with LeRobot's real
# DiffusionPolicy, used by scripts/make_lerobot_fixture.py (regenerates
# policies/tests/fixtures/lerobot_dp_tiny/) and scripts/bench_lerobot_dp.py.
#
#   bash scripts/lerobot_venv.sh      # prints the venv path on stdout
#   "$(bash scripts/lerobot_venv.sh)/bin/python" scripts/make_lerobot_fixture.py
#
# Idempotent: creates ${LABRIG_CACHE:-$HOME/.cache/labrig}/venv-lerobot if missing and
# pip-installs the pinned versions (a no-op when they are already there).
# Needs PyPI only. lerobot 0.4.x is the newest line that installs on Python 3.11; it
# pulls the default (CUDA-enabled) torch wheel from PyPI, ~2.7 GB download, ~6 GB on disk.
set -euo pipefail

LABRIG_CACHE="${LABRIG_CACHE:-$HOME/.cache/labrig}"
VENV="$LABRIG_CACHE/venv-lerobot"
PYTHON="${LABRIG_PYTHON:-python3.11}"
command -v "$PYTHON" >/dev/null 2>&1 || PYTHON=python3

# The versions the committed fixture was generated with.
PINS=(
    "lerobot==0.4.4"
    "torch==2.10.0"
    "torchvision==0.25.0"
    "diffusers==0.35.2"
    "safetensors==0.8.0"
    "numpy==2.2.6"
)

log() { printf '[lerobot_venv] %s\n' "$*" >&2; }

mkdir -p "$LABRIG_CACHE"
if [ ! -x "$VENV/bin/python" ]; then
    log "creating $VENV with $("$PYTHON" --version 2>&1)"
    "$PYTHON" -m venv "$VENV"
    "$VENV/bin/pip" install -q --upgrade pip >&2
fi

if "$VENV/bin/python" - "${PINS[@]}" <<'EOF' >/dev/null 2>&1
import sys
from importlib.metadata import version
for pin in sys.argv[1:]:
    name, want = pin.split("==")
    assert version(name) == want, pin
EOF
then
    log "pins already satisfied"
else
    log "installing ${PINS[*]}"
    "$VENV/bin/pip" install "${PINS[@]}" >&2
fi

echo "$VENV"
