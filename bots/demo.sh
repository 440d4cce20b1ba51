#!/usr/bin/env bash
# The zone server + bot swarm demo (docs/bots.md): starts zone-server on a free loopback port,
# runs bot-swarm against it with a live progress line, prints the swarm's report and the server's
# tick report, and shuts both down cleanly (also on Ctrl-C or an error).
#
#   bash bots/demo.sh [BUILD_DIR]        # default build dir: build
#
# Environment: DEMO_BOTS, DEMO_NPCS, DEMO_SECONDS, DEMO_TICK_HZ, DEMO_OUT (report folder), DEMO_ORACLE (1: the oracle on, 0: off),
# DEMO_SERVER_ARGS (more zone-server options, split on spaces: e.g. "--tick-csv ticks.csv"), DEMO_SWARM_ARGS
# (more bot-swarm options), DEMO_CUT (connections dropped a second, each bot back to its own entity
# with its resume token: default 2; 0: none).
# Defaults: 300 bots + 5,000 NPCs at 20 Hz for 30 s (a 2-core machine keeps up); 2,000 bots +
# 20,000 NPCs with a CUDA device (the zone then runs its interest step on the GPU: --interest auto,
# docs/zone.md).
set -euo pipefail

BUILD=${1:-build}
SERVER_EXE=$BUILD/zone/zone-server
SWARM_EXE=$BUILD/bots/bot-swarm
for exe in "$SERVER_EXE" "$SWARM_EXE"; do
  [[ -x $exe ]] || { echo "demo: $exe is missing (build first)" >&2; exit 2; }
done

if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
  BOTS=${DEMO_BOTS:-2000} NPCS=${DEMO_NPCS:-20000}
else
  BOTS=${DEMO_BOTS:-300} NPCS=${DEMO_NPCS:-5000}
fi
SECONDS_=${DEMO_SECONDS:-30}
HZ=${DEMO_TICK_HZ:-20}
OUT=${DEMO_OUT:-$(mktemp -d /tmp/zone-demo-XXXXXX)}
mkdir -p "$OUT"
# Both programs raise their open-file limit to the hard limit themselves and say so when the bots
# or clients cannot fit.

# The oracle (docs/bots.md) checks every bot's view against the server's ground truth; DEMO_ORACLE=0 leaves it out.
ORACLE=()
[[ ${DEMO_ORACLE:-1} != 0 ]] && ORACLE=(--oracle)
"$SERVER_EXE" --listen 127.0.0.1 --port 0 --metrics-port 0 --npcs "$NPCS" --tick-rate "$HZ" \
  --max-clients $((BOTS + 100)) --teleport 1 --linger 30 "${ORACLE[@]}" ${DEMO_SERVER_ARGS:-} > "$OUT/zone-server.log" 2>&1 &
SERVER=$!
stop_server() {
  if kill -0 "$SERVER" 2>/dev/null; then
    kill -TERM "$SERVER" 2>/dev/null || true
    for _ in $(seq 100); do kill -0 "$SERVER" 2>/dev/null || break; sleep 0.1; done
    kill -KILL "$SERVER" 2>/dev/null || true
  fi
  wait "$SERVER" 2>/dev/null || true
}
trap stop_server EXIT INT TERM

PORT=
for _ in $(seq 300); do
  PORT=$(grep -o 'listening on [0-9.]*:[0-9]*' "$OUT/zone-server.log" | sed 's/.*://' || true)
  [[ -n $PORT ]] && break
  kill -0 "$SERVER" 2>/dev/null || { cat "$OUT/zone-server.log" >&2; exit 1; }
  sleep 0.1
done
[[ -n $PORT ]] || { echo "demo: zone-server did not start" >&2; exit 1; }
echo "demo: zone-server on 127.0.0.1:$PORT ($NPCS NPCs, $HZ Hz); $BOTS bots for $SECONDS_ s; reports in $OUT"

# A few connections a second drop as a network would drop them (no leave); each bot logs in
# again with its resume token and gets its own entity back (the server keeps it for --linger s).
# The cuts stop 5 s before the end, so every bot plays at the end.
CUT=()
[[ ${DEMO_CUT:-2} != 0 ]] && CUT=(--cut "${DEMO_CUT:-2}" --churn-for "$(( SECONDS_ > 6 ? SECONDS_ - 5 : 1 ))")
set +e
"$SWARM_EXE" --port "$PORT" --bots "$BOTS" --duration "$SECONDS_" --ramp 200 --verify "${ORACLE[@]}" "${CUT[@]}" \
  --mix walk=0.5,patrol=0.2,follow=0.1,crowd=0.1,teleport=0.1 ${DEMO_SWARM_ARGS:-} \
  --report-json "$OUT/report.json" --report-csv "$OUT/report.csv" --plot "$OUT/latency.png"
RC=$?
set -e

stop_server
trap - EXIT INT TERM
echo "zone-server:"
grep -A9 'stopped after' "$OUT/zone-server.log" | sed 's/^\[[^]]*\] \[[a-z]*\] /  /'
exit $RC
