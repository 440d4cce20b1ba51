#!/usr/bin/env bash
# The zone benchmarks of issues 4 and 5 on the device machine (docs/zone-benchmarks.md), from
# binaries packed here by scripts/pack_device.sh into $DEVICE_DIR (default .device):
#   cmake --build build --target test-zone-gpu bench-zone zone-server bot-swarm
#   DEVICE_DIR=.device-zone bash scripts/pack_device.sh build build/tests/zone/test-zone-gpu \
#     build/tools/bench-zone build/zone/zone-server build/bots/bot-swarm
# then, on the device (tool `run`, carry .device-zone):
#   DEVICE_DIR=.device-zone bash scripts/device_zone.sh [test] [bench] [swarm]
# Steps:
#   test   test_zone_gpu: CPU-vs-GPU tick determinism
#   bench  bench-zone: 100,000 entities at 30 Hz with the GPU finder, and with the CPU finder
#   clients  bench-zone: 80,000 NPCs + 20,000 replicated clients (the swarm's load, no sockets)
#   swarm  zone-server (80,000 NPCs, 30 Hz, finder auto) + bot-swarm (20,000 bots, verify) on loopback
# Environment: SWARM_BOTS (20000), SWARM_NPCS (80000), SWARM_SECONDS (60, after the ramp-up),
# SWARM_RAMP (bots per second, 2000), SWARM_THREADS (bot-swarm I/O threads, 6), SERVER_THREADS (8),
# SERVER_IO_THREADS (4), SERVER_INTEREST (auto), SERVER_SNDBUF (65536), SERVER_ARGS (more zone-server
# options), SERVER_CPUS / SWARM_CPUS (taskset CPU lists, e.g. 0-9 and 10-15: server and swarm on
# disjoint cores; unset = no pinning), SERVER_BIN (the zone-server binary, $DEVICE_DIR/zone-server),
# SWARM_ARGS (more bot-swarm options; with SERVER_ARGS=--oracle, SWARM_ARGS=--oracle checks every
# bot's view against the ground truth, docs/bots.md),
# RUN_TAG (prefix of the swarm step's log names, to keep several runs in one $OUT), BENCH_ENTITIES
# (100000), BENCH_TICKS (600), BENCH_FINDERS ("gpu cpu").
# The swarm step also writes the server's per-tick CSV (--tick-csv: <tag>zone-ticks.csv) and the
# server's CPU time per thread, summed by thread name (zone-worker-N,
# zone-io-N, the main thread as zone-server), before it stops the server: <tag>server-threads.txt;
# and the host's TCP drops and retransmissions over the swarm's run (tools/net_counters.py):
# <tag>net-counters.txt.
# Logs, CSV and JSON go to $OUT (or ./out).
set -uo pipefail
. "$(dirname "${BASH_SOURCE[0]}")/zone_procs.sh"
dir=${DEVICE_DIR:-.device}
out=${OUT:-out}
mkdir -p "$out"
export LD_LIBRARY_PATH=$PWD/$dir${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; echo "cores: $(nproc)"; free -g; } \
  > "$out/device.txt" 2>&1
cat "$out/device.txt"
# Each of zone-server and bot-swarm holds one descriptor per bot: raise the limit as far as allowed.
ulimit -Hn 1048576 2>/dev/null || ulimit -Hn 200000 2>/dev/null || true
ulimit -n "$(ulimit -Hn)" 2>/dev/null
echo "open-file limit: $(ulimit -n) (hard $(ulimit -Hn))"

for step in "$@"; do
  case "$step" in
    test)
      echo "== test_zone_gpu $(date -u +%FT%TZ)"
      "$dir/test-zone-gpu" 2>&1 | tail -4 | tee "$out/test_zone_gpu.log"
      ;;
    bench)
      n=${BENCH_ENTITIES:-100000}
      ticks=${BENCH_TICKS:-600}
      for finder in ${BENCH_FINDERS:-gpu cpu}; do
        echo "== bench-zone --finder $finder --entities $n $(date -u +%FT%TZ)"
        "$dir/bench-zone" --finder "$finder" --entities "$n" --ticks "$ticks" --rate 30 \
          --csv "$out/bench-zone-$finder.csv" 2>&1 | tee "$out/bench-zone-$finder.log"
      done
      ;;
    clients)
      # The swarm's server load without sockets: 80,000 NPCs + 20,000 player clients replicated.
      echo "== bench-zone --finder gpu --entities ${SWARM_NPCS:-80000} --clients ${SWARM_BOTS:-20000} $(date -u +%FT%TZ)"
      "$dir/bench-zone" --finder gpu --entities "${SWARM_NPCS:-80000}" --clients "${SWARM_BOTS:-20000}" \
        --ticks "${BENCH_TICKS:-300}" --rate 30 --csv "$out/bench-zone-clients.csv" 2>&1 | tee "$out/bench-zone-clients.log"
      ;;
    swarm)
      bots=${SWARM_BOTS:-20000}
      limit=$(ulimit -n)
      if [ "$limit" != unlimited ] && [ $((bots + 64)) -gt "$limit" ]; then
        echo "WARNING: open-file limit $limit is too low for $bots bots; running $((limit - 100))"
        bots=$((limit - 100))
      fi
      npcs=${SWARM_NPCS:-80000}
      secs=${SWARM_SECONDS:-60}
      ramp=${SWARM_RAMP:-2000}
      duration=$((secs + bots / ramp + 1))
      tag=${RUN_TAG:+$RUN_TAG-}
      server_bin=${SERVER_BIN:-$dir/zone-server}
      echo "== ${tag}zone-server ($server_bin ${SERVER_ARGS:-}) + bot-swarm: $bots bots, $npcs NPCs, 30 Hz, ${duration} s $(date -u +%FT%TZ)"
      server_pin=()
      swarm_pin=()
      [ -n "${SERVER_CPUS:-}" ] && server_pin=(taskset -c "$SERVER_CPUS")
      [ -n "${SWARM_CPUS:-}" ] && swarm_pin=(taskset -c "$SWARM_CPUS")
      "${server_pin[@]}" "$server_bin" --listen 127.0.0.1 --port 0 --metrics-port 0 --npcs "$npcs" --tick-rate 30 \
        --max-clients $((bots + 100)) --max-pending-per-address $((bots + 100)) --teleport 1 --threads "${SERVER_THREADS:-8}" --io-threads "${SERVER_IO_THREADS:-4}" \
        --finder auto --interest "${SERVER_INTEREST:-auto}" --socket-send-buffer "${SERVER_SNDBUF:-65536}" \
        --tick-csv "$out/${tag}zone-ticks.csv" ${SERVER_ARGS:-} > "$out/${tag}zone-server.log" 2>&1 &
      server=$!
      port=$(zone_port "$out/${tag}zone-server.log" 600)
      if [ -z "$port" ]; then
        echo "zone-server did not start"; cat "$out/${tag}zone-server.log"; kill "$server"; continue
      fi
      python3 tools/net_counters.py --save "$out/${tag}net-counters0.json" || true
      "${swarm_pin[@]}" "$dir/bot-swarm" --port "$port" --bots "$bots" --duration "$duration" --ramp "$ramp" --threads "${SWARM_THREADS:-6}" --verify \
        --mix "${SWARM_MIX:-walk=0.5,patrol=0.2,follow=0.1,crowd=0.1,teleport=0.1}" --quiet ${SWARM_ARGS:-} \
        --report-json "$out/${tag}swarm-report.json" --report-csv "$out/${tag}swarm-series.csv" > "$out/${tag}swarm.log" 2>&1
      echo "bot-swarm exit code: $?"
      # Drops and retransmissions over the run (loopback's losses come back only as retransmissions).
      python3 tools/net_counters.py --since "$out/${tag}net-counters0.json" --frames-from "$out/${tag}swarm-report.json" \
        > "$out/${tag}net-counters.txt" 2>&1 || true
      tail -40 "$out/${tag}swarm.log"
      grep -E "over the run|RetransSegs|SynRetrans|LossProbes|TCPTimeouts|softnet_dropped" "$out/${tag}net-counters.txt"
      awk '{printf "zone-server CPU time (user + system): %.1f s\n", ($14 + $15) / 100}' "/proc/$server/stat" 2>/dev/null
      thread_cpu "$server" | awk '{printf "  %-16s %3d threads %8.1f s\n", $1, $2, $3 / 100}' > "$out/${tag}server-threads.txt"
      echo "zone-server CPU by thread name:"; cat "$out/${tag}server-threads.txt"
      kill -TERM "$server"
      wait "$server"
      grep -A8 'stopped after' "$out/${tag}zone-server.log"
      grep -E 'CPU|cpu' "$out/${tag}zone-server.log" | tail -3
      grep -E 'finder|auto|listening' "$out/${tag}zone-server.log" | head -5
      ;;
    *) echo "unknown step $step"; exit 2 ;;
  esac
done
