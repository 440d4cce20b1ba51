#!/usr/bin/env bash
# Installs what the build needs from Debian's packages, idempotently and without prompts.
# Usage: scripts/setup.sh            (as root, or with sudo available)
set -euo pipefail

packages=(
  build-essential cmake
  libboost-dev libboost-program-options-dev
  libflatbuffers-dev flatbuffers-compiler
  libspdlog-dev libfmt-dev
  nlohmann-json3-dev  # JSON output (bot-swarm's report, the viewer)
  libtbb-dev  # bench-pool: the thread pool beside oneTBB (docs/zone-benchmarks.md)
  doctest-dev
  libcgal-dev libgmp-dev libmpfr-dev
  liburing-dev pkg-config
  python3
  nats-server libnats-dev  # the world of zones (world/, docs/world.md)
  chromium
  clang libclang-rt-14-dev  # the fuzz targets (fuzz/, scripts/fuzz.sh): clang's libFuzzer, ASan, UBSan
)

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "setup: all build dependencies are installed"
else
  echo "setup: installing ${missing[*]}"
  sudo_cmd=()
  if [ "$(id -u)" -ne 0 ]; then sudo_cmd=(sudo); fi
  export DEBIAN_FRONTEND=noninteractive
  "${sudo_cmd[@]}" apt-get update -qq
  "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

# The viewer's browser test (tests/viewer): playwright-core from npm, pinned by its lock file, into
# tests/viewer/node_modules (git-ignored). It downloads no browser: the test drives chromium above.
# Without node and npm the test is skipped.
viewer_dir="$(dirname "$0")/../tests/viewer"
if [ -d "$viewer_dir/node_modules/playwright-core" ]; then
  echo "setup: playwright-core is installed"
elif command -v npm > /dev/null; then
  echo "setup: installing playwright-core into tests/viewer/node_modules"
  PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 npm ci --prefix "$viewer_dir" --no-audit --no-fund --loglevel=error
else
  echo "setup: npm not found: the viewer's browser test will be skipped (install node and npm, then rerun)"
fi
echo "setup: done"
