#!/usr/bin/env bash
# README command 2: installs what is missing, builds, and runs every test through CTest.
# GPU suites report "Skipped" on a machine without a CUDA device.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh "$@"
ctest --test-dir "${ZONE_BUILD_DIR:-build}" --output-on-failure -j 2 --timeout 1200
