#!/usr/bin/env bash
# Device call 1: 19,900 bots + 80,000 NPCs, server pinned to cores 0-9, swarm to 10-15.
# a: the old server (main at ee9ee9b), b: new with direct writes, c: new with I/O-thread writes at nice 10.
set -u
R=${OUT:-out}; export OUT=/tmp/runs; mkdir -p $OUT
export DEVICE_DIR=.device-srv SERVER_CPUS=0-9 SWARM_CPUS=10-15 SWARM_BOTS=19900 SERVER_THREADS=8 SERVER_IO_THREADS=4 \
  SWARM_THREADS=6 SWARM_SECONDS=${SECS:-30}
for run in ${RUNS:-a b c}; do
  case $run in
    a) RUN_TAG=A-old SERVER_BIN=.device-srv/zone-server-old SERVER_ARGS="--worker-spin-us 0" bash .device-srv/device_zone.sh swarm ;;
    b) RUN_TAG=A-direct SERVER_ARGS="--worker-spin-us 0" bash .device-srv/device_zone.sh swarm ;;
    c) RUN_TAG=A-lane-nice SERVER_ARGS="--worker-spin-us 0 --direct-writes 0 --io-nice 10" bash .device-srv/device_zone.sh swarm ;;
  esac 2>&1 | grep -E "^==|zone-server CPU|^  zone-|update latency p50|update latency p99|downstream per bot, median|messages per bot|MISMATCHES|resyncs|tick updates|bot-swarm CPU|connected|tick  |replicate|overran|stopped after|listening"
done
tar czf $R/runs.tgz -C /tmp runs
