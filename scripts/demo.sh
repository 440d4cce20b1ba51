#!/usr/bin/env bash
# README command 1: installs what is missing, builds, and runs the main job: zone-server with a
# swarm of scripted bot clients in verify mode (bots/demo.sh: a free loopback port, a live
# progress line, the swarm's report and the server's tick report, a clean shutdown of both).
# DEMO_BOTS, DEMO_NPCS, DEMO_SECONDS, DEMO_TICK_HZ, DEMO_OUT, DEMO_ORACLE and DEMO_SERVER_ARGS change the run.
# scripts/demo-interest.sh runs the offline pair finders side by side instead.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh
exec bash bots/demo.sh build
