#!/usr/bin/env bash
# The world of zones at the issue's scale (docs/world.md, "Measured"), in one call on the device
# machine (16 cores): host-jitter, then a 2x2 world of 2,000 bots and 20,000 NPCs (the oracle on),
# the same load in one zone, and a SIGKILL run (the oracle on, following the restarted zone). Needs
# a folder packed by scripts/pack_device.sh with zone-server, bot-swarm, world-check, host-jitter,
# nats-server, world.sh and zone_procs.sh (and their shared libraries); runs from that folder. Results under $OUT (at most 8 files).
#   DEVICE_DIR=.device-x scripts/pack_device.sh build build/zone/zone-server build/bots/bot-swarm \
#     build/world/world-check build/tools/host-jitter /usr/sbin/nats-server
#   cp scripts/world.sh scripts/zone_procs.sh scripts/device_world.sh .device-x/
#   (device) bash .device-x/device_world.sh [options]
# Options (defaults: the issue's targets): --duration S (60) --single S (20; 0: none)
#   --kill-duration S (15) --bots N (2000) --npcs N (per zone, 5000) --threads N (per zone, 2)
#   --interest gpu|cpu (gpu) --zone-args "..." (NPCs wandering at 10 m/s) --jitter-periods N (150)
set -uo pipefail
duration=60 single=20 kill_duration=15 bots=2000 npcs=5000 threads=2 size=1024 interest=gpu jitter_periods=150
zone_args="--npc-speed 10 --share-wander 1 --share-patrol 0 --share-town 0 --share-chase 0"
while [ $# -gt 0 ]; do
  case "$1" in
    --duration) duration=$2; shift 2 ;;
    --single) single=$2; shift 2 ;;
    --kill-duration) kill_duration=$2; shift 2 ;;
    --bots) bots=$2; shift 2 ;;
    --npcs) npcs=$2; shift 2 ;;
    --threads) threads=$2; shift 2 ;;
    --interest) interest=$2; shift 2 ;;
    --jitter-periods) jitter_periods=$2; shift 2 ;;
    --zone-args) zone_args=$2; shift 2 ;;
    --help|-h) sed -n 2,13p "$0"; exit 0 ;;
    *) echo "device_world.sh: unknown option $1" >&2; exit 64 ;;
  esac
done
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
out=${OUT:-/tmp/device-world-out}
mkdir -p "$out"
export LD_LIBRARY_PATH="$here${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export PATH="$here:$PATH"  # nats-server
b=$(mktemp -d /tmp/world-build-XXXXXX)
mkdir -p "$b/zone" "$b/bots" "$b/world"
ln -s "$here/zone-server" "$b/zone/zone-server"
ln -s "$here/bot-swarm" "$b/bots/bot-swarm"
ln -s "$here/world-check" "$b/world/world-check"
ulimit -n 65536 2>/dev/null || true
{
  echo "date: $(date -u '+%F %T') UTC; host: $(nproc) cores; $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)"
  echo "nats-server $(nats-server --version 2>&1 | head -1)"
} | tee "$out/summary.txt"
"$here/host-jitter" --periods "$jitter_periods" >"$out/host-jitter.txt" 2>&1
grep -A3 '^| us' "$out/host-jitter.txt" | tee -a "$out/summary.txt"
run() {  # run NAME world.sh-args...: its report into $OUT/NAME.txt, its logs into /tmp/NAME
  local name=$1
  shift
  echo "== $name: world.sh $*" | tee -a "$out/summary.txt"
  local t0=$SECONDS
  bash "$here/world.sh" --build "$b" --out "/tmp/$name" "$@" >"$out/$name.txt" 2>&1
  echo "exit $? after $((SECONDS - t0)) s" | tee -a "$out/$name.txt" "$out/summary.txt"
}
run world --grid 2x2 --bots "$bots" --npcs "$npcs" --duration "$duration" --threads "$threads" --world-size "$size" --interest "$interest" \
  --zone-args "$zone_args" --oracle --single "$single"
run kill --grid 2x2 --bots "$bots" --npcs "$npcs" --duration "$kill_duration" --threads "$threads" --world-size "$size" --interest "$interest" \
  --zone-args "$zone_args" --kill --oracle
# The raw outputs the tables cite: tick CSVs, swarm reports, zone logs' last lines, world-check.
tar -C /tmp -cJf "$out/world-raw.tar.xz" --exclude='js' world kill 2>/dev/null
ls -la "$out"
