#!/usr/bin/env python3
"""The zone's tick with and without a viewer open, in alternating phases of one zone-server.

Starts `zone-server --viewer 1 --tick-csv ...` with --npcs entities, waits --warmup-s, then runs
--rounds rounds of two --phase-s phases, one without a viewer and one with --viewers viewer
sockets open (in alternating order: none/open, open/none, ..., so a drift of the machine's load
weighs on both conditions alike). A viewer
socket is what the page does on the wire (docs/viewer.md): a WebSocket on /viewer/ws that asks for
the whole world with a point budget of 2^20 (every entity in every frame, the most the server
encodes and writes), selects an entity (its AOI, visible set and events are then in every
snapshot, and a GPU interest engine copies its row back), re-sends its view every second and reads
every frame; it draws nothing. Python standard library only (no browser, no npm): it runs on the
device machine too. Prints a table (per condition: ticks, p50, p99, max of the CSV's tick_ms,
which includes the tick's own viewer phase) and the p99 change; per round pair the p99 change, with
the median of those changes, its 95% bootstrap interval (pairs resampled) and their min/max; the
pooled p99 change with its 95% bootstrap interval (whole pairs resampled); the machine's load
average over the run; and the tick's viewer phase itself (from the stats messages); --csv writes
every tick with its phase.

The ticks with a snapshot due (every round(tick rate / viewer Hz) ticks: the 3rd at 30 Hz and 10
Hz; the rates are read from --server-args, else zone-server's defaults) are split from the others
(`--snapshot-every` with --analyze): per condition their tick p50/p99, so a cost paid only where
a snapshot is filled shows apart from one paid on every tick; and from the server's --tick-csv,
on the due ticks with the viewer open, the snapshot's fill on the tick's threads (viewer_fill_ms,
wherever it ran) and, on the GPU interest engine, how much of its device wait was left after the
host work overlapped with it (interest_wait_ms; near 0: that work outlasted the device, so it
lengthened the tick). At the end, the server's viewer counters from /metrics (zone_viewer_*: among
them how often a due snapshot's ids, classes and kinds were copied whole or only its classes
patched) and zone_visibility_switches_total.

  python3 tools/viewer_tick_ab.py --server build/zone/zone-server --npcs 20000 --phase-s 1.5 --rounds 40

The first --settle-s of every phase is not counted (both conditions alike); the run is bounded by
--max-s (fewer rounds when they would not fit); the script's clock is matched to the CSV's t_s at
a write of the server's stdio buffer (sync_clock).

With --bots N (and --bot-swarm, the bot-swarm binary), N bots play in the zone through the whole
run, both conditions alike (started before the warm-up, stopped after the last phase): the tick
then replicates to clients, and with the GPU replication engine a due viewer snapshot is filled in
that engine's wait for the device (docs/viewer.md); without clients there is no replication and
the snapshot is filled in the tick.
"""
import argparse
import base64
import json
import os
import random
import re
import select
import socket
import struct
import subprocess
import sys
import tempfile
import time


def thread_cpu(pid):
    """CPU seconds (user + system) of each of the process's threads, summed by thread name with
    its digits dropped (zone-worker-1 and zone-worker-2 -> zone-worker-); {} where /proc is not readable."""
    out = {}
    hz = os.sysconf("SC_CLK_TCK")
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for t in tasks:
        try:
            with open(f"/proc/{pid}/task/{t}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")].rstrip("0123456789")
        fields = stat[stat.rindex(")") + 2:].split()
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / hz
    return out


def median(v):
    s = sorted(v)
    return float("nan") if not s else (s[len(s) // 2] if len(s) % 2 else 0.5 * (s[len(s) // 2 - 1] + s[len(s) // 2]))


def print_pairs(ticks_of, bootstrap):
    """ticks_of: (pair key, open) -> that phase's tick_ms. Prints the per-pair p99 changes (median,
    its 95% bootstrap interval, min, max) and the pooled p99 change with its 95% bootstrap interval,
    pairs resampled (ticks within a phase are not independent; pairs are)."""
    keys = sorted(k for (k, o) in ticks_of if not o and (k, True) in ticks_of and ticks_of[(k, False)] and ticks_of[(k, True)])
    if not keys:
        return
    p99 = {(k, o): pct(ticks_of[(k, o)], 0.99) for k in keys for o in (False, True)}
    diffs = [100 * (p99[(k, True)] - p99[(k, False)]) / p99[(k, False)] for k in keys]
    rng = random.Random(12345)

    def pooled_change(ks):
        none = [ms for k in ks for ms in ticks_of[(k, False)]]
        opn = [ms for k in ks for ms in ticks_of[(k, True)]]
        return 100 * (pct(opn, 0.99) - pct(none, 0.99)) / pct(none, 0.99)

    def interval(stat, items):
        if bootstrap == 0:
            return float("nan"), float("nan")
        v = sorted(stat([rng.choice(items) for _ in items]) for _ in range(bootstrap))
        return v[int(0.025 * len(v))], v[min(len(v) - 1, int(0.975 * len(v)))]

    lo, hi = interval(median, diffs)
    plo, phi = interval(pooled_change, keys)
    per_phase = median([len(ticks_of[(k, o)]) for k in keys for o in (False, True)])
    if per_phase < 100:
        print(f"(a phase holds {per_phase:g} ticks (median): a phase's p99 is its slowest tick or next to it)")
    print(f"per-pair p99 change ({len(diffs)} pairs): median {median(diffs):+.2f}% (95% bootstrap {lo:+.2f}% .. {hi:+.2f}%), "
          f"min {min(diffs):+.2f}%, max {max(diffs):+.2f}%, open higher in {sum(d > 0 for d in diffs)} of {len(diffs)}")
    print(f"pooled p99 change: {pooled_change(keys):+.2f}% (95% bootstrap over pairs {plo:+.2f}% .. {phi:+.2f}%)")
    d50 = [100 * (pct(ticks_of[(k, True)], 0.5) - pct(ticks_of[(k, False)], 0.5)) / pct(ticks_of[(k, False)], 0.5) for k in keys]
    lo50, hi50 = interval(median, d50)
    print(f"per-pair p50 change: median {median(d50):+.2f}% (95% bootstrap {lo50:+.2f}% .. {hi50:+.2f}%), "
          f"open higher in {sum(d > 0 for d in d50)} of {len(d50)}")


def print_due_split(rows, every):
    """rows: (tick, open, tick_ms, viewer_fill_ms or None, interest_wait_ms or None) of the counted
    ticks. Prints the tick's p50/p99 on the ticks with a snapshot due (tick % every == 0) and on
    the others, none -> open, and on the due ticks the fill and the interest engine's wait left."""
    def of(due, opened, k):
        return [r[k] for r in rows if (r[0] % every == 0) == due and r[1] == opened and r[k] is not None]
    parts = []
    for due in (True, False):
        n, o = of(due, False, 2), of(due, True, 2)
        if not n or not o:
            return
        parts.append(f"{'due' if due else 'other'} ticks ({len(n)} / {len(o)}) p50 {pct(n, 0.5):.3f} -> {pct(o, 0.5):.3f} ms "
                     f"({1000 * (pct(o, 0.5) - pct(n, 0.5)):+.0f} us), p99 {pct(n, 0.99):.3f} -> {pct(o, 0.99):.3f} ms "
                     f"({100 * (pct(o, 0.99) - pct(n, 0.99)) / pct(n, 0.99):+.1f}%)")
    print(f"a snapshot due every {every} ticks: " + "; ".join(parts))
    fill = of(True, True, 3)
    if fill:
        print(f"the snapshot's fill on the tick's threads (viewer_fill_ms, due ticks, open): p50 {pct(fill, 0.5):.4f} ms, "
              f"p99 {pct(fill, 0.99):.4f} ms, max {max(fill):.4f} ms")
    waits = {(due, o): of(due, o, 4) for due in (True, False) for o in (False, True)}
    if all(waits.values()) and max(max(v) for v in waits.values()) > 0:
        print("the interest engine's device wait left after its overlapped host work (interest_wait_ms), p50 / p10 none -> open: "
              + "; ".join(f"{'due' if due else 'other'} ticks {pct(waits[(due, False)], 0.5):.4f} / {pct(waits[(due, False)], 0.1):.4f} -> "
                          f"{pct(waits[(due, True)], 0.5):.4f} / {pct(waits[(due, True)], 0.1):.4f} ms" for due in (True, False)))


def snapshot_every(server_args):
    """round(tick rate / viewer Hz) from zone-server options (its defaults 30 and 10 otherwise)."""
    def opt(name, default):
        m = re.search(r"--" + name + r"[= ]+([0-9.eE+-]+)", server_args)
        return float(m.group(1)) if m else default
    return max(1, int(round(opt("tick-rate", 30.0) / opt("viewer-hz", 10.0))))


def analyze(paths, bootstrap, every):
    """--analyze: the statistics of earlier runs' --csv files together (pairs keyed by file and round)."""
    ticks_of = {}
    rows = []
    for n, path in enumerate(paths):
        if not os.path.isfile(path):
            sys.exit(f"--analyze {path}: no such file")
        with open(path) as f:
            header = f.readline().strip().split(",")
            if header[:5] != ["tick", "t_s", "tick_ms", "phase", "round"]:
                sys.exit(f"{path}: not a viewer_tick_ab.py --csv file")
            extra = [header.index(c) if c in header else None for c in ("viewer_fill_ms", "interest_wait_ms")]
            for line in f:
                p = line.strip().split(",")
                if len(p) == len(header):
                    opened = p[3] == "viewer"
                    ticks_of.setdefault(((n, int(p[4])), opened), []).append(float(p[2]))
                    rows.append((int(p[0]), opened, float(p[2])) + tuple(float(p[i]) if i is not None and p[i] else None for i in extra))
    by = {o: [ms for (k, oo), v in ticks_of.items() if oo == o for ms in v] for o in (False, True)}
    print(f"\nviewer A/B, {len(paths)} run(s) together: " + ", ".join(paths))
    print("| viewer | ticks | p50 ms | p99 ms | max ms |")
    print("|---|---|---|---|---|")
    for o in (False, True):
        v = by[o]
        print(f"| {'open' if o else 'none'} | {len(v)} | {pct(v, 0.5):.3f} | {pct(v, 0.99):.3f} | {max(v) if v else float('nan'):.3f} |")
    print_pairs(ticks_of, bootstrap)
    print_due_split(rows, every)


def pct(values, q):
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


class viewer_socket:
    """A minimal RFC 6455 client: binary view requests out (masked), every frame read."""

    def __init__(self, port, world):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /viewer/ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise RuntimeError("viewer socket: closed during the handshake")
            head += chunk
        status = head.split(b"\r\n", 1)[0]
        if b" 101 " not in status:
            raise RuntimeError(f"viewer socket: handshake refused: {status!r}")
        self.buf = bytearray(head.split(b"\r\n\r\n", 1)[1])
        self.sock.setblocking(False)
        self.world = world
        self.selected = 0
        self.frames = 0
        self.bytes = 0
        self.viewer_ms = []  # the tick's viewer phase, from the stats messages
        self.last_view = 0.0
        self.send_view()

    def send_frame(self, opcode, payload):
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | opcode])
        head += bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.setblocking(True)
        self.sock.sendall(head + mask + masked)
        self.sock.setblocking(False)

    def send_view(self):
        x0, y0, x1, y1 = self.world
        self.send_frame(2, struct.pack("<B3xffffII", 1, x0, y0, x1, y1, self.selected, 1 << 20))
        self.last_view = time.monotonic()

    def pump(self):
        """Reads what has arrived; answers pings; re-sends the view once a second."""
        while True:
            try:
                chunk = self.sock.recv(1 << 20)
            except BlockingIOError:
                break
            if not chunk:
                raise RuntimeError("viewer socket: closed by the server")
            self.buf += chunk
        buf, at0 = self.buf, 0  # parsed in place (a bytearray; one cut at the end): little CPU for 1 MB frames
        while True:
            if len(buf) - at0 < 2:
                break
            b0, b1 = buf[at0], buf[at0 + 1]
            n, at = b1 & 0x7F, at0 + 2
            if n == 126:
                if len(buf) - at0 < 4:
                    break
                n, at = struct.unpack_from(">H", buf, at0 + 2)[0], at0 + 4
            elif n == 127:
                if len(buf) - at0 < 10:
                    break
                n, at = struct.unpack_from(">Q", buf, at0 + 2)[0], at0 + 10
            if len(buf) < at + n:
                break
            opcode = b0 & 0x0F
            at0 = at + n
            if opcode == 9:
                self.send_frame(10, bytes(buf[at:at + n]))
            elif opcode == 8:
                raise RuntimeError("viewer socket: the server closed it")
            elif opcode == 1:
                msg = json.loads(bytes(buf[at:at + n]))
                for t in msg.get("ticks", []):
                    self.viewer_ms.append(t[6])
            elif opcode == 0:
                self.bytes += n  # a continuation of a fragmented message
            elif opcode == 2:
                self.frames += 1
                self.bytes += n
                if self.selected == 0 and n >= 42 and buf[at] == 1 and struct.unpack_from("<I", buf, at + 12)[0] > 0:
                    # The first entity of the frame: watched from now on.
                    self.selected = struct.unpack_from("<I", buf, at + 32)[0]
                    self.send_view()
        if at0:
            del buf[:at0]
        if time.monotonic() - self.last_view > 1.0:
            self.send_view()

    def close(self):
        try:
            self.send_frame(8, struct.pack(">H", 1000))
        except OSError:
            pass
        self.sock.close()


def scrape_metrics(port, prefixes):
    """The server's /metrics lines (name and value) that start with one of prefixes; {} when unreachable."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as c:
            c.sendall(f"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
            data = b""
            while True:
                chunk = c.recv(65536)
                if not chunk:
                    break
                data += chunk
    except OSError:
        return {}
    out = {}
    for line in data.decode(errors="replace").split("\r\n\r\n", 1)[-1].splitlines():
        p = line.split()
        if len(p) == 2 and not line.startswith("#") and p[0].startswith(prefixes):
            out[p[0]] = p[1]
    return out


def sync_clock(path, srv, deadline, flushes=2):
    """The script's monotonic time at the CSV's t_s = 0 (the loop's first tick; a line's t_s is
    written at its tick's end). zone-server writes its --tick-csv through a stdio buffer (4 KB,
    about 70 ticks): a line becomes visible seconds after its tick, so the first line's arrival
    says nothing of when it was written. At the moment the file grows, the buffer was just
    written: its last complete line is at most one tick old. The earliest of `flushes` such
    readings (a late reading only makes it later) is within a tick of the truth."""
    best, seen, size = None, 0, -1
    while seen < flushes and time.monotonic() < deadline:
        if srv.poll() is not None:
            sys.exit("zone-server exited during the warm-up")
        try:
            now_size = os.path.getsize(path)
        except OSError:
            now_size = -1
        if now_size == size or now_size < 0:
            time.sleep(0.001)
            continue
        if now_size == 0:
            size = 0  # created, nothing written yet: its first write is a fresh one
            continue
        now = time.monotonic()
        first = size < 0
        size = now_size
        if first:
            continue  # already there when first looked at: not a fresh write
        with open(path) as f:
            data = f.read(now_size)
        lines = [l for l in data.split("\n")[:-1] if l.count(",") >= 10 and not l.startswith("tick,")]
        if not lines:
            continue
        t0 = now - float(lines[-1].split(",")[1])
        best = t0 if best is None else min(best, t0)
        seen += 1
    if best is None:
        sys.exit("the tick CSV was not written (no flush seen before the deadline)")
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", help="the zone-server binary (required unless --analyze)")
    ap.add_argument("--analyze", nargs="+", metavar="CSV",
                    help="run nothing: the statistics of earlier runs' --csv files together (pairs keyed by file and round)")
    ap.add_argument("--npcs", type=int, default=20000)
    ap.add_argument("--phase-s", type=float, default=5)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--warmup-s", type=float, default=5)
    ap.add_argument("--viewers", type=int, default=1, help="viewer sockets open in the 'with' phases")
    ap.add_argument("--world", type=float, default=4096, help="the world's side (m), as --world-x/--world-y")
    ap.add_argument("--server-args", default="", help="more zone-server options")
    ap.add_argument("--csv", help="write tick,t_s,tick_ms,phase,round per tick (and viewer_fill_ms,interest_wait_ms where "
                                  "the server's --tick-csv has them)")
    ap.add_argument("--snapshot-every", type=int, default=0,
                    help="with --analyze: a snapshot due every N ticks (default: from --server-args, else 3)")
    ap.add_argument("--label", default="", help="a label for the printed table")
    ap.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples for the intervals")
    ap.add_argument("--bots", type=int, default=0, help="bots playing in the zone through the whole run (needs --bot-swarm)")
    ap.add_argument("--bot-swarm", help="the bot-swarm binary, for --bots")
    ap.add_argument("--client-nice", type=int, default=0,
                    help="nice value (absolute) of this script, the viewer socket's client, once the server runs (0: unchanged)")
    ap.add_argument("--client-idle", type=int, default=0, choices=(0, 1),
                    help="1: this script (the viewer socket's client) at SCHED_IDLE once the server runs (a page on another "
                         "machine, as docs/viewer.md has it, costs the zone's host nothing; here it runs beside the tick)")
    ap.add_argument("--settle-s", type=float, default=0.25,
                    help="the first seconds of every phase (both conditions alike) are not counted: the socket of the phase "
                         "before closes, this one opens")
    ap.add_argument("--max-s", type=float, default=240,
                    help="the whole run's bound (s, from the start): fewer rounds are planned when they would not fit "
                         "(with 20 s for the server's start), and no round starts that would end past it")
    a = ap.parse_args()
    if (a.rounds < 1 or a.phase_s <= 0 or a.npcs < 0 or a.viewers < 1 or a.bootstrap < 0 or not 0 <= a.client_nice <= 19
            or a.settle_s < 0 or a.max_s <= 0):
        ap.error("rounds >= 1, phase-s > 0, npcs >= 0, viewers >= 1, bootstrap >= 0, client-nice 0..19, settle-s >= 0, max-s > 0")
    every = a.snapshot_every if a.snapshot_every > 0 else snapshot_every(a.server_args)
    if a.analyze:
        return analyze(a.analyze, a.bootstrap, every)
    if a.bots < 0 or (a.bots > 0 and not (a.bot_swarm and os.access(a.bot_swarm, os.X_OK))):
        ap.error("--bots N needs --bot-swarm, an executable bot-swarm")
    if not a.server:
        ap.error("--server is required (or --analyze CSV ...)")
    if not os.access(a.server, os.X_OK):
        ap.error(f"--server {a.server}: not an executable file")

    t_begin = time.monotonic()
    pair_s = 2 * (a.phase_s + a.settle_s)
    fit = int((a.max_s - 20 - a.warmup_s - 1) // pair_s)
    if fit < 1:
        ap.error(f"--max-s {a.max_s:g}: no round of 2 x ({a.phase_s:g} + {a.settle_s:g}) s fits after the start and warm-up")
    if fit < a.rounds:
        print(f"--rounds {a.rounds} would not fit in --max-s {a.max_s:g}: {fit} rounds planned", flush=True)
        a.rounds = fit
    tmp = tempfile.mkdtemp(prefix="viewer-ab-")
    ticks_csv = os.path.join(tmp, "ticks.csv")
    log_path = os.path.join(tmp, "zone-server.log")
    args = [a.server, "--listen", "127.0.0.1", "--port", "0", "--metrics-port", "0", "--viewer", "1",
            "--max-viewers", str(max(4, a.viewers)), "--npcs", str(a.npcs), "--world-x", str(a.world), "--world-y", str(a.world),
            "--tick-csv", ticks_csv, "--log-level", "info"] + a.server_args.split()
    log = open(log_path, "w")
    srv = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT)
    swarm = None
    metrics = {}  # the server's viewer counters at the end (scrape_metrics)
    try:
        port = None
        deadline = time.monotonic() + 120
        while port is None and time.monotonic() < deadline:
            if srv.poll() is not None:
                sys.exit("zone-server exited:\n" + open(log_path).read())
            m = re.search(r"viewer on http://[0-9.]+:(\d+)/viewer", open(log_path).read())
            port = int(m.group(1)) if m else None
            time.sleep(0.1)
        if port is None:
            sys.exit("zone-server did not start in 120 s")
        if a.bots > 0:
            m = re.search(r"listening on [0-9.]+:(\d+)", open(log_path).read())
            if not m:
                sys.exit("zone-server's log names no game port")
            # Bounded: it stops by itself after the run (and is stopped below when the run ends first).
            run_s = a.warmup_s + a.rounds * pair_s + 30
            swarm = subprocess.Popen([a.bot_swarm, "--port", m.group(1), "--bots", str(a.bots), "--duration", str(int(run_s)),
                                      "--ramp", str(max(50, a.bots)), "--threads", "2", "--quiet"],
                                     stdout=open(os.path.join(tmp, "bot-swarm.log"), "w"), stderr=subprocess.STDOUT)
        warm_from = time.monotonic()
        t_start = sync_clock(ticks_csv, srv, time.monotonic() + max(a.warmup_s, 3.0) + 60)
        now = lambda: time.monotonic() - t_start
        if a.client_nice:
            os.setpriority(os.PRIO_PROCESS, 0, a.client_nice)  # this process only (the server runs already)
        client_policy = "SCHED_OTHER"
        if a.client_idle:
            try:
                os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # this process only
                client_policy = "SCHED_IDLE"
            except (OSError, AttributeError) as e:
                client_policy = f"SCHED_OTHER (SCHED_IDLE refused: {e})"
        time.sleep(max(0.0, a.warmup_s - (time.monotonic() - warm_from)))
        phases = []  # (round, open, t0, t1)
        viewer_ms, frames, nbytes = [], 0, 0
        loads = [os.getloadavg()[0]]
        cpu = {False: {}, True: {}}   # condition -> thread name -> CPU seconds in its phases
        client_cpu = {False: 0.0, True: 0.0}
        phase_s = {False: 0.0, True: 0.0}
        deadline = t_begin + a.max_s - 1
        for r in range(a.rounds):
            if time.monotonic() + pair_s > deadline:
                print(f"stopped after {r} rounds: --max-s {a.max_s:g} reached", flush=True)
                break
            for opened in ((False, True) if r % 2 == 0 else (True, False)):
                socks = [viewer_socket(port, (0.0, 0.0, a.world, a.world)) for _ in range(a.viewers)] if opened else []
                # Settling: the previous phase's socket closes, this one opens and gets its first frames; not counted.
                settle_end = time.monotonic() + a.settle_s
                while True:
                    left = settle_end - time.monotonic()
                    if left <= 0:
                        break
                    if socks:
                        select.select([s.sock for s in socks], [], [], min(0.05, left))
                        for s in socks:
                            s.pump()
                    else:
                        time.sleep(min(0.05, left))
                for s in socks:
                    s.viewer_ms.clear()
                t0 = now()
                cpu0, own0 = thread_cpu(srv.pid), os.times()
                end = time.monotonic() + a.phase_s
                while time.monotonic() < end:
                    if socks:
                        select.select([s.sock for s in socks], [], [], 0.05)
                        for s in socks:
                            s.pump()
                    else:
                        time.sleep(0.05)
                cpu1, own1 = thread_cpu(srv.pid), os.times()
                phases.append((r, opened, t0, now()))
                for s in socks:
                    viewer_ms += s.viewer_ms
                    frames += s.frames
                    nbytes += s.bytes
                    s.close()
                phase_s[opened] += phases[-1][3] - t0
                for name, v in cpu1.items():
                    cpu[opened][name] = cpu[opened].get(name, 0.0) + v - cpu0.get(name, 0.0)
                client_cpu[opened] += (own1.user + own1.system) - (own0.user + own0.system)
                loads.append(os.getloadavg()[0])
        time.sleep(0.5)
        metrics = scrape_metrics(port, ("zone_viewer_", "zone_visibility_switches_total"))
    finally:
        if swarm is not None:
            swarm.terminate()
            try:
                swarm.wait(30)
            except subprocess.TimeoutExpired:
                swarm.kill()
        srv.terminate()
        try:
            srv.wait(30)
        except subprocess.TimeoutExpired:
            srv.kill()
        log.close()

    rows = []
    extras = {}  # tick -> (viewer_fill_ms, interest_wait_ms), where the server writes them
    with open(ticks_csv) as f:
        header = f.readline().strip().split(",")
        it, ic, icl = header.index("t_s"), header.index("tick_ms"), header.index("clients")
        ix = [header.index(c) if c in header else None for c in ("viewer_fill_ms", "interest_wait_ms")]
        clients = {}  # t_s -> clients, for the printout with --bots
        for line in f:
            p = line.strip().split(",")
            if len(p) == len(header):
                rows.append((int(p[0]), float(p[it]), float(p[ic])))
                clients[float(p[it])] = int(p[icl])
                extras[int(p[0])] = tuple(float(p[i]) if i is not None else None for i in ix)
    by = {False: [], True: []}
    per_round = []
    out = []
    for (r, opened, t0, t1) in phases:
        sel = [ms for (_, t, ms) in rows if t0 <= t < t1]
        by[opened] += sel
        per_round.append((r, opened, len(sel), pct(sel, 0.5), pct(sel, 0.99)))
        out += [(tick, t, ms, "viewer" if opened else "none", r) for (tick, t, ms) in rows if t0 <= t < t1]
    ticks_of = {}
    for (r, opened, t0, t1) in phases:
        ticks_of[(r, opened)] = [ms for (_, t, ms) in rows if t0 <= t < t1]

    label = f" {a.label}" if a.label else ""
    print(f"\nviewer A/B{label}: {a.npcs} NPCs, {a.rounds} rounds of {a.phase_s:g} s + {a.phase_s:g} s, "
          f"{a.viewers} viewer socket(s), {a.bots} bots, server args: {a.server_args or '(none)'}")
    if a.bots > 0:
        in_phases = [c for (t, c) in clients.items() if any(t0 <= t < t1 for (_, _, t0, t1) in phases)]
        print(f"clients over the phases' ticks: {min(in_phases, default=0)} .. {max(in_phases, default=0)} (of {a.bots} bots)")
    print("| viewer | ticks | p50 ms | p99 ms | max ms |")
    print("|---|---|---|---|---|")
    for opened in (False, True):
        v = by[opened]
        print(f"| {'open' if opened else 'none'} | {len(v)} | {pct(v, 0.5):.3f} | {pct(v, 0.99):.3f} | {max(v) if v else float('nan'):.3f} |")
    p_none, p_open = pct(by[False], 0.99), pct(by[True], 0.99)
    print(f"p99 change with the viewer open: {100 * (p_open - p_none) / p_none:+.2f}%  "
          f"(p50 change {100 * (pct(by[True], 0.5) - pct(by[False], 0.5)) / pct(by[False], 0.5):+.2f}%)")
    print("per round: " + "; ".join(f"r{r} {'open' if o else 'none'} p99 {p99:.3f}" for (r, o, n, p50, p99) in per_round))
    print_pairs(ticks_of, a.bootstrap)
    print_due_split([(tick, ph == "viewer", ms) + extras.get(tick, (None, None)) for (tick, t, ms, ph, r) in out], every)
    if metrics:
        print("the server's counters at the end (/metrics, refreshed about once a second): "
              + ", ".join(f"{k} {v}" for k, v in sorted(metrics.items())))
    if cpu[True]:
        names = sorted(set(cpu[False]) | set(cpu[True]), key=lambda n: -cpu[True].get(n, 0.0))
        print("CPU ms per second of the phases (none -> open), by thread: " + "; ".join(
            f"{n} {1000 * cpu[False].get(n, 0.0) / phase_s[False]:.1f} -> {1000 * cpu[True].get(n, 0.0) / phase_s[True]:.1f}"
            for n in names if cpu[False].get(n, 0.0) + cpu[True].get(n, 0.0) > 0) +
            f"; the viewer client (this script) {1000 * client_cpu[False] / phase_s[False]:.1f} -> {1000 * client_cpu[True] / phase_s[True]:.1f}")
    print(f"load average (1 min) over the run: {min(loads):.2f} .. {max(loads):.2f} (median {median(loads):.2f}); "
          f"client nice {a.client_nice}, {client_policy}; settle {a.settle_s:g} s a phase (not counted); "
          f"the run took {time.monotonic() - t_begin:.0f} s")
    print(f"the tick's own viewer phase (stats messages, {len(viewer_ms)} ticks): p50 {pct(viewer_ms, 0.5):.4f} ms, "
          f"p99 {pct(viewer_ms, 0.99):.4f} ms, max {max(viewer_ms) if viewer_ms else float('nan'):.4f} ms; "
          f"frames read {frames} ({nbytes / 1e6:.1f} MB)")
    if a.csv:
        with open(a.csv, "w") as f:
            f.write("tick,t_s,tick_ms,phase,round,viewer_fill_ms,interest_wait_ms\n")
            for row in out:
                fill, wait = extras.get(row[0], (None, None))
                f.write("%d,%.4f,%.4f,%s,%d,%s,%s\n" % (row + ("" if fill is None else "%.4f" % fill, "" if wait is None else "%.4f" % wait)))


if __name__ == "__main__":
    main()
