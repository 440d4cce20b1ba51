#!/bin/bash
# Issue 22 (GPU fan-out), second call: GPU test suites; bench-zone CPU vs GPU replicate (sets read
# in place, and staged from the host); frames compared; zone-server --replicate gpu start log and
# /metrics; host-jitter before and after.
set -u
D=$(cd "$(dirname "$0")" && pwd)
export LD_LIBRARY_PATH=$D:${LD_LIBRARY_PATH:-}
O=${OUT:-/tmp/out}; mkdir -p "$O"
{ date -u; nvidia-smi -L; nproc; uptime; } > "$O/machine.txt" 2>&1
"$D/host-jitter" --threads 16 --work-us 500 --periods 300 > "$O/jitter.txt" 2>&1
{
  echo "== test_zone_gpu: GPU replication cases, with coverage"
  timeout 300 "$D/test_zone_gpu" -tc="GPU replication*" -s > /tmp/rep.txt 2>&1; rc=$?
  grep -E "MESSAGE|ERROR|test cases|assertions|Status|frame differs" /tmp/rep.txt | head -40; grep -m3 seed /tmp/rep.txt
  echo "rc=$rc"
  if [ "$rc" != 0 ]; then
    echo "== compute-sanitizer on the in-place case"
    timeout 150 compute-sanitizer --print-limit 5 "$D/test_zone_gpu" -tc="GPU replication reading*" 2>&1 | tail -40
  fi
  for t in test_zone_gpu test_gpu test_finders; do
    echo "== $t (whole suite)"
    timeout 300 "$D/$t" > /tmp/suite.txt 2>&1; rc=$?; tail -4 /tmp/suite.txt; echo "rc=$rc"
  done
} > "$O/tests.txt" 2>&1
{
  for m in "cpu" "gpu" "gpu --host-views"; do
    echo "== bench-zone --entities 80000 --clients 20000 --interest gpu --replicate $m"
    timeout 200 "$D/bench-zone" --entities 80000 --clients 20000 --interest gpu --replicate $m; echo "rc=$?"
  done
  echo "== bench-zone --entities 80000 --clients 20000 --interest gpu --replicate gpu-vs-cpu --ticks 60 --warmup 10"
  timeout 200 "$D/bench-zone" --entities 80000 --clients 20000 --interest gpu --replicate gpu-vs-cpu --ticks 60 --warmup 10; echo "rc=$?"
} > "$O/bench.txt" 2>&1
{
  echo "== zone-server --replicate gpu --npcs 20000 --port 0 --metrics-port 9123 (4 s)"
  "$D/zone-server" --replicate gpu --npcs 20000 --port 0 --metrics-port 9123 > /tmp/zs.txt 2>&1 & pid=$!
  sleep 4
  exec 3<>/dev/tcp/127.0.0.1/9123 && printf 'GET /metrics HTTP/1.0\r\nHost: x\r\n\r\n' >&3 && timeout 3 cat <&3 | grep -E "zone_replication_on_gpu|zone_ticks_total"
  exec 3>&-
  kill -INT $pid; wait $pid; echo "rc=$?"
  head -5 /tmp/zs.txt
} > "$O/server.txt" 2>&1
"$D/host-jitter" --threads 16 --work-us 500 --periods 300 > "$O/jitter_after.txt" 2>&1
date -u >> "$O/machine.txt"
