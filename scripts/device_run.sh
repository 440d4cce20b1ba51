#!/usr/bin/env bash
# Runs the GPU test suite and the GPU benchmark on the device machine from the binaries packed by
# scripts/pack_device.sh into .device/ (built here with CUDA arch 90, Release).
# Usage (on the device, from the repository root): scripts/device_run.sh [test] [bench ARGS...]
# Logs and CSV go to $OUT (or ./out when OUT is unset).
set -uo pipefail
out=${OUT:-out}
mkdir -p "$out"
export LD_LIBRARY_PATH=$PWD/.device${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.mem --format=csv; nproc; free -g; } \
  > "$out/device.txt" 2>&1
cat "$out/device.txt"
while [ $# -gt 0 ]; do
  case "$1" in
    test)
      shift
      echo "== test_gpu $(date -u +%FT%TZ)"
      .device/test-gpu -d 2>&1 | tee "$out/test_gpu.log" | grep -v '^$' | tail -25
      echo "test_gpu exit code: ${PIPESTATUS[0]}" | tee -a "$out/test_gpu.log"
      ;;
    bench)
      shift
      args=()
      while [ $# -gt 0 ] && [ "$1" != test ] && [ "$1" != bench ]; do args+=("$1"); shift; done
      echo "== bench-gpu ${args[*]} $(date -u +%FT%TZ)"
      .device/bench-gpu --csv "$out/bench.csv" "${args[@]}" 2>&1 | tee "$out/bench.log"
      echo "bench-gpu exit code: ${PIPESTATUS[0]}"
      ;;
    *) echo "unknown step $1"; exit 2 ;;
  esac
done
