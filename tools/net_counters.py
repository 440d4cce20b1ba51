#!/usr/bin/env python3
"""The host's TCP loss counters around a run (Python standard library only: it runs on the device
host too). On loopback a segment the kernel drops (the per-CPU backlog of netdev_max_backlog
packets, a full receive queue, an accept queue) comes back only as a retransmission: a SYN after
1 s (a connect ramp that stalls), data after the RTO (200 ms or more of latency). These counters
say whether a swarm run paid that.

  net_counters.py --save FILE                          snapshot the counters into FILE (JSON)
  net_counters.py --since FILE [--frames-from REPORT]  the changes since FILE, one line each;
                                                       per frame with the bot-swarm --report-json
                                                       REPORT (its `frames`)

Read from /proc/net/snmp (Tcp), /proc/net/netstat (TcpExt) and /proc/net/softnet_stat (summed
over CPUs). A counter the kernel does not have is left out.
"""
import argparse
import json
import sys

TCP = ["OutSegs", "RetransSegs", "InErrs"]
TCP_EXT = ["TCPSynRetrans", "TCPLossProbes", "TCPTimeouts", "ListenOverflows", "ListenDrops",
           "TCPRcvQDrop", "TCPBacklogDrop", "TCPDelivered"]
SOFTNET = {"softnet_dropped": 1, "softnet_squeezed": 2}  # columns of softnet_stat (hex, per CPU)


def read_pairs(path, prefix):
    """The `prefix:` header line and the value line after it, as a dict."""
    try:
        lines = open(path).read().splitlines()
    except OSError:
        return {}
    for names, values in zip(lines, lines[1:]):
        if names.startswith(prefix + ":") and values.startswith(prefix + ":"):
            keys, vals = names.split()[1:], values.split()[1:]
            if len(keys) == len(vals) and not any(k.isdigit() for k in keys):
                return {k: int(v) for k, v in zip(keys, vals)}
    return {}


def snapshot():
    out = {}
    tcp = read_pairs("/proc/net/snmp", "Tcp")
    ext = read_pairs("/proc/net/netstat", "TcpExt")
    out.update({f"Tcp.{k}": tcp[k] for k in TCP if k in tcp})
    out.update({f"TcpExt.{k}": ext[k] for k in TCP_EXT if k in ext})
    try:
        rows = [line.split() for line in open("/proc/net/softnet_stat")]
        for name, col in SOFTNET.items():
            out[name] = sum(int(r[col], 16) for r in rows if len(r) > col)
    except OSError:
        pass
    return out


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--save", metavar="FILE", help="snapshot the counters into FILE")
    mode.add_argument("--since", metavar="FILE", help="print the changes since the snapshot in FILE")
    ap.add_argument("--frames-from", metavar="REPORT", help="bot-swarm --report-json: per frame as well")
    a = ap.parse_args(argv)
    if a.save:
        with open(a.save, "w") as f:
            json.dump(snapshot(), f)
        return 0
    try:
        before = json.load(open(a.since))
    except (OSError, ValueError) as e:
        print(f"net_counters.py: cannot read the snapshot {a.since}: {e}", file=sys.stderr)
        return 2
    frames = 0
    if a.frames_from:
        try:
            frames = int(json.load(open(a.frames_from)).get("frames", 0))
        except (OSError, ValueError, TypeError) as e:
            print(f"net_counters.py: no frame count from {a.frames_from}: {e}", file=sys.stderr)
    now = snapshot()
    print("host TCP counters over the run (all of the host's sockets)" + (f"; per frame of {frames:,}" if frames else ""))
    for k, v in now.items():
        if k not in before:
            continue
        d = v - before[k]
        per = f"  {d / frames:.6f} a frame" if frames else ""
        print(f"  {k:<24} {d:>12,}{per}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
