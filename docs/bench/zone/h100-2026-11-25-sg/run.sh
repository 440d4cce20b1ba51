#!/usr/bin/env bash
# Issue 22 items 3 and 5 on the H100 (branch send-growth): host-jitter, the constant-density growth
# curve (bench-zone --density ref --interest gpu, no clients), and 19,900 bots + 80,000 NPCs with the
# new zone-server (io_uring writes) and the old one (main before the branch), pinned layout.
set -u
D=.device-sg
export LD_LIBRARY_PATH=$PWD/$D
O=${OUT:-out}
L=$O/logs
mkdir -p "$L"
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; echo "cores $(nproc)"; uname -r;
  echo "io_uring_disabled: $(cat /proc/sys/kernel/io_uring_disabled 2>/dev/null || echo absent)"; } 2>&1 | tee "$L/device.txt"
echo "== host-jitter $(date -u +%T)"
"$D/host-jitter" --threads 16 --work-us 500 --periods 300 > "$L/jitter.txt" 2>&1
tail -6 "$L/jitter.txt"
for n in ${GROWTH_N:-100000 300000 1000000 2000000 4000000}; do
  echo "== growth $n $(date -u +%T)"
  timeout "${GROWTH_TIMEOUT:-90}" "$D/bench-zone" --entities "$n" --density ref --interest gpu --rate 30 --warmup 20 \
    --ticks "${GROWTH_TICKS:-200}" --summary-csv "$O/growth.csv" > "$L/growth-$n.txt" 2>&1
  echo "rc $?"
  grep -E "placed|first tick|^\| (tick|interest|  engine call|  engine device|behaviours|integrate) |visible per|load average before" "$L/growth-$n.txt"
done
for v in ${SWARM_VARIANTS:-new base sendmsg}; do
  bin=$PWD/$D/zone-server
  args="--worker-spin-us 0"
  [ "$v" = base ] && bin=$PWD/$D/zone-server-base
  [ "$v" = sendmsg ] && args="$args --write-batching sendmsg"
  echo "== swarm $v $(date -u +%T)"
  SERVER_ARGS=$args SERVER_BIN=$bin SWARM_SECONDS=${SWARM_SECONDS:-30} SWEEP_BOTS=${SWARM_BOTS:-19900} DEVICE_DIR=$D OUT=$L/swarm-$v \
    bash "$D/device_swarm_sweep.sh" > "$L/swarm-$v.txt" 2>&1
  tail -6 "$L/swarm-$v.txt"
  python3 "$D/joins.py" "$L/swarm-$v"/*zone-server.log 2000
  grep -hE "zone-io|zone-worker|zone-server |listening" "$L/swarm-$v"/*server-threads.txt "$L/swarm-$v"/*zone-server.log 2>/dev/null | head -8
done
tar czf "$O/logs.tgz" -C "$O" logs
ls -la "$O"
