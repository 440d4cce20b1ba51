#!/usr/bin/env bash
# Packs the GPU test and benchmark binaries with the shared libraries they need into .device/
# (git-ignored), for the device machine. Build first:
#   cmake -S . -B build-gpu -DCMAKE_BUILD_TYPE=Release && make -C build-gpu -j2 test_gpu bench_gpu
set -euo pipefail
build=${1:-build-gpu}
rm -rf .device && mkdir -p .device
for b in "$build/tests/gpu/test_gpu" "$build/tools/bench_gpu"; do
  [ -x "$b" ] && cp "$b" .device/
done
for lib in libcudart.so.13 libspdlog.so.1.10 libfmt.so.9 libboost_program_options.so.1.74.0; do
  path=$(ldd .device/* 2>/dev/null | awk -v l="$lib" '$1 == l {print $3}' | head -1)
  [ -n "$path" ] && cp -L "$path" .device/
done
du -sh .device
ls .device
