# Shell functions shared by the scripts that start zone-server and measure it (device_zone.sh,
# local_swarm_cpu.sh). Source it from beside them: . "$(dirname "${BASH_SOURCE[0]}")/zone_procs.sh"

# zone_port LOG TRIES: the port zone-server's log says it listens on, polling every 0.1 s up to
# TRIES times; prints nothing when it never does.
zone_port() {
  local log=$1 tries=$2 port=
  for _ in $(seq "$tries"); do
    port=$(grep -o 'listening on [0-9.]*:[0-9]*' "$log" 2>/dev/null | sed 's/.*://')
    [ -n "$port" ] && break
    sleep 0.1
  done
  printf '%s' "$port"
}

# thread_cpu PID: one line per thread name (a trailing -<number> read as -N: zone-worker-N,
# zone-io-N): the name, how many threads have it, and their CPU time (user + system) in clock
# ticks (1/100 s); sorted by name.
thread_cpu() {
  local t
  for t in /proc/"$1"/task/*; do
    printf '%s %s\n' "$(sed 's/-[0-9][0-9]*$/-N/' "$t/comm")" "$(cut -d' ' -f14,15 "$t/stat")"
  done | awk '{cpu[$1] += $2 + $3; n[$1]++} END {for (k in cpu) print k, n[k], cpu[k]}' | sort
}
