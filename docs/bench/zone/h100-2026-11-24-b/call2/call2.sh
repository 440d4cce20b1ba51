#!/usr/bin/env bash
# Device call 2: 19,900 bots + 80,000 NPCs. A: server pinned to cores 0-9, swarm to 10-15 (8 workers,
# 4 I/O threads, 6 swarm threads); S: both on all 16 cores (8 workers, 6 I/O threads, 8 swarm threads).
# old: main at ee9ee9b; new: srv-1124 (I/O-thread writes by default, frame blocks, send_many).
set -u
R=${OUT:-out}; export OUT=/tmp/runs; mkdir -p $OUT
export DEVICE_DIR=.device-srv SWARM_BOTS=19900 SERVER_THREADS=8 SWARM_SECONDS=${SECS:-30}
pin() { export SERVER_CPUS=0-9 SWARM_CPUS=10-15 SERVER_IO_THREADS=4 SWARM_THREADS=6; }
shared() { unset SERVER_CPUS SWARM_CPUS; export SERVER_IO_THREADS=6 SWARM_THREADS=8; }
for run in ${RUNS:-Aold Anew Anice Snew Sold}; do
  case $run in
    Aold) pin; RUN_TAG=A-old SERVER_BIN=.device-srv/zone-server-old SERVER_ARGS="--worker-spin-us 0" bash .device-srv/device_zone.sh swarm ;;
    Anew) pin; RUN_TAG=A-new SERVER_ARGS="--worker-spin-us 0" bash .device-srv/device_zone.sh swarm ;;
    Anice) pin; RUN_TAG=A-new-nice10 SERVER_ARGS="--worker-spin-us 0 --io-nice 10" bash .device-srv/device_zone.sh swarm ;;
    Snew) shared; RUN_TAG=S-new SERVER_ARGS="--worker-spin-us 0" bash .device-srv/device_zone.sh swarm ;;
    Sold) shared; RUN_TAG=S-old SERVER_BIN=.device-srv/zone-server-old SERVER_ARGS="--worker-spin-us 0" bash .device-srv/device_zone.sh swarm ;;
  esac 2>&1 | grep -E "^==|zone-server CPU|^  zone-|update latency p50|update latency p99|downstream per bot, median|messages per bot|MISMATCHES|resyncs|tick updates|bot-swarm CPU|connected|tick  |replicate|stopped after|listening"
done
tar czf $R/runs.tgz -C /tmp runs
