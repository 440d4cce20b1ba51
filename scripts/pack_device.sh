#!/usr/bin/env bash
# Packs the GPU test and benchmark binaries (and any extra binaries named after the build folder)
# with the shared libraries they need into a git-ignored folder (.device/ by default, or $DEVICE_DIR,
# which must start with .device), for the device machine. Build first:
#   cmake -S . -B build-gpu -DCMAKE_BUILD_TYPE=Release && make -C build-gpu -j2 test-gpu bench-gpu
# Usage: [DEVICE_DIR=.device-x] scripts/pack_device.sh [BUILD_DIR] [EXTRA_BINARY ...]
set -euo pipefail
build=${1:-build-gpu}
shift || true
dir=${DEVICE_DIR:-.device}
case "$dir" in .device*) ;; *) echo "DEVICE_DIR must start with .device (git-ignored)" >&2; exit 2 ;; esac
rm -rf "$dir" && mkdir -p "$dir"
for b in "$build/tests/gpu/test-gpu" "$build/tools/bench-gpu" "$@"; do
  if [ -x "$b" ]; then cp "$b" "$dir/"; fi
done
# Every shared library the binaries need except the C/C++ runtime and the driver, which the device
# host has (in newer versions).
ldd "$dir"/* 2>/dev/null | awk '$2 == "=>" && $3 ~ /^\// {print $1, $3}' | sort -u |
  while read -r name path; do
    case "$name" in
      libc.so*|libm.so*|libpthread.so*|libdl.so*|librt.so*|libgcc_s.so*|libstdc++.so*|ld-linux*|libcuda.so*) ;;
      *) cp -L "$path" "$dir/" ;;
    esac
  done
du -sh "$dir"
ls "$dir"
