#!/usr/bin/env bash
# A local world of zones (docs/world.md) in one command: a nats-server with JetStream on a free
# loopback port, COLSxROWS zone-servers (one region each), one bot swarm per zone whose bots walk
# across borders (following redirects), and optionally a zone killed with SIGKILL and restarted
# (or taken over by a standby), or nats-server stopped for a while and started again.
# Prints one report: the swarms' checks, handoffs and their latency, ghost bytes per border per
# tick, tick p99 per zone, and world-check's census (no entity owned twice; KV agrees).
# Bounded in time: everything stops after --duration (+ about 15 s to start, drain and check).
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/world.sh [options]
  --build DIR      build directory with zone-server, bot-swarm, world-check (default: build)
  --grid CxR       regions (default 2x2)
  --bots N         bots in all, spread over the zones (default 200)
  --npcs N         NPCs per zone (default 5000)
  --duration S     seconds the swarms run (default 30)
  --world-size M   world side in metres (default 1024)
  --bosses N       bosses per zone (default 0: a boss's 400 m AOI widens the ghost band to ~453 m)
  --kill           SIGKILL zone 1 at a third of the run and restart it (fault test): its bots log in
                   again with their resume tokens and get their entities back from its successor;
                   the run fails unless some did
  --standby        with --kill: a hot standby (zone-server --world-standby, started beside the zones
                   on zone 1's port, which it binds once it holds a region) takes the killed zone's
                   region over instead of a restart; the run fails unless it did
  --gate           a world-gate (the world's login service) beside the zones: with --kill the
                   swarms log in again through it (bot-swarm --relogin-port) 1 s after the loss,
                   and it sends each to the zone that serves its region now (a resume token) or to
                   one that serves (a new login); with --standby the standby listens on a port of its
                   own, found through the gate (and by the oracle once it answers); with --kill the
                   run fails unless the gate sent logins on
  --nats-empty     with --nats-restart: start it again with an empty store (the world's JetStream
                   state lost: the zones make it again); every entity must still be there at the end
  --nats-restart S stop nats-server at a third of the run for S seconds, then start it again on its
                   port with its JetStream state (fault test): every zone must still serve at the end
                   and world-check find every entity; not with --kill
  --oracle         zones publish their ground truth (zone-server --oracle) and every swarm checks each
                   bot against the truth of the zone it is in (ghosts included), following it across
                   borders (bot-swarm --oracle --oracle-zones); the run fails if no bot crossed a
                   border (followed a redirect) or the oracle checked nothing; with --kill the
                   swarms follow the restarted zone's truth too, and the run fails if no frame of
                   the restarted zone was checked
  --test-fault K   TESTING: zone 0 breaks one client's frames on purpose (zone-server --test-fault K:
                   drop, extra, stealth, freeze, class) from tick 60; with --oracle the exit status is
                   then 0 only when the oracle caught it (mismatches > 0) and nothing else failed
  --threads N      worker threads per zone (default 1)
  --interest WHERE cpu (default: --finder cpu --interest host) or gpu (--finder gpu --interest gpu:
                   every zone, and --single, on the host's GPU)
  --zone-args "A"  more zone-server options for every zone (e.g. "--npc-speed 8")
  --single S       afterwards, run the same load in ONE zone-server for S seconds (all the zones'
                   NPCs and all the bots, zones x --threads worker threads) and report its tick p99
  --out DIR        keep logs and reports here (default: a temporary directory)
  --help
Exit status: 0 when no entity is owned twice, KV agrees and the swarms saw no mismatch; 1 otherwise.
EOF
}

extra_zone_args=()
build=build grid=2x2 bots=200 npcs=5000 duration=30 size=1024 kill=0 standby=0 gate=0 nats_restart=0 nats_empty=0 threads=1 bosses=0 out= oracle=0 fault= single=0 interest=cpu
while [ $# -gt 0 ]; do
  case "$1" in
    --build) build=$2; shift 2 ;;
    --grid) grid=$2; shift 2 ;;
    --bots) bots=$2; shift 2 ;;
    --npcs) npcs=$2; shift 2 ;;
    --duration) duration=$2; shift 2 ;;
    --world-size) size=$2; shift 2 ;;
    --kill) kill=1; shift ;;
    --standby) standby=1; shift ;;
    --gate) gate=1; shift ;;
    --nats-restart) nats_restart=$2; shift 2 ;;
    --nats-empty) nats_empty=1; shift ;;
    --oracle) oracle=1; shift ;;
    --interest) interest=$2; shift 2 ;;
    --test-fault) fault=$2; shift 2 ;;
    --single) single=$2; shift 2 ;;
    --bosses) bosses=$2; shift 2 ;;
    --zone-args) read -r -a extra_zone_args <<<"$2"; shift 2 ;;
    --threads) threads=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --help|-h) usage; exit 0 ;;
    *) echo "world.sh: unknown option $1 (try --help)" >&2; exit 64 ;;
  esac
done
[[ $grid =~ ^([0-9]+)x([0-9]+)$ ]] || { echo "world.sh: --grid must be COLSxROWS" >&2; exit 64; }
zones=$(( ${BASH_REMATCH[1]} * ${BASH_REMATCH[2]} ))
for v in "$bots" "$npcs" "$duration" "$size" "$threads" "$bosses" "$single" "$nats_restart"; do
  [[ $v =~ ^[0-9]+$ ]] || { echo "world.sh: --bots, --npcs, --duration, --world-size, --threads, --bosses, --single and --nats-restart take whole numbers (got '$v')" >&2; exit 64; }
done
[ "$nats_empty" = 1 ] && [ "$nats_restart" = 0 ] && { echo "world.sh: --nats-empty needs --nats-restart" >&2; exit 64; }
[ "$standby" = 1 ] && [ "$kill" = 0 ] && { echo "world.sh: --standby needs --kill (it stands in for the killed zone)" >&2; exit 64; }
[ "$kill" = 1 ] && [ "$nats_restart" -gt 0 ] && { echo "world.sh: --kill and --nats-restart do not go together (one fault a run)" >&2; exit 64; }
case "$interest" in cpu) where=(--finder cpu --interest host) ;; gpu) where=(--finder gpu --interest gpu) ;;
  *) echo "world.sh: --interest must be cpu or gpu" >&2; exit 64 ;; esac
case "$fault" in ''|drop|extra|stealth|freeze|class) ;; *) echo "world.sh: --test-fault must be drop, extra, stealth, freeze or class" >&2; exit 64 ;; esac
exes="zone/zone-server bots/bot-swarm world/world-check"
[ "$gate" = 1 ] && exes="$exes world/world-gate"
for exe in $exes; do
  [ -x "$build/$exe" ] || { echo "world.sh: $build/$exe missing (build with libnats-dev installed)" >&2; exit 64; }
done
command -v nats-server >/dev/null || { echo "world.sh: nats-server not installed (scripts/setup.sh)" >&2; exit 64; }
[ -n "$out" ] || out=$(mktemp -d /tmp/world-XXXXXX)
mkdir -p "$out"
. "$(dirname "${BASH_SOURCE[0]}")/zone_procs.sh"

pids=()
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done
}
trap cleanup EXIT

# 1. nats-server on a free loopback port (a fresh JetStream store: an --out reused from an earlier
# run must not bring that world's streams and KV back).
rm -rf "$out/js" "$out/js-empty"
store="$out/js"
# start_nats PORT (-1: a free one): nats-server on it, its pid in nats_pid and its URL in url.
start_nats() {
  nats-server -a 127.0.0.1 -p "$1" -js -sd "$store" --ports_file_dir "$out" >>"$out/nats.log" 2>&1 &
  nats_pid=$!
  pids+=("$nats_pid")
  url=
  for _ in $(seq 100); do
    url=$(grep -o 'nats://[0-9.]*:[0-9]*' "$out/nats-server_$nats_pid.ports" 2>/dev/null | head -1 || true)
    [ -n "$url" ] && break
    sleep 0.1
  done
  [ -n "$url" ] || { echo "world.sh: nats-server did not start ($out/nats.log)" >&2; exit 1; }
}
: >"$out/nats.log"
start_nats -1

name=local
zone_args=(--world "$name" --nats "$url" --world-grid "$grid" --world-x "$size" --world-y "$size" --listen 127.0.0.1
           --metrics 0 --npcs "$npcs" --bosses "$bosses" --threads "$threads" "${where[@]}" --max-clients $((bots + 100))
           ${extra_zone_args[@]+"${extra_zone_args[@]}"})
# Every swarm's oracle reads every zone's truth: a zone serves one subscriber per zone (at least the default 4).
[ "$oracle" = 1 ] && zone_args+=(--oracle --oracle-subscribers "$(( zones > 4 ? zones : 4 ))")
# start_zone K [PORT]: zone K's process (log zone-K.log), its pid in zone_pid. Started from this
# shell, not from a $(...) subshell: the zone is this script's child, so `wait` waits for it (a
# subshell's background process is handed to init: `wait` returned at once, and a world.sh killed
# by a test's timeout left its zones running).
start_zone() {
  local more=()
  [ -n "$fault" ] && [ "$1" = 0 ] && more=(--test-fault "$fault" --test-fault-tick 60)
  "$build/zone/zone-server" "${zone_args[@]}" ${more[@]+"${more[@]}"} --port "${2:-0}" --tick-csv "$out/zone-$1.csv" \
    >"$out/zone-$1.log" 2>&1 &
  zone_pid=$!
}

# 2. The zones, one after the other (each takes the next free region).
declare -a zpid zport zregion
for k in $(seq 0 $((zones - 1))); do
  start_zone "$k"
  zpid[$k]=$zone_pid
  pids+=("${zpid[$k]}")
  zport[$k]=$(zone_port "$out/zone-$k.log" 200)
  [ -n "${zport[$k]}" ] || { echo "world.sh: zone $k did not start ($out/zone-$k.log)" >&2; tail -5 "$out/zone-$k.log" >&2; exit 1; }
  zregion[$k]=$(grep -o 'region [0-9]* of' "$out/zone-$k.log" | head -1 | awk '{print $2}')
done

# The gate: the world's login service (it reads the leases; a hello there is sent on to a zone).
if [ "$gate" = 1 ]; then
  # Every bot connects from 127.0.0.1: the per-address limit (64 by default) would refuse most of a
  # zone's players coming back at once (they would retry), so it is the swarm's size here.
  "$build/world/world-gate" --nats "$url" --world "$name" --port 0 --max-per-address $((bots + 64)) \
    --max-connections $((bots + 64)) >"$out/gate.log" 2>&1 &
  gate_pid=$!
  pids+=("$gate_pid")
  gate_port=$(zone_port "$out/gate.log" 100)
  [ -n "$gate_port" ] || { echo "world.sh: the gate did not start ($out/gate.log)" >&2; tail -5 "$out/gate.log" >&2; exit 1; }
fi

# The standby: every region held, it waits for a lease to lapse. Without a gate it binds zone 1's
# port once it holds a region (only zone 1 is killed here): the region's address, as a
# deployment's service name or load balancer in front of whichever process serves the region
# would be; with the gate a port of its own, which the gate finds in its lease.
if [ "$standby" = 1 ]; then
  standby_port=${zport[1]}
  [ "$gate" = 1 ] && standby_port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  "$build/zone/zone-server" "${zone_args[@]}" --world-standby --port "$standby_port" --tick-csv "$out/standby.csv" \
    >"$out/standby.log" 2>&1 &
  standby_pid=$!
  pids+=("$standby_pid")
  for _ in $(seq 100); do grep -q 'standing by' "$out/standby.log" && break; sleep 0.1; done
  grep -q 'standing by' "$out/standby.log" || { echo "world.sh: the standby is not standing by ($out/standby.log)" >&2; tail -5 "$out/standby.log" >&2; exit 1; }
fi

# 3. One swarm per zone: its bots spawn at that zone's towns and walk (random headings) across borders.
per=$(( (bots + zones - 1) / zones ))
reconnect=()
[ "$kill" = 1 ] && reconnect=(--reconnect --relogin-delay 0.5 --connect-timeout 15)  # back to the restarted zone
# With the gate: wherever it sends them (a resume token to its region's zone, once one serves it).
[ "$kill" = 1 ] && [ "$gate" = 1 ] && reconnect=(--reconnect --relogin-delay 1 --connect-timeout 15 --relogin-port "$gate_port")
check=()
if [ "$oracle" = 1 ]; then
  all_ports=$(IFS=,; echo "${zport[*]}")
  check=(--oracle --oracle-threads 1 --oracle-zones "$all_ports")  # each bot judged by the truth of the zone it is in now
  [ "$standby" = 1 ] && [ "$gate" = 1 ] && check+=(--oracle-zones-later "$standby_port")
fi
declare -a spid
for k in $(seq 0 $((zones - 1))); do
  "$build/bots/bot-swarm" --host 127.0.0.1 --port "${zport[$k]}" --bots "$per" --duration "$duration" --ramp 100 \
    --mix walk=1 --verify --quiet ${reconnect[@]+"${reconnect[@]}"} ${check[@]+"${check[@]}"} \
    --report-json "$out/swarm-$k.json" >"$out/swarm-$k.log" 2>&1 &
  spid[$k]=$!
  pids+=("${spid[$k]}")
done

# 4. Fault: SIGKILL zone 1 at a third of the run; restart it (it waits for the lease to lapse).
killed_note=
if [ "$kill" = 1 ] && [ "$zones" -gt 1 ]; then
  sleep $(( duration / 3 ))
  # What the zone owns just before the kill (a census of the whole world, about a second before):
  # what the kill may lose at most.
  "$build/world/world-check" --nats "$url" --world "$name" --wait-ms 800 >"$out/world-check-before-kill.txt" 2>&1 || true
  kill -9 "${zpid[1]}" 2>/dev/null || true
  wait "${zpid[1]}" 2>/dev/null || true
  t_kill=$(date +%s.%N)
  mv "$out/zone-1.log" "$out/zone-1-killed.log"
  mv "$out/zone-1.csv" "$out/zone-1-killed.csv"
  if [ "$standby" = 1 ]; then
    zpid[1]=$standby_pid  # it takes the region over once the lease lapses
    zport[1]=$(zone_port "$out/standby.log" 300)
    mv "$out/standby.log" "$out/zone-1.log"
    how="taken over by the standby"
  else
    start_zone 1 "${zport[1]}"  # the same port: its bots log in again there
    zpid[1]=$zone_pid
    pids+=("${zpid[1]}")
    zport[1]=$(zone_port "$out/zone-1.log" 300)
    how="back"
  fi
  t_up=$(date +%s.%N)
  [ -n "${zport[1]}" ] || { echo "world.sh: region ${zregion[1]} not served again after the kill ($out/zone-1.log)" >&2; exit 1; }
  [ "$standby" = 1 ] && mv "$out/standby.csv" "$out/zone-1.csv"
  killed_note=$(awk -v a="$t_kill" -v b="$t_up" -v h="$how" -v r="$(grep -o 'region [0-9]* of' "$out/zone-1.log" | tail -1 | awk '{print $2}')" \
    'BEGIN{printf "zone 1 (SIGKILL) %s on region %s after %.1f s (lease lapse + start)", h, r, b - a}')
  before=$(grep -o "region ${zregion[1]} (incarnation [0-9]*, [0-9]* owned)" "$out/world-check-before-kill.txt" | grep -o '[0-9]* owned' | awk '{print $1}' || true)
  killed_note="$killed_note; it owned ${before:-?} entities at a census about a second before the kill"
fi

# Fault: nats-server stopped (SIGTERM: its JetStream state stays on disk) for --nats-restart
# seconds, then started again on the same port.
nats_note=
if [ "$nats_restart" -gt 0 ]; then
  sleep $(( duration / 3 ))
  kill -TERM "$nats_pid" 2>/dev/null || true
  wait "$nats_pid" 2>/dev/null || true
  sleep "$nats_restart"
  [ "$nats_empty" = 1 ] && store="$out/js-empty"  # the world's JetStream state lost
  start_nats "${url##*:}"
  nats_note="nats-server stopped at $(( duration / 3 )) s for ${nats_restart} s and started again on its port"
  [ "$nats_empty" = 1 ] && nats_note="$nats_note with an empty store (the world's JetStream state lost)"
fi

# 5. Wait for the swarms, then take the census while the zones still run.
for k in $(seq 0 $((zones - 1))); do wait "${spid[$k]}" 2>/dev/null || true; done
sleep 2  # the zones see the swarms' disconnects (their players leave; a loaded zone takes a few ticks)
expect=()
[ "$kill" = 1 ] || expect=(--expect $(( zones * (npcs + bosses) )))
set +e
"$build/world/world-check" --nats "$url" --world "$name" --wait-ms 2000 "${expect[@]}" >"$out/world-check.txt" 2>&1
check_rc=$?
set -e
# Each zone writes its exit report (read below) on the way out: wait for them (10 s at most, then SIGKILL).
running() {  # running PID: the process has not exited (an exited child stays a zombie, state Z, until waited for)
  local st
  st=$(cut -d' ' -f3 "/proc/$1/stat" 2>/dev/null) || return 1
  [ -n "$st" ] && [ "$st" != Z ]
}
stopped_early=0
for k in $(seq 0 $((zones - 1))); do
  running "${zpid[$k]}" || { echo "zone $k stopped before the end of the run ($out/zone-$k.log)" >&2; stopped_early=1; }
done
for k in $(seq 0 $((zones - 1))); do kill -TERM "${zpid[$k]}" 2>/dev/null || true; done
for _ in $(seq 100); do
  alive=0
  for k in $(seq 0 $((zones - 1))); do running "${zpid[$k]}" && alive=1; done
  [ "$alive" = 0 ] && break
  sleep 0.1
done
for k in $(seq 0 $((zones - 1))); do kill -KILL "${zpid[$k]}" 2>/dev/null || true; wait "${zpid[$k]}" 2>/dev/null || true; done
if [ "$gate" = 1 ]; then kill -TERM "$gate_pid" 2>/dev/null || true; wait "$gate_pid" 2>/dev/null || true; fi

# 6. The same load in one zone (--single), for the tick p99 beside the world's.
if [ "$single" -gt 0 ]; then
  "$build/zone/zone-server" --world-x "$size" --world-y "$size" --listen 127.0.0.1 --metrics 0 --npcs $((zones * npcs)) \
    --bosses $((zones * bosses)) --threads $((zones * threads)) "${where[@]}" --max-clients $((bots + 100)) \
    ${extra_zone_args[@]+"${extra_zone_args[@]}"} --port 0 --tick-csv "$out/single.csv" >"$out/single.log" 2>&1 &
  single_pid=$!
  pids+=("$single_pid")
  single_port=$(zone_port "$out/single.log" 200)
  if [ -n "$single_port" ]; then
    "$build/bots/bot-swarm" --host 127.0.0.1 --port "$single_port" --bots "$bots" --duration "$single" --ramp $((100 * zones)) \
      --mix walk=1 --verify --quiet --report-json "$out/swarm-single.json" >"$out/swarm-single.log" 2>&1 || true
  else
    echo "world.sh: the single zone did not start ($out/single.log)" >&2
  fi
  kill -TERM "$single_pid" 2>/dev/null || true
  wait "$single_pid" 2>/dev/null || true
fi

# 7. The report.
json() { grep -o "\"$2\": [0-9.e+-]*" "$1" | head -1 | awk '{print $2}'; }
echo "== world '$name': $grid regions of ${size} m, $npcs NPCs per zone, $bots bots, ${duration} s ($(nproc) cores, $(date -u +%F))"
restored=
if [ "$kill" = 1 ] && [ -n "$killed_note" ]; then
  restored=$(grep -o '[0-9]* entities restored from region' "$out/zone-1.log" | head -1 | awk '{print $1}' || true)
  waited=$(grep -o 'players restored [0-9]* resumed [0-9]*' "$out/zone-1.log" | tail -1 || true)
  resumed=$(echo "$waited" | awk '{print $5}')
  back=$(grep -o 'the restored players: .*' "$out/zone-1.log" | tail -1 | sed 's/^the restored players: //' || true)
  killed_note="$killed_note; its successor restored ${restored:-none} from the region's checkpoint, players waiting for their clients and back: $(echo "$waited" | awk '{print $3 " / " $5}')${back:+ ($back)}"
fi
[ -n "$killed_note" ] && echo "fault: $killed_note"
[ -n "$nats_note" ] && echo "fault: $nats_note"
mism=0
printf '%-6s %-7s %9s %9s %9s %11s %10s %10s %16s\n' zone region connected redirects digests mismatches failures "re-logins" "tick p50/p99 ms"
for k in $(seq 0 $((zones - 1))); do
  f="$out/swarm-$k.json"
  m=$(json "$f" mismatches); m=${m:-0}
  mism=$((mism + ${m%.*}))
  p99=$(awk -F, 'NR > 1 && $2 > 5 {print $11}' "$out/zone-$k.csv" | sort -g |
        awk '{a[NR] = $1} END {if (NR) printf "%s/%s", a[int(NR * 0.5 + 0.999)], a[int(NR * 0.99 + 0.999)]; else print "-"}')
  printf '%-6s %-7s %9s %9s %9s %11s %10s %10s %16s\n' "$k" "${zregion[$k]:-?}" "$(json "$f" bots_connected)" "$(json "$f" redirects)" \
    "$(json "$f" digests_checked)" "$m" "$(( $(json "$f" connect_failures || echo 0) + $(json "$f" unexpected_disconnects || echo 0) ))" \
    "$(json "$f" reconnects)" "$p99"
done
oracle_mism=0 digest_mism=0 oracle_checked=0 crossings=0 restarts_followed=0 checked_after_restart=0
if [ "$oracle" = 1 ]; then
  echo "-- the oracle (each bot against the truth of the zone it is in; ghosts of the neighbours included)"
  printf '%-6s %14s %12s %11s %9s %8s %8s %8s %9s %8s %9s\n' zone "frames checked" unchecked mismatches missing extra leaked stale position class deferral
  for k in $(seq 0 $((zones - 1))); do
    f="$out/swarm-$k.json"
    om=$(json "$f" oracle_mismatches); om=${om:-0}
    oracle_mism=$((oracle_mism + om))
    oracle_checked=$((oracle_checked + $(json "$f" frames_checked || echo 0)))
    r=$(json "$f" truth_restarts); restarts_followed=$((restarts_followed + ${r:-0}))
    r=$(json "$f" frames_checked_after_restart); checked_after_restart=$((checked_after_restart + ${r:-0}))
    printf '%-6s %14s %12s %11s %9s %8s %8s %8s %9s %8s %9s\n' "$k" "$(json "$f" frames_checked)" "$(json "$f" frames_unchecked)" "$om" \
      "$(json "$f" missing)" "$(json "$f" extra)" "$(json "$f" leaked)" "$(json "$f" stale)" "$(json "$f" position)" \
      "$(json "$f" wrong_class)" "$(json "$f" deferral)"
  done
  [ "$kill" = 1 ] && echo "the killed zone's restart: followed by $restarts_followed of $zones swarms' oracles; $checked_after_restart frames checked against its new truth"
fi
# Every mismatch a swarm counted, by the check that counted it (the swarm's own checks and each
# kind of the oracle's), with the swarm's first problems: a count that no kind explains fails the run.
unexplained=0
for k in $(seq 0 $((zones - 1))); do
  f="$out/swarm-$k.json"
  m=$(json "$f" mismatches); m=${m:-0}; m=${m%.*}
  [ "$m" -gt 0 ] || continue
  kinds="digest_mismatches inconsistent aoi_violations missing extra leaked wrong_class position stale deferral"
  [ "$oracle" = 1 ] || kinds="digest_mismatches inconsistent aoi_violations"
  sum=0 line=
  for kind in $kinds; do
    v=$(json "$f" "$kind"); v=${v:-0}
    sum=$((sum + v))
    [ "$v" = 0 ] || line="$line $kind $v,"
  done
  if [ "$oracle" = 1 ] && ! grep -q '"stream_error": ""' "$f"; then sum=$((sum + 1)); line="$line truth stream broken 1,"; fi
  echo "-- zone $k: $m mismatches:${line%,}; the swarm's first problems ($out/swarm-$k.log):"
  sed -n '/^problems (/,$p' "$out/swarm-$k.log" | sed -n '2,11p'
  if [ "$sum" != "$m" ]; then
    echo "zone $k: $((m - sum)) of its $m mismatches counted by no check this report knows (see swarm-$k.json)" >&2
    unexplained=1
  fi
done
for k in $(seq 0 $((zones - 1))); do
  d=$(json "$out/swarm-$k.json" digest_mismatches); digest_mism=$((digest_mism + ${d:-0}))
  c=$(json "$out/swarm-$k.json" redirects); crossings=$((crossings + ${c:-0}))
done
echo "-- handoffs and ghosts per zone (from each zone's exit line)"
for log in "$out"/zone-*.log; do
  line=$(grep -o 'world: region.*' "$log" | tail -1 || true)
  [ -n "$line" ] || { echo "$(basename "$log"): no exit report (killed)"; continue; }
  ticks=$(grep -o 'stopped after [0-9]* ticks' "$log" | awk '{print $3}')
  nb=$(grep -o 'neighbours [0-9]*' "$log" | head -1 | awk '{print $2}')
  echo "$(basename "$log" .log): $line"
  echo "$line" | awk -v t="${ticks:-1}" -v n="${nb:-1}" '{
    for (i = 1; i <= NF; ++i) if ($i == "bytes" && $(i+1) == "out") out = $(i+2);
    printf "    ghost bytes per tick per neighbour: %.0f (over %d ticks, %d neighbours)\n", out / t / n, t, n }'
done
# Over the world: handoffs adopted, and the worst zone's handoff p99 (ms and ticks).
cat "$out"/zone-*.log | grep -o 'world: region.*' | awk '{
    for (i = 1; i <= NF; ++i) {
      if ($i == "in" && $(i+2) == "(duplicates") n += $(i+1)
      if ($i == "p99" && $(i+2) == "ms" && $(i+1) + 0 > ms) ms = $(i+1) + 0
      if ($i == "(p99" && $(i+2) ~ /^ticks/ && $(i+1) + 0 > tk) tk = $(i+1) + 0
    }
  } END { printf "handoffs adopted in all: %d; worst zone handoff p99: %.1f ms = %.2f ticks\n", n, ms, tk }'
if [ "$single" -gt 0 ]; then
  p=$(awk -F, 'NR > 1 && $2 > 5 {print $11}' "$out/single.csv" 2>/dev/null | sort -g |
      awk '{a[NR] = $1} END {if (NR) printf "%s / %s", a[int(NR * 0.5 + 0.999)], a[int(NR * 0.99 + 0.999)]; else print "-"}')
  f="$out/swarm-single.json"
  echo "-- the same load in one zone ($((zones * npcs)) NPCs, $bots bots, $((zones * threads)) worker threads, ${single} s): tick p50 / p99 ${p} ms;" \
    "bots connected $(json "$f" bots_connected), digests $(json "$f" digests_checked), mismatches $(json "$f" mismatches)"
fi
gate_sent=0
if [ "$gate" = 1 ]; then
  line=$(grep -o 'world gate: [0-9]* logins redirected.*' "$out/gate.log" | tail -1 || true)
  echo "-- the gate: ${line:-no exit line ($out/gate.log)}"
  gate_sent=$(echo "$line" | awk '{print $3}'); gate_sent=${gate_sent:-0}
  gate_resumed=$(echo "$line" | grep -o '[0-9]* resumes redirected' | awk '{print $1}')
  gate_sent=$((gate_sent + ${gate_resumed:-0}))
fi
echo "-- world-check (census of the zones + KV ownership records and leases)"
cat "$out/world-check.txt"
echo "logs: $out"
if [ -n "$fault" ] && [ "$oracle" = 1 ]; then
  # The injected fault must be caught by the oracle (the fault fixes up digests: only it can see
  # it), and nothing else may fail.
  others=$((mism - oracle_mism))
  echo "injected fault '$fault' in zone 0: oracle mismatches $oracle_mism (must be > 0), other failures $others (must be 0)"
  [ "$check_rc" = 0 ] && [ "$oracle_mism" -gt 0 ] && [ "$others" = 0 ] && [ "$digest_mism" = 0 ] && [ "$crossings" -gt 0 ] && [ "$unexplained" = 0 ] && [ "$stopped_early" = 0 ]
  exit
fi
if [ "$nats_empty" = 1 ]; then
  remade=$(cat "$out"/zone-*.log | grep -c "state made again" || true)
  echo "the world's JetStream state made again by the zones: $remade times (each zone once: $zones)"
  [ "$remade" -ge 1 ] || { echo "no zone made the world's JetStream state again" >&2; exit 1; }
fi
[ "$oracle" = 1 ] && [ "$oracle_checked" = 0 ] && { echo "the oracle checked no frame" >&2; exit 1; }
[ "$oracle" = 1 ] && [ "$crossings" = 0 ] && { echo "no bot crossed a border: the oracle spanned no zones" >&2; exit 1; }
[ "$oracle" = 1 ] && [ "$kill" = 1 ] && [ "$checked_after_restart" = 0 ] && { echo "the oracle checked no frame of the restarted zone" >&2; exit 1; }
[ "$gate" = 1 ] && [ "$kill" = 1 ] && [ "$gate_sent" = 0 ] && { echo "the gate sent no login on to a zone" >&2; exit 1; }
[ "$standby" = 1 ] && ! grep -q 'free after' "$out/zone-1.log" && { echo "the standby did not take the killed zone's region over" >&2; exit 1; }
[ "$kill" = 1 ] && [ -n "$killed_note" ] && [ "${restored:-0}" = 0 ] && { echo "the restarted zone restored nothing from the killed zone's checkpoint" >&2; exit 1; }
[ "$kill" = 1 ] && [ -n "$killed_note" ] && [ "${resumed:-0}" = 0 ] && { echo "no player of the killed zone came back to its entity (resume token)" >&2; exit 1; }
[ "$check_rc" = 0 ] && [ "$mism" = 0 ] && [ "$unexplained" = 0 ] && [ "$stopped_early" = 0 ]
