#!/usr/bin/env bash
# Installs what the build needs from Debian's packages, idempotently and without prompts.
# Usage: scripts/setup.sh            (as root, or with sudo available)
set -euo pipefail

packages=(
  build-essential cmake
  libboost-dev libboost-program-options-dev
  libflatbuffers-dev flatbuffers-compiler
  libspdlog-dev libfmt-dev
  doctest-dev
  libcgal-dev libgmp-dev libmpfr-dev
  liburing-dev pkg-config
  python3
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
  exit 0
fi

echo "setup: installing ${missing[*]}"
sudo_cmd=()
if [ "$(id -u)" -ne 0 ]; then sudo_cmd=(sudo); fi
export DEBIAN_FRONTEND=noninteractive
"${sudo_cmd[@]}" apt-get update -qq
"${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}"
echo "setup: done"
