#!/usr/bin/env bash
# How many bots one host holds: scripts/device_zone.sh's swarm step (zone-server + bot-swarm on
# loopback, verify mode) once per bot count, then one table of what each run measured against
# issue 5's targets (docs/zone-benchmarks.md, "The swarm").
#
#   SWEEP_BOTS="5000 10000 15000 19900" DEVICE_DIR=.device-zone bash scripts/device_swarm_sweep.sh
#
# Environment: SWEEP_BOTS (the bot counts, in order), SWEEP_LAYOUT (pinned: the server on the first
# 5/8 of the cores with 4 workers and 6 I/O threads per 10 cores, one thread per core, the workers
# and the I/O threads each on their own of those cores (SWEEP_SPLIT, below), the swarm on the rest
# with two threads per core; on a 16-core host: server 0-9 (4 workers on 0-3, 6 I/O threads on
# 4-9), swarm 10-15, 12 threads; on a 32-core host: 0-19 (8 and 12), and 20-31, 24. Six I/O
# threads write a tick's frames soon enough for a 50 ms latency p99 where four do not, at more CPU
# a frame, and a swarm thread per core reads them late (docs/zone-benchmarks.md, "The swarm"). The
# layout before, leaner in CPU a frame: SERVER_THREADS=6 SERVER_IO_THREADS=4 SWARM_THREADS=6 on 16
# cores, 12, 8 and 12 on 32. shared: both on every core, 3/8 of the cores as I/O threads and half
# as swarm threads: 6 and 8 on 16 cores. Default pinned),
# SWEEP_REPEAT (runs per bot count, default 1), SWEEP_FLOOR (1, the default where $DEVICE_DIR has
# bench-handoff: after each run, the floor of a frame's write on this machine, bench-handoff --mode
# floor with the run's bot count as sockets, its mean frame size, the server's I/O threads as
# writers on their CPUs and the swarm's threads as readers on theirs: the table's last columns, and
# the server's CPU a frame above it; docs/zone-benchmarks.md, "The floor"), and everything
# device_zone.sh's swarm step reads
# (SWARM_NPCS, SWARM_SECONDS, SERVER_THREADS, SERVER_CPUS, SERVER_ARGS, ...), which win over the
# layout's.
# Each run's logs are in $OUT with the prefix <layout>-<bots>[-<repeat>]-; the table is printed and
# written to $OUT/sweep.csv.
set -uo pipefail
dir=${DEVICE_DIR:-.device}
out=${OUT:-out}
mkdir -p "$out"
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
layout=${SWEEP_LAYOUT:-pinned}
cores=$(nproc)
[ "$cores" -ge 4 ] || { echo "device_swarm_sweep.sh: $cores cores; the layouts need at least 4" >&2; exit 2; }
at_least_1() { echo $(($1 > 0 ? $1 : 1)); }
server_cores=$((cores * 5 / 8))
case "$layout" in
  pinned) export SERVER_CPUS=${SERVER_CPUS:-0-$((server_cores - 1))} SWARM_CPUS=${SWARM_CPUS:-$server_cores-$((cores - 1))} \
            SERVER_THREADS=${SERVER_THREADS:-$(at_least_1 $((server_cores * 2 / 5)))} \
            SERVER_IO_THREADS=${SERVER_IO_THREADS:-$(at_least_1 $((server_cores * 3 / 5)))} \
            SWARM_THREADS=${SWARM_THREADS:-$((2 * (cores - server_cores)))} ;;
  shared) unset SERVER_CPUS SWARM_CPUS
          export SERVER_IO_THREADS=${SERVER_IO_THREADS:-$(at_least_1 $((cores * 3 / 8)))} SWARM_THREADS=${SWARM_THREADS:-$((cores / 2))} ;;
  *) echo "SWEEP_LAYOUT must be pinned or shared" >&2; exit 2 ;;
esac
export SERVER_ARGS=${SERVER_ARGS:---worker-spin-us 0}
# Pinned, within the server's cores: the tick's threads (the pool, the tick's own thread among
# them) on the first SERVER_THREADS, the I/O threads on the next SERVER_IO_THREADS, so that no I/O
# thread preempts a tick's task (zone-server --worker-cpus / --io-cpus). SWEEP_SPLIT=0, a
# SERVER_CPUS not of the form 0-N, thread counts that are not positive numbers, SERVER_ARGS naming
# CPUs or more threads than cores: not split.
split=
if [ "$layout" = pinned ] && [ "${SWEEP_SPLIT:-1}" = 1 ] && [[ "$SERVER_CPUS" =~ ^0-([0-9]+)$ ]]; then
  server_last=$((10#${BASH_REMATCH[1]}))
  if [[ "$SERVER_THREADS" =~ ^[1-9][0-9]*$ && "$SERVER_IO_THREADS" =~ ^[1-9][0-9]*$ && "$SERVER_ARGS" != *cpus* ]] &&
     [ $((SERVER_THREADS + SERVER_IO_THREADS)) -le $((server_last + 1)) ]; then
    split="--worker-cpus 0-$((SERVER_THREADS - 1)) --io-cpus $SERVER_THREADS-$((SERVER_THREADS + SERVER_IO_THREADS - 1))"
    export SERVER_ARGS="$SERVER_ARGS $split"
  fi
fi
echo "layout $layout on $cores cores: zone-server on ${SERVER_CPUS:-every core} (${SERVER_THREADS:-8} workers," \
  "$SERVER_IO_THREADS I/O threads${split:+: $split}), bot-swarm on ${SWARM_CPUS:-every core} ($SWARM_THREADS threads)"
tags=()
for bots in ${SWEEP_BOTS:-5000 10000 15000 19900}; do
  for r in $(seq "${SWEEP_REPEAT:-1}"); do
    tag=$layout-$bots
    [ "${SWEEP_REPEAT:-1}" -gt 1 ] && tag=$tag-$r
    tags+=("$tag")
    SWARM_BOTS=$bots RUN_TAG=$tag DEVICE_DIR=$dir OUT=$out bash "$here/device_zone.sh" swarm > "$out/$tag-step.log" 2>&1
    grep -E "^==|bot-swarm exit" "$out/$tag-step.log"
    if [ "${SWEEP_FLOOR:-1}" = 1 ] && [ -x "$dir/bench-handoff" ]; then
      frame_bytes=$(python3 -c 'import json, sys; r = json.load(open(sys.argv[1])); print(max(64, round(r["bytes"] / max(1, r["frames"]))))' \
        "$out/$tag-swarm-report.json" 2>/dev/null || echo 650)
      io_cpus=${split#*--io-cpus }
      [ -n "$split" ] || io_cpus=${SERVER_CPUS:-}
      rm -f "$out/$tag-floor.csv"
      floor_args=(--mode floor --sessions "$bots" --io-threads "$SERVER_IO_THREADS" --readers "$SWARM_THREADS"
                  --frame-bytes "$frame_bytes" --ticks 300 --rate 30 ${io_cpus:+--io-cpus "$io_cpus"}
                  ${SWARM_CPUS:+--reader-cpus "$SWARM_CPUS"} --csv "$out/$tag-floor.csv")
      # io_uring as the server writes by default; sendmsg where this build or kernel has none
      timeout 120 "$dir/bench-handoff" "${floor_args[@]}" --write-batching io_uring > "$out/$tag-floor.txt" 2>&1 ||
        timeout 120 "$dir/bench-handoff" "${floor_args[@]}" > "$out/$tag-floor.txt" 2>&1
      grep -A3 "^bench-handoff --mode floor" "$out/$tag-floor.txt" | sed -n '1p;4p'
    fi
  done
done

# One row per run: the swarm's report (JSON), the server's tick CSV and, for the whole run, its log.
python3 - "$out" "${tags[@]}" <<'EOF'
import csv, json, math, re, sys
out, tags = sys.argv[1], sys.argv[2:]
# Latency and tick percentiles are the steady state's: from the first second with every bot
# connected (the swarm's latency_steady_ms) and the ticks with every bot a client (the server's
# --tick-csv); the whole run's, ramp-up included, follow in brackets. "written": the server's
# share of the latency over the whole run (its stop summary: each tick update's age when written).
cols = ["run", "bots", "connected", "mismatches", "resyncs", "frames/s/bot", "KB/s/bot median",
        "latency p50 / p99 ms [whole run]", "written p50 / p99 ms (whole run)", "tick p50 / p99 / max ms [whole run p99]",
        "replicate p50 / p99 ms (of it choosing the clients, p50)",
        "interest p99 ms", "steady ticks (over 33.3 ms)", "server CPU s", "swarm CPU s", "CPU us/frame (server + swarm)",
        "floor us/frame (bytes a frame)", "server above the floor us/frame"]

def pct(values, q):
    # Nearest rank.
    if not values:
        return float("nan")
    v = sorted(values)
    return v[min(len(v), max(1, math.ceil(q * len(v)))) - 1]
rows = []
for tag in tags:
    try:
        rep = json.load(open(f"{out}/{tag}-swarm-report.json"))
        log = open(f"{out}/{tag}-zone-server.log").read()
    except OSError as e:
        rows.append([tag] + ["(missing: %s)" % e.filename] + [""] * (len(cols) - 2))
        continue
    def phase(name):
        m = re.search(r"\]\s+%s\s+p50\s+([\d.]+) ms\s+p99\s+([\d.]+) ms" % name, log)
        return (float(m.group(1)), float(m.group(2))) if m else (float("nan"), float("nan"))
    steady = []
    try:
        for row in csv.DictReader(open(f"{out}/{tag}-zone-ticks.csv")):
            if int(row["clients"]) >= rep["bots"]:
                steady.append({k: float(v) for k, v in row.items()})
    except OSError:
        pass
    tick = [r["tick_ms"] for r in steady]
    repl = [r["replicate_ms"] for r in steady]
    select = [r["select_ms"] for r in steady if "select_ms" in r]  # zone-server from 2026-11-30 on
    inter = [r["interest_ms"] for r in steady]
    over = sum(1 for t in tick if t > 1000.0 / 30)
    lat = rep.get("latency_steady_ms", {})
    cpu = 0.0
    try:
        for line in open(f"{out}/{tag}-server-threads.txt"):
            cpu += float(line.split()[-2])
    except OSError:
        cpu = float("nan")
    frames = rep["tick_updates"] or 1
    # The floor after the run (SWEEP_FLOOR): its writers' CPU a frame, from bench-handoff's CSV (the
    # last line: the sendmsg run where io_uring failed).
    floor, floor_bytes = float("nan"), ""
    try:
        floor_rows = list(csv.DictReader(open(f"{out}/{tag}-floor.csv")))
        if floor_rows:
            floor, floor_bytes = float(floor_rows[-1]["server_us_per_frame"]), floor_rows[-1]["frame_bytes"]
    except (OSError, KeyError, ValueError):
        pass
    rows.append([tag, rep["bots"], rep["bots_connected"], rep["mismatches"], rep["resets"],
                 "%.1f" % rep["per_bot"]["msgs_per_s_median"], "%.1f" % rep["per_bot"]["kbps_median"],
                 "%.1f / %.1f [%.1f / %.1f]" % (lat.get("p50", float("nan")), lat.get("p99", float("nan")),
                                                rep["latency_ms"]["p50"], rep["latency_ms"]["p99"]),
                 "%.1f / %.1f" % phase("written"),
                 "%.1f / %.1f / %.1f [%.1f]" % (pct(tick, 0.5), pct(tick, 0.99), max(tick, default=float("nan")),
                                                phase("tick")[1]),
                 "%.1f / %.1f (%s)" % (pct(repl, 0.5), pct(repl, 0.99), "%.1f" % pct(select, 0.5) if select else "-"),
                 "%.1f" % pct(inter, 0.99),
                 "%d (%d)" % (len(tick), over), "%.1f" % cpu,
                 "%.1f" % rep["swarm_cpu_s"], "%.1f + %.1f" % (cpu / frames * 1e6, rep["swarm_cpu_s"] / frames * 1e6),
                 "%.2f (%s)" % (floor, floor_bytes) if floor_bytes else "-",
                 "%.1f" % (cpu / frames * 1e6 - floor) if floor_bytes else "-"])
with open(f"{out}/sweep.csv", "w") as f:
    f.write(",".join(cols) + "\n")
    for r in rows:
        f.write(",".join('"%s"' % c if "," in str(c) else str(c) for c in r) + "\n")
print("| " + " | ".join(cols) + " |")
print("|" + "---|" * len(cols))
for r in rows:
    print("| " + " | ".join(str(c) for c in r) + " |")
EOF
