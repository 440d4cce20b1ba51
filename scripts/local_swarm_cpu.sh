#!/usr/bin/env bash
# Server CPU per frame sent, on this machine: zone-server + bot-swarm on loopback, the server's CPU
# over a window of steady state (after the ramp) divided by the frames it wrote in that window
# (zone_net_frames_out_total from its metrics endpoint), with the CPU per thread (named threads:
# zone-worker-N, zone-io-N; the main thread as zone-server) and the tick and latency reports.
#   ulimit -n 8192
#   bash scripts/local_swarm_cpu.sh SERVER_BIN SWARM_BIN TAG [more zone-server options]
# Environment: BOTS (1500), NPCS (5000), SECS (25, after the ramp), HZ (20), THREADS (2 workers),
# IO_THREADS (2), OUTDIR (/tmp/zone-cpu), PERF (seconds of `perf record -g` on the server in the
# window instead of a plain wait; the data goes to OUTDIR/TAG/perf.data).
# docs/zone-benchmarks.md ("The swarm", the 2-core VM) has its subject; alternate old and new binaries.
set -u
. "$(dirname "${BASH_SOURCE[0]}")/zone_procs.sh"
srv=$1; sw=$2; tag=$3; shift 3
ulimit -n 8192 2>/dev/null
BOTS=${BOTS:-1500}; NPCS=${NPCS:-5000}; SECS=${SECS:-25}; HZ=${HZ:-20}
out=${OUTDIR:-/tmp/zone-cpu}/$tag; mkdir -p "$out"
"$srv" --listen 127.0.0.1 --port 0 --metrics-port 0 --npcs "$NPCS" --tick-rate "$HZ" --threads "${THREADS:-2}" \
  --io-threads "${IO_THREADS:-2}" --max-clients $((BOTS + 100)) --max-pending-per-address $((BOTS + 100)) --teleport 1 --socket-send-buffer 65536 "$@" > "$out/server.log" 2>&1 &
pid=$!
port=$(zone_port "$out/server.log" 300)
[ -n "$port" ] || { echo "zone-server did not start"; cat "$out/server.log"; kill "$pid"; exit 1; }
mport=$(grep -o 'metrics on http://[0-9.]*:[0-9]*' "$out/server.log" | sed 's/.*://')
ramp=250
load0=$(cut -d' ' -f1 /proc/loadavg)
"$sw" --port "$port" --bots "$BOTS" --duration $((SECS + BOTS / ramp + 1)) --ramp $ramp --verify --threads 2 --quiet \
  --mix walk=0.5,patrol=0.2,follow=0.1,crowd=0.1,teleport=0.1 --report-json "$out/swarm.json" > "$out/swarm.log" 2>&1 &
swarm=$!
sleep $((BOTS / ramp + 3))
metric() { curl -s "http://127.0.0.1:$mport/metrics" | awk -v m="$1" '$1 == m {print $2}'; }
threads() { thread_cpu "$pid"; }
f0=$(metric zone_net_frames_out_total); c0=$(cut -d' ' -f14,15 "/proc/$pid/stat" | awk '{print $1 + $2}'); threads > "$out/t0"
w0=$(date +%s.%N)
if [ -n "${PERF:-}" ]; then
  perf record -F 999 -g -p "$pid" -o "$out/perf.data" -- sleep "$PERF" > /dev/null 2>&1
else
  sleep $((SECS - 6))
fi
f1=$(metric zone_net_frames_out_total); c1=$(cut -d' ' -f14,15 "/proc/$pid/stat" | awk '{print $1 + $2}'); threads > "$out/t1"
w1=$(date +%s.%N)
wait "$swarm"
kill -TERM "$pid"; wait "$pid"
echo "== $tag (load before $load0), window $(awk -v a="$w0" -v b="$w1" 'BEGIN {printf "%.1f", b - a}') s"
join "$out/t0" "$out/t1" | awk '{printf "  %-16s %6.2f s\n", $1, ($5 - $3) / 100}'  # name, count, ticks twice
awk -v f0="$f0" -v f1="$f1" -v c0="$c0" -v c1="$c1" 'BEGIN {
  f = f1 - f0; c = (c1 - c0) / 100
  printf "  frames written %d, server CPU %.2f s: %.2f us per frame\n", f, c, (f > 0 ? c / f * 1e6 : 0) }'
grep -E "update latency p50|update latency p99|messages per bot per s, median|MISMATCHES" "$out/swarm.log"
grep -E "  tick |replicate" "$out/server.log" | sed 's/.*\] //'
