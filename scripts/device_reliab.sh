#!/usr/bin/env bash
# Issue 21's GPU-fault and ping-flood targets and issue 17's viewer target on the device machine,
# from binaries packed by scripts/pack_device.sh into $DEVICE_DIR (default .device):
#   cmake --build build --target zone-server bot-swarm host-jitter zone-probe test-zone-server test-zone
#   DEVICE_DIR=.device-x bash scripts/pack_device.sh build build/zone/zone-server build/bots/bot-swarm \
#     build/tools/host-jitter build/tools/zone-probe build/tests/zone/test-zone-server build/tests/zone/test-zone
# then, on the device (tool `run`, carry .device-x): DEVICE_DIR=.device-x bash scripts/device_reliab.sh [steps]
# Steps (default all, in this order):
#   jitter  host-jitter (5 s, 8 threads): the host's own noise, to read the timings beside
#   tests   test_zone_server's GPU-fault case (on the device: the real engines fail and fall back)
#   faults  per fault (FAULTS, default "gpu-interest gpu-replication gpu-lost"): zone-server --oracle
#           --test-fault F --test-fault-tick FAULT_TICK (FAULT_NPCS NPCs, 30 Hz) + bot-swarm
#           (FAULT_BOTS bots, --verify --oracle): the swarm's exit code and mismatches, the server's
#           fallback log lines and /metrics counters, and the ticks around the fault (late = over the
#           33.3 ms budget)
#   ping    zone-probe --attack pingflood, then --attack reconnect, against zone-server at its defaults pinned to 2 cores
#           (PING_CPUS, default 0-1; the probe on others): the server's CPU and a good client's
#           frame gap p99, alone and during the floods
#   viewer  tools/viewer_tick_ab.py: tick p50/p99 with and without a viewer socket at VIEWER_NPCS
#           (100000) NPCs, VIEWER_ROUNDS (40) alternating pairs of VIEWER_PHASE_S (1.5) s each way, the
#           first VIEWER_SETTLE_S (0.25) s of each phase not counted, each run bounded by VIEWER_MAX_S
#           (240) s; the viewer's client (the script) at SCHED_IDLE with VIEWER_CLIENT_IDLE=1
#           (VIEWER_AB: the script's path, when it is not run from a checkout). VIEWER_BOTS: a list,
#           one run for each (0: no clients, no replication; N: N bots (bot-swarm) play through it, so
#           that the tick replicates and the GPU replication engine's wait holds the viewer's snapshot):
#           VIEWER_BOTS="0 200" measures both ways (about 2 x 3 min); unset: 0
# Logs and CSV go to $OUT (or ./out).
set -uo pipefail
. "$(dirname "${BASH_SOURCE[0]}")/zone_procs.sh"
dir=${DEVICE_DIR:-.device}
out=${OUT:-out}
mkdir -p "$out"
export LD_LIBRARY_PATH=$PWD/$dir${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; echo "cores: $(nproc)"; } > "$out/device.txt" 2>&1
cat "$out/device.txt"
steps=("$@")
[ ${#steps[@]} -eq 0 ] && steps=(jitter tests faults ping viewer)
ulimit -n "$(ulimit -Hn)" 2>/dev/null

# Stops a server started here: TERM, then KILL after 10 s (a server must never hang the run).
stop_server() {
  kill -TERM "$1" 2>/dev/null
  for _ in $(seq 100); do kill -0 "$1" 2>/dev/null || break; sleep 0.1; done
  kill -0 "$1" 2>/dev/null && { echo "zone-server $1 did not stop in 10 s: killed"; kill -KILL "$1"; }
  wait "$1"
  echo "zone-server exit code: $?"
}
metrics_port() { grep -o 'metrics on http://[0-9.]*:[0-9]*' "$1" | sed 's/.*://' | head -1; }

for step in "${steps[@]}"; do
  case "$step" in
    jitter)
      echo "== host-jitter $(date -u +%FT%TZ)"
      "$dir/host-jitter" --threads 8 --periods 150 2>&1 | tee "$out/host-jitter.log" | tail -8
      ;;
    tests)
      echo "== test_zone_server (GPU fault case) $(date -u +%FT%TZ)"
      "$dir/test-zone-server" -tc="--test-fault gpu-*" > "$out/test_zone_server.log" 2>&1; tail -4 "$out/test_zone_server.log"
      "$dir/test-zone" -ts=zone.engine_faults 2>&1 | tail -3
      ;;
    faults)
      tick=${FAULT_TICK:-240}
      for fault in ${FAULTS:-gpu-interest gpu-replication gpu-lost}; do
        echo "== $fault at tick $tick $(date -u +%FT%TZ)"
        log="$out/fault-$fault-server.log"
        "$dir/zone-server" --listen 127.0.0.1 --port 0 --metrics-port 0 --npcs "${FAULT_NPCS:-20000}" --tick-rate 30 \
          --threads 8 --io-threads 4 --max-clients 2000 --max-pending-per-address 2000 --teleport 1 \
          --oracle --test-fault "$fault" --test-fault-tick "$tick" --tick-csv "$out/fault-$fault-ticks.csv" > "$log" 2>&1 &
        server=$!
        port=$(zone_port "$log" 600)
        if [ -z "$port" ]; then echo "zone-server did not start"; cat "$log"; kill "$server"; continue; fi
        "$dir/bot-swarm" --port "$port" --bots "${FAULT_BOTS:-400}" --duration "${FAULT_SECONDS:-14}" --ramp 400 --threads 4 \
          --verify --oracle --mix walk=0.5,patrol=0.2,follow=0.1,crowd=0.1,teleport=0.1 --quiet \
          --report-json "$out/fault-$fault-swarm.json" > "$out/fault-$fault-swarm.log" 2>&1
        echo "bot-swarm exit code: $? (0: all bots connected, no mismatch)"
        mport=$(metrics_port "$log")
        python3 -c "import urllib.request,sys; print(urllib.request.urlopen('http://127.0.0.1:$mport/metrics', timeout=5).read().decode())" \
          2>&1 | grep -E '^zone_(interest|replication)_(gpu_fallbacks_total|on_gpu)|^zone_tick_overruns_total|^zone_ticks_total'
        stop_server "$server"
        grep -E 'mismatch|frames|verified|oracle' "$out/fault-$fault-swarm.log" | head -12
        echo "server log: $(grep -c 'engine failed' "$log") 'engine failed' line(s), $(grep -c 'CUDA error' "$log") line(s) naming a CUDA error, $(grep -c -E '\[(error|critical)\]' "$log") error/critical line(s):"
        grep -E 'engine failed|TESTING|\[(error|critical)\]' "$log" | cut -c1-300 | head -8
        python3 - "$out/fault-$fault-ticks.csv" "$tick" <<'EOF'
import sys
rows = [l.strip().split(",") for l in open(sys.argv[1])][1:]
at = int(sys.argv[2]); budget = 1000 / 30
ticks = [(int(r[0]), float(r[8]), float(r[9]), float(r[10])) for r in rows if len(r) >= 11]
late = [t for t in ticks if t[3] > budget]
near = [t for t in late if at - 2 <= t[0] <= at + 3]
s = sorted(t[3] for t in ticks if t[0] > 60)
print(f"ticks {len(ticks)}, p50 {s[len(s)//2]:.2f} ms, p99 {s[int(0.99*len(s))]:.2f} ms; late (> {budget:.1f} ms): {len(late)} in all, {len(near)} within ticks {at-2}..{at+3}")
for t in ticks:
    if at - 2 <= t[0] <= at + 3:
        print(f"  tick {t[0]}: interest {t[1]:.2f} ms, replicate {t[2]:.2f} ms, tick {t[3]:.2f} ms")
EOF
      done
      ;;
    ping)
      echo "== ping flood $(date -u +%FT%TZ)"
      log="$out/ping-server.log"
      cpus=${PING_CPUS:-0-1}
      taskset -c "$cpus" "$dir/zone-server" --listen 127.0.0.1 --port 0 --metrics-port 0 --threads 2 > "$log" 2>&1 &
      server=$!
      port=$(zone_port "$log" 600)
      taskset -c "${PROBE_CPUS:-4-7}" "$dir/zone-probe" --port "$port" --attack pingflood --seconds "${PING_SECONDS:-5}" --server-pid "$server" \
        2>&1 | tee "$out/ping-probe.log"
      stop_server "$server"
      # The reconnect flood (32 threads: connect, hello, wait for the answer, close), on a fresh server.
      taskset -c "$cpus" "$dir/zone-server" --listen 127.0.0.1 --port 0 --metrics-port 0 --threads 2 > "$out/reconnect-server.log" 2>&1 &
      server=$!
      port=$(zone_port "$out/reconnect-server.log" 600)
      taskset -c "${PROBE_CPUS:-4-7}" "$dir/zone-probe" --port "$port" --attack reconnect --seconds "${PING_SECONDS:-5}" --server-pid "$server" \
        2>&1 | tee "$out/reconnect-probe.log"
      stop_server "$server"
      ;;
    viewer)
      for bots in ${VIEWER_BOTS:-0}; do
        echo "== viewer A/B, $bots bots $(date -u +%FT%TZ)"
        bot_args=()
        [ "$bots" -gt 0 ] && bot_args=(--bots "$bots" --bot-swarm "$dir/bot-swarm")
        python3 "${VIEWER_AB:-tools/viewer_tick_ab.py}" --server "$dir/zone-server" --npcs "${VIEWER_NPCS:-100000}" \
          --phase-s "${VIEWER_PHASE_S:-1.5}" --rounds "${VIEWER_ROUNDS:-40}" --settle-s "${VIEWER_SETTLE_S:-0.25}" \
          --max-s "${VIEWER_MAX_S:-240}" --client-idle "${VIEWER_CLIENT_IDLE:-0}" --warmup-s 5 \
          --server-args "--threads 8 --io-threads 4" "${bot_args[@]}" \
          --label "(device, $bots bots)" --csv "$out/viewer-ab-bots$bots.csv" 2>&1 | tee "$out/viewer-ab-bots$bots.log"
      done
      ;;
    *) echo "unknown step $step"; exit 2 ;;
  esac
done
